"""A `MapState` as a flat dict of NumPy arrays and back, exactly (pure conversions, no files).

The voxel-block pool is mostly empty: only slots `[0, num_blocks)` hold blocks and the last slot is the
scratch slot; every other slot stays at its initial value (tsdf 1, weights 0, instance ids -1, ...),
because every engine pass writes allocated slots only. `state_to_arrays` therefore keeps, of each pool
array, the allocated rows and the scratch row; `state_from_arrays` pads the rest back with the initial
values. The invariant is checked when saving: a pool array whose unallocated rows are not at their
initial values is saved whole (and loaded whole), so the round trip is exact either way.

Keys are the pytree paths, e.g. ``blocks.tsdf``, ``instances.valid``, ``frame_index``; a pool array saved
in part has ``blocks.tsdf`` (the allocated rows) and ``blocks.tsdf@scratch`` (the scratch row, `(1, ...)`).
`fmfusion_jax.mapping.map_file` writes these dicts to `.npz` files with the configs as metadata.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Iterator

import jax
import jax.numpy as jnp
import numpy as np

from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import InstanceTable, MapState, VoxelBlocks, init_map_state

#: Arrays of the pool whose leading axis is the pool slot (saved as allocated rows + scratch row).
POOL_FIELDS = ("block_coords", "tsdf", "weight", "color", "instance_id", "instance_weight", "instance_bits", "geometry_stale")

#: Suffix of the key holding the scratch row of a pool array saved in part.
SCRATCH_SUFFIX = "@scratch"

#: Arrays not saved, with their value on loading: scratch space of the steps (the same between steps).
UNSAVED_FILL = {"blocks.cell_owner": -1}

#: Arrays that maps saved by older versions lack, with the value they load with: the merge's kept census,
#: not valid (the next merge step counts it), and every block stale (the next geometry fusion visits all).
MISSING_FILL = {
    "blocks.geometry_stale": True,
    "blocks.up_heights": 0,
    "instances.census_counts": 0,
    "instances.census_overlap": 0,
    "instances.census_overfull": 0,
    "instances.census_valid": False,
}


def _keys() -> list[str]:
    return (
        [f"blocks.{name}" for name in VoxelBlocks._fields]
        + [f"instances.{name}" for name in InstanceTable._fields]
        + ["frame_index"]
    )


def _leaf(state: MapState, key: str):
    parts = key.split(".")
    value = state
    for part in parts:
        value = getattr(value, part)
    return value


def _layout_of(state: MapState) -> MapConfig:
    """A config with the state's layout (block size, slots, table sizes): enough for the initial rows."""
    blocks, table = state.blocks, state.instances
    voxels, slots = blocks.instance_id.shape[1:]
    block_size = round(voxels ** (1 / 3))
    return MapConfig(
        block_size=block_size,
        instance_slots=int(slots),
        block_capacity=int(blocks.tsdf.shape[0]),
        instance_capacity=int(table.valid.shape[0]),
        num_classes=int(table.label_evidence.shape[1]),
        num_open_labels=int(table.open_label_histogram.shape[1]),
    )


@functools.lru_cache(maxsize=16)
def _initial_rows(config: MapConfig) -> dict[str, np.ndarray]:
    """The initial value of one pool row of each pool array (from a two-slot pool of the same layout)."""
    tiny = init_map_state(dataclasses.replace(config, block_capacity=2, grid_shape=(1, 1, 1), instance_capacity=1))
    rows = {name: np.asarray(getattr(tiny.blocks, name))[0] for name in POOL_FIELDS}
    for row in rows.values():
        row.setflags(write=False)
    return rows


def state_to_arrays(
    state: MapState, map_config: MapConfig | None = None, check_unallocated: bool = True
) -> dict[str, np.ndarray]:
    """The state as host arrays: the pool's allocated rows and scratch row, every other array whole.

    Args:
      state: the map (device or host arrays).
      map_config: its config (optional: the layout is also read off the array shapes).
      check_unallocated: verify that the unallocated pool rows are at their initial values; a pool array
        for which this fails is saved whole (off: trust the invariant and save the allocated rows).

    Returns:
      `{key: np.ndarray}` (see the module docstring for the keys), each array a copy of its own.
    """
    return {key: value.copy() for key, value in state_arrays(state, map_config, check_unallocated)}


def state_arrays(
    state: MapState, map_config: MapConfig | None = None, check_unallocated: bool = True
) -> Iterator[tuple[str, np.ndarray]]:
    """`state_to_arrays`' items one at a time, as views of the state's host arrays (a writer that stores each
    before asking for the next holds one array at a time; the state must not change meanwhile)."""
    map_config = map_config or _layout_of(state)
    n = int(state.blocks.num_blocks)
    capacity = map_config.block_capacity
    if not 0 <= n < capacity:
        raise ValueError(f"num_blocks {n} outside [0, {capacity - 1})")
    initial = _initial_rows(map_config)
    for key in _keys():
        if key in UNSAVED_FILL:
            continue
        value = np.asarray(jax.device_get(_leaf(state, key)))
        name = key.split(".")[-1]
        if key.startswith("blocks.") and name in POOL_FIELDS:
            if value.shape[0] != capacity:
                raise ValueError(f"{key} has {value.shape[0]} slots, the config says {capacity}")
            unallocated = value[n : capacity - 1]
            if check_unallocated and not np.array_equal(unallocated, np.broadcast_to(initial[name], unallocated.shape)):
                yield key, value  # the invariant does not hold here: keep every slot
                continue
            yield key, value[:n]
            yield key + SCRATCH_SUFFIX, value[capacity - 1 :]
        else:
            yield key, value


