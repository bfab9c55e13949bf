"""Instances live in the voxels: S instance slots per voxel of the block pool (jitted, fixed shapes).

Each voxel stores up to `S = instance_slots` distinct instance ids with a weight each
(`VoxelBlocks.instance_id`, `.instance_weight`). An instance's volume is the set of voxels that hold
its id; instances may overlap (a voxel on the border of two detections holds both). Everything here
is a gather, an elementwise pass or a scatter bounded by a pixel or cell count; nothing loops over
instances.

Per-pixel work (`pixel_instances`, `integrate_instances`) runs on the stride-subsampled pixel grid
(`config.pixel_stride`): subsampled pixel `(r, c)` is full-resolution pixel `(r * stride, c * stride)`,
i.e. `image[::stride, ::stride]`.

**Surface voxel of a pixel**: the voxel containing the back-projected depth point `d * (x_n, y_n, 1)`.

**Slot update rule** (`integrate_instances`, each pixel is one vote for its surface voxel):
  1. the pixel's instance already has a slot in the voxel: that slot's weight +1;
  2. else the voxel has an empty slot: the instance takes the first empty slot with weight 1;
  3. else (all slots held by other instances) the weakest slot loses 1 weight, and is emptied when
     its weight reaches 0 (a Misra-Gries frequent-items update): a slot established by many
     observations survives a few contradicting pixels, a one-off is evicted quickly, and the
     newcomer takes the freed slot on its next observation.
  Targets are chosen from the state before the frame; conflicts are resolved deterministically:
  several instances claiming the same empty slot in one frame -> the largest id wins (scatter-max),
  the others' pixels are dropped; weight changes are additions, so their order does not matter.
  Pixels whose surface voxel lies in an unallocated block are dropped (integrate the global TSDF of
  the same frame first, which allocates those blocks).

**Robust lookup** (`pixel_instances`): depth noise and the change of viewpoint move the observed
surface by about a voxel between frames, and an instance integrated from one view occupies a
"staircase" of voxels that another view's surface points do not always hit. So each pixel probes
the voxels at the ray offsets `config.instance_lookup_offsets` around its depth point (default -1,
0, +1 voxel along the ray) and reports the union of the instance ids found there, deduplicated,
strongest (summed slot weight) first, at most S. Measured on the synthetic box room (instances
integrated from one 320x240 view at stride 1, looked up from the next view, pixels seen by both,
depth noise 1.5 mm * d^2): the correct id is found for 72% of the pixels with the centre voxel
alone, 88% with offsets (-0.5, 0, 0.5), 93% with (-1, 0, 1), 94% with (-1, -0.5, 0, 0.5, 1);
wrong-only answers stay at 0.1%. The cost is one gather per probe and slot.

Counting, renaming and geometry fusion over the occupied voxel cells live in `occupied_cells`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from fmfusion_jax.engine import _geometry as geo
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import VoxelBlocks

# --------------------------------------------------------------------------------------------------
# Per-pixel lookup and integration. Per-slot quantities are kept as lists of pixel arrays (one
# array per slot or probe) rather than as a small trailing axis: XLA vectorises over the long axis.


def _subsampled_points(depth, T, K, config: MapConfig, offset_voxels: float, origin_block):
    """Valid flag and global voxel of each subsampled pixel's depth point moved `offset_voxels` along the ray."""
    s = config.pixel_stride
    d = depth[::s, ::s]
    xn, yn = geo.subsampled_rays(K, config, s)
    ok = geo.valid_depth(d, config)
    if offset_voxels != 0.0:
        # A distance offset along the ray changes z by offset / |(xn, yn, 1)|.
        d = d + offset_voxels * config.voxel_size / jnp.sqrt(xn * xn + yn * yn + 1.0)
    x, y, z = geo.camera_to_world(T, xn * d, yn * d, d)
    return ok, geo.world_to_voxel(x, y, z, config, origin_block)


def _entry_base(blocks: VoxelBlocks, slot, voxel):
    """Flat pool entry of slot 0 at the addresses `(slot, voxel)` (0 where slot is -1)."""
    _, v_per_block, num_slots = blocks.instance_id.shape
    return jnp.where(slot >= 0, (slot * v_per_block + voxel) * num_slots, 0)


