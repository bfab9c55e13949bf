"""Raycast of the global TSDF into a camera: the model's depth, vertex and normal maps (KinectFusion's surface
prediction), the reference of frame-to-model tracking (`engine.tracking.track_frame`).

Every pixel's ray is marched from `depth_min` through the voxel-block pool a fixed number of times
(`lax.while_loop` bounded by `steps`: the compiled loop is the same for every frame; it ends early when every ray
is done). A step is sized by what the ray is in, looked up at the nearest voxel (one block-index and one pool
gather):

- a block that is not allocated holds no surface (blocks are allocated around every observed surface): the ray
  jumps to where it leaves the block;
- an observed voxel with `tsdf > 0` is at least about `tsdf * sdf_trunc` in front of the surface: the ray moves
  `SAFE_STEP` of that, and never less than `MIN_STEP_VOXELS` voxels (a projective TSDF may overstate the
  distance; a step of less than the truncation distance cannot pass through the negative band behind it);
- an allocated voxel that was never observed (weight 0) moves `SAFE_STEP` of the truncation distance.

A *guided* raycast (`guide_depth`, frame-to-model tracking's: the depth just fused) marches each ray only from
`GUIDE_BEFORE` truncation distances in front of its guide to one behind it, and casts the rays without a guide
whole when `unguided` is true and not at all otherwise: the loop then ends after a few samples instead of the
march of the slowest ray through the model.

A ray stops at the first sign change from an observed positive voxel to an observed negative one (a back face,
unobserved space into negative, is passed). The crossing is first placed linearly between the two nearest-voxel
samples, then by two Newton steps along the ray on the trilinear TSDF (kept within a voxel of the bracket; the
trilinear TSDF interpolates the observed ones of its 8 voxels), and the normal is the trilinear TSDF's gradient
there (central differences one voxel apart). Pixels whose ray finds no crossing before `depth_max` or within
`steps` samples, whose last Newton step started more than `NEAR_SURFACE_VOXELS` from the surface, or that lie on
a depth edge (a 4-neighbour invalid or more than `tracking.EDGE_STEP` of the depth away, as in `frame_maps`) are
invalid.

Shapes: `(H, W)` the image given by the static `height, width`; intrinsics float32 `(4,) = (fx, fy, cx, cy)` of
that image; poses float32 `(4, 4)` `T_world_camera`. The outputs are in the camera frame, as
`engine.tracking.frame_maps` gives them. Frame-to-model tracking (`engine.model_tracking`) takes the depth alone
(`with_normals=False`: no gradient samples) and makes its reference with `frame_maps`, normals from the depth map
as for a frame.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from fmfusion_jax.engine import _geometry as geo
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import VoxelBlocks
from fmfusion_jax.engine.tracking import EDGE_STEP

#: Share of the distance the TSDF promises that a step in front of the surface moves.
SAFE_STEP = 0.8
#: ... and the least step there, in voxels (near the surface the promised distance goes to zero).
MIN_STEP_VOXELS = 0.5
#: A trilinear sample is observed when its observed corners hold at least this share of the interpolation weight.
MIN_OBSERVED_WEIGHT = 0.5
#: A crossing is kept when the last Newton step started at most this many voxels (of TSDF) from the surface.
NEAR_SURFACE_VOXELS = 0.5
#: A guided ray (`guide_depth`) starts this many truncation distances in front of its guide.
GUIDE_BEFORE = 1.5
#: Newton steps along the ray on the trilinear TSDF that place the crossing found between two samples.
NEWTON_STEPS = 2


class Raycast(NamedTuple):
    """The model seen from a camera (zero where invalid)."""

    depth: jax.Array  # float32[H, W]: z of the surface in the camera frame (m)
    vertices: jax.Array  # float32[H, W, 3]: camera frame
    normals: jax.Array  # float32[H, W, 3]: unit, camera frame, facing the camera
    valid: jax.Array  # bool[H, W]


def _origin_voxels(blocks: VoxelBlocks, config: MapConfig) -> list:
    """The block index's origin in world voxel units, per axis (float32 scalars)."""
    if config.origin_on_lattice:
        return [(blocks.origin_block[a] * config.block_size).astype(jnp.float32) for a in range(3)]
    return [jnp.float32(o / config.voxel_size) for o in config.grid_origin]


