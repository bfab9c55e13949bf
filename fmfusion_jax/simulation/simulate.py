"""Simulated RAM -> GroundingDINO -> SAM detections from ground-truth instance images.

`simulate_frame` turns one `(H, W)` ground-truth instance image into a `FrameDetections` with the
failure modes of `NoiseModel`; it knows nothing about files or scenes, so procedural test scenes that
render their own instance images use it directly. `simulate_scene` renders the ground truth of a real
scene frame by frame (`render.GroundTruthRenderer`), simulates, and writes the detections in the
authors' file format, plus a `simulation.json` recording the parameters.

How one frame is made (each step draws from its own random stream spawned from the frame's generator,
so turning one failure mode off leaves the draws of the others unchanged):
1. objects: ground-truth instances of a closed class with at least `min_mask_pixels` pixels; adjacent
   pairs may merge into one object (`merge_prob`);
2. labels: each object draws its open-set labels and scores from its class's likelihood column;
3. tagger: the labels present in the image form the tags, each missed with `missed_tag_prob`; the
   prompt is the tags plus, with prompt augmentation, the labels detected in the recent frames;
4. detector: an object is missed (`miss_prob`, more when small); labels not in the prompt are lost and an
   object left without a label above the box threshold is relabelled with a prompt label or dropped;
5. masks: partial segmentation or a split into two detections, then border noise;
6. false detections on background objects or blobs, labelled with random prompt labels;
7. overlaps resolved (the smaller mask wins, as the authors' PNG mask format holds one detection per
   pixel), small and image-filling masks dropped, boxes from the masks.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Iterator, Mapping

import numpy as np

from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import LabelSets, load_label_sets, load_likelihood
from fmfusion_jax.simulation.noise import NoiseModel, cut_mask, mask_box, perturb_border, random_blob
from fmfusion_jax.types import FrameDetections

if TYPE_CHECKING:  # pragma: no cover
    from fmfusion_jax.io.ground_truth import SceneGroundTruth

log = logging.getLogger(__name__)

#: Tags the image tagger produces that are not labels of interest (they end up in `raw_tags` only).
GENERIC_TAGS = ("room", "indoor", "home", "interior", "furniture", "lamp", "pillow", "box", "book",
                "computer", "monitor", "white", "wood", "living room", "bedroom", "office", "kitchen",
                "bag", "plant", "light", "ceiling", "shoe")

#: Least length (pixel pairs 3 px apart) of the shared border of two objects that may merge.
MERGE_MIN_BORDER = 10
#: Least area ratio (smaller / larger) of two objects that may merge: SAM does not merge a cup into a wall.
MERGE_MIN_AREA_RATIO = 0.15
#: Classes never merged with a neighbour: a box prompt on an object does not pull in the wall or floor.
MERGE_EXCLUDED_CLASSES = ("wall", "floor")
#: Least p(label | class) of a prompt label that a relabelled detection takes as a related label.
RELATED_LABEL_MIN_PROB = 0.01
#: Probability that a relabelled detection with no related label in the prompt takes an unrelated one.
RELABEL_UNRELATED_SHARE = 0.2
#: Least p(label | class) of a label that can come as a detection's second or third label.
EXTRA_LABEL_MIN_PROB = 0.03
#: Share of false detections placed on a background (non-target) object when one is visible.
FALSE_POSITIVE_ON_OBJECT = 0.5


@dataclasses.dataclass
class _Object:
    instances: tuple[int, ...]   # ground-truth instances making up the object (2 when merged)
    key: int                     # the largest one: its class and persistent label are used
    class_index: int
    area: int


def _instance_areas(image: np.ndarray) -> dict[int, int]:
    flat = image.ravel()
    if flat.size and flat.min() >= 0 and flat.max() < (1 << 22):
        counts = np.bincount(flat)
        ids = np.flatnonzero(counts)
        return {int(i): int(counts[i]) for i in ids if i > 0}
    ids, counts = np.unique(flat[flat > 0], return_counts=True)
    return {int(i): int(c) for i, c in zip(ids, counts)}


def adjacent_pairs(image: np.ndarray, gap: int = 3) -> dict[tuple[int, int], int]:
    """Pairs `(a, b)`, `a < b`, of instances that touch in the image, with their shared border length.

    Two pixels `gap` apart horizontally or vertically with different nonzero ids count one unit of
    border; the gap bridges the thin unlabelled seams a depth-based rendering leaves between objects.
    """
    image = np.asarray(image, np.int64)
    keys = []
    for a, b in ((image[:, :-gap], image[:, gap:]), (image[:-gap, :], image[gap:, :])):
        a, b = a.ravel(), b.ravel()
        m = (a != b) & (a > 0) & (b > 0)
        lo, hi = np.minimum(a[m], b[m]), np.maximum(a[m], b[m])
        keys.append(np.stack([lo, hi], axis=1))
    pairs = np.concatenate(keys)
    if pairs.size == 0:
        return {}
    unique, counts = np.unique(pairs, axis=0, return_counts=True)
    return {(int(a), int(b)): int(c) for (a, b), c in zip(unique, counts)}


class _LabelModel:
    """Draws a detection's open-set labels and scores for a true closed class."""

    def __init__(self, noise: NoiseModel, label_sets: LabelSets, likelihood: np.ndarray):
        likelihood = np.asarray(likelihood, np.float64)
        if likelihood.shape != (label_sets.num_open, label_sets.num_classes):
            raise ValueError(f"likelihood shape {likelihood.shape}, expected "
                             f"({label_sets.num_open}, {label_sets.num_classes})")
        sums = likelihood.sum(axis=0, keepdims=True)
        if np.any(sums <= 0):
            raise ValueError("every likelihood column needs a positive entry")
        self.columns = likelihood / sums            # p(open label | class), each column sums to 1
        self.best = self.columns.argmax(axis=0)     # most likely open label of each class
        self.noise = noise
        self.names = label_sets.open_labels

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
        score = float(np.clip(noise.score_mean + noise.score_std * rng.standard_normal(),
                              noise.box_threshold, 0.95))
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


