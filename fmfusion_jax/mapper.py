"""`Mapper`: one map object with a few verbs, for notebooks and robot loops.

    mapper = Mapper("scannet")                       # a packaged config, a YAML path, a dict or a PipelineConfig
    for frame, detections in ...:                    # frames: RGBDFrame, or arrays (depth, colour, pose, K)
        mapper.integrate(frame, detections)          # applies the detection schedule itself
    mapper.instances()                               # a snapshot: the map goes on unchanged
    mapper.finalize()                                # geometry fusion + post-merge, once
    mapper.extract_mesh().export("mesh.ply"); mapper.save("map.npz"); Mapper.load("map.npz")

Without `bounds`, the map grows as the camera explores: the block index, the voxel-block pool and the instance
table start small and are enlarged (by doubling, so a handful of recompiles per run, each logged) before a
frame that would not fit. The voxel lattice is fixed (origins on whole blocks), so a grown map equals one
allocated at its final size. With `bounds` (as `fmfusion run` passes the scene's), the index is fixed; the pool
starts at `expected_blocks` (the config's capacity when not given) and grows the same way, and so does the
instance table (from `INITIAL_INSTANCE_ROWS`: its pairwise merge tests cost K^2, so a table sized to the
map's instances rather than to the ceiling makes the merge several times faster, with the same map). The
config's capacities are the ceiling of growth.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from fmfusion_jax.config import PipelineConfig, load_config
from fmfusion_jax.engine import extraction, growth, step
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.detections import DetectionBatch
from fmfusion_jax.engine.state import init_map_state
from fmfusion_jax.errors import UserError
from fmfusion_jax.instances import MapInstance
from fmfusion_jax.labels import LabelSets, load_label_sets
from fmfusion_jax.map_file import read_map_file, write_map_file
from fmfusion_jax.pipeline import (
    CapacityMonitor,
    DetectionSchedule,
    DetectionSource,
    FusionResult,
    HostAdapter,
    MapBuilder,
    MapSizes,
    StageTimer,
    build_map_config,
    extract_map_instances,
)
from fmfusion_jax.types import ROTATION_TOLERANCE, CameraIntrinsics, FrameDetections, RGBDFrame, rotation_error

log = logging.getLogger(__name__)

#: Blocks (12.5 cm at the default voxel) of free index kept around what the frames have shown, on each side.
INDEX_PAD_BLOCKS = 8
#: Smallest voxel-block pool a growing map starts with.
MIN_POOL_BLOCKS = 1024
#: Rows the instance table starts with (with or without bounds): a room's live instances fit (scene0000_00
#: peaks under 200), so a typical run never recompiles for the table; it doubles when a frame might not fit.
INITIAL_INSTANCE_ROWS = 256


def as_config(config: "str | Path | Mapping[str, Any] | PipelineConfig | None") -> PipelineConfig:
    """A `PipelineConfig` from a packaged name (`"scannet"`), a YAML path, a dict or a config (None: scannet).

    A dict holds overrides of the scannet config, nested (`{"detections": {"every": 1}}`) or dotted
    (`{"detections.every": 1}`); a `"base"` key names another config to start from.
    """
    if config is None:
        return load_config("scannet")
    if isinstance(config, PipelineConfig):
        return config
    if isinstance(config, (str, Path)):
        return load_config(str(config))
    if isinstance(config, Mapping):
        values = dict(config)
        base = values.pop("base", "scannet")
        overrides = []
        for key, value in values.items():
            if isinstance(value, Mapping):
                overrides += [f"{key}.{inner}={_yaml_value(v)}" for inner, v in value.items()]
            else:
                overrides.append(f"{key}={_yaml_value(value)}")
        return load_config(base, overrides)
    raise UserError(f"config: expected a config name, a YAML path, a dict or a PipelineConfig, got {type(config).__name__}")


def _yaml_value(value: Any) -> str:
    import json

    return json.dumps(list(value) if isinstance(value, tuple) else value)


def as_intrinsics(intrinsics: "CameraIntrinsics | np.ndarray | Sequence", height: int, width: int) -> CameraIntrinsics:
    """`CameraIntrinsics` from itself, a 3x3 K matrix or `(fx, fy, cx, cy)`, for `height x width` images."""
    if isinstance(intrinsics, CameraIntrinsics):
        k = intrinsics
    else:
        values = np.asarray(intrinsics, np.float64)
        if values.shape == (3, 3):
            values = values[[0, 1, 0, 1], [0, 1, 2, 2]]
        if values.shape != (4,):
            raise UserError(f"intrinsics: expected a 3x3 K matrix or (fx, fy, cx, cy), got shape {values.shape}")
        fx, fy, cx, cy = (float(v) for v in values)
        k = CameraIntrinsics(fx, fy, cx, cy, width=width, height=height)
    if (k.height, k.width) != (height, width):
        raise UserError(f"intrinsics are for {k.width}x{k.height} images, the depth image is {width}x{height}")
    if not (np.isfinite([k.fx, k.fy, k.cx, k.cy]).all() and k.fx > 0 and k.fy > 0):
        raise UserError(f"intrinsics: focal lengths must be positive and finite, got fx={k.fx}, fy={k.fy}")
    return k


def as_frame(
    frame: RGBDFrame | None = None,
    *,
    depth=None,
    color=None,
    T_world_camera=None,
    intrinsics=None,
    index: int = 0,
    name: str | None = None,
) -> RGBDFrame:
    """An `RGBDFrame` from itself or from arrays: depth `(H, W)` metres, colour `(H, W, 3)` uint8 RGB (None:
    grey), `T_world_camera` `(4, 4)` camera-to-world, intrinsics (see `as_intrinsics`). Wrong units, shapes and
    non-rigid poses are UserErrors that say what to fix."""
    if frame is not None:
        if not isinstance(frame, RGBDFrame):
            raise UserError(
                f"integrate: expected an RGBDFrame (or depth=..., T_world_camera=... arrays), got {type(frame).__name__}"
            )
        checked_pose(frame.T_world_camera, frame.name)
        return frame
    if depth is None or T_world_camera is None or intrinsics is None:
        raise UserError("integrate: give a frame, or depth=, T_world_camera= and intrinsics=")
    name = name or f"frame-{index:06d}"
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise UserError(f"{name}: depth must be an (H, W) image, got shape {depth.shape}")
    if not np.issubdtype(depth.dtype, np.floating):
        raise UserError(f"{name}: depth is {depth.dtype}; give float metres (e.g. a ScanNet uint16 PNG / 1000.0)")
    depth = depth.astype(np.float32)
    if np.any(depth < 0):
        raise UserError(f"{name}: depth has negative values ({int(np.sum(depth < 0))} pixels); give metres, 0 = no reading")
    valid = depth[np.isfinite(depth) & (depth > 0)]
    if valid.size and np.median(valid) > 50.0:
        raise UserError(f"{name}: median depth {np.median(valid):.0f}: depth must be in metres, not millimetres")
    if valid.size < 0.01 * depth.size:
        log.warning("%s: only %d of %d depth pixels are valid: the frame adds almost nothing", name, valid.size, depth.size)
    depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
    height, width = depth.shape
    if color is None:
        color = np.full((height, width, 3), 128, np.uint8)
    color = np.asarray(color)
    if color.shape != (height, width, 3) or color.dtype != np.uint8:
        raise UserError(f"{name}: colour must be ({height}, {width}, 3) uint8 RGB, got {color.shape} {color.dtype}")
    pose = checked_pose(T_world_camera, name)
    return RGBDFrame(
        index=index, name=name, color=color, depth=depth, T_world_camera=pose, intrinsics=as_intrinsics(intrinsics, height, width)
    )


def check_detections(frame_name: str, detections: FrameDetections) -> None:
    """The file reader's rules for detections given in Python: scores in [0, 1] (a UserError), and a warning when
    they are another frame's (their `frame_name` differs from `frame_name`)."""
    for k, labels in enumerate(detections.labels):
        for label, score in labels.items():
            if not 0.0 <= float(score) <= 1.0:
                raise UserError(f"{frame_name}: detection {k} scores {label!r} {score}: scores must lie in [0, 1]")
    if detections.frame_name and detections.frame_name != frame_name:
        log.warning("%s: fusing the detections of %s (another frame's?)", frame_name, detections.frame_name)


