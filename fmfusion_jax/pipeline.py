"""The Python loop: the one place where readers, detectors and the jitted engine meet.

    scene frames ──► HostAdapter.frame ──► engine.step.integrate_frame / fuse_detections ──► refine / fuse_geometry
    detections (files, ONNX front end, simulator) ──► HostAdapter.detections ─┘

Everything here is host-side orchestration: schedules (detection every Nth frame, refinement, geometry
fusion), capacity warnings, progress and timings. The math lives in `fmfusion_jax.engine`.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import logging
import math
import os
import time
from collections.abc import Callable, Iterable, Iterator
from statistics import median
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.engine import extraction, step, support
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.detections import DetectionBatch, pack_detections
from fmfusion_jax.engine.state import MapState, init_map_state
from fmfusion_jax.errors import UserError
from fmfusion_jax.instances import MapInstance, drop_far_specks, postprocess_instances, score_existence
from fmfusion_jax.labels import LabelSets, load_label_sets, load_likelihood
from fmfusion_jax.types import FrameDetections, RGBDFrame

log = logging.getLogger(__name__)


class DetectionSource(Protocol):
    """Gives the detections of a frame, or None when the frame has none (not a detection frame, no file).

    A folder of detection files (`io.detections.DetectionFolder`), models run online (`sources.ModelSource`) or
    any function of a frame. A source whose attribute `reads_ahead` is true (a folder of files: no state, cheap
    to call for a frame that turns out not due) is called by `fmfusion run`'s reader threads for the next frames;
    others (the models, whose prompt window counts the detection frames) only on due frames, in order: in a
    detection thread of their own when their attribute `detects_ahead` is true.
    `sources.open_detection_source` chooses one from a run's arguments.
    """

    def __call__(self, frame: RGBDFrame, /) -> FrameDetections | None: ...


def build_map_config(config: PipelineConfig, bounds_min, bounds_max, height: int, width: int) -> MapConfig:
    """The engine's static sizes for a scene with these world bounds and image size; a map that could never fit in
    this machine's memory is a UserError naming the knobs (before anything is allocated)."""
    map_config = MapConfig.for_bounds(
        bounds_min,
        bounds_max,
        margin=config.tsdf.bounds_margin,
        voxel_size=config.tsdf.voxel_size,
        block_size=config.tsdf.block_size,
        sdf_trunc=config.tsdf.sdf_trunc,
        depth_max=config.dataset.depth_max,
        max_weight=config.tsdf.max_weight,
        block_capacity=config.tsdf.block_capacity,
        max_touched_blocks=config.tsdf.max_touched_blocks,
        image_height=height,
        image_width=width,
        pixel_stride=config.association.pixel_stride,
        instance_capacity=config.instances.capacity,
        instance_slots=config.instances.voxel_slots,
    )
    check_map_fits(map_config, config)
    return map_config


