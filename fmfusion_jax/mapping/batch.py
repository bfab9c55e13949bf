"""`MapperBatch`: `B` independent maps of one config fused in lock step (the engine's `fuse_frames`)."""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from fmfusion_jax.compile_cache import use_compile_cache
from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.frame import finalize_maps, fuse_frames
from fmfusion_jax.engine.state import MapState, init_map_state
from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import LabelSets, load_label_sets
from fmfusion_jax.mapping.builder import FusionProgress, FusionResult
from fmfusion_jax.mapping.capacity import FIXED_POOL_MARGIN, CapacityMonitor, initial_pool_blocks, scene_extent
from fmfusion_jax.mapping.engine_configs import build_fusion_config, build_map_config, fusion_likelihood
from fmfusion_jax.mapping.inputs import HostAdapter, as_config
from fmfusion_jax.mapping.mapper import Mapper
from fmfusion_jax.mapping.schedule import DetectionSchedule
from fmfusion_jax.mapping.telemetry import StageTimer
from fmfusion_jax.types import FrameDetections, RGBDFrame

log = logging.getLogger(__name__)


@functools.partial(jax.jit, static_argnames=("map_config", "batch_size"))
def _initial_states(map_config: MapConfig, batch_size: int) -> MapState:
    """`batch_size` empty maps stacked along a leading axis: one compiled program, not one per leaf of the state."""
    return jax.tree.map(lambda leaf: jnp.broadcast_to(leaf, (batch_size, *leaf.shape)), init_map_state(map_config))


@jax.jit
def _state_at(states: MapState, index: jax.Array) -> MapState:
    """Map `index` of stacked states, in fresh buffers: one compiled program for any index, not a slice and a
    squeeze per leaf."""
    return jax.tree.map(lambda leaf: leaf[index], states)


