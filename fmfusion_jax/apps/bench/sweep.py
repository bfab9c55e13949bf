"""The controlled per-object sweep of `fmfusion bench`: the same frames, the same map, only the number of
detections fused per frame varies.

Across the generated rooms the detections per frame barely vary (the rooms also differ in size), so a
line fitted across them says little about what one more object costs. Here one scene's first frames
are fused once per cap `k`, each frame's detections capped to `k` on the host before packing
(`cap_detections`): the padded shapes (`detections.max_detections`, `instances.capacity`) stay those
of the config, so nothing recompiles and only the load changes. Fitting ms per frame against the mean
detections fused per frame gives the base + per-object cost (the paper's Table IV).

Which detections a cap keeps: the `k` highest-scoring usable ones (`engine.detections.select_detections`,
the packer's own rule when a frame has more detections than its capacity; ties: the earlier one), in
their original order; a frame with `k` or fewer usable detections is left as it is. So a run capped at
`k` fuses what a run with `detections.max_detections = k` would fuse.

    python -m fmfusion_jax.apps.bench.worker SPEC.json RESULT.json   (pipeline "ours-sweep" or "peer-sweep")

The runs of the different caps advance together, one frame each in turn (the order rotating from frame
to frame), so that a change in the machine's load hits every cap alike; for ours, as many maps as fit in
half the free memory are held at once (the others follow in a later group). Ours first fuses the frames
once uncapped (not timed), which compiles every jitted function once for the whole process.
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import sys
import time
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from fmfusion_jax.apps.bench.harness import (
    PEER_MODULE,
    device_description,
    frames_with_detections,
    open_bench_scene,
    peak_rss_mb,
    peer_unavailable_reason,
    scene_map_config,
)
from fmfusion_jax.apps.bench.scenes import BenchScene
from fmfusion_jax.apps.bench.stages import FrameTimer
from fmfusion_jax.engine.detections import select_detections
from fmfusion_jax.labels import load_label_sets
from fmfusion_jax.mapping.builder import MapBuilder
from fmfusion_jax.mapping.engine_configs import fusion_likelihood
from fmfusion_jax.types import FrameDetections


def cap_detections(detections: FrameDetections, k: int, open_labels: Sequence[str], min_mask_pixels: int) -> FrameDetections:
    """The frame's detections capped to the `k` highest-scoring usable ones (original order kept).

    Usable and score as `pack_detections` counts them (a mask of `min_mask_pixels` pixels or more, a
    score on some open label; score = max over its labels; ties: the earlier detection). A frame with
    `k` or fewer usable detections is returned as it is (the same object).
    """
    if k < 1:
        raise ValueError(f"the cap must be >= 1, got {k}")
    keep, usable = select_detections(detections, open_labels, k, min_mask_pixels)
    if usable <= k:
        return detections
    return dataclasses.replace(
        detections,
        masks=np.asarray(detections.masks)[keep],
        labels=[detections.labels[i] for i in keep],
        boxes=np.asarray(detections.boxes)[keep],
    )


def _rotated(items: Sequence, shift: int) -> list:
    shift %= len(items)
    return list(items[shift:]) + list(items[:shift])


def _free_bytes() -> float:
    """Memory the maps can take: the accelerator's free bytes where it reports them, else the host's."""

    try:
        stats = jax.devices()[0].memory_stats() or {}
    except Exception:  # noqa: BLE001 - backends without memory statistics raise various errors
        stats = {}
    if "bytes_limit" in stats:
        return float(stats["bytes_limit"] - stats.get("bytes_in_use", 0))
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    return float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))


def groups_that_fit(ks: Sequence[int], map_bytes: float, free_bytes: float) -> list[list[int]]:
    """The caps in groups whose maps fit together in half of `free_bytes` (at least one per group)."""
    together = max(1, min(len(ks), int(0.5 * free_bytes // max(map_bytes, 1.0))))
    return [list(ks[i : i + together]) for i in range(0, len(ks), together)]


def _new_run(k: int) -> dict:
    return {"k": k, "frames": [], "compiled": [], "detections_in": [], "detections_fused": [], "live_instances": []}


def run_ours_sweep(scene: BenchScene, frames: int | None, progress: bool, sweep: Sequence[int]) -> dict:
    """Our engine (the fused step, as `fmfusion run` drives it) once per cap in `sweep` on the first
    `frames` frames. Per cap: `frames`/`compiled` as the ours worker's, detections given and fused and
    live instances per frame."""

    config, opened, folder = open_bench_scene(scene, frames)
    baseline_mb = peak_rss_mb()
    map_config = scene_map_config(config, open_bench_scene(scene, None)[1])  # the map of the ours worker (all the scene's frames)
    label_sets = load_label_sets()
    likelihood = jnp.asarray(fusion_likelihood(config), jnp.float32)
    open_labels, det = label_sets.open_labels, config.detections
    device = device_description()

    def builder(timer: FrameTimer) -> MapBuilder:
        return MapBuilder(config, map_config, label_sets=label_sets, likelihood=likelihood, timer=timer)

    start = time.perf_counter()
    warm = FrameTimer()  # the uncapped pass that compiles everything
    warm_builder = builder(warm)
    for frame, detections in frames_with_detections(opened, folder, config, progress, f"ours warm-up {scene.name}"):
        warm.start_frame()
        warm_builder.add_frame(frame, detections)
    del warm_builder
    groups = groups_that_fit(sweep, map_config.memory_bytes(), _free_bytes())
    print(
        f"ours sweep on {scene.name}: {len(opened)} frames, caps {list(sweep)} in {len(groups)} group(s), "
        f"device {device['device_kind']} ({device['platform']}); warm-up {time.perf_counter() - start:.0f} s",
        file=sys.stderr,
        flush=True,
    )

    runs = {k: _new_run(k) for k in sweep}
    for group in groups:
        timers = {k: FrameTimer(first_ms=dict(warm.first_ms), warm=set(warm.warm)) for k in group}  # compiled: all samples
        builders = {k: builder(timers[k]) for k in group}
        for position, (frame, detections) in enumerate(
            frames_with_detections(opened, folder, config, progress, f"ours sweep {scene.name} k={','.join(map(str, group))}")
        ):
            for k in _rotated(group, position):
                capped = None if detections is None else cap_detections(detections, k, open_labels, det.min_mask_pixels)
                timers[k].start_frame()
                builders[k].add_frame(frame, capped)
                _count(runs[k], detections, capped, builders[k].state.instances.valid.sum(), open_labels, det)
        for k in group:
            runs[k].update(frames=timers[k].frames, compiled=timers[k].compiled)
        del builders
    return {
        "pipeline": "ours-sweep",
        "device": device,
        "map": map_config.describe(),
        "sweep": list(sweep),
        "groups": groups,
        "runs": [runs[k] for k in sweep],
        "peak_rss_mb": peak_rss_mb(),
        "baseline_rss_mb": baseline_mb,
        "seconds": time.perf_counter() - start,
    }


def run_peer_sweep(scene: BenchScene, frames: int | None, progress: bool, sweep: Sequence[int]) -> dict:
    """The Open3D per-instance peer once per cap in `sweep` on the first `frames` frames (all caps
    together: its pipelines are small)."""

    reason = peer_unavailable_reason()
    if reason:
        return {"pipeline": "peer-sweep", "unavailable": reason}
    peer = importlib.import_module(PEER_MODULE)
    config, opened, folder = open_bench_scene(scene, frames)
    baseline_mb = peak_rss_mb()
    label_sets = load_label_sets()
    likelihood = fusion_likelihood(config)
    open_labels, det = label_sets.open_labels, config.detections
    pipelines = {k: peer.Open3DInstancePipeline(config, opened.intrinsics, likelihood, label_sets) for k in sweep}
    runs = {k: _new_run(k) for k in sweep}
    start = time.perf_counter()
    for position, (frame, detections) in enumerate(
        frames_with_detections(opened, folder, config, progress, f"Open3D peer sweep {scene.name}")
    ):
        for k in _rotated(list(sweep), position):
            capped = None if detections is None else cap_detections(detections, k, open_labels, det.min_mask_pixels)
            runs[k]["frames"].append({name: float(v) for name, v in pipelines[k].add_frame(frame, capped).items()})
            runs[k]["compiled"].append({})
            _count(runs[k], detections, capped, pipelines[k].num_instances, open_labels, det)
    return {
        "pipeline": "peer-sweep",
        "sweep": list(sweep),
        "runs": [runs[k] for k in sweep],
        "peak_rss_mb": peak_rss_mb(),
        "baseline_rss_mb": baseline_mb,
        "seconds": time.perf_counter() - start,
    }


def _count(run: dict, detections: FrameDetections | None, capped: FrameDetections | None, live, open_labels, det) -> None:
    """Appends a frame's detections given, detections fused (what the packer keeps) and live instances."""
    run["detections_in"].append(0 if detections is None else detections.num_detections)
    fused = 0 if capped is None else len(select_detections(capped, open_labels, det.max_detections, det.min_mask_pixels)[0])
    run["detections_fused"].append(fused)
    run["live_instances"].append(int(live))


RUNNERS = {"ours-sweep": run_ours_sweep, "peer-sweep": run_peer_sweep}

__all__ = ["cap_detections", "groups_that_fit", "run_ours_sweep", "run_peer_sweep", "RUNNERS"]
