"""The visible surfaces of a procedural scene as a triangle mesh with per-vertex ground truth (like ScanNet's
`_vh_clean_2.ply`), coloured by the renderer's lighting."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from fmfusion_jax.simulation import raycast
from fmfusion_jax.simulation.procedural import ProceduralScene


@dataclasses.dataclass(frozen=True)
class SceneMesh:
    """The visible surfaces of a scene as a triangle mesh, with per-vertex ground truth.

    Attributes:
      vertices: `(V, 3)` float32 metres.
      faces: `(F, 3)` int32 vertex indices, counter-clockwise seen from outside.
      colors: `(V, 3)` uint8 RGB (albedo x texture x the renderer's lighting, no noise).
      instance_ids: `(V,)` int32 instance of each vertex (>= 1).
      segment_ids: `(V,)` int32 over-segmentation: one segment per patch (at most `patch_size` square) of a box
        face; a segment never spans two instances.
      spacing: the grid spacing used, metres.
    """

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    instance_ids: np.ndarray
    segment_ids: np.ndarray
    spacing: float


def build_mesh(
    scene: ProceduralScene,
    spacing: float = 0.03,
    max_vertices: int = 300_000,
    patch_size: float = 0.4,
    include_ceiling: bool = True,
) -> SceneMesh:
    """Meshes the visible surfaces of the boxes on a regular grid.

    Every box face is a grid of about `spacing` metres (coarser when the mesh would exceed `max_vertices`).
    Grid cells that cannot be seen are dropped, like the unscanned parts of a ScanNet mesh: cells outside the
    room, and cells in contact with another box (the point 5 mm in front of the cell's centre lies in another
    box: the floor under a leg, a wall behind a cabinet, a shelf's end inside the side panel).
    """
    if spacing <= 0 or max_vertices < 1000 or patch_size <= 0:
        raise ValueError("spacing and patch_size must be positive, max_vertices at least 1000")
    boxes = scene.box_arrays()
    use = np.ones(len(boxes), bool)
    if not include_ceiling:
        use[scene.enclosure_boxes[5]] = False
    # Choose the spacing from the visible area (walls, floor, objects; the outer faces are dropped anyway).
    room = np.asarray(scene.room_size)
    area = 0.0
    for i in np.nonzero(use)[0]:
        he = boxes.half_extents[i]
        area += 8 * (he[0] * he[1] + he[1] * he[2] + he[0] * he[2])
    # Structural boxes contribute one face each (their others are outside the room).
    for e in scene.enclosure_boxes:
        if use[e]:
            he = boxes.half_extents[e]
            area -= 8 * (he[0] * he[1] + he[1] * he[2] + he[0] * he[2])
            area += 4 * np.sort(he)[1] * np.sort(he)[2]
    spacing = max(spacing, math.sqrt(area / (0.9 * max_vertices)))

    vertex_parts: list[np.ndarray] = []
    face_parts: list[np.ndarray] = []
    owner_parts: list[np.ndarray] = []
    segment_parts: list[np.ndarray] = []
    normal_parts: list[np.ndarray] = []
    offset, segment_base = 0, 0
    for i in np.nonzero(use)[0]:
        R, c, he = boxes.rotations[i], boxes.centers[i], boxes.half_extents[i]
        for axis in range(3):
            for sign in (-1.0, 1.0):
                u_axis, v_axis = (axis + 1) % 3, (axis + 2) % 3
                if sign < 0:
                    u_axis, v_axis = v_axis, u_axis
                nu = max(1, int(math.ceil(2 * he[u_axis] / spacing)))
                nv = max(1, int(math.ceil(2 * he[v_axis] / spacing)))
                gu = np.linspace(-he[u_axis], he[u_axis], nu + 1)
                gv = np.linspace(-he[v_axis], he[v_axis], nv + 1)
                U, V = np.meshgrid(gu, gv, indexing="ij")
                local = np.zeros((nu + 1, nv + 1, 3))
                local[..., axis] = sign * he[axis]
                local[..., u_axis] = U
                local[..., v_axis] = V
                world = local.reshape(-1, 3) @ R.T + c
                # Cells: (iu, iv) -> 2 triangles, counter-clockwise around the outward normal (u x v = normal).
                iu, iv = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
                v00 = (iu * (nv + 1) + iv).ravel()
                v10, v01, v11 = v00 + (nv + 1), v00 + 1, v00 + nv + 2
                cell_faces = np.stack([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)], 1)  # (C, 2, 3)
                # Segments: patches of the face.
                pu = max(1, int(math.ceil(2 * he[u_axis] / patch_size)))
                pv = max(1, int(math.ceil(2 * he[v_axis] / patch_size)))
                su = np.minimum((np.arange(nu + 1) * pu) // (nu + 1), pu - 1)
                sv = np.minimum((np.arange(nv + 1) * pv) // (nv + 1), pv - 1)
                seg = (su[:, None] * pv + sv[None, :]).ravel() + segment_base
                segment_base += pu * pv
                vertex_parts.append(world)
                face_parts.append(cell_faces + offset)
                owner_parts.append(np.full(world.shape[0], i))
                segment_parts.append(seg)
                normal_parts.append(np.broadcast_to(R[:, axis] * sign, world.shape))
                offset += world.shape[0]
    vertices = np.concatenate(vertex_parts)
    faces = np.concatenate(face_parts)  # (C, 2, 3)
    owners = np.concatenate(owner_parts)
    segments = np.concatenate(segment_parts)
    normals = np.concatenate(normal_parts)

    # Visibility of each cell from its centre.
    cell_owner = owners[faces[:, 0, 0]]
    centre = vertices[faces[:, 0, [0, 2]]].mean(axis=1)
    probe = centre + 0.005 * normals[faces[:, 0, 0]]
    keep = np.all((centre >= -1e-3) & (centre <= room + 1e-3), axis=1)
    by_x = np.argsort(probe[:, 0], kind="stable")
    sorted_x = probe[by_x, 0]
    for j in range(len(boxes)):
        lower = boxes.centers[j] - np.abs(boxes.rotations[j]) @ boxes.half_extents[j]
        upper = boxes.centers[j] + np.abs(boxes.rotations[j]) @ boxes.half_extents[j]
        candidates = by_x[np.searchsorted(sorted_x, lower[0], "left") : np.searchsorted(sorted_x, upper[0], "right")]
        q = probe[candidates]
        near = keep[candidates] & np.all((q >= lower) & (q <= upper), axis=1) & (cell_owner[candidates] != j)
        if not near.any():
            continue
        idx = candidates[near]
        local = (probe[idx] - boxes.centers[j]) @ boxes.rotations[j]
        inside = np.all(np.abs(local) <= boxes.half_extents[j], axis=1)
        keep[idx[inside]] = False
    faces = faces[keep].reshape(-1, 3)
    used = np.zeros(vertices.shape[0], bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    faces = remap[faces].astype(np.int32)
    vertices, owners, segments, normals = vertices[used], owners[used], segments[used], normals[used]
    _, segments = np.unique(segments, return_inverse=True)

    # Colours: the renderer's albedo x texture x lighting, seen from the light (no view term).
    v32, n32 = vertices.astype(np.float32), normals.astype(np.float32)
    point = (v32[:, 0], v32[:, 1], v32[:, 2])
    shade = raycast.lambert((n32[:, 0], n32[:, 1], n32[:, 2]), point, scene.light_position)
    shade *= raycast.texture(boxes.materials[owners], owners, boxes, point)
    colors = np.clip(boxes.colors[owners] * (shade + 0.06)[:, None] * 255 + 0.5, 0, 255).astype(np.uint8)
    return SceneMesh(
        vertices=vertices.astype(np.float32),
        faces=faces,
        colors=colors,
        instance_ids=boxes.instance_ids[owners].astype(np.int32),
        segment_ids=segments.astype(np.int32),
        spacing=float(spacing),
    )