class MapperBatch:
    """`B` independent maps of one config, fused in lock step: each engine step runs once for all maps,
    vmapped, with the states donated (one compiled step whatever `B`). For many short scenes on one device,
    or for experiments over seeds and noise models.

    All maps share the image size and one block layout: `bounds` must cover every map's scene, each in its own
    world frame (e.g. the union of the scenes' bounds). The maps do not grow: the instance table is the config's, and
    so is the block pool unless `expected_blocks` sizes it (the most any map is expected to use, as
    `capacity.scene_extent` counts it for a scene: the pool takes `FIXED_POOL_MARGIN` times that; each vmapped step
    walks every map's whole pool, so a pool sized to the scenes is faster and smaller than the config's). Each map
    keeps its own detection schedule and refinement schedule, as a `Mapper` would; map `i` fused here equals a
    `Mapper(config, bounds=bounds)` fed the same frames (`tests/test_mapper.py`).

        batch = MapperBatch("scannet", 3, bounds=(lo, hi), image_shape=(480, 640))
        for frames, detections in zip(...):          # one frame (or None) and its detections per map
            batch.integrate(frames, detections)
        results = batch.finalize()                    # a FusionResult per map
        batch.mapper(0).instances()                   # map 0 as an ordinary Mapper
    """

    def __init__(
        self,
        config: "str | Path | Mapping[str, Any] | PipelineConfig | None",
        batch_size: int,
        *,
        bounds: "tuple[Sequence[float], Sequence[float]]",
        image_shape: tuple[int, int],
        expected_blocks: int | None = None,
        label_sets: LabelSets | None = None,
        likelihood: np.ndarray | None = None,
    ):
        if batch_size < 1:
            raise UserError(f"batch_size must be >= 1, got {batch_size}")
        self.config = as_config(config)
        use_compile_cache()
        self.label_sets = label_sets or load_label_sets()
        self.batch_size = batch_size
        self._bounds = (np.asarray(bounds[0], float), np.asarray(bounds[1], float))
        height, width = image_shape
        self.map_config = build_map_config(self.config, *self._bounds, height, width, self.label_sets)
        if expected_blocks is not None:
            pool = initial_pool_blocks(expected_blocks, self.map_config.block_capacity, FIXED_POOL_MARGIN)
            self.map_config = dataclasses.replace(self.map_config, block_capacity=pool)
        self._step_config = self.map_config.compiled_layout()  # the steps' static config (the states hold the origin)
        self.states = _initial_states(self.map_config, batch_size)
        self.fusion_config = build_fusion_config(self.config, self.label_sets)
        if likelihood is None:
            likelihood = fusion_likelihood(self.config)
        self._likelihood = jax.device_put(np.asarray(likelihood, np.float32))  # converted on the host: no cast compiled
        self._adapter = HostAdapter.for_map(self.config, self.map_config, self.label_sets)
        # each map's own counts, cadences, detection schedule and capacity warnings (a `MapBuilder` keeps them
        # for one map); the states live stacked in `states`
        self._progress = [FusionProgress(self.config.refinement) for _ in range(batch_size)]
        self._monitors = [CapacityMonitor() for _ in range(batch_size)]
        self._schedules = [DetectionSchedule(self.config) for _ in range(batch_size)]
        self._results: list[FusionResult] | None = None

    @classmethod
    def for_scenes(
        cls, scenes: Sequence[Any], config: "str | Path | Mapping[str, Any] | PipelineConfig | None" = None, **options: Any
    ) -> MapperBatch:
        """A batch for `scenes` (`fmfusion_jax.open_scene`'s `Scene`s of one image size), sized as `fmfusion run` sizes
        a map: one block index over the union of their bounds and a pool for the most blocks any of them is expected
        to use, each from a sample of the scene's frames (`capacity.scene_extent`). `options`: `label_sets`,
        `likelihood`. Scenes of different image sizes are a `UserError`."""
        pipeline = as_config(config)
        shapes = {(scene.intrinsics.height, scene.intrinsics.width) for scene in scenes}
        if len(shapes) != 1:
            raise UserError(f"scenes of different image sizes {sorted(shapes)} cannot be fused in one batch")
        extents = [scene_extent(scene, pipeline, label_sets=options.get("label_sets")) for scene in scenes]
        lo = np.min([bounds[0] for bounds, _ in extents], axis=0)
        hi = np.max([bounds[1] for bounds, _ in extents], axis=0)
        expected = max(blocks for _, blocks in extents)
        return cls(pipeline, len(scenes), bounds=(lo, hi), image_shape=shapes.pop(), expected_blocks=expected, **options)

    def integrate(
        self, frames: "Sequence[RGBDFrame | None]", detections: "Sequence[FrameDetections | None] | None" = None
    ) -> list[bool]:
        """Integrates one frame per map (None: that map waits) and fuses each due map's detections.
        Returns, per map, whether its detections were fused."""
        if self._results is not None:
            raise UserError("this batch is finalized: integrate frames before finalize()")
        if len(frames) != self.batch_size or (detections is not None and len(detections) != self.batch_size):
            raise UserError(
                f"integrate: expected {self.batch_size} frames and detections (one per map, None to "
                f"skip), got {len(frames)} and {len(detections) if detections is not None else 0}"
            )
        detections = list(detections) if detections is not None else [None] * self.batch_size
        template = next((f for f in frames if f is not None), None)
        if template is None:
            return [False] * self.batch_size
        inputs, batches, has_frame, due = [], [], [], []
        merge_due, geometry_due = np.zeros(self.batch_size, bool), np.zeros(self.batch_size, bool)
        for i, (frame, dets) in enumerate(zip(frames, detections)):
            progress, schedule = self._progress[i], self._schedules[i]
            fused = (
                frame is not None
                and dets is not None
                and schedule.due(progress.frames_integrated, np.asarray(frame.T_world_camera))
            )
            inputs.append(self._adapter.frame(frame if frame is not None else template))
            batches.append(self._adapter.detections(dets if fused else None))
            has_frame.append(frame is not None)
            due.append(fused)
            if frame is None:
                continue
            progress.frames_integrated += 1
            schedule.advance(frame.T_world_camera)
            if fused:
                schedule.fused(frame.T_world_camera)
                merge_due[i], geometry_due[i] = progress.count_detection_frame()
        stack = lambda items: jax.tree.map(lambda *leaves: np.stack(leaves), *items)  # noqa: E731
        self.states, stats, refine_stats = fuse_frames(
            self.states,
            stack(inputs),
            stack(batches),
            self._likelihood,
            np.array(has_frame),
            np.array(due),
            merge_due,
            geometry_due,
            self._step_config,
            self.fusion_config,
        )
        stats, refine_stats = jax.device_get((stats, refine_stats))
        for i, frame in enumerate(frames):
            if due[i]:
                self._progress[i].add_frame_counts(jax.tree.map(lambda x, i=i: x[i], stats))
            if merge_due[i] and frame is not None:
                self._progress[i].add_refinement(frame.name, jax.tree.map(lambda x, i=i: x[i], refine_stats))
        # the overflow counters of every map in one small transfer (not each map's state sliced out)
        counts = jax.device_get(CapacityMonitor.counts_of(self.states))
        for i, frame in enumerate(frames):
            if frame is not None:
                self._monitors[i].check_counts(
                    {name: value[i] for name, value in counts.items()}, self.map_config, self._progress[i].frames_integrated
                )
        return due

    def finalize(self) -> list[FusionResult]:
        """Finalizes every map once (geometry fusion and post-processing merge when refinement is on)."""
        if self._results is None:
            if self.config.refinement.enabled:
                self.states, stats = finalize_maps(self.states, self._step_config, self.fusion_config)
                stats = jax.device_get(stats)
                for i, progress in enumerate(self._progress):
                    progress.add_refinement("final", jax.tree.map(lambda x, i=i: x[i], stats))
            likelihood = np.asarray(self._likelihood)
            self._results = [
                progress.result(self._map_state(i), self.map_config, self.fusion_config, self.config, StageTimer(), likelihood)
                for i, progress in enumerate(self._progress)
            ]
        return self._results

    def mapper(self, index: int) -> Mapper:
        """Map `index` as an ordinary `Mapper` (a copy: it continues on its own; finalized if the batch is)."""
        progress = self._progress[index]
        return Mapper.resume(
            self.config,
            self.map_config,
            self._map_state(index),  # fresh buffers: the Mapper donates them to its next step
            {
                **progress.as_dict(),
                "schedule": self._schedules[index].state(),
                "finalized": self._results is not None,
            },
            bounds=self._bounds,
            label_sets=self.label_sets,
            likelihood=np.asarray(self._likelihood),
        )

    def _map_state(self, index: int) -> MapState:
        return _state_at(self.states, index)
