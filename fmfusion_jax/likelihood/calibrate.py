"""The likelihood matrix fitted by gradient descent through the additive label fusion.

Why it is cheap: in additive mode an instance's evidence is exactly `h @ L`, where `h` (O,) is the
instance's open-set label histogram (the summed score vectors of the detections fused into it; a merge
sums both), so its class distribution under any `L` is `class_distribution(h @ L)` with no need to
re-run the map. The loss over instances matched to the ground truth is

    loss(theta) = mean_n -log p(c_n | h_n @ L(theta)) + l2 * mean((theta - theta_0)^2),

`p` the engine's `label_fusion.class_distribution` (additive, the authors' uniform start of weight 1),
`c_n` the instance's true class, `theta_0` the logits of the initial matrix; the pull toward them keeps
entries the training instances never exercise where they started.

Parametrizations (each keeps `L` a valid likelihood for any logits):
- ``"column"`` (default): for each class c, a softmax over O + 1 entries, the O open-set labels and one
  "no label / not detected" entry that is dropped: `L[:, c] = softmax(theta[:, c])[:O]`. So `L >= 0` and
  each column sums to at most 1: `L[o, c] = p(main label o, o in prompt | c)` is a distribution over the
  exclusive outcomes "detected as o" (o in L_o) and "not detected as any label of interest". A matrix
  whose columns sum to more than 1 (the published statistical one: up to 1.6, its two factors being
  estimated over different frame sets) is scaled per column to sum to `1 - floor` when turned into logits.
- ``"entry"``: each entry on its own, `L = sigmoid(theta)`, in (0, 1); the columns are not normalized, as
  in the published matrix (an entry is the probability of one event, and events of different labels may
  co-occur when a detection carries several labels).

Softmax and sigmoid never give exact zeros: an initial zero becomes about `floor` (1e-4), and in the
column parametrization the other entries of a column shrink by at most O * floor (0.4 %) to make room.

Classes with few training instances: every instance of another class lowers a class's probability, so
a class the training scenes hardly show would only be pushed down (its column shrunk), which is a fact
about the training set, not about the detector. `fit_likelihood` therefore takes a column mask
`trainable` (C,); the workflow freezes the columns of classes with fewer than 3 training instances.

The regularization (`l2`, and the number of Adam steps as early stopping) is chosen by `cross_validate`:
K folds of training scenes, the validation loss recorded along every fit.

The optimizer is Adam, written out below (a few lines; no optax dependency), run as one `lax.scan`.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from fmfusion_jax.engine import label_fusion

PARAMETRIZATIONS = ("column", "entry")
#: Least entry (and least "not detected" share) of the matrix an initial matrix is turned into.
LOGIT_FLOOR = 1e-4


def _check(parametrization: str) -> None:
    if parametrization not in PARAMETRIZATIONS:
        raise ValueError(f"parametrization {parametrization!r}: expected one of {PARAMETRIZATIONS}")


def likelihood_from_logits(logits: jax.Array, parametrization: str = "column") -> jax.Array:
    """`(O, C)` likelihood from logits: `(O + 1, C)` for "column" (last row: not detected), `(O, C)` for
    "entry"."""
    _check(parametrization)
    if parametrization == "column":
        return jax.nn.softmax(logits, axis=0)[:-1]
    return jax.nn.sigmoid(logits)


def logits_from_likelihood(matrix: np.ndarray, parametrization: str = "column", floor: float = LOGIT_FLOOR) -> np.ndarray:
    """Logits whose likelihood is `matrix` (entries raised to `floor`; for "column", columns summing to
    more than `1 - floor` scaled down to that first). `(O + 1, C)` or `(O, C)` float32."""
    _check(parametrization)
    matrix = np.asarray(matrix, np.float64)
    if parametrization == "entry":
        p = np.clip(matrix, floor, 1.0 - floor)
        return np.log(p / (1.0 - p)).astype(np.float32)
    sums = matrix.sum(axis=0)
    scale = np.minimum(1.0, (1.0 - floor) / np.maximum(sums, 1e-12))
    p = matrix * scale[None, :]
    not_detected = 1.0 - p.sum(axis=0, keepdims=True)
    return np.log(np.maximum(np.concatenate([p, not_detected]), floor)).astype(np.float32)


def project_likelihood(matrix: np.ndarray, parametrization: str = "column", floor: float = LOGIT_FLOOR) -> np.ndarray:
    """The nearest matrix the parametrization can represent (what calibration actually starts from)."""
    logits = logits_from_likelihood(matrix, parametrization, floor)
    return np.asarray(likelihood_from_logits(jnp.asarray(logits, jnp.float32), parametrization), np.float64)


def class_log_probs(likelihood: jax.Array, histograms: jax.Array) -> jax.Array:
    """`(N, C)` log class distribution of instances with these `(N, O)` open-label histograms under the
    `(O, C)` likelihood, as the engine's additive fusion gives it."""
    evidence = label_fusion.measurement_likelihood(histograms, likelihood)
    return jnp.log(label_fusion.class_distribution(evidence, "additive"))


