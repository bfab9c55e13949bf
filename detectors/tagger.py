"""RAM-style image tagger: an image -> the tags of its vocabulary whose probability passes a threshold.

Preprocessing (RAM's inference transform): RGB resized to 384x384 without keeping the aspect ratio, scaled
to 0..1 and normalized with the ImageNet mean/std, `(1, 3, 384, 384)` float32.

Scores: sigmoid of the `logits` output (or the `probs` output as it is, or the export's 0/1 `targets`).
A tag is on when its probability exceeds its threshold: RAM's per-class thresholds when
`ram_tag_list_threshold.txt` sits beside the model (one number per line, in vocabulary order), else one
threshold for every tag (RAM's default 0.68). The vocabulary is `ram_tag_list.txt` beside the model.

FM-Fusion keeps only the tags that are open-set labels of interest (`filter_tags`); every tag is kept as
`raw_tags` for the record.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from detectors.contracts import RAM_DEFAULT_THRESHOLD, RAM_IMAGE_SIZE, RAM_THRESHOLD_FILE, TAGGER
from detectors.image_ops import check_rgb_image, normalize_chw, resize
from detectors.onnx_runtime import ContractError, OnnxModel, require_file
from fmfusion_jax.errors import DataError

logger = logging.getLogger(__name__)

VOCABULARY_FILE = TAGGER.sidecars[0][0]


@dataclasses.dataclass(frozen=True)
class TagResult:
    """The tagger's output for one image.

    Attributes:
      raw_tags: every tag over its threshold, in vocabulary order.
      raw_scores: their probabilities.
      tags: `raw_tags` that are open-set labels of interest, in the same order.
    """

    raw_tags: list[str]
    raw_scores: list[float]
    tags: list[str]


def preprocess_tagger(image: np.ndarray, size: int = RAM_IMAGE_SIZE) -> np.ndarray:
    """`(H, W, 3)` uint8 RGB -> `(1, 3, size, size)` float32 (resized, /255, ImageNet-normalized)."""
    return normalize_chw(resize(check_rgb_image(image), size, size))


def read_vocabulary(path: Path) -> list[str]:
    """One tag per line (blank lines kept as empty tags so line numbers stay logit indices)."""
    lines = path.read_text(encoding="utf-8").splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    if not any(line.strip() for line in lines):
        raise DataError(f"{path}: empty tag vocabulary")
    return [sanitize_tag(line) for line in lines]


def sanitize_tag(tag: str) -> str:
    """A tag as the detection files can hold it: lower case, no '.', single spaces."""
    return " ".join(tag.replace(".", " ").lower().split())


def filter_tags(tags: Iterable[str], open_labels: Sequence[str]) -> list[str]:
    """The tags that are open-set labels of interest, in their order, without repeats."""
    wanted = set(open_labels)
    kept: list[str] = []
    for tag in tags:
        if tag in wanted and tag not in kept:
            kept.append(tag)
    return kept


class ImageTagger:
    """RAM through onnxruntime (see the module docstring).

    Args:
      model: an `OnnxModel` under the `TAGGER` contract.
      vocabulary: one tag per logit.
      thresholds: `(num_tags,)` per-tag thresholds, or one float for all.
    """

    def __init__(self, model: OnnxModel, vocabulary: Sequence[str], thresholds: np.ndarray | float = RAM_DEFAULT_THRESHOLD):
        self.model = model
        self.vocabulary = list(vocabulary)
        count = len(self.vocabulary)
        thresholds = np.asarray(thresholds, np.float32)
        self.thresholds = np.full(count, thresholds, np.float32) if thresholds.ndim == 0 else thresholds
        if self.thresholds.shape != (count,):
            raise DataError(f"{model.path}: thresholds of shape {self.thresholds.shape} for {count} tags")
        self.output = next(name for name in ("logits", "probs", "targets") if model.has_output(name))
        declared = model.dims.get("num_tags")
        if declared is not None and declared != count:
            raise ContractError(
                f"{model.path}: the model scores {declared} tags but its vocabulary {VOCABULARY_FILE} has {count} lines"
            )

    @classmethod
    def from_folder(cls, folder: str | Path, providers="cpu", threshold: float = RAM_DEFAULT_THRESHOLD) -> "ImageTagger":
        """Loads `ram.onnx`, `ram_tag_list.txt` and, when present, `ram_tag_list_threshold.txt` from `folder`."""
        folder = Path(folder)
        model = OnnxModel(folder / TAGGER.filename, TAGGER, providers)
        vocabulary_path = require_file(
            folder / VOCABULARY_FILE, "RAM tag vocabulary", "Copy ram/data/ram_tag_list.txt of recognize-anything beside ram.onnx"
        )
        vocabulary = read_vocabulary(vocabulary_path)
        declared = model.dims.get("num_tags")
        if declared is not None and declared != len(vocabulary):
            raise ContractError(
                f"{model.path}: the model scores {declared} tags but its vocabulary {vocabulary_path} has {len(vocabulary)} lines"
            )
        thresholds: np.ndarray | float = threshold
        threshold_path = folder / RAM_THRESHOLD_FILE
        if threshold_path.is_file():
            try:
                values = [float(line) for line in threshold_path.read_text().split()]
            except ValueError as error:
                raise DataError(f"{threshold_path}: not one number per line ({error})") from None
            if len(values) != len(vocabulary):
                raise DataError(
                    f"{threshold_path}: {len(values)} thresholds for the {len(vocabulary)} tags of {vocabulary_path.name}"
                )
            thresholds = np.asarray(values, np.float32)
        return cls(model, vocabulary, thresholds)

    def scores(self, image: np.ndarray) -> np.ndarray:
        """`(num_tags,)` float32 probabilities (0/1 for an export that thresholds inside)."""
        batch = preprocess_tagger(image)
        values = self.model.run({"image": batch}, [self.output])[self.output]
        values = np.asarray(values, np.float32).reshape(-1)
        if values.shape[0] != len(self.vocabulary):
            raise ContractError(
                f"{self.model.path}: the model scored {values.shape[0]} tags but its vocabulary has {len(self.vocabulary)}"
            )
        if self.output == "logits":
            values = 1.0 / (1.0 + np.exp(-values.astype(np.float64)))
        return values.astype(np.float32)

    def __call__(self, image: np.ndarray, open_labels: Sequence[str]) -> TagResult:
        scores = self.scores(image)
        # An export that thresholds inside gives 0/1: its own thresholds decide, ours must not.
        on = scores > 0.5 if self.output == "targets" else scores > self.thresholds
        raw_tags, raw_scores = [], []
        for index in np.flatnonzero(on):
            tag = self.vocabulary[index]
            if tag and tag not in raw_tags:
                raw_tags.append(tag)
                raw_scores.append(float(scores[index]))
        return TagResult(raw_tags, raw_scores, filter_tags(raw_tags, open_labels))
