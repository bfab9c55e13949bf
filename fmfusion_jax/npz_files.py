"""Writing `.npz` files (NumPy's zip of `.npy` arrays) fast: deflated by ISA-L when it is installed.

A map state or a cloud of labelled points is tens of megabytes of float arrays, and zlib's deflate takes ~1.5 s
for a ScanNet room's map even at its fastest level. ISA-L's deflate (`isal`, a wheel on every common platform)
writes the same format ten times faster at the same size, so the files stay ordinary zip/deflate archives that
`numpy.load`, `unzip` and every zip reader open. Without `isal` (or if Python's zip writer changes its
internals) the files are deflated by zlib: slower, the same format.
"""

from __future__ import annotations

import zipfile
import zlib
from collections.abc import Iterable
from pathlib import Path
from typing import IO, Any

import numpy as np

try:  # optional at run time: the core dependency may lack a wheel on an odd platform
    from isal import isal_zlib as _isal_zlib

    isal_zlib: Any = _isal_zlib
except ImportError:  # pragma: no cover - exercised where isal is missing
    isal_zlib = None


def isal_level(compresslevel: int) -> int | None:
    """The ISA-L level (0-3) of a zlib `compresslevel` (1-9): 1-3 -> 1, 4-6 -> 2, 7-9 -> 3; None for 0 (stored,
    left to zlib) or without ISA-L."""
    if isal_zlib is None or compresslevel <= 0:
        return None
    return 1 + (min(compresslevel, 9) - 1) // 3


def _use_isal(stream: IO[bytes], compresslevel: int) -> None:
    """Swaps the deflate compressor of a zip entry just opened for writing (nothing written yet) for ISA-L's.

    `zipfile` has no public hook for its compressor; its writer keeps it in `_compressor` and calls only
    `compress` and `flush` on it, which an ISA-L compressobj (raw deflate, `wbits=-15`, as zipfile's own) has.
    Where that attribute is not a zlib compressor, the entry keeps zlib's."""
    level = isal_level(compresslevel)
    if level is None or not isinstance(getattr(stream, "_compressor", None), type(zlib.compressobj())):
        return
    stream._compressor = isal_zlib.compressobj(level, zlib.DEFLATED, -15)  # type: ignore[attr-defined]


def write_npz(path: str | Path, arrays: Iterable[tuple[str, Any]], compresslevel: int = 1) -> Path:
    """Writes `(name, array)` pairs, one at a time as they come, to the `.npz` file `path` (deflated; no pickle:
    object arrays are refused). Returns the path. The file is written in place: callers that must never leave
    half a file write beside the target and rename (`mapping.map_file.write_state_file`)."""
    path = Path(path)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=compresslevel) as archive:
        for name, value in arrays:
            value = np.asarray(value)
            if value.dtype == object:
                raise ValueError(f"{name}: object arrays cannot be saved (no pickle)")
            with archive.open(f"{name}.npy", "w", force_zip64=True) as stream:
                _use_isal(stream, compresslevel)
                np.lib.format.write_array(stream, value, allow_pickle=False)
    return path
