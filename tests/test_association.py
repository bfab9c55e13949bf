"""Detections as arrays, the detection image, depth filtering and data association vs NumPy references."""

from __future__ import annotations

import warnings

import chex
import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from oracles import reference_semantics as R

from fmfusion_jax.engine import association as A
from fmfusion_jax.engine import detections as D
from fmfusion_jax.types import FrameDetections

N, H, W, K, S, STRIDE = 6, 20, 28, 10, 2, 2
HS, WS = D.subsampled_shape(H, W, STRIDE)
CHECK = settings(max_examples=30, deadline=None)
seeds = st.integers(0, 2**32 - 1)


def random_masks(rng, n=N, h=H, w=W):
    """Rectangles, some nested inside an earlier one (part/whole overlaps like SAM's)."""
    masks = np.zeros((n, h, w), bool)
    for i in range(n):
        if i > 0 and rng.random() < 0.3:
            v, u = np.nonzero(masks[rng.integers(0, i)])
            if v.size:
                v0, u0 = v.min() + rng.integers(0, 3), u.min() + rng.integers(0, 3)
                masks[i, v0 : v0 + rng.integers(1, 6), u0 : u0 + rng.integers(1, 8)] = True
                continue
        v0, u0 = rng.integers(0, h - 2), rng.integers(0, w - 2)
        masks[i, v0 : v0 + rng.integers(2, h), u0 : u0 + rng.integers(2, w)] = True
    return masks


def random_frame(rng):
    masks = random_masks(rng)
    valid = rng.random(N) < 0.8
    pix = rng.integers(-1, K, (HS, WS, S)).astype(np.int32)
    dup = rng.random((HS, WS)) < 0.15
    pix[dup, 1] = pix[dup, 0]  # the same instance in two slots counts once
    depth = rng.uniform(0.2, 3.9, (HS, WS)).astype(np.float32)
    depth[rng.random((HS, WS)) < 0.1] = 0.0
    return masks, valid, depth, pix


# ----------------------------------------------------------------------------- packing


def _frame(masks, labels):
    return FrameDetections("frame-000000", masks, labels, np.zeros((len(labels), 4), np.float32))


def test_pack_detections_drops_pads_and_keeps_order():
    masks = np.zeros((4, 40, 50), bool)
    masks[0, :30, :30] = True  # 900 px
    masks[1, :5, :5] = True  # 25 px: too small
    masks[2, :20, :20] = True  # 400 px, label outside the open labels: no measurement
    masks[3, 10:40, 10:40] = True
    labels = [{"chair": 0.5, "armchair": 0.3}, {"chair": 0.9}, {"banana": 0.8}, {"table": 0.4}]
    batch = D.pack_detections(_frame(masks, labels), ["chair", "armchair", "table"], max_detections=5, min_mask_pixels=100)
    assert batch.masks.shape == (5, 40, 50) and batch.label_scores.shape == (5, 3)
    np.testing.assert_array_equal(batch.valid, [True, True, False, False, False])
    np.testing.assert_array_equal(batch.masks[0], masks[0])
    np.testing.assert_array_equal(batch.masks[1], masks[3])
    np.testing.assert_allclose(batch.label_scores[:2], [[0.5, 0.3, 0.0], [0.0, 0.0, 0.4]])
    assert not batch.masks[2:].any() and not batch.label_scores[2:].any()


def test_pack_detections_warns_and_keeps_the_highest_scoring():
    masks = np.ones((4, 10, 10), bool)
    labels = [{"chair": 0.3}, {"chair": 0.9}, {"table": 0.5}, {"table": 0.7}]
    with pytest.warns(RuntimeWarning, match="capacity 2"):
        batch = D.pack_detections(_frame(masks, labels), ["chair", "table"], max_detections=2, min_mask_pixels=1)
    np.testing.assert_allclose(batch.label_scores, [[0.9, 0.0], [0.0, 0.7]])  # original order kept
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        empty = D.pack_detections(FrameDetections.empty("f", 10, 10), ["chair"], 3, 1)
    assert empty.masks.shape == (3, 10, 10) and not empty.valid.any()


# ----------------------------------------------------------------------------- detection image


@CHECK
@given(seeds)
def test_detection_pixel_image_matches_reference(seed):
    rng = np.random.default_rng(seed)
    masks, valid, _, _ = random_frame(rng)
    got = np.asarray(D.detection_pixel_image(masks, valid, STRIDE))
    np.testing.assert_array_equal(got, R.detection_pixel_image(masks, valid, STRIDE))


