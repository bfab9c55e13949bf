"""The overview's z-buffer: `_top_points` keeps, for each pixel, its highest point (to the millimetre, the
later of equal heights), on the fast scatter path and on the sorting fallback alike; `_rasterize` splats discs
as a per-point z-buffer loop does."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fmfusion_jax.viz.overview import _rasterize, _top_points, disc_offsets


def _reference(idx: np.ndarray, z: np.ndarray) -> np.ndarray:
    zq = np.round((z - z.min()) * 1000).astype(np.int64)
    best: dict[int, int] = {}
    for i, (key, height) in enumerate(zip(idx.tolist(), zq.tolist())):
        if key not in best or height >= zq[best[key]]:
            best[key] = i
    return np.array([best[k] for k in sorted(best)], np.int64)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.integers(0, 40), st.integers(-3000, 3000)), min_size=1, max_size=200),
    st.sampled_from([1, 10**9]),
)
def test_top_points_keeps_the_highest_point_of_each_index(entries, spread):
    idx = np.array([i for i, _ in entries], np.int64) * spread  # a wide spread takes the sorting fallback
    z = np.array([h for _, h in entries], np.float64) / 1000.0
    np.testing.assert_array_equal(_top_points(idx, z), _reference(idx, z))


def test_top_points_of_nothing_is_empty():
    assert _top_points(np.zeros(0, np.int64), np.zeros(0)).shape == (0,)


def _rasterize_reference(shape, u, v, z, colors, radii):
    """A z-buffer loop over the splats: each radius's highest point per pixel (the later of equals), then, in
    (radius, pixel) order, each one's disc over a pixel wherever it is higher than, or as high as, what is there."""
    height, width = shape
    inside = [i for i in range(len(u)) if 0 <= u[i] < width and 0 <= v[i] < height]
    if not inside:
        return np.zeros((height, width, 3), np.uint8), np.zeros((height, width), bool)
    zq = np.round((z - z[inside].min()) * 1000).astype(np.int64)
    top: dict[tuple[int, int], int] = {}
    for i in inside:
        key = (int(radii[i]), int(v[i] * width + u[i]))
        if key not in top or zq[i] >= zq[top[key]]:
            top[key] = i
    kept = [top[key] for key in sorted(top)]
    mm = np.round((z[kept] - z[kept].min()) * 1000).astype(np.int64)
    image, covered = np.zeros((height, width, 3), np.uint8), np.zeros((height, width), bool)
    best = np.full((height, width), -1, np.int64)
    for point, height_mm in zip(kept, mm.tolist()):
        for dx, dy in disc_offsets(int(radii[point])).tolist():
            x, y = u[point] + dx, v[point] + dy
            if 0 <= x < width and 0 <= y < height and height_mm >= best[y, x]:
                best[y, x], image[y, x], covered[y, x] = height_mm, colors[point], True
    return image, covered


@settings(max_examples=80, deadline=None)
@given(
    st.integers(1, 12),
    st.integers(1, 10),
    st.lists(
        st.tuples(st.integers(-3, 14), st.integers(-3, 12), st.integers(0, 6), st.integers(1, 3), st.integers(0, 255)),
        min_size=1,
        max_size=40,
    ),
)
def test_rasterize_splats_discs_as_a_z_buffer_loop(width, height, splats):
    u, v, z_mm, radius, grey = (np.array(column) for column in zip(*splats))
    z = z_mm / 1000.0 + 0.25  # few heights: many ties, broken as the loop breaks them
    colors = np.stack([grey, 255 - grey, grey // 2], axis=1).astype(np.uint8)
    image, covered = _rasterize((height, width), u.astype(np.int32), v.astype(np.int32), z, colors, radius.astype(np.int8))
    expected_image, expected_covered = _rasterize_reference((height, width), u, v, z, colors, radius)
    np.testing.assert_array_equal(covered, expected_covered)
    np.testing.assert_array_equal(image, expected_image)
