"""Likelihood calibration: the histogram identity against the engine, the parametrization, the gradient
against finite differences, the fit on synthetic instances, and matching instances to ground truth."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from fmfusion_jax.engine import label_fusion
from fmfusion_jax.labels import load_label_sets, load_likelihood, write_likelihood_csv
from fmfusion_jax.likelihood import calibrate as cal
from fmfusion_jax.likelihood.matching import match_instances, vertex_iou

LABELS = load_label_sets()
STATISTICAL = load_likelihood("statistical")
O, C = STATISTICAL.shape


def synthetic_instances(true: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """`n` instances of random classes, each fused from 1-5 detections whose label is drawn from the true
    likelihood's normalized column, with scores in [0.3, 0.9]: `(histograms (n, O), classes (n,))`."""
    q = true / true.sum(axis=0)
    classes = rng.integers(C, size=n)
    hist = np.zeros((n, O), np.float32)
    for i, c in enumerate(classes):
        for _ in range(rng.integers(1, 6)):
            hist[i, rng.choice(O, p=q[:, c])] += rng.uniform(0.3, 0.9)
    return hist, classes


# ----------------------------------------------------------------------------- parametrization


@settings(max_examples=40, deadline=None)
@given(st.sampled_from(cal.PARAMETRIZATIONS), hnp.arrays(np.float32, (O + 1, C), elements=st.floats(-40, 40, width=32)))
def test_parametrization_always_gives_a_valid_likelihood(parametrization, logits):
    logits = logits if parametrization == "column" else logits[:O]
    matrix = np.asarray(cal.likelihood_from_logits(jnp.asarray(logits), parametrization), np.float64)
    assert matrix.shape == (O, C) and np.all(np.isfinite(matrix))
    assert matrix.min() >= 0 and matrix.max() <= 1
    if parametrization == "column":
        assert np.all(matrix.sum(axis=0) <= 1 + 1e-5)


@settings(max_examples=20, deadline=None)
@given(st.sampled_from(cal.PARAMETRIZATIONS), st.integers(0, 2**32 - 1))
def test_logits_of_a_valid_matrix_give_it_back(parametrization, seed):
    rng = np.random.default_rng(seed)
    matrix = rng.random((O, C)) * (rng.random((O, C)) < 0.2)
    matrix *= rng.uniform(0.2, 0.95) / np.maximum(matrix.sum(axis=0), 1e-9)  # columns sum < 1
    back = cal.project_likelihood(matrix, parametrization)
    # zeros become ~floor; a column's other entries shrink by at most O * floor to make room
    np.testing.assert_allclose(back, matrix, atol=2 * cal.LOGIT_FLOOR, rtol=O * cal.LOGIT_FLOOR)


def test_column_parametrization_scales_columns_summing_over_one():
    back = cal.project_likelihood(STATISTICAL, "column")
    assert np.all(back.sum(axis=0) <= 1)
    over = STATISTICAL.sum(axis=0) > 1
    assert over.any()
    np.testing.assert_allclose(back[:, over].sum(axis=0), 1.0, atol=O * cal.LOGIT_FLOOR)
    # scaled, not reshaped (up to the floor given to zeros)
    np.testing.assert_allclose(
        back[:, over] / back[:, over].sum(axis=0),
        STATISTICAL[:, over] / STATISTICAL[:, over].sum(axis=0),
        atol=2 * cal.LOGIT_FLOOR,
        rtol=O * cal.LOGIT_FLOOR,
    )


# ----------------------------------------------------------------------------- loss and gradient


