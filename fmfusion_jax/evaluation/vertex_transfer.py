"""Transfer of instances given as point sets (e.g. voxel centres of a fused map) onto the evaluation mesh."""

from __future__ import annotations

from typing import Sequence

import numpy as np


def points_to_vertex_masks(vertices: np.ndarray, instance_points: Sequence[np.ndarray],
                           radius: float = 0.08) -> np.ndarray:
    """Vertex masks of instances: a vertex joins the instance of its nearest point closer than `radius`.

    Tie rule: nearest instance wins, so the masks are disjoint like the benchmark's ground truth, where
    each vertex belongs to at most one instance. Letting every instance within `radius` claim a vertex
    would grow neighbouring instances into each other (a chair tucked under a table would take table
    vertices), costing both IoU. A point present in several instances goes to the first of them (lowest
    index); other exact distance ties go to whichever the KD-tree returns.

    Args:
      vertices: `(V, 3)` mesh vertices.
      instance_points: `P` arrays `(N_i, 3)` in the mesh frame; an empty one gives an empty mask.
      radius: metres; a vertex at least this far from every point belongs to no instance.

    Returns:
      `(P, V)` bool.
    """
    from scipy.spatial import cKDTree

    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    masks = np.zeros((len(instance_points), len(vertices)), bool)
    sets = [np.asarray(points, np.float64).reshape(-1, 3) for points in instance_points]
    if not sets or sum(len(s) for s in sets) == 0 or len(vertices) == 0:
        return masks
    points = np.concatenate(sets)
    owner = np.repeat(np.arange(len(sets)), [len(s) for s in sets])
    # np.unique keeps the first occurrence of a repeated point: the lowest instance index owns it.
    points, first = np.unique(points, axis=0, return_index=True)
    owner = owner[first]
    distances, nearest = cKDTree(points).query(vertices, k=1, distance_upper_bound=radius)
    hit = np.isfinite(distances)
    masks[owner[nearest[hit]], np.flatnonzero(hit)] = True
    return masks
