"""A fused map's instances matched to the ground-truth instances of the scene's annotated mesh.

The rule (documented, simpler than the benchmark's per-class matching, and covering all 20 classes,
wall and floor included): each instance's points are transferred to the ground-truth mesh vertices as for
the benchmark export (`io.vertex_transfer.points_to_vertex_masks`, nearest instance within the
transfer radius, so the vertex masks are disjoint); an instance is matched to the ground-truth instance
of a closed class with which its vertex IoU is largest, when that IoU is at least 0.5. Disjoint masks
make an IoU above 0.5 unique on both sides, so the matching is one to one.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from fmfusion_jax.instances import MapInstance
from fmfusion_jax.io.vertex_transfer import points_to_vertex_masks
from fmfusion_jax.labels import LabelSets, load_label_sets
from fmfusion_jax.likelihood.summarize import mask_iou
from fmfusion_jax.simulation.render import instance_classes

MATCH_IOU = 0.5


@dataclasses.dataclass
class MatchedInstances:
    """Instances of fused maps matched to ground truth: what calibration and label accuracy need.

    Attributes:
      histograms: `(N, O)` float32 open-set label histogram of each instance.
      classes: `(N,)` int64 true class (closed-class index) of its ground-truth instance.
      predicted: `(N,)` int64 the class the map gave it (argmax of the engine's distribution).
      iou: `(N,)` vertex IoU with its ground-truth instance.
      scenes: `N` scene names.
    """

    histograms: np.ndarray
    classes: np.ndarray
    predicted: np.ndarray
    iou: np.ndarray
    scenes: list[str]

    def __len__(self) -> int:
        return int(self.classes.size)

    @staticmethod
    def empty(num_open: int) -> "MatchedInstances":
        return MatchedInstances(
            np.zeros((0, num_open), np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), []
        )

    @staticmethod
    def concatenate(parts: Sequence["MatchedInstances"], num_open: int) -> "MatchedInstances":
        if not parts:
            return MatchedInstances.empty(num_open)
        return MatchedInstances(
            np.concatenate([p.histograms for p in parts]),
            np.concatenate([p.classes for p in parts]),
            np.concatenate([p.predicted for p in parts]),
            np.concatenate([p.iou for p in parts]),
            [name for p in parts for name in p.scenes],
        )


def vertex_iou(pred_masks: np.ndarray, gt_instance_ids: np.ndarray, candidate_ids: np.ndarray) -> np.ndarray:
    """`(P, G)` IoU of each predicted vertex mask (`(P, V)` bool) with the vertices of each ground-truth
    instance in `candidate_ids` (`(G,)`; `gt_instance_ids` `(V,)`, 0 = none): `summarize.mask_iou` with the
    mesh's vertices as the pixels, transposed."""
    return mask_iou(gt_instance_ids, candidate_ids, pred_masks).T


def match_instances(
    instances: Sequence[MapInstance],
    gt,
    scene_name: str,
    label_sets: LabelSets | None = None,
    radius: float = 0.08,
    min_iou: float = MATCH_IOU,
) -> MatchedInstances:
    """The instances of one map matched to the scene's ground truth (see the module docstring).

    Args:
      instances: the map's instances (`mapping.extract_map_instances(result, postprocess=False)`: with
        post-processing the merged floor's distribution is an average, no longer `h @ L`).
      gt: the scene's `io.ground_truth.SceneGroundTruth`.
      radius: the transfer radius (config `export.transfer_radius`).
    """

    label_sets = label_sets or load_label_sets()
    classes = instance_classes(gt, label_sets)
    candidates = np.array(sorted(classes), np.int64)
    if not instances or candidates.size == 0:
        return MatchedInstances.empty(label_sets.num_open)
    masks = points_to_vertex_masks(gt.vertices, [inst.points for inst in instances], radius)
    iou = vertex_iou(masks, gt.instance_ids, candidates)
    best = iou.argmax(axis=1)
    best_iou = iou[np.arange(len(instances)), best]
    keep = np.flatnonzero(best_iou >= min_iou)
    if keep.size == 0:
        return MatchedInstances.empty(label_sets.num_open)
    return MatchedInstances(
        histograms=np.stack([instances[int(k)].open_label_histogram for k in keep]).astype(np.float32),
        classes=np.array([classes[int(candidates[best[k]])] for k in keep], np.int64),
        predicted=np.array([instances[int(k)].class_index for k in keep], np.int64),
        iou=best_iou[keep].astype(np.float64),
        scenes=[scene_name] * keep.size,
    )