@CHECK
@given(seeds, st.sampled_from([1, STRIDE, 3]))
def test_the_host_label_image_is_the_engine_detection_image(seed, stride):
    # what the host adapter sends (`pack_detections(..., as_image=True)`) is what the engine makes of the masks
    rng = np.random.default_rng(seed)
    masks, valid, _, _ = random_frame(rng)
    masks[2] = masks[1]  # an exact tie: the lower index wins on both sides
    labels = [{"chair": 0.5} if ok else {"banana": 0.9} for ok in valid]  # invalid rows: no open label, not packed
    frame = _frame(masks, labels)
    stack = D.pack_detections(frame, ["chair"], N + 2, 1, stride=stride)
    image = D.pack_detections(frame, ["chair"], N + 2, 1, stride=stride, as_image=True)
    assert image.masks is None and image.pixel_detection.dtype == np.int16
    np.testing.assert_array_equal(image.valid, stack.valid)
    np.testing.assert_array_equal(image.label_scores, stack.label_scores)
    expected = np.asarray(D.detection_pixel_image(stack.masks, stack.valid, 1))
    np.testing.assert_array_equal(image.pixel_detection, expected)
    got = np.asarray(D.batch_pixel_image(image, (H, W), stride))
    np.testing.assert_array_equal(got, np.asarray(D.batch_pixel_image(stack, (H, W), stride)))


@CHECK
@given(seeds, st.integers(1, 3), st.integers(1, 9), st.integers(1, 9))
def test_subsampled_masks_are_the_strided_pixels(seed, stride, h, w):
    masks = np.random.default_rng(seed).random((3, h, w)) < 0.5
    for m in (masks, masks[::-1], masks[:, :, ::-1]):  # contiguous or not
        got = D.subsampled_masks(m, stride)
        assert got.dtype == bool and got.flags.c_contiguous
        np.testing.assert_array_equal(got, m[:, ::stride, ::stride])


def test_an_empty_frame_packs_as_an_empty_label_image():
    empty = D.pack_detections(FrameDetections.empty("f", 10, 10), ["chair"], 3, 1, stride=2, as_image=True)
    assert empty.pixel_detection.shape == (5, 5) and (empty.pixel_detection == -1).all() and not empty.valid.any()
    unusable = D.pack_detections(_frame(np.ones((2, 10, 10), bool), [{"banana": 0.9}] * 2), ["chair"], 3, 1, 2, as_image=True)
    assert (unusable.pixel_detection == -1).all() and not unusable.valid.any()  # detections, none of them kept
    with pytest.raises(ValueError, match="pixel_detection has shape"):
        D.batch_pixel_image(empty, (10, 10), 1)


def test_smallest_mask_wins_the_overlap():
    masks = np.zeros((N, H, W), bool)
    masks[0] = True  # a bed
    masks[1, 4:8, 4:8] = True  # a pillow on it
    masks[2, 4:8, 4:8] = True  # the same pillow again: the lower index wins the tie
    valid = np.array([True, True, True, False, False, False])
    img = np.asarray(D.detection_pixel_image(masks, valid, 1))
    assert (img[4:8, 4:8] == 1).all()
    assert (img[masks[0] & ~masks[1]] == 0).all()
    valid[1] = False
    assert (np.asarray(D.detection_pixel_image(masks, valid, 1))[4:8, 4:8] == 2).all()


# ----------------------------------------------------------------------------- depth filter


@CHECK
@given(seeds, st.sampled_from([(0.1, 0.9), (0.0, 1.0), (0.25, 0.6)]))
def test_filter_detection_depth_matches_reference(seed, lohi):
    rng = np.random.default_rng(seed)
    masks, valid, depth, _ = random_frame(rng)
    det = np.asarray(D.detection_pixel_image(masks, valid, STRIDE))
    got = np.asarray(D.filter_detection_depth(det, depth, N, *lohi))
    np.testing.assert_array_equal(got, R.filter_detection_depth(det, depth, N, *lohi))
    assert ((got == det) | (got == -1)).all()
    assert (got[depth == 0] == -1).all()


