"""Image helpers shared by the models' preprocessing: resizing and ImageNet normalization (NumPy + OpenCV).

The reference pipelines resize with PIL (bilinear, antialiased when shrinking); here OpenCV's INTER_AREA is
used when shrinking and INTER_LINEAR (same half-pixel convention as PIL) when enlarging, which agree with
PIL to about one grey level: well below what changes a detection.
"""

from __future__ import annotations

import cv2
import numpy as np

from fmfusion_jax.types import RGBDFrame

#: ImageNet statistics, on the 0..1 scale (RAM, GroundingDINO); SAM uses the same values x 255.
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)


def check_rgb_image(image: np.ndarray) -> np.ndarray:
    """`image` if it is `(H, W, 3)` uint8 (RGB), else `ValueError`."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {image.dtype} {image.shape}")
    if image.shape[0] < 1 or image.shape[1] < 1:
        raise ValueError(f"empty image {image.shape}")
    return image


def frame_image(frame: RGBDFrame | np.ndarray, frame_name: str | None = None) -> tuple[np.ndarray, str]:
    """The `(H, W, 3)` uint8 RGB image and the name of what a front end's `detect` is given: an `RGBDFrame` (its
    colour and name, unless `frame_name`), or an image with its `frame_name` (required)."""
    name: str | None
    if isinstance(frame, RGBDFrame):
        image, name = frame.color, frame_name or frame.name
    else:
        image, name = frame, frame_name
    if not name:
        raise ValueError("detect() on an image needs its frame_name")
    return check_rgb_image(image), name


def resize(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resizes `(H, W, C)` (or `(H, W)`) to `height x width`: INTER_AREA when shrinking both sides, else bilinear."""
    if image.shape[:2] == (height, width):
        return image
    shrinking = height <= image.shape[0] and width <= image.shape[1]
    return cv2.resize(image, (int(width), int(height)), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)


def normalize_chw(image: np.ndarray) -> np.ndarray:
    """`(H, W, 3)` uint8 RGB -> `(1, 3, H, W)` float32 ``(x / 255 - mean) / std`` with ImageNet statistics."""
    scaled = image.astype(np.float32) * np.float32(1.0 / 255.0)
    normalized = (scaled - IMAGENET_MEAN) / IMAGENET_STD
    return np.ascontiguousarray(normalized.transpose(2, 0, 1)[None])
