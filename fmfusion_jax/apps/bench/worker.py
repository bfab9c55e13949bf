"""One pipeline on one scene, in a process of its own (so that peak memory is that pipeline's alone).

    python -m fmfusion_jax.apps.bench.worker SPEC.json RESULT.json

SPEC: `{"pipeline": "ours" | "peer" | "vbg" | "ours-sweep" | "peer-sweep", "scene": BenchScene.to_json(),
"frames": N | null, "progress": bool}`; the sweeps (`bench.sweep`) add `"sweep": [k, ...]`. RESULT:
per-frame stage times in milliseconds and the counts and memory figures the report needs (see each
`run_*`). A pipeline that cannot run (Open3D missing) writes `{"unavailable": reason}`.

- `ours`: the engine as `fmfusion run` drives it (`mapping.MapBuilder`: its schedules), three times over the
  same frames: with the fused `fuse_detections` and a timer around each jitted step (each then waits for the
  device; the peak memory), with its stages jitted one by one (`bench.stages`) to see where the time goes,
  and as run, without timers (the whole frame: the host's work overlaps the device's). All make the same map.
- `peer`: the Open3D reference pipeline (a global ScalableTSDFVolume and one volume per instance).
- `vbg`: Open3D's VoxelBlockGrid integration alone.
Times exclude reading images and detection files, for every pipeline (and, for ours, putting the frame's
arrays on the device, which `MapBuilder` does before each step).
"""

from __future__ import annotations

import concurrent.futures
import hashlib
import importlib
import itertools
import json
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np

from fmfusion_jax.apps.bench import profile as tracing
from fmfusion_jax.apps.bench.harness import (
    PEER_MODULE,
    device_description,
    device_memory_mb,
    frames_with_detections,
    open_bench_scene,
    peak_rss_mb,
    peer_unavailable_reason,
)
from fmfusion_jax.apps.bench.report import AS_RUN_CHUNK
from fmfusion_jax.apps.bench.scenes import BenchScene
from fmfusion_jax.apps.bench.stages import FUSION_STAGES, FrameTimer, staged_fuse_detections
from fmfusion_jax.apps.bench.sweep import RUNNERS as SWEEP_RUNNERS
from fmfusion_jax.compile_cache import enable_compile_cache
from fmfusion_jax.labels import load_label_sets
from fmfusion_jax.mapping.engine_configs import fusion_likelihood
from fmfusion_jax.mapping.mapper import Mapper
from fmfusion_jax.run.scene_fusion import SceneFusion, read_ahead


def run_ours(scene: BenchScene, frames: int | None, progress: bool, profile: dict | None = None) -> dict:
    """Our engine: the fused pass (`frames`: stage name -> ms per frame, from `MapBuilder`'s timer: `fusion`,
    `tsdf`, `refine`, `geometry_fusion`), then the staged pass (`stage_frames`: `stages.FUSION_STAGES`), then the
    pass as run, without timers (`run_frames`: `call`, the wall time of each `Mapper.integrate`).

    The map is `fmfusion run`'s (`Mapper.for_scene`): sized from a depth sample, growing (pool, table) by
    doubling when a frame might not fit; the calls that recompiled after a growth are left out of the figures."""
    from fmfusion_jax.apps.bench.stages import FrameTimer

    cache = enable_compile_cache()  # as `fmfusion run` has it (FMFUSION_COMPILE_CACHE=off: compile everything)
    cache_entries = _entries(cache)
    config, opened, folder = open_bench_scene(scene, frames)
    baseline_mb = peak_rss_mb()
    sample = opened.sample_depth(max_frames=60)
    device = device_description()
    print(
        f"ours on {scene.name}: {len(opened)} frames, device {device['device_kind']} ({device['platform']}), "
        f"{device['cpus']} CPUs",
        file=sys.stderr,
        flush=True,
    )

    def fuse(staged: bool) -> tuple[Mapper, FrameTimer, dict]:
        timer = FrameTimer()
        step_hook = {"fuse_detections": staged_fuse_detections(timer)} if staged else {}
        mapper = Mapper.for_scene(opened, config, sample=sample, timer=timer, **step_hook)
        counts: dict[str, list[int]] = {"detections_in": [], "live_instances": []}
        for frame, detections in frames_with_detections(
            opened, folder, config, progress, f"ours {'staged' if staged else 'fused'} {scene.name}"
        ):
            timer.start_frame()
            start = time.perf_counter()  # `fmfusion run` prepares frames in its reader threads: timed apart
            prepared = mapper.prepare(frame, detections)
            timer.record("prepare", (time.perf_counter() - start) * 1e3, compiled=False)
            mapper.integrate(prepared)
            counts["detections_in"].append(0 if detections is None else detections.num_detections)
            counts["live_instances"].append(int(mapper.state.instances.valid.sum()))
        return mapper, timer, counts

    start = time.perf_counter()
    mapper, timer, counts = fuse(staged=False)
    map_config = mapper.map_config
    assert map_config is not None  # the scene has frames
    result = {
        "pipeline": "ours",
        "device": device,
        "map": map_config.describe(),
        "map_state_mb": map_config.memory_bytes() / 2**20,
        "growths": mapper.growths,
        "frames": timer.frames,
        "compiled": timer.compiled,
        "compile_ms": _compile_ms(timer),
        "counters": mapper.counters,
        **counts,
        "blocks_used": int(mapper.state.blocks.num_blocks),
        "dropped_blocks": int(mapper.state.blocks.dropped_blocks),
        "compile_cache": {
            "dir": str(cache) if cache else None,
            "entries_before": cache_entries,
            # more entries after the pass than before: some steps were compiled here (their peak memory with them)
            "entries_after": _entries(cache),
        },
        "block_capacity": map_config.block_capacity,
        "peak_rss_mb": peak_rss_mb(),
        "baseline_rss_mb": baseline_mb,
        "device_memory_mb": device_memory_mb(),
        "geometry_fusion_every": config.refinement.geometry_fusion_every,
        "seconds_fused": time.perf_counter() - start,
    }
    fused_digest = state_digest(mapper.state)
    del mapper  # frees the map before the second pass
    staged_mapper, staged_timer, _ = fuse(staged=True)
    if state_digest(staged_mapper.state) != fused_digest:  # the stages composed must make the same map
        result["staged_mismatch"] = "the stages jitted apart made a different map than the fused step" + _mismatch_cause(device)
    result.update(stage_frames=staged_timer.frames, stage_compiled=staged_timer.compiled)
    result["compile_ms"].update({f"stage:{k}": v for k, v in _compile_ms(staged_timer).items() if k in FUSION_STAGES})
    del staged_mapper
    run_mapper = Mapper.for_scene(opened, config, sample=sample)
    run_frames, run_left_out = _as_run_pass(run_mapper, opened, folder, config, progress, scene, profile)
    if profile:
        result["profile"] = profile
    if state_digest(run_mapper.state) != fused_digest:  # waiting for each step or not must not change the map
        result["as_run_mismatch"] = "the pass without timers made a different map than the timed one" + _mismatch_cause(device)
    result.update(run_frames=run_frames, run_compiled=run_left_out)
    return result


