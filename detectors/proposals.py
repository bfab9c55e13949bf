"""Class-agnostic object proposals for what a COCO detector cannot name (shelves, cabinets, doors, curtains...).

SAM is prompted with a grid of points (one positive click each, plus SAM's padding point (0, 0) of label -1),
the masks are filtered, and the classifier names what is left:

1. points: the centres of a `grid` = (columns, rows) of equal cells over the image; points inside a
   detector's mask are not prompted (that object is segmented already);
2. quality: SAM's predicted IoU >= `min_predicted_iou` (0.8) and stability >= `min_stability` (0.85), the
   stability being the mask's area at logit threshold +1 over its area at -1 (segment-anything's automatic
   mask generator uses the same score);
3. size: masks under `min_area` (1 %) or over `max_area` (60 %) of the image are dropped (specks; the floor or
   a wall with everything in front of it);
4. masks lying more than `max_detection_overlap` (half) inside the detectors' masks are dropped;
5. duplicates: of masks overlapping with IoU > `duplicate_iou` (0.7) the one of higher predicted IoU is kept
   (neighbouring points often land on the same object);
6. labels: the classifier's top-k (5) names, mapped to open-set labels by the vocabulary table (score =
   probability x weight), on two crops of the mask's box (10 % margin): the crop as it is, and the crop
   with the pixels outside the mask greyed out. A label counts when both crops give it, with the lower of
   the two scores, and when that is >= `min_score` (0.1); a proposal left without a label is dropped.

Why both crops (`crop="both"`, measured on ScanNet scene0000_00 frames 20, 100, 200, 280): the box crop
alone names the context, not the segment (a wall beside a toilet became "toilet seat" 0.73, a kitchen counter
"bathtub" / "washbasin" 0.21); the masked crop alone often names the grey cut-out ("panpipe", "envelope")
but rarely an object that is not there. Requiring both kept the bookcase (0.49), the couch and the toilet and
dropped those context labels. `crop="box"` or `"masked"` use one crop (one classifier run instead of two).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from detectors.classifier import ImageClassifier, crop_bounds
from detectors.segmenter import ImageEmbedding, Segmenter, point_prompts
from detectors.vocabulary import Vocabulary
from fmfusion_jax.errors import UserError

#: Grey put outside the mask of a masked crop (ImageNet's mean colour).
CROP_FILL = np.array([124, 116, 104], np.uint8)
CROPS = ("both", "box", "masked")


@dataclasses.dataclass(frozen=True)
class ProposalConfig:
    """Settings of the proposal stage (see the module docstring for what each does).

    Attributes:
      grid: (columns, rows) of point prompts; the decoder runs once per point (about 26 ms each on 2 cores).
      min_predicted_iou, min_stability: SAM quality filters.
      stability_offset: the logit offset of the stability score (1.0).
      min_area, max_area: mask area bounds, fractions of the image.
      max_detection_overlap: drop a proposal with more than this fraction of its pixels in detector masks.
      duplicate_iou: two proposals with a mask IoU above this are one object.
      top_k: classifier names looked up in the vocabulary.
      min_score: drop labels scoring below this (probability x weight).
      crop: ``"both"`` (a label must come from both crops), ``"box"`` (the box crop as it is) or ``"masked"``
        (pixels outside the mask greyed out).
      crop_margin: margin around the box, a fraction of its size.
    """

    grid: tuple[int, int] = (6, 4)
    min_predicted_iou: float = 0.8
    min_stability: float = 0.85
    stability_offset: float = 1.0
    min_area: float = 0.01
    max_area: float = 0.6
    max_detection_overlap: float = 0.5
    duplicate_iou: float = 0.7
    top_k: int = 5
    min_score: float = 0.1
    crop: str = "both"
    crop_margin: float = 0.1

    def __post_init__(self) -> None:
        grid = tuple(self.grid)
        if len(grid) != 2 or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 1 for n in grid):
            raise UserError(f"proposals grid {list(self.grid)}: expected [columns, rows], two integers >= 1")
        object.__setattr__(self, "grid", grid)
        for name in ("min_predicted_iou", "min_stability", "min_area", "max_area", "max_detection_overlap", "duplicate_iou"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value <= 1.0:
                raise UserError(f"proposals {name} {value!r} must be a number in [0, 1]")
        if self.min_area >= self.max_area:
            raise UserError(f"proposals min_area {self.min_area} must be below max_area {self.max_area}")
        if not 0.0 <= self.min_score <= 1.0 or self.top_k < 1 or self.stability_offset <= 0 or self.crop_margin < 0:
            raise UserError("proposals: min_score must lie in [0, 1], top_k >= 1, stability_offset > 0, crop_margin >= 0")
        if self.crop not in CROPS:
            raise UserError(f"proposals crop {self.crop!r}: expected one of {', '.join(CROPS)}")


@dataclasses.dataclass(frozen=True)
class Candidate:
    """A SAM mask that passed the quality, size and overlap filters.

    Attributes:
      mask: `(H, W)` bool.
      box: `(4,)` float32 ``[u0, v0, u1, v1]`` bounding the mask.
      point: `(2,)` float32 the pixel prompt (u, v).
      predicted_iou, stability: SAM's quality estimates.
    """

    mask: np.ndarray
    box: np.ndarray
    point: np.ndarray
    predicted_iou: float
    stability: float


@dataclasses.dataclass(frozen=True)
class Proposal:
    """A labelled proposal: a `Candidate` with the classifier's names and the open-set labels they map to.

    Attributes:
      candidate: the mask and its quality.
      names: the classifier's top-k `(name, probability)` (of the box crop, then of the masked crop with "both").
      labels: open-set label -> score (probability x weight), at least one.
    """

    candidate: Candidate
    names: list[tuple[str, float]]
    labels: dict[str, float]


def grid_points(height: int, width: int, grid: tuple[int, int]) -> np.ndarray:
    """`(columns * rows, 2)` float32 pixel points (u, v): the centres of a `grid` of equal cells, row by row."""
    columns, rows = grid
    u = (np.arange(columns) + 0.5) * width / columns
    v = (np.arange(rows) + 0.5) * height / rows
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu.ravel(), vv.ravel()], 1).astype(np.float32)


def stability_score(logits: np.ndarray, offset: float = 1.0) -> float:
    """Area of ``logits > offset`` over the area of ``logits > -offset`` (1 when both are empty)."""
    loose = int(np.count_nonzero(logits > -offset))
    return int(np.count_nonzero(logits > offset)) / loose if loose else 1.0


def mask_box(mask: np.ndarray) -> np.ndarray:
    """`(4,)` float32 ``[u0, v0, u1, v1]`` of the pixels of a non-empty `(H, W)` bool mask (u1, v1 exclusive)."""
    rows, columns = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    return np.array([columns[0], rows[0], columns[-1] + 1, rows[-1] + 1], np.float32)


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    union = int(np.count_nonzero(a | b))
    return int(np.count_nonzero(a & b)) / union if union else 0.0


def propose_masks(
    segmenter: Segmenter, embedding: ImageEmbedding, taken: np.ndarray | None, config: ProposalConfig
) -> tuple[list[Candidate], dict[str, int]]:
    """Steps 1-5 of the module docstring: candidates by decreasing predicted IoU, and counts per step.

    `taken`: `(H, W)` bool union of the detectors' masks, or None. Counts: ``points``, ``prompted``,
    ``quality`` (passed step 2), ``size``, ``overlap``, ``unique``.
    """
    height, width = embedding.image_shape
    points = grid_points(height, width, config.grid)
    counts = {"points": len(points)}
    if taken is not None:
        inside = taken[points[:, 1].astype(int).clip(0, height - 1), points[:, 0].astype(int).clip(0, width - 1)]
        points = points[~inside]
    counts["prompted"] = len(points)
    counts.update(quality=0, size=0, overlap=0)
    found: list[Candidate] = []
    if len(points):
        coords, labels = point_prompts(points, embedding.image_shape, embedding.resized_shape)
        for rows, logits, iou in segmenter.decode(embedding, coords, labels):
            for point, mask_logits, quality in zip(points[rows], logits, iou):
                candidate = _filter(mask_logits, float(quality), point, taken, config, counts, height * width)
                if candidate is not None:
                    found.append(candidate)
    kept = _deduplicate(found, config.duplicate_iou)
    counts["unique"] = len(kept)
    return kept, counts


def _filter(
    logits: np.ndarray,
    quality: float,
    point: np.ndarray,
    taken: np.ndarray | None,
    config: ProposalConfig,
    counts: dict[str, int],
    image_area: int,
) -> Candidate | None:
    """Steps 2-4 on one prompt's `(H, W)` logits; `counts` gets the steps passed."""
    if quality < config.min_predicted_iou:
        return None
    stability = stability_score(logits, config.stability_offset)
    if stability < config.min_stability:
        return None
    counts["quality"] += 1
    mask = logits > 0
    area = int(np.count_nonzero(mask))
    if not config.min_area * image_area <= area <= config.max_area * image_area:
        return None
    counts["size"] += 1
    if taken is not None and np.count_nonzero(mask & taken) > config.max_detection_overlap * area:
        return None
    counts["overlap"] += 1
    return Candidate(mask, mask_box(mask), np.asarray(point, np.float32), quality, stability)