def predicted_classes(likelihood: np.ndarray, histograms: np.ndarray) -> np.ndarray:
    """`(N,)` argmax class of each instance under `likelihood`."""
    return np.asarray(
        jnp.argmax(class_log_probs(jnp.asarray(likelihood, jnp.float32), jnp.asarray(histograms, jnp.float32)), axis=1)
    )


def label_accuracy(likelihood: np.ndarray, histograms: np.ndarray, classes: np.ndarray) -> float:
    """Share of instances whose argmax class under `likelihood` is their true class (nan for none)."""
    classes = np.asarray(classes)
    if classes.size == 0:
        return float("nan")
    return float(np.mean(predicted_classes(likelihood, histograms) == classes))


def negative_log_likelihood(
    likelihood: jax.Array, histograms: jax.Array, classes: jax.Array, weights: jax.Array | None = None
) -> jax.Array:
    """Weighted mean of `-log p(true class)` over the instances (`weights` default: all 1)."""
    log_p = class_log_probs(likelihood, histograms)
    picked = jnp.take_along_axis(log_p, classes[:, None].astype(jnp.int32), axis=1)[:, 0]
    weights = jnp.ones_like(picked) if weights is None else weights.astype(picked.dtype)
    return -jnp.sum(weights * picked) / jnp.maximum(jnp.sum(weights), 1e-12)


def calibration_loss(
    logits: jax.Array,
    histograms: jax.Array,
    classes: jax.Array,
    init_logits: jax.Array,
    l2: float = 0.0,
    parametrization: str = "column",
    weights: jax.Array | None = None,
) -> jax.Array:
    """The scalar loss of the module docstring.

    Args:
      logits: the parameters (see `likelihood_from_logits`).
      histograms: `(N, O)` open-set label histograms of the instances matched to the ground truth.
      classes: `(N,)` int their true classes.
      init_logits: `theta_0`, same shape as `logits`.
      l2: weight of the pull toward `theta_0`.
      weights: optional `(N,)` per-instance weights.
    """
    nll = negative_log_likelihood(likelihood_from_logits(logits, parametrization), histograms, classes, weights)
    return nll + l2 * jnp.mean(jnp.square(logits - init_logits))


@dataclasses.dataclass
class FitResult:
    """What `fit_likelihood` returns: final logits and likelihood, and the loss before each step."""

    logits: np.ndarray
    likelihood: np.ndarray
    losses: np.ndarray  # (steps + 1,): the loss before each step and after the last

    @property
    def initial_loss(self) -> float:
        return float(self.losses[0])

    @property
    def final_loss(self) -> float:
        return float(self.losses[-1])


def _adam_scan(init_logits, histograms, classes, weights, trainable, steps, learning_rate, l2, parametrization, record=None):
    """Adam from `init_logits`: `(theta, losses (steps + 1,), recorded (steps + 1,) or None)`, `recorded` the
    value of `record(theta)` before each step and after the last (traced; call inside `jit`)."""
    loss_and_grad = jax.value_and_grad(calibration_loss)
    beta1, beta2, eps = 0.9, 0.999, 1e-8
    record = (lambda theta: jnp.zeros((), init_logits.dtype)) if record is None else record

    def step(carry, t):
        theta, m, v = carry
        loss, grad = loss_and_grad(theta, histograms, classes, init_logits, l2, parametrization, weights)
        grad = grad * trainable[None, :]  # frozen columns keep their initial logits
        m = beta1 * m + (1 - beta1) * grad
        v = beta2 * v + (1 - beta2) * grad * grad
        m_hat = m / (1 - beta1**t)
        v_hat = v / (1 - beta2**t)
        return (theta - learning_rate * m_hat / (jnp.sqrt(v_hat) + eps), m, v), (loss, record(theta))

    zeros = jnp.zeros_like(init_logits)
    (theta, _, _), (losses, recorded) = jax.lax.scan(
        step, (init_logits, zeros, zeros), jnp.arange(1, steps + 1, dtype=init_logits.dtype)
    )
    final = calibration_loss(theta, histograms, classes, init_logits, l2, parametrization, weights)
    return theta, jnp.concatenate([losses, final[None]]), jnp.concatenate([recorded, record(theta)[None]])


