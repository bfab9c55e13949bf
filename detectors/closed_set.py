"""The closed-set front end: COCO detector -> vocabulary -> SAM box masks (+ classifier, + SAM point proposals).

A lighter alternative to RAM -> GroundingDINO -> SAM (`detectors.pipeline`) built from small public models
(the shared models folder: NanoDet or SSD, MobileSAM, EfficientNet-Lite3). Per frame:

1. the COCO detector finds boxes with class names (`coco_detector.CocoDetector`);
2. each name goes through the vocabulary table (`vocabulary`) to open-set labels L_o, score x weight;
   detections whose name maps to nothing (person, tv, book...) are dropped here, before SAM;
3. optionally (`classify_boxes`) the classifier names each kept box's crop; its mapped labels that *agree*
   with the detection's (name the same closed class in FM-Fusion's manual likelihood: folding chair ->
   chair, barber chair -> swivel chair, dining table -> kitchen table for a COCO table) join the
   detection's labels at `box_label_weight` x their score if that reaches `box_label_min_score` (never
   lowering a score). Disagreeing ones are ignored: on the ScanNet frames looked at they named the context
   (a desk beside the bed, the counter behind a stool), not the object;
4. SAM: the encoder once per frame (only when there is a box or proposals are on), the decoder per box;
5. optionally (`proposals`) class-agnostic SAM point proposals named by the classifier (`proposals`).

`FrameDetections`: detector detections first (by score), then proposals; `raw_tags` the model names seen
(the detector's classes above threshold, and the classifier names behind the labels kept); `tags` and
`prompt` the open-set labels produced, in L_o order (there is no prompt: the closed-set models take none).
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from detectors.classifier import ImageClassifier, box_crop
from detectors.coco_detector import CocoDetector
from detectors.image_ops import frame_image
from detectors.proposals import Proposal, ProposalConfig, label_proposals, propose_masks
from detectors.segmenter import ImageEmbedding, Segmenter
from detectors.vocabulary import Vocabulary, load_vocabulary
from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import LabelSets, load_label_sets, load_likelihood
from fmfusion_jax.types import FrameDetections, RGBDFrame

logger = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class ClosedSetConfig:
    """Options of the closed-set front end (the detector's thresholds live in its `CocoDetector`).

    Attributes:
      classify_boxes: name each detector box with the classifier and add agreeing labels (step 3).
      box_label_weight: factor on those labels' scores (0.5).
      box_label_min_score: such a label is added only when its score (weight x probability) reaches this.
      top_k: classifier names looked up per box.
      proposals: the proposal stage's settings, or None to skip it.
    """

    classify_boxes: bool = True
    box_label_weight: float = 0.5
    box_label_min_score: float = 0.05
    top_k: int = 5
    proposals: ProposalConfig | None = dataclasses.field(default_factory=ProposalConfig)

    def __post_init__(self) -> None:
        if not 0.0 < self.box_label_weight <= 1.0:
            raise UserError(f"classifier box_label_weight {self.box_label_weight} must lie in (0, 1]")
        if not 0.0 <= self.box_label_min_score <= 1.0:
            raise UserError(f"classifier box_label_min_score {self.box_label_min_score} must lie in [0, 1]")
        if self.top_k < 1:
            raise UserError(f"classifier top_k {self.top_k} must be >= 1")


def closed_classes(label_sets: LabelSets) -> dict[str, frozenset[str]]:
    """Open-set label -> the closed classes FM-Fusion's manual likelihood lists it under (0.9 entries)."""
    manual = load_likelihood("manual")
    return {
        label: frozenset(c for c, value in zip(label_sets.class_names, row) if value > 0.5)
        for label, row in zip(label_sets.open_labels, manual)
    }


class ClosedSetModels:
    """COCO detector + SAM (+ ImageNet classifier), loaded once; `detect` per frame (see the module docstring).

    Same surface as `FoundationModels`: `detect`, `reset`, `timings` (cumulative seconds per model:
    ``detector``, ``sam_encoder``, ``sam_decoder``, ``classifier``), `frames`, `providers`.

    Attributes:
      last_counts: the proposal stage's counts of the last frame (`proposals.propose_masks`), plus
        ``labelled``; empty when proposals are off.
    """

    def __init__(
        self,
        detector: CocoDetector,
        segmenter: Segmenter,
        classifier: ImageClassifier | None = None,
        vocabulary: Vocabulary | None = None,
        config: ClosedSetConfig | None = None,
        label_sets: LabelSets | None = None,
    ):
        self.detector, self.segmenter, self.classifier = detector, segmenter, classifier
        self.config = config or ClosedSetConfig()
        self.label_sets = label_sets or load_label_sets()
        self.vocabulary = vocabulary or load_vocabulary(open_labels=self.label_sets.open_labels)
        if classifier is None and (self.config.classify_boxes or self.config.proposals is not None):
            raise UserError("the closed-set front end needs a classifier for classify_boxes and for proposals")
        self.classes = closed_classes(self.label_sets)
        self.timings = {"detector": 0.0, "sam_encoder": 0.0, "sam_decoder": 0.0, "classifier": 0.0}
        self.frames = 0
        self.last_counts: dict[str, int] = {}

    @property
    def providers(self) -> list[str]:
        return self.detector.providers

    def reset(self) -> None:
        """Forgets the timings (the closed-set front end keeps no other state between frames)."""
        self.timings = dict.fromkeys(self.timings, 0.0)
        self.frames = 0

    def detect(self, frame: RGBDFrame | np.ndarray, frame_name: str | None = None) -> FrameDetections:
        """Detections of one frame (an `RGBDFrame`, or an `(H, W, 3)` uint8 RGB image with `frame_name`)."""
        image, name = frame_image(frame, frame_name)
        boxes, labels, raw_tags = self._detections(image)
        proposals: list[Proposal] = []
        masks = np.zeros((0, *image.shape[:2]), bool)
        if len(boxes) or self.config.proposals is not None:
            embedding = self._embed(image)
            masks = self._segment(embedding, boxes)
            if self.config.proposals is not None:
                proposals = self._propose(image, embedding, masks)
        for proposal in proposals:
            raw_tags += [n for n, _ in proposal.names if self._label_of(n) in proposal.labels]
        if proposals:
            masks = np.concatenate([masks, np.stack([p.candidate.mask for p in proposals])])
            boxes = np.concatenate([boxes, np.stack([p.candidate.box for p in proposals])])
            labels += [dict(p.labels) for p in proposals]
        self.frames += 1
        produced = {label for found in labels for label in found}
        tags = [label for label in self.label_sets.open_labels if label in produced]
        logger.debug("%s: %d detections, %d proposals, labels %s", name, len(labels) - len(proposals), len(proposals), tags)
        return FrameDetections(
            frame_name=name,
            masks=masks,
            labels=labels,
            boxes=np.asarray(boxes, np.float32).reshape(-1, 4),
            raw_tags=list(dict.fromkeys(raw_tags)),
            tags=tags,
            prompt=list(tags),
        )

    def _detections(self, image: np.ndarray) -> tuple[np.ndarray, list[dict[str, float]], list[str]]:
        """Steps 1-3: kept boxes `(N, 4)`, their label dicts, and the model names seen."""
        start = time.perf_counter()
        found = self.detector(image)
        self.timings["detector"] += time.perf_counter() - start
        raw_tags = list(dict.fromkeys(found.names))
        mapped = [self.vocabulary.map_scores({n: float(s)}, "coco") for n, s in zip(found.names, found.scores)]
        keep = [k for k, labels in enumerate(mapped) if labels]
        boxes, labels = found.boxes[keep].reshape(-1, 4), [mapped[k] for k in keep]
        if self.config.classify_boxes and self.classifier is not None and keep:
            start = time.perf_counter()
            for box, detection_labels in zip(boxes, labels):
                names = self.classifier(box_crop(image, box), self.config.top_k)
                raw_tags += self._add_agreeing(detection_labels, names)
            self.timings["classifier"] += time.perf_counter() - start
        return boxes, labels, raw_tags

    def _label_of(self, imagenet_name: str) -> str | None:
        entry = self.vocabulary.entry("imagenet", imagenet_name)
        return entry.label if entry else None

    def _add_agreeing(self, detection_labels: dict[str, float], names: list[tuple[str, float]]) -> list[str]:
        """Adds (in place) the classifier's labels that agree with the detection's; returns the names that did.

        A name whose label the detection has already with a higher score counts as agreeing too.
        """
        used = []
        classes = frozenset().union(*(self.classes[label] for label in detection_labels))
        for name, probability in names:
            entry = self.vocabulary.entry("imagenet", name)
            if entry is None or not self.classes[entry.label] & classes:
                continue
            score = self.config.box_label_weight * probability * entry.weight
            if score < self.config.box_label_min_score:
                continue
            detection_labels[entry.label] = max(score, detection_labels.get(entry.label, 0.0))
            used.append(name)
        return used

    def _embed(self, image: np.ndarray) -> ImageEmbedding:
        start = time.perf_counter()
        embedding = self.segmenter.embed(image)
        self.timings["sam_encoder"] += time.perf_counter() - start
        return embedding

    def _segment(self, embedding: ImageEmbedding, boxes: np.ndarray) -> np.ndarray:
        if len(boxes) == 0:
            return np.zeros((0, *embedding.image_shape), bool)
        start = time.perf_counter()
        masks, _ = self.segmenter.segment(embedding, boxes)
        self.timings["sam_decoder"] += time.perf_counter() - start
        return masks

    def _propose(self, image: np.ndarray, embedding: ImageEmbedding, masks: np.ndarray) -> list[Proposal]:
        config = self.config.proposals
        assert config is not None and self.classifier is not None
        start = time.perf_counter()
        taken = np.any(masks, axis=0) if len(masks) else None
        candidates, counts = propose_masks(self.segmenter, embedding, taken, config)
        middle = time.perf_counter()
        proposals = label_proposals(self.classifier, self.vocabulary, image, candidates, config)
        self.timings["sam_decoder"] += middle - start
        self.timings["classifier"] += time.perf_counter() - middle
        self.last_counts = {**counts, "labelled": len(proposals)}
        return proposals
