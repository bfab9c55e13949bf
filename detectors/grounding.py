"""GroundingDINO-style open-set detection: an image and a list of labels -> boxes with per-label scores.

Steps (FM-Fusion's detector settings; see the contract in `contracts.GROUNDING`):

1. image: RGB resized so that its shorter side is 800 and its longer side at most 1333 (aspect kept; an
   export with a fixed input size gets exactly that size), /255, ImageNet mean/std, `(1, 3, h, w)`;
2. text: ``"a . b . c ."`` in BERT WordPiece ids with GroundingDINO's phrase-wise self-attention mask
   (`tokenizer.build_caption`, `tokenizer.text_self_attention`), padded when the export fixes the length;
3. run; sigmoid of the logits; a query's box score is its highest token score; queries with a box score
   above the box threshold (0.35) are kept;
4. labels: a label scores the max over its tokens, counted only if all its tokens pass the text threshold
   (0.25); a query left without a label is dropped;
5. boxes: normalized cx, cy, w, h -> pixel [u0, v0, u1, v1] of the input image (clipped to it); boxes
   covering more than 95 % of the image in both width and height are dropped (they are the room, not an
   object); then class-agnostic NMS at IoU 0.5 by box score.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import cast

import numpy as np

from detectors.contracts import GROUNDING, GROUNDING_MAX_TEXT_LEN
from detectors.image_ops import check_rgb_image, normalize_chw, resize
from detectors.onnx_runtime import ContractError, OnnxModel, require_file
from detectors.tokenizer import (
    PHRASE_BREAKS,
    Caption,
    WordPieceTokenizer,
    build_caption,
    label_scores,
    text_self_attention,
)

VOCABULARY_FILE = GROUNDING.sidecars[0][0]


@dataclasses.dataclass(frozen=True)
class GroundingResult:
    """Detections of one image, sorted by decreasing score.

    Attributes:
      boxes: `(N, 4)` float32 pixel boxes ``[u0, v0, u1, v1]`` in the input image.
      scores: `(N,)` float32 box scores (highest token score).
      labels: `N` dicts label -> score.
      caption: the caption sent.
    """

    boxes: np.ndarray
    scores: np.ndarray
    labels: list[dict[str, float]]
    caption: Caption | None

    @staticmethod
    def empty(caption: Caption | None = None) -> "GroundingResult":
        return GroundingResult(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), [], caption)


def grounding_input_size(height: int, width: int, shorter: int = 800, longest: int = 1333) -> tuple[int, int]:
    """`(h, w)` with the shorter side `shorter`, reduced so the longer side stays within `longest`."""
    small, large = min(height, width), max(height, width)
    size = shorter
    if longest and large / small * size > longest:
        size = int(round(longest * small / large))
    if width < height:
        return int(size * height / width), size
    if height < width:
        return size, int(size * width / height)
    return size, size


def preprocess_grounding(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """`(H, W, 3)` uint8 RGB -> `(1, 3, height, width)` float32, resized and ImageNet-normalized."""
    return normalize_chw(resize(check_rgb_image(image), height, width))


def cxcywh_to_xyxy(boxes: np.ndarray, width: int, height: int) -> np.ndarray:
    """`(N, 4)` normalized cx, cy, w, h -> `(N, 4)` float32 pixel ``[u0, v0, u1, v1]`` clipped to the image."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    cx, cy, w, h = boxes.T
    xyxy = np.stack([(cx - w / 2) * width, (cy - h / 2) * height, (cx + w / 2) * width, (cy + h / 2) * height], 1)
    xyxy[:, [0, 2]] = xyxy[:, [0, 2]].clip(0, width)
    xyxy[:, [1, 3]] = xyxy[:, [1, 3]].clip(0, height)
    return xyxy.astype(np.float32)


def box_iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """IoU of one ``[u0, v0, u1, v1]`` box with each of `(N, 4)` boxes (areas without the +1 pixel)."""
    u0 = np.maximum(box[0], boxes[:, 0])
    v0 = np.maximum(box[1], boxes[:, 1])
    u1 = np.minimum(box[2], boxes[:, 2])
    v1 = np.minimum(box[3], boxes[:, 3])
    inter = np.clip(u1 - u0, 0, None) * np.clip(v1 - v0, 0, None)
    area = (box[2] - box[0]) * (box[3] - box[1])
    areas = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    union = area + areas - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1), 0.0)


def nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float = 0.5) -> np.ndarray:
    """Greedy non-maximum suppression: indices kept, by decreasing score (ties: lower index first).

    A box is suppressed when its IoU with a kept, higher-scoring box exceeds `iou_threshold`.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")
    keep = []
    while order.size:
        best, order = order[0], order[1:]
        keep.append(best)
        if order.size:
            order = order[box_iou(boxes[best], boxes[order]) <= iou_threshold]
    return np.asarray(keep, np.int64)


def large_boxes(boxes: np.ndarray, width: int, height: int, max_fraction: float = 0.95) -> np.ndarray:
    """`(N,)` bool: boxes wider than `max_fraction` of the image AND taller than `max_fraction` of it."""
    boxes = np.asarray(boxes).reshape(-1, 4)
    return ((boxes[:, 2] - boxes[:, 0]) > max_fraction * width) & ((boxes[:, 3] - boxes[:, 1]) > max_fraction * height)


def sigmoid(x: np.ndarray) -> np.ndarray:
    return (1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))).astype(np.float32)


class GroundingDetector:
    """GroundingDINO through onnxruntime (see the module docstring)."""

    def __init__(
        self,
        model: OnnxModel,
        tokenizer: WordPieceTokenizer,
        shorter: int = 800,
        longest: int = 1333,
        max_text_len: int = GROUNDING_MAX_TEXT_LEN,
    ):
        self.model = model
        self.tokenizer = tokenizer
        self.shorter, self.longest = shorter, longest
        fixed_tokens = model.dims.get("num_tokens")
        logits_len = model.dims.get("max_text_len")
        limits = [n for n in (max_text_len, fixed_tokens, logits_len) if n]
        self.max_tokens = min(limits)
        self.fixed_tokens = fixed_tokens
        image = model.inputs["img"]
        # (h, w) of the image input when the file fixes both (no None among them), else None
        self.fixed_size = cast(
            "tuple[int, int] | None", (image.shape[2], image.shape[3]) if None not in image.shape[2:] else None
        )
        self.break_ids = [tokenizer.ids[t] for t in PHRASE_BREAKS if t in tokenizer.ids]

    @classmethod
    def from_folder(cls, folder: str | Path, providers="cpu", **options) -> "GroundingDetector":
        """Loads `groundingdino.onnx` and the BERT `vocab.txt` beside it."""
        folder = Path(folder)
        model = OnnxModel(folder / GROUNDING.filename, GROUNDING, providers)
        vocabulary = require_file(
            folder / VOCABULARY_FILE,
            "BERT vocabulary of GroundingDINO",
            "Copy vocab.txt of bert-base-uncased (Hugging Face) beside groundingdino.onnx",
        )
        return cls(model, WordPieceTokenizer.from_file(vocabulary), **options)

    def input_size(self, height: int, width: int) -> tuple[int, int]:
        """The `(h, w)` the image is resized to."""
        return self.fixed_size or grounding_input_size(height, width, self.shorter, self.longest)

    def prepare(self, image: np.ndarray, labels: Sequence[str]) -> tuple[dict[str, np.ndarray], Caption]:
        """The feeds (contract names) for `image` and `labels`, and the caption they encode."""
        image = check_rgb_image(image)
        caption = build_caption(labels, self.tokenizer, self.max_tokens)
        ids = caption.input_ids
        length = self.fixed_tokens or ids.shape[0]
        if ids.shape[0] > length:
            raise ContractError(f"{self.model.path}: caption of {ids.shape[0]} tokens, the model takes {length}")
        padded = np.full(length, self.tokenizer.ids.get("[PAD]", 0), np.int64)
        padded[: ids.shape[0]] = ids
        attention = np.zeros(length, bool)
        attention[: ids.shape[0]] = True
        mask, positions = text_self_attention(padded, self.break_ids)
        height, width = self.input_size(*image.shape[:2])
        feeds = {
            "img": preprocess_grounding(image, height, width),
            "input_ids": padded[None],
            "attention_mask": attention[None],
            "position_ids": positions[None],
            "token_type_ids": np.zeros((1, length), np.int64),
            "text_token_mask": mask[None],
        }
        return feeds, caption

    def __call__(
        self,
        image: np.ndarray,
        labels: Sequence[str],
        box_threshold: float = 0.35,
        text_threshold: float = 0.25,
        nms_iou: float = 0.5,
        max_box_fraction: float = 0.95,
    ) -> GroundingResult:
        if not labels:
            return GroundingResult.empty()
        feeds, caption = self.prepare(image, labels)
        if not caption.labels:
            return GroundingResult.empty(caption)
        out = self.model.run(feeds, ["logits", "boxes"])
        return postprocess_grounding(
            out["logits"][0],
            out["boxes"][0],
            caption,
            image.shape[0],
            image.shape[1],
            box_threshold,
            text_threshold,
            nms_iou,
            max_box_fraction,
        )


def postprocess_grounding(
    logits: np.ndarray,
    boxes: np.ndarray,
    caption: Caption,
    height: int,
    width: int,
    box_threshold: float = 0.35,
    text_threshold: float = 0.25,
    nms_iou: float = 0.5,
    max_box_fraction: float = 0.95,
) -> GroundingResult:
    """Steps 3-5 of the module docstring on one image's `(Q, L)` logits and `(Q, 4)` normalized boxes."""
    logits = np.asarray(logits)
    if logits.ndim != 2 or logits.shape[1] < caption.num_tokens:
        raise ContractError(f"detector logits of shape {logits.shape}: expected (queries, >= {caption.num_tokens} tokens)")
    probs = sigmoid(logits[:, : caption.num_tokens])
    box_scores = probs.max(axis=1)
    candidates = np.flatnonzero(box_scores > box_threshold)
    labels = label_scores(probs[candidates], caption, text_threshold)
    candidates = np.array([q for q, found in zip(candidates, labels) if found], np.int64)
    labels = [found for found in labels if found]
    if candidates.size == 0:
        return GroundingResult.empty(caption)
    xyxy = cxcywh_to_xyxy(np.asarray(boxes)[candidates], width, height)
    keep = ~large_boxes(xyxy, width, height, max_box_fraction)
    keep &= (xyxy[:, 2] > xyxy[:, 0]) & (xyxy[:, 3] > xyxy[:, 1])
    kept = np.flatnonzero(keep)
    xyxy, scores = xyxy[kept], box_scores[candidates][kept]
    labels = [labels[i] for i in kept]
    order = nms(xyxy, scores, nms_iou)
    return GroundingResult(xyxy[order], scores[order].astype(np.float32), [labels[i] for i in order], caption)