def _as_run_pass(
    mapper, opened, folder, config, progress: bool, scene: BenchScene, profile: dict | None = None
) -> tuple[list, list]:
    """Fuses the frames into `mapper` (a `Mapper` without timers) as `fmfusion run` drives it: each step is dispatched
    without waiting, the main thread's work for a frame (checks, growth check, dispatch) overlaps the device's work
    on the one before, and reader threads (as many as `fmfusion run` has here) prepare the next frames
    (`Mapper.prepare`: block extent, packing, sent to the device).

    Returns per-frame `{"call": ms}` (the wall time of waiting for the frame's preparation and of `Mapper.integrate`:
    its host work, then the wait for the previous frame's steps, then the dispatch of its own; in a steady run
    their median is the time per frame)
    and, in the same layout, the calls left out: the first of each chunk of `AS_RUN_CHUNK` frames read ahead
    (it finds the device idle) and those in which the map grew (their steps compiled in the first pass).
    The frames of a chunk are read before its calls: reading between two calls would give the device time that a
    run whose reader works in another thread (`fmfusion run`) does not have.
    With `profile` (`{"frames": N, "trace": path}`, `--profile`), the last N frames are traced with `jax.profiler`
    and left out; `profile` gains the trace's summary (`bench.profile.summarize_trace`).
    """

    import jax

    frames: list[dict] = []
    left_out: list[dict] = []
    # at most half of the frames traced: the others make the as-run figures
    traced_from = len(opened) - min(int(profile["frames"]), len(opened) // 2) if profile else None
    trace_dir = Path(profile["trace"]).with_suffix(".tmp") if profile else None
    stream = frames_with_detections(opened, folder, config, progress, f"ours as run {scene.name}")
    workers = SceneFusion.READ_WORKERS  # as `fmfusion run`: one reader on a small machine, up to four on many cores
    with concurrent.futures.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="fmfusion-read") as reader:
        while chunk := list(itertools.islice(stream, AS_RUN_CHUNK)):
            # as `fmfusion run`'s readers: a few frames ahead of the one fused
            prepared = read_ahead(lambda pair: mapper.prepare(*pair), chunk, reader, SceneFusion.READ_AHEAD * workers)
            for position in range(len(chunk)):
                if len(frames) == traced_from and profile is not None:
                    try:
                        tracing.start_trace(trace_dir)  # type: ignore[arg-type]
                    except Exception as error:  # noqa: BLE001 - a profiler that cannot start leaves the bench as it was
                        profile["error"] = f"jax.profiler did not start: {error}"
                        traced_from = None
                growths = mapper.growths
                start = time.perf_counter()
                mapper.integrate(next(prepared))
                elapsed = {"call": (time.perf_counter() - start) * 1e3}
                skip = position == 0 or mapper.growths != growths or (traced_from is not None and len(frames) >= traced_from)
                frames.append({} if skip else elapsed)
                left_out.append(elapsed if skip else {})
    jax.block_until_ready(mapper.state)
    if profile is not None and traced_from is not None and traced_from < len(frames):
        kept = tracing.stop_trace(trace_dir, Path(profile["trace"]))  # type: ignore[arg-type]
        traced = len(frames) - traced_from
        profile.update(frames=traced)
        if kept is None:
            profile["error"] = "jax.profiler wrote no Perfetto trace"
        else:
            profile["threads"] = tracing.summarize_trace(kept, traced)
    elif profile is not None and "error" not in profile:
        profile["error"] = f"{len(frames)} frames: too few to trace any (at most half of them are)"
    return frames, left_out


