"""Global TSDF integration (`engine.tsdf`) against the dense NumPy reference and its invariants."""

from __future__ import annotations

import dataclasses
import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from oracles import reference as ref

from fmfusion_jax.engine import tsdf
from fmfusion_jax.engine.config import MapConfig, integrate_chunk_for_backend
from fmfusion_jax.engine.extraction import extract_surface_points
from fmfusion_jax.engine.state import init_map_state, init_voxel_blocks, voxel_offsets

H, W = 60, 80
# Walls off the voxel lattice, so that float32 and float64 floor() agree on the surface points.
ROOM = ref.BoxRoom(
    lo=(0.013, 0.021, 0.007),
    hi=(3.011, 2.517, 2.209),
    boxes=(((0.6, 0.5, 0.007), (1.3, 1.2, 0.75)),),
    spheres=(((1.9, 1.3, 0.8), 0.3),),
)
K = ref.scannet_like_intrinsics(W, H)
CONFIG = MapConfig.for_bounds(
    ROOM.lo,
    ROOM.hi,
    voxel_size=0.04,
    block_size=4,
    sdf_trunc=0.1,
    image_height=H,
    image_width=W,
    block_capacity=4096,
    max_touched_blocks=2048,
    integrate_chunk_blocks=256,
    alloc_pixel_stride=1,
)
POSES = ref.orbit_poses(ROOM, 5, radius=0.8, height=1.3)


@functools.cache
def frame(i: int):
    depth, color, labels = ROOM.render(POSES[i], K, H, W)
    return depth, color, POSES[i].astype(np.float32)


def touched_region(blocks, touched: tsdf.TouchedBlocks, config: MapConfig) -> np.ndarray:
    region = np.zeros(ref.dense_shape(config), bool)
    slots = np.asarray(touched.slots)[np.asarray(touched.valid)]
    g = np.asarray(blocks.block_coords)[slots][:, None, :] * config.block_size + voxel_offsets(config.block_size)[None]
    region[g[..., 0], g[..., 1], g[..., 2]] = True
    return region


def check_pool_consistent(blocks, config: MapConfig) -> None:
    """Allocated slots are indexed exactly once and their coordinates point back to the index."""
    n = int(blocks.num_blocks)
    index = np.asarray(blocks.block_index)
    assert 0 <= n <= config.block_capacity - 1
    used = index[index >= 0]
    assert sorted(used.tolist()) == list(range(n))
    coords = np.asarray(blocks.block_coords)[:n]
    assert np.array_equal(index[coords[:, 0], coords[:, 1], coords[:, 2]], np.arange(n))


def test_matches_dense_reference_frame_by_frame():
    blocks = init_voxel_blocks(CONFIG)
    grid = ref.empty_dense(CONFIG)
    for i in range(len(POSES)):
        depth, color, T = frame(i)
        touched = tsdf.find_touched_blocks(blocks, depth, T, K, CONFIG)
        blocks = tsdf.integrate_tsdf(blocks, depth, color, T, K, CONFIG)
        region = touched_region(blocks, touched, CONFIG)
        grid = ref.reference_integrate_tsdf(grid, depth, color, T, K, CONFIG, region=region)
        got = ref.blocks_to_dense(blocks, CONFIG)
        m = got.allocated
        assert np.array_equal(got.weight[m], grid.weight[m])
        np.testing.assert_allclose(got.tsdf[m], grid.tsdf[m], atol=1e-4)
        # colour is stored in half precision (steps of 1/8 between 128 and 255): within two steps of the reference
        np.testing.assert_allclose(got.color[m].astype(np.float32), grid.color[m], atol=0.25)
        assert not np.any(grid.weight[~m]), "the reference updated voxels outside the allocated blocks"
    check_pool_consistent(blocks, CONFIG)
    assert int(blocks.dropped_blocks) == int(blocks.out_of_bounds) == int(blocks.touched_overflow) == 0


def test_allocation_covers_the_truncation_band():
    blocks = init_voxel_blocks(CONFIG)
    full = ref.empty_dense(CONFIG)
    for i in range(len(POSES)):
        depth, color, T = frame(i)
        blocks = tsdf.integrate_tsdf(blocks, depth, color, T, K, CONFIG)
        full = ref.reference_integrate_tsdf(full, depth, color, T, K, CONFIG)  # every voxel of the grid
    allocated = ref.blocks_to_dense(blocks, CONFIG).allocated
    band = (full.weight > 0) & (np.abs(full.tsdf) < 0.5)
    assert allocated[band].mean() > 0.99