def test_gradient_matches_central_finite_differences():
    rng = np.random.default_rng(3)
    hist, classes = synthetic_instances(STATISTICAL, 30, rng)
    for parametrization in cal.PARAMETRIZATIONS:
        with jax.enable_x64(True):
            init = jnp.asarray(cal.logits_from_likelihood(STATISTICAL, parametrization), jnp.float64)
            logits = init + 0.3 * jnp.asarray(rng.standard_normal(init.shape))
            args = (jnp.asarray(hist, jnp.float64), jnp.asarray(classes), init, 0.01, parametrization)
            loss = lambda theta: cal.calibration_loss(theta, *args)  # noqa: E731
            grad = np.asarray(jax.grad(loss)(logits))
            assert grad.dtype == np.float64
            # the coordinates with the largest gradients, and random ones
            flat = np.concatenate([np.argsort(-np.abs(grad).ravel())[:6], rng.choice(grad.size, 6, replace=False)])
            eps = 1e-6
            for index in flat:
                step = np.zeros(grad.size)
                step[index] = eps
                step = jnp.asarray(step.reshape(grad.shape))
                numeric = (float(loss(logits + step)) - float(loss(logits - step))) / (2 * eps)
                assert numeric == pytest.approx(grad.ravel()[index], rel=1e-5, abs=1e-9)


def test_class_log_probs_is_the_engine_fusion():
    hist, _ = synthetic_instances(STATISTICAL, 10, np.random.default_rng(0))
    expected = label_fusion.class_distribution(hist @ STATISTICAL.astype(np.float32), "additive")
    got = np.exp(cal.class_log_probs(jnp.asarray(STATISTICAL, jnp.float32), jnp.asarray(hist)))
    np.testing.assert_allclose(got, expected, rtol=1e-5)