def _instance_bits(arrays: dict, n: int, shape) -> np.ndarray:
    """`VoxelBlocks.instance_bits` of the saved ids (the allocated rows `[0, n)`; nothing else holds ids)."""
    ids = np.asarray(arrays["blocks.instance_id"])[:n].reshape(n, -1).astype(np.int64)
    bits = np.zeros(shape, bool)
    block, at = np.nonzero(ids >= 0)
    bits[block, ids[block, at] % shape[1]] = True
    return bits


def state_from_arrays(arrays: dict[str, np.ndarray], map_config: MapConfig, device: bool = True) -> MapState:
    """The `MapState` of `state_to_arrays(state, map_config)`: pool rows padded back with initial values.

    Shapes and dtypes are checked against `init_map_state(map_config)`; a mismatch (a file written for
    another config or another version of the engine) is a ValueError naming the array.

    Args:
      arrays: as returned by `state_to_arrays` (or read by `fmfusion_jax.mapping.map_file.read_state_file`).
      map_config: the config the state was saved with.
      device: return JAX arrays (True) or NumPy arrays (False).
    """
    expected = jax.eval_shape(lambda: init_map_state(map_config))
    capacity = map_config.block_capacity
    initial = _initial_rows(map_config)
    known = set(_keys())
    unknown = sorted(k for k in arrays if k.removesuffix(SCRATCH_SUFFIX) not in known)
    if unknown:
        raise ValueError(f"unknown map state arrays {unknown}")
    n = int(np.asarray(arrays["blocks.num_blocks"])) if "blocks.num_blocks" in arrays else -1
    if not 0 <= n < capacity:
        raise ValueError(f"blocks.num_blocks {n} outside [0, {capacity - 1}) (pool of {capacity} slots)")
    leaves: dict[str, np.ndarray] = {}
    for key in _keys():
        spec = _leaf(expected, key)
        if key == "blocks.origin_block" and key not in arrays:  # a map saved before the state carried its origin
            arrays = {**arrays, key: np.asarray(map_config.origin_block, np.int32)}
        if key in UNSAVED_FILL or (key in MISSING_FILL and key not in arrays):
            fill = UNSAVED_FILL[key] if key in UNSAVED_FILL else MISSING_FILL[key]
            arrays = {**arrays, key: np.full(spec.shape, fill, spec.dtype)}
        if key == "blocks.instance_bits" and key not in arrays:  # a map saved before the blocks kept them
            arrays = {**arrays, key: _instance_bits(arrays, n, spec.shape)}
        if key not in arrays:
            raise ValueError(f"map state array {key} is missing")
        value = np.asarray(arrays[key])
        name = key.split(".")[-1]
        if key.startswith("blocks.") and name in POOL_FIELDS and key + SCRATCH_SUFFIX in arrays:
            scratch = np.asarray(arrays[key + SCRATCH_SUFFIX])
            if value.shape[0] != n or scratch.shape[0] != 1:
                raise ValueError(
                    f"{key}: {value.shape[0]} allocated rows and {scratch.shape[0]} scratch rows, expected {n} and 1"
                )
            full = np.empty(spec.shape, spec.dtype)
            full[:] = initial[name]
            full[:n] = value
            full[capacity - 1 :] = scratch
            value = full
        if name == "color" and value.dtype == np.float32 and spec.dtype != np.float32:
            value = value.astype(spec.dtype)  # a map saved before colour was stored in half precision
        if name == "instance_id" and value.dtype == np.int32 and spec.dtype == np.int16:
            if value.size and (value.min() < -1 or value.max() >= map_config.instance_capacity):
                raise ValueError(f"map state array {key} holds ids outside [-1, {map_config.instance_capacity})")
            value = value.astype(spec.dtype)  # a map saved before ids were stored in 16 bits
        if value.shape != spec.shape or value.dtype != spec.dtype:
            raise ValueError(
                f"map state array {key} is {value.dtype}{list(value.shape)}, the config needs {spec.dtype}{list(spec.shape)}"
            )
        leaves[key] = value
    convert = jnp.asarray if device else (lambda x: x)

    def group(cls, prefix):
        return cls(**{name: convert(leaves[f"{prefix}.{name}"]) for name in cls._fields})

    return MapState(
        blocks=group(VoxelBlocks, "blocks"),
        instances=group(InstanceTable, "instances"),
        frame_index=convert(leaves["frame_index"]),
    )


__all__ = ["state_arrays", "state_to_arrays", "state_from_arrays", "POOL_FIELDS", "SCRATCH_SUFFIX"]
