"""Host-side extraction (`engine.extraction`): meshes, surface points and instance point sets."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from oracles import reference as ref

from fmfusion_jax.engine import instance_volume as iv
from fmfusion_jax.engine import tsdf
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.extraction import (
    _chunks,
    _dilated_by_one,
    _host_blocks,
    _pool_blocks,
    _PoolColors,
    _raster_blocks,
    _sample_linear,
    _sample_on_edges,
    extract_instance_points,
    extract_mesh,
    extract_surface_points,
    extract_surface_voxels,
)
from fmfusion_jax.engine.state import MapState, init_map_state, init_voxel_blocks, local_voxel_index

SPHERE_CONFIG = MapConfig(
    voxel_size=0.02,
    block_size=4,
    sdf_trunc=0.06,
    grid_origin=(-0.5, -0.5, -0.5),
    grid_shape=(13, 13, 13),
    block_capacity=4096,
    instance_capacity=4,
)
CENTRE = np.array([0.013, 0.021, 0.007])
RADIUS = 0.3


def sphere_blocks(observed=lambda x, y, z: np.ones_like(x, bool)):
    """A pool holding the truncated SDF of a sphere, in the voxels where `observed` is True."""
    grid = ref.empty_dense(SPHERE_CONFIG)
    x, y, z = ref.voxel_centres(SPHERE_CONFIG)
    sdf = np.sqrt((x - CENTRE[0]) ** 2 + (y - CENTRE[1]) ** 2 + (z - CENTRE[2]) ** 2) - RADIUS
    near = (np.abs(sdf) < SPHERE_CONFIG.sdf_trunc) & observed(x, y, z)
    grid.tsdf = np.where(near, np.clip(sdf / SPHERE_CONFIG.sdf_trunc, -1, 1), 1.0)
    grid.weight = near.astype(float)
    grid.color[...] = np.stack([x, y, z], -1) * 100 + 120
    grid.allocated = near
    return ref.dense_to_blocks(grid, SPHERE_CONFIG)


def edge_use_counts(faces: np.ndarray) -> np.ndarray:
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(edges, axis=0, return_counts=True)[1]


@pytest.mark.parametrize("chunk_blocks", [2, 8])
def test_sphere_mesh_is_accurate_closed_and_outward(chunk_blocks):
    vertices, faces, colors = extract_mesh(sphere_blocks(), SPHERE_CONFIG, chunk_blocks=chunk_blocks)
    assert vertices.dtype == np.float32 and faces.dtype == np.int32 and colors.dtype == np.uint8
    assert len(faces) > 1000
    error = np.abs(np.linalg.norm(vertices - CENTRE, axis=1) - RADIUS)
    assert error.max() < 0.1 * SPHERE_CONFIG.voxel_size
    assert np.all(edge_use_counts(faces) == 2), "chunk seams left the mesh open"
    normals = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    assert np.all(np.sum(normals * (vertices[faces].mean(1) - CENTRE), axis=1) > 0)
    expected = np.clip(np.round(vertices * 100 + 120), 0, 255)
    assert np.abs(colors.astype(float) - expected).max() <= 1.0


def canonical_triangles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangles as rows of 9 coordinates, each rotated to start at its smallest vertex, rows sorted."""
    tri = vertices[faces].astype(np.float64)  # (F, 3, 3)
    start = np.array([min(range(3), key=lambda i: tuple(t[i])) for t in tri])
    tri = np.stack([np.roll(t, -s, axis=0) for t, s in zip(tri, start)]).reshape(len(tri), 9)
    return tri[np.lexsort(np.round(tri, 4).T[::-1])]


def test_mesh_does_not_depend_on_the_chunking():
    blocks = sphere_blocks()
    a = extract_mesh(blocks, SPHERE_CONFIG, chunk_blocks=3)
    b = extract_mesh(blocks, SPHERE_CONFIG, chunk_blocks=8)
    assert len(a[0]) == len(b[0]) and len(a[1]) == len(b[1])
    np.testing.assert_allclose(canonical_triangles(*a[:2]), canonical_triangles(*b[:2]), atol=1e-5)


def test_unobserved_space_makes_no_surface():
    """Half a sphere observed: the mesh is an open cap on the true surface, nothing elsewhere."""
    blocks = sphere_blocks(lambda x, y, z: z > CENTRE[2])
    vertices, faces, _ = extract_mesh(blocks, SPHERE_CONFIG)
    assert len(faces) > 100
    assert np.abs(np.linalg.norm(vertices - CENTRE, axis=1) - RADIUS).max() < 0.1 * SPHERE_CONFIG.voxel_size
    assert vertices[:, 2].min() > CENTRE[2]
    assert np.any(edge_use_counts(faces) == 1)  # open boundary where observation stops
    points, _ = extract_surface_points(blocks, SPHERE_CONFIG)
    assert np.abs(np.linalg.norm(points - CENTRE, axis=1) - RADIUS).max() < 0.1 * SPHERE_CONFIG.voxel_size


