"""The label side of simulated detections (`simulate`): the labels a detection of a class gets, drawn from the
likelihood (perturbed, with extra confusions and consistent mislabels by noise family), filtered by the
frame's prompt."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from fmfusion_jax.labels import LabelSets
from fmfusion_jax.simulation.noise import (
    NoiseModel,
)

# Tags of the seed-only streams (one detector, one set of mislabels, one set of confusers per seed).
_PERTURBATION_STREAM, _MISLABEL_STREAM, _CONFUSER_STREAM, _PHANTOM_STREAM = 6101, 6113, 6121, 6131
#: Tags the image tagger produces that are not labels of interest (they end up in `raw_tags` only).
GENERIC_TAGS = (
    "room",
    "indoor",
    "home",
    "interior",
    "furniture",
    "lamp",
    "pillow",
    "box",
    "book",
    "computer",
    "monitor",
    "white",
    "wood",
    "living room",
    "bedroom",
    "office",
    "kitchen",
    "bag",
    "plant",
    "light",
    "ceiling",
    "shoe",
)


#: Least p(label | class) of a prompt label that a relabelled detection takes as a related label.
RELATED_LABEL_MIN_PROB = 0.01


#: Probability that a relabelled detection with no related label in the prompt takes an unrelated one.
RELABEL_UNRELATED_SHARE = 0.2


#: Least p(label | class) of a label that can come as a detection's second or third label.
EXTRA_LABEL_MIN_PROB = 0.03


#: Confusions real detectors make that the published statistical matrix lacks (p(label | class) < 0.03):
#: class -> open-set labels it is taken for under `extra_confusion_prob`. Mostly look-alike pairs: a table
#: and a kitchen counter, a cabinet and a door, a window and a picture, a sink and a toilet.
EXTRA_CONFUSIONS: dict[str, tuple[str, ...]] = {
    "cabinet": ("door", "fridge", "side table"),
    "bed": ("couch",),
    "chair": ("side table", "table"),
    "sofa": ("bed",),
    "table": ("kitchen counter", "dresser"),
    "door": ("wall", "window"),
    "window": ("picture", "door"),
    "picture": ("window",),
    "counter": ("cabinet", "kitchen table"),
    "desk": ("counter top", "side table"),
    "curtain": ("wall", "door"),
    "refrigerator": ("door",),
    "shower curtain": ("glass door", "window"),
    "toilet": ("sink", "bin"),
    "sink": ("toilet bowl", "tub"),
    "bathtub": ("sink",),
    "otherfurniture": ("side table",),
}


#: Weight added to the `EXTRA_CONFUSIONS` labels of a class when drawing its consistent mislabel, and the
#: floor weight of every other wrong label: plausible look-alikes are preferred, any wrong label can occur.
MISLABEL_LOOKALIKE_WEIGHT = 0.05


MISLABEL_FLOOR_WEIGHT = 0.002


#: Share of the unit column mass that `likelihood_perturbation` = 1 moves onto labels a column lacks, and
#: how many such labels per column receive it.
PERTURBATION_NEW_MASS = 0.05


PERTURBATION_NEW_LABELS = 3


def perturb_likelihood(columns: np.ndarray, sigma: float, seed: int) -> np.ndarray:
    """A misspecified detector's label distributions: `columns` (each summing to 1) with every entry
    scaled by a log-normal factor exp(N(0, sigma)) and `PERTURBATION_NEW_MASS * sigma` of mass put on a few
    labels the column lacks, re-normalized. Depends on `seed` only: one detector per seed."""
    rng = np.random.default_rng([int(seed), _PERTURBATION_STREAM])
    factors = np.exp(sigma * rng.standard_normal(columns.shape))
    out = columns * factors
    out /= out.sum(axis=0, keepdims=True)
    for j in range(out.shape[1]):
        lacking = np.flatnonzero(columns[:, j] == 0)
        chosen = rng.choice(lacking, size=min(PERTURBATION_NEW_LABELS, lacking.size), replace=False)
        if chosen.size:
            out[chosen, j] += PERTURBATION_NEW_MASS * sigma / chosen.size
    return out / out.sum(axis=0, keepdims=True)


def wrong_labels(columns: np.ndarray) -> np.ndarray:
    """`(num_open, num_classes)` bool: label `l` is wrong for class `c` when the published matrix ascribes
    it to another class (its row's largest entry is elsewhere), so fusing it pulls towards that class."""
    return columns.argmax(axis=1)[:, None] != np.arange(columns.shape[1])[None, :]


def consistent_mislabels(columns: np.ndarray, prob: float, seed: int, lookalikes: Mapping[int, list[int]]) -> dict[int, int]:
    """Class -> the one wrong open label it is always named by, for the classes (per seed) drawn with `prob`.

    Wrong labels are weighted by their published probability, look-alikes (`EXTRA_CONFUSIONS`) get
    `MISLABEL_LOOKALIKE_WEIGHT` more and any wrong label at least `MISLABEL_FLOOR_WEIGHT`. Each class draws
    its label whatever `prob` is, so raising `prob` only adds classes.
    """
    wrong = wrong_labels(columns)
    out = {}
    for c in range(columns.shape[1]):
        rng = np.random.default_rng([int(seed), _MISLABEL_STREAM, c])
        weights = columns[:, c] + MISLABEL_FLOOR_WEIGHT
        weights[lookalikes.get(c, [])] += MISLABEL_LOOKALIKE_WEIGHT
        weights = np.where(wrong[:, c], weights, 0.0)
        hit = rng.random() < prob
        label = int(rng.choice(columns.shape[0], p=weights / weights.sum()))
        if hit:
            out[c] = label
    return out


class _LabelModel:
    """Draws a detection's open-set labels and scores for a true closed class."""

    def __init__(self, noise: NoiseModel, label_sets: LabelSets, likelihood: np.ndarray):
        likelihood = np.asarray(likelihood, np.float64)
        if likelihood.shape != (label_sets.num_open, label_sets.num_classes):
            raise ValueError(f"likelihood shape {likelihood.shape}, expected ({label_sets.num_open}, {label_sets.num_classes})")
        sums = likelihood.sum(axis=0, keepdims=True)
        if np.any(sums <= 0):
            raise ValueError("every likelihood column needs a positive entry")
        self.published = likelihood / sums  # p(open label | class), each column sums to 1
        # The detector's own distributions: the published ones unless the label model is misspecified.
        self.columns = (
            perturb_likelihood(self.published, noise.likelihood_perturbation, noise.seed)
            if noise.likelihood_perturbation > 0
            else self.published
        )
        self.best = self.columns.argmax(axis=0)  # most likely open label of each class
        self.noise = noise
        self.names = label_sets.open_labels
        index = {name: i for i, name in enumerate(self.names)}
        self.lookalikes = {
            label_sets.class_names.index(c): [index[name] for name in names if name in index]
            for c, names in EXTRA_CONFUSIONS.items()
            if c in label_sets.class_names
        }
        self.mislabels = (
            consistent_mislabels(self.published, noise.consistent_mislabel_prob, noise.seed, self.lookalikes)
            if noise.consistent_mislabel_prob > 0
            else {}
        )

    def persistent_label(self, class_index: int, instance: int) -> int:
        """The object's own label draw: fixed for a seed and instance, the same in every frame."""
        rng = np.random.default_rng([int(self.noise.seed), 7919, int(instance) & 0x7FFFFFFF, class_index])
        return int(rng.choice(len(self.names), p=self.columns[:, class_index]))

    def draw(self, rng: np.random.Generator, class_index: int, instance: int) -> dict[str, float]:
        noise, column = self.noise, self.columns[:, class_index]
        confused, persistent = rng.random(), rng.random()
        fresh = int(rng.choice(len(self.names), p=column))
        if confused >= noise.label_confusion:
            main = int(self.best[class_index])
        elif persistent < noise.label_persistence:
            main = self.persistent_label(class_index, instance)
        else:
            main = fresh
        main = self.mislabels.get(class_index, main)
        score = float(np.clip(noise.score_mean + noise.score_std * rng.standard_normal(), noise.box_threshold, 0.95))
        labels = {self.names[main]: score}
        extra = 0
        while extra < noise.max_labels - 1 and rng.random() < noise.extra_label_prob:
            extra += 1
        weights = np.where(column >= EXTRA_LABEL_MIN_PROB, column, 0.0)
        weights[main] = 0.0
        extra = min(extra, int(np.count_nonzero(weights)))
        if extra:
            for k in rng.choice(len(self.names), size=extra, replace=False, p=weights / weights.sum()):
                secondary = score * rng.uniform(0.5, 0.95)
                if secondary >= noise.text_threshold:
                    labels[self.names[int(k)]] = secondary
        return labels

    def confuse(self, rng: np.random.Generator, class_index: int, labels: dict[str, float]) -> dict[str, float]:
        """With `extra_confusion_prob`, the main label replaced by a look-alike the published matrix lacks.

        Classes under a consistent mislabel keep it (that mislabel is the point: it never varies).
        """
        partners = self.lookalikes.get(class_index, [])
        fires = rng.random() < self.noise.extra_confusion_prob
        if not fires or not partners or class_index in self.mislabels:
            return labels
        partner = self.names[partners[int(rng.integers(len(partners)))]]
        main, score = next(iter(labels.items()))
        return {partner: score, **{k: v for k, v in labels.items() if k not in (main, partner)}}

    def score(self, rng: np.random.Generator) -> float:
        """A normal main-label score, as a detection of a real object gets."""
        return float(
            np.clip(self.noise.score_mean + self.noise.score_std * rng.standard_normal(), self.noise.box_threshold, 0.95)
        )

    def confuser(self, instance: int, class_names: list[str]) -> tuple[bool, int, str]:
        """Whether non-target object `instance` is a confuser (per seed and object), the class it is taken
        for, and its fixed label (drawn from that class's published column)."""
        rng = np.random.default_rng([int(self.noise.seed), _CONFUSER_STREAM, int(instance) & 0x7FFFFFFF])
        hit = rng.random() < self.noise.confuser_prob
        candidates = [class_names.index(c) for c in CONFUSER_CLASSES if c in class_names]
        class_index = candidates[int(rng.integers(len(candidates)))]
        label = int(rng.choice(len(self.names), p=self.published[:, class_index]))
        return hit, class_index, self.names[label]

    def relabel(self, rng: np.random.Generator, class_index: int, prompt: list[str]) -> dict[str, float] | None:
        """A false label measurement: the detector assigns the object to a label of the prompt.

        A prompt label the class is sometimes detected as (p >= `RELATED_LABEL_MIN_PROB`) is chosen in
        proportion to its likelihood; with none in the prompt, an unrelated label only with probability
        `RELABEL_UNRELATED_SHARE`. None: the object is not detected.
        """
        if not prompt:
            return None
        index = {name: i for i, name in enumerate(self.names)}
        weights = np.array([self.columns[index[p], class_index] if p in index else 0.0 for p in prompt])
        weights[weights < RELATED_LABEL_MIN_PROB] = 0.0
        if weights.sum() > 0:
            choice = prompt[int(rng.choice(len(prompt), p=weights / weights.sum()))]
        elif rng.random() < RELABEL_UNRELATED_SHARE:
            choice = prompt[int(rng.integers(len(prompt)))]
        else:
            return None
        return {choice: float(rng.uniform(self.noise.box_threshold, self.noise.box_threshold + 0.1))}


def _prompt_filter(labels: dict[str, float], prompt: set[str]) -> dict[str, float]:
    return {name: score for name, score in labels.items() if name in prompt}


def _round_labels(labels: Mapping[str, float]) -> dict[str, float]:
    ordered = sorted(labels.items(), key=lambda item: (-item[1], item[0]))
    return {name: round(float(score), 4) for name, score in ordered}


@dataclasses.dataclass
class _Object:
    instances: tuple[int, ...]  # ground-truth instances making up the object (2 when merged)
    key: int  # the largest one (or the absorbing one): its class and persistent label are used
    class_index: int
    area: int
    fixed_labels: dict[str, float] | None = None  # a confuser's labels (the same object in every view)


#: Classes a confuser (a non-target object: a box, a lamp, a bag) is taken for.
CONFUSER_CLASSES = ("cabinet", "chair", "table", "bookshelf", "picture", "desk", "otherfurniture")
