"""Host-side extraction from the voxel-block pool: mesh, surface points, instance point sets (NumPy).

Nothing here is jitted: these run once per export on arrays copied to the host. The allocated blocks
are assembled chunk by chunk into small dense volumes (`chunk_blocks`^3 blocks plus a one-voxel
apron taken from the neighbouring blocks), so memory stays bounded for a whole room. Voxels whose
weight is below `min_weight`, or whose block is not allocated, are invalid: a marching-cubes cube or
a zero-crossing edge is used only if all its corners are valid, so no surface appears in unobserved
space.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import MapState, VoxelBlocks, local_voxel_index, voxel_offsets


def _host_blocks(state_or_blocks) -> dict[str, np.ndarray]:
    blocks: VoxelBlocks = state_or_blocks.blocks if isinstance(state_or_blocks, MapState) else state_or_blocks
    n = int(blocks.num_blocks)
    return {
        "coords": np.asarray(blocks.block_coords)[:n],
        "tsdf": np.asarray(blocks.tsdf)[:n],
        "weight": np.asarray(blocks.weight)[:n],
        "color": np.asarray(blocks.color)[:n],  # half precision: widened chunk by chunk (`_chunks`' volumes)
        "instance_id": np.asarray(blocks.instance_id)[:n],
        "instance_weight": np.asarray(blocks.instance_weight)[:n],
    }


def _raster_blocks(values: np.ndarray, bs: int) -> np.ndarray:
    """`(B, V, ...)` pool rows (2x2x2-cell order, `state.local_voxel_index`) -> `(B, bs, bs, bs, ...)` blocks in
    (x, y, z) raster order: one transpose of the cell layout, no gather."""
    c, tail = bs // 2, values.shape[2:]
    cells = values.reshape(-1, c, c, c, 2, 2, 2, *tail)
    return cells.transpose(0, 1, 4, 2, 5, 3, 6, *range(7, 7 + len(tail))).reshape(-1, bs, bs, bs, *tail)


def _pool_blocks(blocks: np.ndarray) -> np.ndarray:
    """The inverse of `_raster_blocks`: `(B, bs, bs, bs)` -> `(B, V)` pool rows."""
    bs = blocks.shape[1]
    c = bs // 2
    return blocks.reshape(-1, c, 2, c, 2, c, 2).transpose(0, 1, 3, 5, 2, 4, 6).reshape(len(blocks), bs**3)


class _PoolColors:
    """A chunk's colour volume `(n, n, n, 3)` float32 read from the pool rows where it is indexed (integer voxel
    coordinates, as `_sample_linear` indexes a volume): the same values as the dense volume (half precision widened,
    0 in unallocated blocks) without building it, 4.5 MiB a chunk of which a mesh's vertices read a few per cent."""

    def __init__(self, color_rows: np.ndarray, row_of_block: np.ndarray, local: np.ndarray, n: int):
        """`row_of_block`: the pool row of each of the chunk's blocks (-1: none); `local` `(bs, bs, bs)`: a block's
        raster voxel -> its pool column."""
        self.color_rows, self.row_of_block, self.local, self.bs = color_rows, row_of_block, local, local.shape[0]
        self.shape, self.ndim = (n, n, n, color_rows.shape[-1]), 4

    def __getitem__(self, index: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
        x, y, z = index
        bs = self.bs
        row = self.row_of_block[x // bs, y // bs, z // bs]
        values = self.color_rows[np.maximum(row, 0), self.local[x % bs, y % bs, z % bs]].astype(np.float32)
        values[row < 0] = 0.0
        return values


def _chunks(host: dict, config: MapConfig, chunk_blocks: int, min_weight: float) -> Iterator[tuple]:
    """Yield `(origin_voxel int[3], tsdf, valid, color)` dense volumes of `chunk_blocks * bs + 1` voxels
    per axis: the chunk's blocks plus the first voxel layer of the neighbours on the + sides; the colour is a
    `_PoolColors`, read where it is indexed. The tsdf volume is overwritten by the next chunk: a caller copies
    what it keeps."""
    bs = config.block_size
    coords = host["coords"]
    if len(coords) == 0:
        return
    # Each block feeds its own chunk, and (as the apron) the chunks just below it along each axis
    # where it sits on the chunk's lower face.
    block_parts: list[np.ndarray] = []
    chunk_parts: list[np.ndarray] = []
    rel_parts: list[np.ndarray] = []
    for corner in np.ndindex(2, 2, 2):
        d = np.asarray(corner)
        on_face = np.all((d == 0) | (coords % chunk_blocks == 0), axis=1)
        chunk = coords // chunk_blocks - d
        block_parts.append(np.nonzero(on_face)[0])
        chunk_parts.append(chunk[on_face])
        rel_parts.append((coords - chunk * chunk_blocks)[on_face])
    block_ids, chunk_ids, rel = (np.concatenate(x) for x in (block_parts, chunk_parts, rel_parts))
    order = np.lexsort(chunk_ids.T[::-1])
    block_ids, chunk_ids, rel = block_ids[order], chunk_ids[order], rel[order]
    starts = np.flatnonzero(np.any(np.diff(chunk_ids, axis=0) != 0, axis=1)) + 1
    n = chunk_blocks * bs + 1
    size = (chunk_blocks + 1) * bs
    # one pair of volumes refilled for every chunk: fresh ones cost their page faults each time (~10 % of a mesh)
    vol_t = np.empty((size, size, size), np.float32)
    vol_w = np.empty((size, size, size), np.float32)
    local = _raster_blocks(np.arange(bs**3)[None], bs)[0]
    for group in np.split(np.arange(len(block_ids)), starts):
        chunk = chunk_ids[group[0]]
        if not np.any(np.all(rel[group] < chunk_blocks, axis=1)):
            continue  # only apron blocks: this chunk holds no block of its own
        vol_t.fill(1.0)
        vol_w.fill(0.0)
        # the chunk's blocks, put in raster order here (not the whole pool up front), written at once through
        # block-major views of the volumes
        b, r = block_ids[group], rel[group]
        for volume, name in ((vol_t, "tsdf"), (vol_w, "weight")):
            values = _raster_blocks(host[name][b], bs)
            _block_view(volume, chunk_blocks + 1, bs)[r[:, 0], r[:, 1], r[:, 2]] = values
        row_of_block = np.full((chunk_blocks + 1,) * 3, -1, np.int64)
        row_of_block[r[:, 0], r[:, 1], r[:, 2]] = b
        valid = (vol_w >= min_weight)[:n, :n, :n]
        yield chunk * chunk_blocks * bs, vol_t[:n, :n, :n], valid, _PoolColors(host["color"], row_of_block, local, n)


def _packed_rows(key: np.ndarray) -> np.ndarray:
    """`key int64 (N, 3)` as one uint64 per row in the same lexicographic order (x first), when the rows' ranges
    fit in 64 bits (a 1-D unique is ~5x faster than a unique over rows; a room's vertex keys take 64); else
    `key` itself."""
    low = key.min(axis=0)
    bits = [int(span).bit_length() for span in key.max(axis=0) - low]
    if sum(bits) > 64:
        return key
    # column by column (non-negative once shifted: read as unsigned without a copy): one column's temporaries at a
    # time, not a shifted copy of all three
    packed = (key[:, 0] - low[0]).view(np.uint64) << np.uint64(bits[1] + bits[2])
    packed |= (key[:, 1] - low[1]).view(np.uint64) << np.uint64(bits[2])
    packed |= (key[:, 2] - low[2]).view(np.uint64)
    return packed


def _block_view(volume: np.ndarray, blocks: int, bs: int) -> np.ndarray:
    """`volume (blocks*bs, blocks*bs, blocks*bs, ...)` as a writable view `(blocks, blocks, blocks, bs, bs, bs, ...)`."""
    tail = volume.shape[3:]
    view = volume.reshape(blocks, bs, blocks, bs, blocks, bs, *tail)
    return view.transpose(0, 2, 4, 1, 3, 5, *range(6, 6 + len(tail)))


def _voxel_to_world(g: np.ndarray, config: MapConfig) -> np.ndarray:
    """World coordinates of (fractional) global voxel coordinates (voxel centres at integers)."""
    world = g + 0.5  # one temporary, then in place: the same values as `origin + (g + 0.5) * voxel_size`
    world *= config.voxel_size
    world += np.asarray(config.grid_origin)
    return world.astype(np.float32)


def _sample_linear(volume: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Trilinear samples of `volume (X, Y, Z, ...)` at fractional voxel coordinates `(N, 3)`."""
    lo = np.floor(points).astype(int)
    lo = np.clip(lo, 0, np.asarray(volume.shape[:3]) - 1)
    f = points - lo
    hi = np.minimum(lo + 1, np.asarray(volume.shape[:3]) - 1)
    out: np.ndarray | float = 0.0
    for corner in np.ndindex(2, 2, 2):
        idx = [np.where(corner[a], hi[:, a], lo[:, a]) for a in range(3)]
        wgt = np.prod([f[:, a] if corner[a] else 1.0 - f[:, a] for a in range(3)], axis=0)
        out = out + volume[idx[0], idx[1], idx[2]] * wgt.reshape((-1,) + (1,) * (volume.ndim - 3))
    assert isinstance(out, np.ndarray)  # the eight corners have been added
    return out


def _sample_on_edges(volume: np.ndarray, points: np.ndarray) -> np.ndarray:
    """`_sample_linear` at marching cubes' vertices, which lie on voxel edges (at most one fractional coordinate):
    the edge's two corners only, the same values (the other six trilinear weights are exactly 0, and adding a 0
    changes no sum). Points off the edges (Lewiner's vertices inside ambiguous cubes) are sampled trilinearly."""
    if len(points) == 0:
        return _sample_linear(volume, points)
    lo = np.clip(np.floor(points).astype(int), 0, np.asarray(volume.shape[:3]) - 1)
    f = points - lo
    fractional = f != 0
    rows = np.arange(len(points))
    axis = np.argmax(fractional, axis=1)  # axis 0 (weight 0 on its far corner) for a point on a voxel
    hi = lo.copy()
    hi[rows, axis] = np.minimum(lo[rows, axis] + 1, np.asarray(volume.shape[:3])[axis] - 1)
    along = f[rows, axis]
    tail = (-1,) + (1,) * (volume.ndim - 3)
    near = volume[lo[:, 0], lo[:, 1], lo[:, 2]] * (1.0 - along).reshape(tail)
    far = volume[hi[:, 0], hi[:, 1], hi[:, 2]] * along.reshape(tail)
    samples = 0.0 + near + far
    inside = np.flatnonzero(fractional.sum(axis=1) > 1)
    if len(inside):
        samples[inside] = _sample_linear(volume, points[inside])
    return samples


def _dilated_by_one(cube: np.ndarray) -> np.ndarray:
    """`(m, m, m)` bool -> `(m + 1,) * 3`: the voxels that are a corner of some true cube (an OR over the 2x2x2
    cubes around each voxel, one axis at a time)."""
    m = cube.shape[0]
    grown = cube
    for axis in range(3):
        shape = list(grown.shape)
        shape[axis] = m + 1
        wider = np.zeros(shape, bool)
        low, high = [slice(None)] * 3, [slice(None)] * 3
        low[axis], high[axis] = slice(0, m), slice(1, m + 1)
        wider[tuple(low)] |= grown
        wider[tuple(high)] |= grown
        grown = wider
    return grown


def extract_mesh(state, config: MapConfig, min_weight: float = 1.0, chunk_blocks: int = 8):
    """Marching-cubes mesh of the global TSDF's zero level set.

    Args:
      state: a `MapState` or `VoxelBlocks`.
      config: the map config.
      min_weight: voxels with a smaller integration weight are unobserved.
      chunk_blocks: blocks per axis of the dense chunks the pool is assembled into.

    Returns:
      `(vertices float32 (N, 3) world metres, faces int32 (F, 3), colors uint8 (N, 3))`; faces are
      oriented with normals pointing to free space (positive tsdf). Vertices shared by two chunks
      are merged.
    """
    from skimage.measure import marching_cubes  # heavy (~0.5 s): imported when a mesh is asked for

    host = _host_blocks(state)
    verts, faces, colors = [], [], []
    offset = 0
    for origin, tsdf, valid, color in _chunks(host, config, chunk_blocks, min_weight):
        # cube (i, j, k) -> (i+1, j+1, k+1) is usable iff its 8 corners are valid (an AND over the 2x2x2
        # neighbourhood, one axis at a time); skimage reads the mask at the cube's upper corner.
        pairs = valid[:-1] & valid[1:]
        pairs = pairs[:, :-1] & pairs[:, 1:]
        cube = pairs[:, :, :-1] & pairs[:, :, 1:]
        if not cube.any():
            continue
        mask = np.zeros_like(valid)
        mask[1:, 1:, 1:] = cube
        corners = _dilated_by_one(cube)  # the voxels that are a corner of a usable cube
        volume = np.where(corners, tsdf, np.float32(1.0))
        if not (volume.min() < 0.0 and np.any(volume[corners] > 0.0)):
            continue
        try:
            v, f, _, _ = marching_cubes(volume, level=0.0, mask=mask, gradient_direction="descent", allow_degenerate=False)
        except (RuntimeError, ValueError):  # no crossing inside the usable cubes
            continue
        if len(f) == 0:
            continue
        # narrowed per chunk (the same values as narrowing at the end): a room's mesh is a million vertices
        colors.append(np.clip(np.round(_sample_on_edges(color, v)), 0, 255).astype(np.uint8))
        verts.append(v + origin)
        faces.append((f + offset).astype(np.int32))
        offset += len(v)
    if not verts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.uint8)
    g = np.concatenate(verts)  # each list let go as soon as it is joined
    del verts
    f = np.concatenate(faces)
    del faces
    c = np.concatenate(colors)
    del colors
    # merge the copies of vertices on chunk faces (identical coordinates: same values, same arithmetic)
    key = g * 4096  # rounded in place: the vertices' temporaries are tens of MiB each at the outputs' peak
    rounded = np.round(key, out=key).astype(np.int64)
    del key
    packed = _packed_rows(rounded)
    del rounded
    _, first, inverse = np.unique(packed, axis=0 if packed.ndim == 2 else None, return_index=True, return_inverse=True)
    del packed
    f = inverse.reshape(-1).astype(np.int32)[f]
    del inverse
    kept = g[first]
    del g
    return _voxel_to_world(kept, config), f, c[first]


def extract_surface_points(state, config: MapConfig, min_weight: float = 1.0, chunk_blocks: int = 8):
    """Zero crossings of the global TSDF along voxel edges (Open3D's extract_point_cloud equivalent).

    Returns:
      `(points float32 (N, 3) world metres, colors uint8 (N, 3))`: one point per edge between two
      valid voxels whose tsdf changes sign, linearly interpolated; colour interpolated likewise.
    """
    host = _host_blocks(state)
    points, colors = [], []
    for origin, tsdf, valid, color in _chunks(host, config, chunk_blocks, min_weight):
        n = tsdf.shape[0] - 1  # edges start inside the chunk, end inside it or in the apron
        for axis in range(3):
            lo = [slice(0, n)] * 3
            hi = [slice(0, n)] * 3
            hi[axis] = slice(1, n + 1)
            t0, t1 = tsdf[tuple(lo)], tsdf[tuple(hi)]
            ok = valid[tuple(lo)] & valid[tuple(hi)] & ((t0 < 0) != (t1 < 0))
            idx = np.argwhere(ok)
            if len(idx) == 0:
                continue
            a, b = t0[ok], t1[ok]
            frac = a / (a - b)
            p = idx.astype(np.float64)
            p[:, axis] += frac
            step = np.zeros(3, int)
            step[axis] = 1
            c0 = color[idx[:, 0], idx[:, 1], idx[:, 2]]
            c1 = color[idx[:, 0] + step[0], idx[:, 1] + step[1], idx[:, 2] + step[2]]
            points.append(p + origin)
            colors.append(c0 * (1 - frac[:, None]) + c1 * frac[:, None])
    if not points:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    return _voxel_to_world(np.concatenate(points), config), np.clip(np.round(np.concatenate(colors)), 0, 255).astype(np.uint8)


#: Pool rows taken at a time by `extract_instance_points` and `extract_surface_voxels` (their temporaries are a few
#: bytes per voxel of a slice, not of the pool).
POOL_SLICE_BLOCKS = 2048


def extract_instance_points(
    state,
    config: MapConfig,
    min_weight: float = 1.0,
    on_surface: bool = False,
    surface_band: float | None = None,
    min_tsdf_weight: float = 1.0,
    min_share: float = 0.0,
) -> dict[int, np.ndarray]:
    """Voxel centres of each instance's voxels.

    Args:
      state: a `MapState` or `VoxelBlocks`.
      config: the map config.
      min_weight: minimum instance-slot weight for a voxel to belong to the instance.
      min_share: a slot also needs at least this share of the voxel's strongest slot weight: where a
        well-observed instance (the floor under a smear, a chair under a merged mask's table) holds the
        voxel, a weakly supported second instance does not get it (0: every slot).
      on_surface: keep only voxels on the global surface: TSDF weight >= `min_tsdf_weight` and
        `|tsdf| * sdf_trunc <= surface_band` (default one voxel).
      surface_band: see `on_surface`, metres.
      min_tsdf_weight: see `on_surface`.

    Returns:
      `{instance id: float32 (Ni, 3) world coordinates}` for every id with at least one voxel.
    """
    host = _host_blocks(state)
    if len(host["coords"]) == 0:
        return {}

    offsets = voxel_offsets(config.block_size)
    band = config.voxel_size if surface_band is None else surface_band
    parts: list[tuple[np.ndarray, np.ndarray]] = []
    for start in range(0, len(host["coords"]), POOL_SLICE_BLOCKS):  # a slice of the pool at a time: small temporaries
        rows = slice(start, start + POOL_SLICE_BLOCKS)
        ids, weights = host["instance_id"][rows], host["instance_weight"][rows]
        keep = (ids >= 0) & (weights >= min_weight)
        if min_share > 0:
            held = np.where(ids >= 0, weights, 0.0)
            strongest = held[..., 0].copy()  # slot by slot: numpy reduces a short last axis ~7x slower
            for slot in range(1, held.shape[-1]):
                np.maximum(strongest, held[..., slot], out=strongest)
            keep &= weights >= min_share * strongest[..., None]
        if on_surface:
            tsdf, weight = host["tsdf"][rows], host["weight"][rows]
            keep &= ((weight >= min_tsdf_weight) & (np.abs(tsdf) * config.sdf_trunc <= band))[..., None]
        block, voxel, _ = np.nonzero(keep)
        g = host["coords"][rows][block] * config.block_size + offsets[voxel]
        parts.append((ids[keep], _voxel_to_world(g.astype(np.float64), config)))
    inst = np.concatenate([p[0] for p in parts])
    points = np.concatenate([p[1] for p in parts])
    order = np.argsort(inst, kind="stable")
    inst, points = inst[order], points[order]
    unique, starts = np.unique(inst, return_index=True)
    return {int(i): p for i, p in zip(unique, np.split(points, starts[1:]))}


def extract_surface_voxels(state, config: MapConfig, min_weight: float = 1.0, band: float | None = None):
    """Centres of the voxels on the global surface, without assembling volumes: a cheap stand-in for the mesh
    where the surface is only looked at from afar (the overview picture is drawn from these while the mesh is
    still being extracted).

    Args:
      state: a `MapState` or `VoxelBlocks`.
      config: the map config.
      min_weight: voxels with a smaller integration weight are unobserved.
      band: a voxel is on the surface when `|tsdf| * sdf_trunc` is at most this many metres (default: one voxel);
        so is the voxel on the positive side of a sign change to a valid neighbour, in its block or the next (a
        thin, noisy surface passing between two voxels farther than the band from it): every edge the mesh crosses
        has one of its voxels drawn.

    Returns:
      `(points float32 (N, 3) world metres, colors uint8 (N, 3))`, in pool order.
    """
    host = _host_blocks(state)
    limit = (config.voxel_size if band is None else band) / config.sdf_trunc
    offsets = voxel_offsets(config.block_size)
    across = _crossings_between_blocks(host, config.block_size, min_weight)
    points, colors = [np.zeros((0, 3), np.float32)], [np.zeros((0, 3), np.uint8)]
    for start in range(0, len(host["coords"]), POOL_SLICE_BLOCKS):
        rows = slice(start, start + POOL_SLICE_BLOCKS)
        tsdf = host["tsdf"][rows]
        surface = _surface_mask(tsdf, host["weight"][rows] >= min_weight, limit, config.block_size) | across[rows]
        block, voxel = np.nonzero(surface)
        g = host["coords"][rows][block] * config.block_size + offsets[voxel]
        points.append(_voxel_to_world(g.astype(np.float64), config))
        colors.append(np.clip(np.round(host["color"][rows][block, voxel].astype(np.float32)), 0, 255).astype(np.uint8))
    return np.concatenate(points), np.concatenate(colors)


def _crossings_between_blocks(host: dict, bs: int, min_weight: float) -> np.ndarray:
    """`(B, V)` bool: the voxels on a block's faces on the positive side of a sign change to the valid voxel facing
    them in the next block along x, y or z (the in-block changes are `_surface_mask`'s)."""
    coords = host["coords"].astype(np.int64)
    marked = np.zeros(host["tsdf"].shape, bool)
    if len(coords) == 0:
        return marked
    low, span = coords.min(axis=0), np.ptp(coords, axis=0) + 2
    linear = ((coords[:, 0] - low[0]) * span[1] + (coords[:, 1] - low[1])) * span[2] + (coords[:, 2] - low[2])
    order = np.argsort(linear)
    face = np.stack(np.meshgrid(np.arange(bs), np.arange(bs), indexing="ij"), -1).reshape(-1, 2)
    voxels = marked.shape[1]
    tsdf, observed, flat = host["tsdf"].reshape(-1), (host["weight"] >= min_weight).reshape(-1), marked.reshape(-1)
    for axis in range(3):
        step = np.zeros(3, np.int64)
        step[axis] = 1
        target = linear + ((step[0] * span[1] + step[1]) * span[2] + step[2])
        found = np.minimum(np.searchsorted(linear[order], target), len(order) - 1)
        here = np.flatnonzero(linear[order][found] == target)  # blocks whose + neighbour along `axis` exists
        there = order[found[here]]
        last, first = (np.insert(face, axis, value, axis=1) for value in (bs - 1, 0))
        last_voxel = local_voxel_index(last[:, 0], last[:, 1], last[:, 2], bs)
        first_voxel = local_voxel_index(first[:, 0], first[:, 1], first[:, 2], bs)
        # flat indices into the (B, V) rows: `np.take` on them is ~3x quicker than indexing with two arrays
        at_last = here[:, None] * voxels + last_voxel[None, :]
        at_first = there[:, None] * voxels + first_voxel[None, :]
        t_last, t_first = np.take(tsdf, at_last), np.take(tsdf, at_first)
        change = np.take(observed, at_last) & np.take(observed, at_first) & ((t_last >= 0) != (t_first >= 0))
        flat[at_last] |= change & (t_last >= 0)  # a voxel once per axis: no index repeats
        flat[at_first] |= change & (t_first >= 0)
    return marked


def _surface_mask(tsdf: np.ndarray, valid: np.ndarray, limit: float, bs: int) -> np.ndarray:
    """`(B, V)` bool: valid voxels with `|tsdf| <= limit`, or on the positive side of a sign change to a valid
    neighbour within the block (`extract_surface_voxels`)."""
    surface = valid & (np.abs(tsdf) <= limit)
    raster_valid, positive = _raster_blocks(valid, bs), _raster_blocks(tsdf >= 0, bs)
    crossing = np.zeros_like(positive)
    for axis in (1, 2, 3):
        lo, hi = [slice(None)] * 4, [slice(None)] * 4
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        change = (positive[tuple(lo)] != positive[tuple(hi)]) & raster_valid[tuple(lo)] & raster_valid[tuple(hi)]
        crossing[tuple(lo)] |= change & positive[tuple(lo)]
        crossing[tuple(hi)] |= change & positive[tuple(hi)]
    return surface | _pool_blocks(crossing)


__all__ = ["extract_mesh", "extract_surface_points", "extract_surface_voxels", "extract_instance_points"]
