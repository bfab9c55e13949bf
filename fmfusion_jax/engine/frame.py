"""One frame through the engine, the order of its steps written once: `fuse_frame` for one map, `fuse_frames`
for a batch of maps in lock step (its vmapped twin), `finalize_maps` for the batch's end.

The host decides what is due (the detection schedule, and the merge and geometry-fusion cadences, count
frames on the host: no device value is waited for); these functions run the due steps of `engine.step` in
their order. The states are donated, as to the steps.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from fmfusion_jax.engine import step
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.detections import DetectionBatch
from fmfusion_jax.engine.state import MapState

#: A detection frame's statistics as `fuse_frame` returns them (device values, read later by the host):
#: `(FrameStats, RefineStats | None)`, or `step.fuse_and_refine`'s packed int32 vector (`step.unpack_statistics`).
FrameStatistics = tuple[step.FrameStats, step.RefineStats | None] | jax.Array


def fuse_frame(
    state: MapState,
    frame: step.FrameInputs,
    batch: DetectionBatch | None,
    likelihood: jax.Array,
    config: MapConfig,
    fusion: step.FusionConfig,
    *,
    merge: bool,
    geometry: bool,
    run: Callable[..., Any] = step.call_stage,
    fuse: Callable[..., Any] = step.fuse_detections,
    one_call: bool = False,
) -> tuple[MapState, FrameStatistics | None]:
    """One frame: the global TSDF alone (no `batch`), or the detection step, then the online merge when `merge`
    is due and the geometry fusion when `geometry` is due (both only after a detection frame).

    Args:
      batch: the frame's packed detections, or None.
      likelihood: float32[O, C].
      config: the compiled layout (`MapConfig.compiled_layout()`).
      fusion: the host `FusionConfig` (put on the device here once per config).
      run: `run(name, step, *args)` calls each step (names `tsdf`, `fusion`, `refine`, `geometry_fusion`):
        `MapBuilder` passes its `StageTimer.run`.
      fuse: the detection step: `step.fuse_detections`, or the bench's stage-by-stage twin.
      one_call: a detection frame with the merge due is one executable (`step.fuse_and_refine`, untimed): the
        same map from one call instead of two (worth it off the CPU, where a call costs the host ~1 ms).

    Returns:
      The state, and None after a frame without detections, else its `FrameStatistics`.
    """
    if batch is None:
        return run("tsdf", step.integrate_frame, state, frame, config), None
    on_device = step.fusion_on_device(fusion)
    statistics: FrameStatistics
    if merge and one_call:
        state, statistics = step.fuse_and_refine(state, frame, batch, likelihood, config, on_device)
    else:
        state, stats = run("fusion", fuse, state, frame, batch, likelihood, config, on_device)
        refine_stats = None
        if merge:
            state, refine_stats = run("refine", step.refine, state, config, fusion)
        statistics = (stats, refine_stats)
    if geometry:
        state = run("geometry_fusion", step.fuse_geometry, state, config, on_device)
    return state, statistics


def _where(keep_new: jax.Array, new, old):
    """Per leaf `new if keep_new else old` (`keep_new` a scalar bool: one map of a vmapped batch)."""
    return jax.tree.map(lambda a, b: jnp.where(keep_new, a, b), new, old)


@functools.partial(jax.jit, static_argnames=("config",), donate_argnames=("states",))
def _detection_frames(states, frames, batches, likelihood, has_frame, has_detections, config: MapConfig, fusion):
    """The detection step for every map of a batch where it has detections, the TSDF alone where it has none,
    nothing where it has no frame. (A detection step with no valid detection integrates the TSDF and leaves
    the voxels' instance slots as they are; only its table, whose missed counts it would advance, is taken
    from before.)"""

    def one(state, frame, batch, with_frame, with_detections):
        batch = batch._replace(valid=batch.valid & with_detections)
        new, stats = step.fuse_detections(state, frame, batch, likelihood, config, fusion)
        new = new._replace(instances=_where(with_detections, new.instances, state.instances))
        return _where(with_frame, new, state), stats

    return jax.vmap(one)(states, frames, batches, has_frame, has_detections)


@functools.partial(jax.jit, static_argnames=("config", "kind"), donate_argnames=("states",))
def _refine_where(states, due, config: MapConfig, fusion, kind: str):
    """`refine`, `fuse_geometry` or `finalize` (`kind`) on the maps where `due bool[B]`; the others unchanged."""

    def one(state, is_due):
        if kind == "geometry":
            new, stats = step.fuse_geometry(state, config, fusion), None
        else:
            new, stats = (step.refine if kind == "refine" else step.finalize)(state, config, fusion)
        return _where(is_due, new, state), stats

    return jax.vmap(one)(states, due)


def fuse_frames(
    states: MapState,
    frames: step.FrameInputs,
    batches: DetectionBatch,
    likelihood: jax.Array,
    has_frame: np.ndarray,
    has_detections: np.ndarray,
    merge: np.ndarray,
    geometry: np.ndarray,
    config: MapConfig,
    fusion: step.FusionConfig,
) -> tuple[MapState, step.FrameStats, step.RefineStats | None]:
    """`fuse_frame` for `B` maps in lock step, each step once for all maps (vmapped): the maps' arrays are
    stacked on a leading axis, the masks `has_frame`, `has_detections`, `merge`, `geometry` are bool[B] (the
    merge and the geometry fusion run, for the maps due, only when one is due). Map `i` comes out as
    `fuse_frame` would leave it.

    Returns:
      The states, the `FrameStats` (stacked; meaningful where `has_detections`), and the merge's stacked
      `RefineStats` (None when no map's merge was due).
    """
    states, stats = _detection_frames(states, frames, batches, likelihood, has_frame, has_detections, config, fusion)
    refine_stats = None
    if merge.any():
        states, refine_stats = _refine_where(states, merge, config, fusion, "refine")
    if geometry.any():
        states, _ = _refine_where(states, geometry, config, fusion, "geometry")
    return states, stats, refine_stats


def finalize_maps(states: MapState, config: MapConfig, fusion: step.FusionConfig) -> tuple[MapState, step.RefineStats]:
    """`step.finalize` on every map of a stacked batch (`fuse_frames`)."""
    everyone = np.ones(jax.tree.leaves(states)[0].shape[0], bool)
    return _refine_where(states, everyone, config, fusion, "finalize")
