"""Closed-set COCO detection: an RGB image -> pixel boxes, scores and COCO class names.

Two detectors of the shared models folder (contracts `NANODET`, `SSD`; README.md there describes both):

- ``nanodet``: NanoDet-g 416. The image is letterboxed into 416x416 (scale ``r = min(416 / W, 416 / H)``,
  centred, black border), BGR, normalized with NanoDet's mean/std. Each output cell of stride s (52, 26, 13
  cells a side) has 80 class scores (sigmoid applied) and, per side (left, top, right, bottom), 11 distance
  bins: distance = ``sum(softmax(bins) * [0..10]) * s`` from the cell centre ``((x + 0.5) s, (y + 0.5) s)``.
  Every (cell, class) above the score threshold is a candidate; per-class NMS (IoU 0.6, NanoDet's value),
  at most 100; boxes mapped back through the inverse letterbox.
- ``ssd``: SSD MobileNetV2 COCO (TF Object Detection API). The graph takes the RGB uint8 image as it is and
  does resizing, normalization and per-class NMS (IoU 0.6, scores > 0.3) itself; boxes come back as
  normalized ``(ymin, xmin, ymax, xmax)``, classes as COCO category ids 1..90.

Both give boxes ``[u0, v0, u1, v1]`` float32 in pixels of the input image, clipped to it, sorted by score.
Class names come from ``detector/coco_labels.txt``: tab-separated ``nanodet_id  ssd_id  name``, a header line,
then the 80 classes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from detectors.contracts import COCO_CLASSES, NANODET, NANODET_SIZE, NANODET_STRIDES, SSD, ModelContract
from detectors.grounding import nms
from detectors.image_ops import check_rgb_image
from detectors.onnx_runtime import ContractError, OnnxModel, open_session, require_file
from fmfusion_jax.errors import DataError, UserError

#: NanoDet's normalization (its config's img_norm_cfg), in BGR order on the 0..255 scale.
NANODET_MEAN_BGR = np.array([103.53, 116.28, 123.675], np.float32)
NANODET_STD_BGR = np.array([57.375, 57.12, 58.395], np.float32)
#: Detector kinds, their contracts and default score thresholds (NanoDet's quality-focal scores run lower).
KINDS: dict[str, ModelContract] = {"nanodet": NANODET, "ssd": SSD}
DEFAULT_SCORE_THRESHOLD = {"nanodet": 0.35, "ssd": 0.4}
#: IoU above which per-class NMS drops the lower box, and the most boxes a frame keeps.
DEFAULT_NMS_IOU, DEFAULT_MAX_DETECTIONS = 0.6, 100
LABELS_HEADER = ["nanodet_id", "ssd_id", "name"]


@dataclasses.dataclass(frozen=True)
class CocoLabels:
    """The 80 COCO class names with both detectors' ids.

    Attributes:
      names: `80` names by NanoDet class index (0..79).
      by_category: COCO category id (SSD's 1..90, with gaps) -> name.
    """

    names: tuple[str, ...]
    by_category: dict[int, str]


def read_coco_labels(path: str | Path) -> CocoLabels:
    """Reads ``coco_labels.txt`` (see the module docstring); `DataError` naming the file and line if malformed."""
    path = require_file(Path(path), "COCO label file", "Copy detector/coco_labels.txt of the shared models folder")
    lines = path.read_text(encoding="utf-8").splitlines()
    if not lines or lines[0].split("\t") != LABELS_HEADER:
        raise DataError(f"{path}: expected the header line {' TAB '.join(LABELS_HEADER)}")
    names: list[str] = []
    by_category: dict[int, str] = {}
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        fields = line.split("\t")
        try:
            index, category, name = int(fields[0]), int(fields[1]), fields[2].strip()
        except (IndexError, ValueError):
            raise DataError(f"{path}:{number}: expected 'nanodet_id TAB ssd_id TAB name', got {line!r}") from None
        if index != len(names) or not name or category in by_category:
            raise DataError(f"{path}:{number}: nanodet_id {index} out of order, empty name or repeated ssd_id {category}")
        names.append(name)
        by_category[category] = name
    if len(names) != COCO_CLASSES:
        raise DataError(f"{path}: {len(names)} classes, expected {COCO_CLASSES}")
    return CocoLabels(tuple(names), by_category)


@dataclasses.dataclass(frozen=True)
class CocoDetections:
    """Detections of one image, by decreasing score.

    Attributes:
      boxes: `(N, 4)` float32 pixel boxes ``[u0, v0, u1, v1]``, clipped to the image.
      scores: `(N,)` float32.
      names: `N` COCO class names.
    """

    boxes: np.ndarray
    scores: np.ndarray
    names: list[str]

    def __len__(self) -> int:
        return len(self.names)

    def select(self, keep: Sequence[int] | np.ndarray) -> "CocoDetections":
        keep = np.asarray(keep, np.int64).reshape(-1)
        return CocoDetections(self.boxes[keep].reshape(-1, 4), self.scores[keep], [self.names[i] for i in keep])

    @staticmethod
    def empty() -> "CocoDetections":
        return CocoDetections(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), [])


def per_class_nms(
    boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray, iou_threshold: float, max_detections: int | None = None
) -> np.ndarray:
    """Greedy NMS within each class: indices kept, by decreasing score, at most `max_detections`.

    `boxes` `(N, 4)`, `scores` `(N,)`, `classes` `(N,)` int. Boxes of different classes never suppress each other.
    """
    classes = np.asarray(classes).reshape(-1)
    scores = np.asarray(scores, np.float64).reshape(-1)
    keep = [
        np.flatnonzero(classes == c)[nms(boxes[classes == c], scores[classes == c], iou_threshold)] for c in np.unique(classes)
    ]
    kept = np.concatenate(keep) if keep else np.zeros(0, np.int64)
    kept = kept[np.argsort(-scores[kept], kind="stable")]
    return kept[:max_detections] if max_detections is not None else kept


def letterbox(height: int, width: int, size: int = NANODET_SIZE) -> np.ndarray:
    """`(2, 3)` float32 affine map image pixel -> network pixel: scale to fit `size` x `size`, centred."""
    r = min(size / width, size / height)
    return np.array([[r, 0.0, (size - width * r) / 2], [0.0, r, (size - height * r) / 2]], np.float32)


def preprocess_nanodet(image: np.ndarray, size: int = NANODET_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """`(H, W, 3)` uint8 RGB -> `(1, 3, size, size)` float32 BGR normalized, and the `(2, 3)` letterbox map."""
    image = check_rgb_image(image)
    transform = letterbox(image.shape[0], image.shape[1], size)
    boxed = cv2.warpAffine(image[:, :, ::-1], transform, (size, size), flags=cv2.INTER_LINEAR, borderValue=(0, 0, 0))
    normalized = (boxed.astype(np.float32) - NANODET_MEAN_BGR) / NANODET_STD_BGR
    return np.ascontiguousarray(normalized.transpose(2, 0, 1)[None]), transform


def decode_nanodet(
    class_scores: Sequence[np.ndarray], regression: Sequence[np.ndarray], score_threshold: float, size: int = NANODET_SIZE
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NanoDet's per-stride outputs -> candidate boxes `(M, 4)` in the network frame, scores `(M,)`, classes `(M,)`.

    `class_scores[k]` `(n*n, C)` and `regression[k]` `(n*n, 4 * bins)` belong to stride `NANODET_STRIDES[k]`,
    cells row-major (index = y * n + x). Candidates are the (cell, class) pairs above `score_threshold`;
    only their cells' bins are decoded. Boxes are clipped to `[0, size]`.
    """
    boxes, scores, classes = [], [], []
    for stride, cls, reg in zip(NANODET_STRIDES, class_scores, regression):
        cells, ids = np.nonzero(cls > score_threshold)
        if cells.size == 0:
            continue
        bins = reg[cells].reshape(-1, 4, reg.shape[-1] // 4).astype(np.float64)
        weights = np.exp(bins - bins.max(-1, keepdims=True))
        distance = (weights / weights.sum(-1, keepdims=True) * np.arange(bins.shape[-1])).sum(-1) * stride
        n = size // stride
        cy, cx = np.divmod(cells, n)
        cx, cy = (cx + 0.5) * stride, (cy + 0.5) * stride  # NanoDet v0.x: cell centres
        box = np.stack([cx - distance[:, 0], cy - distance[:, 1], cx + distance[:, 2], cy + distance[:, 3]], 1)
        boxes.append(box.clip(0, size))
        scores.append(cls[cells, ids])
        classes.append(ids)
    if not boxes:
        return np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64)
    return np.concatenate(boxes).astype(np.float32), np.concatenate(scores).astype(np.float32), np.concatenate(classes)


def unletterbox(boxes: np.ndarray, transform: np.ndarray, height: int, width: int) -> np.ndarray:
    """`(N, 4)` boxes in the network frame -> image pixels (inverse of `transform`), clipped to the image."""
    r, du, dv = transform[0, 0], transform[0, 2], transform[1, 2]
    out = np.asarray(boxes, np.float32).reshape(-1, 4).copy()
    out[:, [0, 2]] = ((out[:, [0, 2]] - du) / r).clip(0, width)
    out[:, [1, 3]] = ((out[:, [1, 3]] - dv) / r).clip(0, height)
    return out


def detector_kind(session, path: Path) -> str:
    """``"ssd"`` or ``"nanodet"`` from an onnxruntime session's input names; `ContractError` when neither fits."""
    names = {arg.name for arg in session.get_inputs()}
    for kind, contract in KINDS.items():
        if names == {name for spec in contract.inputs for name in spec.names}:
            return kind
    raise ContractError(
        f"{path}: inputs {sorted(names)} are neither NanoDet's ({NANODET.inputs[0].name}) nor SSD's "
        f"({SSD.inputs[0].name}); give the detector's kind in models.yaml or use a file of the shared models folder"
    )


class CocoDetector:
    """NanoDet or SSD through onnxruntime (see the module docstring).

    Args:
      model: the ONNX model, bound to the `NANODET` or `SSD` contract.
      labels: the COCO names.
      kind: ``"nanodet"`` or ``"ssd"`` (the contract `model` was bound to).
      score_threshold: keep detections scoring above this; None: 0.35 for NanoDet, 0.4 for SSD.
      nms_iou: NanoDet's per-class NMS IoU (SSD's NMS is inside the graph).
      max_detections: at most this many detections (highest scores).
    """

    def __init__(
        self,
        model: OnnxModel,
        labels: CocoLabels,
        kind: str,
        score_threshold: float | None = None,
        nms_iou: float = DEFAULT_NMS_IOU,
        max_detections: int = DEFAULT_MAX_DETECTIONS,
    ):
        if kind not in KINDS:
            raise UserError(f"detector kind {kind!r}: expected one of {', '.join(KINDS)}")
        if model.contract is not KINDS[kind]:
            raise ValueError(f"{model.path}: bound to the {model.contract.key} contract, not {kind}'s")
        self.model, self.labels, self.kind = model, labels, kind
        self.score_threshold = DEFAULT_SCORE_THRESHOLD[kind] if score_threshold is None else float(score_threshold)
        for name, value in (("score_threshold", self.score_threshold), ("nms_iou", nms_iou)):
            if not 0.0 <= value <= 1.0:
                raise UserError(f"{model.path}: detector {name} {value} must lie in [0, 1]")
        self.nms_iou = nms_iou
        self.max_detections = max_detections

    @classmethod
    def from_files(
        cls,
        path: str | Path,
        labels: str | Path,
        kind: str | None = None,
        providers="cpu",
        threads: int | None = None,
        **options,
    ) -> "CocoDetector":
        """Loads `path` as `kind`, or as the kind its input names say (`detector_kind`) when None."""
        path = Path(path)
        if kind is not None and kind not in KINDS:
            raise UserError(f"{path}: detector kind {kind!r}: expected one of {', '.join(KINDS)}")
        probe = KINDS[kind] if kind else dataclasses.replace(NANODET, title="COCO detector (NanoDet or SSD)")
        session = open_session(path, probe, providers, threads)
        kind = kind or detector_kind(session, path)
        model = OnnxModel(path, KINDS[kind], providers, threads, session=session)
        return cls(model, read_coco_labels(labels), kind, **options)

    @property
    def providers(self) -> list[str]:
        return self.model.providers

    def __call__(self, image: np.ndarray) -> CocoDetections:
        """Detections in `image` `(H, W, 3)` uint8 RGB above the score threshold, by decreasing score."""
        image = check_rgb_image(image)
        found = self._nanodet(image) if self.kind == "nanodet" else self._ssd(image)
        wide = (found.boxes[:, 2] > found.boxes[:, 0]) & (found.boxes[:, 3] > found.boxes[:, 1])
        return found.select(np.flatnonzero(wide)[: self.max_detections])

    def _nanodet(self, image: np.ndarray) -> CocoDetections:
        batch, transform = preprocess_nanodet(image)
        names = [f"{kind}_stride{s}" for kind in ("cls", "reg") for s in NANODET_STRIDES]
        out = self.model.run({"image": batch}, names)
        count = len(NANODET_STRIDES)
        boxes, scores, classes = decode_nanodet(
            [out[name][0] for name in names[:count]], [out[name][0] for name in names[count:]], self.score_threshold
        )
        keep = per_class_nms(boxes, scores, classes, self.nms_iou, self.max_detections)
        pixels = unletterbox(boxes[keep], transform, *image.shape[:2])
        return CocoDetections(pixels, scores[keep], [self.labels.names[c] for c in classes[keep]])

    def _ssd(self, image: np.ndarray) -> CocoDetections:
        out = self.model.run(
            {"image_tensor": image[None]}, ["detection_boxes", "detection_scores", "detection_classes", "num_detections"]
        )
        count = int(out["num_detections"][0])
        scores = out["detection_scores"][0, :count]
        categories = out["detection_classes"][0, :count].round().astype(np.int64)
        # the graph's own threshold is 0.3; unknown category ids (none in COCO-80) are dropped
        keep = np.flatnonzero((scores > self.score_threshold) & np.isin(categories, list(self.labels.by_category)))
        keep = keep[np.argsort(-scores[keep], kind="stable")]
        height, width = image.shape[:2]
        ymin, xmin, ymax, xmax = out["detection_boxes"][0, keep].T
        boxes = np.stack([xmin * width, ymin * height, xmax * width, ymax * height], 1).reshape(-1, 4)
        boxes = boxes.clip(0, [width, height, width, height]).astype(np.float32)
        return CocoDetections(boxes, scores[keep].astype(np.float32), [self.labels.by_category[c] for c in categories[keep]])
