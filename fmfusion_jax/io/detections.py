"""Reading and writing per-frame detection files in the authors' format.

One detection frame is a pair in a folder such as ``prediction/``:

- ``<frame>_label.json``::

      {"raw_tags": "armchair. chair. floor", "tags": "armchair. chair. floor",
       "mask": [{"value": 0, "label": "background"},
                {"value": 1, "labels": {"chair": 0.52, "armchair": 0.38}, "box": [u0, v0, u1, v1]}]}

  An entry with a ``box`` is a detection; any other entry must be the background (``value`` 0).
  ``tags`` is the prompt sent to the detector; tag strings are ``". "``-separated.
- ``<frame>_mask.npy``: `(K, H, W)` 0/1, mask ``value - 1`` belongs to the detection of that ``value``
  (values are 1..K); or ``<frame>_mask.png``: uint8 (or uint16), pixel = detection ``value``, 0 = background.

Our extensions (ignored by the authors' reader, optional here): ``"tagger_tags"`` (list of str), the
tagger's tags kept after filtering, which `FrameDetections.tags` holds apart from the prompt. Files
without it read with ``tags = prompt``.

Writing ``mask_format="png"`` keeps the authors' compact format when the masks are disjoint; a png holds one
detection per pixel, so when masks overlap (or there are more than 255) the frame is written as ``.npy``
instead (lossless; logged at info level). Writing one format removes the frame's file of the other.
"""

from __future__ import annotations

import io
import json
import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io.atomic import write_atomic
from fmfusion_jax.io.image_file import read_image
from fmfusion_jax.types import FrameDetections, RGBDFrame, score_problem

logger = logging.getLogger(__name__)

LABEL_SUFFIX = "_label.json"
NPY_SUFFIX = "_mask.npy"
PNG_SUFFIX = "_mask.png"

#: Limits of one ``_label.json`` (a detector gives tens of detections a frame): larger files are refused with
#: an error instead of costing memory in proportion (each detection's mask is a full-size image).
MAX_LABEL_FILE_BYTES = 16 * 2**20
MAX_DETECTIONS_PER_FRAME = 1024

#: Boxes may reach this fraction of the image size beyond its border (detector boxes are not clamped);
#: they are clipped to the image. Farther out means the box is in other pixel units: an error.
BOX_MARGIN_FRACTION = 0.05


def label_path(folder: str | Path, frame_name: str) -> Path:
    return Path(folder) / f"{frame_name}{LABEL_SUFFIX}"


def list_detection_frames(folder: str | Path) -> list[str]:
    """Names of the frames with a ``_label.json`` in `folder`, sorted; `UserError` if `folder` is not one."""
    folder = Path(folder)
    if not folder.is_dir():
        raise UserError(f"{folder}: detection folder not found")
    return sorted(name[: -len(LABEL_SUFFIX)] for name in os.listdir(folder) if name.endswith(LABEL_SUFFIX))


def parse_tags(value: Any, where: str, key: str) -> list[str]:
    """``"a. b. c"`` (or a list of str) -> ``["a", "b", "c"]``."""
    if value is None:
        return []
    if isinstance(value, str):
        return [tag.strip() for tag in value.split(".") if tag.strip()]
    if isinstance(value, list) and all(isinstance(tag, str) for tag in value):
        return list(value)
    raise DataError(f"{where}: {key!r} must be a '. '-separated string or a list of strings, got {value!r}")


def format_tags(tags: Sequence[str], frame_name: str) -> str:
    """``["a", "b"]`` -> ``"a. b"``; `ValueError` for a tag that would not read back the same."""
    for tag in tags:
        if not isinstance(tag, str) or not tag or tag != tag.strip() or "." in tag:
            raise ValueError(
                f"{frame_name}: tag {tag!r} cannot be written as a '. '-separated tag "
                "(must be a non-empty string without '.' or surrounding spaces)"
            )
    return ". ".join(tags)


