"""`Mapper`: one map object with a few verbs, for notebooks and robot loops.

    mapper = Mapper("scannet")                       # a packaged config, a YAML path, a dict or a PipelineConfig
    for frame, detections in ...:                    # frames: RGBDFrame, or arrays (depth, colour, pose, K)
        mapper.integrate(frame, detections)          # applies the detection schedule itself
    mapper.instances()                               # a snapshot: the map goes on unchanged
    mapper.finalize()                                # geometry fusion + post-merge, once
    mapper.extract_mesh().export("mesh.ply"); mapper.save("map.npz"); Mapper.load("map.npz")

Without `bounds`, the map grows as the camera explores: the first frame sizes a room around what it sees
(`capacity.growing_map_config`: an index reaching two depth ranges beyond it, a pool of 8 times its blocks), and the
block index, the pool and the instance table are enlarged (the pool four times while far below its ceiling, then by
doubling; the index a side by its whole extent: a recompile each, logged) before a frame that would not fit. The
voxel lattice is fixed (origins on whole blocks), so a grown map equals one allocated at its final size. With
`bounds` (as `fmfusion run` passes the scene's), the index is fixed; the pool starts at `expected_blocks` (the
config's capacity when not given) and grows the same way, and so does the instance table (from
`INITIAL_INSTANCE_ROWS`: its pairwise merge tests cost K^2, so a table sized to the map's instances rather than to
the ceiling makes the merge several times faster, with the same map). The
config's capacities are the ceiling of growth.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np
from numpy.typing import ArrayLike

from fmfusion_jax import host_memory
from fmfusion_jax.compile_cache import use_compile_cache
from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.engine import extraction, growth, step
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import MapState, copy_map_state
from fmfusion_jax.errors import UserError
from fmfusion_jax.instances import MapInstance
from fmfusion_jax.labels import LabelSets, load_label_sets
from fmfusion_jax.mapping.builder import FusionResult, MapBuilder
from fmfusion_jax.mapping.capacity import (
    INDEX_PAD_BLOCKS,
    MapSizes,
    _extent_parameters,
    _next_power_of_two,
    bounded_map_config,
    frame_block_extent,
    growing_map_config,
    initial_instance_rows,
    scene_extent,
)
from fmfusion_jax.mapping.engine_configs import build_map_config
from fmfusion_jax.mapping.export import extract_map_instances
from fmfusion_jax.mapping.inputs import (
    DetectionSource,
    HostAdapter,
    PreparedFrame,
    as_config,
    as_frame,
    check_detections,
    checked_pose,
)
from fmfusion_jax.mapping.map_file import read_map_file, write_map_file
from fmfusion_jax.mapping.schedule import DetectionSchedule
from fmfusion_jax.mapping.telemetry import StageTimer
from fmfusion_jax.types import CameraIntrinsics, FrameDetections, RGBDFrame

log = logging.getLogger(__name__)


class Mapper:
    """An instance-aware semantic map, fused frame by frame.

    Args:
      config: a packaged config name (`"scannet"`, `"scannet-subsampled"`, `"scenenn"`, `"demo"`), a YAML path,
        a dict of overrides, or a `PipelineConfig` (None: scannet).
      intrinsics: the camera, used for frames given as arrays without their own (`CameraIntrinsics`, 3x3 K
        or `(fx, fy, cx, cy)`).
      bounds: `(min xyz, max xyz)` world metres the map must cover: fixes the block index. None: the index
        grows as the camera explores.
      expected_blocks: voxel blocks the map is expected to use (e.g. `sample_block_count` over a sample of
        the frames): the pool starts at the power of two above 1.25x this and doubles when a frame might not
        fit. None: the config's `tsdf.block_capacity` up front with `bounds`, a small pool without.
      label_sets, likelihood: the label sets and the `(O, C)` likelihood (default: the config's).
      time_stages: time every engine step (waits for the device after each, so reading the next frame no
        longer overlaps the device's work); the medians are in `finalize().timings`.
      timer, fuse_detections: hooks of the `MapBuilder` inside (`fmfusion_jax.apps.bench` passes its per-frame
        timer and the stage-by-stage twin of the detection step); `timer` overrides `time_stages`.
    """

    def __init__(
        self,
        config: "str | Path | Mapping[str, Any] | PipelineConfig | None" = None,
        intrinsics: "CameraIntrinsics | np.ndarray | Sequence | None" = None,
        *,
        bounds: "tuple[ArrayLike, ArrayLike] | None" = None,
        expected_blocks: int | None = None,
        label_sets: LabelSets | None = None,
        likelihood: np.ndarray | None = None,
        time_stages: bool = False,
        timer: StageTimer | None = None,
        fuse_detections: Callable[..., Any] = step.fuse_detections,
    ):
        self.config = as_config(config)
        use_compile_cache()
        self.time_stages = time_stages
        self._timer = timer
        self._fuse_detections = fuse_detections
        self.label_sets = label_sets or load_label_sets()
        self._known_labels = frozenset(self.label_sets.open_labels)
        #: detections' labels that are not open-set labels, with how often they came (their scores are not fused)
        self.unknown_labels: dict[str, int] = {}
        self._likelihood = likelihood
        self._intrinsics = intrinsics
        self._bounds = None if bounds is None else (np.asarray(bounds[0], float), np.asarray(bounds[1], float))
        self._builder: MapBuilder | None = None
        self._schedule = DetectionSchedule(self.config)
        self._result: FusionResult | None = None
        self._expected_blocks = expected_blocks
        self._layouts: dict[tuple[int, int], MapConfig] = {}  # `_layout` by image size
        # per frame since the last known sizes (`MapBuilder.sizes_after`): (position, bound of the blocks it adds,
        # bound of the rows it adds), so that the growth check reads the device only near a capacity
        self._recent: list[tuple[int, int, int]] = []
        #: how often the map's layout grew (each one recompiles the steps)
        self.growths = 0

    # ------------------------------------------------------------------------------------------------
    # Fusing.

    def integrate(
        self,
        frame: RGBDFrame | PreparedFrame | None = None,
        detections: FrameDetections | DetectionSource | None = None,
        *,
        depth=None,
        color=None,
        T_world_camera=None,
        intrinsics=None,
        name: str | None = None,
    ) -> bool:
        """Integrates one frame into the global TSDF and, when the detection schedule says the frame is due,
        fuses its `detections`. Returns whether the detections were fused.

        `frame` is an `RGBDFrame` (or a `PreparedFrame` of one and its detections, see `prepare`), or give the
        arrays: `depth` `(H, W)` float metres, `color` `(H, W, 3)` uint8 RGB (optional), `T_world_camera`
        `(4, 4)` and `intrinsics` (default: the Mapper's). Detections of a frame that is not due are ignored
        (ask `detection_due` first to skip running the detectors). `detections` may also be a detection source
        (`mapping.DetectionSource`: a `DetectionFolder`, `sources.ModelSource`, any function of the frame), which
        is called on due frames only.
        """
        if self._result is not None:
            raise UserError("this map is finalized: integrate frames before finalize(), or start a new Mapper")
        timer = self._builder.timer if self._builder is not None else self._timer
        start, recorded_before = time.perf_counter(), (timer.recorded_ms if timer is not None else 0.0)
        prepared, batch, inputs = None, None, None
        if isinstance(frame, PreparedFrame):  # checked by `prepare`
            prepared, inputs = frame, frame.inputs
            frame = prepared.frame
            if prepared.detections is not None:
                if detections is not None:
                    raise UserError(f"{frame.name}: detections given twice (to prepare and to integrate)")
                detections, batch = prepared.detections, prepared.batch
        else:
            frame = as_frame(
                frame,
                depth=depth,
                color=color,
                T_world_camera=T_world_camera,
                intrinsics=self._intrinsics if intrinsics is None else intrinsics,
                index=self.frames_integrated,
                name=name,
            )
        if detections is not None and not isinstance(detections, FrameDetections) and not callable(detections):
            raise UserError(
                f"{frame.name}: detections must be FrameDetections or a detection source (a function of the "
                f"frame), got {type(detections).__name__}"
            )
        fused: FrameDetections | None = None
        if detections is not None and self.detection_due(frame.T_world_camera):
            # a source is called on due frames only
            fused = detections if isinstance(detections, FrameDetections) else detections(frame)
        due = fused is not None
        if fused is not None and batch is None:  # detections given to `prepare` were checked there (reader thread)
            self._accept(frame.name, fused)
        self._fit_map_to(frame, due, prepared)
        assert self._builder is not None
        self._builder.add_frame(frame, fused, batch, inputs)
        if due:
            self._schedule.fused(frame.T_world_camera)
        self._schedule.advance(frame.T_world_camera)
        # the Mapper's own share (checks, schedule, growth check): with the builder's stages, the whole call
        self._builder.timer.host_since("mapper", start, recorded_before)
        return due

    def prepare(self, frame: RGBDFrame, detections: FrameDetections | None = None) -> PreparedFrame:
        """`frame` and its `detections` with the host work that needs only the config done (the frame's block
        extent for the growth check, the detections packed, they and the frame's arrays sent to the device), for
        `integrate`, which still applies the detection schedule. Reads nothing of the map, so another thread may
        call it while frames are integrated. A non-finite or non-rigid pose is a UserError naming the frame."""
        if not isinstance(frame, RGBDFrame):
            raise UserError(
                f"prepare: expected an RGBDFrame (fmfusion_jax.mapping.as_frame makes one of arrays), got {type(frame).__name__}"
            )
        checked_pose(frame.T_world_camera, frame.name)
        layout = self._layout(*frame.depth.shape)
        adapter = HostAdapter.for_map(self.config, layout, self.label_sets)
        if detections is not None:
            self._accept(frame.name, detections)
        batch = None if detections is None else adapter.detections(detections)
        # sent to the device here, off the thread that calls the steps (on a GPU that thread bounds the frame)
        inputs, batch = jax.device_put((adapter.frame(frame), batch))
        return PreparedFrame(frame, frame_block_extent(frame, layout), _extent_parameters(layout), detections, batch, inputs)

    def _accept(self, frame_name: str, detections: FrameDetections) -> None:
        """The file reader's rules for detections given in Python (`check_detections`), and a warning once per label
        that is not an open-set label of the label sets (its scores cannot be fused)."""
        check_detections(frame_name, detections)
        known = self._known_labels
        for labels in detections.labels:
            for label in labels:
                if label not in known and label not in self.unknown_labels:
                    log.warning(
                        "%s: label %r is not one of the %d open-set labels (configs/labels/label_sets.yaml): its "
                        "scores are not fused (warned once per label; Mapper.unknown_labels counts them)",
                        frame_name,
                        label,
                        len(known),
                    )
                if label not in known:
                    self.unknown_labels[label] = self.unknown_labels.get(label, 0) + 1

    def schedule_copy(self) -> DetectionSchedule:
        """A copy of the detection schedule as it stands, for a thread that decides ahead which of the next frames
        are due (with `frames_integrated` as the position of the next one)."""
        copy = DetectionSchedule(self.config)
        copy.restore(self._schedule.state())
        return copy

    def detection_due(self, T_world_camera) -> bool:
        """Whether the next frame, taken at this pose, would have its detections fused (the schedule)."""
        return self._schedule.due(self.frames_integrated, np.asarray(T_world_camera, np.float64))

    def finalize(self) -> FusionResult:
        """Finalizes the map once (geometry fusion and post-processing merge, when refinement is on) and
        returns it; later calls return the same result. No frames can be integrated afterwards."""
        if self._result is None:
            if self._builder is None:
                raise UserError("the map is empty: integrate at least one frame first")
            self._result = self._builder.result()
            host_memory.trim_heap()  # what fusion and compiling freed goes back before the exports' temporaries
        return self._result

    # ------------------------------------------------------------------------------------------------
    # Looking at the map.

    @property
    def frames_integrated(self) -> int:
        return 0 if self._builder is None else self._builder.frames_integrated

    @property
    def detection_frames(self) -> int:
        """Frames whose detections were fused."""
        return 0 if self._builder is None else self._builder.detection_frames

    @property
    def counters(self) -> dict[str, int]:
        """Instances created, matched, merged and removed, and detections fused, so far."""
        return {} if self._builder is None else dict(self._builder.counters)

    @property
    def map_config(self) -> MapConfig | None:
        """The engine's current sizes (None before the first frame)."""
        return None if self._builder is None else self._builder.map_config

    @property
    def state(self):
        """The current `MapState` pytree (None before the first frame)."""
        return None if self._builder is None else self._builder.state

    def result(self) -> FusionResult:
        """The map as a `FusionResult`: the finalized one after `finalize()`, else a finalized snapshot."""
        if self._result is not None:
            return self._result
        builder = self._require_builder()
        state = copy_map_state(builder.state)  # finalize donates its input: never the live map
        host_memory.release_unallocated_rows(state)  # the copy's empty rows, before finalize's own temporaries
        if self.config.refinement.enabled:
            state, _ = step.finalize(state, builder.step_config, builder.fusion_config)
        return builder.snapshot(state)

    def instances(self, postprocess: bool = True) -> list[MapInstance]:
        """The map's instances (class distribution, points, observations), as the export sees them. Before
        `finalize()` this is a snapshot, finalized on a copy: the map itself does not change."""
        return extract_map_instances(self.result(), self.label_sets, postprocess)

    def extract_mesh(self):
        """The global TSDF's surface as a coloured `trimesh.Trimesh` (world metres)."""
        import trimesh  # heavy: imported when a mesh is asked for

        vertices, faces, colors = extraction.extract_mesh(self._require_builder().state, self.map_config)
        mesh = trimesh.Trimesh(vertices=np.asarray(vertices, np.float64), faces=np.asarray(faces), process=False)
        if len(vertices):
            mesh.visual.vertex_colors = np.concatenate([colors, np.full((len(colors), 1), 255, np.uint8)], axis=1)
        return mesh

    def extract_point_cloud(self) -> tuple[np.ndarray, np.ndarray]:
        """`(points float32 (N, 3) world metres, colors uint8 (N, 3))` on the global TSDF's surface."""
        builder = self._require_builder()
        return extraction.extract_surface_points(builder.state, builder.map_config)

    # ------------------------------------------------------------------------------------------------
    # Saving and loading.

    def save(self, path: str | Path) -> Path:
        """Writes the map (state, configs, schedules) to an `.npz` file that `Mapper.load` continues."""
        builder = self._require_builder()
        state = self._result.state if self._result is not None else builder.state
        progress = {
            **builder.snapshot(state).progress(),
            "finalized": self._result is not None,
            "grows": self._bounds is None,
            "schedule": self._schedule.state(),
        }
        return write_map_file(path, state, builder.map_config, builder.config, progress)

    @classmethod
    def for_scene(
        cls,
        scene: Any,
        config: "str | Path | Mapping[str, Any] | PipelineConfig | None" = None,
        *,
        sample: Any = None,
        **options: Any,
    ) -> "Mapper":
        """The Mapper `fmfusion run` fuses `scene` into (`fmfusion_jax.open_scene`'s `Scene`, or anything with its
        `sample_depth`, `bounds` and `intrinsics`): sized up front from a sample of its frames (the bounds of their
        poses and depth, the blocks they allocate), so that the map does not grow and recompile while fusing, and
        its compiled steps are the ones `fmfusion run` compiled for a room of this size. A growing
        `Mapper(config)` suits a live camera, whose scene is not known ahead.

        Args:
          sample: a `scene.sample_depth(...)` result (default: 60 evenly spaced frames).
          options: the other keyword arguments of `Mapper` (`label_sets`, `likelihood`, `time_stages`, hooks).
        """
        pipeline = as_config(config)
        bounds, expected = scene_extent(scene, pipeline, sample, options.get("label_sets"))
        return cls(pipeline, scene.intrinsics, bounds=bounds, expected_blocks=expected, **options)

    @classmethod
    def load(cls, path: str | Path, time_stages: bool = False) -> "Mapper":
        """A Mapper that continues the map saved at `path` (by `save`, or a run's `map_state.npz`)."""
        saved = read_map_file(path)
        bounds = None if saved.progress.get("grows") else saved.map_config.grid_bounds
        return cls.resume(saved.config, saved.map_config, saved.state, saved.progress, bounds=bounds, time_stages=time_stages)

    @classmethod
    def resume(
        cls,
        config: PipelineConfig,
        map_config: MapConfig,
        state: MapState,
        progress: dict,
        *,
        bounds: "tuple[ArrayLike, ArrayLike] | None",
        label_sets: LabelSets | None = None,
        likelihood: np.ndarray | None = None,
        time_stages: bool = False,
    ) -> "Mapper":
        """A Mapper that continues `state` (donated to its next step): `progress` as `save` writes it (the
        counts of `FusionProgress.as_dict`, the detection `schedule`, whether it is `finalized`)."""
        mapper = cls(config, bounds=bounds, label_sets=label_sets, likelihood=likelihood, time_stages=time_stages)
        builder = MapBuilder(
            config, map_config, mapper.label_sets, likelihood, state=state, timer=StageTimer(enabled=time_stages)
        )
        builder.progress.restore(progress)
        mapper._builder = builder
        mapper._schedule.restore(progress.get("schedule", progress))  # older files: the detection pose alone
        if progress.get("finalized"):
            mapper._result = builder.snapshot(builder.state)
        return mapper

    # ------------------------------------------------------------------------------------------------
    # Sizes.

    def _require_builder(self) -> MapBuilder:
        if self._builder is None:
            raise UserError("the map is empty: integrate at least one frame first")
        return self._builder

    def _layout(self, height: int, width: int) -> MapConfig:
        """The config's map for frames of this size before any bounds: its capacities are the ceiling of growth
        (cached: `prepare` asks for it per frame)."""
        key = (height, width)
        if key not in self._layouts:
            self._layouts[key] = build_map_config(self.config, np.zeros(3), np.ones(3), height, width, self.label_sets)
        return self._layouts[key]

    @staticmethod
    def _block_extent(
        frame: RGBDFrame, map_config: MapConfig, prepared: PreparedFrame | None
    ) -> tuple[int, np.ndarray, np.ndarray]:
        """`frame_block_extent(frame, map_config)`, from `prepared` when it was counted alike."""
        if prepared is not None and prepared.extent_parameters == _extent_parameters(map_config):
            return prepared.block_extent
        return frame_block_extent(frame, map_config)

    def _fit_map_to(self, frame: RGBDFrame, detections_due: bool, prepared: PreparedFrame | None = None) -> None:
        """Makes the map ready for `frame`: built on the first frame, grown when it might not fit."""
        height, width = frame.depth.shape
        if self._builder is not None:
            built = self._builder.map_config
            if (height, width) != (built.image_height, built.image_width):
                raise UserError(
                    f"{frame.name}: image {width}x{height}, the map's frames are {built.image_width}x{built.image_height}"
                )
            self._grow_for(frame, detections_due, prepared)
            return
        # the config's capacities for these frames: a fixed map's sizes, a growing map's ceiling
        layout = self._layout(height, width)
        if self._bounds is not None:
            expected = self._expected_blocks
            if expected is not None:  # at least what the first frame needs
                index = build_map_config(self.config, *self._bounds, height, width, self.label_sets)
                expected = max(expected, self._block_extent(frame, index, prepared)[0])
            map_config = bounded_map_config(self.config, self._bounds, height, width, expected)
        else:
            # around the frame's blocks (a frame without depth: around the origin), room-sized: few growths
            count, lo, hi = self._block_extent(frame, layout, prepared)
            rows = initial_instance_rows(self.config.detections.max_detections, layout.instance_capacity)
            map_config = growing_map_config(layout, count, lo, hi, rows)
        self._builder = MapBuilder(
            self.config,
            map_config,
            self.label_sets,
            self._likelihood,
            timer=self._timer or StageTimer(enabled=self.time_stages),
            fuse_detections=self._fuse_detections,
        )
        self._recent = []  # the sizes are read after the first frame
        log.info("map: %s", map_config.describe())

    def _size_bounds(self, builder: MapBuilder) -> tuple[int, int] | None:
        """Upper bounds of the pool's blocks and the table's rows with the frames of `_recent` in: the sizes after
        the last frame whose statistics were read plus each later frame's bound (None before any was read). Drops
        from `_recent` the frames those sizes already hold."""
        known = builder.sizes_after
        if known is None:
            return None
        self._recent = [entry for entry in self._recent if entry[0] > known.position]
        return known.blocks + sum(entry[1] for entry in self._recent), known.instances + sum(entry[2] for entry in self._recent)

    def _grow_for(self, frame: RGBDFrame, detections_due: bool, prepared: PreparedFrame | None = None) -> None:
        """Enlarges the pool (four times while far below its ceiling, then doubling), the table (doubling) and,
        without bounds, the index (a side by at least the whole extent) if `frame` might not fit.

        The frame adds at most its distinct blocks to the pool and `detections.max_detections` rows to the
        table. The bounds are the sizes after the last frame whose statistics were read (`MapBuilder.sizes_after`,
        a frame or two back) plus these per-frame bounds of the frames since; the device's counts are read (a wait)
        only when a bound would pass a capacity, so most frames are checked without waiting for the previous one.
        """
        builder = self._require_builder()
        old = builder.map_config
        ceiling = self._layout(old.image_height, old.image_width)  # the config's capacities: how far the map may grow
        grows_index = self._bounds is None
        full_pool, full_table = old.block_capacity >= ceiling.block_capacity, old.instance_capacity >= ceiling.instance_capacity
        if full_pool and full_table and not grows_index:
            return  # nothing left to grow: the capacity monitor reports an overflow
        new_blocks, keys_lo, keys_hi = self._block_extent(frame, old, prepared)
        new_rows = self.config.detections.max_detections if detections_due else 0

        pool, rows = old.block_capacity, old.instance_capacity
        position = builder.frames_integrated  # this frame's
        self._recent.append((position, new_blocks, new_rows))
        bounds = self._size_bounds(builder)
        if bounds is None or (not full_pool and bounds[0] + 1 > pool) or (not full_table and bounds[1] > rows):
            # unknown, or close to a capacity: the exact sizes after the steps dispatched so far (waits for the device)
            state = builder.state
            live = int(np.count_nonzero(np.asarray(state.instances.valid)))  # on the host: no reduction compiled for it
            builder.sizes_after = MapSizes(position - 1, int(state.blocks.num_blocks), live)
            bounds = self._size_bounds(builder)
            assert bounds is not None
        blocks_bound, rows_bound = bounds
        if not full_pool and blocks_bound + 1 > pool:
            # far below the ceiling, four times: a room's pool is reached in a couple of recompiles, not five
            factor = 4 if 4 * pool <= ceiling.block_capacity // 2 else 2
            pool = min(ceiling.block_capacity, max(factor * pool, _next_power_of_two(blocks_bound + 1)))
        if not full_table and rows_bound > rows:
            rows = min(ceiling.instance_capacity, max(2 * rows, _next_power_of_two(rows_bound)))

        lo, hi = growth.bounds_block_range(old)
        new_lo, new_hi = lo.copy(), hi.copy()
        if grows_index and new_blocks:
            need_lo, need_hi = keys_lo - 1, keys_hi + 1
            extent = hi - lo
            for axis in range(3):  # grow a side by at least half the extent: few recompiles
                if need_lo[axis] < lo[axis]:
                    new_lo[axis] = min(need_lo[axis] - INDEX_PAD_BLOCKS, lo[axis] - extent[axis])
                if need_hi[axis] > hi[axis]:
                    new_hi[axis] = max(need_hi[axis] + INDEX_PAD_BLOCKS, hi[axis] + extent[axis])
        if (new_lo == lo).all() and (new_hi == hi).all() and pool == old.block_capacity and rows == old.instance_capacity:
            return
        new = dataclasses.replace(growth.config_for_block_range(old, new_lo, new_hi), block_capacity=pool, instance_capacity=rows)
        builder.state = growth.grow_state(builder.state, old, new)
        host_memory.release_unallocated_rows(builder.state)
        builder.map_config = new
        builder.timer.new_layout()  # the steps recompile for the new shapes
        self.growths += 1
        log.info("%s: the map grew (the steps recompile): %s", frame.name, new.describe())


# ----------------------------------------------------------------------------------------------------
# Many maps at once.