@pytest.mark.parametrize("chunk", [96, 0])  # 1000 % 96 != 0; 0: the backend's default
def test_chunking_does_not_change_the_result(chunk):
    odd = dataclasses.replace(CONFIG, max_touched_blocks=1000, integrate_chunk_blocks=chunk)
    a, b = init_voxel_blocks(CONFIG), init_voxel_blocks(odd)
    for i in range(3):
        depth, color, T = frame(i)
        a = tsdf.integrate_tsdf(a, depth, color, T, K, CONFIG)
        b = tsdf.integrate_tsdf(b, depth, color, T, K, odd)
    assert int(b.touched_overflow) == 0
    da, db = ref.blocks_to_dense(a, CONFIG), ref.blocks_to_dense(b, odd)
    assert np.array_equal(da.allocated, db.allocated)
    assert np.array_equal(da.weight, db.weight)
    np.testing.assert_allclose(da.tsdf, db.tsdf, atol=1e-6)


def test_geometry_only_integration_leaves_the_colours():
    """`color=None` (frame-to-model tracking's TSDF): the same TSDF and weights as with a colour image, colours
    untouched."""
    with_color, geometry = init_voxel_blocks(CONFIG), init_voxel_blocks(CONFIG)
    for i in range(3):
        depth, color, T = frame(i)
        with_color = tsdf.integrate_tsdf(with_color, depth, color, T, K, CONFIG)
        geometry = tsdf.integrate_tsdf(geometry, depth, None, T, K, CONFIG)
    for name in ("block_index", "block_coords", "tsdf", "weight"):
        assert np.array_equal(np.asarray(getattr(geometry, name)), np.asarray(getattr(with_color, name))), name
    assert np.any(np.asarray(with_color.color) != 0)
    assert not np.any(np.asarray(geometry.color))


def test_integrate_chunk_by_backend():
    """0 leaves the TSDF's loop step to the backend: cache-sized on the CPU, fewer steps on an accelerator."""
    assert integrate_chunk_for_backend("cpu") == 96 and integrate_chunk_for_backend("gpu") == 256
    assert MapConfig().integrate_chunk_blocks == 0
    with pytest.raises(ValueError, match="chunk"):
        MapConfig(integrate_chunk_blocks=-1)


def test_plane_zero_crossing_within_a_voxel():
    """A wall at a known distance: every extracted zero crossing lies on the analytic surface."""
    blocks = init_voxel_blocks(CONFIG)
    for i in range(len(POSES)):
        depth, color, T = frame(i)
        blocks = tsdf.integrate_tsdf(blocks, depth, color, T, K, CONFIG)
    points, _ = extract_surface_points(blocks, CONFIG)
    assert len(points) > 1000
    error = np.abs(ROOM.signed_distance(points.astype(np.float64)))
    assert np.median(error) < 0.1 * CONFIG.voxel_size
    assert np.quantile(error, 0.99) < CONFIG.voxel_size
    # fronto-parallel check: the camera looking straight at the +x wall
    T = ref.look_at((1.5, 2.0, 1.7), (4.0, 2.0, 1.7)).astype(np.float32)
    depth, color, _ = ROOM.render(T, K, H, W)
    one = tsdf.integrate_tsdf(init_voxel_blocks(CONFIG), depth, color, T, K, CONFIG)
    g = ref.blocks_to_dense(one, CONFIG)
    x = ref.voxel_centres(CONFIG)[0][:, 0, 0]
    iy = int((2.0 - CONFIG.grid_origin[1]) / CONFIG.voxel_size)
    iz = int((1.7 - CONFIG.grid_origin[2]) / CONFIG.voxel_size)
    t, w = g.tsdf[:, iy, iz], g.weight[:, iy, iz]
    k = np.flatnonzero((w[:-1] > 0) & (w[1:] > 0) & (t[:-1] > 0) & (t[1:] <= 0))
    assert len(k) == 1
    k = k[0]
    crossing = x[k] + (x[k + 1] - x[k]) * t[k] / (t[k] - t[k + 1])
    assert abs(crossing - ROOM.hi[0]) < 0.25 * CONFIG.voxel_size


settings_small = settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@settings_small
@given(seed=st.integers(0, 2**31 - 1), n_frames=st.integers(1, 3))
def test_weights_never_decrease_and_tsdf_stays_bounded(seed, n_frames):
    rng = np.random.default_rng(seed)
    blocks = init_voxel_blocks(CONFIG)
    for _ in range(n_frames):
        eye = rng.uniform(np.asarray(ROOM.lo) + 0.3, np.asarray(ROOM.hi) - 0.3)
        T = ref.look_at(eye, eye + rng.normal(size=3) * [1, 1, 0.3] + [0, 0, 1e-3]).astype(np.float32)
        depth, color, _ = ROOM.render(T, K, H, W)
        depth = depth * rng.uniform(0.95, 1.05, depth.shape).astype(np.float32)  # noise
        depth[rng.random(depth.shape) < 0.1] = 0.0  # holes
        before = ref.blocks_to_dense(blocks, CONFIG)
        blocks = tsdf.integrate_tsdf(blocks, depth, color, T, K, CONFIG)
        after = ref.blocks_to_dense(blocks, CONFIG)
        assert np.all(after.weight >= before.weight)
        assert np.all(after.allocated >= before.allocated)
        assert np.all(np.abs(after.tsdf) <= 1.0)
        assert np.all(after.weight <= CONFIG.max_weight)
        assert np.all((after.color >= 0) & (after.color <= 255))
        check_pool_consistent(blocks, CONFIG)


