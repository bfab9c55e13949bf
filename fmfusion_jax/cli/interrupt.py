"""Ctrl-C for long commands: the first asks the work to stop at its next safe point, the second exits at once."""

from __future__ import annotations

import os
import signal
import sys
from types import FrameType


class StopRequest:
    """A SIGINT handler as a context manager; calling the object says whether a stop was requested.

    The work polls it at safe points (between frames) instead of being torn by a `KeyboardInterrupt` raised in
    the middle of a device computation or a file write. A second Ctrl-C exits with status 130 immediately,
    without running the interpreter's teardown (whatever the work was doing is abandoned; the last checkpoint
    stays).
    """

    def __init__(self, message: str = "stopping after this frame (Ctrl-C again to exit at once)"):
        self.message = message
        self.requested = False
        self._previous: object = None

    def __call__(self) -> bool:
        return self.requested

    def __enter__(self) -> "StopRequest":
        self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc_info) -> None:
        signal.signal(signal.SIGINT, self._previous)  # type: ignore[arg-type]

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.requested:
            sys.stderr.write("\ninterrupted again: exiting now\n")
            sys.stderr.flush()
            os._exit(130)
        self.requested = True
        sys.stderr.write(f"\ninterrupt: {self.message}\n")
        sys.stderr.flush()