def checked_pose(T_world_camera, name: str) -> np.ndarray:
    """float64 `(4, 4)` camera-to-world pose; a non-finite or non-rigid one is a UserError naming frame `name` (a NaN
    pose would otherwise size the map from NaN block coordinates)."""
    pose = np.asarray(T_world_camera, np.float64)
    if pose.shape != (4, 4):
        raise UserError(f"{name}: T_world_camera must be a 4x4 matrix, got shape {pose.shape}")
    if not np.all(np.isfinite(pose)):
        raise UserError(f"{name}: T_world_camera is not finite (a lost track? skip the frame)")
    if not np.allclose(pose[3], (0.0, 0.0, 0.0, 1.0), atol=1e-6):
        raise UserError(
            f"{name}: T_world_camera's bottom row is {pose[3].tolist()}, not [0, 0, 0, 1] (a transposed pose? the "
            "translation belongs in the last column)"
        )
    if rotation_error(pose) > ROTATION_TOLERANCE or np.linalg.det(pose[:3, :3]) < 0:  # the readers' rule
        raise UserError(
            f"{name}: T_world_camera's rotation is not a rotation (check the pose's convention and that it maps camera to world)"
        )
    return pose


@functools.lru_cache(maxsize=8)
def _pixel_rays(height: int, width: int, stride: int, fx: float, fy: float, cx: float, cy: float) -> tuple[np.ndarray, ...]:
    """float32 `(height // stride, width // stride)` x2: `(u - cx) / fx` and `(v - cy) / fy` of the strided pixels."""
    v, u = np.mgrid[0:height:stride, 0:width:stride]
    rays = (((u - cx) / fx).astype(np.float32), ((v - cy) / fy).astype(np.float32))
    for ray in rays:
        ray.flags.writeable = False  # shared by every call
    return rays