def read_frame_labels(folder: str | Path, frame_name: str) -> dict[str, Any] | None:
    """Reads and checks one ``_label.json`` without its masks (cheap, for statistics).

    Returns None when the file is absent, else a dict with ``values`` (list of int), ``labels`` (list of
    dict label -> score), ``boxes`` (`(N, 4)` float64, unchecked against the image size), ``raw_tags``,
    ``tags``, ``prompt`` (lists of str), in the file's detection order sorted by value.
    """
    path = label_path(folder, frame_name)
    if not path.exists():
        return None
    if not path.is_file():
        raise DataError(f"{path}: not a regular file")
    size = path.stat().st_size
    if size > MAX_LABEL_FILE_BYTES:
        raise DataError(
            f"{path}: {size / 2**20:.1f} MiB, more than a detection file can be ({MAX_LABEL_FILE_BYTES // 2**20} MiB)"
        )
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as error:
        raise DataError(f"{path}: unreadable ({error})") from None
    except json.JSONDecodeError as error:
        raise DataError(f"{path}: malformed JSON ({error})") from None
    except RecursionError:
        raise DataError(f"{path}: malformed JSON (nested too deep)") from None
    if not isinstance(data, dict):
        raise DataError(f"{path}: expected a JSON object, found {type(data).__name__}")
    entries = data.get("mask")
    if not isinstance(entries, list):
        raise DataError(f"{path}: 'mask' must be a list of detection entries")
    if len(entries) > MAX_DETECTIONS_PER_FRAME + 1:
        raise DataError(
            f"{path}: {len(entries)} entries, more than the {MAX_DETECTIONS_PER_FRAME} detections a "
            "frame may hold (filter the detector's output first)"
        )

    detections = []
    for position, entry in enumerate(entries):
        where = f"{path}: mask[{position}]"
        if not isinstance(entry, dict):
            raise DataError(f"{where}: expected an object, found {entry!r}")
        value = entry.get("value")
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise DataError(f"{where}: 'value' must be a non-negative integer, found {value!r}")
        if "box" not in entry:
            if value != 0:
                raise DataError(f"{where}: value {value} has no 'box' (only the background, value 0, may omit it)")
            continue
        if value == 0:
            raise DataError(f"{where}: value 0 is the background, but this entry has a 'box'")
        detections.append((value, _check_labels(entry.get("labels"), where), _check_box(entry["box"], where)))

    detections.sort(key=lambda item: item[0])
    values = [value for value, _, _ in detections]
    if len(set(values)) != len(values):
        duplicates = sorted({v for v in values if values.count(v) > 1})
        raise DataError(f"{path}: detection values {duplicates} appear more than once")
    prompt = parse_tags(data.get("tags"), str(path), "tags")
    tagger_tags = data.get("tagger_tags")
    return {
        "values": values,
        "labels": [labels for _, labels, _ in detections],
        "boxes": np.array([box for _, _, box in detections], np.float64).reshape(-1, 4),
        "raw_tags": parse_tags(data.get("raw_tags"), str(path), "raw_tags"),
        "tags": prompt if tagger_tags is None else _check_tag_list(tagger_tags, str(path), "tagger_tags"),
        "prompt": prompt,
    }


def read_frame_detections(
    folder: str | Path, frame_name: str, image_shape: tuple[int, int] | None = None
) -> FrameDetections | None:
    """Reads one detection frame; None when `frame_name` has no ``_label.json`` in `folder`.

    Args:
      image_shape: `(H, W)` the masks must have (the depth image's), or None to take the masks' size.

    Returns detections in increasing ``value`` order; boxes clipped to the image. Labels outside the
    open-set label set are kept (the fusion ignores them).

    Raises:
      DataError: naming the file, for a missing mask file, malformed JSON, bad values, labels, scores or
        boxes, a mask count that does not match the JSON, or masks of another size than `image_shape`.
    """
    parsed = read_frame_labels(folder, frame_name)
    if parsed is None:
        return None
    folder = Path(folder)
    npy_path, png_path = folder / f"{frame_name}{NPY_SUFFIX}", folder / f"{frame_name}{PNG_SUFFIX}"
    values = parsed["values"]
    if npy_path.is_file():
        if png_path.is_file():
            logger.warning("%s: both %s and %s exist; reading the .npy", folder, npy_path.name, png_path.name)
        masks = _read_npy_masks(npy_path, values)
        mask_path = npy_path
    elif png_path.is_file():
        masks = _read_png_masks(png_path, values)
        mask_path = png_path
    else:
        raise DataError(f"{npy_path}: mask file missing (nor {png_path.name}) for {label_path(folder, frame_name)}")

    height, width = masks.shape[1:]
    if image_shape is not None and (height, width) != tuple(image_shape):
        raise DataError(f"{mask_path}: masks are {width}x{height}, the images are {image_shape[1]}x{image_shape[0]}")
    boxes = _clip_boxes(parsed["boxes"], height, width, label_path(folder, frame_name))
    return FrameDetections(
        frame_name=frame_name,
        masks=masks,
        labels=parsed["labels"],
        boxes=boxes,
        raw_tags=parsed["raw_tags"],
        tags=parsed["tags"],
        prompt=parsed["prompt"],
    )