def _slot_weights(blocks: VoxelBlocks, base, ids: list) -> list:
    """Per slot the weights at the entries `base + s` (`_entry_base`), 0 where the slot's id is empty."""
    w_flat = blocks.instance_weight.reshape(-1)
    return [jnp.where(i >= 0, w_flat.at[base + s].get(mode="promise_in_bounds"), 0.0) for s, i in enumerate(ids)]


def _slot_entries(blocks: VoxelBlocks, slot, voxel):
    """Per-slot lists of (ids, weights) at pool addresses `(slot, voxel)` (slot -1: empty)."""
    num_slots = blocks.instance_id.shape[-1]
    hit = slot >= 0
    base = _entry_base(blocks, slot, voxel)
    ids_flat = blocks.instance_id.reshape(-1)
    ids = [jnp.where(hit, ids_flat.at[base + s].get(mode="promise_in_bounds").astype(jnp.int32), -1) for s in range(num_slots)]
    return ids, _slot_weights(blocks, base, ids)


def pixel_instance_slots(blocks: VoxelBlocks, depth, T_world_camera, intrinsics, config: MapConfig) -> list:
    """`pixel_instances` as a list of its S slots, int32 `(Hs, Ws)` each (unjitted, for composing: readers of
    single slots then read them as computed, with no stacked copy)."""
    T, K = geo.as_pose(T_world_camera), geo.as_intrinsics(intrinsics)
    depth = jnp.asarray(depth, jnp.float32)
    num_slots = blocks.instance_id.shape[-1]
    ids, weights = [], []
    for offset in config.instance_lookup_offsets:
        ok, (gx, gy, gz) = _subsampled_points(depth, T, K, config, offset, blocks.origin_block)
        slot, v, _ = geo.locate_voxels(blocks, gx, gy, gz, config)
        i, w = _slot_entries(blocks, jnp.where(ok, slot, -1), v)
        ids += i
        weights += w
    # Union: a candidate counts if no earlier candidate has its id; its score sums all its weights.
    scores = []
    for a, id_a in enumerate(ids):
        first = id_a >= 0
        total = weights[a]
        for b, id_b in enumerate(ids):
            if b < a:
                first = first & (id_b != id_a)
            elif b > a:
                total = total + jnp.where(id_b == id_a, weights[b], 0.0)
        scores.append(jnp.where(first, total, -1.0))
    # The S best, strongest first (ties: the earlier candidate).
    out = []
    for _ in range(num_slots):
        best, best_id, best_at = scores[0], ids[0], jnp.zeros(ids[0].shape, jnp.int32)
        for a in range(1, len(ids)):
            better = scores[a] > best
            best = jnp.where(better, scores[a], best)
            best_id = jnp.where(better, ids[a], best_id)
            best_at = jnp.where(better, a, best_at)
        out.append(jnp.where(best >= 0.0, best_id, -1))
        scores = [jnp.where(best_at == a, -1.0, sc) for a, sc in enumerate(scores)]
    return _computed_once(out)


def _pixel_instances(blocks: VoxelBlocks, depth, T_world_camera, intrinsics, config: MapConfig):
    return jnp.stack(pixel_instance_slots(blocks, depth, T_world_camera, intrinsics, config), axis=-1)


def _computed_once(ids: list) -> list:
    """The int32 id arrays `ids` (values in [-1, 2^16 - 1)), each computed once: two to a uint32 word, each word
    materialized, then split. Stacked as they were, XLA evaluated the whole lookup once per output slot and
    the ranking once more for the second (3.3x slower on the CPU)."""
    out = []
    for first in range(0, len(ids), 2):
        pair = ids[first : first + 2]
        word = functools.reduce(jnp.bitwise_or, [(i + 1).astype(jnp.uint32) << (16 * j) for j, i in enumerate(pair)])
        word = geo.materialize(word)
        out += [((word >> (16 * j)) & 0xFFFF).astype(jnp.int32) - 1 for j in range(len(pair))]
    return out