def _sample_block_coordinates(frame: RGBDFrame, map_config: MapConfig) -> list[np.ndarray]:
    """int32 `(3, N)` per depth offset: the world block (x, y, z rows; lattice origin 0) of each depth sample that
    the engine's block finder takes, the strided pixels at `[d - trunc, d + trunc]`, duplicates kept. In float32
    as the engine, in rows and one offset at a time: the growth check runs this on every frame, and numpy reduces
    contiguous rows of cache-sized arrays several times faster than the columns of one `(N, 3)` array."""
    stride, trunc = map_config.alloc_pixel_stride, map_config.sdf_trunc
    k = frame.intrinsics
    ray_x, ray_y = _pixel_rays(*frame.depth.shape, stride, k.fx, k.fy, k.cx, k.cy)
    d = np.asarray(frame.depth[::stride, ::stride], np.float32)
    ok = (d >= map_config.depth_min) & (d <= map_config.depth_max)
    camera = np.stack([ray_x[ok], ray_y[ok], np.ones(int(ok.sum()), np.float32)])  # (3, N): rays at unit depth
    samples = map_config.alloc_depth_samples
    offsets = np.linspace(-trunc, trunc, samples, dtype=np.float32) if samples > 1 else np.zeros(1, np.float32)
    rotation, translation = frame.T_world_camera[:3, :3].astype(np.float32), frame.T_world_camera[:3, 3:].astype(np.float32)
    rotated = rotation @ camera  # (3, N): each ray in the world, scaled by its sample's depth below
    depth = d[ok]
    return [
        np.floor((rotated * (depth + offset) + translation) / np.float32(map_config.block_length)).astype(np.int32)
        for offset in offsets
    ]