def write_frame_detections(folder: str | Path, detections: FrameDetections, mask_format: str = "png") -> list[Path]:
    """Writes one detection frame (mask file, then ``_label.json``, each atomically); returns both paths.

    ``mask_format="png"`` falls back to ``.npy`` when masks overlap or there are more than 255 detections
    (see the module docstring). JSON ``tags`` holds `detections.prompt`; ``tagger_tags`` holds `.tags`.
    """
    if mask_format not in ("png", "npy"):
        raise UserError(f"mask_format {mask_format!r}: expected 'png' or 'npy'")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    name = detections.frame_name
    masks = np.asarray(detections.masks).astype(bool)
    count = detections.num_detections
    entries: list[dict[str, Any]] = [{"value": 0, "label": "background"}]
    for k in range(count):
        labels = {str(label): float(score) for label, score in detections.labels[k].items()}
        _check_labels(labels, f"{name}: detection {k}", error=ValueError)
        box = [float(x) for x in np.asarray(detections.boxes[k], np.float64)]
        _check_box(box, f"{name}: detection {k}", error=ValueError)
        entries.append({"value": k + 1, "labels": labels, "box": box})
    document = {
        "raw_tags": format_tags(detections.raw_tags, name),
        "tags": format_tags(detections.prompt, name),
        "tagger_tags": list(detections.tags),
        "mask": entries,
    }
    _check_tag_list(document["tagger_tags"], name, "tags", error=ValueError)

    if mask_format == "png" and (count > 255 or (count and masks.sum(axis=0).max() > 1)):
        logger.info(
            "%s: %s; writing %s instead of a png (which holds one detection per pixel)",
            name,
            "more than 255 detections" if count > 255 else "masks overlap",
            NPY_SUFFIX,
        )
        mask_format = "npy"
    if mask_format == "png":
        label_image = np.zeros(masks.shape[1:], np.uint8)
        for k in range(count):
            label_image[masks[k]] = k + 1
        ok, encoded = cv2.imencode(".png", label_image)
        if not ok:
            raise DataError(f"{folder / (name + PNG_SUFFIX)}: PNG encoding failed")
        mask_path, stale_path, payload = folder / f"{name}{PNG_SUFFIX}", folder / f"{name}{NPY_SUFFIX}", encoded.tobytes()
    else:
        mask_path, stale_path = folder / f"{name}{NPY_SUFFIX}", folder / f"{name}{PNG_SUFFIX}"
        payload = _npy_bytes(masks.astype(np.uint8))
    write_atomic(mask_path, payload)
    stale_path.unlink(missing_ok=True)
    json_path = label_path(folder, name)
    write_atomic(json_path, json.dumps(document, indent=1).encode())
    return [mask_path, json_path]


class DetectionFolder:
    """A folder of detection files: `.get(frame_name)` reads one frame (None when it has none). Called with a
    frame it is a detection source (`mapping.DetectionSource`) that `fmfusion run` reads ahead."""

    #: no state and no model to run: a reader thread may read frames that the schedule then leaves out
    reads_ahead = True

    def __init__(self, folder: str | Path, image_shape: tuple[int, int] | None = None):
        self.folder = Path(folder)
        self.image_shape = image_shape
        self.frame_names = list_detection_frames(self.folder)
        self._names = set(self.frame_names)

    def __len__(self) -> int:
        return len(self.frame_names)

    def __contains__(self, frame_name: str) -> bool:
        return frame_name in self._names

    def __repr__(self) -> str:
        return f"DetectionFolder({str(self.folder)!r}, frames={len(self)})"

    def get(self, frame_name: str) -> FrameDetections | None:
        if frame_name not in self._names:
            return None
        return read_frame_detections(self.folder, frame_name, self.image_shape)

    def __call__(self, frame: RGBDFrame) -> FrameDetections | None:
        return self.get(frame.name)


