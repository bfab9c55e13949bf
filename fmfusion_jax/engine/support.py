"""The floor under the map: where it is, and which detection pixels lie on it.

Real masks spill: SAM, prompted with a box around a couch or a bed, often returns the rug or the whole floor
in front of it, and a box detector calls a floor a bed. An object of the closed classes never lies in the
floor itself, so the pixels of a detection that see the floor are not the object's, and a detection that sees
mostly floor is not an object at all (unless its labels say floor).

The floor is found from the map's own observations: every detection frame adds the heights (along the world's
up axis) of the surface points that face up to a histogram kept in the map (`VoxelBlocks.up_heights`); the
floor is the lowest height that holds a large share of them. Nothing is assumed about where the world's
origin is; the up axis is a setting (ScanNet, SceneNN and the generated rooms are z-up).

Shapes: `(Hs, Ws)` is the stride-subsampled pixel grid (`config.pixel_stride`), `N` detection rows.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from fmfusion_jax.engine._geometry import subsampled_rays, valid_depth
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import UP_HEIGHT_BINS

#: Height bins of `VoxelBlocks.up_heights`: 2 cm each, heights in [-20.48, 20.48) m along the up axis.
HEIGHT_BIN = 0.02
HEIGHT_BINS = UP_HEIGHT_BINS
#: A surface faces up when its normal is within ~25 degrees of the up axis.
UP_FACING_COS = 0.9
#: A depth step of more than this share of the depth between neighbours is an edge: no normal there.
EDGE_STEP = 0.05
#: The floor: the lowest height whose count (3 bins summed) is at least this share of the largest ...
FLOOR_SHARE_OF_PEAK = 0.2
#: ... with at least this many up-facing samples there (a few frames' worth of floor) ...
FLOOR_MIN_SAMPLES = 1000
#: ... and at least this far (m) below the camera (a table top seen from above is not taken for the floor).
FLOOR_MIN_DEPTH_BELOW_CAMERA = 0.6


class SurfaceSamples(NamedTuple):
    """The frame's surface points on the fused pixel grid."""

    height: jax.Array  # float32[Hs, Ws]: height of the point along the up axis (m, world frame)
    up_facing: jax.Array  # bool[Hs, Ws]: a valid point whose surface normal is within ~25 degrees of up
    camera_height: jax.Array  # float32[]: the camera's height along the up axis (m)


def surface_samples(depth, T_world_camera, intrinsics, up: tuple[float, float, float], config: MapConfig) -> SurfaceSamples:
    """Heights and up-facing flags of the frame's points at the fused pixels.

    Args:
      depth: float32 `(H, W)` metres (0 = invalid).
      T_world_camera: float32 `(4, 4)`.
      intrinsics: float32 `(4,)` = `(fx, fy, cx, cy)`.
      up: the world's up axis (unit vector, static).

    Normals: the cross product of the central differences between the neighbouring fused pixels, where all four
    neighbours have depth and none is across a depth edge.
    """
    stride = config.pixel_stride
    d = jnp.asarray(depth, jnp.float32)[::stride, ::stride]
    rx, ry = subsampled_rays(intrinsics, config, stride)
    x, y = rx * d, ry * d
    ok = valid_depth(d, config)

    def neighbours(a, axis):
        return jnp.roll(a, -1, axis), jnp.roll(a, 1, axis)

    def difference(axis):
        (x1, x0), (y1, y0), (d1, d0) = neighbours(x, axis), neighbours(y, axis), neighbours(d, axis)
        o1, o0 = neighbours(ok, axis)
        smooth = o1 & o0 & (jnp.abs(d1 - d0) < 2 * EDGE_STEP * d)
        return (x1 - x0, y1 - y0, d1 - d0), smooth

    (ax, ay, az), smooth_u = difference(1)
    (bx, by, bz), smooth_v = difference(0)
    nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    T = jnp.asarray(T_world_camera, jnp.float32)
    ux, uy, uz = up
    # the up axis in the camera frame (R^T up): heights and normals without rotating every point
    cux = T[0, 0] * ux + T[1, 0] * uy + T[2, 0] * uz
    cuy = T[0, 1] * ux + T[1, 1] * uy + T[2, 1] * uz
    cuz = T[0, 2] * ux + T[1, 2] * uy + T[2, 2] * uz
    camera_height = T[0, 3] * ux + T[1, 3] * uy + T[2, 3] * uz
    height = camera_height + cux * x + cuy * y + cuz * d
    along_up = nx * cux + ny * cuy + nz * cuz
    norm = jnp.sqrt(nx * nx + ny * ny + nz * nz)
    # the sign of the cross product depends on the axes' order: the floor and a ceiling are both horizontal,
    # and only the lowest horizontal surface is ever taken for the floor
    up_facing = ok & smooth_u & smooth_v & (jnp.abs(along_up) > UP_FACING_COS * jnp.maximum(norm, 1e-12))
    # the image border wraps around in the rolls: no normal there
    border = jnp.zeros(d.shape, bool).at[1:-1, 1:-1].set(True)
    return SurfaceSamples(height, up_facing & border, camera_height)