def _entries(cache) -> int | None:
    """Files in the compile cache folder (None without one)."""
    return sum(1 for _ in cache.iterdir()) if cache else None


def _mismatch_cause(device: dict) -> str:
    """Why two passes over the same frames may differ on this device ("" where they must not)."""

    if device["platform"] != "gpu" or "xla_gpu_deterministic_ops=true" in os.environ.get("XLA_FLAGS", ""):
        return ""
    # seen on an H200: two fused passes differ from each other as well; with the flag all four maps agree
    return (
        " (expected on a GPU: XLA's scatters there add in no fixed order, so floating-point sums differ in their last"
        " bits from run to run; XLA_FLAGS=--xla_gpu_deterministic_ops=true makes them bit-identical, at a cost in speed)"
    )


def state_digest(state) -> str:
    """SHA-256 of every array of a map state (bit-exact comparison of two maps without keeping both)."""

    digest = hashlib.sha256()
    for leaf in jax.tree.leaves(state):
        digest.update(np.ascontiguousarray(jax.device_get(leaf)).data)
    return digest.hexdigest()


def _compile_ms(timer) -> dict[str, float]:
    """First call minus the median call, per timed function: the compile time (and first-run effects)."""
    return {name: first - timer.median_ms(name) for name, first in timer.first_ms.items() if timer.samples_ms.get(name)}


def run_peer(scene: BenchScene, frames: int | None, progress: bool) -> dict:
    """The Open3D per-instance reference pipeline: `frames` is its stage name -> ms per frame."""

    reason = peer_unavailable_reason()
    if reason:
        return {"pipeline": "peer", "unavailable": reason}
    peer = importlib.import_module(PEER_MODULE)

    config, opened, folder = open_bench_scene(scene, frames)
    baseline_mb = peak_rss_mb()
    pipeline = peer.Open3DInstancePipeline(config, opened.intrinsics, fusion_likelihood(config), load_label_sets())
    times = []
    counts: dict[str, list[int]] = {"detections_in": [], "live_instances": []}
    for frame, detections in frames_with_detections(opened, folder, config, progress, f"Open3D peer {scene.name}"):
        times.append({k: float(v) for k, v in pipeline.add_frame(frame, detections).items()})
        counts["detections_in"].append(0 if detections is None else detections.num_detections)
        counts["live_instances"].append(int(pipeline.num_instances))
    return {
        "pipeline": "peer",
        "frames": times,
        **counts,
        "peak_rss_mb": peak_rss_mb(),
        "baseline_rss_mb": baseline_mb,
        "open3d": _open3d_version(),
    }


def run_vbg(scene: BenchScene, frames: int | None, progress: bool) -> dict:
    """Open3D's VoxelBlockGrid TSDF integration alone: `frames` is `{"tsdf": ms}` per frame."""

    reason = peer_unavailable_reason()
    if reason:
        return {"pipeline": "vbg", "unavailable": reason}
    peer = importlib.import_module(PEER_MODULE)
    config, opened, folder = open_bench_scene(scene, frames)
    baseline_mb = peak_rss_mb()
    tsdf = peer.VoxelBlockGridTSDF(config.tsdf.voxel_size, config.tsdf.sdf_trunc, config.dataset.depth_max, opened.intrinsics)
    times = [
        {"tsdf": float(tsdf.integrate(frame))}
        for frame, _ in frames_with_detections(opened, folder, config, progress, f"Open3D VBG {scene.name}")
    ]
    return {
        "pipeline": "vbg",
        "frames": times,
        "peak_rss_mb": peak_rss_mb(),
        "baseline_rss_mb": baseline_mb,
        "open3d": _open3d_version(),
    }


def _open3d_version() -> str | None:
    try:
        import open3d
    except ImportError:
        return None
    return open3d.__version__


RUNNERS = {"ours": run_ours, "peer": run_peer, "vbg": run_vbg}


def main(argv: list[str]) -> int:
    spec_path, result_path = map(Path, argv)
    spec = json.loads(spec_path.read_text())
    scene = BenchScene.from_json(spec["scene"])
    args = (scene, spec.get("frames"), bool(spec.get("progress", True)))
    if spec["pipeline"].endswith("-sweep"):
        result = SWEEP_RUNNERS[spec["pipeline"]](*args, [int(k) for k in spec["sweep"]])
    else:
        traced = {"profile": spec["profile"]} if spec.get("profile") else {}  # `--profile`: ours on the main scene
        result = RUNNERS[spec["pipeline"]](*args, **traced)
    result["scene"] = scene.name
    result_path.write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
