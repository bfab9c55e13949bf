"""Ray casting of scenes made of oriented boxes, in NumPy: depth, hit box, surface normal, shading.

The renderer is exact (every pixel's ray is intersected analytically with the boxes) and fast enough for
benchmarks because each box is only tested against the pixels of its own screen-space bounding rectangle
(its 8 corners, clipped at the near plane, projected), in row blocks of at most `max_pixels` pixels. A room
whose walls, floor and ceiling are the faces of an axis-aligned box holding the camera (the `Enclosure`)
costs one slab exit per pixel instead of six big rectangles.

Conventions: camera frame x right, y down, z forward (OpenCV / ScanNet); a pixel `(u, v)` (column, row,
integers at pixel centres) looks along `((u - cx) / fx, (v - cy) / fy, 1)`, so the ray parameter of a hit
*is* its z-depth.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from fmfusion_jax.types import CameraIntrinsics

if TYPE_CHECKING:  # pragma: no cover
    pass

#: ScanNet's depth camera at 640x480 (scene0000_00 `intrinsic_depth.txt`); scale it for other sizes.
SCANNET_INTRINSICS = CameraIntrinsics(fx=577.590698, fy=578.729797, cx=318.905426, cy=242.683609, width=640, height=480)

#: Rays hitting nothing within this z-depth (metres) start at the near plane: closer surfaces are skipped.
NEAR = 0.02

#: Material codes understood by `texture`.
MATERIALS = ("plain", "wood", "tiles", "fabric", "glass", "metal", "carpet", "paint")
_MATERIAL_CODES = {name: code for code, name in enumerate(MATERIALS)}


def material_code(name: str) -> int:
    """The integer code of a material name (see `MATERIALS`); `ValueError` for an unknown one."""
    try:
        return _MATERIAL_CODES[name]
    except KeyError:
        raise ValueError(f"unknown material {name!r}; expected one of {MATERIALS}") from None


def yaw_rotation(yaw: float) -> np.ndarray:
    """`(3, 3)` rotation by `yaw` radians about +z."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclasses.dataclass(frozen=True)
class BoxArrays:
    """Oriented boxes as structure-of-arrays (what the renderer consumes).

    Attributes:
      centers: `(B, 3)` float64 world centres, metres.
      half_extents: `(B, 3)` float64 half sizes along the box's local axes, metres (> 0).
      rotations: `(B, 3, 3)` float64 box-to-world rotations (columns = local axes in world).
      colors: `(B, 3)` float32 albedo in [0, 1].
      materials: `(B,)` int32 material codes (`MATERIALS`).
      instance_ids: `(B,)` int32 instance of each box (0 = none).
    """

    centers: np.ndarray
    half_extents: np.ndarray
    rotations: np.ndarray
    colors: np.ndarray
    materials: np.ndarray
    instance_ids: np.ndarray

    def __len__(self) -> int:
        return int(self.centers.shape[0])

    def corners(self) -> np.ndarray:
        """`(B, 8, 3)` world corners."""
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
        local = signs[None] * self.half_extents[:, None, :]
        return np.einsum("bij,bkj->bki", self.rotations, local) + self.centers[:, None, :]


@dataclasses.dataclass(frozen=True)
class Enclosure:
    """An axis-aligned room holding the camera: rays leaving through a face hit that face's box.

    Attributes:
      lower, upper: `(3,)` the room's interior bounds, metres.
      face_boxes: `(6,)` int, index in the `BoxArrays` of the box whose inner face is each room face, in the
        order x-, x+, y-, y+, z-, z+. These boxes are skipped by the generic pass, so their inner face must be
        exactly the room face (the rest of them is outside the room and invisible from inside).
    """

    lower: np.ndarray
    upper: np.ndarray
    face_boxes: np.ndarray


