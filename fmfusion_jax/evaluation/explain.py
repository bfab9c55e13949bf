"""Error analysis of one scene's instance predictions: why each object was (not) found, what each
prediction is. Complements the benchmark's scores (`scannet_benchmark`); never changes them.

Everything is counted per mesh vertex, as the benchmark counts. Vocabulary:

- *object*: a counted ground-truth instance (one of the benchmark's 18 classes, at least
  `MIN_REGION_SIZE` vertices). Smaller instances of those classes are *small objects*; the benchmark
  ignores them, and here they count as "no object" too.
- *evaluated prediction*: one the benchmark evaluates (one of the 18 classes, at least
  `MIN_REGION_SIZE` vertices); the others are only counted (`num_skipped_predictions`).
- IoU of a prediction and an object: shared vertices / vertices in either, whatever their classes.
- A prediction *passes* 0.5 (or 0.25) with an object when the IoU is strictly greater than the
  benchmark's threshold (its floats, `OVERLAPS`), as the benchmark tests it. At most one object can
  pass 0.5 with a prediction (it must hold more than half of the prediction's vertices).
- A prediction *overlaps* an object when the IoU is at least `OVERLAP_IOU` (0.1) or the prediction
  covers at least `OVERLAP_COVER` (30 %) of the object's vertices.
- A prediction's *reference object*: among the objects it overlaps, the one holding most of its
  vertices; when it overlaps none, the object holding most of its vertices (if it touches one at all).
  Ties go to the higher IoU, then to the lower ground-truth id. Its vertex shares are given against
  it: on the object, on other objects, on small objects, on wall (nyu40 1), on floor (nyu40 2) and on
  void (anything else: other classes, unlabelled); they sum to 1.

Status of an object (the first rule that applies):

1. ``found``: a prediction of its class passes 0.5 (it is a true positive at AP50).
2. ``wrong_class``: no prediction of its class passes 0.5, but one of another class does (a label
   fix would find it).
3. ``fragmented``: at least `MIN_FRAGMENTS` (2) evaluated predictions, of any class, each hold more
   than half of their vertices inside it (none passes 0.5 with it, by rules 1-2). Ranked before
   ``low_iou``: an object cut in three has pieces of IoU about 1/3, and the cut is what to fix.
4. ``low_iou``: the best prediction of its class has an IoU in (0.25, 0.5]: found at AP25 only.
5. ``missed``: none of the above.

Whatever the status, each object's record keeps the facts behind it (best IoU of its class, passes
0.5 / 0.25, number of fragments), so a ``fragmented`` object found at AP25 still says so.

Kind of an evaluated prediction (the first rule that applies):

1. ``true_positive``: the benchmark's AP50 match of an object: of the predictions of the object's class
   passing 0.5 with it, the one with the highest confidence (the earlier one in the input on ties).
   There are as many as the benchmark's AP50 true positives.
2. ``duplicate``: passes 0.5 with an object of its class whose match is another prediction (which
   has a higher confidence, or the same and comes first); the benchmark scores it a false positive.
3. ``wrong_class``: passes 0.5 with an object of another class.
4. ``smear``: it overlaps its reference object and more than `SMEAR_OFF_SHARE` (40 %) of its vertices
   lie off it (wall, floor, void, other or small objects): the object plus what lies around it.
5. ``fragment``: more than half of its vertices lie inside its reference object (its IoU is at most
   0.5 by rules 1-3): a piece of an object.
6. ``no_object``: the rest: it overlaps no object and no object holds more than half of it; mostly
   wall, floor or void, or a thin spread over several objects.

Each evaluated prediction also has its role in the benchmark at AP50 (``ap50``): ``true_positive``,
``false_positive`` (duplicates, and predictions passing 0.5 with no instance of their class unless
ignored), or ``ignored`` (the benchmark's rule: more than half of it on void, wall and floor included,
or on small instances of its class; or passing 0.5 only with a small instance of its class).
Predictions mostly on wall or floor are therefore not penalised by the benchmark, though they are
errors of the map.

Pure NumPy; `explain_report` writes the files.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import cast

import numpy as np

from fmfusion_jax.evaluation.scannet_benchmark import MIN_REGION_SIZE, OVERLAPS, benchmark_class_names
from fmfusion_jax.io.benchmark_format import InstancePredictions
from fmfusion_jax.labels import BENCHMARK_NYU40_IDS

#: The benchmark's AP50 and AP25 thresholds, the very floats it compares with (passed when IoU > it).
IOU_50 = float(OVERLAPS[np.flatnonzero(np.isclose(OVERLAPS, 0.5))[0]])
IOU_25 = float(OVERLAPS[np.flatnonzero(np.isclose(OVERLAPS, 0.25))[0]])
#: A prediction overlaps an object at this IoU, or when it covers this share of the object's vertices.
OVERLAP_IOU = 0.1
OVERLAP_COVER = 0.3
#: A prediction overlapping an object is a smear when more than this share of it lies off the object.
SMEAR_OFF_SHARE = 0.4
#: A prediction lies inside an object when more than this share of its vertices do.
INSIDE_SHARE = 0.5
#: An object is fragmented when at least this many predictions lie inside it.
MIN_FRAGMENTS = 2
WALL_NYU40, FLOOR_NYU40 = 1, 2

#: Object statuses and prediction kinds, in the order of their rules (and of every table).
GT_STATUSES = ("found", "wrong_class", "fragmented", "low_iou", "missed")
PREDICTION_KINDS = ("true_positive", "duplicate", "wrong_class", "smear", "fragment", "no_object")
AP50_ROLES = ("true_positive", "false_positive", "ignored")
#: Vertex shares of a prediction, in the order of `PredictionExplanation.shares`.
SHARE_NAMES = ("object", "other_objects", "small_objects", "wall", "floor", "void")


@dataclasses.dataclass(frozen=True)
class GroundTruthExplanation:
    """One object (counted ground-truth instance) and how the predictions met it.

    Attributes:
      gt_id: benchmark id (`nyu40 * 1000 + objectId + 1`).
      nyu40, class_name: its class.
      size: its vertex count.
      status: one of `GT_STATUSES`.
      best_prediction: input row of the prediction with the highest IoU with it, any class (None: no
        evaluated prediction touches it); best_iou, best_class, best_confidence describe that one.
      best_same_class_iou: highest IoU of a prediction of its class (0 without one).
      passes_50, passes_25: a prediction of its class passes 0.5 / 0.25 (the benchmark's AP50 / AP25).
      match: input row of its AP50 match (the ``true_positive`` prediction), None when not found.
      num_fragments: evaluated predictions holding more than half of their vertices inside it without
        passing 0.5 with it (pieces of it).
      centroid: `(3,)` mean of its vertices, when the vertices were given.
    """

    gt_id: int
    nyu40: int
    class_name: str
    size: int
    status: str
    best_prediction: int | None
    best_iou: float
    best_class: str | None
    best_confidence: float | None
    best_same_class_iou: float
    passes_50: bool
    passes_25: bool
    match: int | None
    num_fragments: int
    centroid: tuple[float, float, float] | None = None


@dataclasses.dataclass(frozen=True)
class PredictionExplanation:
    """One evaluated prediction and what it is.

    Attributes:
      index: its row in the input predictions (mask file `<scene>_<index>.txt` of `fmfusion run`).
      nyu40, class_name, confidence, size: as predicted (size in vertices).
      kind: one of `PREDICTION_KINDS`.
      ap50: its role in the benchmark at AP50, one of `AP50_ROLES`.
      best_gt: benchmark id of the object with its highest IoU (None: it touches no object);
        best_iou and best_gt_class describe that one.
      reference_gt: benchmark id of its reference object (module docstring), None without one.
      shares: vertex shares per `SHARE_NAMES`, against the reference object (sum 1).
      centroid: `(3,)` mean of its vertices, when the vertices were given.
    """

    index: int
    nyu40: int
    class_name: str
    confidence: float
    size: int
    kind: str
    ap50: str
    best_gt: int | None
    best_iou: float
    best_gt_class: str | None
    reference_gt: int | None
    shares: tuple[float, ...]
    centroid: tuple[float, float, float] | None = None


@dataclasses.dataclass(frozen=True)
class SceneExplanation:
    """The error analysis of one scene.

    Attributes:
      scene_name: for titles.
      ground_truth: one entry per object, in increasing benchmark id (the evaluator's order).
      predictions: one entry per evaluated prediction, in input order.
      num_input_predictions: predictions given, evaluated or not.
      num_skipped_predictions: those the benchmark does not evaluate (under `MIN_REGION_SIZE` vertices or
        of a class outside the 18).
    """

    scene_name: str
    ground_truth: tuple[GroundTruthExplanation, ...]
    predictions: tuple[PredictionExplanation, ...]
    num_input_predictions: int
    num_skipped_predictions: int

    def status_counts(self) -> dict[str, int]:
        """Status -> objects, every status present (0 included), in `GT_STATUSES` order."""
        return _count([g.status for g in self.ground_truth], GT_STATUSES)

    def kind_counts(self) -> dict[str, int]:
        """Kind -> evaluated predictions, in `PREDICTION_KINDS` order."""
        return _count([p.kind for p in self.predictions], PREDICTION_KINDS)

    def ap50_counts(self) -> dict[str, int]:
        """AP50 role -> evaluated predictions (true positives equal the benchmark's)."""
        return _count([p.ap50 for p in self.predictions], AP50_ROLES)

    def class_counts(self) -> dict[str, dict]:
        """Class -> {"objects": n, "status": {status: n}, "predictions": n, "kind": {kind: n}}, for the
        classes with objects or predictions (benchmark order)."""
        table = {}
        for name in benchmark_class_names():
            gts = [g.status for g in self.ground_truth if g.class_name == name]
            preds = [p.kind for p in self.predictions if p.class_name == name]
            if gts or preds:
                table[name] = {
                    "objects": len(gts),
                    "status": _count(gts, GT_STATUSES),
                    "predictions": len(preds),
                    "kind": _count(preds, PREDICTION_KINDS),
                }
        return table

    def summary_line(self) -> str:
        """One line: status counts | kind counts (the counts `fmfusion eval --explain` prints)."""
        statuses = ", ".join(f"{k} {v}" for k, v in self.status_counts().items())
        kinds = ", ".join(f"{k} {v}" for k, v in self.kind_counts().items())
        return f"{len(self.ground_truth)} objects: {statuses} | {len(self.predictions)} predictions: {kinds}"

    def to_json_dict(self) -> dict:
        return {
            "scene": self.scene_name,
            "rules": {
                "iou_50": IOU_50,
                "iou_25": IOU_25,
                "overlap_iou": OVERLAP_IOU,
                "overlap_cover": OVERLAP_COVER,
                "smear_off_share": SMEAR_OFF_SHARE,
                "inside_share": INSIDE_SHARE,
                "min_fragments": MIN_FRAGMENTS,
                "min_region_size": MIN_REGION_SIZE,
            },
            "counts": {
                "objects": self.status_counts(),
                "predictions": self.kind_counts(),
                "ap50": self.ap50_counts(),
                "num_input_predictions": self.num_input_predictions,
                "num_skipped_predictions": self.num_skipped_predictions,
            },
            "classes": self.class_counts(),
            "ground_truth": [dataclasses.asdict(g) for g in self.ground_truth],
            "predictions": [{**dataclasses.asdict(p), "shares": dict(zip(SHARE_NAMES, p.shares))} for p in self.predictions],
        }


# ---------------------------------------------------------------------------------------------------
# The counts everything is decided from.


@dataclasses.dataclass(frozen=True, eq=False)
class OverlapCounts:
    """Vertices shared by the evaluated predictions (P) and the benchmark-class instances (I).

    Attributes:
      instance_ids: `(I,)` int64 benchmark ids of the instances of the 18 classes, increasing (small ones too).
      instance_sizes: `(I,)` int64 vertex counts.
      counted: `(I,)` bool, at least `min_region_size` vertices (an object).
      rows: `(P,)` int64 input rows of the evaluated predictions.
      pred_sizes: `(P,)` int64 vertex counts.
      shared: `(P, I)` int64 vertices in both, whatever the classes.
      wall, floor, void: `(P,)` int64 vertices on wall, on floor, and on everything else outside the instances.
    """

    instance_ids: np.ndarray
    instance_sizes: np.ndarray
    counted: np.ndarray
    rows: np.ndarray
    pred_sizes: np.ndarray
    shared: np.ndarray
    wall: np.ndarray
    floor: np.ndarray
    void: np.ndarray

    @property
    def instance_classes(self) -> np.ndarray:
        return self.instance_ids // 1000

    def iou(self) -> np.ndarray:
        """`(P, I)` float64 IoU."""
        union = self.pred_sizes[:, None] + self.instance_sizes[None, :] - self.shared
        return self.shared / np.maximum(union, 1)


def vertex_categories(gt_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex category for the counts.

    Args:
      gt_ids: `(V,)` int benchmark ids (`nyu40 * 1000 + instance`, 0 = none).

    Returns:
      instance_ids: `(I,)` int64 benchmark ids of the instances of the 18 classes, increasing.
      category: `(V,)` int64: `0..I-1` the vertex's instance, `I` wall, `I + 1` floor, `I + 2` void.
    """
    gt_ids = np.asarray(gt_ids, np.int64).reshape(-1)
    nyu40 = gt_ids // 1000
    benchmark = np.isin(nyu40, np.asarray(BENCHMARK_NYU40_IDS, np.int64))
    instance_ids = np.unique(gt_ids[benchmark])
    n = len(instance_ids)
    category = np.where(nyu40 == WALL_NYU40, n, np.where(nyu40 == FLOOR_NYU40, n + 1, n + 2))
    category[benchmark] = np.searchsorted(instance_ids, gt_ids[benchmark])
    return instance_ids, category


def overlap_counts(gt_ids: np.ndarray, preds: InstancePredictions, min_region_size: int = MIN_REGION_SIZE) -> OverlapCounts:
    """The shared-vertex counts of the predictions the benchmark evaluates (`OverlapCounts`).

    Args:
      gt_ids: `(V,)` int benchmark ids; preds: `(P_in, V)` masks over the same vertices.
    """
    gt_ids = np.asarray(gt_ids, np.int64).reshape(-1)
    if preds.num_vertices != gt_ids.shape[0]:
        raise ValueError(f"predictions cover {preds.num_vertices} vertices but the ground truth has {gt_ids.shape[0]}")
    instance_ids, category = vertex_categories(gt_ids)
    n = len(instance_ids)
    sizes_in = preds.masks.sum(axis=1)
    # The benchmark's own filter (match_scene): its classes, at least the minimum size.
    rows = np.flatnonzero(np.isin(preds.nyu40_ids, BENCHMARK_NYU40_IDS) & (sizes_in >= min_region_size))
    counts = np.zeros((len(rows), n + 3), np.int64)
    for k, row in enumerate(rows):
        counts[k] = np.bincount(category[preds.masks[row]], minlength=n + 3)
    instance_sizes = np.bincount(category, minlength=n + 3)[:n].astype(np.int64)
    return OverlapCounts(
        instance_ids=instance_ids,
        instance_sizes=instance_sizes,
        counted=instance_sizes >= min_region_size,
        rows=rows.astype(np.int64),
        pred_sizes=sizes_in[rows].astype(np.int64),
        shared=counts[:, :n],
        wall=counts[:, n],
        floor=counts[:, n + 1],
        void=counts[:, n + 2],
    )


# ---------------------------------------------------------------------------------------------------
# The rules (module docstring), each a small function of the counts.


def ap50_matches(counts: OverlapCounts, classes: np.ndarray, confidences: np.ndarray) -> np.ndarray:
    """`(I,)` int64 index (into the evaluated predictions) of each object's AP50 match, -1 for none.

    Args:
      classes, confidences: `(P,)` of the evaluated predictions.
    """
    passes = _same_class(counts, classes) & (counts.iou() > IOU_50)  # (P, I)
    match = np.full(len(counts.instance_ids), -1, np.int64)
    for i in np.flatnonzero(counts.counted):
        candidates = np.flatnonzero(passes[:, i])
        if len(candidates):
            match[i] = candidates[np.argmax(confidences[candidates])]  # argmax: the first on ties
    return match


def ap50_roles(counts: OverlapCounts, classes: np.ndarray, match: np.ndarray) -> list[str]:
    """Each evaluated prediction's role in the benchmark at AP50 (`AP50_ROLES`), by its rules."""
    passes = _same_class(counts, classes) & (counts.iou() > IOU_50)
    matched = set(match[match >= 0].tolist())
    small_same = (_same_class(counts, classes) & ~counts.counted[None, :]) * counts.shared
    ignorable = (counts.wall + counts.floor + counts.void + small_same.sum(axis=1)) / counts.pred_sizes
    roles = []
    for p in range(len(counts.rows)):
        if p in matched:
            roles.append("true_positive")
        elif (passes[p] & counts.counted).any():
            roles.append("false_positive")  # a duplicate of a match
        elif passes[p].any() or ignorable[p] > IOU_50:
            roles.append("ignored")  # passes only with a small instance, or mostly on void / small ones
        else:
            roles.append("false_positive")
    return roles


def reference_objects(counts: OverlapCounts) -> tuple[np.ndarray, np.ndarray]:
    """Each prediction's reference object (module docstring) and whether it overlaps it.

    Returns:
      reference: `(P,)` int64 instance index, -1 when it touches no object.
      overlapping: `(P,)` bool, it overlaps its reference object.
    """
    iou = counts.iou()
    cover = counts.shared / np.maximum(counts.instance_sizes, 1)[None, :]
    overlaps = counts.counted[None, :] & ((iou >= OVERLAP_IOU) | (cover >= OVERLAP_COVER))
    touches = counts.counted[None, :] & (counts.shared > 0)
    reference = np.full(len(counts.rows), -1, np.int64)
    for p in range(len(counts.rows)):
        candidates = np.flatnonzero(overlaps[p]) if overlaps[p].any() else np.flatnonzero(touches[p])
        if len(candidates):
            # most shared vertices, then higher IoU, then lower id (candidates are in id order)
            reference[p] = max(candidates, key=lambda i: (counts.shared[p, i], iou[p, i], -i))
    overlapping = np.array([r >= 0 and bool(overlaps[p, r]) for p, r in enumerate(reference)], bool)
    return reference, overlapping


def prediction_kinds(
    counts: OverlapCounts, classes: np.ndarray, match: np.ndarray, reference: np.ndarray, overlapping: np.ndarray
) -> list[str]:
    """Each evaluated prediction's kind (`PREDICTION_KINDS`), by the rules of the module docstring."""
    passes = (counts.iou() > IOU_50) & counts.counted[None, :]
    same = _same_class(counts, classes)
    matched = set(match[match >= 0].tolist())
    kinds = []
    for p in range(len(counts.rows)):
        inside = counts.shared[p, reference[p]] / counts.pred_sizes[p] if reference[p] >= 0 else 0.0
        if p in matched:
            kinds.append("true_positive")
        elif (passes[p] & same[p]).any():
            kinds.append("duplicate")
        elif passes[p].any():
            kinds.append("wrong_class")
        elif overlapping[p] and 1.0 - inside > SMEAR_OFF_SHARE:
            kinds.append("smear")
        elif inside > INSIDE_SHARE:
            kinds.append("fragment")
        else:
            kinds.append("no_object")
    return kinds


def object_statuses(counts: OverlapCounts, classes: np.ndarray) -> list[str]:
    """Each object's status (`GT_STATUSES`), by the rules of the module docstring; `(G,)` in id order."""
    iou = counts.iou()
    same = _same_class(counts, classes)
    pieces = _pieces(counts)
    statuses = []
    for i in np.flatnonzero(counts.counted):
        best_same = float(iou[same[:, i], i].max(initial=0.0))
        if best_same > IOU_50:
            statuses.append("found")
        elif (iou[~same[:, i], i] > IOU_50).any():
            statuses.append("wrong_class")
        elif int(pieces[:, i].sum()) >= MIN_FRAGMENTS:
            statuses.append("fragmented")
        elif best_same > IOU_25:
            statuses.append("low_iou")
        else:
            statuses.append("missed")
    return statuses


def explain_scene(
    gt_ids: np.ndarray,
    preds: InstancePredictions,
    vertices: np.ndarray | None = None,
    class_names: Mapping[int, str] | None = None,
    scene_name: str = "scene",
    min_region_size: int = MIN_REGION_SIZE,
) -> SceneExplanation:
    """The error analysis of one scene (rules in the module docstring).

    Args:
      gt_ids: `(V,)` int benchmark ids of the mesh vertices (`nyu40 * 1000 + objectId + 1`, 0 = none).
      preds: `(P, V)` masks, nyu40 ids and confidences over the same vertices; the analysis is of the map's
        instances, each once under its most likely class (`InstancePredictions.primary()`: the alternative class
        hypotheses are left out).
      vertices: `(V, 3)` mesh vertices, for the centroids in the records (optional).
      class_names: nyu40 id -> name (default: the benchmark's names of its 18 classes).
      scene_name: for titles.
    """
    preds = preds.primary()
    if class_names is None:
        class_names = dict(zip(BENCHMARK_NYU40_IDS, benchmark_class_names()))
    counts = overlap_counts(gt_ids, preds, min_region_size)
    classes = preds.nyu40_ids[counts.rows]
    confidences = preds.confidences[counts.rows]
    iou = counts.iou()
    match = ap50_matches(counts, classes, confidences)
    roles = ap50_roles(counts, classes, match)
    reference, overlapping = reference_objects(counts)
    kinds = prediction_kinds(counts, classes, match, reference, overlapping)
    statuses = object_statuses(counts, classes)
    gt_centroids, pred_centroids = _centroids(gt_ids, preds, counts, vertices)
    objects = np.flatnonzero(counts.counted)
    same = _same_class(counts, classes)
    pieces = _pieces(counts)

    ground_truth = []
    for status, i in zip(statuses, objects):
        best = int(np.argmax(iou[:, i])) if len(classes) and counts.shared[:, i].any() else -1
        ground_truth.append(
            GroundTruthExplanation(
                gt_id=int(counts.instance_ids[i]),
                nyu40=int(counts.instance_classes[i]),
                class_name=class_names.get(int(counts.instance_classes[i]), str(counts.instance_classes[i])),
                size=int(counts.instance_sizes[i]),
                status=status,
                best_prediction=int(counts.rows[best]) if best >= 0 else None,
                best_iou=float(iou[best, i]) if best >= 0 else 0.0,
                best_class=class_names.get(int(classes[best]), str(classes[best])) if best >= 0 else None,
                best_confidence=float(confidences[best]) if best >= 0 else None,
                best_same_class_iou=float(iou[same[:, i], i].max(initial=0.0)),
                passes_50=bool((iou[same[:, i], i] > IOU_50).any()),
                passes_25=bool((iou[same[:, i], i] > IOU_25).any()),
                match=int(counts.rows[match[i]]) if match[i] >= 0 else None,
                num_fragments=int(pieces[:, i].sum()),
                centroid=gt_centroids.get(int(i)),
            )
        )

    predictions = []
    object_iou = np.where(counts.counted[None, :], iou, -1.0)
    for p, row in enumerate(counts.rows):
        best = int(np.argmax(object_iou[p])) if (counts.shared[p] * counts.counted).any() else -1
        predictions.append(
            PredictionExplanation(
                index=int(row),
                nyu40=int(classes[p]),
                class_name=class_names.get(int(classes[p]), str(classes[p])),
                confidence=float(confidences[p]),
                size=int(counts.pred_sizes[p]),
                kind=kinds[p],
                ap50=roles[p],
                best_gt=int(counts.instance_ids[best]) if best >= 0 else None,
                best_iou=float(iou[p, best]) if best >= 0 else 0.0,
                best_gt_class=class_names.get(int(counts.instance_classes[best])) if best >= 0 else None,
                reference_gt=int(counts.instance_ids[reference[p]]) if reference[p] >= 0 else None,
                shares=_shares(counts, p, reference[p]),
                centroid=pred_centroids.get(p),
            )
        )
    return SceneExplanation(
        scene_name,
        tuple(ground_truth),
        tuple(predictions),
        num_input_predictions=preds.num_instances,
        num_skipped_predictions=preds.num_instances - len(counts.rows),
    )


def _same_class(counts: OverlapCounts, classes: np.ndarray) -> np.ndarray:
    """`(P, I)` bool, prediction and instance of the same class."""
    return np.asarray(classes, np.int64)[:, None] == counts.instance_classes[None, :]


def _pieces(counts: OverlapCounts) -> np.ndarray:
    """`(P, I)` bool: the prediction holds more than half of its vertices inside the instance but does
    not pass 0.5 with it."""
    inside = counts.shared / np.maximum(counts.pred_sizes, 1)[:, None] > INSIDE_SHARE
    return inside & ~(counts.iou() > IOU_50)


def _shares(counts: OverlapCounts, p: int, reference: int) -> tuple[float, ...]:
    """Prediction `p`'s vertex shares per `SHARE_NAMES` (rounded to 4 decimals)."""
    on_object = counts.shared[p, reference] if reference >= 0 else 0
    on_objects = counts.shared[p, counts.counted].sum()
    values = (
        on_object,
        on_objects - on_object,
        counts.shared[p, ~counts.counted].sum(),
        counts.wall[p],
        counts.floor[p],
        counts.void[p],
    )
    return tuple(round(float(v) / float(counts.pred_sizes[p]), 4) for v in values)


def _centroids(
    gt_ids: np.ndarray, preds: InstancePredictions, counts: OverlapCounts, vertices: np.ndarray | None
) -> tuple[dict[int, tuple], dict[int, tuple]]:
    """Vertex means (rounded to mm) of the objects (by instance index) and evaluated predictions (by
    position); empty without vertices."""
    if vertices is None:
        return {}, {}
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    _, category = vertex_categories(gt_ids)
    n = len(counts.instance_ids)
    sums = np.stack([np.bincount(category, weights=vertices[:, d], minlength=n + 3)[:n] for d in range(3)], axis=1)
    gt = {int(i): _point(sums[i] / counts.instance_sizes[i]) for i in np.flatnonzero(counts.counted)}
    pred_sums = preds.masks[counts.rows].astype(np.float64) @ vertices if len(counts.rows) else np.zeros((0, 3))
    pred = {p: _point(pred_sums[p] / counts.pred_sizes[p]) for p in range(len(counts.rows))}
    return gt, pred


def _point(xyz: np.ndarray) -> tuple[float, float, float]:
    return cast("tuple[float, float, float]", tuple(round(float(v), 3) for v in xyz))  # xyz: (3,)


def _count(values: list[str], names: tuple[str, ...]) -> dict[str, int]:
    return {name: sum(v == name for v in values) for name in names}