def _deduplicate(candidates: Sequence[Candidate], max_iou: float) -> list[Candidate]:
    """Greedy by decreasing predicted IoU: a candidate overlapping a kept one with IoU > `max_iou` goes."""
    kept: list[Candidate] = []
    for candidate in sorted(candidates, key=lambda c: -c.predicted_iou):
        if all(mask_iou(candidate.mask, other.mask) <= max_iou for other in kept):
            kept.append(candidate)
    return kept


def proposal_crop(image: np.ndarray, candidate: Candidate, masked: bool, margin: float = 0.1) -> np.ndarray:
    """The crop of the candidate's box with a `margin`, greyed outside its mask when `masked`."""
    rows, columns = crop_bounds(image.shape, candidate.box, margin)
    if not masked:
        return image[rows, columns]
    return np.where(candidate.mask[rows, columns, None], image[rows, columns], CROP_FILL)


def label_proposals(
    classifier: ImageClassifier,
    vocabulary: Vocabulary,
    image: np.ndarray,
    candidates: Sequence[Candidate],
    config: ProposalConfig,
) -> list[Proposal]:
    """Step 6: each candidate named by the classifier; those without an open-set label are dropped."""
    proposals = []
    for candidate in candidates:
        names: list[tuple[str, float]] = []
        labels: dict[str, float] | None = None
        for masked in {"box": (False,), "masked": (True,), "both": (False, True)}[config.crop]:
            top = classifier(proposal_crop(image, candidate, masked, config.crop_margin), config.top_k)
            found = vocabulary.map_scores(top, "imagenet")
            labels = found if labels is None else {k: min(v, found[k]) for k, v in labels.items() if k in found}
            names += top
        kept = {label: score for label, score in (labels or {}).items() if score >= config.min_score}
        if kept:
            proposals.append(Proposal(candidate, names, kept))
    return proposals