@functools.partial(jax.jit, static_argnames=("config",))
def pixel_instances(blocks: VoxelBlocks, depth, T_world_camera, intrinsics, config: MapConfig) -> jax.Array:
    """The projected instance map: instance ids stored at the surface each subsampled pixel sees.

    Args:
      blocks: the pool.
      depth: float32 `(H, W)` metres (0 = invalid).
      T_world_camera: float32 `(4, 4)`.
      intrinsics: float32 `(4,)` = `(fx, fy, cx, cy)`.
      config: static.

    Returns:
      int32 `(Hs, Ws, S)`: per subsampled pixel, up to S distinct instance ids found at the probed
      voxels (see the module docstring), strongest first, -1 padded. Occlusion is handled by the
      depth itself: only the surface the pixel measures is probed.
    """
    return _pixel_instances(blocks, depth, T_world_camera, intrinsics, config)


def _apply_instance_hits(
    blocks: VoxelBlocks,
    slot,
    voxel,
    instance,
    config: MapConfig,
    detected=None,
    neutral=None,
    contrary_weight: float = 0.0,
    cell_entries=None,
    report_changes: bool = False,
):
    """`apply_instance_hits`; with `report_changes` (static) also returns bool[N]: the votes that changed an id of
    their voxel (a claim, or an emptied slot): every voxel whose ids changed has one."""
    num_blocks, v_per_block, num_slots = blocks.instance_id.shape
    n_entries = num_blocks * v_per_block * num_slots
    slot = jnp.asarray(slot, jnp.int32).reshape(-1)
    voxel = jnp.asarray(voxel, jnp.int32).reshape(-1)
    instance = jnp.asarray(instance, jnp.int32).reshape(-1)
    seen = (slot >= 0) & (slot < config.dummy_slot)  # the pixel observes an allocated voxel
    valid = seen & (instance >= 0)
    if cell_entries is None:
        ids, weights = _slot_entries(blocks, jnp.where(seen, slot, -1), voxel)  # the state before the frame
    else:
        # the ids read from the vote's cell row (`pixel_cells`) instead: the same values, and the writes below
        # then depend on that read, so XLA reads the row before writing in place rather than copy the pool
        at = jnp.arange(slot.shape[0], dtype=jnp.int32) * cell_entries.shape[1] + (voxel % 8) * num_slots
        entries = cell_entries.reshape(-1)
        ids = [jnp.where(seen, entries[at + s].astype(jnp.int32), -1) for s in range(num_slots)]
        weights = _slot_weights(blocks, _entry_base(blocks, jnp.where(seen, slot, -1), voxel), ids)
    # read by every scatter below: each computed once (else each consumer redoes the gathers)
    ids = _computed_once(ids)
    weights = [geo.materialize(w) for w in weights]

    # Target slot: the instance's own slot, else the first empty one, else the weakest.
    has_match = jnp.zeros(instance.shape, bool)
    has_empty = jnp.zeros(instance.shape, bool)
    own = jnp.zeros(instance.shape, jnp.int32)
    empty = jnp.zeros(instance.shape, jnp.int32)
    weakest = jnp.zeros(instance.shape, jnp.int32)
    weakest_w = jnp.full(instance.shape, jnp.inf, jnp.float32)
    for s in reversed(range(num_slots)):  # reversed: the first matching / empty slot wins
        match_s, empty_s = ids[s] == instance, ids[s] < 0
        own = jnp.where(match_s, s, own)
        empty = jnp.where(empty_s, s, empty)
        has_match |= match_s
        has_empty |= empty_s
    for s in range(num_slots):  # forward with strict <: the first of equal weights
        lighter = weights[s] < weakest_w
        weakest = jnp.where(lighter, s, weakest)
        weakest_w = jnp.where(lighter, weights[s], weakest_w)
    target = jnp.where(has_match, own, jnp.where(has_empty, empty, weakest))
    claim = valid & ~has_match & has_empty
    decay = valid & ~has_match & ~has_empty
    base = (slot * v_per_block + voxel) * num_slots
    entry = jnp.where(valid, base + target, n_entries)
    safe_entry = jnp.minimum(entry, n_entries - 1)

    # Pass 1, claim: empty target slots take the largest claiming id (-1 is a no-op for the others).
    id_dtype = blocks.instance_id.dtype  # stored narrow (`state.INSTANCE_ID_DTYPE`), compared as int32
    ids_flat = blocks.instance_id.reshape(-1).at[entry].max(jnp.where(claim, instance, -1).astype(id_dtype), mode="drop")
    # Pass 2, add: pixels whose instance holds the target slot vote +1, displaced ones vote -1.
    won = valid & ~decay & (ids_flat[safe_entry].astype(jnp.int32) == instance)
    vote = jnp.where(won, 1.0, jnp.where(decay, -1.0, 0.0))
    if contrary_weight > 0.0 and detected is not None:
        # Contrary votes: a slot whose instance was detected in this frame loses `contrary_weight` for each
        # pixel that sees its voxel outside that detection (neutral pixels, inside a mask but cut by its
        # depth filter, say nothing). One scatter of N entries per slot: XLA's CPU scatter keeps to its
        # fast path for N entries, where one scatter of S * N concatenated entries cost 3x as much.
        k = detected.shape[0]
        speaks = seen if neutral is None else seen & ~jnp.asarray(neutral, bool).reshape(-1)
        per_slot = []
        for s in range(num_slots):
            against = speaks & (ids[s] >= 0) & (ids[s] != instance) & detected[jnp.clip(ids[s], 0, k - 1)]
            mine = valid & (target == s)
            delta = jnp.where(mine, vote, 0.0) - jnp.where(against, contrary_weight, 0.0)
            per_slot.append((jnp.where(mine | against, base + s, n_entries), delta, against | (mine & decay)))
    else:
        per_slot = [(entry, vote, decay)]
    w_flat = blocks.instance_weight.reshape(-1)
    for entries, deltas, _ in per_slot:
        w_flat = w_flat.at[entries].add(deltas, mode="drop")
    # Slots voted down to zero are emptied.
    changed = claim
    for entries, _, lowered in per_slot:
        emptied = lowered & (w_flat[jnp.minimum(entries, n_entries - 1)] <= 0.0)
        cleared_entry = jnp.where(emptied, entries, n_entries)
        ids_flat = ids_flat.at[cleared_entry].set(jnp.asarray(-1, id_dtype), mode="drop")
        w_flat = w_flat.at[cleared_entry].set(0.0, mode="drop")
        changed = changed | emptied
    # a claim adds an id to its voxel: the next geometry fusion visits the block
    stale = blocks.geometry_stale.at[jnp.where(claim, slot, num_blocks)].set(True, mode="drop")
    blocks = blocks._replace(
        instance_id=ids_flat.reshape(blocks.instance_id.shape),
        instance_weight=w_flat.reshape(blocks.instance_weight.shape),
        geometry_stale=stale,
    )
    return (blocks, changed) if report_changes else blocks


