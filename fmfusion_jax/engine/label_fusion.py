"""Probabilistic label fusion (paper Sec. III-D), vectorized over detections and instances.

Each instance keeps an *evidence* row `label_evidence[k, :]` (C = 20 closed classes). Its meaning
depends on the fusion mode, chosen so that a row of zeros is the instance's prior in both modes; a
freshly created (or reset) instance therefore needs nothing but zeros, as `init_map_state` writes:

"additive" (the paper's final equation; the mode of the authors' pipeline). Evidence is the sum of the
  measurement vectors `z = sum_i s_i * L[y_i, :]` fused into the instance. The paper's update
  `p_t = (z_t + (t - 1) p_{t-1}) / t` unrolls to `p_t = (1/t) sum_{tau<=t} z_tau`: it averages the
  measurements, so `p_t = evidence / t` with `t` the instance's `observations`, and the order of the
  measurements does not matter. `class_distribution` normalizes
  `(evidence + w / C) / (sum(evidence) + w)`: `w = 1` (default) is the authors' implementation, which
  starts every instance at the uniform 1/C and adds measurements to it; `w = 0` is the paper's average
  normalized (uniform while nothing was measured). Both have the same argmax except for ties.

"bayes" (the multiplicative update, eqs. 3-4, off in the authors' runs). Evidence is the log posterior
  relative to the uniform prior, `sum over fused detections of log p(z | c)`, shifted per row so its
  maximum is 0 (a constant per row cancels in the normalization and keeps the numbers bounded above).
  `p(z | c) = prod_i p(s_i | y_i, q, c) p(y_i, q | c)`; the score factor does not depend on the class
  and cancels, so `log p(z | c) = sum_{i: s_i > 0} log max(L[y_i, c], eps)`. The floor `eps` keeps a
  zero entry of L (most of the statistical matrix is 0) from driving a class to probability 0 for ever:
  a class hit by a zero likelihood loses `log(1/eps)` nats instead, and later evidence can restore it.
  With `score_weighted=True` each label counts with its score as exponent (`L^s`, a tempered
  likelihood), so weak labels count less; this is an option, not the paper.

Several detections fused into one instance in the same frame add up (a `segment_sum` by instance);
`observations` counts detections, the `t` of the paper's equation.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

MODES = ("additive", "bayes")
DEFAULT_BAYES_EPS = 1e-3


def _check_mode(mode: str) -> None:
    if mode not in MODES:
        raise ValueError(f"unknown label fusion mode {mode!r}; expected one of {MODES}")


@jax.jit
def measurement_likelihood(label_scores: jax.Array, likelihood: jax.Array) -> jax.Array:
    """`(N, C)` measurement vectors `z_n = sum_i s_{n,i} * L[i, :]` (the authors' additive measurement).

    Args:
      label_scores: `(N, O)` score per open-set label (0 = not measured).
      likelihood: `(O, C)` label likelihood `p(y = o, o in prompt | c)`.
    """
    return jnp.dot(label_scores, likelihood, precision=jax.lax.Precision.HIGHEST)


@functools.partial(jax.jit, static_argnames=("score_weighted",))
def measurement_log_likelihood(
    label_scores: jax.Array, likelihood: jax.Array, eps: float = DEFAULT_BAYES_EPS, score_weighted: bool = False
) -> jax.Array:
    """`(N, C)` log p(z_n | c) of eq. 4 up to a class-independent constant (see the module docstring).

    `sum_{i: s_i > 0} log max(L[i, c], eps)`, or `sum_i s_i log max(L[i, c], eps)` when
    `score_weighted`.
    """
    log_l = jnp.log(jnp.maximum(likelihood, eps))
    weight = label_scores if score_weighted else (label_scores > 0).astype(log_l.dtype)
    return jnp.dot(weight, log_l, precision=jax.lax.Precision.HIGHEST)


def _instance_segments(instance_for_detection: jax.Array, valid: jax.Array, k: int) -> jax.Array:
    """Segment id per detection: its instance, or `k` (a dropped segment) when invalid or unassigned."""
    ok = valid & (instance_for_detection >= 0) & (instance_for_detection < k)
    return jnp.where(ok, instance_for_detection, k)


def _accumulate(evidence, instance_for_detection, values, valid, reset):
    k = evidence.shape[0]
    seg = _instance_segments(instance_for_detection, valid, k)
    added = jax.ops.segment_sum(values.astype(evidence.dtype), seg, num_segments=k + 1)[:k]
    if reset is not None:
        evidence = jnp.where(reset[:, None], jnp.zeros_like(evidence), evidence)
    return evidence + added


@jax.jit
def fuse_additive(
    evidence: jax.Array,
    instance_for_detection: jax.Array,
    measurement: jax.Array,
    valid: jax.Array,
    reset: jax.Array | None = None,
) -> jax.Array:
    """The paper's weighted additive update for all detections at once: `(K, C)` new evidence.

    Args:
      evidence: `(K, C)` summed measurements so far (zeros = the uniform prior, new instance).
      instance_for_detection: `(N,)` int32 instance of each detection, -1 = none.
      measurement: `(N, C)` from `measurement_likelihood`.
      valid: `(N,)` bool.
      reset: optional `(K,)` bool rows to clear to the prior first (slots created this frame).
    """
    return _accumulate(evidence, instance_for_detection, measurement, valid, reset)


@jax.jit
def fuse_bayes(
    evidence: jax.Array,
    instance_for_detection: jax.Array,
    log_measurement: jax.Array,
    valid: jax.Array,
    reset: jax.Array | None = None,
) -> jax.Array:
    """The multiplicative Bayes update (eqs. 3-4) in log space: `(K, C)` new evidence (row max 0).

    Args:
      evidence: `(K, C)` log posterior relative to the uniform prior (zeros = prior).
      log_measurement: `(N, C)` from `measurement_log_likelihood`.
      Others as in `fuse_additive`.
    """
    new = _accumulate(evidence, instance_for_detection, log_measurement, valid, reset)
    return new - jax.lax.stop_gradient(jnp.max(new, axis=1, keepdims=True))


@functools.partial(jax.jit, static_argnames=("mode", "score_weighted"))
def fuse_labels(
    evidence: jax.Array,
    instance_for_detection: jax.Array,
    label_scores: jax.Array,
    likelihood: jax.Array,
    valid: jax.Array,
    mode: str = "additive",
    reset: jax.Array | None = None,
    eps: float = DEFAULT_BAYES_EPS,
    score_weighted: bool = False,
) -> jax.Array:
    """Measurement and update in one call for the static `mode` ("additive" | "bayes")."""
    _check_mode(mode)
    if mode == "additive":
        return fuse_additive(evidence, instance_for_detection, measurement_likelihood(label_scores, likelihood), valid, reset)
    return fuse_bayes(
        evidence, instance_for_detection, measurement_log_likelihood(label_scores, likelihood, eps, score_weighted), valid, reset
    )


@functools.partial(jax.jit, static_argnames=("mode",))
def class_distribution(evidence: jax.Array, mode: str = "additive", prior_weight: float = 1.0) -> jax.Array:
    """`(K, C)` normalized class distribution of each instance (rows sum to 1, non-negative).

    additive: `(evidence + w / C) / (sum(evidence) + w)` with `w = prior_weight` (1: the authors'
    uniform start; 0: the paper's average, uniform when nothing was measured). Evidence must be
    non-negative (it is, for a non-negative likelihood).
    bayes: `softmax(evidence)`.
    """
    _check_mode(mode)
    c = evidence.shape[1]
    if mode == "bayes":
        return jax.nn.softmax(evidence, axis=1)
    w = jnp.asarray(prior_weight, evidence.dtype)
    num = evidence + w / c
    total = jnp.sum(num, axis=1, keepdims=True)
    ok = total > 0
    return jnp.where(ok, num / jnp.where(ok, total, 1.0), jnp.asarray(1.0 / c, evidence.dtype))


@jax.jit
def predicted_class(dist: jax.Array) -> jax.Array:
    """`(K,)` int32 argmax class (ties: lowest class index)."""
    return jnp.argmax(dist, axis=1).astype(jnp.int32)


@jax.jit
def confidence(dist: jax.Array) -> jax.Array:
    """`(K,)` probability of the predicted class."""
    return jnp.max(dist, axis=1)


@jax.jit
def update_label_statistics(
    open_label_histogram: jax.Array,
    observations: jax.Array,
    instance_for_detection: jax.Array,
    label_scores: jax.Array,
    valid: jax.Array,
    reset: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array]:
    """Adds each fused detection's open-set scores to its instance's histogram and counts it.

    Args:
      open_label_histogram: `(K, O)` float32 summed scores per open-set label.
      observations: `(K,)` int32 fused detections (the `t` of the additive equation).
      instance_for_detection, valid: as in `fuse_additive`; `label_scores`: `(N, O)`.
      reset: optional `(K,)` bool rows to clear first.

    Returns:
      `(open_label_histogram, observations)`.
    """
    k = observations.shape[0]
    seg = _instance_segments(instance_for_detection, valid, k)
    hist = jax.ops.segment_sum(label_scores.astype(open_label_histogram.dtype), seg, num_segments=k + 1)[:k]
    count = jax.ops.segment_sum(jnp.ones(seg.shape, observations.dtype), seg, num_segments=k + 1)[:k]
    if reset is not None:
        open_label_histogram = jnp.where(reset[:, None], jnp.zeros_like(open_label_histogram), open_label_histogram)
        observations = jnp.where(reset, jnp.zeros_like(observations), observations)
    return open_label_histogram + hist, observations + count
