"""Growing a map into a larger layout: a wider block index, a bigger block pool, a longer instance table.

Capacities are static (the jit's shapes), so a map that outgrows them is copied into a larger state once and
the steps recompile for the new shapes. Growth by doubling keeps the number of recompiles logarithmic in the
map's final size. The voxel lattice never moves: grid origins are multiples of the block length
(`MapConfig.for_bounds`), so a wider index only shifts block coordinates by whole blocks, and every voxel,
slot and instance id keeps its value.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import MapState, init_instance_table, init_voxel_blocks

#: Fields of `MapConfig` that `grow_state` may change; every other field must be equal.
GROWABLE_FIELDS = ("grid_origin", "grid_shape", "block_capacity", "instance_capacity")


def block_offset(old: MapConfig, new: MapConfig) -> np.ndarray:
    """int[3]: where block `(0, 0, 0)` of `old`'s index lies in `new`'s (whole blocks; raises if the lattices
    differ or `new` does not cover `old`)."""
    shift = (np.asarray(old.grid_origin) - np.asarray(new.grid_origin)) / old.block_length
    offset = np.round(shift).astype(np.int64)
    if np.any(np.abs(shift - offset) > 1e-6):
        raise ValueError(f"grid origins {old.grid_origin} and {new.grid_origin} are not whole blocks apart")
    if np.any(offset < 0) or np.any(offset + np.asarray(old.grid_shape) > np.asarray(new.grid_shape)):
        raise ValueError(
            f"the new block index {new.grid_shape} at {new.grid_origin} does not cover the old "
            f"{old.grid_shape} at {old.grid_origin}"
        )
    return offset


def grow_state(state: MapState, old: MapConfig, new: MapConfig) -> MapState:
    """The map `state` (made with `old`) in the layout of `new`: same lattice, capacities at least `old`'s.

    Pool rows `[0, num_blocks)` and table rows keep their positions; the old scratch slot and every new row
    start at their initial values. Counters are kept. Not jitted (a rare, host-driven step).
    """
    fixed = {f.name for f in dataclasses.fields(MapConfig)} - set(GROWABLE_FIELDS)
    changed = [name for name in sorted(fixed) if getattr(old, name) != getattr(new, name)]
    if changed:
        raise ValueError(f"grow_state changes only {GROWABLE_FIELDS}; these differ: {changed}")
    if new.block_capacity < old.block_capacity or new.instance_capacity < old.instance_capacity:
        raise ValueError("grow_state cannot shrink the block pool or the instance table")
    offset = block_offset(old, new)
    blocks, table = state.blocks, state.instances
    b_old, k_old = old.block_capacity, old.instance_capacity

    fresh = init_voxel_blocks(new)
    allocated = jnp.arange(b_old) < blocks.num_blocks  # excludes the old scratch slot (num_blocks < B)

    def pool(name: str):
        old_rows, new_rows = getattr(blocks, name), getattr(fresh, name)
        mask = allocated.reshape((-1,) + (1,) * (old_rows.ndim - 1))
        return new_rows.at[:b_old].set(jnp.where(mask, old_rows, new_rows[:b_old]))

    sx, sy, sz = old.grid_shape
    ox, oy, oz = (int(x) for x in offset)
    index = fresh.block_index.at[ox : ox + sx, oy : oy + sy, oz : oz + sz].set(blocks.block_index)
    coords = jnp.where(allocated[:, None], blocks.block_coords + jnp.asarray(offset, jnp.int32), -1)
    grown_blocks = fresh._replace(
        block_index=index,
        block_coords=fresh.block_coords.at[:b_old].set(coords),
        num_blocks=blocks.num_blocks,
        tsdf=pool("tsdf"),
        weight=pool("weight"),
        color=pool("color"),
        instance_id=pool("instance_id"),
        instance_weight=pool("instance_weight"),
        instance_bits=pool("instance_bits"),
        geometry_stale=pool("geometry_stale"),
        up_heights=blocks.up_heights,
        cell_owner=pool("cell_owner"),
        dropped_blocks=blocks.dropped_blocks,
        out_of_bounds=blocks.out_of_bounds,
        touched_overflow=blocks.touched_overflow,
    )

    empty = init_instance_table(new)
    rows = {
        name: getattr(empty, name).at[:k_old].set(getattr(table, name))
        for name in (
            "valid",
            "label_evidence",
            "open_label_histogram",
            "observations",
            "missed",
            "voxel_count",
            "created_frame",
            "last_seen_frame",
            "census_counts",
        )
    }
    pairs = {
        name: getattr(empty, name).at[:k_old, :k_old].set(getattr(table, name))
        for name in ("covered", "separated", "census_overlap")
    }
    scalars = {name: getattr(table, name) for name in ("overflow", "census_overfull", "census_valid")}
    grown_table = empty._replace(**rows, **pairs, **scalars)
    return MapState(grown_blocks, grown_table, state.frame_index)


def bounds_block_range(config: MapConfig) -> tuple[np.ndarray, np.ndarray]:
    """`(lo, hi)` int[3] block coordinates on the world lattice (origin 0) that the index covers, hi exclusive."""
    lo = np.asarray(config.origin_block, np.int64)
    return lo, lo + np.asarray(config.grid_shape, np.int64)


def config_for_block_range(config: MapConfig, lo: np.ndarray, hi: np.ndarray) -> MapConfig:
    """`config` with its index covering world-lattice blocks `[lo, hi)` (ints, hi exclusive)."""
    lo, hi = np.asarray(lo, np.int64), np.asarray(hi, np.int64)
    return dataclasses.replace(
        config, grid_origin=tuple((lo * config.block_length).tolist()), grid_shape=tuple(np.maximum(hi - lo, 1).tolist())
    )


__all__ = ["GROWABLE_FIELDS", "block_offset", "grow_state", "bounds_block_range", "config_for_block_range"]