def height_bins(height: jax.Array) -> jax.Array:
    """int32 bin of `VoxelBlocks.up_heights` of each height, `HEIGHT_BINS` where out of range."""
    index = jnp.floor(height / HEIGHT_BIN).astype(jnp.int32) + HEIGHT_BINS // 2
    return jnp.where((index >= 0) & (index < HEIGHT_BINS), index, HEIGHT_BINS)


def add_heights(up_heights: jax.Array, samples: SurfaceSamples) -> jax.Array:
    """`up_heights int32[HEIGHT_BINS]` plus the frame's up-facing samples."""
    bins = jnp.where(samples.up_facing, height_bins(samples.height), HEIGHT_BINS).reshape(-1)
    return up_heights + jax.ops.segment_sum(jnp.ones(bins.shape, jnp.int32), bins, num_segments=HEIGHT_BINS + 1)[:-1]


class Floor(NamedTuple):
    height: jax.Array  # float32[]: the floor's height along the up axis (m), centre of its strongest bin
    found: jax.Array  # bool[]: enough up-facing samples there to call it the floor


@jax.jit
def floor_height(up_heights: jax.Array) -> Floor:
    """The floor from the histogram `up_heights int32[HEIGHT_BINS]`: the lowest height holding at least
    `FLOOR_SHARE_OF_PEAK` of the most-populated height (3 bins summed, so that a plane straddling a bin edge
    counts whole), then its strongest bin within 10 cm above."""
    counts = up_heights.astype(jnp.float32)
    summed = counts + jnp.roll(counts, 1).at[0].set(0) + jnp.roll(counts, -1).at[-1].set(0)
    strong = (summed >= FLOOR_SHARE_OF_PEAK * jnp.max(summed)) & (summed >= FLOOR_MIN_SAMPLES)
    lowest = jnp.argmax(strong)  # first True (0 when none: `found` is False then)
    window = jnp.arange(6)
    local = counts[jnp.minimum(lowest + window, HEIGHT_BINS - 1)]
    peak = lowest + jnp.argmax(local)
    height = (peak - HEIGHT_BINS // 2 + 0.5).astype(jnp.float32) * HEIGHT_BIN
    return Floor(height, jnp.any(strong))


def floor_pixels(samples: SurfaceSamples, floor: Floor, band: ArrayLike) -> jax.Array:
    """bool `(Hs, Ws)`: up-facing points within `band` metres above the floor (none when no floor is found, or
    when the found floor is not well below the camera)."""
    usable = floor.found & (samples.camera_height - floor.height >= FLOOR_MIN_DEPTH_BELOW_CAMERA)
    return usable & samples.up_facing & (samples.height < floor.height + band)


def filter_floor_pixels(
    det_image: jax.Array,
    on_floor: jax.Array,
    floor_detection: jax.Array,
    max_share: ArrayLike,
    filtered_value: int,
) -> jax.Array:
    """A detection image without its floor pixels.

    Args:
      det_image: int32 `(Hs, Ws)`: the detection of each pixel, -1 none.
      on_floor: bool `(Hs, Ws)` (`floor_pixels`).
      floor_detection: bool `(N,)`: detections whose labels say floor (they keep their pixels).
      max_share: a detection with more than this share of its pixels on the floor is dropped whole.
      filtered_value: the value of a removed pixel (neither the detection's nor evidence against others).

    Returns:
      int32 `(Hs, Ws)`.
    """
    n = floor_detection.shape[0]
    segments = jnp.where(det_image >= 0, det_image, n).reshape(-1)
    total = jax.ops.segment_sum(jnp.ones(segments.shape, jnp.int32), segments, num_segments=n + 1)[:n]
    floor = jax.ops.segment_sum(on_floor.reshape(-1).astype(jnp.int32), segments, num_segments=n + 1)[:n]
    dropped = (floor.astype(jnp.float32) > max_share * total.astype(jnp.float32)) & ~floor_detection
    dropped_row = jnp.concatenate([dropped, jnp.zeros((1,), bool)])[segments].reshape(det_image.shape)
    keeps_floor = jnp.concatenate([floor_detection, jnp.ones((1,), bool)])[segments].reshape(det_image.shape)
    removed = (det_image >= 0) & (dropped_row | (on_floor & ~keeps_floor))
    return jnp.where(removed, filtered_value, det_image)


__all__ = [
    "HEIGHT_BIN",
    "HEIGHT_BINS",
    "SurfaceSamples",
    "surface_samples",
    "height_bins",
    "add_heights",
    "Floor",
    "floor_height",
    "floor_pixels",
    "filter_floor_pixels",
]
