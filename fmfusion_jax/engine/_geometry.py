"""Small jittable geometry helpers shared by the TSDF and instance kernels (private).

Point transforms are written out as scalar multiply-adds over coordinate arrays: on this CPU a
`(N, 3) @ (3, 3)` matmul was several times slower than nine fused multiply-adds.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import VoxelBlocks, local_voxel_index


def camera_to_world(T, x, y, z):
    """`T_world_camera` applied to camera-frame coordinate arrays `x, y, z` (any common shape)."""
    return (
        T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3],
        T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3],
        T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3],
    )


def world_to_camera(T, x, y, z):
    """Inverse of `camera_to_world` for a rigid `T_world_camera`: `R^T (p - t)`."""
    dx, dy, dz = x - T[0, 3], y - T[1, 3], z - T[2, 3]
    return (
        T[0, 0] * dx + T[1, 0] * dy + T[2, 0] * dz,
        T[0, 1] * dx + T[1, 1] * dy + T[2, 1] * dz,
        T[0, 2] * dx + T[1, 2] * dy + T[2, 2] * dz,
    )


def pixel_grid(config: MapConfig, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Full-resolution pixel coordinates `(u, v)` (float32 `(Hs, Ws)`) of the stride-subsampled grid."""
    v, u = np.meshgrid(
        np.arange(0, config.image_height, stride, dtype=np.float32),
        np.arange(0, config.image_width, stride, dtype=np.float32),
        indexing="ij",
    )
    return u, v


def subsampled_rays(intrinsics, config: MapConfig, stride: int):
    """Normalised rays `(x/z, y/z)` of the subsampled pixel grid, each float32 `(Hs, Ws)`."""
    u, v = pixel_grid(config, stride)
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    return (u - cx) / fx, (v - cy) / fy


def valid_depth(d, config: MapConfig):
    """bool mask of usable depth readings."""
    return (d >= config.depth_min) & (d <= config.depth_max)


def lattice_floor(x, origin: float, step: float):
    """int32 `floor((x - origin) / step)`, elementwise.

    With `origin` a whole number of steps (`MapConfig.for_bounds` puts the index origin on whole blocks), it
    is computed as `floor(x / step) - origin / step`: the floor sees `x / step` alone, so a point falls in the
    same world cell whatever the index's origin, and a grown map equals one allocated at its final size.
    """
    cells = origin / step
    if abs(cells - round(cells)) < 1e-9:
        return jnp.floor(x / step).astype(jnp.int32) - int(round(cells))
    return jnp.floor((x - origin) / step).astype(jnp.int32)


def index_floor(coords, config: MapConfig, origin_block, step: float):
    """int32 `floor((c - origin) / step)` for the three world coordinates `coords` against the block index's
    origin: the state's `origin_block` (int32[3], whole blocks) when `config.origin_on_lattice` (the compiled
    step then holds no origin), else the config's (compiled in). `step` is the voxel or the block length."""
    if config.origin_on_lattice:
        per_block = int(round(config.block_length / step))
        return tuple(jnp.floor(c / step).astype(jnp.int32) - origin_block[a] * per_block for a, c in enumerate(coords))
    return tuple(lattice_floor(c, config.grid_origin[a], step) for a, c in enumerate(coords))


def world_to_voxel(x, y, z, config: MapConfig, origin_block):
    """Integer global voxel coordinates of world points (floor; see `index_floor`)."""
    return index_floor((x, y, z), config, origin_block, config.voxel_size)


def locate_voxels(blocks: VoxelBlocks, gx, gy, gz, config: MapConfig):
    """Pool address of global voxels.

    Returns `(slot, v, inside)`: `slot` int32 (-1 where the block is outside the index or not
    allocated), `v` the voxel's index inside its block, `inside` whether the block is inside the index.
    Power-of-two blocks (the default 8) use shifts and masks: the floor divisions and remainders of the
    generic path (sign fix-ups included) were a large part of a per-pixel or per-ray lookup's cost on the CPU.
    """
    bs = config.block_size
    sx, sy, sz = config.grid_shape
    if bs & (bs - 1):
        bx, by, bz = gx // bs, gy // bs, gz // bs  # floor division, also for negatives
        v = local_voxel_index(gx - bx * bs, gy - by * bs, gz - bz * bs, bs)
    else:
        shift = bs.bit_length() - 1
        bx, by, bz = gx >> shift, gy >> shift, gz >> shift  # arithmetic shift: floor division, negatives too
        x, y, z = gx & (bs - 1), gy & (bs - 1), gz & (bs - 1)  # floor remainder
        c = bs // 2  # local_voxel_index (2x2x2-cell order) with shifts
        v = (((x >> 1) * c + (y >> 1)) * c + (z >> 1)) * 8 + (x & 1) * 4 + (y & 1) * 2 + (z & 1)
    inside = (bx >= 0) & (bx < sx) & (by >= 0) & (by < sy) & (bz >= 0) & (bz < sz)
    flat = jnp.where(inside, (bx * sy + by) * sz + bz, 0)  # in bounds: outside blocks read entry 0
    slot = jnp.where(inside, blocks.block_index.reshape(-1).at[flat].get(mode="promise_in_bounds"), -1)
    return slot, v, inside