def frame_block_keys(frame: RGBDFrame, map_config: MapConfig) -> np.ndarray:
    """int64 `(N, 3)`: the distinct blocks (world lattice, origin 0) that the engine's block finder would
    touch for this frame, from the same strided depth samples over `[d - trunc, d + trunc]`."""
    return _distinct_blocks(_sample_block_coordinates(frame, map_config))


def _distinct_blocks(pieces: list[np.ndarray]) -> np.ndarray:
    """int64 `(N, 3)`: the distinct blocks of `_sample_block_coordinates`' pieces, sorted."""
    return unique_block_keys(np.concatenate(pieces, axis=1).T.astype(np.int64))


def frame_block_extent(frame: RGBDFrame, map_config: MapConfig) -> tuple[int, np.ndarray, np.ndarray]:
    """(how many distinct blocks, lowest block, highest block + 1) of `frame_block_keys` (`(0, zeros, zeros)`
    for a frame without valid depth), counted on a bitmap over their box rather than by sorting: the growth
    check runs it on every frame."""
    pieces = _sample_block_coordinates(frame, map_config)
    if pieces[0].shape[1] == 0:
        return 0, np.zeros(3, np.int64), np.zeros(3, np.int64)
    lo = np.min([piece.min(axis=1) for piece in pieces], axis=0).astype(np.int64)
    hi = np.max([piece.max(axis=1) for piece in pieces], axis=0).astype(np.int64) + 1
    dims = hi - lo
    if int(np.prod(dims)) > 1 << 24:  # a box too large for a bitmap (depth far beyond a room): sort instead
        return len(_distinct_blocks(pieces)), lo, hi
    seen = np.zeros(int(np.prod(dims)), bool)
    for piece in pieces:
        seen[((piece[0] - lo[0]) * dims[1] + (piece[1] - lo[1])) * dims[2] + (piece[2] - lo[2])] = True
    return int(np.count_nonzero(seen)), lo, hi


def _extent_parameters(map_config: MapConfig) -> tuple:
    """What `frame_block_extent` reads of a map config: maps that agree on these count the same extent."""
    c = map_config
    return (c.alloc_pixel_stride, c.alloc_depth_samples, c.sdf_trunc, c.depth_min, c.depth_max, c.block_length)


@dataclasses.dataclass(frozen=True)
class PreparedFrame:
    """A frame (and its detections) with the host work that needs only the config done ahead (`Mapper.prepare`):
    its `frame_block_extent`, which the growth check needs before the frame's step, the detections packed, and they
    and the frame's arrays sent to the device. `fmfusion run` prepares the next frames in its reader threads, so that
    this work overlaps the fusion of the frame before."""

    frame: RGBDFrame
    block_extent: tuple[int, np.ndarray, np.ndarray]
    #: `_extent_parameters` of the config the extent was counted with (a map with others counts again)
    extent_parameters: tuple
    detections: FrameDetections | None = None
    #: `detections` packed (`HostAdapter.detections`) at the config's pixel stride (None without detections)
    batch: DetectionBatch | None = None
    #: the frame as engine arrays (`HostAdapter.frame`), put on the device with `batch` (None: made at `integrate`)
    inputs: step.FrameInputs | None = None


#: Bits per axis of a packed block key (block coordinates within +-2^20 blocks: +-131 km at 12.5 cm blocks).
_KEY_BITS = 21


