"""`fmfusion run` end to end, as a user waits for it: a fresh process (start-up, compiling or loading the compiled
steps, reading, fusing, every output), once with an empty compile cache (cold) and once more with the cache the
first filled (warm). Its split comes from the run's own run.json: the frames as run, the outputs, the rest
(start-up, compilation or cache loads, opening the scene and its ground truth).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from fmfusion_jax.apps.bench.scenes import BenchScene
from fmfusion_jax.compile_cache import ENV as COMPILE_CACHE_ENV

#: The passes, in order: the first starts with an empty compile cache, the second loads what the first compiled.
PASSES = ("cold", "warm")


def measure_whole_run(scene: BenchScene, work: Path, say) -> dict:
    """`{"cold": pass, "warm": pass}` of `fmfusion run` on the scene's first `scene.frames` frames with its
    detections and config, each pass `{"wall_s", "frames_s", "outputs_s", "other_s", "peak_rss_mib", "outputs"}`,
    or `{"error": ...}` when a run failed."""
    cache = work / f"whole-run-xla-{scene.name}"
    shutil.rmtree(cache, ignore_errors=True)
    passes: dict = {}
    try:
        for name in PASSES:
            out = work / f"whole-run-{name}-{scene.name}"
            shutil.rmtree(out, ignore_errors=True)
            command = [
                sys.executable,
                "-m",
                "fmfusion_jax.cli",
                "run",
                str(scene.scene_dir),
                "--detections",
                str(scene.detections_dir),
                "--out",
                str(out),
                "--config",
                str(scene.config_path),
                "--set",
                f"dataset.max_frames={scene.frames}",
                "--no-progress",
            ]
            say(f"running fmfusion run on {scene.name} ({scene.frames} frames, compile cache {name})")
            start = time.perf_counter()
            completed = subprocess.run(
                command, env={**os.environ, COMPILE_CACHE_ENV: str(cache)}, capture_output=True, text=True, check=False
            )
            wall = time.perf_counter() - start
            if completed.returncode != 0:
                return {"error": f"fmfusion run exited with {completed.returncode}: {completed.stderr.strip()[-400:]}"}
            passes[name] = split_of_run(json.loads((out / "run.json").read_text()), wall)
            say(f"  {wall:.1f} s")
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    return passes


def split_of_run(record: dict, wall_s: float) -> dict:
    """A run's wall time split by its run.json: the frames as run (read, detections, fusion), the outputs (wall
    time, the instances' extraction included), and the rest."""
    frames = record.get("frame_ms_as_run", {})
    frames_s = frames.get("mean", 0.0) * frames.get("frames", 0) / 1e3
    outputs = record.get("export_seconds", {})
    outputs_s = float(record.get("export_wall_seconds", sum(outputs.values())))
    return {
        "wall_s": round(wall_s, 2),
        "frames_s": round(frames_s, 2),
        "outputs_s": round(outputs_s, 2),
        "other_s": round(wall_s - frames_s - outputs_s, 2),
        "peak_rss_mib": record.get("peak_rss_mib"),
        "outputs": outputs,
    }
