"""Static configuration of the map engine: sizes, capacities and TSDF parameters.

`MapConfig` is a frozen, hashable dataclass: every jitted engine function takes it as a static
argument, so each distinct config compiles once and every array shape derives from it. Nothing in
it may depend on data seen at run time (that would recompile); capacities are fixed up front and
every overflow is counted in the state instead.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import numpy as np

#: `MapConfig.for_bounds` rounds the block index's shape up to a multiple of this many blocks per axis.
GRID_SHAPE_BUCKET = 8

#: Most rows an instance table may have: the voxels store instance ids in 16 bits (`state.INSTANCE_ID_DTYPE`).
MAX_INSTANCE_CAPACITY = 32767


def integrate_chunk_for_backend(backend: str) -> int:
    """`MapConfig.integrate_chunk_blocks` when left at 0, for a JAX backend ("cpu", "gpu", ...): 96 blocks (49k
    voxels) on the CPU, where a step's arrays then stay in a core's cache (the global TSDF 10% faster than with
    256 on the 2-core VM); 256 elsewhere (as measured on an H200): fewer steps, each of which a GPU reports
    back to the host."""
    return 96 if backend == "cpu" else 256


@dataclasses.dataclass(frozen=True)
class MapConfig:
    """Sizes and parameters of one map (static argument of the jitted engine functions).

    The defaults of the knobs the config schema sets are the schema's (`tests/test_config.py` proves it; a map is
    built from the schema by `mapping.engine_configs.build_map_config`): 1.5625 cm voxels, blocks of 8^3 voxels
    (12.5 cm), a pool of 64k blocks; the block index (12 x 12 x 4 m here) and the 640x480 frames come from the
    scene, the class counts from the label sets.
    """

    # --- geometry ---
    voxel_size: float = 0.015625  # voxel edge length in metres (4 m / 256, the paper's 1.5 cm)
    block_size: int = 8  # voxels per block edge; even (2x2x2 cells are stored contiguously)
    sdf_trunc: float = 0.04  # TSDF truncation distance in metres; stored tsdf = sdf / sdf_trunc
    depth_min: float = 0.1  # depth readings below this (metres) are ignored
    depth_max: float = 4.0  # depth readings above this (metres) are ignored
    max_weight: float = 255.0  # cap of the per-voxel TSDF weight; beyond it the average keeps moving
    # world xyz of the block index's min corner; on the block lattice it is the state's (`compiled_layout`)
    grid_origin: tuple[float, float, float] = (-6.0, -6.0, -2.0)
    grid_shape: tuple[int, int, int] = (96, 96, 32)  # dense block index size, in blocks per axis
    block_capacity: int = 65536  # B: pool slots, the last one a scratch slot never allocated
    max_touched_blocks: int = 12288  # M: touched-block list length per frame (more are counted, not integrated)
    alloc_pixel_stride: int = 4  # depth subsampling used to find the blocks a frame touches
    alloc_depth_samples: int = 3  # samples per pixel ray over [d - trunc, d + trunc] for block finding
    # touched blocks integrated per loop step (cost follows the touched count; the map is the same for any);
    # 0: by the backend when the step is traced (`integrate_chunk_for_backend`)
    integrate_chunk_blocks: int = 0
    pool_chunk_blocks: int = 1024  # allocated blocks per loop step of pool-wide passes (cost follows num_blocks)
    # --- images ---
    image_height: int = 480  # H of every depth/colour frame
    image_width: int = 640  # W of every depth/colour frame
    pixel_stride: int = 2  # subsampling of the per-pixel instance images (lookup and integration)
    # --- instances ---
    instance_capacity: int = 1024  # K: rows of the instance table
    instance_slots: int = 2  # S: instance ids stored per voxel
    instance_lookup_offsets: tuple[float, ...] = (-1.0, 0.0, 1.0)  # ray offsets (voxels) probed per pixel lookup
    overlap_cell_capacity: int = 0  # occupied 2x2x2 cells counted at most (pool order); 0 = all cells (no drops)
    cell_chunk: int = 4096  # occupied cells per inner loop step of the counting and editing passes
    # Occupied cells the refinement's census keeps listed for its renaming pass (8 bytes each, allocated
    # per refinement). A map with more occupied cells is still renamed exactly, by listing them again
    # (~2x slower renaming); 0 disables the list. Off by default: with the kept census, the census pass and
    # its list serve only the first merge step, a loaded map's and the final merge, while the list's buffers
    # cost every merge step ~1 ms (3.2 -> 2.1 ms on scene0000_00, which ends with 173k occupied cells).
    cell_list_capacity: int = 0
    overlap_ids_per_cell: int = 4  # distinct instances kept per 2x2x2 cell for the inflated overlap
    num_classes: int = 20  # C: closed-set classes (NYUv2 20-class label set)
    num_open_labels: int = 38  # O: open-set labels of interest

    def __post_init__(self) -> None:
        # Sequences given as lists become tuples, so that the config stays hashable.
        object.__setattr__(self, "grid_origin", tuple(float(x) for x in self.grid_origin))
        object.__setattr__(self, "grid_shape", tuple(int(x) for x in self.grid_shape))
        object.__setattr__(self, "instance_lookup_offsets", tuple(float(x) for x in self.instance_lookup_offsets))
        problems = []
        if len(self.grid_origin) != 3 or len(self.grid_shape) != 3:
            problems.append("grid_origin and grid_shape need 3 entries")
        if self.block_size < 2 or self.block_size % 2:
            problems.append(f"block_size must be even and >= 2, got {self.block_size}")
        if self.block_capacity < 2:
            problems.append("block_capacity must be >= 2 (one slot is the scratch slot)")
        if min(self.grid_shape, default=0) < 1:
            problems.append(f"grid_shape must be positive, got {self.grid_shape}")
        if not 0 < self.depth_min < self.depth_max:
            problems.append("need 0 < depth_min < depth_max")
        if self.voxel_size <= 0 or self.sdf_trunc <= 0:
            problems.append("voxel_size and sdf_trunc must be positive")
        if self.alloc_depth_samples < 1 or self.alloc_pixel_stride < 1 or self.pixel_stride < 1:
            problems.append("strides and sample counts must be >= 1")
        if min(self.pool_chunk_blocks, self.cell_chunk) < 1 or self.integrate_chunk_blocks < 0:
            problems.append("chunk sizes must be >= 1 (integrate_chunk_blocks: >= 0, 0 = by the backend)")
        if self.overlap_cell_capacity < 0:
            problems.append("overlap_cell_capacity must be >= 0 (0 = every cell)")
        if self.cell_list_capacity < 0:
            problems.append("cell_list_capacity must be >= 0")
        if self.instance_slots < 1 or self.instance_capacity < 1 or self.overlap_ids_per_cell < 1:
            problems.append("instance_slots, instance_capacity and overlap_ids_per_cell must be >= 1")
        if self.instance_capacity > MAX_INSTANCE_CAPACITY:
            problems.append(f"instance_capacity must be <= {MAX_INSTANCE_CAPACITY} (16-bit ids), got {self.instance_capacity}")
        if not self.instance_lookup_offsets:
            problems.append("instance_lookup_offsets needs at least one offset")
        if problems:
            raise ValueError("invalid MapConfig: " + "; ".join(problems))

    # ----------------------------------------------------------------------------------------------
    # Derived sizes.
    @property
    def voxels_per_block(self) -> int:
        """V = block_size^3."""
        return self.block_size**3

    @property
    def block_length(self) -> float:
        """Edge length of a block in metres."""
        return self.block_size * self.voxel_size

    @property
    def origin_on_lattice(self) -> bool:
        """Whether `grid_origin` is a whole number of blocks (as `for_bounds` and growth make it): then the state
        carries the origin (`VoxelBlocks.origin_block`) and the compiled steps do not depend on it."""
        cells = np.asarray(self.grid_origin) / self.block_length
        return bool(np.all(np.abs(cells - np.round(cells)) < 1e-9))

    @property
    def origin_block(self) -> tuple[int, int, int]:
        """`grid_origin` in whole blocks (rounded; exact when `origin_on_lattice`)."""
        x, y, z = (int(round(o / self.block_length)) for o in self.grid_origin)
        return x, y, z

    def compiled_layout(self) -> "MapConfig":
        """The config the jitted engine steps are compiled for: this one with an on-lattice origin replaced by
        zeros (the steps read the origin from the state), so that maps that differ only in where their block
        index lies share one compiled program. An off-lattice origin stays (it is compiled in)."""
        return _compiled_layout(self)

    @property
    def num_grid_blocks(self) -> int:
        """Entries of the dense block index."""
        return int(np.prod(self.grid_shape))

    @property
    def dummy_slot(self) -> int:
        """The scratch pool slot (B - 1): padding of fixed-size slot lists points there; never allocated."""
        return self.block_capacity - 1

    @property
    def subsampled_shape(self) -> tuple[int, int]:
        """(Hs, Ws): shape of the per-pixel instance images, pixel (r, c) <-> full-res (r*stride, c*stride)."""
        s = self.pixel_stride
        return (-(-self.image_height // s), -(-self.image_width // s))

    @property
    def cell_capacity(self) -> int:
        """Occupied 2x2x2 cells the counting passes visit at most (`overlap_cell_capacity`, 0 = every cell)."""
        every = self.block_capacity * self.voxels_per_block // 8
        return every if self.overlap_cell_capacity <= 0 else min(self.overlap_cell_capacity, every)

    @property
    def grid_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World-space (min, max) corners covered by the block index."""
        lo = np.asarray(self.grid_origin, np.float64)
        return lo, lo + np.asarray(self.grid_shape, np.float64) * self.block_length

    # ----------------------------------------------------------------------------------------------
    @classmethod
    def for_bounds(
        cls,
        bounds_min: Sequence[float],
        bounds_max: Sequence[float],
        margin: float | None = None,
        **kw,
    ) -> "MapConfig":
        """A config whose block index covers `[bounds_min, bounds_max]` (world metres) plus a margin.

        The origin is snapped to the block lattice (a multiple of the block length), so that the same
        bounds always give the same voxel lattice, and the shape is rounded up to whole `GRID_SHAPE_BUCKET`s
        of blocks, so that rooms of similar size share their compiled steps. `margin` defaults to one block
        plus the truncation distance; every other field can be passed as a keyword.
        """
        probe = cls(**kw)
        length = probe.block_length
        if margin is None:
            margin = length + probe.sdf_trunc
        lo = np.asarray(bounds_min, np.float64) - margin
        hi = np.asarray(bounds_max, np.float64) + margin
        if lo.shape != (3,) or hi.shape != (3,) or np.any(hi <= lo):
            raise ValueError(f"bounds must be two xyz points with min < max, got {bounds_min}, {bounds_max}")
        origin = np.floor(lo / length) * length
        shape = np.maximum(1, np.ceil((hi - origin) / length - 1e-9)).astype(int)
        # rounded up to whole buckets: scenes of similar size get the same index shape, hence the same compiled
        # steps (the origin is the state's, see `compiled_layout`); 4 bytes per extra index cell
        shape = -(-shape // GRID_SHAPE_BUCKET) * GRID_SHAPE_BUCKET
        return dataclasses.replace(probe, grid_origin=tuple(origin.tolist()), grid_shape=tuple(shape.tolist()))

    def memory_bytes(self) -> int:
        """Approximate bytes of one `MapState` for this config (device arrays only)."""
        b, v, s, k = self.block_capacity, self.voxels_per_block, self.instance_slots, self.instance_capacity
        # tsdf, weight, colour (f16 x 3), instance id (i16) + weight per slot; a scratch int32 per 2x2x2 cell and
        # 128 bits (bytes) of instance ids per block
        pool = b * v * (4 + 4 + 6 + 6 * s) + b * (v // 8) * 4 + b * 128
        index = self.num_grid_blocks * 4 + b * 12
        table = k * (1 + 4 * (self.num_classes + self.num_open_labels) + 7 * 4 + 12 * k)
        return int(pool + index + table)

    def describe(self) -> str:
        """One line for logs: lattice, capacities and memory."""
        lo, hi = self.grid_bounds
        return (
            f"voxel {self.voxel_size * 100:.4g} cm, blocks {self.block_size}^3, index {self.grid_shape} "
            f"over [{', '.join(f'{x:.2f}' for x in lo)}] - [{', '.join(f'{x:.2f}' for x in hi)}] m, "
            f"pool {self.block_capacity} blocks, {self.max_touched_blocks} per frame, "
            f"{self.instance_capacity} instances x {self.instance_slots} slots/voxel, "
            f"~{self.memory_bytes() / 2**20:.0f} MiB"
        )


@functools.lru_cache(maxsize=64)
def _compiled_layout(config: MapConfig) -> MapConfig:
    if not config.origin_on_lattice or config.grid_origin == (0.0, 0.0, 0.0):
        return config
    return dataclasses.replace(config, grid_origin=(0.0, 0.0, 0.0))


__all__ = ["MapConfig", "GRID_SHAPE_BUCKET", "integrate_chunk_for_backend"]
