"""The TSDF raycast (`engine.raycast`) against its NumPy oracle on a TSDF written from a sphere in front of a wall,
and against the analytic surface."""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from oracles import reference_raycast as R
from oracles import reference_tracking as RT

from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.raycast import raycast_tsdf
from fmfusion_jax.engine.state import init_voxel_blocks, voxel_offsets

WIDTH, HEIGHT = 32, 24
K = np.array([30.0, 30.0, WIDTH / 2 - 0.5, HEIGHT / 2 - 0.5])
CENTRE, RADIUS, WALL = np.array([0.05, -0.03, 1.2]), 0.35, 1.9


def surface_sdf(points: np.ndarray) -> np.ndarray:
    """Signed distance (m) to a sphere in front of a wall `z = WALL` facing the camera at the origin."""
    return np.minimum(np.linalg.norm(points - CENTRE, axis=-1) - RADIUS, WALL - points[..., 2])


@functools.cache
def volume():
    """A pool holding the surface's truncated SDF where a camera at the origin would have observed it (in front
    and up to the truncation behind), allocated only in blocks near the surface."""
    config = MapConfig.for_bounds(
        (-1.0, -1.0, 0.2),
        (1.0, 1.0, 2.1),
        voxel_size=0.02,
        sdf_trunc=0.06,
        block_capacity=4096,
        image_height=HEIGHT,
        image_width=WIDTH,
        instance_capacity=1,
        instance_slots=1,
    )
    blocks = init_voxel_blocks(config)
    bs, vs = config.block_size, config.voxel_size
    offsets = voxel_offsets(bs)
    index = np.full(config.grid_shape, -1, np.int32)
    coords, tsdf, weight = [], [], []
    origin_voxels = np.asarray(config.origin_block) * bs
    for b in np.ndindex(*config.grid_shape):
        centres = ((np.asarray(b) * bs + offsets + origin_voxels) + 0.5) * vs
        sdf = surface_sdf(centres)
        if np.abs(sdf).min() > config.sdf_trunc + vs:
            continue  # no surface near: the block stays unallocated, as integration leaves it
        index[b] = len(coords)
        coords.append(b)
        seen = sdf >= -config.sdf_trunc
        tsdf.append(np.where(seen, np.clip(sdf / config.sdf_trunc, -1.0, 1.0), 1.0))
        weight.append(seen.astype(np.float32))
    n = len(coords)
    blocks = blocks._replace(
        block_index=jnp.asarray(index),
        block_coords=blocks.block_coords.at[:n].set(np.asarray(coords, np.int32)),
        num_blocks=jnp.int32(n),
        tsdf=blocks.tsdf.at[:n].set(np.asarray(tsdf, np.float32)),
        weight=blocks.weight.at[:n].set(np.asarray(weight, np.float32)),
    )
    dense = R.dense_tsdf(blocks.tsdf, blocks.weight, blocks.block_coords, n, config.grid_shape, bs, offsets)
    return config, blocks, dense, origin_voxels


def compare(T_world_camera: np.ndarray) -> None:
    config, blocks, (values, observed), origin_voxels = volume()
    cast = raycast_tsdf(blocks, jnp.asarray(T_world_camera, jnp.float32), jnp.asarray(K, jnp.float32), config, HEIGHT, WIDTH)
    depth, normals, valid = (np.asarray(x) for x in (cast.depth, cast.normals, cast.valid))
    want_depth, want_normals = R.raycast(
        values, observed, origin_voxels, config.voxel_size, T_world_camera, K, HEIGHT, WIDTH, config.depth_min, config.depth_max
    )
    hit = want_depth > 0
    assert hit.mean() > 0.9
    assert not (valid & ~hit).any()  # nothing the oracle does not see
    assert valid.sum() > 0.6 * hit.sum()  # depth edges (the sphere's outline, the image border) are dropped
    np.testing.assert_allclose(depth[valid], want_depth[valid], atol=1e-3)
    assert np.sum(normals[valid] * want_normals[valid], axis=-1).min() > 0.995
    # and the surface itself: the vertices lie on it to a few millimetres
    points = np.asarray(cast.vertices)[valid] @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]
    assert np.abs(surface_sdf(points)).max() < 5e-3
    np.testing.assert_allclose(np.asarray(cast.vertices)[..., 2], depth)


def test_the_raycast_matches_the_oracle_from_the_volume_camera():
    compare(np.eye(4))


@settings(max_examples=4, deadline=None)
@given(st.tuples(*[st.floats(-0.1, 0.1)] * 3, *[st.floats(-0.15, 0.15)] * 3))
def test_the_raycast_matches_the_oracle_from_other_poses(xi):
    """Up to 10 cm and 8.6 degrees per axis from the camera that observed the volume (one compiled raycast)."""
    compare(RT.exp_se3(np.asarray(xi)))


def test_nothing_is_seen_from_outside_the_model():
    config, blocks, _, _ = volume()
    away = np.eye(4)
    away[:3, :3] = np.diag([-1.0, 1.0, -1.0])  # looking away from the sphere and the wall
    cast = raycast_tsdf(blocks, jnp.asarray(away, jnp.float32), jnp.asarray(K, jnp.float32), config, HEIGHT, WIDTH)
    assert not np.asarray(cast.valid).any()
    assert not np.asarray(cast.depth).any()
