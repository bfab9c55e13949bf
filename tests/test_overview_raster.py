"""The overview's z-buffer: `_top_points` keeps, for each pixel, its highest point (to the millimetre, the
later of equal heights), on the fast scatter path and on the sorting fallback alike."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fmfusion_jax.viz.overview import _top_points


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
