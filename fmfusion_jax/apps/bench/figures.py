"""The figures of `fmfusion bench` read from the workers' results: per-frame sums of the stages, medians, the
whole frame as run, and why a result is missing."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TypeGuard

import numpy as np

#: The whole frame as `fmfusion run` runs it (the worker's pass without timers): the figure the targets judge.
AS_RUN_LABEL = "**whole frame, as run** (`Mapper.integrate` without timers: the host's work overlaps the device's)"


#: The row of the host's work that `fmfusion run` does in its reader threads (beside the steps, not in series).
READER_LABEL = "reader thread: frame prepared (the growth check's block extent, detections packed)"


def frame_sums(
    frames: Sequence[dict], compiled: Sequence[dict] | None, keys: Sequence[str] | None, start: int = 1, stop: int | None = None
) -> list[float]:
    """Per frame of `frames[start:stop]`: the sum of the `keys` stages that ran (None: all), ms.

    A frame is left out when none of the stages ran, or when one of them compiled in it.
    """
    sums = []
    stop = len(frames) if stop is None else min(stop, len(frames))
    for i in range(start, stop):
        times, compiling = frames[i], (compiled[i] if compiled else {})
        names = list(times) if keys is None else [k for k in keys if k in times]
        if not names or any(k in compiling for k in (compiling if keys is None else keys)):
            continue
        sums.append(float(sum(times[k] for k in names)))
    return sums


def median(values: Sequence[float]) -> float:
    return float(np.median(values)) if len(values) else math.nan


def _pass(ours: dict, name: str) -> tuple[list, list]:
    if name == "staged":
        return ours.get("stage_frames", []), ours.get("stage_compiled", [])
    if name == "as_run":
        return ours.get("run_frames", []), ours.get("run_compiled", [])
    return ours.get("frames", []), ours.get("compiled", [])


def whole_frame_row(stages: dict | None) -> dict | None:
    """The stage table's whole-frame row the targets judge: as run when that pass ran, else with stages timed."""
    if not stages:
        return None
    rows = {row["label"]: row for row in stages["rows"]}
    as_run = rows.get(AS_RUN_LABEL)
    if as_run is not None and math.isfinite(as_run["ours_all"]):
        return as_run
    return rows.get(TIMED_WHOLE_LABEL)


def _usable(result: dict | None) -> TypeGuard[dict]:
    return bool(result and "frames" in result and not result.get("unavailable") and not result.get("error"))


def why_missing(result: dict | None, default: str = "not run") -> str:
    if not result:
        return default
    return result.get("unavailable") or result.get("error") or default


#: The whole frame with every stage waited for (the worker's timed pass): judged when no pass ran without timers.
TIMED_WHOLE_LABEL = (
    "whole frame, stages timed (`Mapper.prepare` and `Mapper.integrate`, waiting for each step: the sum of the above)"
)
