"""The foundation-model front end of FM-Fusion: RAM -> prompt augmentation -> GroundingDINO -> SAM.

``models = FoundationModels.from_folder("models/")`` loads the four ONNX files once;
``models.detect(frame)`` turns one RGB(-D) frame into the `FrameDetections` the fusion consumes (the
structure the detection-file reader gives back):

1. RAM tags the image; tags that are open-set labels of interest (L_o) are kept;
2. the prompt is those tags plus the labels detected in the previous detection frames (`PromptAugmenter`);
3. GroundingDINO detects boxes with per-label scores for the prompt;
4. SAM segments each box.

Call `detect` on the detection frames of one sequence in order (the prompt augmentation is stateful),
and `reset()` before another sequence.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from detectors.contracts import RAM_DEFAULT_THRESHOLD
from detectors.grounding import GroundingDetector, GroundingResult
from detectors.image_ops import frame_image
from detectors.prompt import PromptAugmenter
from detectors.segmenter import Segmenter
from detectors.tagger import ImageTagger, TagResult
from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import LabelSets, load_label_sets
from fmfusion_jax.types import FrameDetections, RGBDFrame

logger = logging.getLogger(__name__)


@dataclasses.dataclass
class DetectorConfig:
    """Thresholds and options of the front end; defaults are FM-Fusion's.

    Attributes:
      box_threshold: a query is a detection when its best token score exceeds this (0.35).
      text_threshold: a label counts when all its tokens score above this (0.25).
      nms_iou: class-agnostic NMS IoU threshold (0.5).
      max_box_fraction: boxes wider and taller than this fraction of the image are dropped (0.95).
      tag_threshold: RAM's threshold for tags without a per-class one (ram_tag_list_threshold.txt) (0.68).
      prompt_window: detection frames whose labels augment the prompt (5; 0 turns augmentation off).
      prompt_excluded: labels never added by augmentation; None: the label sets' list.
      grounding_shorter, grounding_longest: GroundingDINO's input size (shorter side, cap on the longer).
      max_text_len: GroundingDINO's token limit (256).
      sam_mask_choice: ``"first"`` or ``"best"`` mask of a multi-mask SAM decoder.
      sam_batch: boxes per SAM decoder call (when the export takes batches).
      max_detections: keep at most this many detections (highest scores), or all.
    """

    box_threshold: float = 0.35
    text_threshold: float = 0.25
    nms_iou: float = 0.5
    max_box_fraction: float = 0.95
    tag_threshold: float = RAM_DEFAULT_THRESHOLD
    prompt_window: int = 5
    prompt_excluded: tuple[str, ...] | None = None
    grounding_shorter: int = 800
    grounding_longest: int = 1333
    max_text_len: int = 256
    sam_mask_choice: str = "first"
    sam_batch: int = 16
    max_detections: int | None = None

    def __post_init__(self) -> None:
        for name in ("box_threshold", "text_threshold", "nms_iou", "max_box_fraction"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise UserError(f"detector {name} {value} must lie in [0, 1]")
        if self.prompt_window < 0:
            raise UserError(f"prompt_window {self.prompt_window} must be >= 0")
        if self.sam_mask_choice not in ("first", "best"):
            raise UserError(f"sam_mask_choice {self.sam_mask_choice!r}: expected 'first' or 'best'")
        if self.max_detections is not None and self.max_detections < 0:
            raise UserError(f"max_detections {self.max_detections} must be >= 0")


class FoundationModels:
    """RAM + GroundingDINO + SAM, loaded once; `detect` per frame (see the module docstring).

    Attributes:
      tagger, detector, segmenter: the three stages.
      config: `DetectorConfig`.
      label_sets: the open-set labels of interest and the augmentation exclusions.
      prompts: the `PromptAugmenter` (its `history` holds every frame's prompt).
      timings: cumulative seconds per stage (``tagger``, ``detector``, ``sam_encoder``, ``sam_decoder``).
      frames: frames detected since the last `reset`.
    """

    def __init__(
        self,
        tagger: ImageTagger,
        detector: GroundingDetector,
        segmenter: Segmenter,
        config: DetectorConfig | None = None,
        label_sets: LabelSets | None = None,
    ):
        self.tagger, self.detector, self.segmenter = tagger, detector, segmenter
        self.config = config or DetectorConfig()
        self.label_sets = label_sets or load_label_sets()
        excluded = self.config.prompt_excluded
        if excluded is None:
            excluded = self.label_sets.prompt_augmentation_excluded
        self.prompts = PromptAugmenter(self.config.prompt_window, excluded, self.label_sets.open_labels)
        self.timings = {"tagger": 0.0, "detector": 0.0, "sam_encoder": 0.0, "sam_decoder": 0.0}
        self.frames = 0

    @classmethod
    def from_folder(
        cls,
        models_dir: str | Path,
        providers: str | Sequence[str] = "cpu",
        config: DetectorConfig | None = None,
        label_sets: LabelSets | None = None,
    ) -> "FoundationModels":
        """Loads every model of `models_dir` (layout in docs/detectors.md) on `providers` (cpu | cuda | auto)."""
        models_dir = Path(models_dir)
        if not models_dir.is_dir():
            raise UserError(
                f"{models_dir}: models folder not found (expected ram.onnx, ram_tag_list.txt, "
                "groundingdino.onnx, vocab.txt, sam_encoder.onnx, sam_decoder.onnx; see docs/detectors.md)"
            )
        config = config or DetectorConfig()
        tagger = ImageTagger.from_folder(models_dir, providers, threshold=config.tag_threshold)
        detector = GroundingDetector.from_folder(
            models_dir,
            providers,
            shorter=config.grounding_shorter,
            longest=config.grounding_longest,
            max_text_len=config.max_text_len,
        )
        segmenter = Segmenter.from_folder(models_dir, providers, mask_choice=config.sam_mask_choice, batch_size=config.sam_batch)
        return cls(tagger, detector, segmenter, config, label_sets)

    @property
    def providers(self) -> list[str]:
        return self.detector.model.providers

    def reset(self) -> None:
        """Starts a new sequence: forgets the prompt augmentation history and the timings."""
        self.prompts.reset()
        self.timings = dict.fromkeys(self.timings, 0.0)
        self.frames = 0

    def tag(self, image: np.ndarray) -> TagResult:
        start = time.perf_counter()
        result = self.tagger(image, self.label_sets.open_labels)
        self.timings["tagger"] += time.perf_counter() - start
        return result

    def ground(self, image: np.ndarray, prompt: Sequence[str]) -> GroundingResult:
        config = self.config
        start = time.perf_counter()
        result = self.detector(
            image, prompt, config.box_threshold, config.text_threshold, config.nms_iou, config.max_box_fraction
        )
        self.timings["detector"] += time.perf_counter() - start
        if config.max_detections is not None and len(result.labels) > config.max_detections:
            keep = config.max_detections
            result = GroundingResult(result.boxes[:keep], result.scores[:keep], result.labels[:keep], result.caption)
        return result

    def segment(self, image: np.ndarray, boxes: np.ndarray) -> np.ndarray:
        """`(N, H, W)` bool masks of `boxes` (the encoder runs only when there is a box)."""
        if len(boxes) == 0:
            return np.zeros((0, *image.shape[:2]), bool)
        start = time.perf_counter()
        embedding = self.segmenter.embed(image)
        middle = time.perf_counter()
        masks, _ = self.segmenter.segment(embedding, boxes)
        self.timings["sam_encoder"] += middle - start
        self.timings["sam_decoder"] += time.perf_counter() - middle
        return masks

    def detect(self, frame: RGBDFrame | np.ndarray, frame_name: str | None = None) -> FrameDetections:
        """Detections of one frame (an `RGBDFrame`, or an `(H, W, 3)` uint8 RGB image with `frame_name`)."""
        image, name = frame_image(frame, frame_name)
        tags = self.tag(image)
        prompt = self.prompts.prompt(name, tags.tags)
        result = self.ground(image, prompt)
        masks = self.segment(image, result.boxes)
        self.prompts.observe(label for labels in result.labels for label in labels)
        self.frames += 1
        logger.debug("%s: tags %s, prompt %s, %d detections", name, tags.tags, prompt, len(result.labels))
        return FrameDetections(
            frame_name=name,
            masks=masks,
            labels=[dict(d) for d in result.labels],
            boxes=result.boxes.astype(np.float32).reshape(-1, 4),
            raw_tags=list(tags.raw_tags),
            tags=list(tags.tags),
            prompt=list(prompt),
        )