def test_surface_points_match_mesh_vertices_on_a_closed_surface():
    blocks = sphere_blocks()
    vertices, _, _ = extract_mesh(blocks, SPHERE_CONFIG)
    points, colors = extract_surface_points(blocks, SPHERE_CONFIG)
    from scipy.spatial import cKDTree

    assert len(points) == len(vertices)
    assert cKDTree(vertices).query(points)[0].max() < 1e-5
    assert cKDTree(points).query(vertices)[0].max() < 1e-5
    assert colors.shape == points.shape


def test_surface_voxels_cover_the_mesh_and_lie_on_the_surface():
    """The overview's stand-in for the mesh: voxels within about a voxel of the surface, one near every vertex,
    none where nothing was observed."""
    from scipy.spatial import cKDTree

    blocks = sphere_blocks(lambda x, y, z: z > CENTRE[2])
    vertices, _, _ = extract_mesh(blocks, SPHERE_CONFIG)
    points, colors = extract_surface_voxels(blocks, SPHERE_CONFIG)
    voxel = SPHERE_CONFIG.voxel_size
    assert points.dtype == np.float32 and colors.dtype == np.uint8 and colors.shape == points.shape
    assert np.abs(np.linalg.norm(points - CENTRE, axis=1) - RADIUS).max() <= 1.01 * voxel
    assert cKDTree(points).query(vertices)[0].max() <= np.sqrt(3) * voxel
    assert points[:, 2].min() > CENTRE[2] - voxel
    expected = np.clip(np.round(points * 100 + 120), 0, 255)  # the voxels' own colours
    assert np.abs(colors.astype(float) - expected).max() <= 1.0


def test_a_thin_surface_between_far_voxels_keeps_a_voxel():
    """tsdf +1 over -1 (a surface passing between two voxels farther than the band from it) still draws, within
    a block and between two: every vertex of its mesh has a drawn voxel beside it."""
    from scipy.spatial import cKDTree

    blocks = sphere_blocks()
    tsdf = np.asarray(blocks.tsdf)
    blocks = blocks._replace(tsdf=jnp.asarray(np.sign(tsdf) + (tsdf == 0)))  # every value +-1
    vertices, _, _ = extract_mesh(blocks, SPHERE_CONFIG)
    points, _ = extract_surface_voxels(blocks, SPHERE_CONFIG)
    voxel = SPHERE_CONFIG.voxel_size
    assert np.abs(np.linalg.norm(points - CENTRE, axis=1) - RADIUS).max() <= 1.01 * voxel
    assert cKDTree(points).query(vertices)[0].max() <= 1.01 * voxel  # the vertex's edge has a voxel drawn


def row_major_permutation(block_size: int) -> np.ndarray:
    """The oracle of `_raster_blocks`: `perm` such that `block[..., perm].reshape(bs, bs, bs)` is the block in (x, y, z)
    raster order."""
    g = np.stack(np.meshgrid(*(np.arange(block_size),) * 3, indexing="ij"), -1).reshape(-1, 3)
    return local_voxel_index(g[:, 0], g[:, 1], g[:, 2], block_size)


@given(bs=st.sampled_from([2, 4, 8]), rows=st.integers(1, 4))
def test_raster_blocks_is_the_row_major_gather_and_pool_blocks_its_inverse(bs, rows):
    values = np.arange(rows * bs**3).reshape(rows, bs**3)
    raster = _raster_blocks(values, bs)
    np.testing.assert_array_equal(raster, values[:, row_major_permutation(bs)].reshape(rows, bs, bs, bs))
    np.testing.assert_array_equal(_pool_blocks(raster), values)


def test_empty_map_extracts_nothing():
    state = init_map_state(SPHERE_CONFIG)
    v, f, c = extract_mesh(state, SPHERE_CONFIG)
    assert v.shape == (0, 3) and f.shape == (0, 3) and c.shape == (0, 3)
    p, pc = extract_surface_points(state, SPHERE_CONFIG)
    assert p.shape == (0, 3)
    p, pc = extract_surface_voxels(state, SPHERE_CONFIG)
    assert p.shape == (0, 3) and pc.shape == (0, 3)
    assert extract_instance_points(state, SPHERE_CONFIG) == {}


