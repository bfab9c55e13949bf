"""The label likelihood summarized from frames with ground-truth instances and detections (Appendix B).

The paper factors the label likelihood (eq. labellike) into a tagging and a detection likelihood,

    L[o, c] = p(y = o, o in q | c) = p(y = o | o in q, c) * p(o in q | c),

and estimates both by counting over annotated frames (for o = c = table in its example):

    p(o in q | c)         = |I^_c| / |I_c|   I_c: frames observing a ground-truth instance of class c;
                                             I^_c: those of them whose prompt q contains o.
    p(y = o | o in q, c)  = |O^_c| / |O_c|   O_c: ground-truth instances of class c observed in frames
                                             whose prompt contains o; O^_c: those detected as o.

Choices the paper leaves open, made here:
- the prompt q is the text prompt the detector received (the detection file's `tags`: tagger tags plus
  prompt augmentation), since a detector can only output labels of its prompt;
- an instance is *observed* in a frame when it covers at least `min_pixels` pixels of the frame's
  ground-truth instance image (default 400 at 640x480, the simulator's least mask, scaled with the image
  area); only instances of the 20 closed classes count;
- an observed instance is matched to at most one detection, one to one, greedily by mask IoU, when
  IoU >= 0.5; an unmatched observed instance stays in O_c as *not detected* (it is a failure to output
  o, which the likelihood must account for), so the detection likelihood of a class sums to at most 1;
- the label a matched detection gives is its main (highest-score) label, so O^_c counts instances
  (`label_rule="main"`); `"weighted"` spreads one count over the detection's labels in proportion to their
  scores instead.

The counting is pure NumPy (`frame_counts`, `LikelihoodCounts.__add__`, `estimate`); `summarize_scene`
renders each detection frame's ground-truth instance image from the scene's annotated mesh and depth
(`simulation.render.GroundTruthRenderer`, the look-up the simulator uses), so real scenes with real
detections are summarized the same way as simulated ones.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fmfusion_jax.errors import UserError
from fmfusion_jax.io.detections import DetectionFolder
from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
from fmfusion_jax.io.heatmap import write_heatmap
from fmfusion_jax.io.scene import open_scene
from fmfusion_jax.labels import LabelSets, load_label_sets, write_likelihood_csv
from fmfusion_jax.simulation.render import GroundTruthRenderer, instance_classes
from fmfusion_jax.types import FrameDetections

log = logging.getLogger(__name__)

LABEL_RULES = ("main", "weighted")
#: Least pixels of a ground-truth instance in a 640x480 frame for it to count as observed (scaled with the
#: image area; the simulator's least mask size).
MIN_PIXELS_640X480 = 400
#: Least mask IoU of a detection with a ground-truth instance to count as its detection.
MATCH_IOU = 0.5


def default_min_pixels(height: int, width: int) -> int:
    """`MIN_PIXELS_640X480` scaled to an `height x width` image (at least 10)."""
    return max(10, round(MIN_PIXELS_640X480 * height * width / (640 * 480)))


@dataclasses.dataclass
class LikelihoodCounts:
    """The counts behind the summarized likelihood, summed over frames (`+` adds two).

    Attributes:
      frames_observing: `(C,)` |I_c|, frames observing an instance of class c.
      frames_prompting: `(O, C)` |I^_c| for each o: frames observing c whose prompt contains o.
      instances_prompted: `(O, C)` |O_c| for each o: instances of c observed in frames whose prompt holds o.
      instances_detected_as: `(O, C)` |O^_c| for each o: of those, the ones detected as o (float: with the
        weighted label rule a detection counts fractionally).
      frames: frames counted.
      instances: observed ground-truth instances (of a closed class), summed over frames.
      matched: those matched to a detection.
    """

    frames_observing: np.ndarray
    frames_prompting: np.ndarray
    instances_prompted: np.ndarray
    instances_detected_as: np.ndarray
    frames: int = 0
    instances: int = 0
    matched: int = 0

    @staticmethod
    def zeros(num_open: int, num_classes: int) -> "LikelihoodCounts":
        return LikelihoodCounts(
            np.zeros(num_classes, np.int64),
            np.zeros((num_open, num_classes), np.int64),
            np.zeros((num_open, num_classes), np.int64),
            np.zeros((num_open, num_classes)),
        )

    def __add__(self, other: "LikelihoodCounts") -> "LikelihoodCounts":
        return LikelihoodCounts(*(getattr(self, f.name) + getattr(other, f.name) for f in dataclasses.fields(self)))

    def to_dict(self, label_sets: LabelSets | None = None) -> dict:
        """JSON-ready: arrays as nested lists, with the label names of rows and columns."""
        out = {
            f.name: (getattr(self, f.name).tolist() if isinstance(getattr(self, f.name), np.ndarray) else getattr(self, f.name))
            for f in dataclasses.fields(self)
        }
        if label_sets is not None:
            out["open_labels"], out["class_names"] = list(label_sets.open_labels), list(label_sets.class_names)
        return out

    @staticmethod
    def from_dict(data: Mapping) -> "LikelihoodCounts":
        return LikelihoodCounts(
            np.asarray(data["frames_observing"], np.int64),
            np.asarray(data["frames_prompting"], np.int64),
            np.asarray(data["instances_prompted"], np.int64),
            np.asarray(data["instances_detected_as"], np.float64),
            int(data["frames"]),
            int(data["instances"]),
            int(data["matched"]),
        )


def frame_counts(classes: np.ndarray, label_weights: np.ndarray, prompt: np.ndarray, num_classes: int) -> LikelihoodCounts:
    """The counts of one frame.

    Args:
      classes: `(M,)` int class of each ground-truth instance observed in the frame.
      label_weights: `(M, O)` the labels each instance was detected as (a one-hot row for its matched
        detection's main label, fractions with the weighted rule, zeros when not detected).
      prompt: `(O,)` bool, the labels of the frame's prompt.
      num_classes: C.
    """
    classes = np.asarray(classes, np.int64).reshape(-1)
    prompt = np.asarray(prompt, bool)
    weights = np.asarray(label_weights, np.float64).reshape(classes.size, prompt.size)
    onehot = np.zeros((classes.size, num_classes), np.int64)
    onehot[np.arange(classes.size), classes] = 1
    per_class = onehot.sum(axis=0)  # (C,) instances of each class in the frame
    observing = (per_class > 0).astype(np.int64)
    in_prompt = prompt.astype(np.int64)[:, None]  # (O, 1)
    # A label outside the prompt cannot be a detection of it (O^_c is a subset of O_c).
    detected = (weights * prompt[None, :]).T @ onehot  # (O, C)
    return LikelihoodCounts(
        observing,
        in_prompt * observing[None, :],
        in_prompt * per_class[None, :],
        detected,
        frames=1,
        instances=int(classes.size),
        matched=int(np.count_nonzero(weights.sum(1))),
    )


def _ratio(numerator: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    numerator = np.asarray(numerator, np.float64)
    denominator = np.broadcast_to(np.asarray(denominator, np.float64), numerator.shape)
    return np.divide(numerator, denominator, out=np.zeros_like(numerator), where=denominator > 0)


def estimate(counts: LikelihoodCounts) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(tagging, detection, likelihood)`, each `(O, C)`: p(o in q | c), p(y = o | o in q, c), and their
    product. Entries without data (class never observed, or never with o in the prompt) are 0."""
    tagging = _ratio(counts.frames_prompting, counts.frames_observing[None, :])
    detection = _ratio(counts.instances_detected_as, counts.instances_prompted)
    return tagging, detection, tagging * detection


# ---------------------------------------------------------------------------------------------------
# One frame: ground-truth instances, detections, matches


def observed_instances(
    gt_image: np.ndarray, instance_classes: Mapping[int, int], min_pixels: int
) -> tuple[np.ndarray, np.ndarray]:
    """`(ids (M,), classes (M,))` of the closed-class instances covering at least `min_pixels` pixels.

    Args:
      gt_image: `(H, W)` int ground-truth instance ids, 0 = none.
      instance_classes: class index of each instance of a closed class (others are ignored).
    """
    ids, areas = np.unique(np.asarray(gt_image).ravel(), return_counts=True)
    keep = [
        (int(i), instance_classes[int(i)]) for i, a in zip(ids, areas) if i > 0 and a >= min_pixels and int(i) in instance_classes
    ]
    if not keep:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.array([i for i, _ in keep], np.int64), np.array([c for _, c in keep], np.int64)


def mask_iou(gt_image: np.ndarray, instance_ids: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """`(M, K)` IoU of each ground-truth instance's pixels with each detection mask (`(K, H, W)` bool)."""
    gt_image = np.asarray(gt_image)
    instance_ids = np.asarray(instance_ids, np.int64)
    masks = np.asarray(masks, bool)
    m, k = instance_ids.size, masks.shape[0]
    if m == 0 or k == 0:
        return np.zeros((m, k))
    # Compact index: the pixels of instance_ids[j] -> j + 1, every other pixel -> 0.
    order = np.argsort(instance_ids)
    flat = gt_image.ravel().astype(np.int64)
    pos = np.clip(np.searchsorted(instance_ids[order], flat), 0, m - 1)
    compact = np.where(instance_ids[order][pos] == flat, order[pos] + 1, 0)
    gt_area = np.bincount(compact, minlength=m + 1)[1:]
    inter = np.stack([np.bincount(compact[mask.ravel()], minlength=m + 1)[1:] for mask in masks], axis=1)
    det_area = masks.reshape(k, -1).sum(axis=1)
    union = gt_area[:, None] + det_area[None, :] - inter
    return np.divide(inter, union, out=np.zeros((m, k)), where=union > 0)


def match_one_to_one(iou: np.ndarray, min_iou: float = MATCH_IOU) -> np.ndarray:
    """`(M,)` detection matched to each row (-1 none): greedy by decreasing IoU, one to one, IoU >= min_iou."""
    iou = np.asarray(iou, np.float64)
    match = np.full(iou.shape[0], -1, np.int64)
    if iou.size == 0:
        return match
    rows, cols = np.nonzero(iou >= min_iou)
    used_cols: set[int] = set()
    for r, c in sorted(zip(rows.tolist(), cols.tolist()), key=lambda rc: (-iou[rc], rc)):
        if match[r] < 0 and c not in used_cols:
            match[r] = c
            used_cols.add(c)
    return match


def detection_label_weights(labels: Sequence[Mapping[str, float]], open_labels: Sequence[str], rule: str = "main") -> np.ndarray:
    """`(K, O)` the labels each detection counts as: one-hot on its main (highest-score) label of interest
    (ties: the first of `open_labels`), or its scores normalized to sum 1 (`rule="weighted"`)."""
    if rule not in LABEL_RULES:
        raise ValueError(f"label rule {rule!r}: expected one of {LABEL_RULES}")
    index = {name: i for i, name in enumerate(open_labels)}
    weights = np.zeros((len(labels), len(open_labels)))
    for k, detection in enumerate(labels):
        for name, score in detection.items():
            if name in index:
                weights[k, index[name]] = max(weights[k, index[name]], float(score))
    if rule == "main":
        main = np.zeros_like(weights)
        has = weights.max(axis=1, initial=0.0) > 0
        main[np.flatnonzero(has), weights[has].argmax(axis=1)] = 1.0
        return main
    return _ratio(weights, weights.sum(axis=1, keepdims=True))


def frame_record(
    gt_image: np.ndarray,
    instance_classes: Mapping[int, int],
    detections: FrameDetections,
    label_sets: LabelSets,
    min_pixels: int,
    min_iou: float = MATCH_IOU,
    label_rule: str = "main",
) -> LikelihoodCounts:
    """The counts of one frame from its ground-truth instance image and its detections."""
    ids, classes = observed_instances(gt_image, instance_classes, min_pixels)
    match = match_one_to_one(mask_iou(gt_image, ids, detections.masks), min_iou)
    per_detection = detection_label_weights(detections.labels, label_sets.open_labels, label_rule)
    weights = np.zeros((ids.size, label_sets.num_open))
    hit = match >= 0
    weights[hit] = per_detection[match[hit]]
    prompt = np.isin(np.asarray(label_sets.open_labels), list(detections.prompt))
    return frame_counts(classes, weights, prompt, label_sets.num_classes)


# ---------------------------------------------------------------------------------------------------
# Scenes


def open_with_detections(scene_dir: str | Path, detections_dir: str | Path, depth_max: float = 4.0):
    """`(scene, DetectionFolder, positions of the frames with a detection file, SceneGroundTruth)` of a scene with
    ground truth and its detections; no frame with detections is a UserError."""

    scene = open_scene(scene_dir, depth_max=depth_max)
    folder = DetectionFolder(detections_dir, image_shape=(scene.intrinsics.height, scene.intrinsics.width))
    frames = [i for i, name in enumerate(scene.frame_names) if name in folder]
    if not frames:
        raise UserError(f"no detection file in {detections_dir} matches a frame of {scene.name}")
    return scene, folder, frames, load_scannet_ground_truth(scene.path)


def summarize_scene(
    scene_dir: str | Path,
    detections_dir: str | Path,
    label_sets: LabelSets | None = None,
    min_pixels: int | None = None,
    min_iou: float = MATCH_IOU,
    label_rule: str = "main",
    depth_max: float = 4.0,
    progress: bool = False,
) -> LikelihoodCounts:
    """The counts over every frame of a scene that has a detection file.

    Args:
      scene_dir: a ScanNet-layout scene with its annotated mesh (real or generated).
      detections_dir: its detections (authors' format: simulated, or from real models).
      min_pixels: least visible pixels of an observed instance (default: `default_min_pixels`).
      depth_max: depth truncation of the rendering (metres), as the simulator and the fusion read depth.
    """

    label_sets = label_sets or load_label_sets()
    scene, folder, frames, gt = open_with_detections(scene_dir, detections_dir, depth_max)
    shape = (scene.intrinsics.height, scene.intrinsics.width)
    renderer = GroundTruthRenderer.from_ground_truth(gt)
    classes = instance_classes(gt, label_sets)
    min_pixels = default_min_pixels(*shape) if min_pixels is None else int(min_pixels)
    poses = scene.poses()
    total = LikelihoodCounts.zeros(label_sets.num_open, label_sets.num_classes)
    iterator: Iterable[int] = frames
    if progress:
        iterator = tqdm(frames, desc=f"summarize {scene.name}", unit="frame", dynamic_ncols=True)
    for i in iterator:
        gt_image = renderer.render(scene.read_depth(i), poses[i], scene.intrinsics)
        detections = folder.get(scene.frame_names[i])
        assert detections is not None  # `frames` holds only frames with a detection file
        total = total + frame_record(gt_image, classes, detections, label_sets, min_pixels, min_iou, label_rule)
    log.info(
        "%s: %d frames, %d observed instances, %d matched to a detection",
        scene.name,
        total.frames,
        total.instances,
        total.matched,
    )
    return total


def write_summary(
    out_dir: str | Path,
    counts: LikelihoodCounts,
    label_sets: LabelSets | None = None,
    sources: Sequence[str] = (),
    settings: Mapping | None = None,
) -> dict[str, Path]:
    """Writes the summarized matrices (CSV), their heat maps (PNG) and the counts (JSON) into `out_dir`.

    Files: likelihood.csv (the 38 x 20 matrix, the format of configs/labels/likelihood_statistical.csv),
    tagging.csv, detection.csv, likelihood.png, tagging.png, detection.png, counts.json.
    """

    label_sets = label_sets or load_label_sets()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tagging, detection, likelihood = estimate(counts)
    header = (
        f"Summarized with fmfusion likelihood summarize (paper, Appendix B) over {counts.frames} frames, "
        f"{counts.instances} observed instances ({counts.matched} matched to a detection).\n"
        + "".join(f"source: {s}\n" for s in sources)
    )
    matrices = {
        "likelihood": (likelihood, "label likelihood p(y=o, o in prompt | c) = detection x tagging"),
        "tagging": (tagging, "tagging likelihood p(o in prompt | c)"),
        "detection": (detection, "detection likelihood p(y=o | o in prompt, c)"),
    }
    paths: dict[str, Path] = {}
    for name, (matrix, what) in matrices.items():
        paths[f"{name}.csv"] = write_likelihood_csv(
            out_dir / f"{name}.csv", matrix, label_sets, comment=f"{what}\n{header}".rstrip("\n")
        )
        write_heatmap(
            out_dir / f"{name}.png",
            matrix,
            label_sets.open_labels,
            label_sets.class_names,
            title=f"{what}  ({counts.frames} frames)",
        )
        paths[f"{name}.png"] = out_dir / f"{name}.png"
    record = {"sources": list(sources), "settings": dict(settings or {}), "counts": counts.to_dict(label_sets)}
    paths["counts.json"] = out_dir / "counts.json"
    paths["counts.json"].write_text(json.dumps(record, indent=1) + "\n")
    return paths
