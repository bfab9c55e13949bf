"""Simulated RAM -> GroundingDINO -> SAM detections from ground-truth instance images.

`simulate_frame` turns one `(H, W)` ground-truth instance image into a `FrameDetections` with the
failure modes of `NoiseModel`; it knows nothing about files or scenes, so procedural test scenes that
render their own instance images use it directly. `simulate_scene` renders the ground truth of a real
scene frame by frame (`render.GroundTruthRenderer`), simulates, and writes the detections in the
authors' file format, plus a `simulation.json` recording the parameters.

How one frame is made (each step draws from its own random stream spawned from the frame's generator,
so turning one failure mode off leaves the draws of the others unchanged; the failure modes of the noise
zoo draw from further streams, only when on, so that `clean`/`default` frames are unchanged by them):
1. objects: ground-truth instances of a closed class with at least `min_mask_pixels` pixels; adjacent
   pairs may merge into one object (`merge_prob`), an object may absorb a touching neighbour of any kind
   (`merge_neighbor_prob`), and non-target objects may be taken for a class (`confuser_prob`);
2. labels: each object draws its open-set labels and scores from its class's likelihood column (the
   detector's own, perturbed one with `likelihood_perturbation`), with consistent mislabels and extra
   confusions the published matrix lacks; false blobs on walls and floors (`blob_rate`);
3. tagger: the labels present in the image form the tags, each missed with `missed_tag_prob`; the
   prompt is the tags plus, with prompt augmentation, the labels detected in the recent frames;
4. detector: an object is missed (`miss_prob`, more when small); labels not in the prompt are lost and an
   object left without a label above the box threshold is relabelled with a prompt label or dropped;
5. masks: partial segmentation (wavy, straight or occluder cuts; large objects more) or a split into two
   detections, bleeding onto the background or erosion, then border noise;
6. false detections on background objects or blobs, labelled with random prompt labels; the false
   positives seen on real detections: phantoms fixed in the world (`persistent_phantoms`, projected by
   `simulate_scene` through each frame's depth and pose), background regions taken for furniture
   (`background_rate`) and over-segmented textured regions (`texture_prob`); scores miscalibrated
   (`score_miscalibration`);
7. overlaps resolved (the smaller mask wins, as the authors' PNG mask format holds one detection per
   pixel), small and image-filling masks dropped, boxes from the masks.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import time
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from detectors.prompt import PromptAugmenter
from fmfusion_jax.errors import UserError
from fmfusion_jax.io.detections import write_frame_detections
from fmfusion_jax.labels import LabelSets, load_label_sets, load_likelihood
from fmfusion_jax.simulation.noise import (
    NoiseModel,
    bleed_mask,
    cut_mask,
    erode_mask,
    mask_box,
    occlude_mask,
    perturb_border,
    random_blob,
    straight_cut_angle,
)
from fmfusion_jax.simulation.render import GroundTruthRenderer, instance_classes
from fmfusion_jax.simulation.sim_false_positives import (
    SURFACE_CLASSES,
    _background_regions,
    _blobs,
    _confuser_objects,
    _phantom_detections,
    _texture_pieces,
    phantom_mask,
    place_phantoms,
)
from fmfusion_jax.simulation.sim_labels import GENERIC_TAGS, _LabelModel, _Object, _prompt_filter, _round_labels
from fmfusion_jax.types import FrameDetections

if TYPE_CHECKING:  # pragma: no cover
    from fmfusion_jax.io.ground_truth import SceneGroundTruth

log = logging.getLogger(__name__)


#: Least length (pixel pairs 3 px apart) of the shared border of two objects that may merge.
MERGE_MIN_BORDER = 10
#: Least area ratio (smaller / larger) of two objects that may merge: SAM does not merge a cup into a wall.
MERGE_MIN_AREA_RATIO = 0.15
#: Classes never merged with a neighbour: a box prompt on an object does not pull in the wall or floor.
MERGE_EXCLUDED_CLASSES = ("wall", "floor")
#: Share of false detections placed on a background (non-target) object when one is visible.
FALSE_POSITIVE_ON_OBJECT = 0.5

#: A neighbour absorbed under `merge_neighbor_prob` is at most this many times the object's size.
NEIGHBOR_MAX_AREA_RATIO = 3.0
#: Upper end of the uniform score that `score_miscalibration` mixes in.
MISCALIBRATED_SCORE_MAX = 0.8


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


def _absorb_neighbours(
    objects: list[_Object],
    areas: Mapping[int, int],
    pairs: Mapping[tuple[int, int], int],
    instance_classes: Mapping[int, int],
    no_merge: set[int],
    rng: np.random.Generator,
    prob: float,
) -> list[_Object]:
    """`merge_neighbor_prob`: each single object, with `prob`, absorbs one touching neighbour of any kind.

    The neighbour (a target or a non-target object, never a wall or floor, at most
    `NEIGHBOR_MAX_AREA_RATIO` times the object's size, shared border >= `MERGE_MIN_BORDER`) is chosen in
    proportion to the shared border; the mask keeps the absorbing object's label, as a box prompt on a
    table whose mask takes the chair in front of it. An absorbed target is no object of its own any more.
    """
    neighbours: dict[int, list[tuple[int, int]]] = collections.defaultdict(list)
    for (a, b), border in sorted(pairs.items()):
        if border >= MERGE_MIN_BORDER:
            neighbours[a].append((b, border))
            neighbours[b].append((a, border))
    used = {m for o in objects if len(o.instances) > 1 for m in o.instances}
    absorbed: dict[int, int] = {}  # object key -> the neighbour it absorbs
    for obj in objects:
        draw = rng.random()
        own = obj.instances[0]
        if draw >= prob or len(obj.instances) > 1 or own in used or obj.class_index in no_merge:
            continue
        candidates = [
            (n, border)
            for n, border in neighbours.get(own, ())
            if n not in used and instance_classes.get(n) not in no_merge and areas[n] <= NEIGHBOR_MAX_AREA_RATIO * areas[own]
        ]
        if not candidates:
            continue
        weights = np.array([border for _, border in candidates], np.float64)
        neighbour = candidates[int(rng.choice(len(candidates), p=weights / weights.sum()))][0]
        absorbed[own] = neighbour
        used |= {own, neighbour}
    out = []
    gone = set(absorbed.values())
    for obj in objects:
        if obj.instances[0] in gone and len(obj.instances) == 1:
            continue
        merged = absorbed.get(obj.instances[0])
        if merged is not None:
            obj = dataclasses.replace(obj, instances=(obj.instances[0], merged), area=obj.area + areas[merged])
        out.append(obj)
    return out


def _passive_pixels(image: np.ndarray, instance_classes: Mapping[int, int], no_merge: set[int]) -> np.ndarray:
    """Pixels behind the objects: walls, floors, non-target objects and pixels without ground truth."""
    active = [i for i, c in instance_classes.items() if c not in no_merge]
    return ~np.isin(image, active)


def _partial_cut(
    mask: np.ndarray, fraction: float, cut_rng: np.random.Generator, style_rng: np.random.Generator, noise: NoiseModel
) -> np.ndarray:
    """The part of the mask a partial segmentation keeps: a wavy cut (drawn from `cut_rng`, as the original
    simulator), or with `partial_straight_share` / `partial_occluder_share` a straight part cut or an
    occluder removed (drawn from `style_rng`)."""
    if noise.partial_straight_share > 0 or noise.partial_occluder_share > 0:
        style = style_rng.random()
        if style < noise.partial_straight_share:
            return cut_mask(mask, style_rng, fraction, waviness=0.0, theta=straight_cut_angle(style_rng))[0]
        if style < noise.partial_straight_share + noise.partial_occluder_share:
            return occlude_mask(mask, style_rng, fraction)
    return cut_mask(mask, cut_rng, fraction)[0]


def _bleed_or_erode(
    mask: np.ndarray, passive: np.ndarray | None, rng: np.random.Generator, noise: NoiseModel, is_surface: bool
) -> np.ndarray:
    """With `bleed_prob` the mask bleeds onto the passive pixels (not for walls and floors, which are the
    background themselves), else with `erode_prob` it shrinks."""
    draw = rng.random()
    if draw < noise.bleed_prob:
        return mask if is_surface or passive is None else bleed_mask(mask, passive, rng, noise.bleed_px)
    if draw < noise.bleed_prob + noise.erode_prob:
        return erode_mask(mask, rng, noise.erode_px)
    return mask


def _miscalibrate(labels: Mapping[str, float], rng: np.random.Generator, noise: NoiseModel) -> dict[str, float]:
    """Each score mixed with a uniform draw in [box_threshold, 0.8] (share `score_miscalibration`), so it
    says little about whether the label is right. Convex mixing keeps the detector thresholds."""
    m, low = noise.score_miscalibration, noise.box_threshold
    high = max(MISCALIBRATED_SCORE_MAX, low)
    return {name: (1.0 - m) * score + m * float(rng.uniform(low, high)) for name, score in labels.items()}


def simulate_frame(
    gt_instance_image: np.ndarray,
    instance_classes: Mapping[int, int],
    frame_name: str,
    frame_index: int,
    noise: NoiseModel | None = None,
    label_sets: LabelSets | None = None,
    likelihood: np.ndarray | None = None,
    recent_labels: Iterable[str] = (),
    rng: np.random.Generator | None = None,
    phantoms: Iterable[tuple[np.ndarray, str]] = (),
) -> FrameDetections:
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
      phantoms: `persistent_phantoms` in this frame: each phantom's `(H, W)` bool mask (`phantom_mask`)
        and its fixed label; detected with `persistent_detect_prob`.

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
    # The failure modes beyond the paper's draw from streams of their own, and only when on: with them off
    # a frame is exactly the original simulator's.
    r_confusion, r_neighbor, r_style, r_large, r_edge, r_confuser, r_blob, r_score = rng.spawn(8)
    # Spawned after those: the false positives of real detections leave every earlier stream as it was.
    r_phantom, r_background, r_texture, r_extra_border = rng.spawn(4)
    model = _LabelModel(noise, label_sets, likelihood)
    class_names = list(label_sets.class_names)
    no_merge = {class_names.index(name) for name in MERGE_EXCLUDED_CLASSES if name in class_names}

    # 1. Objects: visible target instances, adjacent pairs possibly merged.
    areas = _instance_areas(image)
    visible = {i: a for i, a in areas.items() if i in instance_classes and a >= noise.min_mask_pixels}
    pairs = adjacent_pairs(image) if (noise.merge_prob > 0 or noise.merge_neighbor_prob > 0) else {}
    merged_into: dict[int, int] = {}
    if noise.merge_prob > 0 and len(visible) > 1:
        for (a, b), border in sorted(pairs.items()):
            if a not in visible or b not in visible or border < MERGE_MIN_BORDER:
                continue
            if instance_classes[a] in no_merge or instance_classes[b] in no_merge:
                continue
            draw = r_mask.random()
            small, large = sorted((visible[a], visible[b]))
            if (
                draw < noise.merge_prob
                and a not in merged_into
                and b not in merged_into
                and small >= MERGE_MIN_AREA_RATIO * large
            ):
                merged_into[a], merged_into[b] = b, a
    objects: list[_Object] = []
    for i in sorted(visible):
        partner = merged_into.get(i)
        if partner is not None and partner < i:
            continue
        members = (i,) if partner is None else (i, partner)
        key = max(members, key=lambda m: (visible[m], -m))
        objects.append(_Object(members, key, int(instance_classes[key]), sum(visible[m] for m in members)))
    if noise.merge_neighbor_prob > 0:
        objects = _absorb_neighbours(objects, areas, pairs, instance_classes, no_merge, r_neighbor, noise.merge_neighbor_prob)
    # Confusers come last, so that the draws of the target objects do not depend on them.
    real = len(objects)
    if noise.confuser_prob > 0:
        objects += _confuser_objects(model, areas, instance_classes, objects, noise, class_names, r_confuser)

    # 2. Labels each object would get from a detector that had every label in its prompt.
    drawn = [model.draw(r_label, o.class_index, o.key) for o in objects[:real]]
    if noise.extra_confusion_prob > 0:
        drawn = [model.confuse(r_confusion, o.class_index, labels) for o, labels in zip(objects[:real], drawn)]
    for o in objects[real:]:
        assert o.fixed_labels is not None  # confusers carry their labels
        drawn.append(dict(o.fixed_labels))
    blobs = _blobs(image, instance_classes, class_names, model, r_blob) if noise.blob_rate > 0 else []
    # Phantoms and background regions are what the detector sees in the image: their labels are tagged.
    surface = {class_names.index(name) for name in SURFACE_CLASSES if name in class_names}
    extra: list[tuple[np.ndarray, dict[str, float]]] = []
    if noise.persistent_detect_prob > 0:
        targets = [i for i, c in instance_classes.items() if c not in surface]
        extra += _phantom_detections(phantoms, ~np.isin(image, targets), model, r_phantom)
    if noise.background_rate > 0:
        background = (image == 0) | np.isin(image, [i for i, c in instance_classes.items() if c in surface])
        extra += _background_regions(image, background, class_names, model, r_background)

    # 3. Tagger and prompt.
    present = sorted(
        {name for labels in drawn for name in labels}
        | {name for _, labels in blobs for name in labels}
        | {name for _, labels in extra for name in labels}
    )
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
    passive = _passive_pixels(image, instance_classes, no_merge) if noise.bleed_prob > 0 else None
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
            mask = _partial_cut(mask, r_mask.uniform(0.35, 0.85), r_mask, r_style, noise)
            parts = [(mask, labels)]
        elif mode < noise.partial_prob + noise.split_prob:
            first, second = cut_mask(mask, r_mask, r_mask.uniform(0.3, 0.7))
            # The second part is a detection of its own: its labels are drawn again (a confuser's are fixed).
            if obj.fixed_labels is not None:
                second_labels = _prompt_filter(obj.fixed_labels, prompt_set)
            else:
                second_labels = model.draw(r_label, obj.class_index, obj.key)
                if noise.extra_confusion_prob > 0:
                    second_labels = model.confuse(r_confusion, obj.class_index, second_labels)
                second_labels = _prompt_filter(second_labels, prompt_set)
            if not second_labels or max(second_labels.values()) < noise.box_threshold:
                # No label of its own reached the prompt: it shares the first part's, a bit less sure.
                factor = r_mask.uniform(0.85, 1.0)
                second_labels = {name: max(score * factor, noise.text_threshold) for name, score in labels.items()}
                top = max(second_labels, key=second_labels.__getitem__)
                second_labels[top] = max(second_labels[top], noise.box_threshold)
            parts = [(first, labels), (second, second_labels)]
        else:
            parts = [(mask, labels)]
        if noise.partial_large_prob > 0:
            # Large objects are the ones occluders and part segmentation cut most (a table behind chairs).
            cut, fraction = r_large.random() < noise.partial_large_prob, r_large.uniform(0.3, 0.8)
            if cut and len(parts) == 1 and mode >= noise.partial_prob and obj.area >= noise.large_object_pixels:
                parts = [(_partial_cut(mask, fraction, r_large, r_style, noise), labels)]
        for part, part_labels in parts:
            if noise.bleed_prob > 0 or noise.erode_prob > 0:
                part = _bleed_or_erode(part, passive, r_edge, noise, obj.class_index in no_merge)
            detections.append((perturb_border(part, r_mask, noise.border_offset_px, noise.border_jitter_px), part_labels))

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
            detections.append((perturb_border(mask, r_false, noise.border_offset_px, noise.border_jitter_px), {label: score}))
    for mask, labels in blobs:
        labels = _prompt_filter(labels, prompt_set)
        if labels:
            detections.append((perturb_border(mask, r_blob, noise.border_offset_px, noise.border_jitter_px), labels))
    for mask, labels in extra:
        labels = _prompt_filter(labels, prompt_set)
        if labels:
            detections.append((perturb_border(mask, r_extra_border, noise.border_offset_px, noise.border_jitter_px), labels))
    if noise.texture_prob > 0:
        detections += _texture_pieces(image, areas, instance_classes, model, prompt, r_texture)
    if noise.score_miscalibration > 0:
        detections = [(mask, _miscalibrate(labels, r_score, noise)) for mask, labels in detections]

    # 7. Disjoint masks (smaller on top), size and box filters.
    return _assemble(frame_name, detections, (height, width), noise, raw_tags, tags, prompt)


def _assemble(
    frame_name: str,
    detections: list[tuple[np.ndarray, dict[str, float]]],
    shape: tuple[int, int],
    noise: NoiseModel,
    raw_tags: list[str],
    tags: list[str],
    prompt: list[str],
) -> FrameDetections:
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
    label_counts: dict[str, int]  # main (highest-score) label of each detection
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


def simulate_scene(
    scene: Any,
    gt: "SceneGroundTruth",
    out_dir: str | Path,
    noise: NoiseModel | None = None,
    render_stride: int = 2,
    every: int = 1,
    max_frames: int | None = None,
    mask_format: str = "png",
    max_distance: float = 0.05,
    progress: bool = True,
    label_sets: LabelSets | None = None,
    likelihood: np.ndarray | None = None,
) -> SimulationSummary:
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
    phantoms = place_phantoms(gt.vertices, gt.faces, gt.instance_ids, classes, noise, label_sets, likelihood)
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
        bar = tqdm(total=expected, unit="frame", desc=f"simulate {scene.name}", dynamic_ncols=True)
    try:
        for index, name, depth, T_world_camera, intrinsics in _depth_frames(scene, every):
            if max_frames is not None and len(names) >= max_frames:
                break
            gt_image = renderer.render(depth, T_world_camera, intrinsics)
            views = [(phantom_mask(p, depth, T_world_camera, intrinsics), p.label) for p in phantoms]
            detections = simulate_frame(
                gt_image, classes, name, index, noise, label_sets, likelihood, augmenter.candidates(), phantoms=views
            )
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
        **(
            {"phantoms": [{"center": p.center.round(4).tolist(), "radius": p.radius, "label": p.label} for p in phantoms]}
            if phantoms
            else {}
        ),
        "seconds": round(seconds, 3),
    }
    (out_dir / "simulation.json").write_text(json.dumps(record, indent=1) + "\n")
    return SimulationSummary(out_dir, names, per_frame, dict(label_counts), seconds)
