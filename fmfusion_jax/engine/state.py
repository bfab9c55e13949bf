"""The immutable map state: a voxel-block pool behind a dense block index, and the instance table.

Every container is a NamedTuple of arrays (a pytree), so the state passes through `jax.jit`,
`jax.vmap` and `jax.lax` control flow unchanged; every function of the engine takes a state and
returns a new one. Shapes are fixed by `MapConfig` and never change at run time.

Lattice and layout
- Global voxel `g = (gx, gy, gz)` (integers) has its centre at `grid_origin + (g + 0.5) * voxel_size`;
  a world point `p` lies in voxel `floor((p - grid_origin) / voxel_size)`.
- Block `b = g // block_size` (floor division), local voxel `l = g - b * block_size` in
  `[0, block_size)^3`. The dense `block_index[b]` holds the block's pool slot, or -1.
- Inside a block the `V = block_size^3` voxels are stored in **2x2x2-cell order**: the 8 voxels of
  each 2x2x2 cell are contiguous, so `(..., V)` reshapes for free to `(..., V // 8, 8)` cells (used by
  the inflated overlap test, whose cells are the 2x coarse voxels). `local_voxel_index` and
  `voxel_offsets` convert between local coordinates and that order.
- Pool slot `B - 1` is a scratch slot: fixed-size slot lists are padded with it, it is never
  allocated, and its contents are meaningless. Only slots `< num_blocks` hold blocks.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from fmfusion_jax.engine.config import MAX_INSTANCE_CAPACITY, MapConfig

#: Storage of the voxels' instance ids: 16 bits (tables of up to `MAX_INSTANCE_CAPACITY` rows) halve the bytes
#: the merge's census reads on every detection frame and a sixth of the pool. Every computation on ids
#: widens them to int32 first (pair keys `a * K + b` do not fit 16 bits).
INSTANCE_ID_DTYPE = jnp.int16
assert MAX_INSTANCE_CAPACITY <= np.iinfo(np.int16).max

#: Bins of `VoxelBlocks.up_heights` (2 cm each; `engine.support` reads and writes them).
UP_HEIGHT_BINS = 2048
#: Bits per block of `VoxelBlocks.instance_bits` (a Bloom filter of the ids the block holds).
INSTANCE_BITS = 128

#: Storage of the voxels' mean colour: half precision (0.06-0.125 steps between 128 and 255), a sixth of the
#: pool's bytes instead of a third; colour only feeds the mesh and the pictures, never a decision.
COLOR_DTYPE = jnp.float16


class VoxelBlocks(NamedTuple):
    """The voxel-block pool: global TSDF, colour and per-voxel instance slots.

    Invariants: slots `[0, num_blocks)` are allocated and indexed by exactly one `block_index` entry;
    in every voxel the non-negative instance ids are distinct, and an empty slot (id -1) has weight 0.
    """

    block_index: jax.Array  # int32[gx, gy, gz]: pool slot of each block of the scene bounds, -1 if none
    block_coords: jax.Array  # int32[B, 3]: block coordinate of each slot (meaningful for slot < num_blocks)
    num_blocks: jax.Array  # int32[]: allocated slots, always < B (slot B - 1 is the scratch slot)
    tsdf: jax.Array  # float32[B, V]: truncated signed distance / sdf_trunc, in [-1, 1] (1 = unobserved/free)
    weight: jax.Array  # float32[B, V]: TSDF integration weight (observations, capped at config.max_weight)
    color: jax.Array  # float16[B, V, 3]: weighted mean RGB in [0, 255] (to 1/16 at 255: colour is only drawn)
    instance_id: jax.Array  # int16[B, V, S]: instance ids seen at the voxel, -1 = empty slot (see INSTANCE_ID_DTYPE)
    instance_weight: jax.Array  # float32[B, V, S]: evidence per slot (pixel hits, see instance_volume)
    dropped_blocks: jax.Array  # int32[]: blocks that needed a slot when the pool was full (cumulative)
    out_of_bounds: jax.Array  # int32[]: sampled depth points outside the block index (cumulative)
    touched_overflow: jax.Array  # int32[]: touched blocks beyond max_touched_blocks, not integrated (cumulative)
    # int32[3]: the block index's origin in whole blocks of the world lattice (`config.grid_origin / block_length`).
    # Data, not a compiled constant: maps of different bounds share one compiled step (`MapConfig.compiled_layout`).
    origin_block: jax.Array
    # bool[B, INSTANCE_BITS]: bit `id % INSTANCE_BITS` is set in a block that holds (or held) id: the renaming
    # visits only the blocks whose bits name a renamed id (set by every step that writes an id; a renaming clears
    # the bits of the blocks it visits and sets them again from the ids they hold)
    instance_bits: jax.Array
    # bool[B]: the block's TSDF changed, or one of its voxels took a new instance id, since the last geometry
    # fusion (which visits only these blocks: elsewhere every id it holds was supported then and still is)
    geometry_stale: jax.Array
    # int32[UP_HEIGHT_BINS]: up-facing surface samples per height along the world's up axis (the floor
    # filter's histogram, `engine.support`; added to on detection frames while the filter is on)
    up_heights: jax.Array
    # int32[B, V / 8]: scratch of the steps that keep the merge's census (one entry per 2x2x2 cell, -1 between
    # steps; see `occupied_cells.census_after_votes`); not saved in map files
    cell_owner: jax.Array


class InstanceTable(NamedTuple):
    """K rows of instance attributes; row k describes instance id k (ids index rows directly)."""

    valid: jax.Array  # bool[K]: the row holds a live instance
    label_evidence: jax.Array  # float32[K, C]: label-fusion state (owned by `engine.semantics`); zeros at init
    open_label_histogram: jax.Array  # float32[K, O]: accumulated open-set label scores
    observations: jax.Array  # int32[K]: detections associated with the instance
    missed: jax.Array  # int32[K]: detection frames in which it was visible but not detected
    voxel_count: jax.Array  # int32[K]: voxels holding the instance (as of the last merge step)
    created_frame: jax.Array  # int32[K]: frame index of creation
    last_seen_frame: jax.Array  # int32[K]: frame index of the last association
    # int32[K, K]: covered[a, b] = detection frames in which instance b, in view and not detected itself,
    # was mostly inside the mask of a detection fused into a (the evidence that reunites fragments);
    # zero in the rows and columns of invalid instances
    covered: jax.Array
    # int32[K, K] symmetric: detection frames in which a and b were fused from two different detections (the
    # detector saw two objects: evidence against merging them); zero in the rows and columns of invalid ones
    separated: jax.Array
    overflow: jax.Array  # int32[]: detections that found no free row (cumulative)
    # The online merge's inflated census of the voxels, kept up to date by the steps that change ids
    # (`occupied_cells.KeptCensus`); when `census_valid` is false, the next merge step counts it again.
    census_counts: jax.Array  # int32[K]: voxels holding each id
    census_overlap: jax.Array  # int32[K, K]: inflated overlap counts (`occupied_cells.census`)
    census_overfull: jax.Array  # int32[]: cells with more distinct ids than the overlap keeps
    census_valid: jax.Array  # bool[]


class MapState(NamedTuple):
    """The whole map."""

    blocks: VoxelBlocks  # geometry and per-voxel instance slots
    instances: InstanceTable  # per-instance attributes
    frame_index: jax.Array  # int32[]: frames integrated so far


# --------------------------------------------------------------------------------------------------
# Voxel layout inside a block.


def local_voxel_index(x, y, z, block_size: int):
    """Index in `[0, V)` of local voxel `(x, y, z)` (each in `[0, block_size)`), 2x2x2-cell order.

    Works elementwise on Python ints, NumPy or JAX integer arrays.
    """
    c = block_size // 2
    cell = ((x // 2) * c + (y // 2)) * c + (z // 2)
    return cell * 8 + (x % 2) * 4 + (y % 2) * 2 + (z % 2)


@functools.cache
def _voxel_offsets_cached(block_size: int) -> np.ndarray:
    grid = np.stack(np.meshgrid(*(np.arange(block_size),) * 3, indexing="ij"), -1).reshape(-1, 3)
    out = np.zeros((block_size**3, 3), np.int32)
    out[local_voxel_index(grid[:, 0], grid[:, 1], grid[:, 2], block_size)] = grid
    out.setflags(write=False)
    return out


def voxel_offsets(block_size: int) -> np.ndarray:
    """int32[V, 3]: local coordinates `(x, y, z)` of each voxel index `v` of a block (read-only)."""
    return _voxel_offsets_cached(int(block_size))


# --------------------------------------------------------------------------------------------------
# Construction.


# Jitted with the config static: one executable per layout, instead of a compiled (or cache-loaded) op per array.
@functools.partial(jax.jit, static_argnums=0)
def init_voxel_blocks(config: MapConfig) -> VoxelBlocks:
    """An empty pool: no block allocated, tsdf 1, weights 0, every instance slot empty."""
    b, v, s = config.block_capacity, config.voxels_per_block, config.instance_slots

    def zero():  # a distinct buffer per counter, so that the state can be donated to jit
        return jnp.zeros((), jnp.int32)

    return VoxelBlocks(
        block_index=jnp.full(config.grid_shape, -1, jnp.int32),
        block_coords=jnp.full((b, 3), -1, jnp.int32),
        num_blocks=zero(),
        tsdf=jnp.ones((b, v), jnp.float32),
        weight=jnp.zeros((b, v), jnp.float32),
        color=jnp.zeros((b, v, 3), COLOR_DTYPE),
        instance_id=jnp.full((b, v, s), -1, INSTANCE_ID_DTYPE),
        instance_weight=jnp.zeros((b, v, s), jnp.float32),
        dropped_blocks=zero(),
        out_of_bounds=zero(),
        touched_overflow=zero(),
        origin_block=jnp.asarray(config.origin_block, jnp.int32),
        instance_bits=jnp.zeros((b, INSTANCE_BITS), bool),
        geometry_stale=jnp.zeros((b,), bool),
        up_heights=jnp.zeros((UP_HEIGHT_BINS,), jnp.int32),
        cell_owner=jnp.full((b, v // 8), -1, jnp.int32),
    )


@functools.partial(jax.jit, static_argnums=0)
def init_instance_table(config: MapConfig) -> InstanceTable:
    """An empty table. `label_evidence` starts at zeros: the label-fusion code gives a row its prior
    (e.g. the uniform 1/C of additive fusion) when it creates the instance."""
    k = config.instance_capacity

    def zeros_k():  # distinct buffers (donation)
        return jnp.zeros((k,), jnp.int32)

    return InstanceTable(
        valid=jnp.zeros((k,), bool),
        label_evidence=jnp.zeros((k, config.num_classes), jnp.float32),
        open_label_histogram=jnp.zeros((k, config.num_open_labels), jnp.float32),
        observations=zeros_k(),
        missed=zeros_k(),
        voxel_count=zeros_k(),
        created_frame=zeros_k(),
        last_seen_frame=zeros_k(),
        covered=jnp.zeros((k, k), jnp.int32),
        separated=jnp.zeros((k, k), jnp.int32),
        overflow=jnp.zeros((), jnp.int32),
        census_counts=zeros_k(),
        census_overlap=jnp.zeros((k, k), jnp.int32),
        census_overfull=jnp.zeros((), jnp.int32),
        census_valid=jnp.zeros((), bool),
    )


@functools.partial(jax.jit, static_argnums=0)
def init_map_state(config: MapConfig) -> MapState:
    """An empty map for `config` (allocates about `config.memory_bytes()` bytes)."""
    return MapState(
        blocks=init_voxel_blocks(config),
        instances=init_instance_table(config),
        frame_index=jnp.zeros((), jnp.int32),
    )


@jax.jit
def copy_map_state(state: MapState) -> MapState:
    """`state` in fresh buffers, for a step that donates its input: one compiled program, not a copy per leaf."""
    return jax.tree.map(jnp.copy, state)


__all__ = [
    "INSTANCE_BITS",
    "VoxelBlocks",
    "InstanceTable",
    "MapState",
    "init_voxel_blocks",
    "init_instance_table",
    "init_map_state",
    "copy_map_state",
    "local_voxel_index",
    "voxel_offsets",
]
