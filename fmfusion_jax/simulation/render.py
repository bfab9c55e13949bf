"""Per-pixel ground-truth instance images of real frames, from the annotated mesh and the frame's depth.

Each valid depth pixel is back-projected to the world and takes the instance id of the nearest
ground-truth mesh vertex, if that vertex is within `max_distance`. The depth is the surface the camera
actually sees, so occlusion comes for free and the image is registered to the depth exactly. (Rasterizing
the mesh would also label pixels without depth, but it disagrees with the depth wherever the mesh is
incomplete and costs a z-buffer; here a small hole filling covers the pixels without depth instead.)

Cost: one KD-tree query per sampled pixel. At `stride=2` (a quarter of the pixels, the result upsampled
by nearest neighbour) a 640x480 frame takes a few tens of milliseconds.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from fmfusion_jax.labels import LabelSets, load_label_sets
from fmfusion_jax.types import CameraIntrinsics

if TYPE_CHECKING:  # pragma: no cover
    from fmfusion_jax.io.ground_truth import SceneGroundTruth


class GroundTruthRenderer:
    """Renders `(H, W)` int32 ground-truth instance-id images (0 = no instance) for posed depth frames.

    Args:
      vertices: `(V, 3)` ground-truth mesh vertices, world frame, metres.
      instance_ids: `(V,)` instance id of each vertex, 0 = none.
      faces: `(F, 3)` triangles; when given, edge midpoints and face centroids are added to the
        look-up points (`densify_mesh`), halving their spacing. ScanNet's decimated meshes have edges of
        6 cm (median) up to 14 cm on flat surfaces, too coarse for a vertex-only look-up within 5 cm.
      max_distance: a pixel whose back-projected point is farther than this (m) from every vertex is
        left unlabelled (0). The sample scene's depth lies a median 2.4 cm from the mesh.
      stride: sample every `stride`-th pixel in both directions, then upsample by nearest neighbour.
      fill_radius_px: pixels without depth take the label of the nearest labelled pixel within this
        many (full-resolution) pixels, as a segmentation of the colour image would cover them; 0: off.
      max_hole_px: unlabelled regions of at most this many (full-resolution) pixels are filled from
        their surroundings (speckle from unannotated clutter, depth noise); 0: off.
      smooth: a 3x3 median filter (at the sampled resolution) that removes single-pixel speckle at
        instance borders, where nearest-vertex look-ups alternate between the two sides.
      workers: threads of the KD-tree query.
    """

    def __init__(
        self,
        vertices: np.ndarray,
        instance_ids: np.ndarray,
        faces: np.ndarray | None = None,
        max_distance: float = 0.05,
        stride: int = 2,
        fill_radius_px: float = 8.0,
        max_hole_px: int = 400,
        smooth: bool = True,
        workers: int = 1,
    ):
        vertices = np.asarray(vertices, np.float64)
        instance_ids = np.asarray(instance_ids)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or instance_ids.shape != (vertices.shape[0],):
            raise ValueError(f"vertices {vertices.shape} and instance_ids {instance_ids.shape} do not match")
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        if faces is not None and len(faces):
            vertices, instance_ids = densify_mesh(vertices, np.asarray(faces, np.int64), instance_ids)
        self.tree = cKDTree(vertices)
        # Compact ids 1..K so that the median filter can run on uint16 images; 0 stays "none".
        self.instance_values, compact = np.unique(instance_ids, return_inverse=True)
        if self.instance_values[0] != 0:
            self.instance_values = np.concatenate([[0], self.instance_values])
            compact = compact + 1
        if self.instance_values.size > 65535:
            raise ValueError("more than 65534 ground-truth instances")
        self._vertex_compact = np.concatenate([compact.astype(np.uint16), [0]])  # index V = no neighbour
        self.max_distance = float(max_distance)
        self.stride = int(stride)
        self.fill_radius_px = float(fill_radius_px)
        self.max_hole_px = int(max_hole_px)
        self.smooth = bool(smooth)
        self.workers = int(workers)

    @classmethod
    def from_ground_truth(cls, gt: "SceneGroundTruth", **kwargs) -> "GroundTruthRenderer":
        return cls(gt.vertices, gt.instance_ids, gt.faces, **kwargs)

    def render(self, depth: np.ndarray, T_world_camera: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
        """`(H, W)` int32 instance ids of the frame (0 where no instance is near the seen surface).

        Args:
          depth: `(H, W)` float32 metres, 0 = invalid.
          T_world_camera: `(4, 4)` camera-to-world pose.
          intrinsics: the depth camera, for an `H x W` image.
        """
        depth = np.asarray(depth, np.float32)
        height, width = depth.shape
        if (intrinsics.width, intrinsics.height) != (width, height):
            intrinsics = intrinsics.scaled(width, height)
        s = self.stride
        sub = depth[::s, ::s]
        vs, us = np.nonzero(sub > 0)
        z = sub[vs, us].astype(np.float64)
        u = us * float(s)
        v = vs * float(s)
        x = (u - intrinsics.cx) * z / intrinsics.fx
        y = (v - intrinsics.cy) * z / intrinsics.fy
        T = np.asarray(T_world_camera, np.float64)
        points = np.empty((z.size, 3))
        for row in range(3):
            points[:, row] = T[row, 0] * x + T[row, 1] * y + T[row, 2] * z + T[row, 3]
        _, nearest = self.tree.query(points, k=1, distance_upper_bound=self.max_distance, workers=self.workers)
        labels: np.ndarray = np.zeros(sub.shape, np.uint16)
        labels[vs, us] = self._vertex_compact[nearest]

        if self.smooth:
            labels = cv2.medianBlur(labels, 3)
        unlabelled = labels == 0
        if (self.fill_radius_px > 0 or self.max_hole_px > 0) and unlabelled.any() and not unlabelled.all():
            fill = np.zeros_like(unlabelled)
            if self.max_hole_px > 0:
                count, components, stats, _ = cv2.connectedComponentsWithStats(unlabelled.astype(np.uint8), connectivity=4)
                small = stats[:, cv2.CC_STAT_AREA] * s * s <= self.max_hole_px
                small[0] = False  # component 0 is the labelled pixels
                fill |= small[components]
            distance, (iv, iu) = ndimage.distance_transform_edt(unlabelled, return_indices=True)
            if self.fill_radius_px > 0:
                fill |= unlabelled & (sub <= 0) & (distance * s <= self.fill_radius_px)
            labels[fill] = labels[iv[fill], iu[fill]]
        if s > 1:
            labels = np.repeat(np.repeat(labels, s, axis=0), s, axis=1)[:height, :width]
        return self.instance_values[labels].astype(np.int32)


def densify_mesh(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices plus each edge's midpoint and each face's centroid, with labels: `(V + E + F, 3)`, `(V + E + F,)`.

    A midpoint takes the label of its edge's lower-index end (both, when they agree); a centroid takes the
    label shared by at least two of its corners, else its first corner's.
    """
    labels = np.asarray(labels)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    midpoints = 0.5 * (vertices[edges[:, 0]] + vertices[edges[:, 1]])
    corner = labels[faces]
    centroid_labels = np.where(corner[:, 1] == corner[:, 2], corner[:, 1], corner[:, 0])
    centroids = vertices[faces].mean(axis=1)
    points = np.concatenate([vertices, midpoints, centroids])
    point_labels = np.concatenate([labels, labels[edges[:, 0]], centroid_labels])
    return points, point_labels


