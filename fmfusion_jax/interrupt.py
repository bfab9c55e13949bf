"""Ctrl-C, SIGTERM and SIGHUP for long commands: the first asks the work to stop at its next safe point, the second
exits at once."""

from __future__ import annotations

import os
import signal
import sys
from types import FrameType

#: Signals that ask a long command to stop at its next safe point: Ctrl-C, and what `docker stop`, systemd, job
#: schedulers (SIGTERM) and a closed terminal (SIGHUP) send.
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


class StopRequest:
    """A handler of SIGINT, SIGTERM and SIGHUP as a context manager; calling the object says whether a stop was
    requested, `signum` by which signal (the command exits with 128 + it: 130, 143, 129).

    The work polls it at safe points (between frames) instead of being torn by a `KeyboardInterrupt` raised in
    the middle of a device computation or a file write. A second signal exits with 128 + its number immediately,
    without running the interpreter's teardown (whatever the work was doing is abandoned; the last checkpoint
    stays).
    """

    def __init__(self, message: str = "stopping after this frame (Ctrl-C again to exit at once)"):
        self.message = message
        self.requested = False
        self.signum = int(signal.SIGINT)
        self._previous: dict[int, object] = {}

    def __call__(self) -> bool:
        return self.requested

    @property
    def exit_status(self) -> int:
        """128 + the signal that asked to stop (130 for Ctrl-C, 143 for SIGTERM, 129 for SIGHUP)."""
        return 128 + self.signum

    def __enter__(self) -> "StopRequest":
        for signum in STOP_SIGNALS:
            self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc_info) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)  # type: ignore[arg-type]

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.requested:
            sys.stderr.write(f"\n{signal.Signals(signum).name} again: exiting now\n")
            sys.stderr.flush()
            os._exit(128 + signum)
        self.requested, self.signum = True, int(signum)
        name = "interrupt" if signum == signal.SIGINT else signal.Signals(signum).name
        sys.stderr.write(f"\n{name}: {self.message}\n")
        sys.stderr.flush()