def unique_block_keys(keys: np.ndarray) -> np.ndarray:
    """int64 `(M, 3)` -> `(N, 3)`: the distinct rows in lexicographic order (as `np.unique(axis=0)`, ~30x
    faster: each row packed into one int64)."""
    half, mask = 1 << (_KEY_BITS - 1), (1 << _KEY_BITS) - 1
    shifted = np.clip(keys + half, 0, mask)
    packed = np.unique((shifted[:, 0] << (2 * _KEY_BITS)) | (shifted[:, 1] << _KEY_BITS) | shifted[:, 2])
    return np.stack([(packed >> (2 * _KEY_BITS)) & mask, (packed >> _KEY_BITS) & mask, packed & mask], axis=1) - half


def sample_block_count(points_world: np.ndarray, ray_origins: np.ndarray, map_config: MapConfig) -> int:
    """Distinct blocks that depth samples would allocate: each point `(N, 3)` and its truncation band along
    the ray from its camera centre `(N, 3)` (world metres). From a sample of the frames this underestimates
    what the whole sequence allocates; `fmfusion run` starts its pool there (see `Mapper(expected_blocks)`)."""
    if len(points_world) == 0:
        return 0
    rays = points_world - ray_origins
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-9)
    trunc = map_config.sdf_trunc
    offsets = np.linspace(-trunc, trunc, map_config.alloc_depth_samples) if map_config.alloc_depth_samples > 1 else [0.0]
    world = np.concatenate([points_world + o * rays for o in offsets])
    return len(unique_block_keys(np.floor(world / map_config.block_length).astype(np.int64)))


def _next_power_of_two(n: int) -> int:
    return 1 << max(0, int(np.ceil(np.log2(max(n, 1)))))


def initial_instance_rows(max_detections: int, ceiling: int) -> int:
    """The instance table a map starts with: `INITIAL_INSTANCE_ROWS`, or the power of two above two frames'
    detections if more, at most `ceiling` (the config's `instances.capacity`)."""
    return min(ceiling, max(INITIAL_INSTANCE_ROWS, _next_power_of_two(2 * max_detections)))


def initial_pool_blocks(expected_blocks: int, ceiling: int) -> int:
    """The pool a map expected to use `expected_blocks` starts with: the power of two above 1.25x that (a
    sample of the frames sees most of a room, not all), at least `MIN_POOL_BLOCKS`, at most `ceiling`."""
    return min(ceiling, max(MIN_POOL_BLOCKS, _next_power_of_two(int(np.ceil(1.25 * expected_blocks)))))


