"""Label fusion (additive and Bayes) vs NumPy references, its laws, and its gradient."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from oracles import reference_semantics as R

from fmfusion_jax.engine import label_fusion as LF
from fmfusion_jax.labels import load_label_sets, load_likelihood, normalize_columns

N, K = 8, 12
LIKELIHOOD = load_likelihood("statistical").astype(np.float32)  # (38, 20), mostly zeros
MANUAL = load_likelihood("manual").astype(np.float32)
O, C = LIKELIHOOD.shape
CHECK = settings(max_examples=30, deadline=None)
seeds = st.integers(0, 2**32 - 1)


def random_detections(rng, n=N, k=K):
    """Scores on 1-3 labels per detection, instances with collisions, some invalid or unassigned."""
    scores = np.zeros((n, O), np.float32)
    for i in range(n):
        labels = rng.choice(O, size=rng.integers(1, 4), replace=False)
        scores[i, labels] = rng.uniform(0.25, 1.0, labels.size)
    inst = rng.integers(-1, k // 2, n).astype(np.int32)  # few instances: several detections each
    valid = rng.random(n) < 0.85
    return scores, inst, valid


def random_likelihood(rng):
    return LIKELIHOOD if rng.random() < 0.5 else rng.random((O, C)).astype(np.float32) * (rng.random((O, C)) < 0.3)


# ----------------------------------------------------------------------------- against references


@CHECK
@given(seeds)
def test_measurements_match_reference(seed):
    rng = np.random.default_rng(seed)
    scores, _, _ = random_detections(rng)
    lik = random_likelihood(rng)
    np.testing.assert_allclose(
        np.asarray(LF.measurement_likelihood(scores, lik)), R.measurement_likelihood(scores, lik), rtol=1e-5, atol=1e-6
    )
    for weighted in (False, True):
        np.testing.assert_allclose(
            np.asarray(LF.measurement_log_likelihood(scores, lik, 1e-3, weighted)),
            R.measurement_log_likelihood(scores, lik, 1e-3, weighted),
            rtol=1e-5,
            atol=1e-4,
        )


@CHECK
@given(seeds, st.sampled_from(LF.MODES), st.booleans())
def test_fusion_matches_reference(seed, mode, with_reset):
    rng = np.random.default_rng(seed)
    scores, inst, valid = random_detections(rng)
    lik = random_likelihood(rng)
    # Some evidence from an earlier frame.
    s0, i0, v0 = random_detections(rng)
    evidence = np.asarray(LF.fuse_labels(np.zeros((K, C), np.float32), i0, s0, lik, v0, mode))
    reset = (rng.random(K) < 0.3) if with_reset else None
    got = np.asarray(LF.fuse_labels(evidence, inst, scores, lik, valid, mode, reset))
    values = R.measurement_likelihood(scores, lik) if mode == "additive" else R.measurement_log_likelihood(scores, lik)
    want = R.fuse(evidence, inst, values, valid, mode, reset)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=2e-4)
    np.testing.assert_allclose(
        np.asarray(LF.class_distribution(got, mode)), R.class_distribution(want, mode), rtol=1e-4, atol=1e-5
    )


@CHECK
@given(seeds, st.booleans())
def test_label_statistics_match_reference(seed, with_reset):
    rng = np.random.default_rng(seed)
    scores, inst, valid = random_detections(rng)
    hist = rng.random((K, O)).astype(np.float32)
    obs = rng.integers(0, 9, K).astype(np.int32)
    reset = (rng.random(K) < 0.3) if with_reset else None
    got_hist, got_obs = LF.update_label_statistics(hist, obs, inst, scores, valid, reset)
    want_hist, want_obs = R.update_label_statistics(hist, obs, inst, scores, valid, reset)
    np.testing.assert_allclose(np.asarray(got_hist), want_hist, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(got_obs), want_obs)
    assert got_obs.dtype == jnp.int32


# ----------------------------------------------------------------------------- laws


def fuse_frames(frames, lik, mode, evidence=None):
    evidence = np.zeros((K, C), np.float32) if evidence is None else evidence
    for scores, inst, valid in frames:
        evidence = LF.fuse_labels(evidence, inst, scores, lik, valid, mode)
    return np.asarray(evidence)


@CHECK
@given(seeds, st.sampled_from(LF.MODES), st.sampled_from([0.0, 1.0]))
def test_distributions_are_normalized(seed, mode, prior_weight):
    rng = np.random.default_rng(seed)
    lik = random_likelihood(rng)
    evidence = fuse_frames([random_detections(rng) for _ in range(3)], lik, mode)
    dist = np.asarray(LF.class_distribution(evidence, mode, prior_weight))
    assert dist.shape == (K, C) and (dist >= 0).all()
    np.testing.assert_allclose(dist.sum(1), 1.0, rtol=1e-5)
    untouched = ~evidence.any(axis=1)  # no measurement (or only uninformative ones): uniform prior
    np.testing.assert_allclose(dist[untouched], 1.0 / C, rtol=1e-5)
    cls, conf = np.asarray(LF.predicted_class(dist)), np.asarray(LF.confidence(dist))
    np.testing.assert_array_equal(cls, dist.argmax(1))
    np.testing.assert_allclose(conf, dist.max(1))


@CHECK
@given(seeds)
def test_additive_fusion_does_not_depend_on_order(seed):
    rng = np.random.default_rng(seed)
    lik = random_likelihood(rng)
    frames = [random_detections(rng) for _ in range(4)]
    reference = fuse_frames(frames, lik, "additive")
    # Frames in another order.
    order = rng.permutation(len(frames))
    np.testing.assert_allclose(fuse_frames([frames[i] for i in order], lik, "additive"), reference, rtol=1e-5, atol=1e-6)
    # Detections shuffled across frames (same multiset of measurements).
    pooled = [np.concatenate(x) for x in zip(*frames)]
    perm = rng.permutation(len(pooled[0]))
    shuffled = [tuple(x[perm][j : j + N] for x in pooled) for j in range(0, len(perm), N)]
    np.testing.assert_allclose(fuse_frames(shuffled, lik, "additive"), reference, rtol=1e-5, atol=1e-6)


@CHECK
@given(seeds)
def test_additive_measurement_never_lowers_evidence(seed):
    rng = np.random.default_rng(seed)
    lik = random_likelihood(rng)
    before = fuse_frames([random_detections(rng)], lik, "additive")
    scores, inst, valid = random_detections(rng)
    after = fuse_frames([(scores, inst, valid)], lik, "additive", before)
    assert (after >= before).all()
    # The measured classes grow: a label with a positive likelihood for class c raises c's evidence.
    z = R.measurement_likelihood(scores, lik)
    for i in np.flatnonzero(valid & (inst >= 0)):
        raised = z[i] > 0
        assert (after[inst[i], raised] > before[inst[i], raised]).all()


@CHECK
@given(seeds)
def test_additive_evidence_is_the_paper_recursion(seed):
    """p_t = (z_t + (t-1) p_{t-1}) / t unrolls to the mean of the measurements: evidence / t."""
    rng = np.random.default_rng(seed)
    lik = random_likelihood(rng)
    t = int(rng.integers(1, N + 1))
    scores = random_detections(rng)[0][:t]
    inst = np.zeros(t, np.int32)
    pad = N - t
    evidence = fuse_frames(
        [(np.pad(scores, ((0, pad), (0, 0))), np.pad(inst, (0, pad), constant_values=-1), np.arange(N) < t)], lik, "additive"
    )
    p_t = R.paper_additive_recursion(list(R.measurement_likelihood(scores, lik)))
    np.testing.assert_allclose(evidence[0] / t, p_t, rtol=1e-5, atol=1e-7)
    if p_t.sum() > 0:
        dist = np.asarray(LF.class_distribution(evidence, "additive", prior_weight=0.0))[0]
        np.testing.assert_allclose(dist, p_t / p_t.sum(), rtol=1e-5, atol=1e-7)
        assert dist.argmax() == np.asarray(LF.class_distribution(evidence, "additive"))[0].argmax()


def test_bayes_is_the_normalized_product_of_likelihoods():
    rng = np.random.default_rng(3)
    lik = np.maximum(MANUAL, 0.05)  # no entry below the floor: the product is exact
    scores, _, _ = random_detections(rng)
    inst, valid = np.zeros(N, np.int32), np.ones(N, bool)
    dist = np.asarray(LF.class_distribution(fuse_frames([(scores, inst, valid)], lik, "bayes"), "bayes"))[0]
    product = np.ones(C)
    for row in scores:
        for y in np.flatnonzero(row > 0):
            product *= lik[y]
    np.testing.assert_allclose(dist, product / product.sum(), rtol=1e-4)


def test_bayes_floor_lets_a_zeroed_class_recover():
    lik = np.zeros((O, C), np.float32)
    lik[0, 0] = 1.0  # label 0 says class 0; class 1 has likelihood 0 under it
    lik[1, 1] = 1.0
    inst, valid = np.zeros(N, np.int32), np.arange(N) < 1
    one = lambda y: np.eye(O, dtype=np.float32)[[y] * N]  # noqa: E731
    evidence = fuse_frames([(one(0), inst, valid)], lik, "bayes")
    dist = np.asarray(LF.class_distribution(evidence, "bayes"))[0]
    assert dist[1] > 0 and dist.argmax() == 0
    evidence = fuse_frames([(one(1), inst, valid)] * 2, lik, "bayes", evidence)
    assert np.asarray(LF.predicted_class(LF.class_distribution(evidence, "bayes")))[0] == 1
    assert np.isfinite(evidence).all() and (evidence.max(1) == 0).all()


def test_unknown_mode_is_an_error():
    with pytest.raises(ValueError, match="unknown label fusion mode"):
        LF.class_distribution(np.zeros((K, C), np.float32), "average")


# ----------------------------------------------------------------------------- gradient


def test_gradient_wrt_likelihood_matches_finite_differences():
    """Users calibrate the likelihood matrix by gradient descent through the additive fusion."""
    rng = np.random.default_rng(0)
    with jax.enable_x64(True):
        scores, inst, valid = random_detections(rng)
        scores = scores.astype(np.float64)
        target = rng.integers(0, C, K)
        lik0 = jnp.asarray(0.05 + rng.random((O, C)), jnp.float64)
        evidence0 = jnp.zeros((K, C), jnp.float64)

        def loss(lik):
            z = LF.measurement_likelihood(scores, lik)
            dist = LF.class_distribution(LF.fuse_additive(evidence0, inst, z, valid), "additive")
            return -jnp.sum(jnp.log(dist[jnp.arange(K), target]))

        grad = np.asarray(jax.grad(loss)(lik0))
        assert grad.dtype == np.float64 and np.abs(grad).max() > 0
        h = 1e-6
        for _ in range(12):
            o, c = rng.integers(0, O), rng.integers(0, C)
            if _ < 6:  # make sure measured labels are probed too
                o = rng.choice(np.flatnonzero(scores[valid & (inst >= 0)].sum(0) > 0))
            e = jnp.zeros((O, C), jnp.float64).at[o, c].set(h)
            fd = (float(loss(lik0 + e)) - float(loss(lik0 - e))) / (2 * h)
            np.testing.assert_allclose(grad[o, c], fd, rtol=1e-5, atol=1e-8)


# ----------------------------------------------------------------------------- no recompilation


@pytest.mark.parametrize("mode", LF.MODES)
def test_label_fusion_compiles_once(mode):
    chex.clear_trace_counter()

    @jax.jit
    @chex.assert_max_traces(n=1)
    def step(evidence, hist, obs, inst, scores, lik, valid, reset):
        evidence = LF.fuse_labels(evidence, inst, scores, lik, valid, mode, reset)
        hist, obs = LF.update_label_statistics(hist, obs, inst, scores, valid, reset)
        dist = LF.class_distribution(evidence, mode)
        return evidence, hist, obs, LF.predicted_class(dist), LF.confidence(dist)

    def calls(seed):
        rng = np.random.default_rng(seed)
        scores, inst, valid = random_detections(rng)
        reset = rng.random(K) < 0.2
        step(
            rng.random((K, C)).astype(np.float32),
            np.zeros((K, O), np.float32),
            np.zeros(K, np.int32),
            inst,
            scores,
            LIKELIHOOD,
            valid,
            reset,
        )
        LF.fuse_labels(rng.random((K, C)).astype(np.float32), inst, scores, LIKELIHOOD, valid, mode, reset)
        LF.class_distribution(rng.random((K, C)).astype(np.float32), mode)

    calls(0)
    before = LF.fuse_labels._cache_size(), LF.class_distribution._cache_size()
    for seed in range(1, 4):
        calls(seed)
    assert (LF.fuse_labels._cache_size(), LF.class_distribution._cache_size()) == before


# ----------------------------------------------------------------------------- normalized columns


@CHECK
@given(seeds)
def test_normalized_columns_sum_to_one_and_keep_each_columns_shape(seed):
    rng = np.random.default_rng(seed)
    lik = random_likelihood(rng).copy()
    lik[:, rng.integers(C)] = 0.0  # a class no label names stays without evidence
    normalized = normalize_columns(lik)
    sums = lik.sum(0)
    np.testing.assert_allclose(normalized.sum(0)[sums > 0], 1.0, rtol=1e-6)
    assert (normalized[:, sums == 0] == 0).all()
    np.testing.assert_allclose(normalized * sums[None, :], lik, rtol=1e-6, atol=1e-12)  # each column only rescaled


def test_every_class_detected_as_the_statistical_matrix_says_fuses_to_itself_with_normalized_columns():
    """An instance whose detections carry labels in the proportions of its class's column of the published
    statistical matrix (as the matrix says the class is detected and tagged), fused by the additive update: with
    normalized columns every one of the 20 classes comes out as itself; with the columns as published a wall comes
    out a bookshelf (its column sums to 0.43, so its labels "wall", "closet", "shelf" weigh less for it than for the
    classes detected more often) and a curtain a shower curtain."""
    names = load_label_sets().class_names
    frequencies = LIKELIHOOD / LIKELIHOOD.sum(0, keepdims=True)  # (O, C): label shares of each class's detections
    outcomes = {}
    for name, lik in (("published", LIKELIHOOD), ("normalized", normalize_columns(LIKELIHOOD).astype(np.float32))):
        scores = (frequencies.T * 10.0).astype(np.float32)  # (C, O): one instance per class, ten detections' worth
        instances = jnp.arange(C, dtype=jnp.int32)
        evidence = LF.fuse_labels(jnp.zeros((C, C)), instances, jnp.asarray(scores), jnp.asarray(lik), jnp.ones(C, bool))
        outcomes[name] = [names[c] for c in np.asarray(LF.predicted_class(LF.class_distribution(evidence)))]
    assert outcomes["normalized"] == list(names)
    wrong = {names[c]: got for c, got in enumerate(outcomes["published"]) if got != names[c]}
    assert wrong == {"wall": "bookshelf", "curtain": "shower curtain"}


def test_the_map_fuses_with_the_published_columns_unless_the_config_normalizes_them():
    from fmfusion_jax.config import load_config
    from fmfusion_jax.mapping.engine_configs import fusion_likelihood

    config = load_config("scannet")
    np.testing.assert_allclose(fusion_likelihood(config), LIKELIHOOD, rtol=1e-6)
    config.label_fusion.normalize_columns = True
    np.testing.assert_allclose(fusion_likelihood(config), normalize_columns(LIKELIHOOD), rtol=1e-6)
