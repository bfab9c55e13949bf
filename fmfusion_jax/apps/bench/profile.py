"""`fmfusion bench --profile N`: a `jax.profiler` trace of the last N frames of the as-run pass, summarized.

The summary says, per thread of the trace (the host's Python thread, the reader thread, XLA's worker threads on
a CPU, a GPU's streams), how busy it was per frame (the union of its events' intervals, less its waits on Python
locks and queues: an idle reader thread waits in its queue's `get`) and on what (the events with the most time,
inclusive: a Python call holds the calls it makes). The trace itself (Perfetto's JSON) is kept beside the
report: open it in https://ui.perfetto.dev to follow a frame.
"""

from __future__ import annotations

import collections
import gzip
import json
import re
import shutil
from pathlib import Path

import jax

#: Threads listed in the report, busiest first, and events listed per thread.
THREADS_SHOWN, EVENTS_SHOWN = 6, 5
#: The Python tracer's names of a thread's waits on a lock, a condition or a queue (C calls are "$<unknown> NAME").
_WAIT_EVENT = re.compile(r"^\$(<unknown> (acquire|get)|threading\.py:\d+ wait)$")


def start_trace(folder: Path) -> None:

    folder.mkdir(parents=True, exist_ok=True)
    jax.profiler.start_trace(str(folder), create_perfetto_trace=True)


def stop_trace(folder: Path, keep_as: Path) -> Path | None:
    """Stops the trace started in `folder` and moves its Perfetto JSON to `keep_as` (None if none was written)."""

    jax.profiler.stop_trace()
    written = sorted(folder.glob("plugins/profile/*/perfetto_trace.json.gz"))
    if not written:
        return None
    keep_as.parent.mkdir(parents=True, exist_ok=True)
    shutil.move(str(written[-1]), keep_as)
    shutil.rmtree(folder, ignore_errors=True)
    return keep_as


def _busy(intervals: list[tuple[float, float]]) -> float:
    """Length of the union of `(start, end)` intervals."""
    total, reached = 0.0, -float("inf")
    for start, end in sorted(intervals):
        if end > reached:
            total += end - max(start, reached)
            reached = end
    return total


def summarize_trace(path: Path, frames: int) -> list[dict]:
    """Per thread of a Perfetto JSON trace (`path`, gzipped) over `frames` frames, busiest first:
    `{"thread", "busy_ms", "events", "top": [{"name", "ms", "calls"}]}`, per frame (ms from the events' µs)."""
    with gzip.open(path, "rt") as stream:
        loaded = json.load(stream)
    events = loaded["traceEvents"] if isinstance(loaded, dict) else loaded
    names: dict[tuple, str] = {}
    for event in events:
        if event.get("ph") == "M" and event.get("name") in ("process_name", "thread_name"):
            tid = event.get("tid") if event["name"] == "thread_name" else None
            names[(event["pid"], tid)] = str(event.get("args", {}).get("name", ""))
    # threads of a process that share a name (Python's threads all show as the interpreter's) keep their ids apart
    shared = collections.Counter((pid, name) for (pid, tid), name in names.items() if tid is not None)
    intervals: dict[str, list] = collections.defaultdict(list)
    waits: dict[str, list] = collections.defaultdict(list)
    time_by_name: dict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
    calls_by_name: dict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
    for event in events:
        if event.get("ph") != "X":
            continue
        pid, tid = event["pid"], event.get("tid")
        name = names.get((pid, tid), tid)
        thread = f"{names.get((pid, None), pid)} / {name}" + (f" #{tid}" if shared[pid, name] > 1 else "")
        start, length = float(event["ts"]), float(event.get("dur", 0.0))
        intervals[thread].append((start, start + length))
        if _WAIT_EVENT.match(event["name"]):
            waits[thread].append((start, start + length))
        time_by_name[thread][event["name"]] += int(round(length * 1e3))  # ns: the counter holds integers
        calls_by_name[thread][event["name"]] += 1
    frames = max(frames, 1)
    rows = []
    for thread, spans in intervals.items():
        top = [
            {"name": name, "ms": ns / frames / 1e6, "calls": calls_by_name[thread][name] / frames}
            for name, ns in time_by_name[thread].most_common(EVENTS_SHOWN)
        ]
        busy = _busy(spans) - _busy(waits[thread])  # the waits lie inside the thread's other events
        rows.append({"thread": thread, "busy_ms": busy / frames / 1e3, "events": len(spans) / frames, "top": top})
    return sorted(rows, key=lambda row: -row["busy_ms"])


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("`", "'")


def profile_lines(profile: dict | None) -> list[str]:
    """bench.md's profile section (none without `--profile`)."""
    if not profile:
        return []
    lines = [f"## Profile: the last {profile['frames']} frames as run (`--profile`)", ""]
    if profile.get("error"):
        return lines + [f"No profile: {profile['error']}", ""]
    lines += [
        f"`jax.profiler` trace: `{profile['trace']}` (open it in https://ui.perfetto.dev). These frames are left out of "
        "the as-run figures (tracing slows them). Per thread, busiest first: busy = the union of its events less "
        "its waits on Python locks and queues, per frame; the events with the most time, inclusive (a call holds "
        "the calls it makes).",
        "",
        "| thread | busy, ms/frame | events/frame | most time (ms/frame, calls/frame) |",
        "|---|---:|---:|---|",
    ]
    for row in profile["threads"][:THREADS_SHOWN]:
        top = "; ".join(f"`{_cell(e['name'][:60])}` {e['ms']:.2f} ({e['calls']:.1f})" for e in row["top"])
        lines.append(f"| {_cell(row['thread'])} | {row['busy_ms']:.2f} | {row['events']:.1f} | {top} |")
    return lines + [""]


__all__ = ["profile_lines", "start_trace", "stop_trace", "summarize_trace"]
