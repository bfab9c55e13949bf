"""The ScanNet 3D semantic instance benchmark (AP, AP50, AP25 over 18 classes), per mesh vertex.

Written from the benchmark's rules (see the project notes on the official evaluation), so that scores
compare with published numbers. The details that differ from a textbook AP:

- IoU thresholds `np.append(np.arange(0.5, 0.95, 0.05), 0.25)`: 0.50 ... 0.90 (0.95 is excluded by
  `arange`) and 0.25. The floats are kept as `arange` makes them, so an IoU of exactly 0.6 does not pass
  the threshold `0.6000000000000001`; an overlap passes when it is strictly greater.
- Ground-truth instances under 100 vertices are not counted; nor are predictions under 100 vertices
  or of a class outside the 18 (they are dropped before anything else).
- Matching, per class and threshold, ground-truth instances in increasing id order: the predictions
  overlapping a ground-truth instance above the threshold, in prediction-file order and skipping those
  already taken by an earlier instance, all go to it. The first of them is marked taken; the instance
  scores as one true positive with the highest of their confidences, and each other one adds a false
  positive (the remaining confidences). Those others are not marked taken, so one may also be the match
  of a later instance (the official script's behaviour, kept on purpose).
- A prediction overlapping no same-class ground truth (counted or small) above the threshold is a false
  positive unless the share of its vertices on void (a class outside the 18, or unlabelled) or on
  small same-class instances exceeds the threshold; then it is ignored.
- The precision/recall curve has one point per distinct confidence (predictions at or above it), plus
  an appended point (recall 0, precision 1); AP = sum_i p_i * (r_{i-1} - r_{i+1}) / 2 with r_{-1} = r_0
  and r_{n+1} = 0, where the points go from the lowest confidence (highest recall) to the appended one.
- AP is nan for a class without counted ground truth, 0 for a class with ground truth but no prediction
  (or whose predictions are all ignored); means are nanmeans. Scenes are pooled per class before the
  curve is built.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Sequence

import numpy as np

from fmfusion_jax.errors import DataError
from fmfusion_jax.io.benchmark_format import InstancePredictions
from fmfusion_jax.labels import BENCHMARK_NYU40_IDS, load_label_sets

#: IoU thresholds, built exactly as the benchmark builds them (the float values matter).
OVERLAPS = np.append(np.arange(0.5, 0.95, 0.05), 0.25)
#: Ground-truth instances and predictions smaller than this (vertices) are not evaluated.
MIN_REGION_SIZE = 100

_AP_COLUMNS = ~np.isclose(OVERLAPS, 0.25)
_AP50_COLUMN = int(np.flatnonzero(np.isclose(OVERLAPS, 0.5))[0])
_AP25_COLUMN = int(np.flatnonzero(np.isclose(OVERLAPS, 0.25))[0])


def benchmark_class_names() -> tuple[str, ...]:
    """Names of the 18 benchmark classes, in `BENCHMARK_NYU40_IDS` order (``"cabinet"``, ...)."""
    label_sets = load_label_sets()
    name_of = {int(n): name for name, n in zip(label_sets.class_names, label_sets.nyu40_ids)}
    return tuple(name_of[n] for n in BENCHMARK_NYU40_IDS)


@dataclasses.dataclass(frozen=True, eq=False)
class SceneMatches:
    """What the benchmark needs of one scene once masks are reduced to counts.

    Ground-truth instances (G) are the distinct benchmark ids of a benchmark class, in increasing id order;
    predictions (P) are those kept (benchmark class, at least the minimum size), in input order.

    Attributes:
      gt_classes: `(G,)` int64 nyu40 class of each ground-truth instance.
      gt_sizes: `(G,)` int64 vertex count of each ground-truth instance.
      pred_classes: `(P,)` int64 nyu40 class of each prediction.
      pred_confidences: `(P,)` float64.
      pred_sizes: `(P,)` int64 vertex count of each prediction.
      pred_void: `(P,)` int64 vertices of each prediction on void ground truth.
      intersections: `(P, G)` int64 shared vertices; 0 between different classes (never compared).
    """

    gt_classes: np.ndarray
    gt_sizes: np.ndarray
    pred_classes: np.ndarray
    pred_confidences: np.ndarray
    pred_sizes: np.ndarray
    pred_void: np.ndarray
    intersections: np.ndarray


def match_scene(
    gt_ids: np.ndarray, preds: InstancePredictions, min_region_size: int = MIN_REGION_SIZE, scene_name: str = "scene"
) -> SceneMatches:
    """Counts each prediction's overlap with the ground truth of its class and with void.

    Args:
      gt_ids: `(V,)` int benchmark ids (`nyu40 * 1000 + instance`, 0 = none).
      preds: masks over the same `V` vertices.
    """
    gt_ids = np.asarray(gt_ids, np.int64).reshape(-1)
    if preds.num_vertices != gt_ids.shape[0]:
        raise DataError(
            f"{scene_name}: predictions cover {preds.num_vertices} vertices but the ground truth has "
            f"{gt_ids.shape[0]}: were they made on another mesh?"
        )
    benchmark_classes = np.asarray(BENCHMARK_NYU40_IDS, np.int64)
    void = ~np.isin(gt_ids // 1000, benchmark_classes)

    instance_ids = np.unique(gt_ids[~void])
    gt_classes = instance_ids // 1000
    # Index of each vertex's ground-truth instance, -1 on void.
    gt_index = np.where(void, -1, np.searchsorted(instance_ids, gt_ids))
    gt_sizes = np.bincount(gt_index[~void], minlength=len(instance_ids)).astype(np.int64)

    pred_sizes_all = preds.masks.sum(axis=1)
    keep = np.isin(preds.nyu40_ids, benchmark_classes) & (pred_sizes_all >= min_region_size)
    masks = preds.masks[keep]
    pred_classes = preds.nyu40_ids[keep]
    intersections = np.zeros((len(masks), len(instance_ids)), np.int64)
    for k, mask in enumerate(masks):
        counts = np.bincount(gt_index[mask & ~void], minlength=len(instance_ids))
        intersections[k] = np.where(gt_classes == pred_classes[k], counts, 0)
    return SceneMatches(
        gt_classes=gt_classes,
        gt_sizes=gt_sizes,
        pred_classes=pred_classes,
        pred_confidences=preds.confidences[keep],
        pred_sizes=pred_sizes_all[keep].astype(np.int64),
        pred_void=(masks & void).sum(axis=1).astype(np.int64),
        intersections=intersections,
    )


@dataclasses.dataclass(frozen=True)
class ClassDetections:
    """The scored entries of one class at one IoU threshold, in one scene or pooled over scenes.

    Attributes:
      scores: `(N,)` float64 confidence of each scored entry (true or false positive).
      is_true: `(N,)` bool, True for a matched ground-truth instance.
      num_missed: ground-truth instances no prediction matched (hard false negatives).
      has_gt: some scene has a counted ground-truth instance of the class.
      has_pred: some scene has a kept prediction of the class (ignored ones included).
    """

    scores: np.ndarray
    is_true: np.ndarray
    num_missed: int
    has_gt: bool
    has_pred: bool


def class_detections(
    scenes: Sequence[SceneMatches], nyu40: int, overlap: float, min_region_size: int = MIN_REGION_SIZE
) -> ClassDetections:
    """True and false positives of class `nyu40` at IoU threshold `overlap`, pooled over scenes."""
    per_scene = [scene_class_detections(scene, nyu40, overlap, min_region_size) for scene in scenes]
    return ClassDetections(
        scores=np.concatenate([d.scores for d in per_scene]) if per_scene else np.zeros(0),
        is_true=np.concatenate([d.is_true for d in per_scene]) if per_scene else np.zeros(0, bool),
        num_missed=sum(d.num_missed for d in per_scene),
        has_gt=any(d.has_gt for d in per_scene),
        has_pred=any(d.has_pred for d in per_scene),
    )


def scene_class_detections(
    scene: SceneMatches, nyu40: int, overlap: float, min_region_size: int = MIN_REGION_SIZE
) -> ClassDetections:
    """True and false positives of class `nyu40` at IoU threshold `overlap` in one scene (the module
    docstring's matching and ignore rules)."""
    gt_cols = np.flatnonzero(scene.gt_classes == nyu40)
    pred_rows = np.flatnonzero(scene.pred_classes == nyu40)
    gt_sizes = scene.gt_sizes[gt_cols]
    counted = gt_sizes >= min_region_size
    confidences = scene.pred_confidences[pred_rows]
    pred_sizes = scene.pred_sizes[pred_rows]
    intersections = scene.intersections[np.ix_(pred_rows, gt_cols)]
    above = intersections / (pred_sizes[:, None] + gt_sizes[None, :] - intersections) > overlap  # (p, g) IoU test

    scores: list[float] = []
    is_true: list[bool] = []
    num_missed = 0
    taken = np.zeros(len(pred_rows), bool)
    for g in np.flatnonzero(counted):  # in increasing ground-truth id order
        best = None
        for p in np.flatnonzero(above[:, g] & ~taken):  # in prediction order
            if best is None:
                best, taken[p] = float(confidences[p]), True
            else:  # a duplicate: the lower of the two confidences becomes a false positive
                scores.append(min(best, float(confidences[p])))
                is_true.append(False)
                best = max(best, float(confidences[p]))
        if best is None:
            num_missed += 1
        else:
            scores.append(best)
            is_true.append(True)

    # Predictions matching no instance of their class (counted or small): false positives unless mostly
    # on void or on small instances.
    for p in np.flatnonzero(~above.any(axis=1)):
        ignored = scene.pred_void[pred_rows[p]] + intersections[p, ~counted].sum()
        if ignored / pred_sizes[p] <= overlap:
            scores.append(float(confidences[p]))
            is_true.append(False)
    return ClassDetections(
        np.asarray(scores, np.float64),
        np.asarray(is_true, bool),
        num_missed,
        has_gt=bool(counted.any()),
        has_pred=pred_rows.size > 0,
    )


def precision_recall_curve(scores: np.ndarray, is_true: np.ndarray, num_missed: int) -> tuple[np.ndarray, np.ndarray]:
    """The benchmark's precision/recall points.

    Args:
      scores: `(N,)` confidences of the entries; is_true: `(N,)` bool; num_missed: unmatched ground truth.

    Returns:
      precision, recall: `(U + 1,)` float64, one point per distinct score `s` in increasing order (the
      entries scoring at least `s` are positives), then the appended point (precision 1, recall 0).
    """
    scores = np.asarray(scores, np.float64)
    is_true = np.asarray(is_true, bool)
    order = np.argsort(scores, kind="stable")
    sorted_scores, sorted_true = scores[order], is_true[order]
    _, first = np.unique(sorted_scores, return_index=True)
    true_before = np.concatenate([[0], np.cumsum(sorted_true)])[first]  # true entries scoring below s
    tp = int(sorted_true.sum()) - true_before
    fp = (len(sorted_scores) - first) - tp
    fn = true_before + num_missed
    precision = np.append(tp / (tp + fp), 1.0)
    recall = np.append(tp / (tp + fn), 0.0)
    return precision, recall


def average_precision(scores: np.ndarray, is_true: np.ndarray, num_missed: int) -> float:
    """The benchmark's AP: sum_i p_i * (r_{i-1} - r_{i+1}) / 2 over `precision_recall_curve` (r_{-1} = r_0,
    r_{n+1} = 0). 0 when there is nothing scored; nan when there is no ground truth at all."""
    is_true = np.asarray(is_true, bool)
    if int(is_true.sum()) + num_missed == 0:
        return math.nan
    if len(is_true) == 0:
        return 0.0
    precision, recall = precision_recall_curve(scores, is_true, num_missed)
    previous = np.concatenate([recall[:1], recall[:-1]])
    following = np.concatenate([recall[1:], [0.0]])
    return float(np.dot(precision, 0.5 * (previous - following)))


def class_ap(detections: ClassDetections) -> float:
    """AP of one class at one threshold: nan without ground truth, 0 without predictions."""
    if not detections.has_gt:
        return math.nan
    if not detections.has_pred:
        return 0.0
    return average_precision(detections.scores, detections.is_true, detections.num_missed)


@dataclasses.dataclass(frozen=True, eq=False)
class BenchmarkResult:
    """Scores of the 18 benchmark classes.

    Attributes:
      class_names: the 18 class names, in `BENCHMARK_NYU40_IDS` order.
      ap_table: `(18, len(OVERLAPS))` float64 AP per class and IoU threshold (nan: no ground truth).
      overlaps: `(len(OVERLAPS),)` the IoU thresholds of the columns.
      gt_counts: class name -> counted ground-truth instances (all scenes).
      pred_counts: class name -> evaluated predictions (benchmark class, at least the minimum size).
      scene_names: the evaluated scenes.
    """

    class_names: tuple[str, ...]
    ap_table: np.ndarray
    overlaps: np.ndarray
    gt_counts: dict[str, int]
    pred_counts: dict[str, int]
    scene_names: tuple[str, ...]

    @property
    def ap(self) -> dict[str, float]:
        """Class -> AP averaged over IoU 0.50:0.05:0.90 (nan without ground truth)."""
        return {n: float(np.mean(row[_AP_COLUMNS])) for n, row in zip(self.class_names, self.ap_table)}

    @property
    def ap50(self) -> dict[str, float]:
        return {n: float(row[_AP50_COLUMN]) for n, row in zip(self.class_names, self.ap_table)}

    @property
    def ap25(self) -> dict[str, float]:
        return {n: float(row[_AP25_COLUMN]) for n, row in zip(self.class_names, self.ap_table)}

    @property
    def mAP(self) -> float:  # noqa: N802 - the benchmark's name
        return _nanmean(self.ap_table[:, _AP_COLUMNS])

    @property
    def mAP50(self) -> float:  # noqa: N802
        return _nanmean(self.ap_table[:, _AP50_COLUMN])

    @property
    def mAP25(self) -> float:  # noqa: N802
        return _nanmean(self.ap_table[:, _AP25_COLUMN])

    def to_table(self) -> str:
        """Aligned text table: class, AP, AP_50%, AP_25%, then the average (nan: no ground truth)."""
        header = f"{'what':<15}:{'AP':>15}{'AP_50%':>15}{'AP_25%':>15}"
        width = len(header)
        lines = ["#" * width, header, "#" * width]
        ap, ap50, ap25 = self.ap, self.ap50, self.ap25
        for name in self.class_names:
            lines.append(f"{name:<15}:{ap[name]:>15.3f}{ap50[name]:>15.3f}{ap25[name]:>15.3f}")
        lines.append("-" * width)
        lines.append(f"{'average':<15}:{self.mAP:>15.3f}{self.mAP50:>15.3f}{self.mAP25:>15.3f}")
        return "\n".join(lines)

    def to_json_dict(self) -> dict:
        """JSON-ready summary; nan (a class without ground truth) becomes None."""
        ap, ap50, ap25 = self.ap, self.ap50, self.ap25
        return {
            "scenes": list(self.scene_names),
            "mAP": _json_float(self.mAP),
            "mAP50": _json_float(self.mAP50),
            "mAP25": _json_float(self.mAP25),
            "classes": {
                name: {
                    "AP": _json_float(ap[name]),
                    "AP50": _json_float(ap50[name]),
                    "AP25": _json_float(ap25[name]),
                    "num_gt": self.gt_counts[name],
                    "num_pred": self.pred_counts[name],
                }
                for name in self.class_names
            },
            "overlaps": [float(o) for o in self.overlaps],
            "min_region_size": MIN_REGION_SIZE,
        }


def evaluate_scenes(
    scenes: Sequence[tuple[np.ndarray, InstancePredictions]], scene_names: Sequence[str] | None = None
) -> BenchmarkResult:
    """Evaluates predictions against ground truth over one or more scenes (pooled per class).

    Args:
      scenes: `(gt_ids, predictions)` per scene; `gt_ids` `(V,)` int benchmark ids of the scene's mesh
        vertices (`nyu40 * 1000 + instance`, 0 = none), predictions with `(P, V)` masks.
      scene_names: for messages and the result (default ``scene0``, ``scene1``, ...).
    """
    scene_names = tuple(scene_names) if scene_names is not None else tuple(f"scene{i}" for i in range(len(scenes)))
    if len(scene_names) != len(scenes):
        raise ValueError(f"{len(scenes)} scenes but {len(scene_names)} scene names")
    matches = [match_scene(gt, preds, scene_name=name) for (gt, preds), name in zip(scenes, scene_names)]
    ap_table = np.full((len(BENCHMARK_NYU40_IDS), len(OVERLAPS)), np.nan)
    for ci, nyu40 in enumerate(BENCHMARK_NYU40_IDS):
        for oi, overlap in enumerate(OVERLAPS):
            ap_table[ci, oi] = class_ap(class_detections(matches, nyu40, overlap))
    names = benchmark_class_names()
    gt_counts = {
        n: sum(int(np.sum((m.gt_classes == c) & (m.gt_sizes >= MIN_REGION_SIZE))) for m in matches)
        for n, c in zip(names, BENCHMARK_NYU40_IDS)
    }
    pred_counts = {n: sum(int(np.sum(m.pred_classes == c)) for m in matches) for n, c in zip(names, BENCHMARK_NYU40_IDS)}
    return BenchmarkResult(names, ap_table, OVERLAPS.copy(), gt_counts, pred_counts, scene_names)


def _nanmean(values: np.ndarray) -> float:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all nan (no ground truth at all) -> nan, quietly
        return float(np.nanmean(values))


def _json_float(value: float) -> float | None:
    return None if math.isnan(value) else float(value)
