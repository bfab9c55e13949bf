"""The error analysis (`evaluation.explain`): every object status and prediction kind on hand-built
scenes, agreement with the evaluator's own AP50 matching, the files, `fmfusion eval --explain`, and the
files beside report.json of a run on a generated scene."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fmfusion_jax.evaluation.explain import GT_STATUSES, PREDICTION_KINDS, SHARE_NAMES, explain_scene
from fmfusion_jax.evaluation.explain_report import write_explanation
from fmfusion_jax.evaluation.scannet_benchmark import OVERLAPS, match_scene, scene_class_detections
from fmfusion_jax.io.benchmark_format import InstancePredictions, write_benchmark_predictions
from fmfusion_jax.labels import BENCHMARK_NYU40_IDS

WALL, FLOOR, CABINET, BED, CHAIR, SOFA, TABLE, DOOR, WINDOW, SINK = 1, 2, 3, 4, 5, 6, 7, 8, 9, 34

# One scene that has every status and every kind. Vertex ranges -> (nyu40, object id); 0 elsewhere.
SCENE = [
    ((0, 200), CABINET, 1),
    ((200, 400), BED, 2),
    ((400, 600), TABLE, 3),
    ((600, 800), DOOR, 4),
    ((800, 1000), WINDOW, 5),
    ((1000, 1050), SINK, 6),
    ((1050, 1250), WALL, 7),
    ((1250, 1400), FLOOR, 8),
]
V = 1450  # 1400..1450: void (unlabelled)
PREDICTIONS = [  # (vertex ranges, nyu40, confidence); the comment is the expected kind
    ([(0, 200)], CABINET, 0.9),  # 0 true_positive of the cabinet
    ([(0, 160)], CABINET, 0.5),  # 1 duplicate (IoU 0.8, lower confidence)
    ([(200, 400)], SOFA, 0.8),  # 2 wrong_class: the bed as a sofa
    ([(400, 500)], TABLE, 0.6),  # 3 fragment: half of the table (IoU exactly 0.5: no pass)
    ([(500, 600)], TABLE, 0.55),  # 4 fragment: the other half
    ([(600, 700), (1250, 1350)], DOOR, 0.7),  # 5 smear: half the door and as much floor (IoU 1/3)
    ([(1050, 1170)], CHAIR, 0.4),  # 6 no_object: on the wall only
    ([(1000, 1050)], SINK, 0.9),  # 7 not evaluated: 50 vertices
    ([(1050, 1250)], WALL, 0.9),  # 8 not evaluated: wall is not a benchmark class
]


def ground_truth(instances, num_vertices: int = V) -> np.ndarray:
    """`(V,)` benchmark ids from `((start, stop), nyu40, object id)`."""
    ids = np.zeros(num_vertices, np.int64)
    for (start, stop), nyu40, instance in instances:
        ids[start:stop] = nyu40 * 1000 + instance
    return ids


def predictions(items, num_vertices: int = V) -> InstancePredictions:
    masks = np.zeros((len(items), num_vertices), bool)
    for k, (ranges, _, _) in enumerate(items):
        for start, stop in ranges:
            masks[k, start:stop] = True
    return InstancePredictions(masks, np.array([i[1] for i in items]), np.array([i[2] for i in items], float))


def grid_vertices(gt_ids: np.ndarray) -> np.ndarray:
    """`(V, 3)`: vertex k at column k % 50, row k // 50 (5 cm apart); objects 0.5 m up, walls 1 m."""
    k = np.arange(len(gt_ids))
    nyu40 = gt_ids // 1000
    z = np.where(nyu40 == WALL, 1.0, np.where(np.isin(nyu40, [0, FLOOR]), 0.0, 0.5))
    return np.stack([(k % 50) * 0.05, (k // 50) * 0.05, z], axis=1)


def evaluator_counts(gt_ids, preds) -> tuple[int, int]:
    """True and false positives at AP50 by the evaluator itself, summed over the classes."""
    matches = match_scene(gt_ids, preds)
    detections = [scene_class_detections(matches, c, OVERLAPS[0]) for c in BENCHMARK_NYU40_IDS]
    return sum(int(d.is_true.sum()) for d in detections), sum(int((~d.is_true).sum()) for d in detections)


@pytest.fixture(scope="module")
def scene():
    gt_ids, preds = ground_truth(SCENE), predictions(PREDICTIONS)
    return gt_ids, preds, explain_scene(gt_ids, preds, grid_vertices(gt_ids), scene_name="hand")


def test_every_status_as_documented(scene):
    _, _, e = scene
    by_id = {g.gt_id: g for g in e.ground_truth}
    assert [g.gt_id for g in e.ground_truth] == [3001, 4002, 7003, 8004, 9005]  # the sink is under 100 vertices
    assert {g.gt_id: g.status for g in e.ground_truth} == {
        3001: "found",
        4002: "wrong_class",
        7003: "fragmented",
        8004: "low_iou",
        9005: "missed",
    }
    assert set(e.status_counts()) == set(GT_STATUSES) and all(v == 1 for v in e.status_counts().values())
    cabinet, bed, table, door, window = (by_id[i] for i in (3001, 4002, 7003, 8004, 9005))
    assert (cabinet.match, cabinet.best_prediction, cabinet.best_iou, cabinet.passes_50) == (0, 0, 1.0, True)
    assert (bed.best_prediction, bed.best_class, bed.best_iou, bed.best_same_class_iou) == (2, "sofa", 1.0, 0.0)
    assert not bed.passes_50 and bed.match is None
    assert table.num_fragments == 2 and table.best_same_class_iou == 0.5 and not table.passes_50 and table.passes_25
    assert door.best_same_class_iou == pytest.approx(1 / 3) and door.passes_25 and not door.passes_50
    assert (window.best_prediction, window.best_iou, window.num_fragments) == (None, 0.0, 0)
    assert cabinet.centroid is not None and len(cabinet.centroid) == 3


def test_every_kind_as_documented(scene):
    _, _, e = scene
    assert [(p.index, p.kind) for p in e.predictions] == [
        (0, "true_positive"),
        (1, "duplicate"),
        (2, "wrong_class"),
        (3, "fragment"),
        (4, "fragment"),
        (5, "smear"),
        (6, "no_object"),
    ]
    assert e.num_input_predictions == 9 and e.num_skipped_predictions == 2
    assert e.kind_counts() == {"true_positive": 1, "duplicate": 1, "wrong_class": 1, "smear": 1, "fragment": 2, "no_object": 1}
    # The benchmark's view: the duplicate, the wrong class, the fragments and the smear (floor is void to the
    # benchmark, but only half of it) are false positives; the prediction on the wall is ignored.
    assert [p.ap50 for p in e.predictions] == ["true_positive"] + ["false_positive"] * 5 + ["ignored"]
    smear, no_object = e.predictions[5], e.predictions[6]
    assert dict(zip(SHARE_NAMES, smear.shares)) == {
        "object": 0.5,
        "other_objects": 0.0,
        "small_objects": 0.0,
        "wall": 0.0,
        "floor": 0.5,
        "void": 0.0,
    }
    assert (smear.reference_gt, smear.best_gt, smear.best_iou) == (8004, 8004, pytest.approx(1 / 3))
    assert (no_object.reference_gt, no_object.best_gt, no_object.shares[SHARE_NAMES.index("wall")]) == (None, None, 1.0)
    for p in e.predictions:
        assert sum(p.shares) == pytest.approx(1.0, abs=1e-3)


def test_true_positives_are_the_evaluators(scene):
    gt_ids, preds, e = scene
    counts = e.ap50_counts()
    assert (counts["true_positive"], counts["false_positive"]) == evaluator_counts(gt_ids, preds) == (1, 5)
    assert e.kind_counts()["true_positive"] == counts["true_positive"]


@pytest.mark.parametrize("inside, kind", [(59, "smear"), (61, "fragment")])
def test_smear_or_fragment_decided_by_the_share_off_the_object(inside, kind):
    # 100 vertices: `inside` on the window (IoU >= 0.1: it overlaps), the rest on the floor.
    gt_ids = ground_truth(SCENE)
    preds = predictions([([(800, 800 + inside), (1250, 1350 - inside)], WINDOW, 0.5)])
    (p,) = explain_scene(gt_ids, preds).predictions
    assert p.kind == kind and p.reference_gt == 9005


@pytest.mark.parametrize("inside, kind", [(60, "fragment"), (45, "no_object")])
def test_small_piece_of_a_big_object(inside, kind):
    # A 2000-vertex bed: a 100-vertex piece neither overlaps it (IoU < 0.1, covers < 30 %) nor smears it;
    # it is a fragment when most of it lies inside, else no object.
    gt_ids = ground_truth([((0, 2000), BED, 1), ((2000, 2200), WALL, 2)], 2200)
    preds = predictions([([(0, inside), (2000, 2100 - inside)], BED, 0.5)], 2200)
    (p,) = explain_scene(gt_ids, preds).predictions
    assert p.kind == kind
    assert explain_scene(gt_ids, preds).ground_truth[0].status == "missed"


def test_precedence_of_the_statuses():
    gt_ids = ground_truth([((0, 300), CABINET, 1), ((300, 600), BED, 2), ((600, 900), TABLE, 3)], 900)
    preds = predictions(
        [
            ([(0, 120)], CABINET, 0.9),
            ([(0, 270)], BED, 0.8),  # cabinet: low IoU of its class, 0.9 as a bed
            ([(300, 400)], BED, 0.7),
            ([(400, 500)], BED, 0.7),
            ([(500, 600)], BED, 0.7),  # bed cut in three
            ([(600, 700)], TABLE, 0.6),  # table: one piece only (IoU 1/3)
        ],
        900,
    )
    e = explain_scene(gt_ids, preds)
    assert [g.status for g in e.ground_truth] == ["wrong_class", "fragmented", "low_iou"]
    bed = e.ground_truth[1]
    assert bed.passes_25 and bed.num_fragments == 3  # found at AP25, but the cut is what is reported
    assert [p.kind for p in e.predictions] == ["fragment", "wrong_class", "fragment", "fragment", "fragment", "fragment"]


def test_equal_confidences_match_the_first_and_ignored_predictions():
    gt_ids = ground_truth([((0, 200), CABINET, 1), ((200, 260), CABINET, 2), ((300, 500), WALL, 3)], 500)
    preds = predictions(
        [
            ([(0, 200)], CABINET, 0.7),
            ([(0, 190)], CABINET, 0.7),  # the same confidence: the first one matches
            ([(200, 260), (300, 345)], CABINET, 0.6),  # on the small cabinet (IoU 0.57): ignored
            ([(200, 250), (300, 360)], CABINET, 0.5),  # only small cabinet and wall: ignored
        ],
        500,
    )
    e = explain_scene(gt_ids, preds)
    assert [p.kind for p in e.predictions] == ["true_positive", "duplicate", "no_object", "no_object"]
    assert [p.ap50 for p in e.predictions] == ["true_positive", "false_positive", "ignored", "ignored"]
    assert e.predictions[3].shares[SHARE_NAMES.index("small_objects")] == pytest.approx(50 / 110, abs=1e-4)
    assert (e.ap50_counts()["true_positive"], e.ap50_counts()["false_positive"]) == evaluator_counts(gt_ids, preds)


@st.composite
def random_scene(draw):
    """Random instances (counted, small, wall, floor, void) and random predictions over them."""
    n = 600
    cuts = sorted(draw(st.lists(st.integers(0, n), min_size=2, max_size=9, unique=True)))
    gt = np.zeros(n, np.int64)
    for k, (start, stop) in enumerate(zip(cuts[:-1], cuts[1:])):
        gt[start:stop] = draw(st.sampled_from([CABINET, BED, CHAIR, WALL, FLOOR, 0])) * 1000 + k + 1
    items = []
    for _ in range(draw(st.integers(0, 10))):
        ranges = []
        for _ in range(draw(st.integers(1, 2))):
            start = draw(st.integers(0, n - 1))
            ranges.append((start, draw(st.integers(start + 1, n))))
        items.append((ranges, draw(st.sampled_from([CABINET, BED, CHAIR, WALL])), draw(st.floats(0.01, 1.0))))
    return gt, (predictions(items, n) if items else InstancePredictions.empty(n))


@settings(max_examples=60, deadline=None)
@given(random_scene())
def test_random_scenes_agree_with_the_evaluator(scene):
    gt_ids, preds = scene
    e = explain_scene(gt_ids, preds)
    counts = e.ap50_counts()
    assert (counts["true_positive"], counts["false_positive"]) == evaluator_counts(gt_ids, preds)
    assert e.kind_counts()["true_positive"] == counts["true_positive"] == e.status_counts()["found"]
    assert all(p.kind in PREDICTION_KINDS for p in e.predictions) and all(g.status in GT_STATUSES for g in e.ground_truth)
    for p in e.predictions:
        assert sum(p.shares) == pytest.approx(1.0, abs=1e-3)
    assert explain_scene(gt_ids, preds) == e  # deterministic


def test_files_and_picture(scene, tmp_path):
    gt_ids, preds, e = scene
    written = write_explanation(tmp_path / "x", e, gt_ids, preds, grid_vertices(gt_ids))
    assert [p.name for p in written] == ["explain.md", "explain.json", "explain.png"]
    text = written[0].read_text()
    for word in (*GT_STATUSES, *PREDICTION_KINDS, "| 8004 | door | 200 | low_iou |"):
        assert word in text, word
    data = json.loads(written[1].read_text())
    assert data["counts"]["objects"] == e.status_counts() and data["counts"]["predictions"] == e.kind_counts()
    assert data["classes"]["table"]["status"]["fragmented"] == 1 and data["classes"]["table"]["kind"]["fragment"] == 2
    assert len(data["ground_truth"]) == 5 and data["predictions"][5]["shares"]["floor"] == 0.5
    image = cv2.imread(str(written[2]))
    assert image is not None and image.shape[1] == 2 * 800 + 16 + 24
    rgb = image[..., ::-1].reshape(-1, 3)
    half = image.shape[1] // 2
    # the missed window in red on the left, the smear in its colour on the right
    assert np.all(image[:, :half][..., ::-1] == (220, 35, 35), axis=2).sum() > 100
    assert np.all(image[:, half:][..., ::-1] == (230, 40, 130), axis=2).sum() > 100
    assert len(np.unique(rgb, axis=0)) > 20
    # without vertices: no picture
    assert [p.name for p in write_explanation(tmp_path / "y", e)] == ["explain.md", "explain.json"]


# ---- fmfusion eval --explain and fmfusion run -------------------------------------------------------------


@pytest.fixture
def cli_main(monkeypatch):
    import fmfusion_jax.cli as cli

    monkeypatch.setattr(cli, "SUBCOMMANDS", ("eval",))
    return cli.main


@pytest.fixture(scope="module")
def generated_scene(tmp_path_factory):
    """A generated room written as a ScanNet scene folder (2 frames; its mesh ground truth is what counts)."""
    from fmfusion_jax.simulation.procedural import generate_scene
    from fmfusion_jax.simulation.scannet_writer import write_scannet_scene

    return write_scannet_scene(
        generate_scene(5, num_objects=4),
        tmp_path_factory.mktemp("gen") / "synth0005_00",
        num_frames=2,
        width=64,
        height=48,
        progress=False,
    )


def test_cli_explain_beside_the_json(cli_main, scene, tmp_path, capsys):
    gt_ids, preds, e = scene
    (tmp_path / "hand.txt").write_text("".join(f"{i}\n" for i in gt_ids))
    pred = write_benchmark_predictions(tmp_path / "pred", "hand", preds)
    assert cli_main(["eval", str(pred), "--gt", str(tmp_path / "hand.txt")]) == 0
    plain = capsys.readouterr().out
    assert (
        cli_main(["eval", str(pred), "--gt", str(tmp_path / "hand.txt"), "--json", str(tmp_path / "s" / "s.json"), "--explain"])
        == 0
    )
    printed = capsys.readouterr().out
    assert printed.startswith(plain)  # the benchmark's output unchanged, the analysis after it
    assert e.summary_line() in printed and "no explain.png" in printed
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == ["explain.json", "explain.md", "s.json"]


def test_cli_explain_writes_the_three_files(cli_main, generated_scene, tmp_path, capsys):
    from fmfusion_jax.io.benchmark_format import export_ground_truth_as_predictions
    from fmfusion_jax.io.ground_truth import load_scannet_ground_truth

    gt_ids = load_scannet_ground_truth(generated_scene).benchmark_ids()
    preds = export_ground_truth_as_predictions(gt_ids)
    pred = write_benchmark_predictions(tmp_path / "pred", generated_scene.name, preds)
    assert cli_main(["eval", str(pred), "--gt", str(generated_scene), "--explain", str(tmp_path / "why")]) == 0
    printed = capsys.readouterr().out
    counted = int(np.sum([np.sum(gt_ids == i) >= 100 for i in np.unique(gt_ids) if i // 1000 in BENCHMARK_NYU40_IDS]))
    assert f"{counted} objects: found {counted}," in printed
    for name in ("explain.md", "explain.json", "explain.png"):
        assert (tmp_path / "why" / name).stat().st_size > 0, name
    assert cv2.imread(str(tmp_path / "why" / "explain.png")) is not None
    # several scenes: one folder each
    other = write_benchmark_predictions(tmp_path / "pred", "copy", preds)
    copy = tmp_path / "gt"
    copy.mkdir()
    (copy / "copy.txt").write_text("".join(f"{i}\n" for i in gt_ids))
    assert (
        cli_main(
            [
                "eval",
                str(pred),
                str(other),
                "--gt",
                str(generated_scene),
                str(copy / "copy.txt"),
                "--explain",
                str(tmp_path / "many"),
            ]
        )
        == 0
    )
    assert (tmp_path / "many" / generated_scene.name / "explain.png").is_file()
    assert (tmp_path / "many" / "copy" / "explain.md").is_file()


def test_cli_explain_does_not_go_with_export_gt(cli_main, generated_scene, tmp_path, capsys):
    assert cli_main(["eval", "--gt", str(generated_scene), "--export-gt", str(tmp_path / "o"), "--explain"]) == 2
    assert "--explain" in capsys.readouterr().err


def test_run_scoring_writes_explain_beside_report(generated_scene, tmp_path):
    """The scoring writers of `fmfusion run` (benchmark, report.json, explain) on map instances taken from the
    generated room's ground truth: two objects whole, one cut in three, one smeared over the floor."""
    from fmfusion_jax.config import load_config
    from fmfusion_jax.instances import MapInstance
    from fmfusion_jax.io.scene import open_scene
    from fmfusion_jax.labels import load_label_sets
    from fmfusion_jax.run.command import load_ground_truth
    from fmfusion_jax.run.outputs import OutputContext, write_files

    label_sets = load_label_sets()
    scene = open_scene(generated_scene)
    gt = load_ground_truth(scene)
    ids = gt.benchmark_ids()
    objects = [i for i in np.unique(ids) if i // 1000 in BENCHMARK_NYU40_IDS and np.sum(ids == i) >= 100]
    floor = gt.vertices[ids // 1000 == FLOOR]

    def instance(k: int, points: np.ndarray, nyu40: int) -> MapInstance:
        distribution = np.full(len(label_sets.class_names), 0.01)
        distribution[list(label_sets.nyu40_ids).index(nyu40)] = 1.0
        return MapInstance(
            k, distribution / distribution.sum(), points.astype(np.float32), 3, np.zeros(len(label_sets.open_labels))
        )

    instances = []
    for k, object_id in enumerate(objects):
        points = gt.vertices[ids == object_id]
        if k == 2:  # cut in three along its longest side (pieces of IoU about 1/3)
            along = points[:, np.argmax(np.ptp(points[:, :2], axis=0))]
            piece = np.searchsorted(np.quantile(along, [1 / 3, 2 / 3]), along)
            instances += [instance(10 + j, points[piece == j], object_id // 1000) for j in range(3)]
        elif k == 3:  # with the floor around it
            near = np.linalg.norm(floor[:, :2] - points[:, :2].mean(0), axis=1) < 1.5
            instances.append(instance(k, np.concatenate([points, floor[near]]), object_id // 1000))
        else:
            instances.append(instance(k, points, object_id // 1000))
    config = load_config("scannet")
    out = tmp_path / "run"
    out.mkdir()
    context = OutputContext(scene, out, config, label_sets, instances, ground_truth=gt)  # a map without a floor
    write_files(context, names=("benchmark", "report.json", "explain"))
    benchmark = context.benchmark
    for name in ("report.json", "explain.md", "explain.json", "explain.png"):
        assert (out / name).stat().st_size > 0, name
    explained = json.loads((out / "explain.json").read_text())
    assert explained["counts"]["objects"] == benchmark["explain"]["objects"]
    assert explained["counts"]["objects"]["found"] == 2 and explained["counts"]["objects"]["fragmented"] == 1
    assert explained["counts"]["predictions"]["smear"] == 1 and explained["counts"]["predictions"]["fragment"] == 3
    # One object per class in this room: a class scores AP50 > 0 exactly when its object is a true positive. The
    # report scores the union hypotheses too (two of the three pieces, IoU about 2/3, find the cut object); the
    # analysis explains the instances only.
    report = json.loads((out / "report.json").read_text())
    scored = sum(c["AP50"] > 0 for c in report["classes"].values() if c["AP50"] is not None)
    assert explained["counts"]["ap50"]["true_positive"] == 2 and scored == 3
    assert benchmark["explain"]["seconds"] < 5


@pytest.mark.slow
def test_demo_run_writes_explain_beside_report(tmp_path):
    """A whole run (`run_demo`: generate, simulate, fuse, write) puts explain.* beside report.json."""
    from fmfusion_jax.apps.demo import run_demo

    # the room of test_demo.py's TINY demo: its steps are compiled already when the whole suite runs
    demo = run_demo(tmp_path / "out", seed=3, num_objects=4, num_frames=12, width=160, height=120, progress=False)
    for name in ("report.json", "explain.md", "explain.json", "explain.png"):
        assert (demo.out_dir / name).stat().st_size > 0, name
    run = json.loads((demo.out_dir / "run.json").read_text())
    explained = json.loads((demo.out_dir / "explain.json").read_text())
    assert run["benchmark"]["explain"]["objects"] == explained["counts"]["objects"]
    assert "explain.md" in demo.text


def test_no_predictions_and_no_objects(tmp_path):
    gt_ids = ground_truth(SCENE)
    e = explain_scene(gt_ids, InstancePredictions.empty(V))
    assert [g.status for g in e.ground_truth] == ["missed"] * 5 and e.predictions == ()
    walls = np.where(gt_ids // 1000 == WALL, gt_ids, 0)  # no object at all
    nothing = explain_scene(walls, predictions(PREDICTIONS))
    assert nothing.ground_truth == () and {p.kind for p in nothing.predictions} == {"no_object"}
    for name, explanation, ids, preds in (
        ("a", e, gt_ids, InstancePredictions.empty(V)),
        ("b", nothing, walls, predictions(PREDICTIONS)),
    ):
        written = write_explanation(tmp_path / name, explanation, ids, preds, grid_vertices(gt_ids))
        assert cv2.imread(str(written[-1])) is not None