def voxel_values(blocks: VoxelBlocks, gx, gy, gz, config: MapConfig):
    """`(tsdf, observed, allocated)` of index voxels `g` (int32 arrays of one shape): the stored tsdf where the
    voxel's block is allocated and its weight positive, else 1 (free) and False; whether its block is allocated."""
    slot, v, _ = geo.locate_voxels(blocks, gx, gy, gz, config)
    allocated = slot >= 0
    flat = jnp.where(allocated, slot, config.dummy_slot) * config.voxels_per_block + v
    weight = blocks.weight.reshape(-1)[flat]
    observed = allocated & (weight > 0)
    return jnp.where(observed, blocks.tsdf.reshape(-1)[flat], 1.0), observed, allocated


def trilinear_tsdf(blocks: VoxelBlocks, qx, qy, qz, config: MapConfig):
    """`(tsdf, gradient, observed)` at continuous index-voxel coordinates `q` (voxel `g`'s centre at `q = g + 0.5`),
    any common shape: the trilinear interpolation of the observed ones of the 8 surrounding voxel centres (their
    weights renormalised: at the border of what was seen, an unobserved corner would pull the value to "free"),
    its gradient (3 arrays, tsdf units per voxel), and observed where the observed corners hold at least
    `MIN_OBSERVED_WEIGHT` of the interpolation weight."""
    base = [qx - 0.5, qy - 0.5, qz - 0.5]
    g0 = [jnp.floor(b) for b in base]
    f = [b - g for b, g in zip(base, g0)]
    g0i = [g.astype(jnp.int32) for g in g0]
    total = jnp.zeros_like(qx)
    value = jnp.zeros_like(qx)
    gradient = [jnp.zeros_like(qx) for _ in range(3)]
    gradient_total = [jnp.zeros_like(qx) for _ in range(3)]
    for corner in range(8):
        d = [(corner >> 2) & 1, (corner >> 1) & 1, corner & 1]
        t, ok, _ = voxel_values(blocks, g0i[0] + d[0], g0i[1] + d[1], g0i[2] + d[2], config)
        w = [f[a] if d[a] else 1.0 - f[a] for a in range(3)]
        seen = ok.astype(qx.dtype)
        weight = w[0] * w[1] * w[2] * seen
        value = value + weight * t
        total = total + weight
        for a in range(3):  # d/dq_a of the corner's weight: +-1 along a times the other two
            others = [w[b] for b in range(3) if b != a]
            dw = (1.0 if d[a] else -1.0) * others[0] * others[1] * seen
            gradient[a] = gradient[a] + dw * t
            gradient_total[a] = gradient_total[a] + dw
    observed = total >= MIN_OBSERVED_WEIGHT
    safe = jnp.where(observed, total, 1.0)
    value = jnp.where(observed, value / safe, 1.0)
    # the quotient rule on (sum w t) / (sum w)
    gradient = [(g - value * gt) / safe for g, gt in zip(gradient, gradient_total)]
    return value, gradient, observed


