"""Plain NumPy references of the geometry kernels, and an analytic box-room scene (test oracles).

Everything here is written for clarity, not speed: dense voxel grids over the whole block index,
float64 arithmetic, Python loops over pixels where that is the obvious formulation. The jitted
kernels in `tsdf` and `instance_volume` must agree with these (up to float32 rounding at voxel and
pixel boundaries).

Dense grids are indexed by global voxel coordinate `(gx, gy, gz)` in
`[0, grid_shape * block_size)`, voxel centre `grid_origin + (g + 0.5) * voxel_size`.
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict

import numpy as np

from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import VoxelBlocks, voxel_offsets

# --------------------------------------------------------------------------------------------------
# Pool <-> dense grids.


@dataclasses.dataclass
class DenseGrid:
    """The map as dense NumPy arrays over the whole block index (voxel resolution)."""

    tsdf: np.ndarray  # float (X, Y, Z), 1 where unallocated
    weight: np.ndarray  # float (X, Y, Z)
    color: np.ndarray  # float (X, Y, Z, 3)
    instance_id: np.ndarray  # int (X, Y, Z, S)
    instance_weight: np.ndarray  # float (X, Y, Z, S)
    allocated: np.ndarray  # bool (X, Y, Z): the voxel's block is allocated


def dense_shape(config: MapConfig) -> tuple[int, int, int]:
    return tuple(int(s) * config.block_size for s in config.grid_shape)


def empty_dense(config: MapConfig) -> DenseGrid:
    shape = dense_shape(config)
    s = config.instance_slots
    return DenseGrid(
        tsdf=np.ones(shape),
        weight=np.zeros(shape),
        color=np.zeros(shape + (3,)),
        instance_id=np.full(shape + (s,), -1, np.int64),
        instance_weight=np.zeros(shape + (s,)),
        allocated=np.zeros(shape, bool),
    )


def blocks_to_dense(blocks: VoxelBlocks, config: MapConfig) -> DenseGrid:
    """Scatter the allocated blocks of a pool into dense grids."""
    grid = empty_dense(config)
    n = int(blocks.num_blocks)
    coords = np.asarray(blocks.block_coords)[:n]
    offsets = voxel_offsets(config.block_size)
    g = coords[:, None, :] * config.block_size + offsets[None]  # (n, V, 3)
    ix, iy, iz = g[..., 0], g[..., 1], g[..., 2]
    grid.tsdf[ix, iy, iz] = np.asarray(blocks.tsdf)[:n]
    grid.weight[ix, iy, iz] = np.asarray(blocks.weight)[:n]
    grid.color[ix, iy, iz] = np.asarray(blocks.color)[:n]
    grid.instance_id[ix, iy, iz] = np.asarray(blocks.instance_id)[:n]
    grid.instance_weight[ix, iy, iz] = np.asarray(blocks.instance_weight)[:n]
    grid.allocated[ix, iy, iz] = True
    return grid


def dense_to_blocks(grid: DenseGrid, config: MapConfig) -> VoxelBlocks:
    """A pool holding every block of `grid` that has an allocated voxel (slots in raster order)."""
    import jax.numpy as jnp

    from fmfusion_jax.engine.state import init_voxel_blocks

    bs = config.block_size
    gx, gy, gz = config.grid_shape
    alloc_blocks = grid.allocated.reshape(gx, bs, gy, bs, gz, bs).any(axis=(1, 3, 5))
    coords = np.argwhere(alloc_blocks).astype(np.int32)
    n = len(coords)
    if n > config.block_capacity - 1:
        raise ValueError(f"{n} blocks do not fit a pool of {config.block_capacity} (one scratch slot)")
    offsets = voxel_offsets(bs)
    g = coords[:, None, :] * bs + offsets[None]
    ix, iy, iz = g[..., 0], g[..., 1], g[..., 2]
    blocks = init_voxel_blocks(config)
    index = np.full(config.grid_shape, -1, np.int32)
    index[coords[:, 0], coords[:, 1], coords[:, 2]] = np.arange(n, dtype=np.int32)

    def put(array, values):
        out = np.array(array)
        out[:n] = values
        return jnp.asarray(out)

    return blocks._replace(
        block_index=jnp.asarray(index),
        block_coords=put(blocks.block_coords, coords),
        num_blocks=jnp.asarray(n, jnp.int32),
        tsdf=put(blocks.tsdf, grid.tsdf[ix, iy, iz]),
        weight=put(blocks.weight, grid.weight[ix, iy, iz]),
        color=put(blocks.color, grid.color[ix, iy, iz]),
        instance_id=put(blocks.instance_id, grid.instance_id[ix, iy, iz]),
        instance_weight=put(blocks.instance_weight, grid.instance_weight[ix, iy, iz]),
    )


def voxel_centres(config: MapConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World coordinates of every dense voxel centre, three float64 `(X, Y, Z)` arrays."""
    axes = [config.grid_origin[a] + (np.arange(n) + 0.5) * config.voxel_size for a, n in enumerate(dense_shape(config))]
    return np.meshgrid(*axes, indexing="ij")


