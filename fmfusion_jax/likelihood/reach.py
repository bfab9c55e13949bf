"""What the detector ever saw: each ground-truth object against the detections of every frame.

Tells detector misses from fusion misses. An object counts as *seen* when, in at least one detection frame, a
detection mask covers its visible pixels with IoU >= 0.5 (the rendered ground-truth instance image at the frame's
depth, as `likelihood summarize` renders it), and as *seen as its class* when such a detection also carries a
label whose closed class (the argmax of the likelihood row, `label_classes`) is the object's. The
*detector-limited ceiling* is the benchmark's mAP50 if the map found exactly the objects seen, each once with
its class (AP50 of a class = the share of its objects seen; precision 1): no fusion can beat it with these
detections (a stricter one counts only the objects seen as their class).

Objects are those the benchmark scores (its 18 classes, at least 100 vertices).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from fmfusion_jax.evaluation.scannet_benchmark import MIN_REGION_SIZE
from fmfusion_jax.labels import BENCHMARK_NYU40_IDS, LabelSets, load_label_sets, load_likelihood
from fmfusion_jax.likelihood.summarize import MATCH_IOU, default_min_pixels, mask_iou, open_with_detections
from fmfusion_jax.simulation.render import GroundTruthRenderer


@dataclasses.dataclass
class ObjectReach:
    gt_id: int  # the benchmark id (nyu40 * 1000 + instance)
    class_name: str
    frames_visible: int  # detection frames in which the object covers enough pixels to be detected
    best_iou: float  # best mask IoU of any detection, any frame
    seen: bool  # best_iou >= 0.5
    seen_as_class: bool  # ... by a detection with a label of the object's class
    labels: dict[str, int]  # labels of the detections that saw it, with the frames


@dataclasses.dataclass
class DetectorReach:
    scene: str
    detection_frames: int
    objects: list[ObjectReach]

    def per_class(self) -> dict[str, dict[str, int]]:
        table: dict[str, dict[str, int]] = {}
        for o in self.objects:
            row = table.setdefault(o.class_name, {"objects": 0, "seen": 0, "seen_as_class": 0})
            row["objects"] += 1
            row["seen"] += int(o.seen)
            row["seen_as_class"] += int(o.seen_as_class)
        return table

    def ceiling_map50(self, as_class: bool = False) -> float:
        """mAP50 if the map found exactly the objects seen (`as_class`: seen as their class), each once with its
        class: the mean over the classes with objects of the share of their objects seen."""
        rows = self.per_class().values()
        key = "seen_as_class" if as_class else "seen"
        return float(np.mean([r[key] / r["objects"] for r in rows])) if rows else float("nan")

    def to_json(self) -> dict[str, Any]:
        return {
            "scene": self.scene,
            "detection_frames": self.detection_frames,
            "objects": [dataclasses.asdict(o) for o in self.objects],
            "per_class": self.per_class(),
            "seen": sum(o.seen for o in self.objects),
            "seen_as_class": sum(o.seen_as_class for o in self.objects),
            "ceiling_map50": self.ceiling_map50(),
            "ceiling_map50_as_class": self.ceiling_map50(as_class=True),
        }

    def markdown(self, found: dict[int, bool] | None = None) -> str:
        """The per-class table; `found`: gt id -> whether the map found it (AP50 match), for the last column."""
        lines = [
            f"## Detector reach: {self.scene} ({self.detection_frames} detection frames)",
            "",
            f"An object is seen when a detection mask matched it (IoU >= {MATCH_IOU}) in at least one frame; seen as "
            "its class when that detection also named its class. Detector-limited ceiling, the mAP50 if the map found "
            f"exactly the objects seen, each with its class: **{100 * self.ceiling_map50():.1f}** (only those seen as "
            f"their class: {100 * self.ceiling_map50(as_class=True):.1f}).",
            "",
            "| class | objects | seen | seen as its class |" + (" found by the map |" if found is not None else ""),
            "|---|---:|---:|---:|" + ("---:|" if found is not None else ""),
        ]
        for name, row in sorted(self.per_class().items()):
            cells = f"| {name} | {row['objects']} | {row['seen']} | {row['seen_as_class']} |"
            if found is not None:
                cells += f" {sum(found.get(o.gt_id, False) for o in self.objects if o.class_name == name)} |"
            lines.append(cells)
        total_found = f" {sum(found.values())} |" if found is not None else ""
        lines.append(
            f"| **all** | {len(self.objects)} | {sum(o.seen for o in self.objects)} | "
            f"{sum(o.seen_as_class for o in self.objects)} |{total_found}"
        )
        return "\n".join(lines) + "\n"


def label_classes(label_sets: LabelSets, likelihood: np.ndarray) -> dict[str, int]:
    """The closed class each open-set label stands for: the argmax of its likelihood row."""
    return {label: int(np.argmax(row)) for label, row in zip(label_sets.open_labels, likelihood)}


def detector_reach(
    scene_dir: str | Path,
    detections_dir: str | Path,
    likelihood: str = "manual",
    depth_max: float = 4.0,
    progress: bool = False,
) -> DetectorReach:
    """Every scored ground-truth object of `scene_dir` against the detections in `detections_dir` (module
    docstring). `likelihood`: the matrix whose rows say which class a label stands for (manual: the name table)."""

    label_sets = load_label_sets()
    stands_for = label_classes(label_sets, load_likelihood(likelihood))
    scene, folder, frames, gt = open_with_detections(scene_dir, detections_dir, depth_max)
    shape = (scene.intrinsics.height, scene.intrinsics.width)
    benchmark = set(BENCHMARK_NYU40_IDS)
    nyu40_to_class = label_sets.nyu40_to_class_index()
    ids, counts = np.unique(gt.instance_ids[gt.instance_ids > 0], return_counts=True)
    objects: dict[int, ObjectReach] = {}
    for instance, count in zip(ids.tolist(), counts.tolist()):
        nyu40 = int(np.bincount(gt.nyu40_ids[gt.instance_ids == instance]).argmax())
        if nyu40 in benchmark and count >= MIN_REGION_SIZE:
            name = label_sets.class_names[nyu40_to_class[nyu40]]
            objects[instance] = ObjectReach(nyu40 * 1000 + instance, name, 0, 0.0, False, False, {})
    renderer = GroundTruthRenderer.from_ground_truth(gt)
    min_pixels = default_min_pixels(*shape)
    poses = scene.poses()
    instance_ids = np.array(sorted(objects), np.int64)
    iterator: Any = frames
    if progress:
        iterator = tqdm(frames, desc=f"detector reach {scene.name}", unit="frame", dynamic_ncols=True)
    for i in iterator:
        detections = folder.get(scene.frame_names[i])
        assert detections is not None  # `frames` holds only frames with a detection file
        gt_image = renderer.render(scene.read_depth(i), poses[i], scene.intrinsics)
        present, pixels = np.unique(gt_image, return_counts=True)
        area = dict(zip(present.tolist(), pixels.tolist()))
        if not any(j in area for j in instance_ids.tolist()):
            continue
        iou = mask_iou(gt_image, instance_ids, detections.masks)
        for row, instance in enumerate(instance_ids.tolist()):
            reach = objects[instance]
            reach.frames_visible += int(area.get(instance, 0) >= min_pixels)
            if iou.shape[1] == 0:
                continue
            reach.best_iou = max(reach.best_iou, float(iou[row].max()))
            for k in np.flatnonzero(iou[row] >= MATCH_IOU).tolist():
                reach.seen = True
                for label in detections.labels[k]:
                    reach.labels[label] = reach.labels.get(label, 0) + 1
                    if label in stands_for and label_sets.class_names[stands_for[label]] == reach.class_name:
                        reach.seen_as_class = True
    return DetectorReach(scene.name, len(frames), sorted(objects.values(), key=lambda o: (o.class_name, o.gt_id)))


__all__ = ["DetectorReach", "ObjectReach", "detector_reach", "label_classes"]