def as_pose(T_world_camera) -> jax.Array:
    return jnp.asarray(T_world_camera, jnp.float32)


def as_intrinsics(intrinsics) -> jax.Array:
    return jnp.asarray(intrinsics, jnp.float32)


def fold_chunks(count, chunk: int, total: int, body, carry):
    """Run `body(start, fresh, carry) -> carry` over fixed-size chunks covering rows `[0, count)`.

    `count` may be traced (the loop runs `ceil(count / chunk)` times, so the cost follows the data,
    not the capacity `total`); `chunk` and `total` are static. A chunk is the row range
    `[start, start + chunk)` with `start` clamped so that it stays inside `total`; `fresh` (bool
    `(chunk,)`) marks the rows of the range that belong to this chunk and are `< count`, so that rows
    seen by an earlier (clamped) chunk are not processed twice.
    """
    chunk = max(1, min(int(chunk), int(total)))
    count = jnp.minimum(jnp.asarray(count, jnp.int32), total)
    num_chunks = (count + chunk - 1) // chunk
    rows = jnp.arange(chunk, dtype=jnp.int32)

    def step(i, carry):
        begin = i * chunk
        start = jnp.minimum(begin, total - chunk)
        index = start + rows
        return body(start, (index >= begin) & (index < count), carry)

    return jax.lax.fori_loop(0, num_chunks, step, carry)


def as_words(x: jax.Array) -> jax.Array | None:
    """`x[..., W]` (1- or 2-byte elements, bools as bytes) read as uint32 words `[..., W * itemsize / 4]`, or None
    when its rows are not whole words. On the CPU, XLA reduces and compares these 2-4x faster than the narrow
    elements (a bool sum even went through a materialized int32 copy)."""
    if x.dtype == jnp.bool_:
        x = x.astype(jnp.uint8)
    per_word = 4 // x.dtype.itemsize
    if x.dtype.itemsize > 2 or x.shape[-1] % per_word:
        return None
    return jax.lax.bitcast_convert_type(x.reshape(*x.shape[:-1], x.shape[-1] // per_word, per_word), jnp.uint32)


def materialize(x: jax.Array) -> jax.Array:
    """`x`, computed once into a buffer of its own: the operand of a one-element scatter (which XLA never fuses
    away; `lax.optimization_barrier` did not stop the recomputation).

    XLA's CPU fusion inlines an elementwise producer into each consumer; a producer that is costly per
    element (gathers, long select chains) and read several times, or through a concatenate (`jnp.stack`
    evaluates each operand's whole chain per output element), is then computed several times over. Here it
    is computed once, into the scatter's buffer (an identity scatter of every element into zeros, as before,
    also cost a fill, a copy and a scalar pass).
    """
    flat = x.reshape(-1)
    if flat.shape[0] == 0:
        return x
    # the scatter's operand is a buffer XLA must fill; rewriting one element in place costs nothing more
    return flat.at[jnp.zeros((1,), jnp.int32)].set(flat[:1], unique_indices=True, indices_are_sorted=True).reshape(x.shape)


def inclusive_cumsum(x: jax.Array, width: int = 16) -> jax.Array:
    """Inclusive prefix sum of a 1-D int32 array, in two levels: within rows of `width`, then of the row
    totals. On the CPU this was ~3x faster than one `jnp.cumsum` over the whole array (and
    `jnp.nonzero`, built on two of them, was the main cost of listing cells); an unrolled version was
    faster still but took a second to compile."""
    n = x.shape[0]
    if n <= width:
        return jnp.cumsum(x)
    m = -(-n // width)
    rows = jnp.cumsum(jnp.pad(x, (0, m * width - n)).reshape(m, width), axis=1)
    totals = rows[:, -1]
    return (rows + (jnp.cumsum(totals) - totals)[:, None]).reshape(-1)[:n]


def compact(out: jax.Array, found, flags: jax.Array, values: jax.Array):
    """Writes `values[flags]` (in order) into the list `out` from position `found`; returns `(out, found')`.

    Entries past the end of `out` are dropped (and still counted in `found'`). One scatter of
    `len(flags)` updates.
    """
    flags = flags.reshape(-1)
    ones = flags.astype(jnp.int32)
    position = found + inclusive_cumsum(ones) - 1
    target = jnp.where(flags, position, out.shape[0])
    out = out.at[target].set(values.reshape(-1), mode="drop")
    return out, found + jnp.sum(ones)
