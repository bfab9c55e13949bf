"""`MapBuilder`: one map's fusion, frame by frame (the engine's `fuse_frame` on the merge and geometry-fusion
cadences, statistics read a frame late, counters and capacity warnings), and its `FusionResult`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

from fmfusion_jax import host_memory
from fmfusion_jax.config import PipelineConfig, RefinementConfig
from fmfusion_jax.engine import step, support
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.detections import DetectionBatch
from fmfusion_jax.engine.frame import fuse_frame
from fmfusion_jax.engine.state import MapState, init_map_state
from fmfusion_jax.labels import LabelSets, load_label_sets
from fmfusion_jax.mapping.capacity import CapacityMonitor, MapSizes
from fmfusion_jax.mapping.engine_configs import build_fusion_config, fusion_likelihood
from fmfusion_jax.mapping.inputs import HostAdapter
from fmfusion_jax.mapping.telemetry import StageTimer, small_tree_to_host
from fmfusion_jax.types import FrameDetections, RGBDFrame

log = logging.getLogger(__name__)


@dataclasses.dataclass
class FusionResult:
    """A fused map with what is needed to interpret and export it."""

    state: MapState
    map_config: MapConfig
    fusion_config: step.FusionConfig
    config: PipelineConfig
    timings: StageTimer
    frames_integrated: int
    detection_frames: int
    counters: dict[str, int]
    #: `(O, C)` the likelihood the labels were fused with (the export reads the labels' votes by it); None: the
    #: config's (`engine_configs.fusion_likelihood`).
    likelihood: np.ndarray | None = None

    def floor(self) -> tuple[tuple[float, float, float], float] | None:
        """`(up, height)` of the floor the fusion found (`engine.support`), or None (floor filter off, or no
        floor seen)."""
        up = self.fusion_config.floor_up
        if up is None:
            return None
        floor = support.floor_height(self.state.blocks.up_heights)
        return (up, float(floor.height)) if bool(floor.found) else None

    def progress(self) -> dict:
        """How far fusion got (what a saved map keeps so that `FusionProgress.restore` continues it)."""
        return FusionProgress(self.config.refinement, self.frames_integrated, self.detection_frames, self.counters).as_dict()


@dataclasses.dataclass
class FusionProgress:
    """How far one map's fusion got, and the cadences counted on it: frames, detection frames, counters; the
    online merge and the geometry fusion are due every `merge_every` / `geometry_fusion_every` detection frames
    (counted on the host: no device value is waited for)."""

    refinement: RefinementConfig
    frames_integrated: int = 0
    detection_frames: int = 0
    counters: dict[str, int] = dataclasses.field(
        default_factory=lambda: {"created": 0, "matched": 0, "merged": 0, "removed": 0, "detections": 0}
    )

    def count_detection_frame(self) -> tuple[bool, bool]:
        """Counts one fused detection frame; returns whether the online merge and the geometry fusion are due
        after it."""
        self.detection_frames += 1
        refinement = self.refinement
        return (
            refinement.enabled and self.detection_frames % refinement.merge_every == 0,
            refinement.enabled and self.detection_frames % refinement.geometry_fusion_every == 0,
        )

    def add_frame_counts(self, stats: step.FrameStats) -> None:
        """Adds a detection frame's counts (`stats` on the host) to the counters."""
        for name in ("created", "matched", "detections"):
            self.counters[name] += int(getattr(stats, name))

    def add_refinement(self, where: str, stats: step.RefineStats) -> None:
        """Adds a merge step's removals and merges (`stats` on the host) to the counters, and logs them."""
        removed, merged = int(stats.removed), int(stats.merged)
        self.counters["removed"] += removed
        self.counters["merged"] += merged
        if removed or merged:
            log.info("%s: refinement removed %d and merged %d instances", where, removed, merged)

    def as_dict(self) -> dict:
        """The counts as a saved map keeps them (`restore` reads them back)."""
        return {
            "frames_integrated": self.frames_integrated,
            "detection_frames": self.detection_frames,
            "counters": dict(self.counters),
        }

    def restore(self, progress: dict) -> None:
        """Continues the counts of a saved map (`FusionResult.progress`): frames, detection frames, counters."""
        self.frames_integrated = int(progress.get("frames_integrated", 0))
        self.detection_frames = int(progress.get("detection_frames", 0))
        self.counters.update({k: int(v) for k, v in progress.get("counters", {}).items()})

    def result(
        self,
        state: MapState,
        map_config: MapConfig,
        fusion_config: step.FusionConfig,
        config: PipelineConfig,
        timer: StageTimer,
        likelihood: np.ndarray | None = None,
    ) -> FusionResult:
        """`state` as a `FusionResult` with these counts (`likelihood`: the `(O, C)` matrix fused with)."""
        return FusionResult(
            state,
            map_config,
            fusion_config,
            config,
            timer,
            self.frames_integrated,
            self.detection_frames,
            dict(self.counters),
            likelihood,
        )


