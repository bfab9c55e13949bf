"""The ScanNet instance benchmark evaluator on hand-computed cases, and the vertex transfer.

AP arithmetic used in the comments: entries sorted by confidence give one curve point per distinct
confidence s (entries scoring >= s are positives, missed ground truth are false negatives), then the
appended point (p=1, r=0); AP = sum_i p_i * (r_{i-1} - r_{i+1}) / 2 with r_{-1} = r_0 and r_{n+1} = 0.
Thresholds: 0.50 ... 0.90 (nine, for AP), 0.50 (AP50) and 0.25 (AP25).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fmfusion_jax.errors import DataError
from fmfusion_jax.evaluation.scannet_benchmark import (
    OVERLAPS,
    average_precision,
    benchmark_class_names,
    evaluate_scenes,
    precision_recall_curve,
)
from fmfusion_jax.io.benchmark_format import InstancePredictions, export_ground_truth_as_predictions
from fmfusion_jax.io.vertex_transfer import points_to_vertex_masks, unique_rows

WALL, CABINET, BED, CHAIR = 1, 3, 4, 5
V = 1000


def ground_truth(*instances: tuple[int, int, int, int]) -> np.ndarray:
    """`(V,)` benchmark ids from `(start, stop, nyu40, instance)` vertex ranges; 0 elsewhere."""
    ids = np.zeros(V, np.int64)
    for start, stop, nyu40, instance in instances:
        ids[start:stop] = nyu40 * 1000 + instance
    return ids


def predictions(*items: tuple[list[tuple[int, int]], int, float]) -> InstancePredictions:
    """Predictions from `(vertex ranges, nyu40, confidence)`."""
    masks = np.zeros((len(items), V), bool)
    for k, (ranges, _, _) in enumerate(items):
        for start, stop in ranges:
            masks[k, start:stop] = True
    return InstancePredictions(masks, np.array([i[1] for i in items]), np.array([i[2] for i in items], float))


def scores(gt, preds, cls="cabinet"):
    result = evaluate_scenes([(gt, preds)])
    return result.ap[cls], result.ap50[cls], result.ap25[cls]


def test_overlaps_are_the_benchmark_floats():
    assert len(OVERLAPS) == 10 and OVERLAPS[-1] == 0.25
    np.testing.assert_allclose(OVERLAPS[:9], np.arange(0.50, 0.91, 0.05))
    assert OVERLAPS[2] > 0.6  # 0.6000000000000001: the arange float, not the literal


def test_class_names_follow_benchmark_ids():
    names = benchmark_class_names()
    assert len(names) == 18 and names[0] == "cabinet" and names[13] == "shower curtain"
    assert names[-1] == "otherfurniture"


def test_one_perfect_prediction_scores_one():
    # One point (p=1, r=1) + appended (1, 0): AP = 1*(1-0)/2 + 1*(1-0)/2 = 1.
    result = evaluate_scenes([(ground_truth((0, 200, CABINET, 1)), predictions(([(0, 200)], CABINET, 0.7)))])
    assert (result.ap["cabinet"], result.ap50["cabinet"], result.ap25["cabinet"]) == (1.0, 1.0, 1.0)
    assert math.isnan(result.ap["chair"])
    assert (result.mAP, result.mAP50, result.mAP25) == (1.0, 1.0, 1.0)
    assert result.gt_counts["cabinet"] == 1 and result.pred_counts["cabinet"] == 1


def test_false_positive_above_the_true_positive_gives_a_quarter():
    # TP 0.5, FP 0.9 (on bed vertices: not void). Points: s=0.5 -> (p=1/2, r=1); s=0.9 -> (0, 0); + (1, 0).
    # AP = 1/2 * (1 - 0)/2 + 0 * (1 - 0)/2 + 1 * (0 - 0)/2 = 0.25 (a step-function AP would say 0.5).
    # The bed has ground truth but no prediction: AP 0; mean over the two classes with ground truth 0.125.
    gt = ground_truth((0, 200, CABINET, 1), (300, 500, BED, 2))
    preds = predictions(([(0, 200)], CABINET, 0.5), ([(300, 500)], CABINET, 0.9))
    result = evaluate_scenes([(gt, preds)])
    assert (result.ap["cabinet"], result.ap50["cabinet"], result.ap25["cabinet"]) == (0.25, 0.25, 0.25)
    assert result.ap["bed"] == 0.0
    assert result.mAP == pytest.approx(0.125, abs=1e-15)


def test_false_positive_below_the_true_positive_costs_nothing():
    # s=0.5 -> (1/2, 1); s=0.9 -> (1, 1); + (1, 0): AP = 1/2*(1-1)/2 + 1*(1-0)/2 + 1*(1-0)/2 = 1.
    gt = ground_truth((0, 200, CABINET, 1), (300, 500, BED, 2))
    preds = predictions(([(0, 200)], CABINET, 0.9), ([(300, 500)], CABINET, 0.5))
    assert scores(gt, preds) == (1.0, 1.0, 1.0)


def test_two_hits_around_a_false_positive():
    # Entries T 0.9, F 0.8, T 0.7 (two GT): s=0.7 -> (2/3, 1); s=0.8 -> (1/2, 1/2); s=0.9 -> (1, 1/2); + (1, 0).
    # Widths: (1-1/2)/2, (1-1/2)/2, (1/2-0)/2, (1/2-0)/2 = 1/4 each: AP = (2/3 + 1/2 + 1 + 1)/4 = 19/24.
    gt = ground_truth((0, 200, CABINET, 1), (200, 400, CABINET, 2), (500, 700, BED, 3))
    preds = predictions(([(0, 200)], CABINET, 0.9), ([(500, 700)], CABINET, 0.8), ([(200, 400)], CABINET, 0.7))
    ap, ap50, ap25 = scores(gt, preds)
    assert ap == pytest.approx(19 / 24, abs=1e-15) and ap50 == ap25 == ap


def test_curve_and_integration_directly():
    precision, recall = precision_recall_curve(np.array([0.9, 0.8, 0.7]), np.array([True, False, True]), 0)
    np.testing.assert_allclose(precision, [2 / 3, 1 / 2, 1, 1])
    np.testing.assert_allclose(recall, [1, 1 / 2, 1 / 2, 0])
    # A missed instance halves the recall: one TP at s=1, (p=1, r=1/2) + (1, 0): AP = 1/4 + 1/4.
    assert average_precision(np.array([1.0]), np.array([True]), 1) == 0.5
    # Ties form a single point: T 1.0 and F 1.0 -> (1/2, 1) + (1, 0): AP = 1/2 * 1/2 + 1 * 1/2 = 3/4.
    assert average_precision(np.array([1.0, 1.0]), np.array([True, False]), 0) == 0.75
    assert average_precision(np.zeros(0), np.zeros(0, bool), 2) == 0.0
    assert math.isnan(average_precision(np.array([0.5]), np.array([False]), 0))


def test_predictions_on_void_are_ignored_not_false_positives():
    # Higher-confidence predictions on unlabelled vertices and on a wall (not a benchmark class): ignored at
    # every threshold, so the cabinet keeps AP 1 (as a false positive it would drop to 0.25).
    gt = ground_truth((0, 200, CABINET, 1), (600, 900, WALL, 2))
    preds = predictions(([(0, 200)], CABINET, 0.5), ([(300, 500)], CABINET, 0.9), ([(600, 800)], CABINET, 0.95))
    assert scores(gt, preds) == (1.0, 1.0, 1.0)


def test_partly_void_prediction_is_ignored_only_below_its_void_share():
    # The extra prediction has 120 of 200 vertices on void (share 0.6) and 80 on a bed: ignored where
    # 0.6 > threshold (0.50, 0.55, 0.25), a false positive at 0.6 ... 0.90 (0.6 <= 0.6000000000000001):
    # there AP = 0.25 (FP above the TP). AP = (2 * 1 + 7 * 0.25) / 9 = 5/12.
    gt = ground_truth((0, 200, CABINET, 1), (400, 480, BED, 2))
    preds = predictions(([(0, 200)], CABINET, 0.5), ([(280, 480)], CABINET, 0.9))
    ap, ap50, ap25 = scores(gt, preds)
    assert ap == pytest.approx(5 / 12, abs=1e-15) and ap50 == 1.0 and ap25 == 1.0


def test_iou_of_exactly_point_six_does_not_pass_point_six():
    # Prediction [50, 250): 150 on the 200-vertex instance, 50 on void -> IoU 150 / 250 = 0.6 exactly.
    # It matches at 0.50 and 0.55 (AP 1); from 0.6 on it is unmatched: a false positive (void share
    # 0.25 <= threshold) and the instance is missed -> AP 0. AP = 2/9.
    gt = ground_truth((0, 200, CABINET, 1))
    ap, ap50, ap25 = scores(gt, predictions(([(50, 250)], CABINET, 0.8)))
    assert ap == pytest.approx(2 / 9, abs=1e-15) and ap50 == 1.0 and ap25 == 1.0


def test_iou_of_exactly_one_half_does_not_pass_ap50():
    # 200 of 400 vertices on the instance, 200 on void: IoU 0.5, void share 0.5 <= every threshold >= 0.5
    # (a false positive, the instance missed: AP 0); AP25 passes.
    gt = ground_truth((0, 200, CABINET, 1))
    assert scores(gt, predictions(([(0, 400)], CABINET, 0.8))) == (0.0, 0.0, 1.0)


def test_class_without_ground_truth_is_nan_and_left_out_of_the_mean():
    gt = ground_truth((0, 200, CABINET, 1))
    preds = predictions(([(0, 200)], CABINET, 0.5), ([(300, 500)], CHAIR, 0.9), ([(0, 150)], CHAIR, 0.9))
    result = evaluate_scenes([(gt, preds)])
    assert math.isnan(result.ap["chair"]) and math.isnan(result.ap50["chair"]) and math.isnan(result.ap25["chair"])
    assert (result.mAP, result.mAP50, result.mAP25) == (1.0, 1.0, 1.0)
    assert result.to_json_dict()["classes"]["chair"]["AP"] is None


def test_no_ground_truth_at_all_gives_nan_means():
    result = evaluate_scenes([(np.zeros(V, np.int64), predictions(([(0, 200)], CABINET, 0.5)))])
    assert math.isnan(result.mAP) and math.isnan(result.mAP50) and math.isnan(result.mAP25)


def test_all_predictions_of_a_class_ignored_gives_zero():
    # Ground truth and a prediction exist, but the prediction lies on void: nothing scored, the instance
    # missed -> 0 (the reference script would index an empty array here).
    gt = ground_truth((0, 200, CABINET, 1))
    assert scores(gt, predictions(([(500, 700)], CABINET, 0.9))) == (0.0, 0.0, 0.0)


def test_predictions_under_100_vertices_are_dropped():
    # The 99-vertex prediction would be a false positive above the true positive (AP 0.25) if kept.
    gt = ground_truth((0, 200, CABINET, 1))
    preds = predictions(([(0, 200)], CABINET, 0.5), ([(0, 99)], CABINET, 0.9))
    assert scores(gt, preds) == (1.0, 1.0, 1.0)
    assert evaluate_scenes([(gt, preds)]).pred_counts["cabinet"] == 1
    # Alone, it leaves the class without predictions: AP 0.
    assert scores(gt, predictions(([(0, 99)], CABINET, 0.9))) == (0.0, 0.0, 0.0)


def test_small_ground_truth_is_not_counted_and_shields_predictions():
    # A 50-vertex cabinet is not counted. A prediction on it (+60 void vertices, IoU 50/110 = 0.45) is
    # matched to it at 0.25 (neither TP nor FP) and ignored above (void + small share 110/110 = 1).
    gt = ground_truth((0, 200, CABINET, 1), (300, 350, CABINET, 2))
    preds = predictions(([(0, 200)], CABINET, 0.5), ([(300, 350), (600, 660)], CABINET, 0.9))
    result = evaluate_scenes([(gt, preds)])
    assert (result.ap["cabinet"], result.ap50["cabinet"], result.ap25["cabinet"]) == (1.0, 1.0, 1.0)
    assert result.gt_counts["cabinet"] == 1


def test_prediction_covering_two_instances_matches_only_the_first():
    # One prediction over two 200-vertex instances: IoU 200/400 = 0.5 with each. At 0.25 it matches the
    # first instance (lower id) and is then taken, so the second is missed: (p=1, r=1/2) -> AP25 = 1/2.
    # At 0.50+ nothing matches: one FP, two misses -> 0.
    gt = ground_truth((0, 200, CABINET, 1), (200, 400, CABINET, 2))
    assert scores(gt, predictions(([(0, 400)], CABINET, 0.9))) == (0.0, 0.0, 0.5)


def test_duplicates_follow_the_benchmark_matching_rule():
    # Instances A = [0, 200), B = [200, 400). P1 = A (conf 0.3, listed first), P2 = A + 150 of B (conf 0.8):
    # IoU(P2, A) = 200/350 = 0.571, IoU(P2, B) = 150/400 = 0.375.
    # 0.25: A takes P1 (first listed); P2 also passes: FP at min(0.3, 0.8) = 0.3 and A scores 0.8. P2 is not
    #   taken, so B matches it too (TP 0.8). Entries T .8, T .8, F .3 -> (2/3, 1), (1, 1) + (1, 0): AP25 = 1.
    # 0.50, 0.55: A as above (T .8, F .3); B missed -> (1/2, 1/2), (1, 1/2) + (1, 0): 0 + 1/4 + 1/4 = 1/2.
    # 0.60 ... 0.90: A matches P1 only (T .3); P2 matches nothing: FP .8; B missed ->
    #   (1/2, 1/2), (0, 0) + (1, 0): 1/2 * 1/4 = 1/8.
    # AP = (2 * 1/2 + 7 * 1/8) / 9 = 15/72.
    gt = ground_truth((0, 200, CABINET, 1), (200, 400, CABINET, 2))
    preds = predictions(([(0, 200)], CABINET, 0.3), ([(0, 350)], CABINET, 0.8))
    ap, ap50, ap25 = scores(gt, preds)
    assert ap == pytest.approx(15 / 72, abs=1e-15) and ap50 == 0.5 and ap25 == 1.0


def test_scenes_are_pooled_per_class():
    # Scene 1: TP 0.9. Scene 2: the instance missed, an FP 0.95 on a bed. Pooled: T .9, F .95, one miss ->
    # (1/2, 1/2), (0, 0) + (1, 0): AP = 1/2 * 1/4 = 1/8 (not the mean of the per-scene 1 and 0).
    scene1 = (ground_truth((0, 200, CABINET, 1)), predictions(([(0, 200)], CABINET, 0.9)))
    scene2 = (ground_truth((0, 200, CABINET, 1), (300, 500, BED, 2)), predictions(([(300, 500)], CABINET, 0.95)))
    result = evaluate_scenes([scene1, scene2], scene_names=["a", "b"])
    assert result.ap["cabinet"] == pytest.approx(0.125, abs=1e-15)
    assert result.gt_counts["cabinet"] == 2 and result.scene_names == ("a", "b")


def test_vertex_count_mismatch_is_a_data_error():
    preds = InstancePredictions(np.ones((1, V - 1), bool), np.array([CABINET]), np.array([1.0]))
    with pytest.raises(DataError, match="sceneX: predictions cover 999 vertices but the ground truth has 1000"):
        evaluate_scenes([(ground_truth((0, 200, CABINET, 1)), preds)], scene_names=["sceneX"])


def test_table_and_json():
    result = evaluate_scenes([(ground_truth((0, 200, CABINET, 1)), predictions(([(0, 200)], CABINET, 0.7)))])
    lines = result.to_table().splitlines()
    assert len(lines) == 3 + 18 + 2
    assert lines[1].split() == ["what", ":", "AP", "AP_50%", "AP_25%"]
    assert lines[3].split() == ["cabinet", ":", "1.000", "1.000", "1.000"]
    assert lines[5].split() == ["chair", ":", "nan", "nan", "nan"]
    assert lines[-1].split() == ["average", ":", "1.000", "1.000", "1.000"]
    assert len({len(line) for line in lines}) == 1  # aligned
    summary = result.to_json_dict()
    assert summary["mAP"] == 1.0 and summary["classes"]["cabinet"] == {
        "AP": 1.0,
        "AP50": 1.0,
        "AP25": 1.0,
        "num_gt": 1,
        "num_pred": 1,
    }


# ---- properties on random scenes -------------------------------------------------------------------------


@st.composite
def random_scene(draw):
    """Ground truth of random instances and predictions near them (some shifted, merged, relabelled)."""
    classes = [CABINET, BED, CHAIR, WALL]
    cuts = sorted(draw(st.lists(st.integers(0, V), min_size=2, max_size=10, unique=True)))
    gt = np.zeros(V, np.int64)
    for k, (start, stop) in enumerate(zip(cuts[:-1], cuts[1:])):
        gt[start:stop] = draw(st.sampled_from(classes + [0])) * 1000 + k + 1
    items = []
    for _ in range(draw(st.integers(0, 8))):
        start = draw(st.integers(0, V - 1))
        stop = draw(st.integers(start + 1, V))
        items.append(([(start, stop)], draw(st.sampled_from(classes[:3])), draw(st.floats(0.01, 1.0))))
    return gt, (predictions(*items) if items else InstancePredictions.empty(V))


def assert_same(a, b):
    np.testing.assert_allclose(a.ap_table, b.ap_table, rtol=0, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(random_scene())
def test_random_scenes_properties(scene):
    gt, preds = scene
    result = evaluate_scenes([scene])
    finite = result.ap_table[np.isfinite(result.ap_table)]
    assert np.all((finite >= 0) & (finite <= 1 + 1e-12))
    # AP depends on the order of the confidences only.
    squashed = InstancePredictions(preds.masks, preds.nyu40_ids, preds.confidences * 0.5)
    assert_same(result, evaluate_scenes([(gt, squashed)]))
    # The same scene twice: every count doubles, the curve stays.
    assert_same(result, evaluate_scenes([scene, scene]))
    # A prediction lying on void only changes nothing.
    void = np.flatnonzero(~np.isin(gt // 1000, [CABINET, BED, CHAIR]))
    if len(void) >= 100:
        extra = np.zeros((1, V), bool)
        extra[0, void] = True
        more = InstancePredictions(
            np.concatenate([preds.masks, extra]), np.append(preds.nyu40_ids, CABINET), np.append(preds.confidences, 2.0)
        )
        assert_same(result, evaluate_scenes([(gt, more)]))
    # Ground truth scores 1 wherever there is ground truth.
    perfect = evaluate_scenes([(gt, export_ground_truth_as_predictions(gt))])
    counted = np.array([result.gt_counts[n] > 0 for n in result.class_names])
    assert np.all(perfect.ap_table[counted] == 1.0) and np.all(np.isnan(perfect.ap_table[~counted]))


# ---- vertex transfer -------------------------------------------------------------------------------------


def test_points_to_vertex_masks_nearest_instance_wins():
    vertices = np.array([[0.0, 0, 0], [0.05, 0, 0], [0.10, 0, 0], [1.0, 0, 0]])
    instance_a = np.array([[0.0, 0, 0]])
    instance_b = np.array([[0.12, 0, 0]])
    masks = points_to_vertex_masks(vertices, [instance_a, instance_b, np.zeros((0, 3))], radius=0.08)
    # Vertex 1 is 0.05 from A and 0.07 from B: A wins; vertex 2 (0.10 from A, 0.02 from B) goes to B;
    # vertex 3 is farther than the radius from both.
    np.testing.assert_array_equal(masks, [[1, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 0]])
    assert not np.any(masks.sum(axis=0) > 1)


@settings(max_examples=40, deadline=None)
@given(
    values=st.lists(st.tuples(*[st.sampled_from([-1.5, -0.0, 0.0, 0.25, 2.0])] * 3), max_size=30),
)
def test_unique_rows_is_numpys_unique_over_rows(values):
    rows = np.asarray(values, np.float64).reshape(-1, 3)
    expected_rows, expected_first = np.unique(rows, axis=0, return_index=True)
    got_rows, got_first = unique_rows(rows)
    np.testing.assert_array_equal(got_rows, expected_rows)
    np.testing.assert_array_equal(got_first, expected_first)


def test_points_to_vertex_masks_shared_point_goes_to_first_instance():
    vertices = np.array([[0.0, 0, 0]])
    point = np.array([[0.01, 0, 0]])
    np.testing.assert_array_equal(points_to_vertex_masks(vertices, [point, point]), [[True], [False]])
    assert points_to_vertex_masks(vertices, []).shape == (0, 1)


# ---- the real scene ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def real_gt_ids(scannet_scene):
    from fmfusion_jax.io.ground_truth import load_scannet_ground_truth

    return load_scannet_ground_truth(scannet_scene).benchmark_ids()


@pytest.mark.scannet
def test_real_scene_ground_truth_scores_one(real_gt_ids):
    result = evaluate_scenes([(real_gt_ids, export_ground_truth_as_predictions(real_gt_ids))], ["scene0000_00"])
    assert (result.mAP, result.mAP50, result.mAP25) == (1.0, 1.0, 1.0)
    assert sum(result.gt_counts.values()) == 25
    assert sum(not math.isnan(ap) for ap in result.ap.values()) == 14


@pytest.mark.scannet
def test_real_scene_known_errors(real_gt_ids):
    """Ground truth as predictions, then: one of the 6 cabinets dropped, one of the 2 windows called a door,
    a false positive above the sofa, and three predictions that must not count."""
    gt = export_ground_truth_as_predictions(real_gt_ids)
    masks, ids, conf = list(gt.masks), list(gt.nyu40_ids), list(gt.confidences)
    first = {c: ids.index(c) for c in (3, 4, 6, 9)}
    ids[first[9]] = 8  # window -> door: window 1 TP + 1 miss: AP 1/2; door gets an FP of
    #                                       confidence 1 tied with its TP: (1/2, 1) + (1, 0): 1/4 + 1/2 = 3/4
    conf[first[6]] = 0.5  # sofa TP at 0.5 and the bed's mask called a sofa at 0.9:
    masks.append(gt.masks[first[4]])  # (1/2, 1), (0, 0) + (1, 0): AP 1/4
    ids.append(6)
    conf.append(0.9)
    wall = real_gt_ids == real_gt_ids[np.flatnonzero(real_gt_ids // 1000 == 1)[0]]
    masks.append(wall)  # a table on a wall: void, ignored (table stays 1)
    ids.append(7)
    conf.append(0.99)
    tiny = np.zeros_like(wall)
    tiny[np.flatnonzero(gt.masks[first[4]])[:50]] = True
    masks.append(tiny)  # 50 vertices: dropped (the toilet stays 1)
    ids.append(33)
    conf.append(0.99)
    floor = real_gt_ids // 1000 == 2
    masks.append(floor)  # a chair on the floor: chair has no ground truth, stays nan
    ids.append(5)
    conf.append(0.9)
    drop = first[3]  # cabinet: 5 TP + 1 miss: (1, 5/6) + (1, 0): 5/12 + 5/12 = 5/6
    keep = [k for k in range(len(ids)) if k != drop]
    preds = InstancePredictions(np.stack(masks)[keep], np.array(ids)[keep], np.array(conf)[keep])

    result = evaluate_scenes([(real_gt_ids, preds)])
    expected = {"cabinet": 5 / 6, "window": 1 / 2, "door": 3 / 4, "sofa": 1 / 4}
    for name in ("bed", "table", "bookshelf", "counter", "desk", "curtain", "refrigerator", "toilet", "sink", "otherfurniture"):
        expected[name] = 1.0
    for table in (result.ap, result.ap50, result.ap25):
        assert {n: v for n, v in table.items() if not math.isnan(v)} == pytest.approx(expected, abs=1e-12)
        assert math.isnan(table["chair"])
    mean = (5 / 6 + 1 / 2 + 3 / 4 + 1 / 4 + 10) / 14
    assert (result.mAP, result.mAP50, result.mAP25) == pytest.approx((mean, mean, mean), abs=1e-12)


# ---- the command line --------------------------------------------------------------------------------------


@pytest.fixture
def cli_main(monkeypatch):
    """`fmfusion_jax.cli.main` with only the eval subcommand registered (independent of the others)."""
    import fmfusion_jax.cli as cli

    monkeypatch.setattr(cli, "SUBCOMMANDS", ("eval",))
    return cli.main


@pytest.mark.scannet
def test_cli_export_ground_truth_then_evaluate(cli_main, scannet_scene, tmp_path, capsys):
    import json

    out = tmp_path / "gt_as_pred"
    assert cli_main(["eval", "--gt", str(scannet_scene), "--export-gt", str(out)]) == 0
    assert (out / "scene0000_00.txt").is_file()
    assert (
        cli_main(["eval", str(out / "scene0000_00.txt"), "--gt", str(scannet_scene), "--json", str(tmp_path / "scores.json")])
        == 0
    )
    printed = capsys.readouterr().out
    assert "average        :          1.000          1.000          1.000" in printed
    summary = json.loads((tmp_path / "scores.json").read_text())
    assert (summary["mAP"], summary["mAP50"], summary["mAP25"]) == (1.0, 1.0, 1.0)
    assert summary["classes"]["cabinet"]["num_gt"] == 6 and summary["classes"]["chair"]["AP"] is None
    # Folder mode: a folder of predictions against the folder of scenes.
    assert cli_main(["eval", "--pred", str(out), "--gt", str(scannet_scene.parent)]) == 0


def test_cli_folders_of_predictions_and_gt_txt(cli_main, tmp_path, capsys):
    import json

    from fmfusion_jax.io.benchmark_format import write_benchmark_predictions

    gt_dir, pred_dir = tmp_path / "gt", tmp_path / "pred"
    gt_dir.mkdir()
    # Scene a: a perfect cabinet (conf 0.9). Scene b: the cabinet missed and an FP (0.95) on a bed.
    # Pooled: 1/8 (see test_scenes_are_pooled_per_class); the bed of b has no prediction: 0.
    (scene_a, preds_a), (scene_b, preds_b) = (
        (ground_truth((0, 200, CABINET, 1)), predictions(([(0, 200)], CABINET, 0.9))),
        (ground_truth((0, 200, CABINET, 1), (300, 500, BED, 2)), predictions(([(300, 500)], CABINET, 0.95))),
    )
    for name, gt, preds in (("a", scene_a, preds_a), ("b", scene_b, preds_b)):
        (gt_dir / f"{name}.txt").write_text("".join(f"{i}\n" for i in gt))
        write_benchmark_predictions(pred_dir, name, preds)
    (gt_dir / "c.txt").write_text("0\n" * V)  # ground truth found in a folder without predictions: skipped
    assert cli_main(["eval", str(pred_dir), "--gt", str(gt_dir), "--json", str(tmp_path / "s.json")]) == 0
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["scenes"] == ["a", "b"]
    assert summary["classes"]["cabinet"]["AP"] == pytest.approx(0.125) and summary["classes"]["bed"]["AP"] == 0.0
    assert "ScanNet instance benchmark, 2 scene(s): a, b" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["eval", "x.txt"], "no ground truth: pass --gt"),
        (["eval", "--gt", "{gt}"], "nothing to evaluate"),
        (["eval", "{pred}", "--gt", "{gt}", "--export-gt", "{tmp}/o"], "do not pass predictions with it"),
        (["eval", "{pred}", "--gt", "{tmp}/missing"], "--gt {tmp}/missing: no such file or folder"),
        (["eval", "{tmp}/missing.txt", "--gt", "{gt}"], "{tmp}/missing.txt: no such prediction file or folder"),
        (["eval", "{pred}", "{tmp}/other/q.txt", "--gt", "{gt}"], "no ground truth for scene(s) q"),
    ],
)
def test_cli_errors_are_one_line(cli_main, tmp_path, capsys, argv, message):
    from fmfusion_jax.io.benchmark_format import write_benchmark_predictions

    gt = tmp_path / "p.txt"
    gt.write_text("0\n" * V)
    write_benchmark_predictions(tmp_path / "pred", "p", InstancePredictions.empty(V))
    write_benchmark_predictions(tmp_path / "other", "q", InstancePredictions.empty(V))
    fill = {"gt": str(gt), "pred": str(tmp_path / "pred" / "p.txt"), "tmp": str(tmp_path)}
    assert cli_main([a.format(**fill) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fmfusion eval: error: ") and message.format(**fill) in err and err.count("\n") == 1


def test_cli_mask_length_mismatch_names_the_file(cli_main, tmp_path, capsys):
    from fmfusion_jax.io.benchmark_format import write_benchmark_predictions

    (tmp_path / "p.txt").write_text("0\n" * (V + 1))
    pred = write_benchmark_predictions(tmp_path / "pred", "p", predictions(([(0, 200)], CABINET, 0.9)))
    assert cli_main(["eval", str(pred), "--gt", str(tmp_path / "p.txt")]) == 2
    assert "p_0.txt (listed at" in capsys.readouterr().err


def test_cli_help(cli_main, capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli_main(["eval", "--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    for option in ("PRED", "--pred", "--gt", "--labels-tsv", "--json", "--export-gt"):
        assert option in text


def test_points_to_vertex_masks_by_neighbour_vote_keeps_interleaved_instances_whole():
    """A dense instance with a sparse one interleaved over it: the nearest point alone speckles the vertices
    between them, the vote of 8 neighbours gives them to the dense one; alone, the sparse one keeps its own."""
    rng = np.random.default_rng(0)
    vertices = np.stack(np.meshgrid(np.arange(0, 1, 0.02), np.arange(0, 1, 0.02), [0.0]), -1).reshape(-1, 3)
    dense = rng.uniform(0, 1, (4000, 3)) * [1, 1, 0]
    sparse = rng.uniform(0, 1, (800, 3)) * [1, 1, 0]
    nearest = points_to_vertex_masks(vertices, [dense, sparse], radius=0.08)
    voted = points_to_vertex_masks(vertices, [dense, sparse], radius=0.08, neighbours=8)
    assert 0.05 < nearest[1].mean() < 0.35  # speckled
    assert voted[0].mean() > 0.97 and voted[1].mean() < 0.03
    assert not np.any(voted[0] & voted[1])
    alone = points_to_vertex_masks(vertices, [np.zeros((0, 3)), sparse], radius=0.08, neighbours=8)
    np.testing.assert_array_equal(alone[1], points_to_vertex_masks(vertices, [sparse], radius=0.08)[0])
    far = points_to_vertex_masks(vertices + [0, 0, 1.0], [dense, sparse], radius=0.08, neighbours=8)
    assert not far.any()