@functools.partial(jax.jit, static_argnames=("steps", "parametrization"))
def _adam(init_logits, histograms, classes, weights, trainable, steps, learning_rate, l2, parametrization):
    theta, losses, _ = _adam_scan(init_logits, histograms, classes, weights, trainable, steps, learning_rate, l2, parametrization)
    return theta, losses


def fit_likelihood(
    init_logits: np.ndarray,
    histograms: np.ndarray,
    classes: np.ndarray,
    steps: int = 500,
    learning_rate: float = 0.05,
    l2: float = 1e-3,
    parametrization: str = "column",
    weights: np.ndarray | None = None,
    trainable: np.ndarray | None = None,
) -> FitResult:
    """Adam on `calibration_loss` from `init_logits` (`logits_from_likelihood` of the initial matrix).

    Args:
      histograms: `(N, O)`; classes: `(N,)` int; weights: optional `(N,)`.
      steps, learning_rate: of Adam (the step moves each logit by about `learning_rate`); 0 steps give the
        initial matrix back.
      l2: weight of the pull toward the initial logits.
      trainable: optional `(C,)` bool, the columns (classes) that may change (default: all).
    """
    _check(parametrization)
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    init = jnp.asarray(init_logits, jnp.float32)
    hist = jnp.asarray(histograms, jnp.float32).reshape(-1, init.shape[0] - (parametrization == "column"))
    cls = jnp.asarray(classes, jnp.int32).reshape(-1)
    w = jnp.ones(cls.shape, jnp.float32) if weights is None else jnp.asarray(weights, jnp.float32)
    mask = jnp.ones(init.shape[1], jnp.float32) if trainable is None else jnp.asarray(trainable, jnp.float32)
    theta, losses = _adam(init, hist, cls, w, mask, int(steps), jnp.float32(learning_rate), jnp.float32(l2), parametrization)
    return FitResult(
        np.asarray(theta), np.asarray(likelihood_from_logits(theta, parametrization), np.float64), np.asarray(losses, np.float64)
    )


# ---------------------------------------------------------------------------------------------------
# Choosing the regularization: cross-validation by scene

#: Candidate `l2` weights of `cross_validate` (the pull is a mean over all (O + 1) * C logits, so its weight per
#: logit is l2 / 780: the grid goes well past 1).
DEFAULT_L2_GRID = (0.0, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0)


def scene_folds(scenes: list[str], folds: int) -> list[list[str]]:
    """The distinct scenes, in order of first appearance, dealt round-robin into `min(folds, #scenes)` folds."""
    distinct = list(dict.fromkeys(scenes))
    if folds < 2 or len(distinct) < 2:
        raise ValueError(f"cross-validation needs at least 2 folds and 2 scenes (folds {folds}, scenes {len(distinct)})")
    k = min(folds, len(distinct))
    return [distinct[i::k] for i in range(k)]


@dataclasses.dataclass
class CrossValidation:
    """What `cross_validate` returns.

    `losses[i, t]`: the mean `-log p(true class)` over all left-out instances (each instance counted once,
    pooled over the folds) after `t` Adam steps with `l2_grid[i]`; `fold_losses[k, i, t]` the same per fold.
    The choice minimizes `losses` over the grid and, with early stopping, over `t` (ties: the larger l2,
    then the fewer steps).
    """

    l2_grid: np.ndarray  # (G,)
    folds: list[list[str]]  # scenes of each fold
    fold_sizes: np.ndarray  # (K,) instances per fold
    losses: np.ndarray  # (G, steps + 1)
    fold_losses: np.ndarray  # (K, G, steps + 1)
    l2: float  # the choice
    steps: int
    early_stopping: bool

    @property
    def loss(self) -> float:
        """Validation loss of the choice."""
        return float(self.losses[list(self.l2_grid).index(self.l2), self.steps])

    def table(self) -> list[dict]:
        """One row per l2: the best step, its validation loss, and the loss after all steps."""
        rows = []
        for i, l2 in enumerate(self.l2_grid):
            t = int(np.argmin(self.losses[i])) if self.early_stopping else self.losses.shape[1] - 1
            rows.append(
                {
                    "l2": float(l2),
                    "best_steps": t,
                    "loss_best": float(self.losses[i, t]),
                    "loss_last": float(self.losses[i, -1]),
                    "loss_initial": float(self.losses[i, 0]),
                }
            )
        return rows


