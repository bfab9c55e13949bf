"""The exported instance map: host-side (NumPy) post-processing of the instances taken out of the engine.

The engine holds instances as voxel slots and a label table; `fmfusion_jax.pipeline` extracts each
instance's points and fused distribution into `MapInstance`s. What happens here follows the reference
pipeline's post-processing before evaluation (see docs): drop small instances, the shower-curtain rule,
merging all floors, and the conversion to ScanNet benchmark predictions.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from fmfusion_jax.config import ExportConfig
from fmfusion_jax.labels import LabelSets


@dataclasses.dataclass
class MapInstance:
    """One instance of the final map.

    Attributes:
      instance_id: row of the instance in the engine's table (stable within a run).
      distribution: `(C,)` fused class distribution (sums to 1).
      points: `(P, 3)` float32 world points (voxel centres) of the instance.
      observations: how many detections were fused into it.
      open_label_histogram: `(O,)` accumulated open-set label scores.
      support: in [0, 1], how well the detections support the instance's existence (`observation_support`);
        1 when not known.
    """

    instance_id: int
    distribution: np.ndarray
    points: np.ndarray
    observations: int
    open_label_histogram: np.ndarray
    support: float = 1.0

    @property
    def class_index(self) -> int:
        return int(np.argmax(self.distribution))

    @property
    def confidence(self) -> float:
        """The class probability times the support: the benchmark ranks by it within a class."""
        return float(np.max(self.distribution)) * float(self.support)


def observation_support(observations: int, scale: float) -> float:
    """`1 - exp(-observations / scale)`: an instance seen in one detection frame (a fragment, a false blob, a
    one-off mislabel) ranks below one that the detector found again and again. `scale <= 0`: 1."""
    if scale <= 0:
        return 1.0
    return float(1.0 - np.exp(-max(int(observations), 0) / scale))


def drop_small_instances(instances: list[MapInstance], min_points: int) -> list[MapInstance]:
    """Instances with fewer than `min_points` points are noise (reference: 200)."""
    return [inst for inst in instances if len(inst.points) >= min_points]


def apply_shower_curtain_rule(
    instances: list[MapInstance], label_sets: LabelSets, radius: float, both_ways: bool = True
) -> list[MapInstance]:
    """Curtain or shower curtain by the bathroom context: a curtain whose centre lies within `radius` of a
    toilet's or bathtub's centre is a shower curtain; with `both_ways`, a shower curtain farther than that
    from every toilet and bathtub (or in a room without one) is a curtain.

    Open-set detectors rarely say "shower curtain", and the published likelihood matrix gives the label
    "curtain" the same weight under both classes (0.665 vs 0.663), so the fused distribution cannot tell
    them apart: a stray "shower curtain" label tips any curtain over. The context decides instead (the
    reference applies the first direction only). The losing class's mass moves to the winning one.
    """
    curtain = label_sets.class_index("curtain")
    shower = label_sets.class_index("shower curtain")
    anchors = [label_sets.class_index("toilet"), label_sets.class_index("bathtub")]
    anchor_centres = np.asarray(
        [inst.points.mean(axis=0) for inst in instances if inst.class_index in anchors and len(inst.points)]
    ).reshape(-1, 3)
    out = []
    for inst in instances:
        if inst.class_index in (curtain, shower) and len(inst.points):
            near = bool(len(anchor_centres)) and np.linalg.norm(anchor_centres - inst.points.mean(axis=0), axis=1).min() < radius
            source, target = (curtain, shower) if near else (shower, curtain)
            if inst.class_index == source and (near or both_ways):
                distribution = inst.distribution.copy()
                distribution[target] += distribution[source]
                distribution[source] = 0.0
                inst = dataclasses.replace(inst, distribution=distribution)
        out.append(inst)
    return out


def merge_same_class(instances: list[MapInstance], class_index: int) -> list[MapInstance]:
    """Merges every instance of one class into one (the reference merges all floors: a room has one)."""
    members = [inst for inst in instances if inst.class_index == class_index]
    if len(members) < 2:
        return instances
    counts = np.array([len(m.points) for m in members], np.float64)
    merged = MapInstance(
        instance_id=members[int(np.argmax(counts))].instance_id,
        distribution=np.average([m.distribution for m in members], axis=0, weights=counts),
        points=np.concatenate([m.points for m in members]),
        observations=sum(m.observations for m in members),
        open_label_histogram=np.sum([m.open_label_histogram for m in members], axis=0),
        support=max(m.support for m in members),
    )
    return [inst for inst in instances if inst.class_index != class_index] + [merged]


def postprocess_instances(instances: list[MapInstance], label_sets: LabelSets, export: ExportConfig) -> list[MapInstance]:
    """The reference's export post-processing, in its order."""
    instances = drop_small_instances(instances, export.min_points)
    instances = apply_shower_curtain_rule(
        instances, label_sets, export.shower_curtain_radius, both_ways=export.curtain_by_context
    )
    instances = merge_same_class(instances, label_sets.class_index("floor"))
    return sorted(instances, key=lambda inst: inst.instance_id)
