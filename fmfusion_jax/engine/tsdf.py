"""Global TSDF integration of one RGB-D frame into the voxel-block pool (jitted, fixed shapes).

Two steps, as in Open3D's VoxelBlockGrid but without hashing:

1. **Find and allocate touched blocks.** A stride-subsampled set of depth pixels is back-projected at
   `alloc_depth_samples` depths spread over `[d - trunc, d + trunc]`; the samples' block coordinates
   are deduplicated through the dense block index (one scatter-min of sample ids, bounded by the
   sample count), compacted to a fixed list of `M = max_touched_blocks` blocks, and blocks not yet in
   the pool take the next free slots (a cumulative sum over the `M` entries). When the pool is full
   the block is counted in `dropped_blocks`; touched blocks beyond `M` in `touched_overflow`; samples
   outside the index in `out_of_bounds`.
2. **Integrate the touched blocks.** A loop over chunks of `integrate_chunk_blocks` slots (0: by the backend) of that
   list runs only as many times as there are touched blocks (the list is fixed-size, the trip count
   is not, so the cost follows the frame, not `M`). Every voxel centre of a chunk is projected into
   the image (gathers only) and updated with the standard projective TSDF rule:

       sdf = depth(u, v) - z_camera;  update iff depth valid and sdf >= -trunc
       tsdf <- (tsdf * w + min(sdf / trunc, 1)) / (w + 1)
       color <- (color * w + rgb(u, v)) / (w + 1)
       w <- min(w + 1, max_weight)

   so the weight counts observations until `max_weight` (255 by default), after which the running
   mean becomes an exponential moving average with factor 1 / (max_weight + 1). Values stay in [-1, 1].
   Whole blocks are written back with one row scatter per array and chunk.

Pass the state as a donated argument of the enclosing jit (`donate_argnums`) so that XLA updates the
pool in place; without donation each call copies the whole pool.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from fmfusion_jax.engine import _geometry as geo
from fmfusion_jax.engine.config import MapConfig, integrate_chunk_for_backend
from fmfusion_jax.engine.state import VoxelBlocks, voxel_offsets


class TouchedBlocks(NamedTuple):
    """Result of `find_touched_blocks`."""

    blocks: VoxelBlocks  # the pool with the frame's new blocks allocated and the counters updated
    slots: jax.Array  # int32[M]: pool slots of the touched blocks (the scratch slot where not valid)
    valid: jax.Array  # bool[M]: entry is a touched block that has a slot
    # shadows tuple.count, as the field's name is part of the API
    count: jax.Array  # type: ignore[assignment]  # int32[]: entries in use (valid ones lie in [0, count))


def _find_touched_blocks(blocks: VoxelBlocks, depth, T_world_camera, intrinsics, config: MapConfig) -> TouchedBlocks:
    """Implementation of `find_touched_blocks`."""
    T = geo.as_pose(T_world_camera)
    K = geo.as_intrinsics(intrinsics)
    stride, m = config.alloc_pixel_stride, config.max_touched_blocks
    num_grid = config.num_grid_blocks
    sx, sy, sz = config.grid_shape
    length = config.block_length

    d = depth[::stride, ::stride]
    xn, yn = geo.subsampled_rays(K, config, stride)
    ok_pixel = geo.valid_depth(d, config)
    n = config.alloc_depth_samples
    offsets = np.linspace(-config.sdf_trunc, config.sdf_trunc, n) if n > 1 else np.zeros(1)
    z = d[None] + jnp.asarray(offsets, jnp.float32)[:, None, None]  # (n, Ha, Wa)
    x, y, z = geo.camera_to_world(T, xn[None] * z, yn[None] * z, z)
    bx, by, bz = geo.index_floor((x, y, z), config, blocks.origin_block, length)
    inside = (bx >= 0) & (bx < sx) & (by >= 0) & (by < sy) & (bz >= 0) & (bz < sz)
    use = ok_pixel[None] & inside
    # computed once: the scatter-min, the representative test and the compaction all read it
    flat = geo.materialize(jnp.where(use, (bx * sy + by) * sz + bz, num_grid).reshape(-1))

    # Points outside the index: count each valid pixel whose measured point (the middle sample) is out.
    mid = n // 2
    out_of_bounds = jnp.sum(ok_pixel & ~inside[mid]).astype(jnp.int32)

    # Deduplicate: the smallest sample id of each block represents it (scatter-min over samples).
    num_samples = flat.shape[0]
    sample_id = jnp.arange(num_samples, dtype=jnp.int32)
    owner = jnp.full((num_grid,), num_samples, jnp.int32).at[flat].min(sample_id, mode="drop")
    is_rep = (flat < num_grid) & (owner[jnp.minimum(flat, num_grid - 1)] == sample_id)
    num_touched = jnp.sum(is_rep).astype(jnp.int32)
    rep, _ = geo.compact(jnp.full((m,), num_samples, jnp.int32), jnp.int32(0), is_rep, sample_id)  # as jnp.nonzero, faster
    # (M,) flat block ids (padding rep = num_samples: none; a select, not a copy of `flat` with a sentinel appended)
    touched = jnp.where(rep < num_samples, flat.at[rep].get(mode="clip"), num_grid)
    real = touched < num_grid

    # Allocate the new ones into the next free slots (slot B - 1 is never handed out).
    index_flat = blocks.block_index.reshape(-1)
    slot = jnp.where(real, index_flat[jnp.minimum(touched, num_grid - 1)], -1)
    new = real & (slot < 0)
    candidate = blocks.num_blocks + jnp.cumsum(new.astype(jnp.int32)) - 1
    granted = new & (candidate < config.dummy_slot)
    slot = jnp.where(granted, candidate, slot)
    index_flat = index_flat.at[jnp.where(granted, touched, num_grid)].set(candidate, mode="drop")
    coords = jnp.stack([touched // (sy * sz), (touched // sz) % sy, touched % sz], axis=-1).astype(jnp.int32)
    block_coords = blocks.block_coords.at[jnp.where(granted, candidate, config.block_capacity)].set(coords, mode="drop")
    blocks = blocks._replace(
        block_index=index_flat.reshape(config.grid_shape),
        block_coords=block_coords,
        num_blocks=blocks.num_blocks + jnp.sum(granted).astype(jnp.int32),
        dropped_blocks=blocks.dropped_blocks + jnp.sum(new & ~granted).astype(jnp.int32),
        out_of_bounds=blocks.out_of_bounds + out_of_bounds,
        touched_overflow=blocks.touched_overflow + jnp.maximum(num_touched - m, 0),
    )
    valid = slot >= 0
    slots = jnp.where(valid, slot, config.dummy_slot).astype(jnp.int32)
    return TouchedBlocks(blocks, slots, valid, jnp.minimum(num_touched, m))


def block_voxel_centres(blocks: VoxelBlocks, slots, config: MapConfig):
    """World coordinates `(x, y, z)` of every voxel centre of the given slots, each float32 `(M, V)`."""
    offsets = voxel_offsets(config.block_size)
    base = blocks.block_coords[slots] * config.block_size  # (M, 3)
    vs = config.voxel_size
    origin_voxels: list  # the origin's whole voxels: from the state (exact integers in float32) or the config
    if config.origin_on_lattice:
        origin_voxels = [(blocks.origin_block[a] * config.block_size).astype(jnp.float32) for a in range(3)]
    else:
        origin_voxels = [o / vs for o in config.grid_origin]
    # (world voxel + 0.5) * vs with the origin's whole voxels added first: the same centre whatever the
    # index's origin (see geo.lattice_floor)
    centre = [jnp.asarray(offsets[:, a] + 0.5, jnp.float32)[None] for a in range(3)]
    return tuple((base[:, a : a + 1] + centre[a] + origin_voxels[a]) * vs for a in range(3))


def _integrate_chunk(blocks: VoxelBlocks, slots, depth, color, T, K, config: MapConfig):
    """New (tsdf, weight, color) rows `(C, V[, 3])` of the given slots after one frame (color None: None)."""
    h, w = config.image_height, config.image_width
    x, y, z = block_voxel_centres(blocks, slots, config)
    xc, yc, zc = geo.world_to_camera(T, x, y, z)
    in_front = zc > 1e-6
    safe_z = jnp.where(in_front, zc, 1.0)
    u = jnp.round(K[0] * xc / safe_z + K[2]).astype(jnp.int32)
    v = jnp.round(K[1] * yc / safe_z + K[3]).astype(jnp.int32)
    # Values computed once (XLA would redo the projection in the depth gather and in each output, colour per
    # channel): each voxel's pixel (-1: outside the image), then that of each updated voxel. (The observation
    # is cheaper recomputed where it is read: computed once too, the step took 0.6 ms more a frame.)
    pixel = geo.materialize(jnp.where(in_front & (u >= 0) & (u < w) & (v >= 0) & (v < h), v * w + u, -1))
    d = depth.reshape(-1)[jnp.maximum(pixel, 0)]
    sdf = d - zc
    update = (pixel >= 0) & geo.valid_depth(d, config) & (sdf >= -config.sdf_trunc)
    pixel = geo.materialize(jnp.where(update, pixel, -1))
    observed = jnp.minimum(sdf / config.sdf_trunc, 1.0)
    update, pixel = pixel >= 0, jnp.maximum(pixel, 0)

    w_old = blocks.weight[slots]
    t_old = blocks.tsdf[slots]
    inv = 1.0 / (w_old + 1.0)
    t_new = jnp.where(update, jnp.clip((t_old * w_old + observed) * inv, -1.0, 1.0), t_old)
    w_new = jnp.where(update, jnp.minimum(w_old + 1.0, config.max_weight), w_old)
    if color is None:
        return t_new, w_new, None
    c_old = blocks.color[slots].astype(jnp.float32)  # stored in half precision, averaged in single
    rgb = color.reshape(-1, 3)[pixel].astype(jnp.float32)  # (C, V, 3); converted once gathered, not the image
    c_new = jnp.where(update[..., None], (c_old * w_old[..., None] + rgb) * inv[..., None], c_old).astype(blocks.color.dtype)
    return t_new, w_new, c_new


def _integrate_tsdf(blocks: VoxelBlocks, depth, color, T_world_camera, intrinsics, config: MapConfig) -> VoxelBlocks:
    depth = jnp.asarray(depth, jnp.float32)
    color = None if color is None else jnp.asarray(color)
    h, w = config.image_height, config.image_width
    if depth.shape != (h, w) or (color is not None and color.shape != (h, w, 3)):
        shown = None if color is None else color.shape
        raise ValueError(f"depth {depth.shape} / color {shown} do not match the config's {h}x{w} image")
    T = geo.as_pose(T_world_camera)
    K = geo.as_intrinsics(intrinsics)
    touched = _find_touched_blocks(blocks, depth, T, K, config)
    chunk = config.integrate_chunk_blocks or integrate_chunk_for_backend(jax.default_backend())
    total = config.max_touched_blocks

    def body(start, fresh, pool: VoxelBlocks) -> VoxelBlocks:
        size = min(chunk, total)
        slots = jax.lax.dynamic_slice_in_dim(touched.slots, start, size)
        ok = jax.lax.dynamic_slice_in_dim(touched.valid, start, size) & fresh
        slots = jnp.where(ok, slots, config.dummy_slot)  # rows of other chunks / padding: scratch slot
        t_new, w_new, c_new = _integrate_chunk(pool, slots, depth, color, T, K, config)
        # rows of padding (the scratch slot) are dropped, not written back: no second read of the old rows
        rows = jnp.where(ok, slots, config.block_capacity)
        pool = pool._replace(tsdf=pool.tsdf.at[rows].set(t_new, mode="drop"), weight=pool.weight.at[rows].set(w_new, mode="drop"))
        return pool if c_new is None else pool._replace(color=pool.color.at[rows].set(c_new, mode="drop"))

    blocks = geo.fold_chunks(touched.count, chunk, total, body, touched.blocks)
    stale = blocks.geometry_stale.at[jnp.where(touched.valid, touched.slots, config.block_capacity)].set(True, mode="drop")
    return blocks._replace(geometry_stale=stale)


@functools.partial(jax.jit, static_argnames=("config",))
def integrate_tsdf(blocks: VoxelBlocks, depth, color, T_world_camera, intrinsics, config: MapConfig) -> VoxelBlocks:
    """Integrate one RGB-D frame into the global TSDF (allocates blocks as needed).

    Args:
      blocks: the pool.
      depth: float32 `(H, W)` metres, 0 (or outside `[depth_min, depth_max]`) where invalid.
      color: uint8 (or float) `(H, W, 3)` RGB registered to the depth, or None: the geometry alone (the
        colours stay as they were; frame-to-model tracking's TSDF).
      T_world_camera: float32 `(4, 4)` camera-to-world pose.
      intrinsics: float32 `(4,)` = `(fx, fy, cx, cy)` of the depth camera, pixel centres at integers.
      config: static; `H, W` must equal `config.image_height, config.image_width`.

    Returns:
      The updated pool. Only the `M = max_touched_blocks` touched blocks are integrated; counters
      record blocks that did not fit (see the module docstring).
    """
    return _integrate_tsdf(blocks, depth, color, T_world_camera, intrinsics, config)


@functools.partial(jax.jit, static_argnames=("config",))
def find_touched_blocks(blocks: VoxelBlocks, depth, T_world_camera, intrinsics, config: MapConfig) -> TouchedBlocks:
    """Step 1 of `integrate_tsdf` alone: allocate the frame's blocks and list them (see module doc).

    Args:
      blocks: the pool.
      depth: float32 `(H, W)` metres, 0 where invalid.
      T_world_camera: float32 `(4, 4)` camera-to-world pose.
      intrinsics: float32 `(4,)` = `(fx, fy, cx, cy)`.
      config: static map config.

    Returns:
      `TouchedBlocks(blocks, slots int32[M], valid bool[M], count int32[])`.
    """
    return _find_touched_blocks(blocks, depth, T_world_camera, intrinsics, config)


integrate_tsdf_unjitted = _integrate_tsdf  # same function, for composing into a larger jitted step

__all__ = ["TouchedBlocks", "integrate_tsdf", "integrate_tsdf_unjitted", "find_touched_blocks", "block_voxel_centres"]
