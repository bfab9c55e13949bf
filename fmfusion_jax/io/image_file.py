"""Reading image files: one place that turns every failure into a `DataError` naming the file."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from fmfusion_jax.errors import DataError


def read_image(path: Path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    """Decodes an image file; a `DataError` naming the file when it is missing, not a regular file or corrupt.

    The bytes are read by Python and decoded from memory (`cv2.imread` mishandles paths that are not UTF-8,
    and decodes a JPEG cut short with a grey rest and an anonymous "premature end" on stderr; from memory such
    a file does not decode, and the error says it was cut).
    """
    if not path.exists():
        raise DataError(f"{path}: file missing")
    if not path.is_file():
        raise DataError(f"{path}: not a regular file")
    try:
        data = path.read_bytes()
    except OSError as error:
        raise DataError(f"{path}: unreadable ({error.strerror or error})") from None
    image = cv2.imdecode(np.frombuffer(data, np.uint8), flags) if data else None
    if image is None:
        truncated = data[:2] == b"\xff\xd8" and data.rstrip(b"\0")[-2:] != b"\xff\xd9"
        raise DataError(f"{path}: {'truncated JPEG (no end marker)' if truncated else 'unreadable or corrupt image'}")
    return image