# --------------------------------------------------------------------------------------------------
# TSDF.


def reference_integrate_tsdf(grid: DenseGrid, depth, color, T_world_camera, intrinsics, config: MapConfig, region=None):
    """Projective TSDF update of every voxel of `region` (bool dense mask; default: all voxels).

    Same rule as `tsdf.integrate_tsdf`: nearest pixel, update iff the depth is valid and
    sdf = depth - z >= -trunc; tsdf, colour running means; weight + 1 capped at max_weight.
    Modifies and returns `grid`.
    """
    fx, fy, cx, cy = (float(x) for x in intrinsics)
    T = np.asarray(T_world_camera, np.float64)
    h, w = depth.shape
    x, y, z = voxel_centres(config)
    p = np.stack([x, y, z], -1) - T[:3, 3]
    pc = p @ T[:3, :3]  # R^T (p - t)
    zc = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.round(fx * pc[..., 0] / zc + cx)
        v = np.round(fy * pc[..., 1] / zc + cy)
    inside = (zc > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    ui = np.where(inside, u, 0).astype(int)
    vi = np.where(inside, v, 0).astype(int)
    d = np.where(inside, depth[vi, ui], 0.0)
    sdf = d - zc
    update = inside & (d >= config.depth_min) & (d <= config.depth_max) & (sdf >= -config.sdf_trunc)
    if region is not None:
        update &= region
    obs = np.minimum(sdf / config.sdf_trunc, 1.0)
    w0 = grid.weight
    grid.tsdf = np.where(update, np.clip((grid.tsdf * w0 + obs) / (w0 + 1), -1, 1), grid.tsdf)
    rgb = color[vi, ui].astype(np.float64)
    grid.color = np.where(update[..., None], (grid.color * w0[..., None] + rgb) / (w0[..., None] + 1), grid.color)
    grid.weight = np.where(update, np.minimum(w0 + 1, config.max_weight), w0)
    return grid


# --------------------------------------------------------------------------------------------------
# Instances.


def subsampled_pixel_points(depth, T_world_camera, intrinsics, config: MapConfig, offset_voxels: float = 0.0):
    """Per subsampled pixel: valid flag and the global voxel of the depth point moved along the ray."""
    fx, fy, cx, cy = (float(x) for x in intrinsics)
    T = np.asarray(T_world_camera, np.float64)
    s = config.pixel_stride
    d = np.asarray(depth, np.float64)[::s, ::s]
    v, u = np.meshgrid(np.arange(0, config.image_height, s), np.arange(0, config.image_width, s), indexing="ij")
    xn, yn = (u - cx) / fx, (v - cy) / fy
    ok = (d >= config.depth_min) & (d <= config.depth_max)
    d = d + offset_voxels * config.voxel_size / np.sqrt(xn**2 + yn**2 + 1)
    pc = np.stack([xn * d, yn * d, d], -1)
    pw = pc @ T[:3, :3].T + T[:3, 3]
    g = np.floor((pw - np.asarray(config.grid_origin)) / config.voxel_size).astype(np.int64)
    inside = np.all((g >= 0) & (g < np.asarray(dense_shape(config))), axis=-1)
    return ok & inside, g


def reference_pixel_instances(grid: DenseGrid, depth, T_world_camera, intrinsics, config: MapConfig) -> np.ndarray:
    """Per subsampled pixel: union of the ids at the probed voxels, by summed weight, first seen first."""
    probes = [subsampled_pixel_points(depth, T_world_camera, intrinsics, config, o) for o in config.instance_lookup_offsets]
    hs, ws = probes[0][0].shape
    s = config.instance_slots
    out = np.full((hs, ws, s), -1, np.int64)
    for r in range(hs):
        for c in range(ws):
            total: dict[int, float] = {}
            for ok, g in probes:
                if not ok[r, c]:
                    continue
                x, y, z = g[r, c]
                if not grid.allocated[x, y, z]:
                    continue
                for k in range(s):
                    i = int(grid.instance_id[x, y, z, k])
                    if i >= 0:
                        total[i] = total.get(i, 0.0) + float(grid.instance_weight[x, y, z, k])
            # dicts keep first-insertion order; a stable sort by weight keeps it among ties
            ranked = sorted(total.items(), key=lambda item: -item[1])[:s]
            for k, (i, _) in enumerate(ranked):
                out[r, c, k] = i
    return out


def reference_apply_hits(
    grid: DenseGrid, voxels, instances, detected=None, neutral=None, contrary_weight: float = 0.0
) -> DenseGrid:
    """The slot update rule of `instance_volume` for explicit votes (global voxel, instance).

    `voxels` int `(N, 3)` global voxel coordinates (votes in unallocated voxels are dropped),
    `instances` int `(N,)` (-1 = no instance). With `contrary_weight > 0`, every vote on an allocated
    voxel that is not `neutral` also takes `contrary_weight` from each slot whose instance is in
    `detected` (a set of ids) and is not the vote's own. Modifies and returns `grid`.
    """
    before_ids = grid.instance_id.copy()
    before_w = grid.instance_weight.copy()
    detected = set() if detected is None else set(int(i) for i in detected)
    neutral = np.zeros(len(instances), bool) if neutral is None else np.asarray(neutral, bool)
    claims: dict[tuple, list[int]] = defaultdict(list)  # (voxel, slot) -> claiming ids
    votes: dict[tuple, float] = defaultdict(float)  # (voxel, slot) -> net weight change of matches
    lowered: dict[tuple, float] = defaultdict(float)  # (voxel, slot) -> decays and contrary votes
    for (x, y, z), inst, quiet in zip(np.asarray(voxels).tolist(), np.asarray(instances).tolist(), neutral):
        if not grid.allocated[x, y, z]:
            continue
        ids = list(before_ids[x, y, z])
        if contrary_weight > 0 and not quiet:
            for k, other in enumerate(ids):
                if other >= 0 and other != inst and other in detected:
                    lowered[(x, y, z, k)] += contrary_weight
        if inst < 0:
            continue
        if inst in ids:
            votes[(x, y, z, ids.index(inst))] += 1
        elif -1 in ids:
            claims[(x, y, z, ids.index(-1))].append(inst)
        else:
            weakest = min(range(len(ids)), key=lambda k: (before_w[x, y, z, k], k))
            lowered[(x, y, z, weakest)] += 1
    for (x, y, z, k), claimants in claims.items():
        winner = max(claimants)
        grid.instance_id[x, y, z, k] = winner
        grid.instance_weight[x, y, z, k] = claimants.count(winner)
    for (x, y, z, k), n in votes.items():
        grid.instance_weight[x, y, z, k] += n
    for (x, y, z, k), n in lowered.items():
        grid.instance_weight[x, y, z, k] -= n
    for x, y, z, k in lowered:  # emptied once every vote of the frame is in
        if grid.instance_weight[x, y, z, k] <= 0:
            grid.instance_weight[x, y, z, k] = 0
            grid.instance_id[x, y, z, k] = -1
    return grid


def reference_integrate_instances(
    grid: DenseGrid,
    depth,
    T_world_camera,
    intrinsics,
    pixel_instance,
    config: MapConfig,
    detected=None,
    neutral=None,
    contrary_weight: float = 0.0,
) -> DenseGrid:
    """Each subsampled pixel votes its instance into its surface voxel (see `reference_apply_hits`)."""
    ok, g = subsampled_pixel_points(depth, T_world_camera, intrinsics, config, 0.0)
    g = g.reshape(-1, 3)
    ok = ok.reshape(-1)
    inst = np.asarray(pixel_instance).reshape(-1)[ok]
    quiet = None if neutral is None else np.asarray(neutral, bool).reshape(-1)[ok]
    return reference_apply_hits(grid, g[ok], inst, detected, quiet, contrary_weight)


def reference_overlap_counts(grid: DenseGrid, num_instances: int, inflate: bool) -> np.ndarray:
    """`counts[a, b]`: b's voxels inside a's volume (plain) or inside a's 2x2x2 coarse cells (inflated)."""
    voxels: dict[int, set] = defaultdict(set)
    for x, y, z, k in np.argwhere(grid.instance_id >= 0):
        voxels[int(grid.instance_id[x, y, z, k])].add((int(x), int(y), int(z)))
    counts = np.zeros((num_instances, num_instances), np.int64)
    for a, va in voxels.items():
        cells_a = {(x // 2, y // 2, z // 2) for x, y, z in va}
        for b, vb in voxels.items():
            if inflate:
                counts[a, b] = sum((x // 2, y // 2, z // 2) in cells_a for x, y, z in vb)
            else:
                counts[a, b] = len(va & vb)
    return counts


# --------------------------------------------------------------------------------------------------
# An analytic scene: a box room with box furniture and a sphere.


@dataclasses.dataclass(frozen=True)
class BoxRoom:
    """Interior of an axis-aligned room, axis-aligned boxes and spheres inside it (metres, world frame).

    Surface labels (per pixel): 0 floor (z = lo), 1 ceiling, 2..5 walls (-x, +x, -y, +y),
    6 + i box i, 6 + len(boxes) + j sphere j; -1 no hit.
    """

    lo: tuple[float, float, float] = (0.0, 0.0, 0.0)
    hi: tuple[float, float, float] = (4.0, 3.5, 2.5)
    boxes: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = (
        ((0.6, 0.5, 0.0), (1.4, 1.3, 0.75)),
        ((2.6, 2.2, 0.0), (3.4, 3.1, 1.1)),
    )
    spheres: tuple[tuple[tuple[float, float, float], float], ...] = (((2.0, 1.2, 0.9), 0.35),)

    def signed_distance(self, p: np.ndarray) -> np.ndarray:
        """Signed distance of points `(..., 3)` to the scene surface, positive in free space."""
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        sdf = np.min(np.concatenate([p - lo, hi - p], -1), -1)  # inside the room: distance to the walls
        for blo, bhi in self.boxes:
            blo, bhi = np.asarray(blo), np.asarray(bhi)
            q = np.maximum(blo - p, p - bhi)
            outside = np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)
            sdf = np.minimum(sdf, outside)
        for centre, radius in self.spheres:
            sdf = np.minimum(sdf, np.linalg.norm(p - np.asarray(centre), axis=-1) - radius)
        return sdf

    def render(self, T_world_camera, intrinsics, height: int, width: int):
        """Ray-cast depth (float32 z-depth, metres), colour (uint8 RGB) and surface labels (int32)."""
        fx, fy, cx, cy = (float(x) for x in intrinsics)
        T = np.asarray(T_world_camera, np.float64)
        v, u = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
        rays_c = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u, float)], -1)  # z = 1
        dirs = rays_c @ T[:3, :3].T
        origin = T[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / dirs
            # room interior: exit distance through the nearest wall
            t_lo = (np.asarray(self.lo) - origin) * inv
            t_hi = (np.asarray(self.hi) - origin) * inv
            t_exit = np.where(dirs > 0, t_hi, np.where(dirs < 0, t_lo, np.inf))
            t = np.min(t_exit, -1)
            axis = np.argmin(t_exit, -1)
            positive = np.take_along_axis(dirs, axis[..., None], -1)[..., 0] > 0
            # labels: z axis -> floor/ceiling (0/1), x -> 2/3, y -> 4/5
            label = np.select([axis == 2, axis == 0, axis == 1], [0 + positive, 2 + positive, 4 + positive])
            for i, (blo, bhi) in enumerate(self.boxes):
                t0 = (np.asarray(blo) - origin) * inv
                t1 = (np.asarray(bhi) - origin) * inv
                t_near = np.max(np.minimum(t0, t1), -1)
                t_far = np.min(np.maximum(t0, t1), -1)
                hit = (t_near <= t_far) & (t_near > 1e-6) & (t_near < t)
                t = np.where(hit, t_near, t)
                label = np.where(hit, 6 + i, label)
            for j, (centre, radius) in enumerate(self.spheres):
                oc = origin - np.asarray(centre)
                a = np.sum(dirs * dirs, -1)
                b = 2 * np.sum(dirs * oc, -1)
                c = oc @ oc - radius**2
                disc = b * b - 4 * a * c
                t_s = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
                hit = (disc >= 0) & (t_s > 1e-6) & (t_s < t)
                t = np.where(hit, t_s, t)
                label = np.where(hit, 6 + len(self.boxes) + j, label)
        depth = np.where(np.isfinite(t), t, 0.0).astype(np.float32)  # rays have z = 1: t is z-depth
        points = origin + dirs * depth[..., None]
        color = (
            np.stack(
                [
                    127 + 100 * np.sin(3 * points[..., 0]),
                    127 + 100 * np.sin(3 * points[..., 1] + 1),
                    127 + 100 * np.cos(2 * points[..., 2]),
                ],
                -1,
            )
            .clip(0, 255)
            .astype(np.uint8)
        )
        return depth, color, label.astype(np.int32)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """`T_world_camera` (float64 4x4) of an OpenCV camera (x right, y down, z forward) at `eye`."""
    eye, target, up = (np.asarray(x, np.float64) for x in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def scannet_like_intrinsics(width: int = 640, height: int = 480) -> np.ndarray:
    """`(fx, fy, cx, cy)` of a ScanNet-like depth camera scaled to `width x height` (float32)."""
    sx, sy = width / 640.0, height / 480.0
    return np.array([577.87 * sx, 577.87 * sy, (319.5 + 0.5) * sx - 0.5, (239.5 + 0.5) * sy - 0.5], np.float32)


def orbit_poses(room: BoxRoom, n: int, radius: float = 1.2, height: float = 1.4, seed: int = 0) -> list[np.ndarray]:
    """`n` camera poses circling the room centre, looking at points near the middle of the room."""
    rng = np.random.default_rng(seed)
    centre = (np.asarray(room.lo) + np.asarray(room.hi)) / 2
    poses = []
    for i in range(n):
        angle = 2 * np.pi * i / max(n, 1) + rng.uniform(-0.2, 0.2)
        eye = centre + np.array([radius * np.cos(angle), radius * np.sin(angle), 0.0])
        eye[2] = height + rng.uniform(-0.1, 0.1)
        target = centre + np.array([-np.cos(angle), -np.sin(angle), 0.0]) * 1.5 + rng.uniform(-0.3, 0.3, 3)
        target[2] = 0.6 + rng.uniform(-0.2, 0.2)
        poses.append(look_at(eye, target))
    return poses


__all__ = [
    "DenseGrid",
    "blocks_to_dense",
    "dense_to_blocks",
    "empty_dense",
    "dense_shape",
    "voxel_centres",
    "reference_integrate_tsdf",
    "reference_pixel_instances",
    "reference_apply_hits",
    "reference_integrate_instances",
    "reference_overlap_counts",
    "subsampled_pixel_points",
    "BoxRoom",
    "look_at",
    "scannet_like_intrinsics",
    "orbit_poses",
]