@functools.partial(jax.jit, static_argnames=("steps", "parametrization"))
def _validation_paths(
    init_logits, histograms, classes, train_weights, val_weights, trainable, steps, learning_rate, l2_grid, parametrization
):
    """`(K, G, steps + 1)` validation loss along Adam for each fold (train/val weights, trainable: (K, ...))
    and each l2 of the grid."""

    def path(train_w, val_w, mask, l2):
        def validation(theta):
            return negative_log_likelihood(likelihood_from_logits(theta, parametrization), histograms, classes, val_w)

        return _adam_scan(init_logits, histograms, classes, train_w, mask, steps, learning_rate, l2, parametrization, validation)[
            2
        ]

    over_l2 = jax.vmap(path, in_axes=(None, None, None, 0))
    return jax.vmap(over_l2, in_axes=(0, 0, 0, None))(train_weights, val_weights, trainable, l2_grid)


def cross_validate(
    init_logits: np.ndarray,
    histograms: np.ndarray,
    classes: np.ndarray,
    scenes: list[str],
    l2_grid=DEFAULT_L2_GRID,
    steps: int = 500,
    folds: int = 4,
    learning_rate: float = 0.05,
    parametrization: str = "column",
    min_class_instances: int = 0,
    early_stopping: bool = True,
) -> CrossValidation:
    """Chooses `l2` (and, with `early_stopping`, the number of Adam steps) by K-fold cross-validation over scenes.

    The scenes are dealt into folds (`scene_folds`: no scene on both sides); for each fold and each `l2` of
    the grid, Adam fits on the other folds' instances (as `fit_likelihood`, with the columns of classes that
    have at least `min_class_instances` instances there trainable) and the left-out instances' mean
    `-log p(true class)` is recorded before every step. All fits run at once (one `vmap` over folds and
    grid, instance weights selecting each side, so one compilation).

    Args:
      histograms: `(N, O)`; classes: `(N,)` int; scenes: `N` scene names (the fold unit).
      steps: the most Adam steps (with `early_stopping`, every count from 0 to `steps` is a candidate;
        without, exactly `steps`).
    """
    _check(parametrization)
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    grid = np.asarray(sorted(float(v) for v in l2_grid), np.float64)
    if grid.size == 0 or np.any(grid < 0):
        raise ValueError(f"l2 grid must be non-empty and >= 0, got {list(l2_grid)}")
    classes = np.asarray(classes).reshape(-1)
    if len(scenes) != classes.size:
        raise ValueError(f"{len(scenes)} scene names for {classes.size} instances")
    fold_scenes = scene_folds(list(scenes), folds)
    scene_array = np.asarray(scenes, dtype=object)
    held = np.stack([np.isin(scene_array, f) for f in fold_scenes])  # (K, N)
    num_classes = np.asarray(init_logits).shape[1]
    counts = np.stack([np.bincount(classes[~h], minlength=num_classes) for h in held])
    trainable = counts >= min_class_instances
    paths = _validation_paths(
        jnp.asarray(init_logits, jnp.float32),
        jnp.asarray(histograms, jnp.float32),
        jnp.asarray(classes, jnp.int32),
        jnp.asarray(~held, jnp.float32),
        jnp.asarray(held, jnp.float32),
        jnp.asarray(trainable, jnp.float32),
        int(steps),
        jnp.float32(learning_rate),
        jnp.asarray(grid, jnp.float32),
        parametrization,
    )
    fold_losses = np.asarray(paths, np.float64)  # (K, G, steps + 1)
    sizes = held.sum(axis=1)
    pooled = np.einsum("k,kgt->gt", sizes / sizes.sum(), fold_losses)
    candidates = pooled if early_stopping else pooled[:, -1:]
    # ties (to float precision): the larger l2, then the fewer steps
    best = candidates.min()
    tied = np.argwhere(candidates <= best + 1e-7 * max(1.0, abs(best)))
    i = int(tied[:, 0].max())
    t = int(tied[tied[:, 0] == i, 1].min()) if early_stopping else int(steps)
    return CrossValidation(grid, fold_scenes, sizes, pooled, fold_losses, float(grid[i]), t, early_stopping)