@functools.partial(jax.jit, static_argnames=("config", "contrary_weight"))
def apply_instance_hits(
    blocks: VoxelBlocks, slot, voxel, instance, config: MapConfig, detected=None, neutral=None, contrary_weight: float = 0.0
) -> VoxelBlocks:
    """Apply one frame's instance votes given explicit voxel addresses (the core of `integrate_instances`).

    Args:
      blocks: the pool.
      slot: int32 `(N,)` pool slot of each vote's voxel (-1 = drop the vote).
      voxel: int32 `(N,)` voxel index inside the block, in `[0, V)`.
      instance: int32 `(N,)` instance id of each vote (-1 = no instance: the pixel can still vote against).
      config: static.
      detected: bool `(K,)` instances detected in this frame (contrary votes only concern them); None: none.
      neutral: bool `(N,)` votes that say nothing against other instances (None: all speak).
      contrary_weight: static; weight of a contrary vote (0 disables them: the plain slot rule).

    Returns:
      The pool after the slot update rule of the module docstring (4 scatters of N updates; 1 + 3S with
      contrary votes).
    """
    return _apply_instance_hits(blocks, slot, voxel, instance, config, detected, neutral, contrary_weight)


def _integrate_instances(
    blocks: VoxelBlocks,
    depth,
    T_world_camera,
    intrinsics,
    pixel_instance,
    config: MapConfig,
    detected=None,
    neutral=None,
    contrary_weight: float = 0.0,
    cell_entries=None,
    voxels=None,
    report_changes: bool = False,
):
    T, K = geo.as_pose(T_world_camera), geo.as_intrinsics(intrinsics)
    depth = jnp.asarray(depth, jnp.float32)
    pixel_instance = jnp.asarray(pixel_instance, jnp.int32)
    if pixel_instance.shape != config.subsampled_shape:
        raise ValueError(f"pixel_instance has shape {pixel_instance.shape}, expected {config.subsampled_shape}")
    if voxels is None:
        voxels = pixel_voxels(blocks, depth, T, K, config)
    v_per_block = config.voxels_per_block
    slot = jnp.where(voxels >= 0, voxels // v_per_block, -1)
    return _apply_instance_hits(
        blocks,
        slot,
        voxels % v_per_block,
        pixel_instance,
        config,
        detected,
        neutral,
        contrary_weight,
        cell_entries,
        report_changes,
    )


def pixel_voxels(blocks: VoxelBlocks, depth, T_world_camera, intrinsics, config: MapConfig) -> jax.Array:
    """int32[Hs * Ws]: the pool voxel (flat index, `slot * V + voxel`) that each subsampled pixel votes into in
    `integrate_instances` (its surface voxel, in an allocated block), -1 where it casts no vote. Computed once
    into a buffer (`_geometry.materialize`): every gather and scatter of the votes reads it, and XLA would
    otherwise redo the back-projection and block lookup in each of them."""
    T, K = geo.as_pose(T_world_camera), geo.as_intrinsics(intrinsics)
    ok, (gx, gy, gz) = _subsampled_points(jnp.asarray(depth, jnp.float32), T, K, config, 0.0, blocks.origin_block)
    slot, v, _ = geo.locate_voxels(blocks, gx, gy, gz, config)
    seen = ok & (slot >= 0) & (slot < config.dummy_slot)
    return geo.materialize(jnp.where(seen, slot * config.voxels_per_block + v, -1).reshape(-1))


def pixel_cells(voxels: jax.Array) -> jax.Array:
    """int32[N]: the pool's 2x2x2 cell (flat index, `slot * V / 8 + voxel // 8`) of each pool voxel of `voxels`
    (`pixel_voxels`), -1 where none."""
    return jnp.where(voxels >= 0, voxels // 8, -1)


@functools.partial(jax.jit, static_argnames=("config", "contrary_weight"))
def integrate_instances(
    blocks: VoxelBlocks,
    depth,
    T_world_camera,
    intrinsics,
    pixel_instance,
    config: MapConfig,
    detected=None,
    neutral=None,
    contrary_weight: float = 0.0,
    cell_entries=None,
    voxels=None,
) -> VoxelBlocks:
    """Vote each subsampled pixel's instance into its surface voxel.

    Args:
      blocks: the pool (the frame's TSDF integration already applied, so its blocks exist).
      depth: float32 `(H, W)` metres.
      T_world_camera: float32 `(4, 4)`.
      intrinsics: float32 `(4,)` = `(fx, fy, cx, cy)`.
      pixel_instance: int32 `(Hs, Ws)` instance id per subsampled pixel (`mask[::stride, ::stride]`),
        -1 for none.
      config: static.
      detected: bool `(K,)` instances detected in this frame; their slots take contrary votes.
      neutral: bool `(Hs, Ws)` pixels that cast no contrary vote (inside a mask, cut by its depth filter).
      contrary_weight: static; weight of one contrary vote (0: none, the plain slot rule).
      cell_entries: optional int16 (or int32) `(Hs * Ws, 8S)`: the ids of each pixel's cell (`pixel_cells`) as read
        before the votes, by a caller that needs them too (the votes then read their ids there).
      voxels: optional int32 `(Hs * Ws,)`: `pixel_voxels` of the same frame, by a caller that needs them too.

    Returns:
      The pool after the slot update rule of the module docstring (scatters of `Hs * Ws` updates, 1 + 3S of them
      with contrary votes).
    """
    return _integrate_instances(
        blocks,
        depth,
        T_world_camera,
        intrinsics,
        pixel_instance,
        config,
        detected,
        neutral,
        contrary_weight,
        cell_entries,
        voxels,
    )


#: `integrate_instances` unjitted, for composing; with `report_changes=True` it returns `(blocks, changed bool[Hs * Ws])`,
#: the pixels whose vote changed an id of their voxel (`_apply_instance_hits`).
integrate_instances_unjitted = _integrate_instances

__all__ = [
    "pixel_instances",
    "pixel_instance_slots",
    "integrate_instances_unjitted",
    "pixel_voxels",
    "pixel_cells",
    "integrate_instances",
    "apply_instance_hits",
]
