"""Capacity and growth: the map's sizes ahead of the frames (a NumPy block finder over a frame's depth), the
first capacities of a growing map, and the warnings when a capacity nears its end (`CapacityMonitor`).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.engine import growth
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import MapState
from fmfusion_jax.mapping.engine_configs import build_map_config
from fmfusion_jax.types import RGBDFrame

log = logging.getLogger(__name__)


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


#: Blocks (12.5 cm at the default voxel) of free index kept around what the frames have shown, on each side.
INDEX_PAD_BLOCKS = 8


#: Smallest voxel-block pool a growing map starts with.
MIN_POOL_BLOCKS = 1024


#: A growing map's first pool holds this many times the blocks of its first frame. A room allocates tens of times
#: what one view shows (scene0000_00: 19,405 blocks, 592 in its first frame); from 2x the pool grew twice there,
#: from 8x once (every growth recompiles the steps, seconds on a CPU; a pool row takes memory once filled).
FIRST_POOL_FACTOR = 8


#: A growing map's first index reaches this many depth ranges (`dataset.depth_max`) beyond its first frame's
#: blocks on every side: the camera walks on and sees that far again. An index cell is 4 bytes: ~12 MiB at 4 m and
#: 12.5 cm blocks. From 1 m of padding the index grew six times on scene0000_00, from this not at all.
FIRST_INDEX_REACH = 2.0

#: ... within this many index cells (16 MiB): a long depth range or small blocks reach less far at first.
FIRST_INDEX_CELLS = 1 << 22


#: Rows the instance table starts with (with or without bounds): a room's live instances fit (scene0000_00
#: peaks under 200), so a typical run never recompiles for the table; it doubles when a frame might not fit.
INITIAL_INSTANCE_ROWS = 256


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


#: The margin over the sampled block count (`sample_block_count`) of a pool that grows when it must (a sample of
#: the frames sees most of a room, not all), and of one that cannot grow (`MapperBatch`): the sample counts 0.7-1.05x
#: the blocks the frames touch (`tests/test_mapper.py`), so 1.5x the count holds the room (before the rounding up to a
#: power of two).
GROWING_POOL_MARGIN, FIXED_POOL_MARGIN = 1.25, 1.5


def initial_pool_blocks(expected_blocks: int, ceiling: int, margin: float = GROWING_POOL_MARGIN) -> int:
    """The pool a map expected to use `expected_blocks` starts with: the power of two above `margin` times that, at
    least `MIN_POOL_BLOCKS`, at most `ceiling`."""
    return min(ceiling, max(MIN_POOL_BLOCKS, _next_power_of_two(int(np.ceil(margin * expected_blocks)))))


def growing_map_config(layout: MapConfig, first_blocks: int, lo: np.ndarray, hi: np.ndarray, instance_rows: int) -> MapConfig:
    """The map a `Mapper` without bounds starts with, from its first frame's `frame_block_extent` (`first_blocks`
    distinct blocks in `[lo, hi)`): the index over those blocks and `FIRST_INDEX_REACH` depth ranges around them
    (within `FIRST_INDEX_CELLS`), the pool for `FIRST_POOL_FACTOR` times the blocks (at least `MIN_POOL_BLOCKS`, at
    most the config's) and `instance_rows` rows. `layout`: the config's map for these frames (its capacities are the
    ceilings of growth)."""
    lo, hi = np.asarray(lo, np.int64), np.asarray(hi, np.int64)
    reach = max(INDEX_PAD_BLOCKS, int(np.ceil(FIRST_INDEX_REACH * layout.depth_max / layout.block_length)))
    while reach > INDEX_PAD_BLOCKS and np.prod(hi - lo + 2 * reach) > FIRST_INDEX_CELLS:
        reach -= 1
    pool = min(layout.block_capacity, max(MIN_POOL_BLOCKS, _next_power_of_two(FIRST_POOL_FACTOR * first_blocks + 1)))
    indexed = growth.config_for_block_range(layout, lo - reach, hi + reach)
    return dataclasses.replace(indexed, block_capacity=pool, instance_capacity=instance_rows)


def bounded_map_config(
    config: PipelineConfig, bounds: tuple[ArrayLike, ArrayLike], height: int, width: int, expected_blocks: int | None
) -> MapConfig:
    """The map a `Mapper` with `bounds` starts with: its block index over the bounds, the first instance table
    (`initial_instance_rows`) and the pool for `expected_blocks` (`initial_pool_blocks`; None: the config's)."""
    layout = build_map_config(config, *bounds, height, width)
    rows = initial_instance_rows(config.detections.max_detections, layout.instance_capacity)
    pool = layout.block_capacity if expected_blocks is None else initial_pool_blocks(expected_blocks, layout.block_capacity)
    return dataclasses.replace(layout, instance_capacity=rows, block_capacity=pool)


def scene_extent(scene: Any, config: PipelineConfig, sample: Any = None, label_sets: Any = None):
    """`(bounds, expected_blocks)` of a scene as `fmfusion run` sizes its map: the bounds of a sample of its frames'
    poses and depth and the voxel blocks those frames allocate. `scene`: an `io.scene.Scene` (its `sample_depth`,
    `bounds` and `intrinsics`); `sample`: its `sample_depth(...)` (default: 60 evenly spaced frames)."""
    sample = sample if sample is not None else scene.sample_depth(max_frames=60)
    low, high = scene.bounds(sample=sample)
    layout = build_map_config(config, low, high, scene.intrinsics.height, scene.intrinsics.width, label_sets)
    return (low, high), sample_block_count(sample.points_world, sample.ray_origins, layout)