def instance_classes(gt: "SceneGroundTruth", label_sets: LabelSets | None = None) -> dict[int, int]:
    """Closed-class index (column of the likelihood) of each ground-truth instance of a closed class.

    An instance's class is the most common nyu40 id of its vertices; instances whose class is not one of
    the 20 closed classes are left out (the simulator treats them as background / false-positive sources).
    """
    label_sets = label_sets or load_label_sets()
    return instance_classes_from_arrays(gt.instance_ids, gt.nyu40_ids, label_sets)


def instance_classes_from_arrays(
    instance_ids: np.ndarray, nyu40_ids: np.ndarray, label_sets: LabelSets | None = None
) -> dict[int, int]:
    """`instance_classes` from per-vertex `(V,)` instance ids and nyu40 ids."""
    label_sets = label_sets or load_label_sets()
    to_class = label_sets.nyu40_to_class_index()
    instance_ids = np.asarray(instance_ids, np.int64)
    nyu40_ids = np.asarray(nyu40_ids, np.int64)
    keep = instance_ids > 0
    pairs, counts = np.unique(np.stack([instance_ids[keep], nyu40_ids[keep]], axis=1), axis=0, return_counts=True)
    result: dict[int, int] = {}
    best_count: dict[int, int] = {}
    for (instance, nyu40), count in zip(pairs.tolist(), counts.tolist()):
        if count > best_count.get(instance, 0):
            best_count[instance] = count
            if nyu40 in to_class:
                result[instance] = to_class[nyu40]
            else:
                result.pop(instance, None)
    return result