@CHECK
@given(seeds)
def test_filter_detection_depth_brackets_numpy_percentiles_within_one_bin(seed):
    rng = np.random.default_rng(seed)
    det = np.where(rng.random((HS, WS)) < 0.9, 0, -1).astype(np.int32)
    depth = rng.uniform(0.2, 3.9, (HS, WS)).astype(np.float32)
    depth[: HS // 3] += rng.uniform(0, 0.3)  # a second depth layer
    got = np.asarray(D.filter_detection_depth(det, depth, N, 0.1, 0.9))
    d = depth[det == 0]
    p_lo, p_hi = np.percentile(d, [10, 90])
    kept = depth[got == 0]
    inside = (depth >= p_lo) & (depth <= p_hi) & (det == 0)
    assert (got[inside] == 0).all()  # everything between NumPy's percentiles is kept
    srt = np.sort(d)
    lo_stat, hi_stat = srt[int(np.floor(0.1 * (d.size - 1)))], srt[int(np.ceil(0.9 * (d.size - 1)))]
    assert kept.min() >= lo_stat - 0.01 - 1e-6 and kept.max() <= hi_stat + 0.01 + 1e-6  # one bin


# ----------------------------------------------------------------------------- association


@CHECK
@given(seeds)
def test_association_scores_and_matrices_match_reference(seed):
    rng = np.random.default_rng(seed)
    masks, valid, depth, pix = random_frame(rng)
    det = np.asarray(D.filter_detection_depth(D.detection_pixel_image(masks, valid, STRIDE), depth, N))
    counts = A.association_scores(det, pix, N, K)
    ref = R.association_scores(det, pix, N, K)
    for got, want in zip(counts, ref):
        np.testing.assert_array_equal(np.asarray(got), want)
    for metric in A.METRICS:
        got = np.asarray(A.association_score_matrix(*counts, metric=metric))
        np.testing.assert_allclose(got, R.association_score_matrix(*ref, metric), rtol=1e-6, atol=1e-7)
        assert (got >= 0).all() and (got <= 1).all()


@CHECK
@given(seeds)
def test_iou_is_symmetric_and_bounded(seed):
    rng = np.random.default_rng(seed)
    masks, valid, _, _ = random_frame(rng)
    det = np.asarray(D.detection_pixel_image(masks, valid, STRIDE))
    inst = np.asarray(D.detection_pixel_image(random_masks(rng, n=K), rng.random(K) < 0.8, STRIDE))
    forward = A.association_score_matrix(*A.association_scores(det, inst[..., None], N, K), metric="iou")
    swapped = A.association_score_matrix(*A.association_scores(inst, det[..., None], K, N), metric="iou")
    np.testing.assert_allclose(np.asarray(forward), np.asarray(swapped).T, rtol=1e-6)
    assert (np.asarray(forward) >= 0).all() and (np.asarray(forward) <= 1).all()


@CHECK
@given(seeds, st.booleans())
def test_match_detections_matches_greedy_reference(seed, one_to_one):
    rng = np.random.default_rng(seed)
    scores = rng.random((N, K)).astype(np.float32)
    if rng.random() < 0.5:  # every detection prefers the same instances: they must fall back down their lists
        scores = np.clip(np.sort(rng.random(K))[None, :] + rng.normal(0, 0.02, (N, K)), 0, 1).astype(np.float32)
    scores[rng.random((N, K)) < 0.2] = 0.7  # ties
    valid_det, valid_inst = rng.random(N) < 0.8, rng.random(K) < 0.7
    got = np.asarray(A.match_detections(scores, valid_det, valid_inst, 0.3, one_to_one=one_to_one))
    np.testing.assert_array_equal(got, R.match_detections(scores, valid_det, valid_inst, 0.3, one_to_one))
    m = got >= 0
    assert valid_det[m].all() and valid_inst[got[m]].all() and (scores[m, got[m]] > 0.3).all()
    if one_to_one:
        assert len(set(got[m])) == m.sum()


@CHECK
@given(seeds, st.booleans())
def test_match_detections_by_rank_matches_greedy_reference(seed, one_to_one):
    """Pairs pass by their score and match best first by their rank (association.rank: iou)."""
    rng = np.random.default_rng(seed)
    scores = rng.random((N, K)).astype(np.float32)
    rank = rng.random((N, K)).astype(np.float32)
    rank[rng.random((N, K)) < 0.2] = 0.5  # ties
    valid_det, valid_inst = rng.random(N) < 0.8, rng.random(K) < 0.7
    got = np.asarray(A.match_detections(scores, valid_det, valid_inst, 0.4, one_to_one=one_to_one, rank=rank))
    np.testing.assert_array_equal(got, R.match_detections(scores, valid_det, valid_inst, 0.4, one_to_one, rank))
    m = got >= 0
    assert (scores[m, got[m]] > 0.4).all()


def test_a_mask_over_a_small_instance_goes_to_the_instance_of_its_size_by_iou():
    """A wall's mask covers a door's projection whole and most of the wall's: by overlap the door takes it, by
    IoU the wall."""
    det = np.zeros((8, 8), np.int32)  # detection 0 everywhere
    seen = np.full((8, 8), 1, np.int32)  # instance 1 (the wall) ...
    seen[2:4, 2:4] = 0  # ... around instance 0 (the door)
    det[:, 7] = -1  # the wall's instance seen a little beyond the mask: overlap 52 / 60 against the door's 4 / 4
    counts = A.association_scores(det, seen[..., None], 1, 2)
    overlap = A.association_score_matrix(*counts, metric="projection_overlap")
    iou = A.association_score_matrix(*counts, metric="iou")
    valid_det, valid_inst = np.ones(1, bool), np.ones(2, bool)
    assert int(A.match_detections(overlap, valid_det, valid_inst, 0.5)[0]) == 0
    assert int(A.match_detections(overlap, valid_det, valid_inst, 0.5, rank=iou)[0]) == 1


@CHECK
@given(seeds)
def test_projection_overlap_matching_is_one_to_one_anyway(seed):
    """Disjoint detection masks: at most one detection covers more than half a projected instance."""
    rng = np.random.default_rng(seed)
    masks, valid, _, pix = random_frame(rng)
    det = np.asarray(D.detection_pixel_image(masks, valid, STRIDE))
    scores = A.association_score_matrix(*A.association_scores(det, pix, N, K), metric="projection_overlap")
    valid_inst = np.ones(K, bool)
    greedy = A.match_detections(scores, valid, valid_inst, 0.5, one_to_one=True)
    per_detection = A.match_detections(scores, valid, valid_inst, 0.5, one_to_one=False)
    np.testing.assert_array_equal(np.asarray(greedy), np.asarray(per_detection))


@CHECK
@given(seeds, st.floats(0.0, 1.0))
def test_allocate_instances_uses_free_slots_and_reports_overflow(seed, fill):
    rng = np.random.default_rng(seed)
    valid = rng.random(K) < fill
    needs = rng.random(N) < 0.7
    inst, new_valid, overflow = A.allocate_instances(valid, needs)
    inst, new_valid = np.asarray(inst), np.asarray(new_valid)
    ref = R.allocate_instances(valid, needs)
    np.testing.assert_array_equal(inst, ref[0])
    np.testing.assert_array_equal(new_valid, ref[1])
    assert int(overflow) == ref[2] == max(needs.sum() - (~valid).sum(), 0)
    given_out = inst[inst >= 0]
    assert not valid[given_out].any()  # never a valid slot
    assert len(set(given_out)) == given_out.size and (inst[~needs] == -1).all()
    assert new_valid.sum() == valid.sum() + given_out.size


def test_allocate_instances_on_a_full_table():
    inst, new_valid, overflow = A.allocate_instances(np.ones(K, bool), np.array([1, 0, 1, 1, 0, 0], bool))
    assert (np.asarray(inst) == -1).all() and np.asarray(new_valid).all() and int(overflow) == 3


def test_assign_detections_combines_matches_and_new_slots():
    valid = np.zeros(K, bool)
    valid[[0, 2]] = True
    matched = np.array([2, -1, -1, 0, -1, -1], np.int32)
    valid_det = np.array([1, 1, 0, 1, 1, 0], bool)
    out = A.assign_detections(matched, valid_det, valid)
    np.testing.assert_array_equal(np.asarray(out.instance_for_detection), [2, 1, -1, 0, 3, -1])
    np.testing.assert_array_equal(np.asarray(out.is_new), [0, 1, 0, 0, 1, 0])
    np.testing.assert_array_equal(np.flatnonzero(np.asarray(out.created)), [1, 3])
    assert int(out.overflow) == 0
    det = np.array([[0, 1, -1], [2, 4, 5]], np.int32)
    np.testing.assert_array_equal(np.asarray(A.instance_pixel_image(det, out.instance_for_detection)), [[2, 1, -1], [-1, 3, -1]])


# ----------------------------------------------------------------------------- no recompilation


def test_association_pipeline_compiles_once():
    chex.clear_trace_counter()

    @jax.jit
    @chex.assert_max_traces(n=1)
    def frame_step(masks, valid, depth, pix, valid_inst, threshold):
        det = D.filter_detection_depth(D.detection_pixel_image(masks, valid, STRIDE), depth, N)
        counts = A.association_scores(det, pix, N, K)
        scores = A.association_score_matrix(*counts, metric="iou")
        matched = A.match_detections(scores, valid, valid_inst, threshold)
        return A.assign_detections(matched, valid, valid_inst)

    jitted = [D.detection_pixel_image, D.filter_detection_depth, A.association_scores, A.match_detections]

    def standalone_calls(seed):  # the same call pattern each time, with different data
        rng = np.random.default_rng(seed)
        masks, valid, depth, pix = random_frame(rng)
        frame_step(masks, valid, depth, pix, rng.random(K) < 0.5, 0.1 + 0.1 * seed)
        det = D.filter_detection_depth(D.detection_pixel_image(masks, valid, STRIDE), depth, N, 0.1 + 0.05 * seed)
        A.association_scores(det, pix, N, K)
        A.match_detections(rng.random((N, K)).astype(np.float32), valid, np.ones(K, bool), 0.2 + 0.1 * seed)

    standalone_calls(0)
    before = [f._cache_size() for f in jitted]
    for seed in range(1, 4):
        standalone_calls(seed)
    assert [f._cache_size() for f in jitted] == before
