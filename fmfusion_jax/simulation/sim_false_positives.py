"""Simulated detections of no annotated object (`simulate`): confusers, blobs on walls and floor, phantoms fixed
in the world, background regions taken for furniture and over-segmented textures."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping

import numpy as np
from scipy.spatial import cKDTree

from fmfusion_jax.labels import LabelSets, load_label_sets, load_likelihood
from fmfusion_jax.simulation.noise import (
    NoiseModel,
    background_region,
    random_blob,
    split_into_pieces,
)
from fmfusion_jax.simulation.sim_labels import _PHANTOM_STREAM, _LabelModel, _Object

#: Labels a false blob on a wall or the floor comes with: what GroundingDINO hallucinates on flat surfaces.
BLOB_LABELS = {"wall": ("picture", "window", "door", "shelf", "cabinet", "curtain"), "floor": ("carpet", "table", "bin", "chair")}


#: Classes a phantom (`persistent_phantoms`) is taken for: what detectors see in an empty spot of a room.
PHANTOM_CLASSES = ("cabinet", "chair", "table", "bookshelf", "picture", "desk", "sofa", "otherfurniture")


#: Classes a background region (`background_rate`) is taken for: furniture that lines walls and floors.
BACKGROUND_CLASSES = ("cabinet", "bookshelf", "refrigerator", "table", "counter", "desk", "door")


#: Background classes: the surfaces phantoms and background regions lie on (with pixels of no instance).
SURFACE_CLASSES = ("wall", "floor")


#: `texture_prob`: most pieces per region, share of them detected, and share labelled from the region's
#: class column (the rest take a random prompt label); a piece's score is at most this above the box threshold.
TEXTURE_MAX_PIECES = 24


TEXTURE_KEEP_SHARE = 0.7


TEXTURE_CLASS_LABEL_SHARE = 0.5


TEXTURE_SCORE_SPAN = 0.08


def _confuser_objects(
    model: _LabelModel,
    areas: Mapping[int, int],
    instance_classes: Mapping[int, int],
    objects: list[_Object],
    noise: NoiseModel,
    class_names: list[str],
    rng: np.random.Generator,
) -> list[_Object]:
    """The visible non-target objects that are confusers (per seed and object), as objects of the class
    they are taken for, each with its fixed label at a normal score."""
    taken = {m for o in objects for m in o.instances}
    out = []
    for i in sorted(areas):
        if i in instance_classes or i in taken or areas[i] < noise.min_mask_pixels:
            continue
        hit, class_index, label = model.confuser(i, class_names)
        if hit:
            out.append(_Object((i,), i, class_index, areas[i], {label: model.score(rng)}))
    return out


def _blobs(
    image: np.ndarray, instance_classes: Mapping[int, int], class_names: list[str], model: _LabelModel, rng: np.random.Generator
) -> list[tuple[np.ndarray, dict[str, float]]]:
    """`blob_rate`: false blobs on a wall or the floor, each with a label such a surface is mistaken for
    (`BLOB_LABELS`) at a normal score, clipped to the surface they lie on."""
    count = int(rng.poisson(model.noise.blob_rate))
    known = set(model.names)
    surfaces = {
        i: class_names[c] for i, c in instance_classes.items() if 0 <= c < len(class_names) and class_names[c] in BLOB_LABELS
    }
    if not count or not surfaces:
        return []
    pixels = np.flatnonzero(np.isin(image, list(surfaces)).ravel())
    if pixels.size == 0:
        return []
    height, width = image.shape
    max_radius = min(70.0, 0.15 * min(height, width))
    out = []
    for _ in range(count):
        pixel = int(pixels[rng.integers(pixels.size)])
        instance = int(image.flat[pixel])
        names = [name for name in BLOB_LABELS[surfaces[instance]] if name in known]
        label = names[int(rng.integers(len(names)))]
        blob = random_blob(image.shape, (pixel % width, pixel // width), rng, min(15.0, max_radius / 2), max_radius)
        out.append((blob & (image == instance), {label: model.score(rng)}))
    return out


@dataclasses.dataclass(frozen=True)
class Phantom:
    """A persistent false positive (`persistent_phantoms`): a place of the world that the detector takes for
    an object whenever it is in view.

    Attributes:
      center: `(3,)` float64 world point on the wall, floor or unannotated surface, metres.
      radius: metres; the phantom is the seen surface inside this sphere.
      class_index: the closed class it is taken for.
      label: its one open-set label (drawn from that class's published column).
    """

    center: np.ndarray
    radius: float
    class_index: int
    label: str


def place_phantoms(
    vertices: np.ndarray,
    faces: np.ndarray,
    instance_ids: np.ndarray,
    instance_classes: Mapping[int, int],
    noise: NoiseModel,
    label_sets: LabelSets | None = None,
    likelihood: np.ndarray | None = None,
    tries: int = 50,
) -> list[Phantom]:
    """The phantoms of a scene for `noise` (its seed): `round(persistent_phantoms)` points drawn uniformly
    over the area of the mesh's background faces (wall, floor, unannotated, non-target), away from the
    target objects where possible (no target vertex within the radius, up to `tries` draws).

    Phantom `k` draws from its own stream `[seed, _PHANTOM_STREAM, k]`, so raising the count only adds
    phantoms.

    Args:
      vertices: `(V, 3)` mesh vertices, world frame, metres.
      faces: `(F, 3)` triangles.
      instance_ids: `(V,)` instance id of each vertex, 0 = none.
      instance_classes: closed-class index of each target instance (`render.instance_classes`).
    """

    count, radius = int(round(noise.persistent_phantoms)), float(noise.persistent_radius_m)
    if count < 1 or radius <= 0 or noise.persistent_detect_prob <= 0:
        return []
    label_sets = label_sets or load_label_sets()
    likelihood = np.asarray(load_likelihood("statistical") if likelihood is None else likelihood, np.float64)
    class_names = list(label_sets.class_names)
    surface = {class_names.index(n) for n in SURFACE_CLASSES if n in class_names}
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64).reshape(-1, 3)
    targets = [i for i, c in instance_classes.items() if c not in surface]
    is_target = np.isin(np.asarray(instance_ids), targets)
    background = faces[~is_target[faces].any(axis=1)]
    if background.shape[0] == 0:
        return []
    corners = vertices[background]  # (F', 3, 3)
    areas = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    if areas.sum() <= 0:
        return []
    tree = cKDTree(vertices[is_target]) if is_target.any() else None
    kinds = [class_names.index(c) for c in PHANTOM_CLASSES if c in class_names]
    published = likelihood / likelihood.sum(axis=0, keepdims=True)
    out = []
    for k in range(count):
        rng = np.random.default_rng([int(noise.seed), _PHANTOM_STREAM, k])
        for _ in range(tries):
            a, b = rng.random(2)
            if a + b > 1.0:  # uniform on the triangle
                a, b = 1.0 - a, 1.0 - b
            tri = corners[int(rng.choice(areas.size, p=areas / areas.sum()))]
            center = tri[0] + a * (tri[1] - tri[0]) + b * (tri[2] - tri[0])
            if tree is None or not np.isfinite(tree.query(center, distance_upper_bound=radius)[0]):
                break
        class_index = kinds[int(rng.integers(len(kinds)))]
        label = label_sets.open_labels[int(rng.choice(published.shape[0], p=published[:, class_index]))]
        out.append(Phantom(center, radius, class_index, label))
    return out


def phantom_mask(phantom: Phantom, depth: np.ndarray, T_world_camera: np.ndarray, intrinsics) -> np.ndarray:
    """`(H, W)` bool: the pixels whose seen surface (the frame's depth, back-projected) lies inside the
    phantom's sphere. What is in front of it hides it, so the mask is the phantom's visible part.

    Args:
      depth: `(H, W)` metres, 0 = invalid.
      T_world_camera: `(4, 4)` camera-to-world pose.
      intrinsics: `CameraIntrinsics` of the depth camera (scaled to `H x W` when it differs).
    """
    depth = np.asarray(depth, np.float32)
    height, width = depth.shape
    if (intrinsics.width, intrinsics.height) != (width, height):
        intrinsics = intrinsics.scaled(width, height)
    T = np.asarray(T_world_camera, np.float64)
    x, y, z = T[:3, :3].T @ (phantom.center - T[:3, 3])
    r = phantom.radius
    mask = np.zeros((height, width), bool)
    if z + r <= 0:
        return mask  # behind the camera
    if z - r > 0.05:
        # The sphere lies in the box [x +- r] x [y +- r] x [z +- r]: its image lies within the corners'.
        us = [intrinsics.cx + intrinsics.fx * (x + dx) / (z + dz) for dx in (-r, r) for dz in (-r, r)]
        vs = [intrinsics.cy + intrinsics.fy * (y + dy) / (z + dz) for dy in (-r, r) for dz in (-r, r)]
        u0, u1 = max(int(np.floor(min(us))), 0), min(int(np.ceil(max(us))) + 1, width)
        v0, v1 = max(int(np.floor(min(vs))), 0), min(int(np.ceil(max(vs))) + 1, height)
    else:
        u0, u1, v0, v1 = 0, width, 0, height
    if u0 >= u1 or v0 >= v1:
        return mask
    crop = depth[v0:v1, u0:u1].astype(np.float64)
    vv, uu = np.mgrid[v0:v1, u0:u1]
    px = (uu - intrinsics.cx) * crop / intrinsics.fx
    py = (vv - intrinsics.cy) * crop / intrinsics.fy
    mask[v0:v1, u0:u1] = (crop > 0) & ((px - x) ** 2 + (py - y) ** 2 + (crop - z) ** 2 < r * r)
    return mask


def _phantom_detections(
    phantoms: Iterable[tuple[np.ndarray, str]], not_target: np.ndarray, model: _LabelModel, rng: np.random.Generator
) -> list[tuple[np.ndarray, dict[str, float]]]:
    """`persistent_phantoms`: each phantom in view (its projected mask, less the target objects' pixels, at
    least `min_mask_pixels`) detected with `persistent_detect_prob`, its fixed label at a normal score."""
    noise, out = model.noise, []
    for mask, label in phantoms:
        mask = np.asarray(mask, bool) & not_target
        detected, score = rng.random() < noise.persistent_detect_prob, model.score(rng)
        if detected and mask.sum() >= noise.min_mask_pixels:
            out.append((mask, {label: score}))
    return out


def _background_regions(
    image: np.ndarray, background: np.ndarray, class_names: list[str], model: _LabelModel, rng: np.random.Generator
) -> list[tuple[np.ndarray, dict[str, float]]]:
    """`background_rate`: regions of the background (`background` pixels: wall, floor, no ground truth) taken
    for furniture (`BACKGROUND_CLASSES`), each a strip (`background_strip_share`) or a large patch centred
    on a background pixel and clipped to the background, labelled from the class's published column."""
    count = int(rng.poisson(model.noise.background_rate))
    pixels = np.flatnonzero(background.ravel())
    kinds = [class_names.index(c) for c in BACKGROUND_CLASSES if c in class_names]
    if not count or pixels.size == 0 or not kinds:
        return []
    width = image.shape[1]
    out = []
    for _ in range(count):
        pixel = int(pixels[rng.integers(pixels.size)])
        strip = rng.random() < model.noise.background_strip_share
        region = background_region(image.shape, (pixel % width, pixel // width), rng, strip) & background
        class_index = kinds[int(rng.integers(len(kinds)))]
        label = model.names[int(rng.choice(len(model.names), p=model.published[:, class_index]))]
        out.append((region, {label: model.score(rng)}))
    return out


def _texture_pieces(
    image: np.ndarray,
    areas: Mapping[int, int],
    instance_classes: Mapping[int, int],
    model: _LabelModel,
    prompt: list[str],
    rng: np.random.Generator,
) -> list[tuple[np.ndarray, dict[str, float]]]:
    """`texture_prob`: visible regions (any instance of at least 4 pieces' size) over-segmented into small
    pieces of about `texture_piece_share` of the image (`TEXTURE_KEEP_SHARE` of them detected), each with a
    prompt label drawn from the region's class column (`TEXTURE_CLASS_LABEL_SHARE`, targets only) or a
    random prompt label, at a low score."""
    noise = model.noise
    piece = noise.texture_piece_share * image.size
    index = {name: i for i, name in enumerate(model.names)}
    out = []
    for i in sorted(areas):
        if rng.random() >= noise.texture_prob or areas[i] < 4 * piece or not prompt:
            continue
        count = int(np.clip(round(areas[i] / piece), 2, TEXTURE_MAX_PIECES))
        for part in split_into_pieces(image == i, count, rng):
            keep, own, pick = rng.random(), rng.random(), rng.random()
            score = float(rng.uniform(noise.box_threshold, noise.box_threshold + TEXTURE_SCORE_SPAN))
            if keep >= TEXTURE_KEEP_SHARE:
                continue
            # One uniform draw picks the label either way, so the draws per piece do not depend on the prompt.
            weights = np.ones(len(prompt))
            if i in instance_classes and own < TEXTURE_CLASS_LABEL_SHARE:
                column = np.array([model.columns[index[p], instance_classes[i]] if p in index else 0.0 for p in prompt])
                weights = column if column.sum() > 0 else weights
            cumulative = np.cumsum(weights / weights.sum())
            label = prompt[min(int(np.searchsorted(cumulative, pick, side="right")), len(prompt) - 1)]
            out.append((part, {label: score}))
    return out
