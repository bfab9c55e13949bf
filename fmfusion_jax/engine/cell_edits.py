"""Pool-wide edits of the instance slots over the occupied cells: renaming instance ids (a merge, a removal) and
instance-geometry fusion (slots the global surface does not support emptied). The passes and the census they
share are `occupied_cells`'.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from fmfusion_jax.engine import _geometry as geo
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.occupied_cells import (
    KeptCensus,
    blocks_holding,
    cell_rows,
    fold_listed,
    fold_occupied,
    gather_cells,
    known_ids,
    segment_count,
    set_instance_bits,
    tag_holds,
    update_kept_census,
)
from fmfusion_jax.engine.state import VoxelBlocks

# --------------------------------------------------------------------------------------------------
# Pool-wide edits: the same pass, a first inner loop flags the cells that change, a second rewrites
# them (row gather, row scatter into the carried arrays). Cells without instances never change, so
# the work follows the occupied (and then the changed) cells, not the pool.


def _remap_rows(ids, weights, new_id):
    k = new_id.shape[0]
    known = (ids >= 0) & (ids < k)
    mapped = jnp.where(known, new_id[jnp.clip(ids, 0, k - 1)], -1)
    weights = jnp.where(mapped >= 0, weights, 0.0)
    num_slots = ids.shape[-1]
    id_list = [mapped[..., s] for s in range(num_slots)]
    w_list = [weights[..., s] for s in range(num_slots)]
    for s in range(1, num_slots):
        for t in range(s):
            duplicate = (id_list[s] >= 0) & (id_list[s] == id_list[t])
            w_list[t] = w_list[t] + jnp.where(duplicate, w_list[s], 0.0)
            w_list[s] = jnp.where(duplicate, 0.0, w_list[s])
            id_list[s] = jnp.where(duplicate, -1, id_list[s])
    return jnp.stack(id_list, axis=-1), jnp.stack(w_list, axis=-1)


def _edit_cells(
    blocks: VoxelBlocks, config: MapConfig, changes, edit, extra, active=None, listed=None, kept=None, wanted=None, visit=None
):
    """Rewrites the instance slots of the occupied cells that `changes` flags.

    `changes(ids int32[C, 8S], index) -> bool[C]`; `edit(ids int32[C, 8, S], weights float32[C, 8, S],
    index, extra) -> (ids, weights, extra)` on the flagged cells (padding rows: ids -1, weights 0).
    `active` (traced bool, optional): false makes the pass a no-op costing nothing (its loops run zero
    times; a `lax.cond` around a pass that edits the pool cost ~13 ms on the CPU even when skipped).
    `listed` (optional `(cells int32[L], tags int32[L], count, valid bool[], flag_of)`): when `valid`,
    the cells to rewrite are those of the list whose tags pass `flag_of(tags) -> bool[C]`, found without
    reading the pool (both loops are compiled, one runs).
    `kept` (optional `KeptCensus`): brought up to date with the rewritten cells.
    `wanted` (optional bool[K]): only cells holding a flagged id change; the pass then visits only the
    blocks whose `instance_bits` may hold one. The ids written are set in `instance_bits` either way.
    `visit` (optional bool[B], without `wanted`): only the cells of these blocks may change; only they are visited.
    Returns `(blocks, extra, kept)`.
    """
    shape = blocks.instance_id.shape
    num_slots = shape[-1]
    cells_per_block = shape[1] // 8

    def cell_step(index, ok, carry):  # ids widened to int32 for `changes` and `edit`, stored narrow
        entries = gather_cells(cell_rows(carry[0]), index, ok, -1).astype(jnp.int32)
        flag = changes(entries, index)
        if wanted is not None:  # the visited blocks' bits are set again: from the cells that stay as they are
            ids, weights, bits, extra, kept = carry
            bits = set_instance_bits(bits, jnp.where(ok, index, 0) // cells_per_block, entries, ok & ~flag)
            carry = (ids, weights, bits, extra, kept)
        return carry, flag, None

    def flagged_step(index, ok, carry):
        ids, weights, bits, extra, kept = carry
        id_rows, w_rows = cell_rows(ids), cell_rows(weights)
        old_ids = gather_cells(id_rows, index, ok, -1).astype(jnp.int32).reshape(-1, 8, num_slots)
        old_w = gather_cells(w_rows, index, ok, 0.0).reshape(-1, 8, num_slots)
        new_ids, new_w, extra = edit(old_ids, old_w, index, extra)
        # the new rows are made before the scatters: fused into a scatter (as XLA does on a GPU), the gather of the
        # old rows would read the array being written, and XLA would copy the whole pool array twice per step
        new_ids, new_w = jax.lax.optimization_barrier((new_ids, new_w))
        rows = old_ids.shape[0]
        if kept is not None:
            kept = update_kept_census(kept, old_ids.reshape(rows, -1), new_ids.reshape(rows, -1), ok, config)
        bits = set_instance_bits(bits, jnp.where(ok, index, 0) // cells_per_block, new_ids.reshape(rows, -1), ok)
        target = jnp.where(ok, index, id_rows.shape[0])
        id_rows = id_rows.at[target].set(new_ids.reshape(-1, id_rows.shape[1]).astype(id_rows.dtype), mode="drop")
        w_rows = w_rows.at[target].set(new_w.reshape(-1, w_rows.shape[1]), mode="drop")
        return id_rows.reshape(shape), w_rows.reshape(shape), bits, extra, kept

    active = jnp.asarray(True) if active is None else active
    if listed is not None and listed[0].shape[0] == 0:  # an empty list (`cell_list_capacity` 0): no list
        listed = None
    carry = (blocks.instance_id, blocks.instance_weight, blocks.instance_bits, extra, kept)
    scan = active
    if listed is not None:
        cells, tags, count, valid, flag_of = listed
        carry = fold_listed(cells, tags, jnp.where(active & valid, count, 0), config, flag_of, flagged_step, carry)
        scan = active & ~valid
    if wanted is None and visit is None:
        num_blocks, block_list = jnp.where(scan, blocks.num_blocks, 0), None
    else:  # the blocks to visit, listed in pool order
        if wanted is not None:  # those that may hold a wanted id (most steps rename no held id: then none)
            flagged = jax.lax.cond(
                jnp.any(wanted) & scan,
                lambda: blocks_holding(blocks.instance_bits, wanted, blocks.num_blocks),
                lambda: jnp.zeros((shape[0],), bool),
            )
        else:
            flagged = visit & scan & (jnp.arange(shape[0]) < blocks.num_blocks)
        empty = jnp.full((shape[0],), -1, jnp.int32)
        block_list, num_blocks = geo.compact(empty, jnp.int32(0), flagged, jnp.arange(shape[0], dtype=jnp.int32))

    def clear_bits(here, ok, carry):  # the visited blocks' bits, set again from the ids they hold (bits of ids
        # gone from a block do not flag it forever)
        ids, weights, bits, extra, kept = carry
        bits = bits.at[jnp.where(ok, here, shape[0])].set(False, mode="drop")
        return ids, weights, bits, extra, kept

    folded = fold_occupied(
        lambda carry: carry[0],
        num_blocks,
        config,
        cell_step,
        flagged_step,
        carry,
        block_list=block_list,
        long_list=visit is not None,
        enter_blocks=clear_bits if wanted is not None else None,
    )
    ids, weights, bits, extra, kept = folded[0]
    return blocks._replace(instance_id=ids, instance_weight=weights, instance_bits=bits), extra, kept


def remap_cells(blocks: VoxelBlocks, new_id, config: MapConfig, active=None, listed=None, kept=None, held=None):
    """`remap_instances`, also returning int32[K]: per id, the voxels where it appeared (a representative
    taking over a merged instance's voxel that it did not hold), for updating voxel counts, and `kept`
    (a `KeptCensus` or None) brought up to date. `active`, `listed`: see `_edit_cells`. `held` (bool[K],
    optional: the ids that voxels hold, e.g. from the census' counts): without a list, visit only the
    blocks whose `instance_bits` name a renamed id that is held (for pools whose bits the steps kept; a
    pool written otherwise may lack them).
    Returns `(blocks, gained, kept)`."""
    new_id = jnp.asarray(new_id, jnp.int32)
    k = new_id.shape[0]
    changed = new_id != jnp.arange(k, dtype=jnp.int32)

    def changes(ids, index):
        return jnp.any(known_ids(ids, k) & changed[jnp.clip(ids, 0, k - 1)], axis=-1)

    if listed is not None:
        listed = tuple(listed) + (lambda tags: tag_holds(tags, changed),)

    def edit(ids, weights, index, gained):
        new_ids, new_w = _remap_rows(ids, weights, new_id)
        num_slots = ids.shape[-1]
        for s in range(num_slots):
            appeared = new_ids[..., s] >= 0
            for t in range(num_slots):
                appeared = appeared & (new_ids[..., s] != ids[..., t])
            gained = gained + segment_count(jnp.where(appeared, new_ids[..., s], -1), k)
        return new_ids, new_w, gained

    gained = jnp.zeros((k + 1,), jnp.int32)
    wanted = None if held is None else changed & held
    blocks, gained, kept = _edit_cells(blocks, config, changes, edit, gained, active, listed, kept, wanted)
    return blocks, gained[:k], kept


def _remap_instances(blocks: VoxelBlocks, new_id, config: MapConfig | None = None) -> VoxelBlocks:
    return remap_cells(blocks, new_id, MapConfig() if config is None else config)[0]


@functools.partial(jax.jit, static_argnames=("config",))
def remap_instances(blocks: VoxelBlocks, new_id, config: MapConfig | None = None) -> VoxelBlocks:
    """Rename instance ids in every voxel: `id -> new_id[id]` (a gather), e.g. to apply merges.

    Args:
      blocks: the pool.
      new_id: int32 `(K,)`: the representative of each id (itself if unchanged), -1 to delete it.
      config: static, optional: only its loop chunk sizes are used (`pool_chunk_blocks`, `cell_chunk`).

    Returns:
      The pool where slots of deleted ids are empty and, where two slots of a voxel now hold the
      same id, their weights are summed into the first and the other is emptied. Only the cells
      holding an id that changes are rewritten.
    """
    return _remap_instances(blocks, new_id, config)


def _fuse_cells(blocks: VoxelBlocks, config: MapConfig, min_weight, surface_band, kept=None, only_stale: bool = False):
    num_slots = blocks.instance_id.shape[-1]
    band = jnp.asarray(surface_band, jnp.float32) / config.sdf_trunc  # in stored (normalised) units
    tsdf_rows, weight_rows = cell_rows(blocks.tsdf), cell_rows(blocks.weight)

    def supported(index):  # bool[C, 8 * S]: the slot's voxel is on the global surface
        ok = index >= 0
        tsdf = gather_cells(tsdf_rows, index, ok, 1.0)
        weight = gather_cells(weight_rows, index, ok, 0.0)
        keep = (weight >= min_weight) & (jnp.abs(tsdf) <= band)
        return jnp.repeat(keep, num_slots, axis=1)

    def changes(ids, index):
        return jnp.any((ids >= 0) & ~supported(index), axis=-1)

    def edit(ids, weights, index, extra):
        keep = supported(index).reshape(ids.shape)
        return jnp.where(keep, ids, -1), jnp.where(keep, weights, 0.0), extra

    # only the stale blocks: elsewhere every id was supported at the last pass, and neither the TSDF nor the
    # ids have changed since (a renaming moves ids between instances in the same voxels)
    visit = blocks.geometry_stale if only_stale else None
    blocks, _, kept = _edit_cells(blocks, config, changes, edit, jnp.zeros((), jnp.int32), kept=kept, visit=visit)
    return blocks._replace(geometry_stale=jnp.zeros_like(blocks.geometry_stale)), kept


def fuse_cells(blocks: VoxelBlocks, config: MapConfig, min_weight, kept: KeptCensus, surface_band=None):
    """`fuse_instance_geometry` of the blocks marked `geometry_stale` (then none is), also returning `kept` brought
    up to date: `(blocks, kept)`. The map's own pass: exact when every call has the same thresholds (as the
    steps' do), since a block that is not stale holds only ids that were supported at the last call."""
    band = config.voxel_size if surface_band is None else surface_band
    return _fuse_cells(blocks, config, min_weight, band, kept, only_stale=True)


def _fuse_instance_geometry(blocks: VoxelBlocks, config: MapConfig, min_weight, surface_band) -> VoxelBlocks:
    return _fuse_cells(blocks, config, min_weight, surface_band)[0]


@functools.partial(jax.jit, static_argnames=("config",))
def fuse_instance_geometry(blocks: VoxelBlocks, config: MapConfig, min_weight=1.0, surface_band=None) -> VoxelBlocks:
    """Instance-geometry fusion (paper, Sec. IV-B): keep instance slots only on the global surface.

    A voxel supports instances if its global TSDF weight is at least `min_weight` and its centre is
    within `surface_band` metres of the fused surface (`|tsdf| * sdf_trunc <= surface_band`; default
    one voxel: the zero crossing passes through or next to the voxel). Slots of other voxels are
    emptied. Only the occupied cells are visited (of every block: after this pass none is `geometry_stale`),
    and only those that change are rewritten.
    """
    if surface_band is None:
        surface_band = config.voxel_size
    return _fuse_instance_geometry(blocks, config, min_weight, surface_band)


__all__ = ["fuse_cells", "fuse_instance_geometry", "remap_cells", "remap_instances"]
