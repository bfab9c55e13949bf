"""The noise model of simulated foundation-model detections, and the mask perturbations it uses.

`NoiseModel` holds one parameter per failure mode of the RAM -> GroundingDINO -> SAM front end
described in the FM-Fusion paper (false label measurements, missed tags, inconsistent masks across
viewpoints, missed and false detections). Setting every failure-mode parameter to zero (the `clean`
preset) gives detections whose masks are exactly the ground-truth instance masks, each labelled with its
class's most likely open-set label. `docs/simulated-detections.md` explains each parameter and its
default. The failure modes beyond the paper's (a misspecified label model, large partial masks, merges with
any neighbour, borders bleeding onto the floor, confusers, miscalibrated scores, phantoms fixed in the
world, background taken for furniture, over-segmented textures) are zero in `clean` and
`default`; the noise families of `fmfusion_jax.simulation.zoo` turn them on, and `NoiseModel.preset`
accepts the family names too.

The mask functions here work on `(H, W)` bool masks and touch only a padded crop around the mask, so
their cost is proportional to the object's size, not the image's.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import cv2
import numpy as np

from fmfusion_jax.errors import UserError

#: The noise families of `fmfusion_jax.simulation.zoo` beyond `default` (also accepted as presets).
FAMILY_PRESETS = ("label_model", "partial", "merged", "border", "confusers", "persistent", "background", "texture")
PRESETS = ("clean", "default", "hard", *FAMILY_PRESETS)
#: Parameters that must lie in [0, 1].
PROBABILITIES = (
    "label_confusion",
    "label_persistence",
    "extra_label_prob",
    "missed_tag_prob",
    "relabel_prob",
    "extra_confusion_prob",
    "consistent_mislabel_prob",
    "score_miscalibration",
    "partial_prob",
    "split_prob",
    "merge_prob",
    "partial_large_prob",
    "partial_straight_share",
    "partial_occluder_share",
    "merge_neighbor_prob",
    "bleed_prob",
    "erode_prob",
    "miss_prob",
    "small_object_miss_prob",
    "confuser_prob",
    "persistent_detect_prob",
    "background_strip_share",
    "texture_prob",
    "texture_piece_share",
)
#: Groups of probabilities of mutually exclusive outcomes: each group must sum to at most 1.
EXCLUSIVE_GROUPS = (
    ("partial_prob", "split_prob"),
    ("partial_straight_share", "partial_occluder_share"),
    ("bleed_prob", "erode_prob"),
)
#: Parameters added after detections were cached and results recorded: `NoiseModel.to_dict` leaves them
#: out at their defaults, so that the record, cache name and detections of every model that does not use
#: them stay what they were.
LATER_PARAMS = (
    "persistent_phantoms",
    "persistent_radius_m",
    "persistent_detect_prob",
    "background_rate",
    "background_strip_share",
    "texture_prob",
    "texture_piece_share",
)


@dataclasses.dataclass(frozen=True)
class NoiseModel:
    """Failure-mode parameters of the simulated detector (probabilities are per frame and per object).

    Labels (GroundingDINO's open-set label measurements):
      label_confusion: probability that a detection's main label is drawn from its true class's column
        of the statistical likelihood (normalized); otherwise it is the column's most likely label.
      label_persistence: probability that an object reuses its own fixed label draw (one per seed and
        instance) instead of a fresh one, so that some mislabels repeat across views as they do for real.
      extra_label_prob: probability of each label beyond the first (geometric, up to `max_labels`).
      max_labels: most labels one detection carries.
      score_mean, score_std: main-label score ~ N(mean, std), kept in [box_threshold, 0.95]; further
        labels score a random 50-95% of it and are dropped below `text_threshold`.
    Misspecified label model (real detectors do not follow the published matrix; the fusion still uses it):
      likelihood_perturbation: sigma of log-normal factors on every entry of the likelihood the labels
        are drawn from (one perturbed matrix per seed: one "detector"), plus `0.05 * sigma` of mass moved
        onto a few labels each column lacks; columns re-normalized.
      extra_confusion_prob: probability that a detection of a class of `sim_labels.EXTRA_CONFUSIONS` takes
        one of the labels listed there (confusions the published matrix lacks) as its main label.
      consistent_mislabel_prob: probability, per seed and class, that the class is always named by one
        fixed wrong open-set label (one that the published matrix ascribes to another class) at a normal
        score, in every view and instance.
      score_miscalibration: share in [0, 1] of every label score replaced by a uniform draw in
        [box_threshold, 0.8], so that wrong labels and false detections score like right ones.
    Tagger (RAM) and prompt:
      missed_tag_prob: probability that the tagger misses a label present in the image in one frame;
        a detection none of whose labels reaches the prompt is relabelled or dropped.
      prompt_augmentation: add the labels detected in the previous `augmentation_window` frames to the
        prompt (except `LabelSets.prompt_augmentation_excluded`), as the paper does; off for ablation B.
      augmentation_window: frames of history for prompt augmentation.
      relabel_prob: probability that a detection whose labels all left the prompt takes a label that is
        in the prompt (weighted by the likelihood column: a false label measurement) instead of vanishing.
      raw_extra_tags: tags outside the labels of interest added to `raw_tags` (filtered out of `tags`).
    Masks (SAM):
      partial_prob: probability that only a part of the object is segmented (a wavy cut keeps 35-85%).
      split_prob: probability that the object comes as two detections (cut into two parts).
      merge_prob: probability per pair of adjacent visible objects that they come as one mask.
      border_offset_px: std of a per-mask erosion (<0) / dilation (>0) of the border, pixels.
      border_jitter_px: amplitude of a smooth random wobble of the border, pixels.
      partial_large_prob: extra probability that an object of at least `large_object_pixels` pixels is
        segmented only in part (occluded, or one part of it): 30-80% kept.
      large_object_pixels: least visible size of an object exposed to `partial_large_prob`.
      partial_straight_share, partial_occluder_share: shares of the partial cuts that are straight
        (near horizontal or vertical: seat vs back, half a cabinet) and that remove an occluder-shaped
        region (a rectangle or ellipse); the rest are wavy cuts.
      merge_neighbor_prob: probability that an object's mask also covers one touching neighbour of any
        kind (targets and non-target objects, never a wall or floor) at most 3x its size, keeping the
        object's label.
      bleed_prob, bleed_px: probability that a mask spreads by ~N(bleed_px, bleed_px / 3) pixels, further
        downwards, onto the pixels behind it only (wall, floor, non-target objects, nothing); walls and
        floors themselves do not bleed.
      erode_prob, erode_px: probability that a mask shrinks by ~N(erode_px, erode_px / 3) pixels.
    Detections:
      miss_prob: probability that a visible object is not detected at all.
      small_object_miss_prob: extra miss probability at `min_mask_pixels`, falling linearly to 0 at
        `small_object_pixels`.
      small_object_pixels: size above which objects get no extra miss probability.
      min_mask_pixels: masks smaller than this are never output (objects seen smaller are dropped).
      false_positive_rate: mean number (Poisson) of false detections per frame: an unannotated or
        non-target object, or a blob on the background, labelled with a random prompt label, low score.
      confuser_prob: probability, per seed and non-target object, that the object is taken for one of the
        closed classes: detected in every view with one fixed open-set label of that class, normal score.
      blob_rate: mean number (Poisson) per frame of false blobs on a wall or the floor, labelled with a
        label such surfaces are mistaken for, normal score.
      persistent_phantoms: phantom objects per scene and seed (rounded): places fixed in the world (a
        sphere of `persistent_radius_m` around a point of the wall, floor or unannotated surface, away
        from the objects), each taken for one closed class with one fixed open-set label. Needs the
        frames' depth and poses (`simulate_scene`; `simulate_frame` takes the projected masks).
      persistent_radius_m: the phantoms' radius, metres.
      persistent_detect_prob: probability that a phantom in view (at least `min_mask_pixels` of the
        seen surface inside its sphere, target objects excluded) is detected in a frame, normal score.
      background_rate: mean number (Poisson) per frame of background regions (wall, floor, pixels
        without ground truth) detected as furniture (`sim_false_positives.BACKGROUND_CLASSES`), normal score:
        thin strips along the surface or large patches. Drawn afresh in every frame.
      background_strip_share: share of those regions that are thin strips; the rest are large patches.
      texture_prob: probability, per frame and visible region (any instance, wall and floor included) of
        at least 4 pieces, that it is over-segmented into many small masks, each with a random prompt
        label (or a label of the region's class) at a low score.
      texture_piece_share: the pieces' mean size, as a share of the image area.
    Detector thresholds (respected by every output):
      box_threshold: least main score of a detection (GroundingDINO box threshold).
      text_threshold: least score of any label of a detection.
      max_box_fraction: masks whose box covers more than this share of the image width and height
        are dropped, as the reference front end drops such boxes.
    seed: base of every random stream; frame `i` uses `default_rng([seed, i])`.
    """

    seed: int = 0
    # labels
    label_confusion: float = 1.0
    label_persistence: float = 0.3
    extra_label_prob: float = 0.5
    max_labels: int = 3
    score_mean: float = 0.47
    score_std: float = 0.07
    # misspecified label model and scores
    likelihood_perturbation: float = 0.0
    extra_confusion_prob: float = 0.0
    consistent_mislabel_prob: float = 0.0
    score_miscalibration: float = 0.0
    # tagger and prompt
    missed_tag_prob: float = 0.2
    prompt_augmentation: bool = True
    augmentation_window: int = 5
    relabel_prob: float = 0.5
    raw_extra_tags: int = 3
    # masks
    partial_prob: float = 0.1
    split_prob: float = 0.08
    merge_prob: float = 0.05
    border_offset_px: float = 1.5
    border_jitter_px: float = 2.0
    partial_large_prob: float = 0.0
    large_object_pixels: int = 15000
    partial_straight_share: float = 0.0
    partial_occluder_share: float = 0.0
    merge_neighbor_prob: float = 0.0
    bleed_prob: float = 0.0
    bleed_px: float = 0.0
    erode_prob: float = 0.0
    erode_px: float = 0.0
    # detections
    miss_prob: float = 0.05
    small_object_miss_prob: float = 0.3
    small_object_pixels: int = 4000
    min_mask_pixels: int = 400
    false_positive_rate: float = 0.3
    confuser_prob: float = 0.0
    blob_rate: float = 0.0
    # false positives seen on real detections (`LATER_PARAMS`)
    persistent_phantoms: float = 0.0
    persistent_radius_m: float = 0.0
    persistent_detect_prob: float = 0.0
    background_rate: float = 0.0
    background_strip_share: float = 0.0
    texture_prob: float = 0.0
    texture_piece_share: float = 0.005
    # detector thresholds
    box_threshold: float = 0.35
    text_threshold: float = 0.25
    max_box_fraction: float = 0.95

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value, default = getattr(self, field.name), field.default
            if isinstance(default, bool):
                ok = isinstance(value, bool)
            elif isinstance(default, int):
                ok = isinstance(value, int) and not isinstance(value, bool)
            else:
                ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            if not ok:
                raise UserError(f"noise parameter {field.name}={value!r} must be a {type(default).__name__}")
        for name in PROBABILITIES:
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise UserError(f"noise parameter {name}={value} must be a probability in [0, 1]")
        for group in EXCLUSIVE_GROUPS:
            total = sum(getattr(self, name) for name in group)
            if total > 1.0:
                raise UserError(f"{' + '.join(group)} = {total:g} must be <= 1")
        for name in (
            "score_std",
            "border_offset_px",
            "border_jitter_px",
            "false_positive_rate",
            "likelihood_perturbation",
            "bleed_px",
            "erode_px",
            "blob_rate",
            "persistent_phantoms",
            "persistent_radius_m",
            "background_rate",
        ):
            if getattr(self, name) < 0:
                raise UserError(f"noise parameter {name}={getattr(self, name)} must be >= 0")
        # A probability without a size would silently do nothing.
        for prob, size in (
            ("bleed_prob", "bleed_px"),
            ("erode_prob", "erode_px"),
            ("persistent_phantoms", "persistent_radius_m"),
            ("texture_prob", "texture_piece_share"),
        ):
            if getattr(self, prob) > 0 and getattr(self, size) <= 0:
                raise UserError(f"{prob}={getattr(self, prob)} needs {size} > 0")
        if self.large_object_pixels < 1:
            raise UserError(f"large_object_pixels={self.large_object_pixels} must be >= 1")
        if self.max_labels < 1:
            raise UserError(f"max_labels={self.max_labels} must be >= 1")
        if self.min_mask_pixels < 1:
            raise UserError(f"min_mask_pixels={self.min_mask_pixels} must be >= 1")
        if self.augmentation_window < 0 or self.raw_extra_tags < 0:
            raise UserError("augmentation_window and raw_extra_tags must be >= 0")
        if not 0.0 < self.text_threshold <= self.box_threshold < 1.0:
            raise UserError(f"need 0 < text_threshold ({self.text_threshold}) <= box_threshold ({self.box_threshold}) < 1")

    def frame_rng(self, frame_index: int) -> np.random.Generator:
        """The generator of frame `frame_index`: reproducible on its own, whatever frames came before."""
        return np.random.default_rng([int(self.seed), int(frame_index)])

    def to_dict(self) -> dict[str, Any]:
        """Every parameter, but those of `LATER_PARAMS` only where they differ from their defaults."""
        defaults = {f.name: f.default for f in dataclasses.fields(self)}
        return {k: v for k, v in dataclasses.asdict(self).items() if k not in LATER_PARAMS or v != defaults[k]}

    def replace(self, **changes: Any) -> "NoiseModel":
        """A copy with some parameters changed; unknown names are a `UserError` naming the valid ones."""
        names = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(changes) - names)
        if unknown:
            raise UserError(f"unknown noise parameter(s) {unknown}; valid: {sorted(names)}")
        return dataclasses.replace(self, **changes)

    @staticmethod
    def preset(name: str, **changes: Any) -> "NoiseModel":
        """`clean` (ground truth, best labels), `default` (the documented defaults), `hard`, or a noise
        family (`FAMILY_PRESETS`, `FAMILY_DOSES`) at severity 1."""
        if name in FAMILY_PRESETS:
            seed = changes.pop("seed", 0)
            return family_noise(name, 1.0, seed, **changes)
        if name == "default":
            base = NoiseModel()
        elif name == "clean":
            base = NoiseModel(
                label_confusion=0.0,
                label_persistence=0.0,
                extra_label_prob=0.0,
                score_std=0.0,
                missed_tag_prob=0.0,
                relabel_prob=0.0,
                raw_extra_tags=0,
                partial_prob=0.0,
                split_prob=0.0,
                merge_prob=0.0,
                border_offset_px=0.0,
                border_jitter_px=0.0,
                miss_prob=0.0,
                small_object_miss_prob=0.0,
                min_mask_pixels=100,
                false_positive_rate=0.0,
                max_box_fraction=1.0,
            )
        elif name == "hard":
            base = NoiseModel(
                label_persistence=0.5,
                extra_label_prob=0.6,
                score_std=0.09,
                missed_tag_prob=0.35,
                relabel_prob=0.6,
                partial_prob=0.2,
                split_prob=0.15,
                merge_prob=0.1,
                border_offset_px=3.0,
                border_jitter_px=4.0,
                miss_prob=0.1,
                small_object_miss_prob=0.5,
                small_object_pixels=6000,
                min_mask_pixels=600,
                false_positive_rate=0.8,
            )
        else:
            raise UserError(f"unknown noise preset {name!r}; choose one of {', '.join(PRESETS)}")
        return base.replace(**changes) if changes else base


# ---------------------------------------------------------------------------------------------------
# Mask perturbations


def mask_bbox(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """`(v0, v1, u0, u1)` half-open row/column range of the mask's pixels, or None if empty."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask[rows[0] : rows[-1] + 1].any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def mask_box(mask: np.ndarray) -> np.ndarray:
    """`(4,)` float32 pixel box `[u0, v0, u1, v1]` enclosing the mask (pixel `u` spans `[u, u+1)`)."""
    bbox = mask_bbox(mask)
    if bbox is None:
        return np.zeros(4, np.float32)
    v0, v1, u0, u1 = bbox
    return np.array([u0, v0, u1, v1], np.float32)


def _padded_crop(shape: tuple[int, int], bbox: tuple[int, int, int, int], pad: int) -> tuple[slice, slice]:
    v0, v1, u0, u1 = bbox
    return (slice(max(v0 - pad, 0), min(v1 + pad, shape[0])), slice(max(u0 - pad, 0), min(u1 + pad, shape[1])))


def smooth_field(shape: tuple[int, int], rng: np.random.Generator, cell: float = 16.0) -> np.ndarray:
    """`shape` float32 smooth random field of about unit amplitude, correlated over ~`cell` pixels."""
    h, w = shape
    gh, gw = max(int(math.ceil(h / cell)) + 1, 2), max(int(math.ceil(w / cell)) + 1, 2)
    coarse = rng.standard_normal((gh, gw)).astype(np.float32)
    # Bilinear interpolation halves the variance between grid points; 1.4 brings it back near 1.
    return 1.4 * cv2.resize(coarse, (w, h), interpolation=cv2.INTER_LINEAR)


def perturb_border(
    mask: np.ndarray, rng: np.random.Generator, offset_std: float, jitter_px: float, cell: float = 16.0
) -> np.ndarray:
    """The mask with its border moved: a global offset ~ N(0, offset_std) px plus a smooth wobble.

    The border is moved by thresholding the signed distance to it, so the result stays one smooth
    region (like a SAM mask) rather than getting salt-and-pepper noise. Both zero: the mask itself.
    """
    if offset_std <= 0 and jitter_px <= 0:
        return mask.copy()
    bbox = mask_bbox(mask)
    if bbox is None:
        return mask.copy()
    offset = float(rng.normal(0.0, offset_std)) if offset_std > 0 else 0.0
    pad = int(math.ceil(abs(offset) + 2.5 * jitter_px)) + 2
    rows, cols = _padded_crop(mask.shape, bbox, pad)
    crop = mask[rows, cols].astype(np.uint8)
    inside = cv2.distanceTransform(crop, cv2.DIST_L2, 3)
    outside = cv2.distanceTransform(1 - crop, cv2.DIST_L2, 3)
    signed = inside - outside  # >= 1 inside, <= -1 outside
    level = signed + offset
    if jitter_px > 0:
        level += jitter_px * smooth_field(crop.shape, rng, cell)
    out = np.zeros_like(mask)
    out[rows, cols] = level > 0
    return out


def cut_mask(
    mask: np.ndarray, rng: np.random.Generator, fraction: float, waviness: float = 0.08, theta: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Cuts the mask along a random wavy line into a part holding `fraction` of its pixels and the rest.

    The line has a uniformly random direction (so either side can be the kept part) and a sinusoidal
    wobble of amplitude up to `waviness` times the object's size, like the part boundaries SAM picks.
    `theta` (radians, the direction from the kept part to the rest) fixes the direction instead.
    """
    v, u = np.nonzero(mask)
    if v.size < 2:
        return mask.copy(), np.zeros_like(mask)
    x, y = u - u.mean(), v - v.mean()
    extent = math.sqrt(v.size)
    theta = rng.uniform(0.0, 2.0 * math.pi) if theta is None else float(theta)
    along = x * math.cos(theta) + y * math.sin(theta)
    across = -x * math.sin(theta) + y * math.cos(theta)
    amplitude = rng.uniform(0.0, waviness) * extent
    wavelength = rng.uniform(0.5, 1.5) * extent
    along = along + amplitude * np.sin(2.0 * math.pi * across / wavelength + rng.uniform(0.0, 2.0 * math.pi))
    threshold = np.quantile(along, fraction)
    keep = along <= threshold
    first, second = np.zeros_like(mask), np.zeros_like(mask)
    first[v[keep], u[keep]] = True
    second[v[~keep], u[~keep]] = True
    return first, second


def straight_cut_angle(rng: np.random.Generator, tilt_deg: float = 10.0) -> float:
    """Direction of a straight part cut: horizontal or vertical within a small tilt.

    Furniture parts meet along near axis-aligned lines in the image (a chair's seat and back, the two
    doors of a cabinet), so SAM's part masks end there rather than at a random angle.
    """
    return float(rng.integers(4)) * 0.5 * math.pi + math.radians(float(rng.normal(0.0, tilt_deg)))


def occlude_mask(mask: np.ndarray, rng: np.random.Generator, fraction: float) -> np.ndarray:
    """The mask less an occluder-shaped region (a rotated rectangle or ellipse), keeping `fraction` of it.

    The occluder is centred on a random pixel of the mask and grown, at a random aspect ratio, until it
    covers `1 - fraction` of the mask: the kept part can be a frame around a hole or pieces on either side,
    as when a chair stands in front of a table.
    """
    v, u = np.nonzero(mask)
    if v.size < 2:
        return mask.copy()
    centre = int(rng.integers(v.size))
    theta = rng.uniform(0.0, math.pi)
    aspect = rng.uniform(0.3, 1.0)
    dx, dy = u - u[centre], v - v[centre]
    along = dx * math.cos(theta) + dy * math.sin(theta)
    across = (-dx * math.sin(theta) + dy * math.cos(theta)) / aspect
    if rng.random() < 0.5:
        reach = np.maximum(np.abs(along), np.abs(across))  # rectangle
    else:
        reach = np.hypot(along, across)  # ellipse
    removed = reach < np.quantile(reach, 1.0 - fraction) if fraction < 1.0 else np.zeros(v.size, bool)
    out = mask.copy()
    out[v[removed], u[removed]] = False
    return out


def bleed_kernel(px: float, down: float = 2.0, up: float = 0.5) -> tuple[np.ndarray, tuple[int, int]]:
    """`cv2.dilate` kernel and anchor that spread a mask `px` sideways, `down * px` below, `up * px` above.

    The shape is two half ellipses: SAM masks of objects standing on the floor leak mostly onto the floor
    in front of and below them, less onto the wall above.
    """
    rx, rd, ru = max(px, 1.0), max(down * px, 1.0), max(up * px, 1.0)
    nx, nd, nu = int(math.ceil(rx)), int(math.ceil(rd)), int(math.ceil(ru))
    dy, dx = np.mgrid[-nd : nu + 1, -nx : nx + 1]  # offsets source - target: dy < 0 spreads downwards
    ry = np.where(dy < 0, rd, ru)
    kernel = ((dx / rx) ** 2 + (dy / ry) ** 2 <= 1.0).astype(np.uint8)
    return kernel, (nx, nd)


def bleed_mask(mask: np.ndarray, passive: np.ndarray, rng: np.random.Generator, px: float) -> np.ndarray:
    """The mask spread by ~N(px, px / 3) pixels (twice that downwards) onto `passive` pixels only.

    `passive` marks what lies behind objects (walls, floor, unannotated clutter, no ground truth): a box
    prompt's mask bleeds onto low-contrast background, not into the neighbouring objects SAM separates.
    """
    bbox = mask_bbox(mask)
    if bbox is None or px <= 0:
        return mask.copy()
    reach = max(float(rng.normal(px, px / 3.0)), 1.0)
    kernel, anchor = bleed_kernel(reach)
    rows, cols = _padded_crop(mask.shape, bbox, max(kernel.shape) + 1)
    grown = cv2.dilate(mask[rows, cols].astype(np.uint8), kernel, anchor=anchor).astype(bool)
    out = mask.copy()
    out[rows, cols] |= grown & passive[rows, cols]
    return out


def erode_mask(mask: np.ndarray, rng: np.random.Generator, px: float) -> np.ndarray:
    """The mask shrunk by ~N(px, px / 3) pixels (at least half a pixel): a SAM mask that stops short of
    the object's border, common on thin or low-contrast edges."""
    bbox = mask_bbox(mask)
    if bbox is None or px <= 0:
        return mask.copy()
    depth = max(float(rng.normal(px, px / 3.0)), 0.5)
    rows, cols = _padded_crop(mask.shape, bbox, 1)
    inside = cv2.distanceTransform(mask[rows, cols].astype(np.uint8), cv2.DIST_L2, 3)
    out = np.zeros_like(mask)
    out[rows, cols] = inside > depth
    return out


def random_blob(
    shape: tuple[int, int], center: tuple[int, int], rng: np.random.Generator, min_radius: float = 15.0, max_radius: float = 70.0
) -> np.ndarray:
    """An ellipse of random size and orientation centred at pixel `(u, v)`, clipped to the image."""
    a = rng.uniform(min_radius, max_radius)
    b = a * rng.uniform(0.4, 1.0)
    angle = rng.uniform(0.0, 180.0)
    canvas = np.zeros(shape, np.uint8)
    cv2.ellipse(canvas, (int(center[0]), int(center[1])), (int(round(a)), int(round(b))), angle, 0, 360, 1, -1)
    return canvas.astype(bool)


def random_rectangle(shape: tuple[int, int], center: tuple[int, int], size: tuple[float, float], angle_deg: float) -> np.ndarray:
    """`shape` bool mask of a `size = (length, thickness)` pixel rectangle centred at pixel `(u, v)`, its
    long side turned `angle_deg` from the image rows, clipped to the image."""
    corners = cv2.boxPoints(((float(center[0]), float(center[1])), (float(size[0]), float(size[1])), float(angle_deg)))
    canvas = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(canvas, np.round(corners).astype(np.int32), 1)
    return canvas.astype(bool)


def background_region(shape: tuple[int, int], center: tuple[int, int], rng: np.random.Generator, strip: bool) -> np.ndarray:
    """A region of the background a detector takes for furniture, centred at pixel `(u, v)`.

    A strip is thin and long, near horizontal (mostly: the top of a counter, a skirting board, the edge
    of a shelf along a wall) or vertical (a door frame); a patch is a large block of wall or floor, as a
    box prompt on a plain wall returns.
    """
    height, width = shape
    if strip:
        vertical = rng.random() < 0.2
        length = rng.uniform(0.3, 0.8) * (height if vertical else width)
        thickness = rng.uniform(0.03, 0.08) * height
        angle = (90.0 if vertical else 0.0) + rng.normal(0.0, 3.0)
        return random_rectangle(shape, center, (length, max(thickness, 2.0)), angle)
    size = (rng.uniform(0.2, 0.5) * width, rng.uniform(0.2, 0.5) * height)
    return random_rectangle(shape, center, size, rng.normal(0.0, 5.0))


def split_into_pieces(mask: np.ndarray, count: int, rng: np.random.Generator) -> list[np.ndarray]:
    """The mask cut into `count` pieces of about equal size: each pixel joins its nearest of `count` random
    seed pixels (a Voronoi partition of the mask), as SAM's automatic masks over-segment a textured surface.
    Empty pieces (seeds repeated) are left out."""
    v, u = np.nonzero(mask)
    if v.size == 0 or count < 1:
        return []
    seeds = rng.choice(v.size, size=min(count, v.size), replace=False)
    # (N, K) squared distances; K is small (tens) and N a region's pixels, so this stays cheap.
    d2 = (v[:, None] - v[seeds][None, :]).astype(np.float32) ** 2 + (u[:, None] - u[seeds][None, :]).astype(np.float32) ** 2
    nearest = d2.argmin(axis=1)
    pieces = []
    for k in range(seeds.size):
        keep = nearest == k
        if keep.any():
            piece = np.zeros_like(mask)
            piece[v[keep], u[keep]] = True
            pieces.append(piece)
    return pieces


#: The noise families, in report order.
FAMILIES = ("default", *FAMILY_PRESETS)


#: The parameters of each family at severity 1, on top of `default`: a clear, realistic dose of its failure mode.
FAMILY_DOSES: dict[str, dict[str, float]] = {
    "default": {},
    "label_model": {
        "likelihood_perturbation": 0.7,
        "extra_confusion_prob": 0.25,
        "consistent_mislabel_prob": 0.3,
        "label_persistence": 0.5,
    },
    "partial": {
        "partial_large_prob": 0.5,
        "partial_prob": 0.35,
        "split_prob": 0.15,
        "partial_straight_share": 0.4,
        "partial_occluder_share": 0.3,
    },
    "merged": {"merge_neighbor_prob": 0.3, "merge_prob": 0.2},
    "border": {
        "bleed_prob": 0.5,
        "bleed_px": 8.0,
        "erode_prob": 0.2,
        "erode_px": 3.0,
        "border_offset_px": 2.5,
        "border_jitter_px": 3.0,
    },
    "confusers": {"confuser_prob": 0.5, "blob_rate": 0.8, "small_object_miss_prob": 0.5, "score_miscalibration": 0.6},
    "persistent": {"persistent_phantoms": 4.0, "persistent_radius_m": 0.3, "persistent_detect_prob": 0.8},
    "background": {"background_rate": 1.0, "background_strip_share": 0.5},
    "texture": {"texture_prob": 0.25},
}


def fit_probabilities(params: dict[str, Any]) -> dict[str, Any]:
    """Probabilities clipped to [0, 1]; exclusive ones (`EXCLUSIVE_GROUPS`) scaled down to sum to 1 at most."""
    out = {k: min(max(v, 0.0), 1.0) if k in PROBABILITIES else v for k, v in params.items()}
    base = NoiseModel()
    for group in EXCLUSIVE_GROUPS:
        if not any(name in out for name in group):
            continue
        total = sum(out.get(name, getattr(base, name)) for name in group)
        if total > 1.0:
            for name in group:
                out[name] = out.get(name, getattr(base, name)) / total
    return out


def family_changes(family: str, severity: float) -> dict[str, Any]:
    """Noise parameters (on top of `default`) that make `family` the dominant failure mode.

    Each parameter goes linearly from its `default` value (severity 0) to its dose (severity 1) and on.
    """
    if family not in FAMILY_DOSES:
        raise UserError(f"unknown noise family {family!r}; choose one of {', '.join(FAMILIES)}")
    s, base = float(severity), NoiseModel()
    return fit_probabilities(
        {name: getattr(base, name) + s * (dose - getattr(base, name)) for name, dose in FAMILY_DOSES[family].items()}
    )


def family_noise(family: str, severity: float = 1.0, seed: int = 0, **changes: Any) -> NoiseModel:
    """The noise model of one family at `severity` (1 = the documented preset; 0 = `default`)."""
    if severity < 0:
        raise UserError(f"severity must be >= 0, got {severity}")
    params = family_changes(family, severity)
    params.update(changes)
    return NoiseModel.preset("default", seed=seed, **params)