def test_integrated_room_mesh_lies_on_the_room():
    room = ref.BoxRoom(
        lo=(0.013, 0.021, 0.007),
        hi=(3.011, 2.517, 2.209),
        boxes=(((0.6, 0.5, 0.007), (1.3, 1.2, 0.75)),),
        spheres=(((1.9, 1.3, 0.8), 0.3),),
    )
    h, w = 60, 80
    k = ref.scannet_like_intrinsics(w, h)
    config = MapConfig.for_bounds(
        room.lo,
        room.hi,
        voxel_size=0.04,
        block_size=4,
        sdf_trunc=0.1,
        image_height=h,
        image_width=w,
        block_capacity=4096,
        max_touched_blocks=2048,
        alloc_pixel_stride=1,
        instance_capacity=12,
    )
    blocks = init_voxel_blocks(config)
    for T in ref.orbit_poses(room, 5, radius=0.8, height=1.3):
        depth, color, labels = room.render(T, k, h, w)
        T = T.astype(np.float32)
        blocks = tsdf.integrate_tsdf(blocks, depth, color, T, k, config)
        blocks = iv.integrate_instances(blocks, depth, T, k, labels[::2, ::2], config)
    vertices, faces, colors = extract_mesh(blocks, config)
    error = np.abs(room.signed_distance(vertices.astype(np.float64)))
    assert len(faces) > 1000
    assert np.quantile(error, 0.99) < config.voxel_size
    assert error.max() < 3 * config.voxel_size  # only near corners and silhouettes

    # instance points: every instance voxel lies on its labelled surface
    state = MapState(blocks, init_map_state(config).instances, np.int32(5))
    points = extract_instance_points(state, config)
    assert set(points) <= set(range(12)) and len(points) >= 6
    dense = ref.blocks_to_dense(blocks, config)
    assert sum(len(p) for p in points.values()) == int((dense.instance_id >= 0).sum())
    sphere = 6 + len(room.boxes)
    d = np.linalg.norm(points[sphere] - np.asarray(room.spheres[0][0]), axis=1) - room.spheres[0][1]
    assert np.quantile(np.abs(d), 0.95) < config.voxel_size
    on_surface = extract_instance_points(state, config, on_surface=True)
    assert 0 < sum(len(p) for p in on_surface.values()) <= sum(len(p) for p in points.values())
    strong = extract_instance_points(state, config, min_weight=3.0)
    assert sum(len(p) for p in strong.values()) < sum(len(p) for p in points.values())


def test_instance_points_with_a_slot_share_drop_weak_second_slots():
    """Two slots per voxel: instance 0 strong everywhere, instance 1 strong in a few voxels and weak (a smear)
    in others. With `min_share` the weak slots go; the strongest slot of a voxel always stays."""
    blocks = sphere_blocks()
    n = int(blocks.num_blocks)
    ids = np.full(np.asarray(blocks.instance_id).shape, -1, np.int32)
    weights = np.zeros(ids.shape, np.float32)
    ids[:n, :, 0], weights[:n, :, 0] = 0, 10.0
    ids[:n, :8, 1], weights[:n, :8, 1] = 1, 2.0  # weak beside 10
    ids[:n, 8:12, 1], weights[:n, 8:12, 1] = 1, 6.0  # comparable
    state = blocks._replace(instance_id=jnp.asarray(ids), instance_weight=jnp.asarray(weights))
    every = extract_instance_points(state, SPHERE_CONFIG)
    shared = extract_instance_points(state, SPHERE_CONFIG, min_share=0.5)
    assert len(every[1]) == 12 * n and len(shared[1]) == 4 * n
    assert len(shared[0]) == len(every[0]) == ids.shape[1] * n


