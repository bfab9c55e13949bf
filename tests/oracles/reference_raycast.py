"""Plain NumPy reference of the TSDF raycast (test oracle of `engine.raycast`).

Written for clarity: the pool is first laid out as one dense float64 grid, every ray is marched in small uniform
steps (a tenth of a voxel) on the trilinear TSDF, the first positive-to-negative crossing is interpolated
linearly, and the normal is the central difference of the trilinear TSDF one voxel apart.
"""

from __future__ import annotations

import numpy as np


def dense_tsdf(tsdf, weight, block_coords, num_blocks, grid_shape, block_size, voxel_offsets):
    """`(values, observed)`, float64 / bool `(X, Y, Z)` voxels of the block index (unobserved: 1)."""
    shape = tuple(int(s) * block_size for s in grid_shape)
    values = np.ones(shape)
    observed = np.zeros(shape, bool)
    for slot in range(int(num_blocks)):
        corner = np.asarray(block_coords[slot]) * block_size
        index = tuple((corner[None] + voxel_offsets).T)
        seen = np.asarray(weight[slot]) > 0
        values[index] = np.where(seen, np.asarray(tsdf[slot], np.float64), 1.0)
        observed[index] = seen
    return values, observed


def trilinear(values, observed, q):
    """Trilinear TSDF at index-voxel coordinates `q` `(N, 3)` (voxel centres at `g + 0.5`); NaN where any of the 8
    corners is unobserved or outside the grid."""
    base = q - 0.5
    g0 = np.floor(base).astype(int)
    f = base - g0
    out = np.zeros(len(q))
    ok = np.ones(len(q), bool)
    for corner in range(8):
        d = np.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
        g = g0 + d
        inside = np.all((g >= 0) & (g < np.array(values.shape)), axis=1)
        gi = np.where(inside[:, None], g, 0)
        w = np.prod(np.where(d == 1, f, 1.0 - f), axis=1)
        out += w * values[gi[:, 0], gi[:, 1], gi[:, 2]]
        ok &= inside & observed[gi[:, 0], gi[:, 1], gi[:, 2]]
    return np.where(ok, out, np.nan)


def raycast(values, observed, origin_voxels, voxel_size, T_world_camera, intrinsics, height, width, depth_min, depth_max):
    """`(depth (H, W), normals (H, W, 3) camera frame)` of the first crossing of each pixel's ray (0 where none)."""
    fx, fy, cx, cy = intrinsics
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
    R, t = T_world_camera[:3, :3], T_world_camera[:3, 3]
    direction = rays @ R.T / voxel_size  # index voxels per unit of depth
    origin = t / voxel_size - np.asarray(origin_voxels, np.float64)
    step = 0.1 / np.linalg.norm(direction, axis=1)  # a tenth of a voxel
    n = len(rays)
    depth = np.zeros(n)
    done = np.zeros(n, bool)
    z = np.full(n, depth_min)
    previous = np.full(n, np.nan)
    while not done.all():
        value = trilinear(values, observed, origin + z[:, None] * direction)
        crossing = ~done & (previous > 0) & (value <= 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            depth[crossing] = (z - step * value / (value - previous))[crossing]
        done |= crossing
        previous = value
        z = z + step
        done |= z > depth_max
    q = origin + depth[:, None] * direction
    gradient = np.stack([trilinear(values, observed, q + e) - trilinear(values, observed, q - e) for e in np.eye(3)], axis=1)
    normals = gradient / np.linalg.norm(gradient, axis=1, keepdims=True)
    normals = normals @ R  # into the camera frame
    normals = np.where(np.sum(normals * rays, axis=1, keepdims=True) > 0, -normals, normals)
    normals = np.where((depth > 0)[:, None], normals, 0.0)
    return depth.reshape(height, width), normals.reshape(height, width, 3)
