"""ImageNet classification of image crops: an RGB crop -> its top-k ImageNet names with probabilities.

The model is EfficientNet-Lite3 uint8 (contract `CLASSIFIER`): the crop resized to 280x280 (INTER_AREA when
shrinking both sides, else bilinear), RGB uint8 as it is (no normalization: the graph's first quantization
does it); the output is a uint8 softmax whose quantization scale is 1/256, so probability = value / 256.
Names are the first comma-separated name of each line of ``classifier/imagenet_labels.txt`` (1000 lines in
output order; e.g. ``studio couch, day bed`` -> ``studio couch``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from detectors.contracts import CLASSIFIER, CLASSIFIER_SIZE, IMAGENET_CLASSES
from detectors.image_ops import check_rgb_image, resize
from detectors.onnx_runtime import OnnxModel, require_file
from fmfusion_jax.errors import DataError

#: The uint8 softmax's quantization scale.
PROBABILITY_SCALE = 1.0 / 256.0


def read_imagenet_labels(path: str | Path) -> tuple[str, ...]:
    """The first name of each line of ``imagenet_labels.txt``; `DataError` unless there are 1000 non-empty lines."""
    path = require_file(Path(path), "ImageNet label file", "Copy classifier/imagenet_labels.txt of the shared models folder")
    lines = path.read_text(encoding="utf-8").splitlines()
    names = tuple(line.split(",")[0].strip() for line in lines)
    if len(names) != IMAGENET_CLASSES or not all(names):
        raise DataError(f"{path}: {len(names)} lines (or empty ones), expected {IMAGENET_CLASSES} class names in output order")
    return names


def crop_bounds(image_shape: tuple[int, ...], box: np.ndarray, pad: float = 0.1) -> tuple[slice, slice]:
    """(rows, columns) slices of `box` ``[u0, v0, u1, v1]`` grown by `pad` of its size on each side, in the image.

    The margin gives the classifier some context, as ImageNet photos have; the slices hold at least one pixel.
    """
    height, width = image_shape[:2]
    u0, v0, u1, v1 = (float(x) for x in np.asarray(box).reshape(4))
    du, dv = (u1 - u0) * pad, (v1 - v0) * pad
    left, top = int(np.clip(u0 - du, 0, width - 1)), int(np.clip(v0 - dv, 0, height - 1))
    right, bottom = int(np.clip(np.ceil(u1 + du), left + 1, width)), int(np.clip(np.ceil(v1 + dv), top + 1, height))
    return slice(top, bottom), slice(left, right)


def box_crop(image: np.ndarray, box: np.ndarray, pad: float = 0.1) -> np.ndarray:
    """The pixels of `box` in `image` `(H, W, 3)` with a margin (`crop_bounds`)."""
    return image[crop_bounds(image.shape, box, pad)]


class ImageClassifier:
    """EfficientNet-Lite3 through onnxruntime (see the module docstring).

    Attributes:
      model: the ONNX model (contract `CLASSIFIER`).
      names: `1000` class names in output order.
    """

    def __init__(self, model: OnnxModel, names: tuple[str, ...]):
        self.model, self.names = model, names

    @classmethod
    def from_files(cls, path: str | Path, labels: str | Path, providers="cpu", threads: int | None = None) -> "ImageClassifier":
        return cls(OnnxModel(path, CLASSIFIER, providers, threads), read_imagenet_labels(labels))

    @property
    def providers(self) -> list[str]:
        return self.model.providers

    def probabilities(self, crop: np.ndarray) -> np.ndarray:
        """`(1000,)` float32 class probabilities of `crop` `(h, w, 3)` uint8 RGB."""
        resized = resize(check_rgb_image(crop), CLASSIFIER_SIZE, CLASSIFIER_SIZE)
        quantized = self.model.run({"images": resized[None]}, ["Softmax"])["Softmax"][0]
        return quantized.astype(np.float32) * np.float32(PROBABILITY_SCALE)

    def __call__(self, crop: np.ndarray, k: int = 5) -> list[tuple[str, float]]:
        """The `k` most probable `(name, probability)` of `crop` `(h, w, 3)` uint8 RGB, best first."""
        p = self.probabilities(crop)
        top = np.argsort(-p, kind="stable")[:k]
        return [(self.names[i], float(p[i])) for i in top]