def test_weight_cap():
    capped = dataclasses.replace(CONFIG, max_weight=3.0)
    blocks = init_voxel_blocks(capped)
    depth, color, T = frame(0)
    for _ in range(5):
        blocks = tsdf.integrate_tsdf(blocks, depth, color, T, K, capped)
    w = np.asarray(blocks.weight)[: int(blocks.num_blocks)]
    assert w.max() == 3.0


def test_overflow_counters_with_a_tiny_pool():
    tiny = dataclasses.replace(CONFIG, block_capacity=9, max_touched_blocks=16, integrate_chunk_blocks=4)
    blocks = init_voxel_blocks(tiny)
    for i in range(2):
        depth, color, T = frame(i)
        blocks = tsdf.integrate_tsdf(blocks, depth, color, T, K, tiny)
    assert int(blocks.num_blocks) == 8  # all but the scratch slot
    assert int(blocks.dropped_blocks) > 0
    assert int(blocks.touched_overflow) > 0
    check_pool_consistent(blocks, tiny)
    # the scratch slot never changes
    assert np.all(np.asarray(blocks.weight)[-1] == 0) and np.all(np.asarray(blocks.tsdf)[-1] == 1)


def test_points_outside_the_index_are_counted():
    small = MapConfig.for_bounds(
        (0.0, 0.0, 0.0),
        (1.5, 1.5, 1.0),
        margin=0.0,
        voxel_size=0.04,
        block_size=4,
        sdf_trunc=0.1,
        image_height=H,
        image_width=W,
        block_capacity=2048,
        max_touched_blocks=1024,
    )
    depth, color, T = frame(0)
    blocks = tsdf.integrate_tsdf(init_voxel_blocks(small), depth, color, T, K, small)
    valid = (depth >= small.depth_min) & (depth <= small.depth_max)
    assert 0 < int(blocks.out_of_bounds) <= valid[:: small.alloc_pixel_stride, :: small.alloc_pixel_stride].sum()
    check_pool_consistent(blocks, small)


def test_no_recompilation_over_frames():
    counted = jax.jit(chex.assert_max_traces(tsdf.integrate_tsdf_unjitted, n=1), static_argnames="config")
    blocks = init_voxel_blocks(CONFIG)
    for i in range(4):
        depth, color, T = frame(i % len(POSES))
        intrinsics = K * np.float32(1.0 + 0.01 * i)  # new values, same shapes
        args = (jnp.asarray(depth), jnp.asarray(color), jnp.asarray(T), jnp.asarray(intrinsics))
        blocks = counted(blocks, *args, CONFIG)
    jax.block_until_ready(blocks)


def test_vmap_over_two_maps_equals_separate_calls():
    depth0, color0, T0 = frame(0)
    depth1, color1, T1 = frame(1)
    start = init_voxel_blocks(CONFIG)
    single0 = tsdf.integrate_tsdf(start, depth0, color0, T0, K, CONFIG)
    single1 = tsdf.integrate_tsdf(start, depth1, color1, T1, K, CONFIG)
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), start)
    batched = jax.vmap(lambda b, d, c, T: tsdf.integrate_tsdf(b, d, c, T, K, CONFIG))(
        batch, jnp.stack([depth0, depth1]), jnp.stack([color0, color1]), jnp.stack([T0, T1])
    )
    for i, single in enumerate((single0, single1)):
        for name, a, b in zip(single._fields, single, batched):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b)[i], atol=1e-6, err_msg=name)


def test_config_helpers():
    cfg = MapConfig.for_bounds((0.0, 0.0, 0.0), (8.0, 8.0, 3.0))
    lo, hi = cfg.grid_bounds
    assert np.all(lo <= -cfg.sdf_trunc) and np.all(hi >= np.array([8.0, 8.0, 3.0]) + cfg.sdf_trunc)
    in_blocks = np.asarray(cfg.grid_origin) / cfg.block_length
    assert np.allclose(in_blocks, np.round(in_blocks))
    assert hash(cfg) == hash(MapConfig.for_bounds([0, 0, 0], [8, 8, 3]))
    assert 300e6 < cfg.memory_bytes() < 1e9
    with pytest.raises(ValueError):
        MapConfig(block_size=5)
    state = init_map_state(dataclasses.replace(CONFIG, instance_capacity=7))
    assert state.instances.label_evidence.shape == (7, CONFIG.num_classes)
    assert state.blocks.instance_id.shape == (CONFIG.block_capacity, CONFIG.voxels_per_block, CONFIG.instance_slots)