@dataclasses.dataclass(frozen=True)
class RayHits:
    """The nearest hit of every pixel.

    Attributes:
      depth: `(H, W)` float32 z-depth in metres, `inf` where nothing was hit.
      box: `(H, W)` int32 index of the box hit, -1 where nothing.
      face: `(H, W)` int8 face of that box: `2 * axis + (sign > 0)` (0..5), -1 where nothing.
    """

    depth: np.ndarray
    box: np.ndarray
    face: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.box >= 0


def camera_rays(intrinsics: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame ray slopes: `x (W,)` = `(u - cx) / fx` and `y (H,)` = `(v - cy) / fy` (z = 1)."""
    x = (np.arange(intrinsics.width, dtype=np.float64) - intrinsics.cx) / intrinsics.fx
    y = (np.arange(intrinsics.height, dtype=np.float64) - intrinsics.cy) / intrinsics.fy
    return x, y


def _screen_rect(corners_camera: np.ndarray, intrinsics: CameraIntrinsics, near: float):
    """Pixel rectangle `(u0, u1, v0, v1)` (half-open) covering a box seen from the camera, or None.

    `corners_camera` `(8, 3)` are the box corners in the camera frame, in `BoxArrays.corners` order. The part
    of the box in front of the near plane is the convex hull of the corners in front and of the points where
    the box's 12 edges cross the plane; the rectangle holds the projection of those points.
    """
    z = corners_camera[:, 2]
    front = z > near
    if not front.any():
        return None
    parts = [corners_camera[front]]
    if not front.all():
        i, j = _EDGES[:, 0], _EDGES[:, 1]
        crossing = front[i] != front[j]
        a, b = corners_camera[i[crossing]], corners_camera[j[crossing]]
        s = (near - a[:, 2]) / (b[:, 2] - a[:, 2])
        parts.append(a + s[:, None] * (b - a))
    points = np.concatenate(parts)
    u = intrinsics.fx * points[:, 0] / points[:, 2] + intrinsics.cx
    v = intrinsics.fy * points[:, 1] / points[:, 2] + intrinsics.cy
    u0 = max(int(np.floor(u.min())), 0)
    u1 = min(int(np.ceil(u.max())) + 1, intrinsics.width)
    v0 = max(int(np.floor(v.min())), 0)
    v1 = min(int(np.ceil(v.max())) + 1, intrinsics.height)
    if u0 >= u1 or v0 >= v1:
        return None
    return u0, u1, v0, v1


_EDGES = np.array([(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1])


def raycast_boxes(
    boxes: BoxArrays,
    T_world_camera: np.ndarray,
    intrinsics: CameraIntrinsics,
    enclosure: Enclosure | None = None,
    near: float = NEAR,
    max_pixels: int = 1 << 16,
) -> RayHits:
    """Nearest box hit of every pixel of a pinhole camera.

    Args:
      boxes: the scene.
      T_world_camera: `(4, 4)` camera-to-world pose (OpenCV camera axes).
      intrinsics: the camera.
      enclosure: an axis-aligned room around the camera (see `Enclosure`), or None.
      near: hits closer than this z-depth are ignored (a camera inside a box sees out of it).
      max_pixels: pixels processed at once per box (bounds the temporary memory to ~40 bytes each).

    Returns:
      `RayHits` of shape `(intrinsics.height, intrinsics.width)`.
    """
    height, width = intrinsics.height, intrinsics.width
    R_wc = np.asarray(T_world_camera, np.float64)[:3, :3]
    origin = np.asarray(T_world_camera, np.float64)[:3, 3]
    xs, ys = camera_rays(intrinsics)
    depth = np.full((height, width), np.inf, np.float32)
    box_index = np.full((height, width), -1, np.int32)
    face = np.full((height, width), -1, np.int8)
    skip = np.zeros(len(boxes), bool)
    block_rows = max(1, max_pixels // max(width, 1))

    if enclosure is not None:
        skip[np.asarray(enclosure.face_boxes)] = True
        lower = np.asarray(enclosure.lower, np.float64)
        upper = np.asarray(enclosure.upper, np.float64)
        for v0 in range(0, height, block_rows):
            v1 = min(v0 + block_rows, height)
            _enclosure_exit(
                R_wc,
                origin,
                xs,
                ys[v0:v1],
                lower,
                upper,
                np.asarray(enclosure.face_boxes),
                depth[v0:v1],
                box_index[v0:v1],
                face[v0:v1],
            )

    # Camera-frame corners of every box, for the screen rectangles.
    corners_camera = (boxes.corners() - origin) @ R_wc
    for b in range(len(boxes)):
        if skip[b]:
            continue
        rect = _screen_rect(corners_camera[b], intrinsics, near)
        if rect is None:
            continue
        u0, u1, v0, v1 = rect
        R_b = boxes.rotations[b]
        M = R_b.T @ R_wc  # camera direction -> box-frame direction
        o = R_b.T @ (origin - boxes.centers[b])
        h = boxes.half_extents[b]
        rows = max(1, max_pixels // (u1 - u0))
        for r0 in range(v0, v1, rows):
            r1 = min(r0 + rows, v1)
            _box_block(M, o, h, xs[u0:u1], ys[r0:r1], near, b, depth[r0:r1, u0:u1], box_index[r0:r1, u0:u1], face[r0:r1, u0:u1])
    return RayHits(depth, box_index, face)


def _box_block(M, o, h, xs, ys, near, b, depth, box_index, face) -> None:
    """Slab test of one box against a block of rays; updates the views `depth`, `box_index`, `face` in place."""
    t_near = None
    axis_near = None
    t_far = None
    for k in range(3):
        # Box-frame direction component k of the rays: separable in columns (x) and rows (y).
        d = (M[k, 2] + M[k, 1] * ys)[:, None].astype(np.float32) + (M[k, 0] * xs)[None, :].astype(np.float32)
        d[d == 0] = 1e-12
        inv = np.reciprocal(d)
        a = inv * np.float32(-o[k])
        spread = np.abs(inv)
        spread *= np.float32(h[k])
        lo = a - spread
        hi = a + spread
        if t_near is None:
            t_near, t_far = lo, hi
            axis_near = np.zeros(lo.shape, np.int8)
        else:
            assert axis_near is not None and t_far is not None  # set with t_near on the first axis
            better = lo > t_near
            t_near = np.where(better, lo, t_near)
            axis_near[better] = k
            np.minimum(t_far, hi, out=t_far)
    assert t_near is not None and t_far is not None and axis_near is not None  # the three axes are done
    hit = (t_near <= t_far) & (t_near > near) & (t_near < depth)
    if not hit.any():
        return
    depth[hit] = t_near[hit]
    box_index[hit] = b
    # Entry face: on axis k the ray enters through the -h side when its direction is positive.
    k = axis_near[hit]
    rows, cols = np.nonzero(hit)
    d_k = M[k, 2] + M[k, 1] * ys[rows] + M[k, 0] * xs[cols]
    face[hit] = (2 * k + (d_k < 0)).astype(np.int8)


def _enclosure_exit(R_wc, origin, xs, ys, lower, upper, face_boxes, depth, box_index, face) -> None:
    """Where the rays of a block leave the room box (the camera is inside it)."""
    best = None
    best_face = None
    for k in range(3):
        d = (R_wc[k, 2] + R_wc[k, 1] * ys)[:, None] + (R_wc[k, 0] * xs)[None, :]
        positive = d > 0
        bound = np.where(positive, upper[k], lower[k])
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (bound - origin[k]) / d
        t[d == 0] = np.inf
        f = (2 * k + positive).astype(np.int8)
        if best is None:
            best, best_face = t, f
        else:
            closer = t < best
            best = np.where(closer, t, best)
            best_face = np.where(closer, f, best_face)
    assert best is not None and best_face is not None  # the three axes are done
    closer = best < depth
    depth[closer] = best[closer]
    box_index[closer] = face_boxes[best_face[closer]]
    # The hit box's inner face is the opposite side of that box: the room's x- face is the +x side of the wall.
    face[closer] = best_face[closer] ^ 1


def _face_normal_table(boxes: BoxArrays) -> np.ndarray:
    """`(6 B + 1, 3)` float32: the world normal of face `f` of box `b` at row `6 b + f`, then a zero row."""
    axes = np.transpose(boxes.rotations, (0, 2, 1))  # (B, 3 local axes, 3 world)
    table = np.stack([-axes[:, 0], axes[:, 0], -axes[:, 1], axes[:, 1], -axes[:, 2], axes[:, 2]], axis=1)
    return np.concatenate([table.reshape(-1, 3), np.zeros((1, 3))]).astype(np.float32)


def _world_points(T: np.ndarray, xs: np.ndarray, ys: np.ndarray, z: np.ndarray):
    """World points `(px, py, pz)` and unit ray directions `(vx, vy, vz)`, each `(H, W)` float32."""
    R, t = T[:3, :3], T[:3, 3]
    ray = [
        (np.float32(R[c, 2]) + (R[c, 1] * ys).astype(np.float32)[:, None]) + (R[c, 0] * xs).astype(np.float32)[None, :]
        for c in range(3)
    ]
    inv = np.float32(1.0) / np.sqrt(ray[0] * ray[0] + ray[1] * ray[1] + ray[2] * ray[2])
    points = tuple(ray[c] * z + np.float32(t[c]) for c in range(3))
    view = tuple(ray[c] * inv for c in range(3))
    return points, view


def texture(materials: np.ndarray, box_index: np.ndarray, boxes: BoxArrays, world) -> np.ndarray:
    """Multiplicative albedo pattern of surface points, `(M,)` float32 around 1.

    Args:
      materials: `(M,)` int material codes.
      box_index: `(M,)` the box each point lies on (wood grain follows the box's longest axis).
      boxes: the boxes.
      world: the points' world coordinates, three `(M,)` arrays (x, y, z).
    """
    m = materials
    x, y, z = world
    grain = _hash_noise(x, y, z, 0.01)  # fixed speckle in [0, 1), the same from every view
    factor = np.float32(0.975) + np.float32(0.05) * grain

    wood = m == _MATERIAL_CODES["wood"]
    glass = m == _MATERIAL_CODES["glass"]
    for mask, kind in ((wood, "wood"), (glass, "glass")):
        if not mask.any():
            continue
        idx = np.nonzero(mask)[0]
        b = box_index[idx]
        rel = np.stack([x[idx], y[idx], z[idx]], axis=1) - boxes.centers[b].astype(np.float32)
        local = np.einsum("mji,mj->mi", boxes.rotations[b].astype(np.float32), rel)
        he = boxes.half_extents[b].astype(np.float32)
        if kind == "wood":
            long_axis = np.argmax(he, axis=1)
            rows = np.arange(idx.size)
            a = local[rows, long_axis]
            c = local[rows, (long_axis + 1) % 3] + local[rows, (long_axis + 2) % 3]
            grain_wave = np.sin(np.float32(2 * np.pi) * (14.0 * c + 0.2 * np.sin(np.float32(2 * np.pi * 1.7) * a)))
            boards = c / np.float32(0.16)
            seam = np.abs(boards - np.round(boards)) < np.float32(0.025)  # board joints every 16 cm
            factor[idx] += np.float32(0.05) * grain_wave.astype(np.float32) - np.float32(0.18) * seam
        else:
            factor[idx] *= np.float32(0.85) + np.float32(0.3) * (local[:, 2] / np.maximum(he[:, 2], 1e-6) * 0.5 + 0.5)

    tiles = m == _MATERIAL_CODES["tiles"]
    if tiles.any():
        px, py = x[tiles] / np.float32(0.6), y[tiles] / np.float32(0.6)
        cx, cy = np.floor(px), np.floor(py)
        fx, fy = px - cx, py - cy
        checker = (cx + cy) % 2 == 0
        grout = (np.minimum(fx, 1 - fx) < 0.012) | (np.minimum(fy, 1 - fy) < 0.012)
        factor[tiles] *= np.where(checker, np.float32(1.0), np.float32(0.93)) * np.where(grout, np.float32(0.65), np.float32(1.0))

    fabric = m == _MATERIAL_CODES["fabric"]
    if fabric.any():
        f = np.float32(2 * np.pi * 20)
        factor[fabric] += np.float32(0.03) * np.sin(f * (x[fabric] + y[fabric])) * np.sin(f * z[fabric])

    carpet = m == _MATERIAL_CODES["carpet"]
    if carpet.any():
        factor[carpet] += np.float32(0.18) * (grain[carpet] - np.float32(0.5))
    return factor.astype(np.float32, copy=False)


def _hash_noise(x: np.ndarray, y: np.ndarray, z: np.ndarray, cell: float) -> np.ndarray:
    """A fixed pseudo-random value in [0, 1) per `cell`-sized cube of space: float32 like `x`."""
    scale = np.float32(1.0 / cell)
    h = np.floor(x * scale).astype(np.int32).view(np.uint32) * np.uint32(73856093)
    h ^= np.floor(y * scale).astype(np.int32).view(np.uint32) * np.uint32(19349663)
    h ^= np.floor(z * scale).astype(np.int32).view(np.uint32) * np.uint32(83492791)
    h ^= h >> np.uint32(13)
    h *= np.uint32(1274126177)
    h ^= h >> np.uint32(16)
    return (h & np.uint32(0xFFFF)).astype(np.float32) * np.float32(1.0 / 65536.0)


def lambert(normal, point, light_position: np.ndarray, view=None) -> np.ndarray:
    """Light intensity, float32: ambient + Lambertian point light (+ a weak headlight when `view` is given).

    `normal`, `point` and `view` (unit ray directions) are each three arrays (x, y, z) of the same shape.
    """
    light = np.asarray(light_position, np.float32)
    lx, ly, lz = (light[c] - point[c] for c in range(3))
    diffuse = (normal[0] * lx + normal[1] * ly + normal[2] * lz) / (np.sqrt(lx * lx + ly * ly + lz * lz) + np.float32(1e-6))
    np.clip(diffuse, 0.0, 1.0, out=diffuse)
    intensity = np.float32(0.38) + np.float32(0.55) * diffuse
    if view is not None:
        intensity += np.float32(0.12) * np.abs(normal[0] * view[0] + normal[1] * view[1] + normal[2] * view[2])
    return intensity.astype(np.float32, copy=False)


def raycast_rays(
    boxes: BoxArrays, origins: np.ndarray, directions: np.ndarray, skip: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of arbitrary rays (a small-batch helper, e.g. for camera checks).

    Args:
      origins: `(N, 3)` ray origins; directions: `(N, 3)` directions (any length: the returned parameter is in
        units of the direction's length).
      skip: `(B,)` bool boxes to ignore.

    Returns:
      `(t (N,), box (N,))`: the smallest positive ray parameter and the box index (inf / -1 where nothing).
    """
    origins = np.asarray(origins, np.float64)
    directions = np.asarray(directions, np.float64)
    o = np.einsum("bji,nbj->nbi", boxes.rotations, origins[:, None, :] - boxes.centers[None])
    d = np.einsum("bji,nj->nbi", boxes.rotations, directions)
    d = np.where(d == 0, 1e-12, d)
    inv = 1.0 / d
    lo = (-boxes.half_extents[None] - o) * inv
    hi = (boxes.half_extents[None] - o) * inv
    t_near = np.minimum(lo, hi).max(axis=2)
    t_far = np.maximum(lo, hi).min(axis=2)
    t = np.where(t_near > 0, t_near, t_far)  # from inside a box, the exit
    valid = (t_near <= t_far) & (t > 0)
    if skip is not None:
        valid &= ~np.asarray(skip, bool)[None]
    t = np.where(valid, t, np.inf)
    box = np.argmin(t, axis=1)
    best = t[np.arange(t.shape[0]), box]
    return best, np.where(np.isfinite(best), box, -1)
