"""`.npz` files of named arrays with JSON metadata: the format of a saved map (`map_state.npz`).

A state file is an ordinary NumPy `.npz` (a zip of `.npy` files; `numpy.load` opens it without pickle)
holding the arrays plus one extra entry, `__metadata__`, a 0-d unicode array with a JSON object. For a
map, the metadata holds the format name and version, the `MapConfig` and the `PipelineConfig` (so the map
can be interpreted and fusion continued with the same static sizes) and how far fusion had got.

Entries are deflated at a low level (by ISA-L when installed, `npz_files`): the pool is mostly empty voxels, so
this shrinks a map several times for little time.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import zipfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from fmfusion_jax.config import config_from_dict
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.serialization import state_arrays, state_from_arrays
from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.mapping.builder import FusionResult
from fmfusion_jax.npz_files import write_npz

METADATA_KEY = "__metadata__"
MAP_FORMAT = "fmfusion-jax map state"
MAP_FORMAT_VERSION = 1


def write_state_file(
    path: str | Path,
    arrays: Mapping[str, np.ndarray] | Iterable[tuple[str, np.ndarray]],
    metadata: dict[str, Any],
    compresslevel: int = 1,
) -> Path:
    """Writes `arrays` (a mapping, or `(name, array)` pairs stored one at a time as they come) and the
    JSON-serializable `metadata` to `path` (`.npz`); returns the path.

    The file is written beside the target and renamed into place, so a crash never leaves half a file.
    """
    path = Path(path)
    items = arrays.items() if isinstance(arrays, Mapping) else arrays
    text = json.dumps(metadata, sort_keys=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")

    def entries() -> Iterable[tuple[str, Any]]:
        for index, (name, value) in enumerate(itertools.chain([(METADATA_KEY, np.array(text))], items)):
            if index and name == METADATA_KEY:
                raise ValueError(f"{METADATA_KEY} is reserved for the metadata")
            yield name, value

    write_npz(partial, entries(), compresslevel)
    partial.replace(path)
    return path


def read_state_file(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """`(arrays, metadata)` of a file written by `write_state_file`; unreadable files are DataErrors."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise DataError(f"{path}: not a readable .npz file ({error})") from None
    if METADATA_KEY not in arrays:
        raise DataError(f"{path}: no {METADATA_KEY} entry (not written by fmfusion)")
    try:
        metadata = json.loads(str(arrays.pop(METADATA_KEY)))
    except json.JSONDecodeError as error:
        raise DataError(f"{path}: metadata is not JSON ({error})") from None
    return arrays, metadata


# ---------------------------------------------------------------------------------------------------
# Maps


def map_config_to_dict(map_config) -> dict[str, Any]:
    return {f.name: _plain(getattr(map_config, f.name)) for f in dataclasses.fields(map_config)}


def map_config_from_dict(values: dict[str, Any]):
    known = {f.name for f in dataclasses.fields(MapConfig)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"unknown MapConfig fields {unknown}")
    return MapConfig(**values)  # __post_init__ turns the JSON lists back into tuples


def pipeline_config_from_dict(values: dict[str, Any], origin: str):
    """A `PipelineConfig` from `PipelineConfig.to_dict()` output, checked like a config file."""
    if not isinstance(values, dict):
        raise DataError(f"{origin}: the config is not a mapping of sections")
    try:
        return config_from_dict(values, origin)
    except UserError as error:
        raise DataError(str(error)) from None


def _plain(value):
    return list(value) if isinstance(value, tuple) else value


def write_map_file(path: str | Path, state, map_config, config, progress: dict[str, Any] | None = None) -> Path:
    """Saves a map: its state (allocated pool rows only), `MapConfig`, `PipelineConfig` and progress.

    Args:
      path: the `.npz` file to write.
      state: the `MapState`.
      map_config: its `MapConfig`.
      config: the `PipelineConfig` it was fused with.
      progress: how far fusion had got (`frames_integrated`, `detection_frames`, `counters`), so that
        a `MapBuilder` can continue the schedules where they stopped.
    """

    metadata = {
        "format": MAP_FORMAT,
        "version": MAP_FORMAT_VERSION,
        "map_config": map_config_to_dict(map_config),
        "pipeline_config": config.to_dict(),
        "progress": progress or {},
    }
    return write_state_file(path, state_arrays(state, map_config), metadata)  # one array in memory at a time


@dataclasses.dataclass
class SavedMap:
    """A map read back by `read_map_file`."""

    state: Any  # MapState
    map_config: Any  # MapConfig
    config: Any  # PipelineConfig
    progress: dict[str, Any]


def read_map_file(path: str | Path) -> SavedMap:
    """Reads a map written by `write_map_file`; a wrong or damaged file is a DataError naming it."""

    arrays, metadata = read_state_file(path)
    if metadata.get("format") != MAP_FORMAT:
        raise DataError(f"{path}: not a map state file (format {metadata.get('format')!r})")
    if metadata.get("version") != MAP_FORMAT_VERSION:
        raise DataError(f"{path}: map state version {metadata.get('version')}, this fmfusion reads version {MAP_FORMAT_VERSION}")
    try:
        map_config = map_config_from_dict(metadata["map_config"])
        state = state_from_arrays(arrays, map_config)
    except (KeyError, TypeError, ValueError) as error:
        raise DataError(
            f"{path}: cannot read this map state ({error}); damaged, or written by another version of fmfusion"
        ) from None
    config = pipeline_config_from_dict(metadata.get("pipeline_config", {}), f"{path} (pipeline config)")
    return SavedMap(state, map_config, config, dict(metadata.get("progress", {})))


def save_map(path: str | Path, result: FusionResult) -> Path:
    """Saves a fused map (state, MapConfig, PipelineConfig, how far fusion got) to an `.npz` file."""
    return write_map_file(path, result.state, result.map_config, result.config, result.progress())