def _march(blocks: VoxelBlocks, origin, direction, config: MapConfig, steps: int, guide=None, unguided=None):
    """The bracket `(t_before, t_after, f_before, f_after, hit)` of each ray's first positive-to-negative crossing:
    `t` in depth units, `f` the nearest voxels' tsdf there.

    `origin` (3 scalars) and `direction` (3 arrays `(N,)`, z-depth units: the point at depth `t` is `origin + t *
    direction`) are in index-voxel coordinates. `guide` `(N,)`: where positive, a depth the ray's surface is
    near (the frame just fused there): the ray is marched from `GUIDE_BEFORE` truncation distances in front of it
    to one behind it only; where 0, it is marched from `depth_min` to `depth_max` when `unguided` (bool scalar)
    and not at all otherwise (no crossing)."""
    vs, bs = config.voxel_size, config.block_size
    length = jnp.sqrt(direction[0] ** 2 + direction[1] ** 2 + direction[2] ** 2)  # voxels per unit of depth
    n = direction[0].shape[0]
    t0 = jnp.full((n,), config.depth_min, jnp.float32)
    t_max = jnp.full((n,), config.depth_max, jnp.float32)
    active0 = jnp.ones((n,), bool)
    if guide is not None:
        guided = guide > 0
        t0 = jnp.where(guided, jnp.maximum(config.depth_min, guide - GUIDE_BEFORE * config.sdf_trunc), t0)
        t_max = jnp.where(guided, jnp.minimum(config.depth_max, guide + config.sdf_trunc), t_max)
        active0 = guided | unguided
    trunc_voxels = config.sdf_trunc / vs
    inverse = [jnp.where(jnp.abs(d) > 1e-9, 1.0 / jnp.where(jnp.abs(d) > 1e-9, d, 1.0), jnp.inf) for d in direction]

    def sample(t):
        q = [origin[a] + t * direction[a] for a in range(3)]
        g = [jnp.floor(c).astype(jnp.int32) for c in q]
        tsdf, observed, allocated = voxel_values(blocks, *g, config)
        # where the ray leaves the voxel's block (an unallocated block is skipped whole)
        exits = []
        for a in range(3):
            low = jnp.floor(q[a] / bs) * bs
            wall = jnp.where(direction[a] > 0, low + bs, low)
            exits.append(jnp.where(jnp.isfinite(inverse[a]), (wall - q[a]) * inverse[a], jnp.inf))
        leave = jnp.minimum(jnp.minimum(exits[0], exits[1]), exits[2]) + 1e-3 / length
        free = jnp.where(observed, jnp.maximum(SAFE_STEP * tsdf * trunc_voxels, MIN_STEP_VOXELS), SAFE_STEP * trunc_voxels)
        step = jnp.where(allocated, free / length, leave)
        return tsdf, observed, step

    def cond(carry):
        i, _, _, _, _, active, _, _ = carry
        return (i < steps) & jnp.any(active)

    def body(carry):
        i, t, t_prev, f_prev, seen_prev, active, hit, f_hit = carry
        f, seen, step = sample(t)
        crossing = active & seen_prev & (f_prev > 0) & seen & (f <= 0)
        hit = hit | crossing
        f_hit = jnp.where(crossing, f, f_hit)
        active = active & ~crossing
        t_next = jnp.where(active, t + step, t)
        active = active & (t_next <= t_max)
        t_prev = jnp.where(active, t, t_prev)
        f_prev = jnp.where(active, f, f_prev)
        return i + 1, t_next, t_prev, f_prev, jnp.where(active, seen, seen_prev), active, hit, f_hit

    ones, no = jnp.ones((n,), jnp.float32), jnp.zeros((n,), bool)
    init = (jnp.int32(0), t0, t0, ones, no, active0, no, ones)
    _, t_after, t_before, f_before, _, _, hit, f_after = jax.lax.while_loop(cond, body, init)
    return t_before, t_after, f_before, f_after, hit