def physical_memory_bytes() -> int | None:
    """This machine's memory, or None where the system does not say."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def check_map_fits(map_config: MapConfig, config: PipelineConfig) -> None:
    """A UserError when the map's block index alone, or the map at its capacities, needs more than this machine's
    memory (a voxel size in the wrong unit would otherwise ask the runtime for petabytes)."""
    memory = physical_memory_bytes()
    if memory is None:
        return
    index = map_config.num_grid_blocks * 4
    if index > memory / 2 or map_config.memory_bytes() > memory:
        raise UserError(
            f"the map would need {map_config.memory_bytes() / 2**30:.3g} GiB (its block index over the scene "
            f"{index / 2**30:.3g} GiB: {map_config.grid_shape} blocks of {config.tsdf.block_size} voxels of "
            f"{config.tsdf.voxel_size} m), more than this machine's {memory / 2**30:.1f} GiB: raise tsdf.voxel_size "
            "(metres: 0.015625 is 1.5 cm) or lower tsdf.block_capacity / instances.capacity"
        )


def build_fusion_config(config: PipelineConfig) -> step.FusionConfig:
    lo, hi = config.detections.depth_percentiles
    return step.FusionConfig(
        association_metric=config.association.metric,
        association_threshold=config.association.threshold,
        min_projected_pixels=float(config.association.min_projected_pixels),
        depth_low=lo,
        depth_high=hi,
        label_mode=config.label_fusion.mode,
        merge_similarity=config.refinement.merge_similarity,
        merge_overlap=config.refinement.merge_overlap,
        remove_missed=config.refinement.remove_missed,
        remove_min_voxels=config.refinement.remove_min_voxels,
        post_merge_iou=config.export.post_merge_iou,
        post_merge_similarity=config.export.post_merge_similarity,
        contrary_vote_weight=config.instances.contrary_vote_weight,
        reunite_min_frames=config.refinement.reunite_min_frames,
        separate_min_frames=config.refinement.separate_min_frames,
        geometry_min_weight=config.refinement.geometry_min_weight,
        floor_up=UP_AXES[config.detections.floor_up_axis],
        floor_class=floor_class_index(load_label_sets()),
        floor_band=config.detections.floor_band,
        floor_max_share=config.detections.floor_max_share,
    )


def floor_class_index(label_sets: LabelSets) -> int:
    """The closed class whose detections keep their floor pixels (-1: the label sets have no floor)."""
    return label_sets.class_names.index("floor") if "floor" in label_sets.class_names else -1


#: `detections.floor_up_axis` as the engine's unit vector (None: the floor filter is off).
UP_AXES: dict[str, tuple[float, float, float] | None] = {
    "+x": (1.0, 0.0, 0.0),
    "-x": (-1.0, 0.0, 0.0),
    "+y": (0.0, 1.0, 0.0),
    "-y": (0.0, -1.0, 0.0),
    "+z": (0.0, 0.0, 1.0),
    "-z": (0.0, 0.0, -1.0),
    "none": None,
}


def frame_inputs(frame: RGBDFrame, map_config: MapConfig) -> step.FrameInputs:
    """A frame as engine arrays; wrong image sizes and non-finite poses are errors naming the frame."""
    expected = (map_config.image_height, map_config.image_width)
    if frame.depth.shape != expected or frame.color.shape[:2] != expected:
        raise UserError(
            f"{frame.name}: depth {frame.depth.shape} / colour {frame.color.shape[:2]} differ from "
            f"the sequence's image size {expected}"
        )
    if not np.all(np.isfinite(frame.T_world_camera)):
        raise UserError(f"{frame.name}: pose is not finite")
    k = frame.intrinsics
    # host arrays (the step's call transfers them): a `jnp.asarray` that converts dispatches a jitted op each
    return step.FrameInputs(
        depth=np.asarray(frame.depth, np.float32),
        color=np.asarray(frame.color, np.uint8),
        T_world_camera=np.asarray(frame.T_world_camera, np.float32),
        intrinsics=np.asarray([k.fx, k.fy, k.cx, k.cy], np.float32),
        frame_index=np.asarray(frame.index, np.int32),
    )


@dataclasses.dataclass(frozen=True)
class HostAdapter:
    """The one joint between the host (readers, detectors, simulator: arrays of any size) and the engine
    (fixed shapes): frames become `FrameInputs`, detections a padded `DetectionBatch` (their label image at the
    fused pixel stride), each checked once against the map's image size with an error that names the frame.
    `MapBuilder` (so `Mapper` and the bench), `MapperBatch` and the Kimera baseline all go through it."""

    map_config: MapConfig
    open_labels: tuple[str, ...]
    max_detections: int
    min_mask_pixels: int

    @classmethod
    def for_map(cls, config: PipelineConfig, map_config: MapConfig, label_sets: LabelSets) -> HostAdapter:
        return cls(map_config, tuple(label_sets.open_labels), config.detections.max_detections, config.detections.min_mask_pixels)

    @property
    def image_shape(self) -> tuple[int, int]:
        return self.map_config.image_height, self.map_config.image_width

    def frame(self, frame: RGBDFrame) -> step.FrameInputs:
        return frame_inputs(frame, self.map_config)

    def detections(self, detections: FrameDetections | None) -> DetectionBatch:
        """The detections padded to `max_detections` rows (None: a batch with no valid row)."""
        if detections is None:
            detections = FrameDetections("-", np.zeros((0, *self.image_shape), bool), [], np.zeros((0, 4), np.float32))
        if detections.image_shape != self.image_shape:
            raise UserError(
                f"{detections.frame_name}: detection masks are {detections.image_shape}, frames are {self.image_shape}"
            )
        return pack_detections(
            detections,
            self.open_labels,
            self.max_detections,
            self.min_mask_pixels,
            stride=self.map_config.pixel_stride,
            as_image=True,
        )


def small_tree_to_host(tree):
    """A tree of small device arrays as numpy arrays: on the CPU each leaf read in place (`np.asarray`, no copy:
    `jax.device_get` took 0.28 ms per frame for the step's eight statistics there, this 0.08); elsewhere the
    leaves joined on the device into one array per dtype and those copied (a GPU profile: each leaf's copy
    cost ~0.09 ms of host time, one per frame's ten statistics)."""
    if jax.default_backend() == "cpu":
        return jax.tree.map(np.asarray, tree)
    return joined_tree_to_host(tree)


def joined_tree_to_host(tree):
    """`tree`'s device arrays as numpy arrays, joined on the device first (one copy per dtype)."""
    leaves, treedef = jax.tree.flatten(tree)
    if not leaves:
        return tree
    dtypes = sorted({leaf.dtype.name for leaf in leaves})
    joined = jax.device_get(_join_by_dtype(leaves, tuple(dtypes)))
    offsets = dict.fromkeys(dtypes, 0)
    host = []
    for leaf in leaves:
        start = offsets[leaf.dtype.name]
        offsets[leaf.dtype.name] = start + leaf.size
        host.append(joined[dtypes.index(leaf.dtype.name)][start : start + leaf.size].reshape(leaf.shape))
    return jax.tree.unflatten(treedef, host)


@functools.partial(jax.jit, static_argnames=("dtypes",))
def _join_by_dtype(leaves: list[jax.Array], dtypes: tuple[str, ...]) -> tuple[jax.Array, ...]:
    """The leaves raveled and joined, one 1-d array per dtype of `dtypes` (in its order; leaves in theirs)."""
    return tuple(jnp.concatenate([leaf.ravel() for leaf in leaves if leaf.dtype.name == name]) for name in dtypes)


@dataclasses.dataclass
class StageTimer:
    """Wall time per named stage (milliseconds per call), with the calls that compiled kept apart.

    Timing a stage waits for its result, so the host cannot work ahead of the device; `enabled=False`
    runs the stages without waiting and records nothing. The first call of a stage compiles; after
    `new_layout()` (a map that grew: the steps recompile for its shapes) the next call of each stage does
    again. `first_ms` keeps each stage's first call, `samples_ms` the calls that did not compile.
    """

    first_ms: dict[str, float] = dataclasses.field(default_factory=dict)
    samples_ms: dict[str, list[float]] = dataclasses.field(default_factory=dict)
    enabled: bool = True
    #: the stages called since the last layout change (their next call does not compile)
    warm: set[str] = dataclasses.field(default_factory=set)
    #: milliseconds of every call recorded so far, compiling ones too (`host_since` leaves out the stages inside)
    recorded_ms: float = 0.0

    def run(self, name: str, fn, *args):
        if not self.enabled:
            return fn(*args)
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        self.record(name, (time.perf_counter() - start) * 1e3, compiled=name not in self.warm)
        return out

    def host_since(self, name: str, start: float, recorded_before: float) -> None:
        """Keeps as a call of stage `name` the host's own time since `start` (`time.perf_counter()`): the wall time
        less the stages recorded since, when `recorded_ms` was `recorded_before` (nothing when not enabled)."""
        if self.enabled:
            inside = self.recorded_ms - recorded_before
            self.record(name, (time.perf_counter() - start) * 1e3 - inside, compiled=name not in self.warm)

    def record(self, name: str, elapsed_ms: float, compiled: bool) -> None:
        """Keeps one call's time: apart when it compiled (the first one in `first_ms`), else as a sample."""
        self.recorded_ms += elapsed_ms
        self.warm.add(name)
        if compiled:
            self.first_ms.setdefault(name, elapsed_ms)
        else:
            self.samples_ms.setdefault(name, []).append(elapsed_ms)

    def new_layout(self) -> None:
        """The map's shapes changed: the next call of every stage compiles (it is not a sample)."""
        self.warm.clear()

    def median_ms(self, name: str) -> float:
        samples = self.samples_ms.get(name) or [self.first_ms.get(name, float("nan"))]
        return float(np.median(samples))

    def summary(self) -> dict[str, dict[str, float]]:
        return {
            name: {"median_ms": self.median_ms(name), "first_call_ms": first, "calls": 1 + len(self.samples_ms.get(name, []))}
            for name, first in self.first_ms.items()
        }


@dataclasses.dataclass
class CapacityMonitor:
    """Warns once per counter when a fixed capacity overflows, naming the figure to raise."""

    reported: set[str] = dataclasses.field(default_factory=set)

    #: Share of the depth samples that may fall outside the bounds before a warning (depth outliers
    #: far beyond the room are normal; a real bounds problem loses far more than this).
    out_of_bounds_tolerance: float = 1e-3

    @staticmethod
    def counts_of(state: MapState) -> dict[str, Any]:
        """The four overflow counters of `state` (device scalars; with a leading batch axis for a batch)."""
        blocks = state.blocks
        return {
            "dropped_blocks": blocks.dropped_blocks,
            "touched_overflow": blocks.touched_overflow,
            "out_of_bounds": blocks.out_of_bounds,
            "table_overflow": state.instances.overflow,
        }

    def check(self, state: MapState, map_config: MapConfig, frames_integrated: int) -> None:
        self.check_counts(self.counts_of(state), map_config, frames_integrated)

    def check_counts(self, counts: dict[str, Any], map_config: MapConfig, frames_integrated: int) -> None:
        """Warns about the counters of `counts_of` (one map's) that overflowed for the first time."""
        stride = map_config.alloc_pixel_stride
        samples = (
            frames_integrated
            * map_config.alloc_depth_samples
            * (-(-map_config.image_height // stride))
            * (-(-map_config.image_width // stride))
        )
        outside = int(counts["out_of_bounds"])
        counters = {
            "dropped_blocks": (
                int(counts["dropped_blocks"]),
                f"the voxel block pool is full ({map_config.block_capacity} blocks): raise "
                "tsdf.block_capacity; parts of the scene are not mapped",
            ),
            "touched_overflow": (
                int(counts["touched_overflow"]),
                f"a frame touched more than {map_config.max_touched_blocks} blocks: raise "
                "tsdf.max_touched_blocks; those blocks were skipped for that frame",
            ),
            "out_of_bounds": (
                outside if outside > self.out_of_bounds_tolerance * samples else 0,
                f"{outside} of {samples} depth samples fell outside the scene bounds estimated "
                "from the poses and depth: raise tsdf.bounds_margin",
            ),
            "table_overflow": (
                int(counts["table_overflow"]),
                f"the instance table is full ({map_config.instance_capacity} instances): raise "
                "instances.capacity; new detections were dropped",
            ),
        }
        for name, (value, message) in counters.items():
            if value > 0 and name not in self.reported:
                self.reported.add(name)
                log.warning("capacity: %s (count so far: %d)", message, value)


class MapSizes(NamedTuple):
    """The map's sizes after the frame at `position` (0-based, in the frames integrated): upper bounds for the frames
    after it (a merge or a removal only lowers `instances`)."""

    position: int
    blocks: int  # allocated pool blocks
    instances: int  # live instance rows


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

    def floor(self) -> tuple[tuple[float, float, float], float] | None:
        """`(up, height)` of the floor the fusion found (`engine.support`), or None (floor filter off, or no
        floor seen)."""
        up = self.fusion_config.floor_up
        if up is None:
            return None
        floor = support.floor_height(jnp.asarray(self.state.blocks.up_heights))
        return (up, float(floor.height)) if bool(floor.found) else None

    def progress(self) -> dict:
        """How far fusion got (what a saved map keeps so that `MapBuilder.restore_progress` continues it)."""
        return {
            "frames_integrated": self.frames_integrated,
            "detection_frames": self.detection_frames,
            "counters": dict(self.counters),
        }


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
        """`state`: start from this map (e.g. `map_file.load_map`) instead of an empty one; it must have
        been made with the same `map_config`. Its buffers are donated to the first step.

        Hooks: `timer` times each step (default: a `StageTimer`); `fuse_detections` is the detection-frame
        step, with the signature of `step.fuse_detections` (`fmfusion_jax.bench` passes its stage-by-stage
        twin). `one_call_per_frame`: see `one_call_per_frame` (None: off the CPU)."""
        self.config = config
        self.map_config = map_config
        self.fusion_config = build_fusion_config(config)
        self.label_sets = label_sets or load_label_sets()
        if likelihood is None:
            likelihood = load_likelihood(config.label_fusion.likelihood)
        self.likelihood = jnp.asarray(likelihood, jnp.float32)
        self.state = init_map_state(map_config) if state is None else state
        self.timer = StageTimer() if timer is None else timer
        self.fuse_detections = fuse_detections
        #: Whether a detection frame the merge is due after is one call (`step.fuse_and_refine`) where the stages are
        #: not timed and the fusion step is not replaced: the same map. Off the CPU by default: there each call costs
        #: the stepping thread ~1 ms (a CUDA graph updated and launched); on a CPU two calls cost no more and compile
        #: sooner (the merge step alone is compiled for `finalize` anyway).
        self.one_call_per_frame = jax.default_backend() != "cpu" if one_call_per_frame is None else one_call_per_frame
        self.monitor = CapacityMonitor()
        self.frames_integrated = 0
        self.detection_frames = 0
        self._counters = {"created": 0, "matched": 0, "merged": 0, "removed": 0, "detections": 0}
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
        unread = None  # this frame's statistics (a detection frame's)
        if batch is None:
            self.state = self.timer.run("tsdf", step.integrate_frame, self.state, inputs, self.step_config)
        else:
            fusion = step.fusion_on_device(self.fusion_config)
            merge_due, geometry_due = self.count_detection_frame()
            statistics: Any
            if merge_due and self._one_call_per_frame:
                self.state, statistics = step.fuse_and_refine(
                    self.state, inputs, batch, self.likelihood, self.step_config, fusion
                )
            else:
                self.state, stats = self.timer.run(
                    "fusion", self.fuse_detections, self.state, inputs, batch, self.likelihood, self.step_config, fusion
                )
                refine_stats = None
                if merge_due:
                    self.state, refine_stats = self.timer.run(
                        "refine", step.refine, self.state, self.step_config, self.fusion_config
                    )
                statistics = (stats, refine_stats)
            if geometry_due:
                self.state = self.timer.run("geometry_fusion", step.fuse_geometry, self.state, self.step_config, fusion)
            unread = (frame.name, statistics, self.frames_integrated)
        # the last detection frame's statistics, read while the device runs this frame's steps (its dispatch first)
        pending, self._pending = self._pending, unread
        self._read_statistics(pending)
        self.frames_integrated += 1
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
        self.add_frame_counts(stats)
        log.info(
            "%s: %d detections, %d matched, %d new instances, %d in view",
            name,
            int(stats.detections),
            int(stats.matched),
            int(stats.created),
            int(stats.in_view),
        )
        if refine_stats is not None:
            self._count_refinement(name, refine_stats)

    @property
    def counters(self) -> dict[str, int]:
        """Instances created, matched, merged, removed and detections fused so far (reads pending statistics)."""
        self.flush()
        return self._counters

    @property
    def _one_call_per_frame(self) -> bool:
        return self.one_call_per_frame and not self.timer.enabled and self.fuse_detections is step.fuse_detections

    @property
    def adapter(self) -> HostAdapter:
        """The host-to-engine packing for the current `map_config` (a growing map replaces it)."""
        return HostAdapter.for_map(self.config, self.map_config, self.label_sets)

    def record_detection_frame(self, stats: step.FrameStats) -> tuple[bool, bool]:
        """Counts one fused detection frame (`stats` on the host); returns whether the online merge and the
        geometry fusion are due after it (their schedules count detection frames)."""
        self.add_frame_counts(stats)
        return self.count_detection_frame()

    def add_frame_counts(self, stats: step.FrameStats) -> None:
        """Adds a detection frame's counts (`stats` on the host) to the counters."""
        for name in ("created", "matched", "detections"):
            self._counters[name] += int(getattr(stats, name))

    def count_detection_frame(self) -> tuple[bool, bool]:
        """Counts one fused detection frame; returns whether the online merge and the geometry fusion are due
        after it (their schedules count detection frames, so no device value is needed)."""
        self.detection_frames += 1
        refinement = self.config.refinement
        return (
            refinement.enabled and self.detection_frames % refinement.merge_every == 0,
            refinement.enabled and self.detection_frames % refinement.geometry_fusion_every == 0,
        )

    def _count_refinement(self, where: str, stats: step.RefineStats) -> None:
        removed, merged = int(stats.removed), int(stats.merged)
        self._counters["removed"] += removed
        self._counters["merged"] += merged
        if removed or merged:
            log.info("%s: refinement removed %d and merged %d instances", where, removed, merged)

    def snapshot(self, state: MapState) -> FusionResult:
        """`state` (this builder's, or a copy of it) with the builder's configs, timings and counts."""
        self.flush()
        return FusionResult(
            state,
            self.map_config,
            self.fusion_config,
            self.config,
            self.timer,
            self.frames_integrated,
            self.detection_frames,
            dict(self._counters),
        )

    def restore_progress(self, progress: dict) -> None:
        """Continues the counts of a saved map (`FusionResult.progress`): frames, detection frames, counters."""
        self.frames_integrated = int(progress.get("frames_integrated", 0))
        self.detection_frames = int(progress.get("detection_frames", 0))
        self._counters.update({k: int(v) for k, v in progress.get("counters", {}).items()})

    def result(self) -> FusionResult:
        """Finalizes (geometry fusion and post-merge when refinement is on) and returns the map."""
        self.flush()
        self.monitor.check(self.state, self.map_config, self.frames_integrated)
        if self.config.refinement.enabled:
            self.state, stats = self.timer.run("finalize", step.finalize, self.state, self.step_config, self.fusion_config)
            self._count_refinement("final", stats)
        return self.snapshot(self.state)


def camera_motion(T_world_a: np.ndarray, T_world_b: np.ndarray) -> tuple[float, float]:
    """`(metres, degrees)`: translation and rotation angle of camera b relative to camera a (4x4 rigid poses).

    Without forming `inv(T_world_a) @ T_world_b` (the schedule asks this three times a frame, in the thread that
    calls the steps): its translation is `R_a^T (t_b - t_a)`, as long as `t_b - t_a`, and the trace of its rotation
    `R_a^T R_b` is the sum of `R_a * R_b`."""
    a, b = np.asarray(T_world_a, np.float64), np.asarray(T_world_b, np.float64)
    cos = min(1.0, max(-1.0, (float(np.sum(a[:3, :3] * b[:3, :3])) - 1.0) / 2.0))
    return math.dist(a[:3, 3], b[:3, 3]), math.degrees(math.acos(cos))


def scheduled_positions(poses: np.ndarray, config: PipelineConfig) -> list[int]:
    """Positions of the frames (of `poses`, `(N, 4, 4)` T_world_camera in reading order) whose detections the
    detection schedule fuses when every frame has detections: the frames worth running the models on."""
    schedule, positions = DetectionSchedule(config), []
    for position, pose in enumerate(np.asarray(poses, np.float64)):
        if schedule.due(position, pose):
            schedule.fused(pose)
            positions.append(position)
        schedule.advance(pose)
    return positions


class DetectionSchedule:
    """Which frames have their detections fused.

    `detections.schedule = motion` (default): a frame is due when the camera has moved at least
    `min_translation` metres or turned `min_rotation` degrees since the last frame whose detections were
    fused (the first frame is always due). The rule follows the camera, not the frame rate: on a 30 Hz
    ScanNet sequence (typically 0.4 cm and 0.35 degrees per frame) it fuses about every 8th-15th frame, near
    the paper's every 10th. A sequence already subsampled in time (its median step between consecutive
    frames is at least `sparse_motion` of a detection step) has every frame fused, as a fixed stride of 1
    would, pauses of the camera included: its frames are keyframes already. A due frame without detections
    (no detection file) leaves the schedule due, so the next frame with detections is taken.
    `schedule = every`: every `every`-th frame read (the paper's rule).

    Call `due` (pure) before a frame, `fused` when its detections were fused and `advance` once per frame
    read, in that order.
    """

    #: consecutive-frame steps the sequence's rate is judged on (a pause shorter than half of it does not
    #: change the judgement)
    RATE_WINDOW = 100

    def __init__(self, config: PipelineConfig):
        self.detections = config.detections
        self._last_pose: np.ndarray | None = None  # T_world_camera of the last detection frame fused
        self._previous_pose: np.ndarray | None = None  # T_world_camera of the last frame read
        self._steps: collections.deque[float] = collections.deque(maxlen=self.RATE_WINDOW)

    def due(self, position: int, T_world_camera: np.ndarray) -> bool:
        """Whether the frame read at `position` (0, 1, ...) with this pose should have detections fused."""
        det = self.detections
        if det.schedule == "every":
            return position % det.every == 0
        if self._last_pose is None:
            return True
        if self.sparse_sequence(T_world_camera):
            return True
        return self._detection_steps(self._last_pose, T_world_camera) >= 1.0

    def sparse_sequence(self, T_world_camera: np.ndarray | None = None) -> bool:
        """Whether the sequence read so far (and a next frame at `T_world_camera`) is subsampled in time."""
        if self.detections.sparse_motion <= 0:
            return False
        steps = list(self._steps)
        if T_world_camera is not None and self._previous_pose is not None:
            steps.append(self._detection_steps(self._previous_pose, T_world_camera))
        return bool(steps) and median(steps) >= self.detections.sparse_motion

    def fused(self, T_world_camera: np.ndarray) -> None:
        """Records that a frame's detections were fused at this pose."""
        self._last_pose = np.asarray(T_world_camera, np.float64)

    def advance(self, T_world_camera: np.ndarray) -> None:
        """Records a frame read (detections fused or not) at this pose."""
        pose = np.asarray(T_world_camera, np.float64)
        if self._previous_pose is not None:
            self._steps.append(self._detection_steps(self._previous_pose, pose))
        self._previous_pose = pose

    def _detection_steps(self, T_world_a: np.ndarray, T_world_b: np.ndarray) -> float:
        """Camera motion from a to b in detection steps: 1.0 = `min_translation` or `min_rotation`."""
        metres, degrees = camera_motion(T_world_a, T_world_b)
        det = self.detections
        return max(
            metres / det.min_translation if det.min_translation > 0 else np.inf,
            degrees / det.min_rotation if det.min_rotation > 0 else np.inf,
        )

    def state(self) -> dict[str, Any]:
        """The schedule's memory as plain JSON values (for saved maps)."""
        pose = lambda p: None if p is None else np.asarray(p).tolist()  # noqa: E731
        return {
            "last_detection_pose": pose(self._last_pose),
            "previous_pose": pose(self._previous_pose),
            "steps": list(self._steps),
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Continues from `state()` (a map saved before the schedule kept its rate has the detection pose only)."""
        pose = lambda p: None if p is None else np.asarray(p, np.float64)  # noqa: E731
        self._last_pose = pose(state.get("last_detection_pose"))
        self._previous_pose = pose(state.get("previous_pose"))
        self._steps = collections.deque((float(s) for s in state.get("steps", [])), maxlen=self.RATE_WINDOW)


def scheduled_detections(
    frames: Iterable[RGBDFrame], detection_source: DetectionSource, config: PipelineConfig
) -> Iterator[tuple[RGBDFrame, "FrameDetections | None"]]:
    """`(frame, detections or None)` for every frame, the detections read only on due frames
    (`DetectionSchedule`)."""
    schedule = DetectionSchedule(config)
    for position, frame in enumerate(frames):
        detections = detection_source(frame) if schedule.due(position, frame.T_world_camera) else None
        if detections is not None:
            schedule.fused(frame.T_world_camera)
        schedule.advance(frame.T_world_camera)
        yield frame, detections


def fuse_sequence(
    frames: Iterable[RGBDFrame],
    detection_source: DetectionSource,
    builder: MapBuilder,
    progress: Callable[[int], None] | None = None,
) -> FusionResult:
    """Runs the loop over `frames` and returns the finalized map."""
    for frame, detections in scheduled_detections(frames, detection_source, builder.config):
        builder.add_frame(frame, detections)
        if progress:
            progress(1)
    return builder.result()


def extract_map_instances(
    result: FusionResult, label_sets: LabelSets | None = None, postprocess: bool = True
) -> list[MapInstance]:
    """The map's instances as host-side objects, post-processed as the reference does before export."""
    label_sets = label_sets or load_label_sets()
    state = jax.device_get(result.state)
    distribution = np.asarray(step.class_distribution(result.state, result.fusion_config))
    export = result.config.export
    points = extraction.extract_instance_points(
        state, result.map_config, min_weight=export.min_weight, min_share=export.min_slot_share
    )
    table = state.instances
    voxel_size = result.map_config.voxel_size
    instances = [
        MapInstance(
            instance_id=int(k),
            distribution=distribution[k],
            points=drop_far_specks(np.asarray(points[int(k)], np.float32), voxel_size, export.speck_distance),
            observations=int(table.observations[k]),
            open_label_histogram=np.asarray(table.open_label_histogram[k]),
            missed=int(table.missed[k]),
        )
        for k in np.flatnonzero(np.asarray(table.valid))
        if k in points
    ]
    instances = score_existence(instances, label_sets, export, voxel_size)
    if postprocess:
        instances = postprocess_instances(instances, label_sets, result.config.export)
    return instances
