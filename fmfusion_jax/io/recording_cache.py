"""The cache of recordings that are decoded before they are read (ROS bags, Record3D exports).

Such a recording is read once and its frames extracted into a folder of the user cache,
``$XDG_CACHE_HOME/fmfusion-jax/recordings/<hash of the key>/`` (the key: the files' paths, sizes and modification
times and the reading choices that change the extracted files). The folder is written under a temporary name and
renamed when complete, its `MANIFEST` written last, so an interrupted extraction is never used; the next open reuses
it. The `Scene` then reads plain image files as for every other layout (reader threads, random access).
"""

from __future__ import annotations

import hashlib
import json
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from fmfusion_jax.compile_cache import user_cache_dir

#: Written last into an extracted folder: its presence marks a complete one.
MANIFEST = "manifest.json"
#: Raw depth units per metre of the extracted depth PNGs (millimetres).
EXTRACTED_DEPTH_SCALE = 1000.0


def cache_root() -> Path:
    """Where extracted recordings are kept: the project's user cache folder's recordings/."""
    return user_cache_dir() / "recordings"


def file_stats(files: Iterable[Path]) -> list[tuple[str, int, int]]:
    """`(resolved path, size, mtime ns)` of each regular file of `files`: what a cache key holds of a recording."""
    return [(str(f.resolve()), f.stat().st_size, f.stat().st_mtime_ns) for f in files if f.is_file()]


def cache_folder(key: Any) -> Path:
    """The cache folder of a recording whose extraction is determined by `key` (JSON-serialisable)."""
    return cache_root() / hashlib.sha256(json.dumps(key).encode()).hexdigest()[:20]


def is_extracted(folder: Path) -> bool:
    """Whether `folder` holds a complete extraction (its manifest)."""
    return (folder / MANIFEST).is_file()


def extract_once(folder: Path, write: Callable[[Path], None]) -> Path:
    """Makes `folder` by `write(staging)` into a temporary folder beside it (which must write `MANIFEST` last), then
    renamed; a failure leaves nothing behind. Returns `folder`."""
    folder.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=folder.name + ".", dir=folder.parent, ignore_cleanup_errors=True) as staging:
        write(Path(staging))
        try:
            Path(staging).rename(folder)
        except OSError:  # another process made it meanwhile: theirs is the same
            if not is_extracted(folder):
                raise
    return folder


def millimetres(metres: np.ndarray) -> np.ndarray:
    """Depth in metres `(H, W)` as uint16 millimetres (`EXTRACTED_DEPTH_SCALE`), 0 where not finite, not positive or
    beyond the 65.5 m a uint16 holds."""
    mm = np.where(np.isfinite(metres) & (metres > 0), np.round(np.nan_to_num(metres) * EXTRACTED_DEPTH_SCALE), 0)
    return np.where(mm <= 65535, mm, 0).astype(np.uint16)
