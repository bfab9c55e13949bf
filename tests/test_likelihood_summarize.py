"""Likelihood summarization (paper, Appendix B): counting core, matching, recovery of a known likelihood
from detections simulated with it, the CSV writer and the heat map."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from fmfusion_jax.io.heatmap import CELL_H, CELL_W, write_heatmap
from fmfusion_jax.labels import load_label_sets, load_likelihood, read_likelihood_csv, write_likelihood_csv
from fmfusion_jax.likelihood import summarize as S
from fmfusion_jax.types import FrameDetections

LABELS = load_label_sets()
O, C = LABELS.num_open, LABELS.num_classes


def sparse_known_likelihood(seed: int = 0, per_column: int = 3) -> np.ndarray:
    """A modified statistical matrix: each column keeps its `per_column` largest entries, with new random
    values (Dirichlet), so it differs from what the simulator uses by default."""
    rng = np.random.default_rng(seed)
    stat = load_likelihood("statistical")
    known = np.zeros_like(stat)
    for c in range(C):
        top = np.argsort(-stat[:, c], kind="stable")[:per_column]
        known[top, c] = rng.dirichlet(np.full(per_column, 2.0))
    return known


# ----------------------------------------------------------------------------- counting core


def test_counting_recovers_tagging_and_detection_factors():
    """Frames drawn from known factors T (tagging) and D (detection, a distribution over labels plus 'not
    detected' per class): the estimates are within 0.08 of each entry and the product within 0.01 mean
    absolute error per column (sampling error at ~400 frames per class)."""
    rng = np.random.default_rng(1)
    tagging = np.where(rng.random((O, C)) < 0.15, rng.uniform(0.3, 1.0, (O, C)), 0.0)
    detection = np.zeros((O, C))
    for c in range(C):
        labels = np.flatnonzero(tagging[:, c])
        if labels.size:
            detection[labels, c] = rng.dirichlet(np.ones(labels.size + 1))[:-1]  # last: not detected
    total = S.LikelihoodCounts.zeros(O, C)
    for _ in range(8000):
        c = int(rng.integers(C))  # one class per frame keeps p(o in q | c) exactly T[o, c]
        prompt = rng.random(O) < tagging[:, c]
        n = int(rng.integers(1, 3))
        weights = np.zeros((n, O))
        for m in range(n):
            candidate = rng.choice(O + 1, p=np.append(detection[:, c], 1.0 - detection[:, c].sum()))
            if candidate < O and prompt[candidate]:  # a detector outputs only labels of its prompt
                weights[m, candidate] = 1.0
        total = total + S.frame_counts(np.full(n, c), weights, prompt, C)
    est_tagging, est_detection, est = S.estimate(total)
    assert total.frames == 8000 and total.frames_observing.min() > 300
    assert np.abs(est_tagging - tagging).max() < 0.08
    has = tagging > 0
    assert np.abs(est_detection - detection)[has].max() < 0.08
    assert np.all(est[~has] == 0)
    assert np.abs(est - tagging * detection).mean(axis=0).max() < 0.01


def test_frame_counts_counts_undetected_instances_and_ignores_labels_outside_the_prompt():
    prompt = np.zeros(O, bool)
    prompt[[0, 4]] = True
    weights = np.zeros((3, O))
    weights[0, 4] = 1.0  # class 2 detected as label 4 (in the prompt)
    weights[1, 7] = 1.0  # class 2 "detected" as label 7, not in the prompt: not a detection of it
    # instance 2 (class 5) not detected
    counts = S.frame_counts(np.array([2, 2, 5]), weights, prompt, C)
    assert counts.frames == 1 and counts.instances == 3 and counts.matched == 2
    assert counts.frames_observing[[2, 5]].tolist() == [1, 1] and counts.frames_observing.sum() == 2
    assert counts.frames_prompting[[0, 4]][:, [2, 5]].tolist() == [[1, 1], [1, 1]]
    assert counts.frames_prompting.sum() == 4
    assert counts.instances_prompted[4, 2] == 2 and counts.instances_prompted[4, 5] == 1
    assert counts.instances_detected_as[4, 2] == 1 and counts.instances_detected_as.sum() == 1
    _, detection, likelihood = S.estimate(counts)
    assert detection[4, 2] == 0.5 and likelihood[4, 2] == 0.5 and likelihood[7, 2] == 0


def test_counts_add_and_survive_json():
    a = S.frame_counts(np.array([1]), np.eye(1, O, 3), np.eye(1, O, 3)[0] > 0, C)
    b = S.frame_counts(np.array([1, 1]), np.zeros((2, O)), np.ones(O, bool), C)
    total = a + b
    assert total.frames == 2 and total.instances == 3 and total.matched == 1
    again = S.LikelihoodCounts.from_dict(total.to_dict(LABELS))
    for name in ("frames_observing", "frames_prompting", "instances_prompted", "instances_detected_as"):
        np.testing.assert_array_equal(getattr(again, name), getattr(total, name))


def test_mask_iou_and_one_to_one_matching():
    gt = np.zeros((10, 10), np.int32)
    gt[:, :5] = 7
    gt[:, 5:] = 3
    masks = np.zeros((3, 10, 10), bool)
    masks[0, :, :5] = True  # exactly instance 7
    masks[1, :, 4:] = True  # instance 3 plus a column of 7: IoU 50/60
    masks[2, :5, :5] = True  # half of instance 7: IoU 0.5, but 7 is taken by the better mask 0
    iou = S.mask_iou(gt, np.array([7, 3]), masks)
    np.testing.assert_allclose(iou, [[1.0, 10 / 100, 0.5], [0.0, 50 / 60, 0.0]])
    assert S.match_one_to_one(iou).tolist() == [0, 1]
    assert S.match_one_to_one(iou, min_iou=0.9).tolist() == [0, -1]
    assert S.observed_instances(gt, {7: 4, 3: 9, 99: 1}, min_pixels=51)[0].size == 0  # 50 px each
    ids, classes = S.observed_instances(gt, {7: 4}, min_pixels=50)
    assert ids.tolist() == [7] and classes.tolist() == [4]


def test_detection_label_weights_main_and_weighted():
    labels = [{"chair": 0.5, "armchair": 0.3, "not a label": 0.9}, {}, {"table": 0.4}]
    main = S.detection_label_weights(labels, LABELS.open_labels, "main")
    weighted = S.detection_label_weights(labels, LABELS.open_labels, "weighted")
    chair, armchair, table = (LABELS.open_labels.index(n) for n in ("chair", "armchair", "table"))
    assert main[0, chair] == 1 and main.sum() == 2 and main[1].sum() == 0 and main[2, table] == 1
    np.testing.assert_allclose(weighted[0, [chair, armchair]], [0.625, 0.375])
    np.testing.assert_allclose(weighted.sum(axis=1), [1, 0, 1])


def test_frame_record_matches_detections_to_ground_truth():
    gt = np.zeros((20, 20), np.int32)
    gt[:10] = 1  # wall-class instance
    gt[10:, :10] = 2  # a chair, detected
    gt[10:, 10:] = 5  # a chair, missed
    masks = np.zeros((1, 20, 20), bool)
    masks[0, 10:, :10] = True
    dets = FrameDetections("frame-000000", masks, [{"armchair": 0.6}], np.zeros((1, 4), np.float32), prompt=["armchair", "wall"])
    wall, chair = LABELS.class_index("wall"), LABELS.class_index("chair")
    counts = S.frame_record(gt, {1: wall, 2: chair, 5: chair}, dets, LABELS, min_pixels=50)
    armchair = LABELS.open_labels.index("armchair")
    assert counts.instances == 3 and counts.matched == 1
    assert counts.instances_prompted[armchair, chair] == 2
    assert counts.instances_detected_as[armchair, chair] == 1
    assert counts.instances_detected_as[:, wall].sum() == 0


# ----------------------------------------------------------------------------- end to end


@pytest.mark.slow
def test_summarize_scene_recovers_the_likelihood_the_simulator_used(tmp_path):
    """A known sparse likelihood drives the simulator (clean masks, labels drawn from the likelihood's
    normalized columns, no missed tags or detections). The simulator's label model is
    q[:, c] = K[:, c] / sum(K[:, c]), and that is what the summary must recover: exact zeros where q is
    zero, column sums of about 1 (every visible object is detected), and each entry within 4 binomial standard
    deviations of q at the class's frame count, plus 0.02."""
    from fmfusion_jax.simulation.noise import NoiseModel
    from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, generated_scene, simulated_detections

    known = sparse_known_likelihood()
    scene_dir = generated_scene(GeneratedSceneSpec(seed=3, num_objects=8, num_frames=40, width=160, height=120), tmp_path)
    noise = NoiseModel.preset("clean", label_confusion=1.0, seed=1, min_mask_pixels=30)
    detections = simulated_detections(scene_dir, tmp_path / "detections", noise, likelihood=known)
    counts = S.summarize_scene(scene_dir, detections, LABELS, min_pixels=30)
    _, _, est = S.estimate(counts)

    q = known / known.sum(axis=0)
    seen = counts.frames_observing > 0
    assert counts.frames == 40 and seen.sum() >= 6 and counts.matched == counts.instances > 100
    assert np.all(est[q == 0] == 0)
    # ~1, not exactly: tagging counts frames, detection counts instances, and a frame may hold several
    # instances of a class (the walls)
    np.testing.assert_allclose(est[:, seen].sum(axis=0), 1.0, atol=0.02)
    n = counts.frames_observing[seen][None, :]
    bound = 4.0 * np.sqrt(q[:, seen] * (1 - q[:, seen]) / n) + 0.02
    assert np.all(np.abs(est[:, seen] - q[:, seen]) <= bound)
    # and the column error is small where the class is seen often
    often = counts.frames_observing >= 20
    assert np.abs(est - q)[:, often].mean(axis=0).max() < 0.02


# ----------------------------------------------------------------------------- files


def test_likelihood_csv_round_trip(tmp_path):
    matrix = np.random.default_rng(0).random((O, C)) * (np.random.default_rng(1).random((O, C)) < 0.3)
    matrix[0, 0] = 1e-17  # repr keeps every digit
    path = write_likelihood_csv(tmp_path / "m.csv", matrix, LABELS, comment="two\nlines")
    assert path.read_text().startswith("# two\n# lines\nopen_label,wall,")
    np.testing.assert_array_equal(read_likelihood_csv(path, LABELS), matrix)
    np.testing.assert_array_equal(load_likelihood(str(path)), matrix)
    with pytest.raises(ValueError, match="shape"):
        write_likelihood_csv(tmp_path / "bad.csv", matrix[:, :3], LABELS)


def test_write_summary_files(tmp_path):
    counts = S.frame_counts(np.array([2]), np.eye(1, O, 4), np.eye(1, O, 4)[0] > 0, C)
    paths = S.write_summary(tmp_path, counts, LABELS, sources=["a: b"])
    for name in ("likelihood", "tagging", "detection"):
        assert paths[f"{name}.png"].is_file()
        assert read_likelihood_csv(paths[f"{name}.csv"], LABELS)[4, 2] == 1.0
    assert '"frames": 1' in paths["counts.json"].read_text()


def test_heatmap_png_size(tmp_path):
    matrix = load_likelihood("statistical")
    image = write_heatmap(tmp_path / "h.png", matrix, LABELS.open_labels, LABELS.class_names, title="t")
    read = cv2.imread(str(tmp_path / "h.png"))
    assert read.shape == image.shape
    height, width = image.shape[:2]
    assert height > O * CELL_H + 60 and width > C * CELL_W + 100  # grid plus names and colour scale
    assert height < 1400 and width < 1400  # fits a screen at 100 %
    # the cell of the largest value is the colour scale's top (viridis yellow: high red and green in BGR)
    assert image[:, :, 2].max() > 200


# ----------------------------------------------------------------------------- command line


def test_cli_seeds_and_errors(tmp_path, capsys):
    from fmfusion_jax.apps.likelihood.commands import parse_seeds
    from fmfusion_jax.cli import main

    assert parse_seeds("1-3,7") == [1, 2, 3, 7] and parse_seeds("none") == []
    assert main(["likelihood", "summarize", "--out", str(tmp_path / "o")]) == 2
    assert "give SCENE folders" in capsys.readouterr().err
    assert (
        main(
            ["likelihood", "summarize", str(tmp_path), "--detections", str(tmp_path), str(tmp_path), "--out", str(tmp_path / "o")]
        )
        == 2
    )
    assert "one folder per SCENE" in capsys.readouterr().err
    assert main(["likelihood", "calibrate", "--train", "1-3", "--test", "3", "--out", str(tmp_path / "o")]) == 2
    assert "both training and held-out" in capsys.readouterr().err
