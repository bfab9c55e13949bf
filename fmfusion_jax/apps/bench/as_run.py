"""The bench's as-run pass alone, repeated: a quick A/B of two versions of the code on the same device.

    python -m fmfusion_jax.apps.bench.as_run --scene ../shared/data/scannet/scene0000_00 --cache outputs/bench/cache

Fuses the real scene `--passes` times in this process, as `fmfusion run` does (reader threads preparing the next
frames, the steps dispatched without waiting; `worker._as_run_pass`), and prints one JSON line per pass: the median,
mean and 90th percentile of the whole frame in ms and the pass's wall time. The first pass compiles the steps (or
loads them from the compile cache): compare the later ones. The detections are simulated once into `--cache` (the
same files as `fmfusion bench --cache`). A full `fmfusion bench --no-peer` adds the timed passes, the sweep and the
report (minutes on a GPU host; this takes seconds a pass); the GPU runs of docs/benchmark.md used both.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fmfusion_jax.apps.bench import harness, worker
from fmfusion_jax.apps.bench.scenes import BenchScene, prepare_real_scene
from fmfusion_jax.compile_cache import enable_compile_cache
from fmfusion_jax.errors import UserError
from fmfusion_jax.mapping.mapper import Mapper
from fmfusion_jax.xla_options import enable_gpu_command_buffers


def as_run_passes(scene: BenchScene, passes: int, frames: int | None = None, say=print) -> list[dict]:
    """`passes` as-run passes over the first `frames` frames of `scene` (None: all); one dict per pass."""

    config, opened, folder = harness.open_bench_scene(scene, frames)
    sample = opened.sample_depth(max_frames=60)
    rows = []
    for number in range(passes):
        mapper = Mapper.for_scene(opened, config, sample=sample)
        start = time.perf_counter()
        measured, _ = worker._as_run_pass(mapper, opened, folder, config, False, scene)
        wall = time.perf_counter() - start
        calls = np.array([frame["call"] for frame in measured if frame])
        row = {
            "pass": number,
            "frames": int(calls.size),
            "median_ms": round(float(np.median(calls)), 3) if calls.size else None,
            "mean_ms": round(float(calls.mean()), 3) if calls.size else None,
            "p90_ms": round(float(np.percentile(calls, 90)), 3) if calls.size else None,
            "wall_s": round(wall, 2),
            "device": harness.device_description()["device_kind"],
        }
        say(json.dumps(row))
        rows.append(row)
        del mapper
    return rows


def main(argv: Sequence[str] | None = None) -> int:

    parser = argparse.ArgumentParser(prog="python -m fmfusion_jax.apps.bench.as_run", description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, required=True, help="real ScanNet-layout scene with ground truth")
    parser.add_argument("--cache", type=Path, default=Path("outputs/bench/cache"), help="simulated detections (made once)")
    parser.add_argument("--passes", type=int, default=3, help="passes over the frames (default 3; the first compiles)")
    parser.add_argument("--frames", type=int, default=None, help="the first N frames (default: all)")
    args = parser.parse_args(argv)
    if args.passes < 1:
        parser.error("--passes must be at least 1")
    enable_gpu_command_buffers()  # as the `fmfusion` commands: before JAX starts a backend
    enable_compile_cache()

    try:
        as_run_passes(prepare_real_scene(args.scene, args.cache, args.frames, progress=False), args.passes, args.frames)
    except UserError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