def test_calibration_lowers_the_loss_on_synthetic_instances():
    """Instances drawn from a known likelihood; the fit starts from the (wrong) manual matrix scaled to a
    valid column sum. It must lower the training loss, and on held-out instances beat the start in loss
    and match the true matrix's accuracy."""
    rng = np.random.default_rng(0)
    true = 0.6 * STATISTICAL / STATISTICAL.sum(axis=0)
    train, test = synthetic_instances(true, 400, rng), synthetic_instances(true, 400, rng)
    start = load_likelihood("manual") / 8
    fit = cal.fit_likelihood(cal.logits_from_likelihood(start), *train, steps=200, learning_rate=0.05, l2=1e-3)
    assert fit.losses.shape == (201,)
    assert fit.final_loss < 0.6 * fit.initial_loss
    assert fit.losses[-1] <= fit.losses[len(fit.losses) // 2] <= fit.losses[0]

    def nll(matrix):
        return float(cal.negative_log_likelihood(jnp.asarray(matrix, jnp.float32), jnp.asarray(test[0]), jnp.asarray(test[1])))

    assert nll(fit.likelihood) < nll(start) - 0.5
    assert cal.label_accuracy(fit.likelihood, *test) >= cal.label_accuracy(true, *test) - 0.03
    assert fit.likelihood.min() >= 0 and np.all(fit.likelihood.sum(axis=0) <= 1 + 1e-6)


def test_frozen_columns_keep_their_initial_values():
    rng = np.random.default_rng(1)
    hist, classes = synthetic_instances(STATISTICAL, 50, rng)
    init = cal.logits_from_likelihood(STATISTICAL)
    trainable = np.arange(C) % 2 == 0
    fit = cal.fit_likelihood(init, hist, classes, steps=20, trainable=trainable)
    np.testing.assert_array_equal(fit.logits[:, ~trainable], init[:, ~trainable])
    assert np.abs(fit.logits[:, trainable] - init[:, trainable]).max() > 0.1


# ----------------------------------------------------------------------------- cross-validation


def test_scene_folds_keep_each_scene_on_one_side():
    scenes = [f"s{i % 7}" for i in range(40)]
    folds = cal.scene_folds(scenes, 4)
    assert len(folds) == 4 and sorted(sum(folds, [])) == sorted(set(scenes))
    assert all(not set(a) & set(b) for i, a in enumerate(folds) for b in folds[i + 1 :])
    assert cal.scene_folds(["a", "b", "a"], 4) == [["a"], ["b"]]  # no more folds than scenes
    with pytest.raises(ValueError):
        cal.scene_folds(["a", "a"], 4)


def test_cross_validation_fits_on_the_other_scenes_only():
    """Each fold's path is a fit on the other folds' instances alone, evaluated on the fold's own."""
    rng = np.random.default_rng(4)
    hist, classes = synthetic_instances(STATISTICAL, 60, rng)
    scenes = [f"s{i % 6}" for i in range(60)]
    init = cal.logits_from_likelihood(STATISTICAL)
    cv = cal.cross_validate(init, hist, classes, scenes, (0.0, 1.0), steps=15, folds=3)
    assert cv.fold_losses.shape == (3, 2, 16) and cv.losses.shape == (2, 16)
    assert cv.fold_sizes.sum() == 60 and cv.folds == [["s0", "s3"], ["s1", "s4"], ["s2", "s5"]]
    # fold 0's fit uses only the instances of the other folds: fitting them directly gives its path
    held = np.isin(scenes, cv.folds[0])
    fit = cal.fit_likelihood(init, hist[~held], classes[~held], steps=15, l2=1.0)
    val = float(
        cal.negative_log_likelihood(jnp.asarray(fit.likelihood, jnp.float32), jnp.asarray(hist[held]), jnp.asarray(classes[held]))
    )
    assert cv.fold_losses[0, 1, -1] == pytest.approx(val, rel=1e-4)
    # the pooled loss weighs each instance once
    np.testing.assert_allclose(cv.losses, np.einsum("k,kgt->gt", cv.fold_sizes / 60, cv.fold_losses))
    assert cv.loss == pytest.approx(cv.losses.min())


def test_cross_validation_regularizes_more_with_few_noisy_instances():
    """Instances drawn from a known likelihood, the fit starting halfway between it and the (wrong) manual
    matrix. With many clean instances the fit should run long and free; with few instances half of whose
    classes are random, cross-validation must choose a stronger pull (at a fixed number of steps) and stop
    earlier (early stopping)."""
    true = 0.6 * STATISTICAL / STATISTICAL.sum(axis=0)
    init = cal.logits_from_likelihood(0.5 * true + 0.5 * load_likelihood("manual") / 8)

    def choose(n, noise, early_stopping):
        rng = np.random.default_rng(0)
        hist, classes = synthetic_instances(true, n, rng)
        classes = np.where(rng.random(n) < noise, rng.integers(C, size=n), classes)
        scenes = [f"scene{i % 8}" for i in range(n)]
        return cal.cross_validate(init, hist, classes, scenes, steps=200, folds=4, early_stopping=early_stopping)

    few, many = choose(48, 0.5, False), choose(800, 0.0, False)
    assert few.steps == many.steps == 200
    assert few.l2 >= 10 * max(many.l2, 1e-3)
    few, many = choose(48, 0.5, True), choose(800, 0.0, True)
    assert few.steps < many.steps / 4
    assert few.l2 >= many.l2
    # the choice is the best entry of the table
    assert few.loss == pytest.approx(min(r["loss_best"] for r in few.table()))
    # the fitted matrix at the chosen (l2, steps) beats the start on fresh instances of the clean case
    fresh = synthetic_instances(true, 400, np.random.default_rng(9))
    hist, classes = synthetic_instances(true, 800, np.random.default_rng(0))
    fit = cal.fit_likelihood(init, hist, classes, steps=many.steps, l2=many.l2)
    start = cal.likelihood_from_logits(jnp.asarray(init))

    def nll(matrix):
        return float(cal.negative_log_likelihood(jnp.asarray(matrix, jnp.float32), *map(jnp.asarray, fresh)))

    assert nll(fit.likelihood) < nll(start) - 0.3


def test_zero_steps_give_the_initial_matrix():
    init = cal.logits_from_likelihood(STATISTICAL)
    hist, classes = synthetic_instances(STATISTICAL, 10, np.random.default_rng(2))
    fit = cal.fit_likelihood(init, hist, classes, steps=0)
    np.testing.assert_array_equal(fit.logits, init)
    assert fit.losses.shape == (1,)


# ----------------------------------------------------------------------------- the engine and ground truth


def test_vertex_iou():
    gt_ids = np.array([0, 4, 4, 4, 9, 9, 2])
    pred = np.array([[0, 1, 1, 1, 1, 0, 0], [0, 0, 0, 0, 0, 1, 0]], bool)
    np.testing.assert_allclose(vertex_iou(pred, gt_ids, np.array([4, 9])), [[3 / 4, 1 / 5], [0, 1 / 2]])


@pytest.mark.slow
def test_histogram_identity_on_a_fused_map_and_matching(tmp_path):
    """In additive mode the engine's distribution of every final instance (merges included) is
    `class_distribution(h @ L)` of its open-label histogram, for the likelihood the map was fused with."""
    from fmfusion_jax.apps.likelihood.workflow import with_likelihood
    from fmfusion_jax.io.detections import DetectionFolder
    from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
    from fmfusion_jax.io.scene import open_scene
    from fmfusion_jax.mapping.export import extract_map_instances
    from fmfusion_jax.run.scene_fusion import fuse_scene
    from fmfusion_jax.simulation.demo_setup import demo_config, demo_noise
    from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, prepare_generated

    rng = np.random.default_rng(5)
    likelihood = 0.5 * STATISTICAL + 0.05 * rng.random((O, C)) * (rng.random((O, C)) < 0.3)  # not a packaged one
    csv = write_likelihood_csv(tmp_path / "l.csv", likelihood, LABELS)
    spec = GeneratedSceneSpec(seed=2, num_objects=4, num_frames=16, width=128, height=96)
    prepared = prepare_generated(spec, tmp_path, demo_noise(2, 128, 96), every=1)
    config = with_likelihood(demo_config(16, 128, 96, ["detections.every=1"]), csv)
    scene = open_scene(prepared.scene_dir)
    folder = DetectionFolder(prepared.detections_dir)
    result = fuse_scene(scene, lambda frame: folder.get(frame.name), config, progress=False)
    instances = extract_map_instances(result, LABELS, postprocess=False)
    assert len(instances) >= 3 and max(inst.observations for inst in instances) > 1
    hist = np.stack([inst.open_label_histogram for inst in instances])
    engine = np.stack([inst.distribution for inst in instances])
    ours = np.exp(np.asarray(cal.class_log_probs(jnp.asarray(likelihood, jnp.float32), jnp.asarray(hist))))
    np.testing.assert_allclose(ours, engine, atol=2e-6)

    # Matching: instances made of a ground-truth instance's own vertices match it (IoU below 1 only
    # because the transfer radius also claims neighbours' vertices at the border); one made of a third of
    # another instance's vertices does not.
    from fmfusion_jax.instances import MapInstance
    from fmfusion_jax.simulation.render import instance_classes

    gt = load_scannet_ground_truth(prepared.scene_dir)
    classes = instance_classes(gt, LABELS)
    ids = sorted(classes, key=lambda i: -np.count_nonzero(gt.instance_ids == i))[:3]
    fake = [
        MapInstance(k, np.eye(C)[k], gt.vertices[gt.instance_ids == i].astype(np.float32), 1, hist[0])
        for k, i in enumerate(ids[:2])
    ]
    half = gt.vertices[gt.instance_ids == ids[2]]
    fake.append(MapInstance(2, np.eye(C)[0], half[: len(half) // 3].astype(np.float32), 1, hist[0]))
    matched = match_instances(fake, gt, scene.name, LABELS, config.export.transfer_radius)
    assert len(matched) == 2 and matched.scenes == [scene.name] * 2
    assert np.all(matched.iou > 0.8)
    assert matched.classes.tolist() == [classes[i] for i in ids[:2]] and matched.predicted.tolist() == [0, 1]
    np.testing.assert_array_equal(matched.histograms, np.stack([hist[0], hist[0]]))
    assert len(match_instances(instances, gt, scene.name, LABELS)) <= len(instances)


def test_cli_regularization_errors(tmp_path, capsys):
    from fmfusion_jax.cli import main

    out = ["--out", str(tmp_path / "o")]
    assert main(["likelihood", "calibrate", "--folds", "1", *out]) == 2
    assert "--folds must be >= 2" in capsys.readouterr().err
    assert main(["likelihood", "calibrate", "--l2-grid", "0,x", *out]) == 2
    assert "--l2-grid" in capsys.readouterr().err
    assert main(["likelihood", "calibrate", "--train", "1", *out]) == 2
    assert "at least 2 training seeds" in capsys.readouterr().err
    assert main(["likelihood", "calibrate", "--steps", "0", "--l2", "0", *out]) == 2
    assert "--steps must be >= 1" in capsys.readouterr().err
