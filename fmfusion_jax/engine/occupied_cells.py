"""Passes over the occupied voxel cells and the census they make: instance voxel counts and overlaps, kept in
the table between merge steps (jitted, fixed shapes; the slots themselves are written per pixel by
`instance_volume`, renamed and fused against the surface by `cell_edits`).

**Inflated overlap**: the paper inflates an instance's voxel grid by scaling each voxel's edge 2x.
Here the inflated volume of `a` is the set of 2x2x2 coarse cells (global voxel coordinate // 2)
holding any voxel of `a`; `b`'s voxel lies inside `a`'s inflated volume iff its coarse cell does.
This dilates by half a voxel on average, like the 2x scaling, and needs no neighbour search: the
2x2x2 cells are contiguous in the pool layout.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from fmfusion_jax.engine import _geometry as geo
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import VoxelBlocks


class InstanceCounts(NamedTuple):
    """A count result together with what the fixed capacities left out."""

    counts: jax.Array  # int32[K] (voxel counts) or int32[K, K] (overlap counts)
    dropped_cells: jax.Array  # int32[]: occupied 2x2x2 cells not counted (capacity, or > ids_per_cell)


# --------------------------------------------------------------------------------------------------
# Passes over the occupied cells. Counting and editing instance slots only concern the occupied 2x2x2
# cells (a cell = 8 contiguous voxels, see `state`): 173k of the 1.2M allocated cells of scene0000_00
# after 300 frames. Each pass is two nested loops whose trip counts follow the data: over the allocated
# blocks (read in order, `pool_chunk_blocks` at a time), whose occupied cells are compacted into a
# chunk-local list, then over that list (`cell_chunk` cells at a time), gathering each cell's `8 * S`
# ids as one row while the chunk is still in cache. Pool-sized lists (16 MB for the default pool) are
# avoided: in a first version, filling two of them cost ~5 ms per call.
#
# Measured on that map (2-core CPU, K = 1024): 60% of the occupied cells hold a single instance and
# 29% two. Each cell is summarised elementwise (smallest and largest id, their voxel counts), so
# that the cells with at most two distinct ids ("simple") are counted with 2 scatter updates each
# instead of `8 * S` (voxel counts) and `8 * S^2` or `ids_per_cell^2` (overlaps). The "crowded"
# cells (3+ distinct ids, 11%) are listed and counted entry by entry in a second inner loop.
# Gathering cells that are not in cache costs ~50 ns each (memory latency), so the refinement's
# census also keeps each occupied cell's ids in short (`_cell_tag`), and its renaming finds the cells
# to rewrite from those tags instead of reading the pool again.


def cell_rows(array: jax.Array) -> jax.Array:
    """A pool array `[B, V, ...]` viewed as one row per 2x2x2 cell: `[B * V / 8, 8 * prod(...)]` (free)."""
    b, v = array.shape[:2]
    return array.reshape(b * v // 8, -1)


def gather_cells(rows: jax.Array, index: jax.Array, ok: jax.Array, fill) -> jax.Array:
    """Rows of `rows` at `index` where `ok`, `fill` elsewhere (one row gather)."""
    got = jnp.take(rows, jnp.where(ok, index, 0), axis=0, mode="clip")
    return jnp.where(ok[:, None], got, jnp.asarray(fill, rows.dtype))


def fold_occupied(
    ids_of,
    num_blocks,
    config: MapConfig,
    cell_step,
    flagged_step,
    carry,
    capacity=None,
    record: int = 0,
    block_list=None,
    long_list: bool = False,
    enter_blocks=None,
):
    """Runs over the occupied cells (any instance slot set) of the allocated blocks, in pool order (or of the
    blocks `block_list`: int32[L], the first `num_blocks` of them, when given).

    Args:
      ids_of: `carry -> int32[B, V, S]`, the instance ids to scan (from the carry when the steps edit them).
      num_blocks: allocated blocks (traced).
      config: static: `pool_chunk_blocks` blocks per outer step, `cell_chunk` cells per inner step.
      cell_step: `(index int32[C], ok bool[C], carry) -> (carry, flag bool[C] or None, tag int32[C] or
        None)` for every occupied cell (`index` = flat cell index, `ok` false for padding).
      flagged_step: `(index, ok, carry) -> carry`, run in the same outer step over the cells that
        `cell_step` flagged (None: no second loop).
      carry: the state threaded through the steps.
      capacity: only the first `capacity` occupied cells of the pool are visited (None: all).
      record: static: also list the visited cells and their tags, for up to `record` cells.
      long_list: static: `block_list` may list many blocks: steps of `pool_chunk_blocks` blocks, as the pool's.
      enter_blocks: optional `(blocks int32[chunk], ok bool[chunk], carry) -> carry`, with `block_list`: run on
        each step's blocks before their cells (every cell of a block is visited in the same step).

    Returns:
      `(carry, occupied, listed)`: the final carry, the number of occupied cells found (all of them)
      and, with `record`, `(cells int32[L], tags int32[L])` (L = record + a step), valid in their first
      `min(occupied, capacity)` entries when that is at most `record` (else None).
    """
    pool_blocks, v_per_block, num_slots = ids_of(carry).shape
    cells_per_block = v_per_block // 8
    if block_list is None:
        chunk = max(1, min(config.pool_chunk_blocks, pool_blocks))
    else:  # a short list: steps of one cell chunk's blocks (a long one: of the pool's)
        chunk = max(1, min(config.pool_chunk_blocks if long_list else config.cell_chunk // cells_per_block, block_list.shape[0]))
    span = chunk * cells_per_block
    sub = max(1, min(config.cell_chunk, span))
    # flagged cells are a small share of the occupied ones: shorter steps waste less on padding
    flagged_sub = max(1, sub // 8)
    local = jnp.arange(span, dtype=jnp.int32)

    def inner(buffer, count, step, carry, sub=sub):
        def body(start, fresh, carry):
            return step(jax.lax.dynamic_slice_in_dim(buffer, start, sub), fresh, carry, start)

        return geo.fold_chunks(count, sub, span, body, carry)

    def first_step(index, ok, c, start):
        carry, flagged_list, flagged, tags = c
        carry, flag, tag = cell_step(index, ok, carry)
        if flagged_step is not None:
            flagged_list, flagged = geo.compact(flagged_list, flagged, ok & flag, index)
        if record:  # the step's tags at its place in the chunk's list (rows not `ok` keep theirs)
            before = jax.lax.dynamic_slice_in_dim(tags, start, sub)
            tags = jax.lax.dynamic_update_slice_in_dim(tags, jnp.where(ok, tag, before), start, 0)
        return carry, flagged_list, flagged, tags

    def outer(start, fresh, state):
        occupied_list, flagged_list, tags, seen, carry, listed = state
        if block_list is None:
            ids = jax.lax.dynamic_slice_in_dim(ids_of(carry), start, chunk)
            first_cells = start * cells_per_block + local
        else:
            here = jax.lax.dynamic_slice_in_dim(block_list, start, chunk)
            if enter_blocks is not None:
                carry = enter_blocks(here, fresh & (here >= 0), carry)
            ids = jnp.take(ids_of(carry), jnp.where(fresh, here, 0), axis=0, mode="clip")
            first_cells = (here[:, None] * cells_per_block + jnp.arange(cells_per_block, dtype=jnp.int32)).reshape(-1)
        occupied = jnp.any(ids.reshape(chunk, cells_per_block, 8 * num_slots) >= 0, axis=-1) & fresh[:, None]
        occupied_list, found = geo.compact(occupied_list, 0, occupied, first_cells)
        visit = found if capacity is None else jnp.clip(capacity - seen, 0, found)
        carry, flagged_list, flagged, tags = inner(occupied_list, visit, first_step, (carry, flagged_list, jnp.int32(0), tags))
        if flagged_step is not None:
            carry = inner(flagged_list, flagged, lambda i, ok, c, s: flagged_step(i, ok, c), carry, flagged_sub)
        if record:  # past `record` the lists are invalid anyway: the writes may then land anywhere
            at = jnp.minimum(seen, record)
            listed = (
                jax.lax.dynamic_update_slice_in_dim(listed[0], occupied_list, at, 0),
                jax.lax.dynamic_update_slice_in_dim(listed[1], tags, at, 0),
            )
        return occupied_list, flagged_list, tags, seen + found, carry, listed

    empty = jnp.full((span,), -1, jnp.int32)
    size = record + span if record else 1
    listed = (jnp.full((size,), -1, jnp.int32), jnp.zeros((size,), jnp.int32))
    state = (empty, empty, jnp.zeros((span if record else 1,), jnp.int32), jnp.zeros((), jnp.int32), carry, listed)
    total = pool_blocks if block_list is None else block_list.shape[0]
    _, _, _, seen, carry, listed = geo.fold_chunks(num_blocks, chunk, total, outer, state)
    return carry, seen, (listed if record else None)


def fold_listed(cells, tags, count, config: MapConfig, flag_of, flagged_step, carry):
    """Over a list of cells (`cells` int32[L] valid in `[0, count)`, with their `tags`): runs
    `flagged_step(index, ok, carry)` on the cells for which `flag_of(tags int32[C]) -> bool[C]` holds
    (listed first, so that the steps are full)."""
    sub = max(1, min(config.cell_chunk, cells.shape[0]))
    flagged_sub = max(1, sub // 8)

    def pick(start, fresh, state):
        flagged_list, flagged = state
        index = jax.lax.dynamic_slice_in_dim(cells, start, sub)
        flag = fresh & (index >= 0) & flag_of(jax.lax.dynamic_slice_in_dim(tags, start, sub))
        return geo.compact(flagged_list, flagged, flag, index)

    flagged_list, flagged = geo.fold_chunks(
        count, sub, cells.shape[0], pick, (jnp.full(cells.shape, -1, jnp.int32), jnp.int32(0))
    )

    def step(start, fresh, carry):
        return flagged_step(jax.lax.dynamic_slice_in_dim(flagged_list, start, flagged_sub), fresh, carry)

    return geo.fold_chunks(flagged, flagged_sub, cells.shape[0], step, carry)


def known_ids(ids, k: int):
    return (ids >= 0) & (ids < k)


class _CellSummary(NamedTuple):
    lo: jax.Array  # int32[C]: smallest id of the cell (k if none)
    hi: jax.Array  # int32[C]: largest id if different from lo, else k
    n_lo: jax.Array  # int32[C]: voxels holding lo
    n_hi: jax.Array  # int32[C]: voxels holding hi (0 if hi == k)
    crowded: jax.Array  # bool[C]: 3 or more distinct ids
    both: jax.Array  # int32[C]: voxels holding two or more ids (both lo and hi when not crowded)


def _summarize_cells(entries: jax.Array, k: int, num_slots: int) -> _CellSummary:
    """Per cell (row of `8 * S` ids, voxel-major), written out column by column so that XLA
    vectorises over the cells (a reduction over the short row axis was 1.5x slower)."""
    cols = [entries[:, j] for j in range(entries.shape[1])]
    known = [known_ids(c, k) for c in cols]
    lo = functools.reduce(jnp.minimum, [jnp.where(q, c, k) for c, q in zip(cols, known)])
    hi = functools.reduce(jnp.maximum, [jnp.where(q, c, -1) for c, q in zip(cols, known)])
    hi = jnp.where(hi > lo, hi, k)
    n_lo = sum(((c == lo) & q).astype(jnp.int32) for c, q in zip(cols, known))
    n_hi = sum(((c == hi) & q).astype(jnp.int32) for c, q in zip(cols, known))
    n = sum(q.astype(jnp.int32) for q in known)
    per_voxel = [sum(known[v * num_slots + s].astype(jnp.int32) for s in range(num_slots)) for v in range(8)]
    both = sum((p >= 2).astype(jnp.int32) for p in per_voxel)
    return _CellSummary(lo, hi, n_lo, n_hi, n > n_lo + n_hi, both)


def segment_count(ids: jax.Array, k: int) -> jax.Array:
    """int32[k + 1]: occurrences of each known id in `ids` (unknown ids counted at k)."""
    ids = ids.reshape(-1)
    return jax.ops.segment_sum(jnp.ones(ids.shape, jnp.int32), jnp.where(known_ids(ids, k), ids, k), num_segments=k + 1)


def _plain_cell_pairs(entries: jax.Array, k: int, num_slots: int) -> jax.Array:
    """Per cell, the (a, b) id pairs held by one voxel (diagonal: a itself) as flat indices (k*k: none)."""
    ids = entries.reshape(entries.shape[0], 8, num_slots)
    pairs = [
        jnp.where(known_ids(ids[..., s], k) & known_ids(ids[..., t], k), ids[..., s] * k + ids[..., t], k * k)
        for s in range(num_slots)
        for t in range(num_slots)
    ]
    return jnp.stack(pairs, axis=-1).reshape(-1)


def _inflated_cell_pairs(entries: jax.Array, k: int, d_max: int):
    """Inflated-overlap contributions of each cell: b's voxels in a cell holding a voxel of a, for the
    `d_max` ids of the cell holding the most voxels (ties: first in the cell's entry order).

    Returns `(pair int32[C * d * d] flat index (k*k: none), value int32[C * d * d], distinct int32[C])`.
    """
    n = entries.shape[1]
    d = min(d_max, n)
    same = entries[:, :, None] == entries[:, None, :]
    earlier = jnp.asarray(np.tril(np.ones((n, n), bool), -1))  # earlier[i, j]: j < i
    # distinct ids of the cell (first occurrences) with their voxel counts (an id is in a voxel once)
    first = known_ids(entries, k) & ~jnp.any(same & earlier, axis=-1)
    voxels = jnp.where(first, jnp.sum(same, axis=-1), 0).astype(jnp.int32)
    # the d largest (d rounds of argmax: faster than top_k on CPU)
    tops, ats = [], []
    for _ in range(d):
        at = jnp.argmax(voxels, axis=-1)
        tops.append(jnp.max(voxels, axis=-1))
        ats.append(at)
        voxels = jnp.where(jnp.arange(n) == at[:, None], 0, voxels)
    top, at = jnp.stack(tops, axis=-1), jnp.stack(ats, axis=-1)
    chosen = jnp.take_along_axis(entries, at, axis=-1)
    ok = (top[:, :, None] > 0) & (top[:, None, :] > 0)
    pair = jnp.where(ok, chosen[:, :, None] * k + chosen[:, None, :], k * k)
    value = jnp.broadcast_to(top[:, None, :], pair.shape)
    return pair.reshape(-1), value.reshape(-1), jnp.sum(first, axis=-1)


def _cell_tag(summary: _CellSummary, crowded, k: int) -> jax.Array:
    """A cell's ids in one int32, enough to tell whether a renaming touches it without reading the
    pool: `lo * (k + 1) + hi` for at most two ids (hi = k: one id), negated minus one for 3+ ids (then
    every id lies in [lo, hi])."""
    code = summary.lo * (k + 1) + summary.hi
    return jnp.where(crowded, -1 - code, code)


def tag_holds(tags: jax.Array, wanted: jax.Array) -> jax.Array:
    """bool[C]: the cells whose tag (`_cell_tag`) may hold an id flagged in `wanted` (bool[K]); exact for
    cells of at most two ids, conservative (any flagged id in [lo, hi]) for the others."""
    k = wanted.shape[0]
    crowded = tags < 0
    code = jnp.where(crowded, -1 - tags, tags)
    lo, hi = code // (k + 1), code % (k + 1)
    padded = jnp.concatenate([wanted, jnp.zeros((1,), bool)])  # index k: no id
    below = jnp.concatenate([jnp.zeros((1,), jnp.int32), jnp.cumsum(wanted.astype(jnp.int32))])  # ids < i
    in_range = below[jnp.clip(hi + 1, 0, k)] - below[jnp.clip(lo, 0, k)] > 0
    return jnp.where(crowded, in_range, padded[jnp.clip(lo, 0, k)] | padded[jnp.clip(hi, 0, k)])


class Census(NamedTuple):
    """Result of `census`."""

    counts: jax.Array  # int32[K]: voxels holding each id
    overlap: jax.Array  # int32[K, K] (int32[0, 0] when not asked for)
    occupied: jax.Array  # int32[]: occupied cells of the pool
    overfull: jax.Array  # int32[]: inflated: visited cells with more than overlap_ids_per_cell distinct ids
    dropped_cells: jax.Array  # int32[]: occupied cells beyond the cell capacity (not counted)
    cells: jax.Array  # int32[L]: with `list_cells`, the visited cells if `occupied <= cell_list_capacity`
    tags: jax.Array  # int32[L]: their ids in short (`_cell_tag`)


def census(blocks: VoxelBlocks, config: MapConfig, overlap=None, keep=None, list_cells: bool = False) -> Census:
    """Voxel counts and the pairwise overlaps, in one pass over the occupied cells.

    Args:
      overlap: None (counts only), "inflated", "plain", or a traced bool scalar choosing at run time
        (true: plain, false: inflated; both are compiled, one runs), so that the online refinement
        and the final merge can share one compiled step.
      keep: bool[K], optional: ids outside it are treated as absent from the voxels (as if removed).
      list_cells: static: also list the occupied cells (up to `config.cell_list_capacity`), for
        `remap_cells`.
    """
    k = config.instance_capacity
    list_cells = list_cells and (k + 1) ** 2 < 2**31  # the tags pack two ids into an int32
    num_slots = blocks.instance_id.shape[-1]
    cell_ids = cell_rows(blocks.instance_id)
    d_max = min(config.overlap_ids_per_cell, 8 * num_slots)
    sentinel = k * k
    with_pairs = overlap is not None
    plain: bool | jax.Array | None
    if isinstance(overlap, str):
        if overlap not in ("inflated", "plain"):
            raise ValueError(f"overlap must be None, 'inflated', 'plain' or a bool array, got {overlap!r}")
        plain = overlap == "plain"
    else:
        plain = None if overlap is None else jnp.asarray(overlap, bool)
    if keep is not None:
        keep = jnp.asarray(keep, bool)

    def choose(plain_value, inflated_value):
        if isinstance(plain, bool):
            return plain_value if plain else inflated_value
        return jnp.where(plain, plain_value, inflated_value)

    def entries_at(index, ok):
        entries = gather_cells(cell_ids, index, ok, -1).astype(jnp.int32)  # widened: pair keys need 32 bits
        if keep is not None:
            entries = jnp.where(known_ids(entries, k) & keep[jnp.clip(entries, 0, k - 1)], entries, -1)
        return entries

    pool_blocks, cells_per_block = blocks.instance_id.shape[0], blocks.instance_id.shape[1] // 8

    def cell_step(index, ok, carry):
        simple_counts, crowded_counts, pairs, overfull = carry
        summary = _summarize_cells(entries_at(index, ok), k, num_slots)
        crowded = ok & summary.crowded
        if with_pairs and d_max < 2:  # inflated: two ids are already too many, counted in crowded_step
            crowded = crowded | (ok & (summary.hi < k) & choose(False, True))
        simple = ok & ~crowded
        lo = jnp.where(simple, summary.lo, k)
        hi = jnp.where(simple, summary.hi, k)
        # (separate scatters: concatenating their operands made XLA fuse the whole summary into a slow
        # concatenate loop)
        simple_counts = simple_counts.at[lo].add(summary.n_lo).at[hi].add(summary.n_hi)
        if with_pairs:  # two-id cells add (lo, hi) and (hi, lo); the diagonal comes from the counts
            two = hi < k
            lo_hi = choose(summary.both, summary.n_hi)
            hi_lo = choose(summary.both, summary.n_lo)
            # into the carry (a segment_sum would build a K*K temporary)
            pairs = pairs.at[jnp.where(two, lo * k + hi, sentinel)].add(lo_hi)
            pairs = pairs.at[jnp.where(two, hi * k + lo, sentinel)].add(hi_lo)
        tag = _cell_tag(summary, crowded, k) if list_cells else None
        return (simple_counts, crowded_counts, pairs, overfull), crowded, tag

    def plain_pairs(entries, ok, pairs, overfull):
        return pairs.at[_plain_cell_pairs(entries, k, num_slots)].add(1), overfull

    def inflated_pairs(entries, ok, pairs, overfull):
        where, value, distinct = _inflated_cell_pairs(entries, k, d_max)
        return pairs.at[where].add(value), overfull + jnp.sum(ok & (distinct > d_max), dtype=jnp.int32)

    def crowded_step(index, ok, carry):
        simple_counts, crowded_counts, pairs, overfull = carry
        entries = entries_at(index, ok)
        crowded_counts = crowded_counts + segment_count(entries, k)
        if with_pairs:
            operands = (entries, ok, pairs, overfull)
            if isinstance(plain, bool):
                pairs, overfull = (plain_pairs if plain else inflated_pairs)(*operands)
            else:
                pairs, overfull = jax.lax.cond(plain, plain_pairs, inflated_pairs, *operands)
        return simple_counts, crowded_counts, pairs, overfull

    zero = jnp.zeros((), jnp.int32)
    init = (
        jnp.zeros((k + 1,), jnp.int32),
        jnp.zeros((k + 1,), jnp.int32),
        jnp.zeros((sentinel + 1 if with_pairs else 1,), jnp.int32),
        zero,
    )
    cap = config.cell_capacity
    full = cap >= pool_blocks * cells_per_block
    record = config.cell_list_capacity if list_cells else 0
    folded = fold_occupied(
        lambda carry: blocks.instance_id,
        blocks.num_blocks,
        config,
        cell_step,
        crowded_step,
        init,
        capacity=None if full else cap,
        record=record,
    )
    (simple_counts, crowded_counts, pairs, overfull), occupied, listed = folded
    if not record:
        listed = (jnp.zeros((0,), jnp.int32), jnp.zeros((0,), jnp.int32))
    if with_pairs:
        matrix = pairs[:sentinel].reshape(k, k)
        matrix = matrix.at[jnp.arange(k), jnp.arange(k)].add(simple_counts[:k])
    else:
        matrix = jnp.zeros((0, 0), jnp.int32)
    return Census(
        counts=(simple_counts + crowded_counts)[:k],
        overlap=matrix,
        occupied=occupied,
        overfull=overfull,
        dropped_cells=jnp.maximum(occupied - cap, 0),
        cells=listed[0],
        tags=listed[1],
    )


# --------------------------------------------------------------------------------------------------
# The kept census. The online merge needs the inflated census on every detection frame, but a frame
# changes the ids of a few thousand cells while the pass visits every occupied one (173k at the end of
# scene0000_00). The census is a sum over cells, so it is kept in the instance table and brought up to
# date by the steps that change ids: each takes the changed cells' contributions out as they were and
# puts them back as they are (the formulas of the pass, so the kept census equals a recount exactly).


class KeptCensus(NamedTuple):
    """The inflated census as kept in the instance table (fields `census_*` of `InstanceTable`)."""

    counts: jax.Array  # int32[K]: voxels holding each id
    overlap: jax.Array  # int32[K, K]: inflated overlap counts (`census(..., "inflated").overlap`)
    overfull: jax.Array  # int32[]: cells with more than `overlap_ids_per_cell` distinct ids
    valid: jax.Array  # bool[]: the fields above are those of the pool (else the next merge step recounts)

    @classmethod
    def of(cls, table) -> "KeptCensus":
        return cls(table.census_counts, table.census_overlap, table.census_overfull, table.census_valid)

    def fields(self) -> dict:
        """The `InstanceTable` fields, for `table._replace(**kept.fields())`."""
        return {f"census_{name}": value for name, value in self._asdict().items()}


def census_can_be_kept(config: MapConfig) -> bool:
    """Static: the inflated census is a plain sum of per-cell contributions (every cell counted, at least
    two ids per cell kept, pair keys within int32), so that it can be kept from step to step."""
    k = config.instance_capacity
    return (
        config.cell_capacity >= config.block_capacity * config.voxels_per_block // 8
        and min(config.overlap_ids_per_cell, 8 * config.instance_slots) >= 2
        and k * k < 2**31
    )


def _cell_contributions(entries: jax.Array, ok: jax.Array, k: int, d_max: int):
    """What the cells (`entries int32[C, 8S]`, rows with `ok`) add to the inflated census: `(counts
    int32[K + 1] (index K: nothing), pair int32[C * d * d] flat index into the K x K overlaps (K * K:
    none), value int32[C * d * d], overfull int32[])`. The pass's two formulas agree on cells of at most
    two ids, so one (the crowded cells') serves every cell. (Splitting the cells as the pass does, simple
    ones by their summary and the crowded ones in a loop of their own, was not faster here and raised the
    peak memory by ~80 MB on scene0000_00.)"""
    entries = geo.materialize(jnp.where(ok[:, None], entries, -1))  # read by the counts and every pair reduction
    pair, value, distinct = _inflated_cell_pairs(entries, k, d_max)
    return segment_count(entries, k), pair, value, jnp.sum(ok & (distinct > d_max), dtype=jnp.int32)


def update_kept_census(kept: KeptCensus, old_entries, new_entries, ok, config: MapConfig) -> KeptCensus:
    """`kept` after the cells `ok` changed their ids from `old_entries` to `new_entries` (int32[C, 8S]
    each, distinct cells): their old contributions out, their new ones in (the formulas of the pass: the
    kept census stays equal to a recount)."""
    k = config.instance_capacity
    d_max = min(config.overlap_ids_per_cell, old_entries.shape[1])
    old_counts, old_pair, old_value, old_overfull = _cell_contributions(old_entries, ok, k, d_max)
    new_counts, new_pair, new_value, new_overfull = _cell_contributions(new_entries, ok, k, d_max)
    flat = kept.overlap.reshape(-1)  # two scatters: concatenating them made XLA fuse them slowly
    flat = flat.at[old_pair].add(-old_value, mode="drop").at[new_pair].add(new_value, mode="drop")
    return kept._replace(
        counts=kept.counts + (new_counts - old_counts)[:k],
        overlap=flat.reshape(kept.overlap.shape),
        overfull=kept.overfull + new_overfull - old_overfull,
    )


def pool_cell_ids(blocks: VoxelBlocks) -> jax.Array:
    """The pool's instance ids as one row per 2x2x2 cell: int16[B * V / 8, 8S] (a free reshape)."""
    return cell_rows(blocks.instance_id)


def gather_cell_ids(cell_ids: jax.Array, cells: jax.Array) -> jax.Array:
    """The ids of the cells `cells int32[N]` (rows of `pool_cell_ids`, -1 rows for cells < 0), as stored:
    int16[N, 8S] (`state.INSTANCE_ID_DTYPE`; widen them before computing keys).

    A cell < 0 reads the pool's last row, a cell of the scratch block (`MapConfig.dummy_slot`, never handed out,
    never voted into or edited), whose ids stay -1: no select over the gathered rows (it cost as much as the
    gather, ~0.5 ms a frame for the 76,800 pixels of a 640x480 frame at stride 2)."""
    return cell_ids.at[jnp.where(cells >= 0, cells, cell_ids.shape[0] - 1)].get(mode="promise_in_bounds")


def census_after_votes(kept: KeptCensus, blocks: VoxelBlocks, cells, old_entries, changed, config: MapConfig):
    """`kept` and `blocks` after a frame's votes: the census brought up to date (meaningless while not valid),
    the voted ids set in `blocks.instance_bits`, the scratch `blocks.cell_owner` returned as it came (all -1).

    Args:
      kept: the census before the votes.
      blocks: the pool after the votes.
      cells: int32[N]: the pool cell (flat index) of each vote's voxel, -1 for none.
      old_entries: int16[N, 8S]: that cell's ids before the votes (`gather_cell_ids`).
      changed: bool[N]: the votes that changed an id of their voxel (`instance_volume.integrate_instances_unjitted`
        with `report_changes`): every cell whose ids changed has one (a flagged cell whose ids did not change
        would count out and in the same ids).

    A cell seen by several votes counts once: the scratch names one vote per changed cell (the largest
    index, a scatter-max), and is reset by a second scatter. Only the changed cells are visited, their ids
    after the votes read from the pool: O(N) work, whatever the size of the map.
    """
    n = cells.shape[0]
    cells_per_block = config.voxels_per_block // 8
    vote = jnp.arange(n, dtype=jnp.int32)
    changed = (cells >= 0) & changed
    owner = blocks.cell_owner.reshape(-1)
    target = jnp.where(changed, cells, owner.shape[0])
    owner = owner.at[target].max(vote, mode="drop")
    got = owner.at[jnp.where(changed, cells, 0)].get(mode="clip")
    first = changed & (got == vote)
    # the reset depends on the read (`got >= -1` always holds), so XLA reads before writing in place
    owner = owner.at[jnp.where(changed & (got >= -1), cells, owner.shape[0])].set(-1, mode="drop")
    listed, count = geo.compact(jnp.full((n,), -1, jnp.int32), jnp.int32(0), first, vote)
    chunk = max(1, min(config.cell_chunk // 4, n))
    cell_ids = pool_cell_ids(blocks)

    def body(start, fresh, carry):
        kept, bits = carry
        at = jax.lax.dynamic_slice_in_dim(listed, start, chunk)
        ok = fresh & (at >= 0)
        at = jnp.where(ok, at, 0)
        cell = cells[at]
        new = gather_cell_ids(cell_ids, jnp.where(ok, cell, -1)).astype(jnp.int32)
        bits = set_instance_bits(bits, cell // cells_per_block, new, ok)
        return update_kept_census(kept, old_entries[at].astype(jnp.int32), new, ok, config), bits

    kept, bits = geo.fold_chunks(count, chunk, n, body, (kept, blocks.instance_bits))
    return kept, blocks._replace(instance_bits=bits, cell_owner=owner.reshape(blocks.cell_owner.shape))


def set_instance_bits(bits: jax.Array, block: jax.Array, entries: jax.Array, ok: jax.Array) -> jax.Array:
    """`bits` (`VoxelBlocks.instance_bits`, bool[B, W]) with the ids `entries int32[C, 8S]` set in their
    blocks `block int32[C]` (rows with `ok`)."""
    pool_blocks, width = bits.shape
    known = ok[:, None] & (entries >= 0)
    flat = jnp.where(known, block[:, None] * width + entries % width, pool_blocks * width)
    return bits.reshape(-1).at[flat.reshape(-1)].set(True, mode="drop").reshape(bits.shape)


def blocks_holding(bits: jax.Array, wanted: jax.Array, num_blocks) -> jax.Array:
    """bool[B]: the allocated blocks whose bits may hold an id flagged in `wanted` (bool[K])."""
    pool_blocks, width = bits.shape
    k = wanted.shape[0]
    wanted_bits = jnp.zeros((width,), bool).at[jnp.arange(k) % width].max(wanted)
    words, wanted_words = geo.as_words(bits), geo.as_words(wanted_bits)
    if words is None or wanted_words is None:
        holds = jnp.any(bits & wanted_bits[None, :], axis=1)
    else:  # four flags to a word: 2.7x faster than the reduction over bools on the CPU
        holds = jnp.any((words & wanted_words[None, :]) != 0, axis=1)
    return holds & (jnp.arange(pool_blocks) < num_blocks)


def kept_from_census(result: "Census", valid) -> KeptCensus:
    """The kept census of a full inflated `census` (valid when `valid` and nothing was dropped)."""
    return KeptCensus(result.counts, result.overlap, result.overfull, jnp.asarray(valid, bool) & (result.dropped_cells == 0))


def _instance_voxel_counts(blocks: VoxelBlocks, config: MapConfig) -> InstanceCounts:
    result = census(blocks, config)
    return InstanceCounts(result.counts, result.dropped_cells)


@functools.partial(jax.jit, static_argnames=("config",))
def instance_voxel_counts(blocks: VoxelBlocks, config: MapConfig) -> InstanceCounts:
    """Voxels holding each instance id.

    Returns:
      `InstanceCounts(counts int32[K], dropped_cells int32[])`, K = `config.instance_capacity`;
      occupied cells beyond `config.cell_capacity` (in pool order) are not counted (reported in
      dropped_cells).
    """
    return _instance_voxel_counts(blocks, config)


def _instance_overlap_counts(blocks: VoxelBlocks, config: MapConfig, inflate: bool, keep=None) -> InstanceCounts:
    result = census(blocks, config, "inflated" if inflate else "plain", keep)
    return InstanceCounts(result.overlap, result.dropped_cells + result.overfull)


@functools.partial(jax.jit, static_argnames=("config", "inflate"))
def instance_overlap_counts(blocks: VoxelBlocks, config: MapConfig, inflate: bool) -> InstanceCounts:
    """Pairwise overlap of the instance volumes.

    `counts[a, b]` = number of b's voxels lying inside a's volume: with `inflate=False` the voxels
    holding both ids (symmetric; 3D IoU = o_ab / (n_a + n_b - o_ab)); with `inflate=True` b's voxels
    whose 2x2x2 coarse cell holds a voxel of a (the paper's 2x inflated grid of a, see the module
    docstring; not symmetric). In both cases the diagonal is the voxel count of each instance.

    Returns:
      `InstanceCounts(counts int32[K, K], dropped_cells int32[])`. Cost: one pass over the allocated
      blocks; 2 scatter updates per occupied cell holding at most two ids, `8 * S^2` (plain) or
      `ids_per_cell^2` (inflated) for the others. Occupied cells beyond `config.cell_capacity`, and
      (inflated) cells with more than `overlap_ids_per_cell` distinct ids (the largest are kept),
      count as dropped.
    """
    return _instance_overlap_counts(blocks, config, inflate)


__all__ = ["Census", "InstanceCounts", "KeptCensus", "census", "instance_overlap_counts", "instance_voxel_counts"]