def _raycast(
    blocks: VoxelBlocks,
    T_world_camera,
    intrinsics,
    config: MapConfig,
    height: int,
    width: int,
    steps: int,
    with_normals: bool = True,
    guide_depth=None,
    unguided=True,
) -> Raycast:
    T = geo.as_pose(T_world_camera)
    K = geo.as_intrinsics(intrinsics)
    vs = config.voxel_size
    u = jnp.tile(jnp.arange(width, dtype=jnp.float32), height)
    v = jnp.repeat(jnp.arange(height, dtype=jnp.float32), width)
    xn, yn = (u - K[2]) / K[0], (v - K[3]) / K[1]
    one = jnp.ones_like(xn)
    # ray directions per unit of depth, in world voxels; the camera centre in index-voxel coordinates
    direction = [(T[a, 0] * xn + T[a, 1] * yn + T[a, 2] * one) / vs for a in range(3)]
    base = _origin_voxels(blocks, config)
    origin = [T[a, 3] / vs - base[a] for a in range(3)]
    guide = None if guide_depth is None else jnp.asarray(guide_depth, jnp.float32).reshape(-1)
    t_before, t_after, f_before, f_after, hit = _march(blocks, origin, direction, config, steps, guide, unguided)

    # the crossing between the nearest voxels' samples, then two Newton steps along the ray on the trilinear TSDF
    # (the nearest samples place it to about half a voxel); the normal is the trilinear gradient at the last one
    depth = t_before + (t_after - t_before) * f_before / jnp.where(hit, f_before - f_after, 1.0)
    # the trilinear crossing may lie up to about a voxel outside the nearest samples' bracket
    voxel = 1.0 / jnp.sqrt(direction[0] ** 2 + direction[1] ** 2 + direction[2] ** 2)
    low, high = t_before - voxel, t_after + voxel

    def newton(_, carry):
        depth, ok, _ = carry
        q = [origin[a] + depth * direction[a] for a in range(3)]
        f, gradient, seen = trilinear_tsdf(blocks, q[0], q[1], q[2], config)
        slope = gradient[0] * direction[0] + gradient[1] * direction[1] + gradient[2] * direction[2]  # df / dt
        ok = ok & seen & (slope < 0)
        return jnp.clip(depth - f / jnp.where(ok, slope, -1.0), low, high), ok, f

    # a loop, not unrolled: one copy of the trilinear lookups in the compiled step
    depth, ok, f = jax.lax.fori_loop(0, NEWTON_STEPS, newton, (depth, hit, jnp.zeros_like(depth)))
    # the last Newton step started near the surface (else the ray left the bracket: an edge, a thin part)
    ok = ok & (jnp.abs(f) * config.sdf_trunc <= NEAR_SURFACE_VOXELS * config.voxel_size)
    if with_normals:
        # the normal: central differences of the trilinear TSDF one voxel apart (the gradient inside one cell is
        # noisier: 2.8 degrees off the rendered normals against 1.1 after five frames)
        q = [origin[a] + depth * direction[a] for a in range(3)]
        # the six samples in one call, `(6, N)`: one voxel ahead along x, y, z, then behind (one copy of the
        # trilinear lookups in the compiled step instead of six; the same points, normals equal to float32 rounding)
        offsets = np.vstack([np.eye(3, dtype=np.float32), -np.eye(3, dtype=np.float32)])[:, :, None]  # (6, 3, 1)
        six = [q[a][None] + offsets[:, a] for a in range(3)]
        f_six, _, ok_six = trilinear_tsdf(blocks, six[0], six[1], six[2], config)
        gradient = [f_six[a] - f_six[3 + a] for a in range(3)]
        ok = ok & jnp.all(ok_six, axis=0)
        normal_world = jnp.stack(gradient, axis=-1)
        norm = jnp.linalg.norm(normal_world, axis=-1)
        ok = ok & (norm > 1e-6)
        normal_world = normal_world / jnp.where(ok, norm, 1.0)[:, None]
    depth = jnp.where(ok, depth, 0.0)
    vertex = jnp.stack([xn * depth, yn * depth, depth], axis=-1)
    if with_normals:
        normal = normal_world @ T[:3, :3]  # R^T n, row-wise
        normal = jnp.where(jnp.sum(normal * vertex, axis=-1, keepdims=True) > 0, -normal, normal)
    else:
        normal = jnp.zeros_like(vertex)
    # no vertex at a depth edge, as `frame_maps` has none there: a silhouette's voxels blur it by a voxel or two
    depth = depth.reshape(height, width)
    padded = jnp.pad(depth, 1)
    ok = ok.reshape(height, width)
    for other in (padded[1:-1, 2:], padded[1:-1, :-2], padded[2:, 1:-1], padded[:-2, 1:-1]):
        ok = ok & (other > 0) & (jnp.abs(other - depth) <= EDGE_STEP * depth)
    vertex, normal = vertex.reshape(height, width, 3), normal.reshape(height, width, 3)
    zero = jnp.zeros_like(vertex)
    return Raycast(
        jnp.where(ok, depth, 0.0),
        jnp.where(ok[..., None], vertex, zero),
        jnp.where(ok[..., None], normal, zero),
        ok,
    )


@functools.partial(jax.jit, static_argnames=("config", "height", "width", "steps"))
def raycast_tsdf(
    blocks: VoxelBlocks, T_world_camera, intrinsics, config: MapConfig, height: int, width: int, steps: int = 96
) -> Raycast:
    """The model's surface seen from a camera (see the module docstring).

    Args:
      blocks: the pool (the global TSDF of `config`'s lattice).
      T_world_camera: float32 `(4, 4)`.
      intrinsics: float32 `(4,)` `(fx, fy, cx, cy)` of the `(height, width)` image.
      config, height, width, steps: static; `steps` bounds the samples per ray.
    """
    return _raycast(blocks, T_world_camera, intrinsics, config, height, width, steps)


raycast_tsdf_unjitted = _raycast  # the same function, for composing into a larger jitted step

__all__ = ["Raycast", "raycast_tsdf", "raycast_tsdf_unjitted", "trilinear_tsdf", "voxel_values"]