@given(
    spans=st.tuples(*[st.integers(0, 22)] * 3),
    rows=st.integers(1, 60),
    seed=st.integers(0, 2**31 - 1),
)
@settings(max_examples=60, deadline=None)
def test_packed_rows_keep_the_rows_order_and_equality(spans, rows, seed):
    """One packed key per row (up to 64 bits: a room's vertex keys take all of them) sorts as the rows do and is
    equal exactly where the rows are."""
    from fmfusion_jax.engine.extraction import _packed_rows

    rng = np.random.default_rng(seed)
    low = rng.integers(-(2**30), 2**30, 3)
    key = np.stack([rng.integers(0, 2**bits, rows) for bits in spans], axis=1) + low
    key[rng.integers(0, rows, rows // 3)] = key[rng.integers(0, rows, rows // 3)]  # some rows repeat
    packed = _packed_rows(key)
    assert packed.ndim == (2 if sum(int(s).bit_length() for s in np.ptp(key, axis=0)) > 64 else 1)
    if packed.ndim == 1:
        np.testing.assert_array_equal(np.unique(packed, return_inverse=True)[1], np.unique(key, axis=0, return_inverse=True)[1])


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), share_inside=st.floats(0.0, 0.5))
def test_colours_on_edges_are_the_trilinear_samples_bit_for_bit(seed, share_inside):
    """Marching cubes' vertices lie on voxel edges (Lewiner's few inside ambiguous cubes do not): two corners give
    the trilinear sample exactly, float32 rounding included."""
    rng = np.random.default_rng(seed)
    volume = rng.uniform(0, 255, (9, 9, 9, 3)).astype(np.float32)
    n = 400
    points = rng.integers(0, 9, (n, 3)).astype(np.float32)
    axis = rng.integers(0, 3, n)
    on_edge = rng.uniform(size=n) >= share_inside
    points[np.arange(n), axis] += np.where(on_edge & (points[np.arange(n), axis] < 8), rng.uniform(0, 1, n), 0).astype(np.float32)
    inside = ~on_edge
    points[inside] = rng.uniform(0, 8, (int(inside.sum()), 3)).astype(np.float32)
    points[: n // 10] = np.floor(points[: n // 10])  # on a voxel: no fractional coordinate
    np.testing.assert_array_equal(_sample_on_edges(volume, points), _sample_linear(volume, points))


@pytest.mark.parametrize("chunk_blocks", [1, 2, 3])
def test_pool_colours_are_the_dense_colour_volume_bit_for_bit(chunk_blocks):
    """The chunks' colours are read from the pool rows (`_PoolColors`): every voxel of every chunk, the apron and
    the unallocated blocks (0) included, as a dense volume of the pool's blocks holds it."""
    blocks = sphere_blocks(lambda x, y, z: x < 0.1)
    host = _host_blocks(blocks)
    bs = SPHERE_CONFIG.block_size
    row_of = {tuple(c): i for i, c in enumerate(host["coords"].tolist())}
    raster = _raster_blocks(host["color"], bs)  # (B, bs, bs, bs, 3)
    checked = 0
    for origin, _, _, color in _chunks(host, SPHERE_CONFIG, chunk_blocks, 1.0):
        x, y, z = (axis.reshape(-1) for axis in np.indices(color.shape[:3]))
        voxel = np.stack([x, y, z], axis=1) + origin
        row = np.array([row_of.get(tuple(b), -1) for b in (voxel // bs).tolist()])
        local = voxel % bs
        expected = raster[np.maximum(row, 0), local[:, 0], local[:, 1], local[:, 2]].astype(np.float32)
        expected[row < 0] = 0.0
        np.testing.assert_array_equal(color[x, y, z], expected)
        checked += int((expected != 0).any(axis=1).sum())
    assert checked > 0


@given(bs=st.sampled_from([2, 4, 6, 8, 10]), seed=st.integers(0, 2**16))
def test_pool_colours_split_a_coordinate_as_floor_division_does(bs, seed):
    """`_PoolColors` reads a chunk coordinate's block and voxel as the oracle's // and % do, for every even block
    size."""
    rng = np.random.default_rng(seed)
    blocks = 3
    color_rows = rng.random((5, bs**3, 3)).astype(np.float16)
    row_of_block = rng.integers(-1, 5, (blocks, blocks, blocks))
    local = _raster_blocks(np.arange(bs**3)[None], bs)[0]
    colors = _PoolColors(color_rows, row_of_block, local, blocks * bs)
    x, y, z = (rng.integers(0, blocks * bs, 200) for _ in range(3))
    row = row_of_block[x // bs, y // bs, z // bs]
    expected = color_rows[np.maximum(row, 0), local[x % bs, y % bs, z % bs]].astype(np.float32)
    expected[row < 0] = 0.0
    np.testing.assert_array_equal(colors[x, y, z], expected)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), m=st.integers(1, 6), share=st.floats(0.0, 1.0))
def test_cube_corners_are_the_or_over_each_voxels_cubes(seed, m, share):
    cube = np.random.default_rng(seed).uniform(size=(m, m, m)) < share
    expected = np.zeros((m + 1,) * 3, bool)
    for d in np.ndindex(2, 2, 2):
        expected[d[0] : d[0] + m, d[1] : d[1] + m, d[2] : d[2] + m] |= cube
    np.testing.assert_array_equal(_dilated_by_one(cube), expected)