def bounded_map_config(
    config: PipelineConfig, bounds: tuple[ArrayLike, ArrayLike], height: int, width: int, expected_blocks: int | None
) -> MapConfig:
    """The map a `Mapper` with `bounds` starts with: its block index over the bounds, the first instance table
    (`initial_instance_rows`) and the pool for `expected_blocks` (`initial_pool_blocks`; None: the config's)."""
    layout = build_map_config(config, *bounds, height, width)
    rows = initial_instance_rows(config.detections.max_detections, layout.instance_capacity)
    pool = layout.block_capacity if expected_blocks is None else initial_pool_blocks(expected_blocks, layout.block_capacity)
    return dataclasses.replace(layout, instance_capacity=rows, block_capacity=pool)


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
      timer, fuse_detections: hooks of the `MapBuilder` inside (`fmfusion_jax.bench` passes its per-frame
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
        (`pipeline.DetectionSource`: a `DetectionFolder`, `sources.ModelSource`, any function of the frame), which
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
                f"prepare: expected an RGBDFrame (fmfusion_jax.mapper.as_frame makes one of arrays), got {type(frame).__name__}"
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
        state = jax.tree.map(jnp.copy, builder.state)  # finalize donates its input: never the live map
        if self.config.refinement.enabled:
            state, _ = step.finalize(state, builder.step_config, builder.fusion_config)
        return builder.snapshot(state)

    def instances(self, postprocess: bool = True) -> list[MapInstance]:
        """The map's instances (class distribution, points, observations), as the export sees them. Before
        `finalize()` this is a snapshot, finalized on a copy: the map itself does not change."""
        return extract_map_instances(self.result(), self.label_sets, postprocess)

    def extract_mesh(self):
        """The global TSDF's surface as a coloured `trimesh.Trimesh` (world metres)."""
        import trimesh

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
    def load(cls, path: str | Path, time_stages: bool = False) -> "Mapper":
        """A Mapper that continues the map saved at `path` (by `save`, or a run's `map_state.npz`)."""
        saved = read_map_file(path)
        progress = saved.progress
        lo, hi = saved.map_config.grid_bounds
        mapper = cls(saved.config, bounds=None if progress.get("grows") else (lo, hi), time_stages=time_stages)
        builder = MapBuilder(
            saved.config, saved.map_config, mapper.label_sets, state=saved.state, timer=StageTimer(enabled=time_stages)
        )
        builder.restore_progress(progress)
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
            self._layouts[key] = build_map_config(self.config, np.zeros(3), np.ones(3), height, width)
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
                index = build_map_config(self.config, *self._bounds, height, width)
                expected = max(expected, self._block_extent(frame, index, prepared)[0])
            map_config = bounded_map_config(self.config, self._bounds, height, width, expected)
        else:
            # the frame's blocks padded (a frame without depth: the padding around the origin)
            count, lo, hi = self._block_extent(frame, layout, prepared)
            map_config = dataclasses.replace(
                growth.config_for_block_range(layout, lo - INDEX_PAD_BLOCKS, hi + INDEX_PAD_BLOCKS),
                block_capacity=min(layout.block_capacity, max(MIN_POOL_BLOCKS, _next_power_of_two(2 * count + 1))),
                instance_capacity=initial_instance_rows(self.config.detections.max_detections, layout.instance_capacity),
            )
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
        """Enlarges the pool or the table (doubling) and, without bounds, the index (by at least half a side)
        if `frame` might not fit.

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
            builder.sizes_after = MapSizes(position - 1, int(state.blocks.num_blocks), int(state.instances.valid.sum()))
            bounds = self._size_bounds(builder)
            assert bounds is not None
        blocks_bound, rows_bound = bounds
        if not full_pool and blocks_bound + 1 > pool:
            pool = min(ceiling.block_capacity, max(2 * pool, _next_power_of_two(blocks_bound + 1)))
        if not full_table and rows_bound > rows:
            rows = min(ceiling.instance_capacity, max(2 * rows, _next_power_of_two(rows_bound)))

        lo, hi = growth.bounds_block_range(old)
        new_lo, new_hi = lo.copy(), hi.copy()
        if grows_index and new_blocks:
            need_lo, need_hi = keys_lo - 1, keys_hi + 1
            extent = hi - lo
            for axis in range(3):  # grow a side by at least half the extent: few recompiles
                if need_lo[axis] < lo[axis]:
                    new_lo[axis] = min(need_lo[axis] - INDEX_PAD_BLOCKS, lo[axis] - extent[axis] // 2)
                if need_hi[axis] > hi[axis]:
                    new_hi[axis] = max(need_hi[axis] + INDEX_PAD_BLOCKS, hi[axis] + extent[axis] // 2)
        if (new_lo == lo).all() and (new_hi == hi).all() and pool == old.block_capacity and rows == old.instance_capacity:
            return
        new = dataclasses.replace(growth.config_for_block_range(old, new_lo, new_hi), block_capacity=pool, instance_capacity=rows)
        builder.state = growth.grow_state(builder.state, old, new)
        builder.map_config = new
        builder.timer.new_layout()  # the steps recompile for the new shapes
        self.growths += 1
        log.info("%s: the map grew (the steps recompile): %s", frame.name, new.describe())


# ----------------------------------------------------------------------------------------------------
# Many maps at once.


def _tree_where(keep_new: jax.Array, new, old):
    """Per leaf `new if keep_new else old` (`keep_new` a scalar bool: one map of a vmapped batch)."""
    return jax.tree.map(lambda a, b: jnp.where(keep_new, a, b), new, old)


@functools.partial(jax.jit, static_argnames=("config",), donate_argnames=("states",))
def _batch_frame(states, frames, batches, likelihood, has_frame, has_detections, config: MapConfig, fusion: step.FusionConfig):
    """One frame for every map of a batch: the detection step where a map has detections, the TSDF alone where
    it has none, nothing where it has no frame. (A detection step with no valid detection integrates the TSDF
    and leaves the voxels' instance slots as they are; only its table, whose missed counts it would advance,
    is taken from before.)"""

    def one(state, frame, batch, with_frame, with_detections):
        batch = batch._replace(valid=batch.valid & with_detections)
        new, stats = step.fuse_detections(state, frame, batch, likelihood, config, fusion)
        new = new._replace(instances=_tree_where(with_detections, new.instances, state.instances))
        return _tree_where(with_frame, new, state), stats

    return jax.vmap(one, in_axes=(0, 0, 0, 0, 0))(states, frames, batches, has_frame, has_detections)


@functools.partial(jax.jit, static_argnames=("config", "kind"), donate_argnames=("states",))
def _batch_refinement(states, due, config: MapConfig, fusion: step.FusionConfig, kind: str):
    """`refine`, `fuse_geometry` or `finalize` (`kind`) on the maps where `due`; the others unchanged."""

    def one(state, is_due):
        if kind == "geometry":
            new, stats = step.fuse_geometry(state, config, fusion), None
        else:
            new, stats = (step.refine if kind == "refine" else step.finalize)(state, config, fusion)
        return _tree_where(is_due, new, state), stats

    return jax.vmap(one)(states, due)


class MapperBatch:
    """`B` independent maps of one config, fused in lock step: each engine step runs once for all maps,
    vmapped, with the states donated (one compiled step whatever `B`). For many short scenes on one device,
    or for experiments over seeds and noise models.

    All maps share the image size and one block layout: `bounds` must cover every map's scene, each in its own
    world frame (e.g. the union of the scenes' bounds). The capacities are the config's (no growth). Each map
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
        label_sets: LabelSets | None = None,
        likelihood: np.ndarray | None = None,
    ):
        if batch_size < 1:
            raise UserError(f"batch_size must be >= 1, got {batch_size}")
        self.config = as_config(config)
        self.label_sets = label_sets or load_label_sets()
        self.batch_size = batch_size
        self._bounds = (np.asarray(bounds[0], float), np.asarray(bounds[1], float))
        height, width = image_shape
        self.map_config = build_map_config(self.config, *self._bounds, height, width)
        self._step_config = self.map_config.compiled_layout()  # the steps' static config (the states hold the origin)
        single = init_map_state(self.map_config)
        self.states = jax.tree.map(lambda leaf: jnp.stack([leaf] * batch_size), single)
        # one builder per map keeps its counts, refinement schedule and capacity warnings; the maps' states
        # live stacked in `states`, so the builders hold none (not even the unbatched initial one: a room's worth)
        self._builders = [
            MapBuilder(self.config, self.map_config, self.label_sets, likelihood, state=single) for _ in range(batch_size)
        ]
        for builder in self._builders:
            builder.state = None  # type: ignore[assignment]  # never stepped: the batch steps `states`
        del single
        self.fusion_config = self._builders[0].fusion_config
        self._likelihood = self._builders[0].likelihood
        self._schedules = [DetectionSchedule(self.config) for _ in range(batch_size)]
        self._results: list[FusionResult] | None = None

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
        adapter = self._builders[0].adapter
        template = next((f for f in frames if f is not None), None)
        if template is None:
            return [False] * self.batch_size
        inputs, batches, has_frame, due = [], [], [], []
        for i, (frame, dets) in enumerate(zip(frames, detections)):
            builder = self._builders[i]
            fused = (
                frame is not None
                and dets is not None
                and self._schedules[i].due(builder.frames_integrated, np.asarray(frame.T_world_camera))
            )
            inputs.append(adapter.frame(frame if frame is not None else template))
            batches.append(adapter.detections(dets if fused else None))
            has_frame.append(frame is not None)
            due.append(fused)
        stack = lambda items: jax.tree.map(lambda *leaves: np.stack(leaves), *items)  # noqa: E731
        self.states, stats = _batch_frame(
            self.states,
            stack(inputs),
            stack(batches),
            self._likelihood,
            np.array(has_frame),
            np.array(due),
            self._step_config,
            self.fusion_config,
        )
        stats = jax.device_get(stats)
        merge_due, geometry_due = np.zeros(self.batch_size, bool), np.zeros(self.batch_size, bool)
        for i, frame in enumerate(frames):
            if frame is None:
                continue
            builder = self._builders[i]
            builder.frames_integrated += 1
            self._schedules[i].advance(frame.T_world_camera)
            if due[i]:
                self._schedules[i].fused(frame.T_world_camera)
                merge_due[i], geometry_due[i] = builder.record_detection_frame(jax.tree.map(lambda x, i=i: x[i], stats))
        if merge_due.any():
            self.states, refine_stats = _batch_refinement(self.states, merge_due, self._step_config, self.fusion_config, "refine")
            refine_stats = jax.device_get(refine_stats)
            for i, frame in enumerate(frames):
                if merge_due[i] and frame is not None:
                    self._builders[i]._count_refinement(frame.name, jax.tree.map(lambda x, i=i: x[i], refine_stats))
        if geometry_due.any():
            self.states, _ = _batch_refinement(self.states, geometry_due, self._step_config, self.fusion_config, "geometry")
        # the overflow counters of every map in one small transfer (not each map's state sliced out)
        counts = jax.device_get(CapacityMonitor.counts_of(self.states))
        for i, frame in enumerate(frames):
            if frame is not None:
                self._builders[i].monitor.check_counts(
                    {name: value[i] for name, value in counts.items()}, self.map_config, self._builders[i].frames_integrated
                )
        return due

    def finalize(self) -> list[FusionResult]:
        """Finalizes every map once (geometry fusion and post-processing merge when refinement is on)."""
        if self._results is None:
            if self.config.refinement.enabled:
                everyone = np.ones(self.batch_size, bool)
                self.states, stats = _batch_refinement(self.states, everyone, self._step_config, self.fusion_config, "finalize")
                stats = jax.device_get(stats)
                for i, builder in enumerate(self._builders):
                    builder._count_refinement("final", jax.tree.map(lambda x, i=i: x[i], stats))
            self._results = [builder.snapshot(self._map_state(i)) for i, builder in enumerate(self._builders)]
        return self._results

    def mapper(self, index: int) -> Mapper:
        """Map `index` as an ordinary `Mapper` (a copy: it continues on its own; finalized if the batch is)."""
        builder = self._builders[index]
        mapper = Mapper(self.config, bounds=self._bounds, label_sets=self.label_sets)
        own = MapBuilder(
            self.config,
            self.map_config,
            self.label_sets,
            np.asarray(self._likelihood),
            state=jax.tree.map(jnp.copy, self._map_state(index)),
        )
        own.restore_progress(builder.snapshot(own.state).progress())
        mapper._builder = own
        mapper._schedule.restore(self._schedules[index].state())
        if self._results is not None:
            mapper._result = own.snapshot(own.state)
        return mapper

    def _map_state(self, index: int):
        return jax.tree.map(lambda leaf: leaf[index], self.states)


__all__ = [
    "Mapper",
    "MapperBatch",
    "PreparedFrame",
    "as_config",
    "as_frame",
    "as_intrinsics",
    "frame_block_extent",
    "frame_block_keys",
]