def simulate_frame(gt_instance_image: np.ndarray, instance_classes: Mapping[int, int], frame_name: str,
                   frame_index: int, noise: NoiseModel | None = None, label_sets: LabelSets | None = None,
                   likelihood: np.ndarray | None = None, recent_labels: Iterable[str] = (),
                   rng: np.random.Generator | None = None) -> FrameDetections:
    """Simulated detections of one frame.

    Args:
      gt_instance_image: `(H, W)` int ground-truth instance ids, 0 = none.
      instance_classes: closed-class index (0..19, a likelihood column) of each target instance; ids in
        the image but not here are background (they can only become false detections).
      frame_name: stem of the frame, e.g. ``"frame-000010"``.
      frame_index: the frame's index; with `rng=None` the frame's generator is
        `np.random.default_rng([noise.seed, frame_index])`.
      noise: the failure modes (default: `NoiseModel()`).
      label_sets, likelihood: open/closed label sets and the `(38, 20)` likelihood whose columns give the
        label distributions (default: the packaged ones, statistical likelihood).
      recent_labels: labels detected in the previous `noise.augmentation_window` frames (used for
        prompt augmentation when `noise.prompt_augmentation` is on).
      rng: the generator to draw from (default: the frame's generator).

    Returns:
      `FrameDetections` with disjoint masks, boxes from the masks, labels and scores above the detector
      thresholds, and `raw_tags`/`tags`/`prompt` consistent with the tagger and augmentation model.
    """
    noise = noise or NoiseModel()
    label_sets = label_sets or load_label_sets()
    likelihood = load_likelihood("statistical") if likelihood is None else likelihood
    image = np.asarray(gt_instance_image)
    if image.ndim != 2:
        raise ValueError(f"gt_instance_image must be (H, W), got {image.shape}")
    height, width = image.shape
    rng = rng if rng is not None else noise.frame_rng(frame_index)
    r_label, r_tag, r_detect, r_mask, r_false = rng.spawn(5)
    model = _LabelModel(noise, label_sets, likelihood)

    # 1. Objects: visible target instances, adjacent pairs possibly merged.
    areas = _instance_areas(image)
    visible = {i: a for i, a in areas.items() if i in instance_classes and a >= noise.min_mask_pixels}
    merged_into: dict[int, int] = {}
    if noise.merge_prob > 0 and len(visible) > 1:
        no_merge = {label_sets.class_names.index(name) for name in MERGE_EXCLUDED_CLASSES
                    if name in label_sets.class_names}
        for (a, b), border in sorted(adjacent_pairs(image).items()):
            if a not in visible or b not in visible or border < MERGE_MIN_BORDER:
                continue
            if instance_classes[a] in no_merge or instance_classes[b] in no_merge:
                continue
            draw = r_mask.random()
            small, large = sorted((visible[a], visible[b]))
            if (draw < noise.merge_prob and a not in merged_into and b not in merged_into
                    and small >= MERGE_MIN_AREA_RATIO * large):
                merged_into[a], merged_into[b] = b, a
    objects: list[_Object] = []
    for i in sorted(visible):
        partner = merged_into.get(i)
        if partner is not None and partner < i:
            continue
        members = (i,) if partner is None else (i, partner)
        key = max(members, key=lambda m: (visible[m], -m))
        objects.append(_Object(members, key, int(instance_classes[key]), sum(visible[m] for m in members)))

    # 2. Labels each object would get from a detector that had every label in its prompt.
    drawn = [model.draw(r_label, o.class_index, o.key) for o in objects]

    # 3. Tagger and prompt.
    present = sorted({name for labels in drawn for name in labels})
    tags = [name for name in present if r_tag.random() >= noise.missed_tag_prob]
    generic = []
    if noise.raw_extra_tags:
        count = min(noise.raw_extra_tags, len(GENERIC_TAGS))
        generic = [GENERIC_TAGS[k] for k in r_tag.choice(len(GENERIC_TAGS), size=count, replace=False)]
    raw_tags = sorted(set(tags) | set(generic))
    prompt = list(tags)
    if noise.prompt_augmentation:
        excluded = set(label_sets.prompt_augmentation_excluded)
        known = set(label_sets.open_labels)
        prompt += sorted({name for name in recent_labels if name in known and name not in excluded} - set(tags))
    prompt_set = set(prompt)

    # 4-5. Detector and segmenter for each object.
    detections: list[tuple[np.ndarray, dict[str, float]]] = []
    span = max(noise.small_object_pixels - noise.min_mask_pixels, 1)
    for obj, labels in zip(objects, drawn):
        small = np.clip((noise.small_object_pixels - obj.area) / span, 0.0, 1.0)
        missed = r_detect.random() < noise.miss_prob + noise.small_object_miss_prob * small
        relabel_draw = r_detect.random()
        if missed:
            continue
        labels = _prompt_filter(labels, prompt_set)
        if not labels or max(labels.values()) < noise.box_threshold:
            replacement = model.relabel(r_detect, obj.class_index, prompt) if relabel_draw < noise.relabel_prob else None
            if replacement is None:
                continue
            labels = {**labels, **replacement}
        mask = image == obj.instances[0]
        for other in obj.instances[1:]:
            mask |= image == other
        mode = r_mask.random()
        if mode < noise.partial_prob:
            mask, _ = cut_mask(mask, r_mask, r_mask.uniform(0.35, 0.85))
            parts = [(mask, labels)]
        elif mode < noise.partial_prob + noise.split_prob:
            first, second = cut_mask(mask, r_mask, r_mask.uniform(0.3, 0.7))
            # The second part is a detection of its own: its labels are drawn again.
            second_labels = _prompt_filter(model.draw(r_label, obj.class_index, obj.key), prompt_set)
            if not second_labels or max(second_labels.values()) < noise.box_threshold:
                # No label of its own reached the prompt: it shares the first part's, a bit less sure.
                factor = r_mask.uniform(0.85, 1.0)
                second_labels = {name: max(score * factor, noise.text_threshold) for name, score in labels.items()}
                top = max(second_labels, key=second_labels.get)
                second_labels[top] = max(second_labels[top], noise.box_threshold)
            parts = [(first, labels), (second, second_labels)]
        else:
            parts = [(mask, labels)]
        for part, part_labels in parts:
            detections.append((perturb_border(part, r_mask, noise.border_offset_px, noise.border_jitter_px),
                               part_labels))

    # 6. False detections.
    count = int(r_false.poisson(noise.false_positive_rate)) if noise.false_positive_rate > 0 else 0
    if count and prompt:
        background = sorted(i for i, a in areas.items() if i not in instance_classes and a >= noise.min_mask_pixels)
        targets = [i for i in visible if label_sets.class_names[instance_classes[i]] != "wall"]
        free = np.flatnonzero(~np.isin(image, targets).ravel())
        for _ in range(count):
            label = prompt[int(r_false.integers(len(prompt)))]
            score = float(r_false.uniform(noise.box_threshold, noise.box_threshold + 0.08))
            if background and r_false.random() < FALSE_POSITIVE_ON_OBJECT:
                mask = image == background[int(r_false.integers(len(background)))]
            else:
                pixel = int(free[r_false.integers(free.size)]) if free.size else int(r_false.integers(image.size))
                mask = random_blob(image.shape, (pixel % width, pixel // width), r_false)
            detections.append((perturb_border(mask, r_false, noise.border_offset_px, noise.border_jitter_px),
                               {label: score}))

    # 7. Disjoint masks (smaller on top), size and box filters.
    return _assemble(frame_name, detections, (height, width), noise, raw_tags, tags, prompt)


def _assemble(frame_name: str, detections: list[tuple[np.ndarray, dict[str, float]]], shape: tuple[int, int],
              noise: NoiseModel, raw_tags: list[str], tags: list[str], prompt: list[str]) -> FrameDetections:
    height, width = shape
    if not detections:
        result = FrameDetections.empty(frame_name, height, width)
        result.raw_tags, result.tags, result.prompt = raw_tags, tags, prompt
        return result
    areas = np.array([mask.sum() for mask, _ in detections])
    canvas = np.zeros(shape, np.int32)
    for k in np.argsort(-areas, kind="stable"):
        canvas[detections[k][0]] = k + 1
    masks, labels, boxes = [], [], []
    for k, (_, detection_labels) in enumerate(detections):
        mask = canvas == k + 1
        if mask.sum() < noise.min_mask_pixels:
            continue
        box = mask_box(mask)
        if (box[2] - box[0] > noise.max_box_fraction * width) and (box[3] - box[1] > noise.max_box_fraction * height):
            continue
        masks.append(mask)
        labels.append(_round_labels(detection_labels))
        boxes.append(box)
    if not masks:
        result = FrameDetections.empty(frame_name, height, width)
    else:
        result = FrameDetections(frame_name, np.stack(masks), labels, np.stack(boxes).astype(np.float32))
    result.raw_tags, result.tags, result.prompt = raw_tags, tags, prompt
    return result


# ---------------------------------------------------------------------------------------------------
# Whole scenes


@dataclasses.dataclass
class SimulationSummary:
    """What `simulate_scene` wrote."""

    out_dir: Path
    frame_names: list[str]
    detections_per_frame: list[int]
    label_counts: dict[str, int]       # main (highest-score) label of each detection
    seconds: float

    @property
    def median_detections(self) -> float:
        return float(np.median(self.detections_per_frame)) if self.detections_per_frame else 0.0


def _clear_previous_output(out_dir: Path) -> None:
    """Empties a previous simulation's folder; refuses a non-empty folder that is not one."""
    if not out_dir.exists():
        return
    if not out_dir.is_dir():
        raise UserError(f"{out_dir} exists and is not a folder")
    entries = [p for p in out_dir.iterdir()]
    if not entries:
        return
    if not (out_dir / "simulation.json").is_file():
        raise UserError(f"{out_dir} is not empty and holds no simulation.json: choose an empty or new folder")
    for path in entries:
        name = path.name
        if path.is_file() and name.endswith(("_label.json", "_mask.png", "_mask.npy")):
            path.unlink()


def _depth_frames(scene: Any, every: int) -> Iterator[tuple[int, str, np.ndarray, np.ndarray, Any]]:
    """`(index, name, depth, T_world_camera, intrinsics)` of the frames whose index is a multiple of `every`.

    A `fmfusion_jax.io.scene.Scene` is read depth-only (no colour decoding); any other object with
    `.frames()` yielding `RGBDFrame`s works too.
    """
    if hasattr(scene, "read_depth") and hasattr(scene, "frame_indices") and hasattr(scene, "poses"):
        poses = scene.poses()
        for i, index in enumerate(np.asarray(scene.frame_indices).tolist()):
            if index % every == 0:
                yield int(index), scene.frame_names[i], scene.read_depth(i), poses[i], scene.intrinsics
        return
    for frame in scene.frames():
        if frame.index % every == 0:
            yield frame.index, frame.name, frame.depth, frame.T_world_camera, frame.intrinsics


def simulate_scene(scene: Any, gt: "SceneGroundTruth", out_dir: str | Path, noise: NoiseModel | None = None,
                   render_stride: int = 2, every: int = 1, max_frames: int | None = None,
                   mask_format: str = "png", max_distance: float = 0.05, progress: bool = True,
                   label_sets: LabelSets | None = None, likelihood: np.ndarray | None = None) -> SimulationSummary:
    """Simulates detections for the frames of `scene` and writes them to `out_dir` in the authors' format.

    Args:
      scene: an opened scene (`fmfusion_jax.io.scene.open_scene`): `.name`, `len()`, `.frames()`.
      gt: its ground truth (`fmfusion_jax.io.ground_truth.load_scannet_ground_truth`).
      out_dir: folder for `frame-XXXXXX_label.json` + mask files and `simulation.json`; made if missing.
        A folder holding a previous simulation is emptied of its detection files first.
      noise: failure modes and seed (default: `NoiseModel()`).
      render_stride: pixel stride of the ground-truth rendering (`GroundTruthRenderer`).
      every: simulate frames whose index is a multiple of `every` (the detection frames of the fusion).
      max_frames: stop after this many simulated frames.
      mask_format: ``"png"`` or ``"npy"`` (see `fmfusion_jax.io.detections`).
      max_distance: m, ground-truth rendering tolerance between the depth and the mesh.
      progress: show a tqdm progress bar.
    """
    from detectors.prompt import PromptAugmenter
    from fmfusion_jax.io.detections import write_frame_detections
    from fmfusion_jax.simulation.render import GroundTruthRenderer, instance_classes

    if every < 1:
        raise UserError(f"every must be >= 1, got {every}")
    noise = noise or NoiseModel()
    label_sets = label_sets or load_label_sets()
    likelihood_name = "statistical" if likelihood is None else "custom"
    likelihood = load_likelihood("statistical") if likelihood is None else likelihood
    out_dir = Path(out_dir)
    _clear_previous_output(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    start = time.perf_counter()
    renderer = GroundTruthRenderer.from_ground_truth(gt, max_distance=max_distance, stride=render_stride)
    classes = instance_classes(gt, label_sets)
    augmenter = PromptAugmenter(noise.augmentation_window, label_sets.prompt_augmentation_excluded)
    names: list[str] = []
    per_frame: list[int] = []
    label_counts: collections.Counter[str] = collections.Counter()

    indices = getattr(scene, "frame_indices", None)
    expected = int(np.count_nonzero(np.asarray(indices) % every == 0)) if indices is not None else None
    if max_frames is not None:
        expected = max_frames if expected is None else min(expected, max_frames)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=expected, unit="frame", desc=f"simulate {scene.name}", dynamic_ncols=True)
    try:
        for index, name, depth, T_world_camera, intrinsics in _depth_frames(scene, every):
            if max_frames is not None and len(names) >= max_frames:
                break
            gt_image = renderer.render(depth, T_world_camera, intrinsics)
            detections = simulate_frame(gt_image, classes, name, index, noise, label_sets, likelihood,
                                        augmenter.candidates())
            write_frame_detections(out_dir, detections, mask_format=mask_format)
            augmenter.observe(label for labels in detections.labels for label in labels)
            names.append(name)
            per_frame.append(detections.num_detections)
            label_counts.update(next(iter(labels)) for labels in detections.labels)
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    seconds = time.perf_counter() - start

    record = {
        "generator": "fmfusion_jax.simulation (simulated RAM/GroundingDINO/SAM detections from ground truth)",
        "scene": scene.name,
        "seed": noise.seed,
        "noise": noise.to_dict(),
        "render": {"stride": render_stride, "max_distance": max_distance},
        "every": every,
        "mask_format": mask_format,
        "likelihood": likelihood_name,
        "frames": names,
        "detections_per_frame": per_frame,
        "main_label_counts": dict(sorted(label_counts.items(), key=lambda item: (-item[1], item[0]))),
        "seconds": round(seconds, 3),
    }
    (out_dir / "simulation.json").write_text(json.dumps(record, indent=1) + "\n")
    return SimulationSummary(out_dir, names, per_frame, dict(label_counts), seconds)