def _check_labels(labels: Any, where: str, error: type[Exception] = DataError) -> dict[str, float]:
    """A detection's ``labels``: dict of str -> number in [0, 1] (bools are not numbers here)."""
    if not isinstance(labels, dict):
        raise error(f"{where}: 'labels' must be an object of label -> score, found {labels!r}")
    checked = {}
    for label, score in labels.items():
        problem = score_problem(label, score)
        if problem is not None:
            raise error(f"{where}: {problem}")
        checked[label] = float(score)
    return checked


def _check_box(box: Any, where: str, error: type[Exception] = DataError) -> list[float]:
    """A box ``[u0, v0, u1, v1]`` of 4 finite numbers with u0 <= u1, v0 <= v1."""
    if not (
        isinstance(box, (list, tuple))
        and len(box) == 4
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in box)
    ):
        raise error(f"{where}: 'box' must be 4 finite numbers [u0, v0, u1, v1], found {box!r}")
    u0, v0, u1, v1 = (float(x) for x in box)
    if u0 > u1 or v0 > v1:
        raise error(f"{where}: box {box} has u0 > u1 or v0 > v1")
    return [u0, v0, u1, v1]


def _check_tag_list(tags: Any, where: str, key: str, error: type[Exception] = DataError) -> list[str]:
    if not (isinstance(tags, list) and all(isinstance(tag, str) for tag in tags)):
        raise error(f"{where}: {key!r} must be a list of strings, found {tags!r}")
    return list(tags)


def _clip_boxes(boxes: np.ndarray, height: int, width: int, path: Path) -> np.ndarray:
    """`(N, 4)` boxes checked to lie within the image grown by `BOX_MARGIN_FRACTION`, clipped to it, float32."""
    margin_u, margin_v = BOX_MARGIN_FRACTION * width, BOX_MARGIN_FRACTION * height
    for k, (u0, v0, u1, v1) in enumerate(boxes):
        if u0 < -margin_u or v0 < -margin_v or u1 > width + margin_u or v1 > height + margin_v:
            raise DataError(
                f"{path}: box {k} [{u0:g}, {v0:g}, {u1:g}, {v1:g}] lies outside the {width}x{height} "
                "image (boxes must be in the masks' pixel units)"
            )
    clipped = boxes.copy()
    clipped[:, [0, 2]] = clipped[:, [0, 2]].clip(0, width)
    clipped[:, [1, 3]] = clipped[:, [1, 3]].clip(0, height)
    return clipped.astype(np.float32)


def _read_npy_masks(path: Path, values: list[int]) -> np.ndarray:
    """`(K, H, W)` bool masks ordered as `values` (mask ``v - 1`` is detection ``v``)."""
    try:
        stack = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as error:
        raise DataError(f"{path}: unreadable .npy ({error})") from None
    if stack.ndim != 3:
        raise DataError(f"{path}: masks must be (K, H, W), found shape {stack.shape}")
    if stack.shape[0] != len(values):
        raise DataError(f"{path}: {stack.shape[0]} masks for {len(values)} detections in the JSON")
    if values and values[-1] > len(values):
        raise DataError(f"{path}: detection values {values} must be 1..{len(values)} to index {len(values)} masks")
    if stack.dtype != bool:
        if not (np.issubdtype(stack.dtype, np.integer) or np.issubdtype(stack.dtype, np.floating)):
            raise DataError(f"{path}: masks of dtype {stack.dtype}, expected 0/1 numbers or bool")
        if stack.size and not np.isin(stack, (0, 1)).all():
            raise DataError(f"{path}: masks hold values other than 0 and 1")
        stack = stack.astype(bool)
    return stack[np.asarray(values, np.int64) - 1] if values else stack


def _read_png_masks(path: Path, values: list[int]) -> np.ndarray:
    """`(K, H, W)` bool masks, one per value, from a label image where pixel = value."""
    image = read_image(path)
    if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
        raise DataError(f"{path}: expected a single-channel uint8 label image, found {image.dtype} {image.shape}")
    present = set(np.flatnonzero(np.bincount(image.ravel())).tolist()) - {0}  # a 1-D count: ~2x np.unique's speed
    unknown = sorted(present - set(values))
    if unknown:
        raise DataError(f"{path}: pixel values {unknown} have no detection in the JSON (values {values})")
    missing = sorted(set(values) - present)
    if missing:
        # A later mask painted over an earlier one: the detection stays, with an empty mask.
        logger.debug("%s: detections %s have no pixel left", path, missing)
    return np.stack([image == v for v in values]) if values else np.zeros((0, *image.shape), bool)


def _npy_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()
