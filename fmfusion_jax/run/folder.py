"""The output folder of a run: checked before (never another program's folder, never the inputs), locked while
written (`OutputLock`), filled in a partial folder and swapped in whole, so a run never leaves half a result.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import socket
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path

from fmfusion_jax.errors import UserError
from fmfusion_jax.run.outputs import OUTPUT_NAMES
from fmfusion_jax.run.outputs import capacity_used as capacity_used  # re-exported: experiments, likelihood, examples
from fmfusion_jax.run.outputs import score_instances as score_instances

log = logging.getLogger(__name__)


def clear_outputs(out_dir: Path) -> None:
    """Removes the outputs of an earlier run from `out_dir` (only the names in `OUTPUT_NAMES`, the files of the
    writers of `run.outputs`), so no file of an earlier run (an instance that no longer exists, a report without
    ground truth) stays."""
    for name in OUTPUT_NAMES:
        path = out_dir / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()


def prepare_output_dir(out_dir: str | Path, create: bool = True) -> Path:
    """Checks (and creates, or with `create=False` its parent) the output folder up front, before minutes of
    fusion; a path that cannot be one is a UserError."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"--out {out_dir} is a file, not a folder")
    where = out_dir if create else out_dir.parent
    try:
        where.mkdir(parents=True, exist_ok=True)
        # the outputs are staged beside --out (OUT.partial): a read-only place fails now, not after the fusion
        os.rmdir(tempfile.mkdtemp(prefix=".fmfusion-write-check-", dir=where))
    except OSError as error:
        raise UserError(f"cannot write the output folder {out_dir} ({where}: {error.strerror or error})") from None
    return out_dir


def check_output_folder(out_dir: Path, inputs: Iterable[Path | None] = (), overwrite: bool = False) -> None:
    """Refuses, before any work, an `--out` that `fmfusion run` must not replace: a folder holding one of the
    run's `inputs` (the scene, the detections, the models: replacing it would delete them), or an existing
    folder with files that is not a previous run's output (no run.json of one) unless `overwrite`."""
    target = out_dir.resolve()
    for path in inputs:
        if path is None:
            continue
        source = Path(path).resolve()
        if source == target or target in source.parents:
            raise UserError(f"--out {out_dir} holds the run's input {path}: the outputs would replace it; choose another folder")
    if not out_dir.is_dir() or overwrite or not any(out_dir.iterdir()):
        return
    try:
        previous = json.loads((out_dir / "run.json").read_text())
        if isinstance(previous, dict) and {"scene", "frames"} <= previous.keys():
            return
    except (OSError, ValueError):
        pass
    raise UserError(
        f"--out {out_dir} is a folder with files that is not an earlier `fmfusion run`'s output (no run.json): its "
        "contents would be replaced; choose a new folder, or pass --overwrite to replace it"
    )


class OutputLock:
    """One writer per output folder: `OUT.lock` beside `--out` holds the owner's pid and host while a run writes.

    A second run on the same `--out` is a UserError naming the owner; a lock whose process is gone (same host, dead
    pid: a run killed outright) is taken over with a warning. Created with O_EXCL, so two runs starting together
    cannot both take it."""

    def __init__(self, out_dir: Path):
        self.path = out_dir.with_name(out_dir.name + ".lock")
        self.owner = {"pid": os.getpid(), "host": socket.gethostname()}

    def __enter__(self) -> "OutputLock":
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                holder = self._holder()
                if holder is None:  # being written this instant, or left half written: look again once
                    time.sleep(0.2)
                    holder = self._holder()
                if holder is not None and not self._stale(holder):
                    raise UserError(
                        f"--out {self.path.with_suffix('')} is being written by another run (pid {holder.get('pid')} on "
                        f"{holder.get('host')}, {self.path}): wait for it, or choose another folder"
                    ) from None
                log.warning("taking over %s, left by a run that is gone (%s)", self.path, holder)
                self.path.unlink(missing_ok=True)
                continue
            with os.fdopen(fd, "w") as file:
                json.dump(self.owner, file)
            return self
        raise UserError(f"cannot take the lock {self.path}: another run keeps taking it")

    def __exit__(self, *exc_info) -> None:
        if self._holder() == self.owner:
            self.path.unlink(missing_ok=True)

    def _holder(self) -> dict | None:
        try:
            holder = json.loads(self.path.read_text())
        except (OSError, ValueError):
            return None  # half written or gone: treated as stale
        return holder if isinstance(holder, dict) else None

    def _stale(self, holder: dict) -> bool:
        if holder.get("host") != self.owner["host"]:
            return False  # another machine's run (a shared file system): never taken over
        try:
            os.kill(int(holder.get("pid", -1)), 0)
        except ProcessLookupError:
            return True
        except (PermissionError, ValueError, TypeError, OverflowError):
            return False
        return False


def partial_dir(out_dir: Path) -> Path:
    """Where `run_and_export` builds a run's outputs and keeps its checkpoint: `OUT.partial` beside `OUT`."""
    return out_dir.with_name(out_dir.name + ".partial")


def replace_folder(new: Path, target: Path) -> None:
    """Renames `new` to `target`; an existing `target` is moved aside first and removed after."""
    if target.exists():
        aside = target.with_name(f".{target.name}.replaced")
        if aside.exists():
            shutil.rmtree(aside)
        target.rename(aside)
        new.rename(target)
        shutil.rmtree(aside, ignore_errors=True)
    else:
        new.rename(target)