class MapBuilder:
    """Incremental fusion of one sequence: `add_frame` per frame, then `result()`.

    Holds the schedules of refinement and geometry fusion (counted in detection frames) and
    the capacity warnings; the state itself is an immutable pytree replaced on every step.
    """

    def __init__(
        self,
        config: PipelineConfig,
        map_config: MapConfig,
        label_sets: LabelSets | None = None,
        likelihood: np.ndarray | jax.Array | None = None,
        state: MapState | None = None,
        *,
        timer: StageTimer | None = None,
        fuse_detections: Callable[..., Any] = step.fuse_detections,
        one_call_per_frame: bool | None = None,
    ):
        """`state`: start from this map (e.g. `map_file.read_map_file(path).state`) instead of an empty one; it must have
        been made with the same `map_config`. Its buffers are donated to the first step.

        Hooks: `timer` times each step (default: a `StageTimer`); `fuse_detections` is the detection-frame
        step, with the signature of `step.fuse_detections` (`fmfusion_jax.apps.bench` passes its stage-by-stage
        twin). `one_call_per_frame`: see `one_call_per_frame` (None: off the CPU)."""
        self.config = config
        self.map_config = map_config
        self.label_sets = label_sets or load_label_sets()
        self.fusion_config = build_fusion_config(config, self.label_sets)
        if likelihood is None:
            likelihood = fusion_likelihood(config)
        self.likelihood = jax.device_put(np.asarray(likelihood, np.float32))  # converted on the host: no cast compiled
        self.state = init_map_state(map_config) if state is None else state
        host_memory.release_unallocated_rows(self.state)  # the pool's empty rows take no memory until filled
        self.timer = StageTimer() if timer is None else timer
        self.fuse_detections = fuse_detections
        #: Whether a detection frame the merge is due after is one call (`step.fuse_and_refine`) where the stages are
        #: not timed and the fusion step is not replaced: the same map. Off the CPU by default: there each call costs
        #: the stepping thread ~1 ms (a CUDA graph updated and launched); on a CPU two calls cost no more and compile
        #: sooner (the merge step alone is compiled for `finalize` anyway).
        self.one_call_per_frame = jax.default_backend() != "cpu" if one_call_per_frame is None else one_call_per_frame
        self.monitor = CapacityMonitor()
        #: frames, detection frames and counters, and the merge and geometry-fusion cadences counted on them
        self.progress = FusionProgress(config.refinement)
        self._pending: tuple[str, Any, int] | None = None  # the last detection frame's unread statistics
        #: the map's sizes after a recent frame, from its statistics (None: none read since the map was built)
        self.sizes_after: MapSizes | None = None

    #: Frames between two reads of the capacity counters (each read waits for the device).
    CAPACITY_CHECK_EVERY = 16

    @property
    def step_config(self) -> MapConfig:
        """The config the engine steps are called with: `map_config.compiled_layout()`, so that maps whose block
        index lies elsewhere share the compiled steps (the state carries the origin)."""
        return self.map_config.compiled_layout()

    def add_frame(
        self,
        frame: RGBDFrame,
        detections: FrameDetections | None,
        batch: DetectionBatch | None = None,
        inputs: step.FrameInputs | None = None,
    ) -> None:
        """Integrates a frame; fuses its detections when given (the caller applies the detection schedule,
        e.g. `scheduled_detections`). `batch`, `inputs`: the detections packed and the frame's arrays, made ahead
        (`Mapper.prepare`) for this map's pixel stride and image size, else they are made here.

        The steps are dispatched without waiting for the device: the frame's statistics (counters, log line)
        are read at the next call, after it dispatched its own steps (or at `flush`), so the caller may read and
        decode the next frame while the device works, and the device has the next steps queued when it finishes;
        the merge and geometry-fusion schedules count detection frames on the host. Off the CPU, unless the stages are
        timed, a detection frame the merge is due after is one call (`step.fuse_and_refine`).
        """
        adapter = self.adapter
        start, recorded_before = time.perf_counter(), self.timer.recorded_ms
        # packed while the device may still run the previous step; unless prepared (and sent) by a reader thread, the
        # step is given host arrays (its C++ dispatch copies them in: a jax.device_put here cost 0.5 ms more per frame
        # in Python on the CPU)
        if inputs is None or inputs.depth.shape != adapter.image_shape:
            inputs = adapter.frame(frame)  # checks the frame (a wrong image size is an error naming it)
        if detections is None:
            batch = None
        elif batch is None:
            batch = adapter.detections(detections)
        merge_due, geometry_due = self.progress.count_detection_frame() if batch is not None else (False, False)
        self.state, statistics = fuse_frame(
            self.state,
            inputs,
            batch,
            self.likelihood,
            self.step_config,
            self.fusion_config,
            merge=merge_due,
            geometry=geometry_due,
            run=self.timer.run,
            fuse=self.fuse_detections,
            one_call=self._one_call_per_frame,
        )
        unread = None if statistics is None else (frame.name, statistics, self.frames_integrated)
        # the last detection frame's statistics, read while the device runs this frame's steps (its dispatch first)
        pending, self._pending = self._pending, unread
        self._read_statistics(pending)
        self.progress.frames_integrated += 1
        if self.frames_integrated % self.CAPACITY_CHECK_EVERY == 0:
            self.monitor.check(self.state, self.map_config, self.frames_integrated)
        self.timer.host_since("host", start, recorded_before)  # all of the above but the steps

    def flush(self) -> None:
        """Reads the statistics of the last detection frame (waits for the device): counters and log line."""
        pending, self._pending = self._pending, None
        self._read_statistics(pending)

    def _read_statistics(self, pending: tuple[str, Any, int] | None) -> None:
        """Counts and logs a detection frame's `(name, statistics, position)` (device values: waits for them), and
        keeps the map's sizes after it (`sizes_after`). `statistics`: `(FrameStats, RefineStats | None)`, or
        `fuse_and_refine`'s packed vector."""
        if pending is None:
            return
        name, statistics, position = pending
        if isinstance(statistics, jax.Array):
            stats, refine_stats = step.unpack_statistics(np.asarray(statistics))
        else:
            stats, refine_stats = small_tree_to_host(statistics)
        if self.sizes_after is None or position > self.sizes_after.position:  # not older than a direct read
            self.sizes_after = MapSizes(position, int(stats.blocks), int(stats.instances))
        self.progress.add_frame_counts(stats)
        log.info(
            "%s: %d detections, %d matched, %d new instances, %d in view",
            name,
            int(stats.detections),
            int(stats.matched),
            int(stats.created),
            int(stats.in_view),
        )
        if refine_stats is not None:
            self.progress.add_refinement(name, refine_stats)

    @property
    def counters(self) -> dict[str, int]:
        """Instances created, matched, merged, removed and detections fused so far (reads pending statistics)."""
        self.flush()
        return self.progress.counters

    @property
    def frames_integrated(self) -> int:
        return self.progress.frames_integrated

    @property
    def detection_frames(self) -> int:
        return self.progress.detection_frames

    @property
    def _one_call_per_frame(self) -> bool:
        return self.one_call_per_frame and not self.timer.enabled and self.fuse_detections is step.fuse_detections

    @property
    def adapter(self) -> HostAdapter:
        """The host-to-engine packing for the current `map_config` (a growing map replaces it)."""
        return HostAdapter.for_map(self.config, self.map_config, self.label_sets)

    def snapshot(self, state: MapState) -> FusionResult:
        """`state` (this builder's, or a copy of it) with the builder's configs, timings and counts."""
        self.flush()
        return self.progress.result(
            state, self.map_config, self.fusion_config, self.config, self.timer, np.asarray(self.likelihood)
        )

    def result(self) -> FusionResult:
        """Finalizes (geometry fusion and post-merge when refinement is on) and returns the map."""
        self.flush()
        self.monitor.check(self.state, self.map_config, self.frames_integrated)
        if self.config.refinement.enabled:
            self.state, stats = self.timer.run("finalize", step.finalize, self.state, self.step_config, self.fusion_config)
            self.progress.add_refinement("final", stats)
        return self.snapshot(self.state)
