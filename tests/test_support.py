"""The floor filter (`engine.support`) against a ray-cast room whose floor is known, and a NumPy oracle."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from oracles import reference as ref

from fmfusion_jax.engine import support
from fmfusion_jax.engine.config import MapConfig

H, W = 96, 128
ROOM = ref.BoxRoom(lo=(0.0, 0.0, 0.013), hi=(4.0, 3.5, 2.5))
K = ref.scannet_like_intrinsics(W, H)
CONFIG = MapConfig.for_bounds(ROOM.lo, ROOM.hi, voxel_size=0.04, block_size=4, sdf_trunc=0.1, image_height=H, image_width=W)
UP = (0.0, 0.0, 1.0)


def _view(eye, target):
    T = ref.look_at(eye, target)
    depth, _, label = ROOM.render(T, K, H, W)
    return T.astype(np.float32), depth, label


def _floor_histogram(views) -> np.ndarray:
    histogram = jnp.zeros((support.HEIGHT_BINS,), jnp.int32)
    for T, depth, _ in views:
        histogram = support.add_heights(histogram, support.surface_samples(depth, T, K, UP, CONFIG))
    return np.asarray(histogram)


def _interior(region: np.ndarray) -> np.ndarray:
    """The pixels of `region` whose 8 neighbours are in it too (normals there see one surface)."""
    inner = np.zeros_like(region)
    inner[1:-1, 1:-1] = region[1:-1, 1:-1]
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            inner[1:-1, 1:-1] &= region[1 + dv : region.shape[0] - 1 + dv, 1 + du : region.shape[1] - 1 + du]
    return inner


VIEWS = [
    _view((1.0, 1.0, 1.5), (2.6, 2.0, 0.3)),
    _view((3.0, 2.5, 1.4), (1.2, 1.0, 0.4)),
    _view((2.0, 0.6, 1.6), (2.0, 2.5, 0.2)),
]


def test_samples_height_and_up_facing_follow_the_rendered_surfaces():
    T, depth, label = VIEWS[0]
    samples = support.surface_samples(depth, T, K, UP, CONFIG)
    s = CONFIG.pixel_stride
    label = label[::s, ::s]
    up = np.asarray(samples.up_facing)
    # heights: the rendered points' z
    fx, fy, cx, cy = (float(x) for x in K)
    v, u = np.meshgrid(np.arange(0, H, s), np.arange(0, W, s), indexing="ij")
    d = depth[::s, ::s].astype(np.float64)
    z = (np.stack([(u - cx) / fx * d, (v - cy) / fy * d, d], -1) @ T[:3, :3].T.astype(np.float64) + T[:3, 3])[..., 2]
    valid = d > 0
    np.testing.assert_allclose(np.asarray(samples.height)[valid], z[valid], atol=2e-4)
    # floor and box tops face up; walls never do; nearly every floor pixel away from edges is found
    assert not up[(label >= 2) & (label <= 5)].any()
    assert up[_interior(label == 0)].mean() > 0.95
    # box tops face up (over the views: each sees some of them)
    tops, found = 0, 0
    for T, depth, label in VIEWS:
        samples = support.surface_samples(depth, T, K, UP, CONFIG)
        label, height, up = label[::s, ::s], np.asarray(samples.height), np.asarray(samples.up_facing)
        for i, (_, hi) in enumerate(ROOM.boxes):
            top = _interior((label == 6 + i) & (np.abs(height - hi[2]) < 0.005))
            tops, found = tops + top.sum(), found + up[top].sum()
    assert tops > 20 and found > 0.9 * tops


def test_floor_height_is_the_lowest_large_horizontal_surface():
    histogram = _floor_histogram(VIEWS)
    floor = support.floor_height(jnp.asarray(histogram))
    assert bool(floor.found)
    assert abs(float(floor.height) - ROOM.lo[2]) <= support.HEIGHT_BIN
    # a few stray low samples (noise below the floor) do not make a floor
    noisy = histogram.copy()
    noisy[support.HEIGHT_BINS // 2 - 40] += 50
    assert abs(float(support.floor_height(jnp.asarray(noisy)).height) - ROOM.lo[2]) <= support.HEIGHT_BIN


def test_no_floor_without_enough_samples():
    floor = support.floor_height(jnp.zeros((support.HEIGHT_BINS,), jnp.int32).at[1500].set(100))
    assert not bool(floor.found)


def test_floor_pixels_are_the_floors_and_need_the_floor_below_the_camera():
    T, depth, label = VIEWS[1]
    floor = support.floor_height(jnp.asarray(_floor_histogram(VIEWS)))
    samples = support.surface_samples(depth, T, K, UP, CONFIG)
    on_floor = np.asarray(support.floor_pixels(samples, floor, jnp.float32(0.05)))
    s = CONFIG.pixel_stride
    label = label[::s, ::s]
    assert not on_floor[label != 0].any()
    assert on_floor[_interior(label == 0)].mean() > 0.95
    # a camera 0.3 m above the floor found: that "floor" is taken for a table top seen from above, not filtered
    low = support.floor_pixels(samples._replace(camera_height=floor.height + 0.3), floor, jnp.float32(0.05))
    assert not np.asarray(low).any()


def _oracle_filter(det_image, on_floor, floor_detection, max_share, filtered):
    out = det_image.copy()
    for k in range(len(floor_detection)):
        pixels = det_image == k
        if not pixels.any() or floor_detection[k]:
            continue
        if (pixels & on_floor).sum() > max_share * pixels.sum():
            out[pixels] = filtered
        else:
            out[pixels & on_floor] = filtered
    return out


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(1, 6),
    max_share=st.floats(0.0, 1.0),
)
def test_filter_floor_pixels_matches_the_oracle(seed, n, max_share):
    rng = np.random.default_rng(seed)
    det_image = rng.integers(-1, n, size=(12, 17)).astype(np.int32)
    on_floor = rng.random((12, 17)) < rng.random()
    floor_detection = rng.random(n) < 0.3
    got = support.filter_floor_pixels(
        jnp.asarray(det_image), jnp.asarray(on_floor), jnp.asarray(floor_detection), jnp.float32(max_share), -2
    )
    np.testing.assert_array_equal(
        np.asarray(got), _oracle_filter(det_image, on_floor, floor_detection, np.float32(max_share), -2)
    )


def test_floor_vertices_are_the_up_facing_ones_near_the_floor():
    import trimesh

    from fmfusion_jax.io.vertex_transfer import floor_vertices

    u, v = np.meshgrid(np.linspace(-2, 2, 21), np.linspace(-2, 2, 21), indexing="ij")
    grid = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], 1)  # a floor at z = 0, 20 cm cells
    i = (np.arange(20)[:, None] * 21 + np.arange(20)[None, :]).ravel()
    faces = np.concatenate([np.stack([i, i + 21, i + 1], 1), np.stack([i + 1, i + 21, i + 22], 1)])
    floor = trimesh.Trimesh(grid, faces, process=False)
    box = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    box.apply_translation((0.0, 0.0, 0.25))  # a box standing on it
    mesh = trimesh.util.concatenate([floor, box])
    on_floor = floor_vertices(mesh.vertices, mesh.faces, (0.0, 0.0, 1.0), 0.0, 0.05)
    z = mesh.vertices[:, 2]
    floor_top = np.arange(len(mesh.vertices)) < len(floor.vertices)
    assert on_floor[floor_top].all() and (z[floor_top] == 0).all()
    assert not on_floor[~floor_top].any()  # the box: its base corners are near the floor but face sideways
    assert not floor_vertices(mesh.vertices, mesh.faces, (0.0, 0.0, 1.0), -1.0, 0.05).any()  # a floor far below


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), degenerate=st.booleans())
def test_vertex_normals_are_trimeshs(seed, degenerate):
    """The floor test's normals without trimesh: its angle-weighted vertex normals (the oracle), on random meshes
    with vertices of no face, repeated corners and zero-area faces."""
    import trimesh

    from fmfusion_jax.io.vertex_transfer import vertex_normals

    rng = np.random.default_rng(seed)
    vertices = rng.normal(size=(30, 3))
    faces = rng.integers(0, 25, size=(40, 3))  # vertices 25..29 in no face
    if degenerate:
        faces[:5, 1] = faces[:5, 0]  # a repeated corner: no normal
        vertices[26] = vertices[27]  # two vertices at one place
        faces[5] = (26, 27, 3)
    expected = trimesh.Trimesh(vertices, faces, process=False).vertex_normals
    np.testing.assert_allclose(vertex_normals(vertices, faces), expected, rtol=0, atol=1e-12)
