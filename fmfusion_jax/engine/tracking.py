"""Camera tracking: projective point-to-plane ICP of a depth frame against a reference frame.

Frame-to-frame: the reference is the previous (or the last well tracked) frame's vertex and normal maps in its
own camera frame; the result is `T_reference_current`, the current camera's pose in the reference camera's
frame. The host chains these into `T_world_camera` (`mapping.tracking`).

A frame's depth is first smoothed by a bilateral filter (`bilateral_depth`, as KinectFusion's): its vertices and
normals come from the smoothed depth. Per frame (`track_frame`), coarse to fine over an image pyramid
(`TrackingConfig.levels` levels, each the one above subsampled 2x), Gauss-Newton iterations per level up to a
bound, ended early at convergence (`lax.while_loop`: compiled once for an image size and a config, never per
frame), on each level's points as rows (`level_rows`):

- every valid current pixel's point `p = T_reference_current @ v_current` is projected into the reference
  image; the reference's vertex `q` and normal `n` at the nearest pixel are its correspondence
  (projective data association, as in KinectFusion);
- pairs further apart than `max_distance` or whose normals differ by more than `max_normal_angle_deg` are
  rejected;
- the point-to-plane residual `r = n . (p - q)` is linearised in a left-multiplied twist `xi = (rho, phi)`
  (translation, rotation; `T <- exp(xi) T`): `dr/dxi = [n, p x n]`; the 6x6 normal equations
  `(J^T J) xi = -J^T r` are solved with `jnp.linalg.solve`.

The failure signal (`TrackResult`): the RMS point-to-plane residual (m) and the inliers at the final pose on
the finest level, their share of the current frame's valid pixels, and `lost` when too few inliers remain, the
residual is too large, the motion is implausibly large for one frame step, or the solve went non-finite.

Shapes: `(H, W)` the depth image, `(Hl, Wl)` a pyramid level (`H >> l, W >> l`); intrinsics are float32
`(4,) = (fx, fy, cx, cy)` of the full image; poses float32 `(4, 4)`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

#: What a frame can be tracked against (`TrackingConfig.reference`).
REFERENCES = ("model", "frame")

#: A depth step of more than this share of the depth between neighbouring pixels is an edge: no normal there.
EDGE_STEP = 0.05


@dataclasses.dataclass(frozen=True)
class TrackingConfig:
    """Static parameters of the tracker (hashable: a static argument of the jitted functions)."""

    levels: int = 3  # pyramid levels, each subsampled 2x from the one above
    iterations: tuple[int, ...] = (10, 5, 4)  # Gauss-Newton iterations per level at most, finest level first ...
    # ... a level ends early once a step moves no entry of the pose by more than this (metres, or radians-ish for
    # the rotation's entries): at 30 Hz most frames converge in a few steps
    converged_step: float = 1e-5
    depth_min: float = 0.1  # depth readings below this (m) are ignored
    depth_max: float = 4.0  # ... and above this
    max_distance: float = 0.1  # correspondences further apart than this (m) are outliers
    max_normal_angle_deg: float = 30.0  # ... and so are those whose normals differ by more than this
    min_inliers: int = 100  # lost: fewer inliers at the final pose (finest level) ...
    min_inlier_share: float = 0.2  # ... or fewer than this share of the current frame's valid pixels ...
    max_residual: float = 0.02  # ... or an RMS point-to-plane residual above this (m) ...
    max_translation: float = 0.3  # ... or a motion of more than this (m) ...
    max_rotation_deg: float = 30.0  # ... or of more than this (degrees) between the two frames
    # Levenberg-Marquardt damping, a share of the mean eigenvalue of J^T J added to its diagonal: a direction the
    # level's geometry hardly constrains (a coarse level of a room of planes) is not moved along by noise
    damping: float = 0.01
    # The colour term (used where both frames' maps hold an intensity, `frame_maps(..., color=)`): a photometric
    # residual, the reference's intensity at the current pixel's projection against the current pixel's, weighted by
    # this against the point-to-plane residuals (metres against intensities in [0, 1]). Where the geometry leaves a
    # direction unconstrained (a camera close to a wall and a sofa) the image still constrains it (0: depth only).
    # 0.003 on generated 30 Hz walks: the one-minute walk 41.5 -> 6.3 mm ATE at 160 x 120, the six 10 s walks
    # 0.47-2.3 mm (0.44-2.8 without); at 0.01 0.57-2.9 mm and more jitter on exact depth, at 0.1 it lost the walk
    color_weight: float = 0.003
    color_max_residual: float = 0.15  # ... a photometric residual larger than this is an outlier (an occlusion)
    crease_cos: float = 0.9  # no normal where the one-sided normals differ by more than acos(this) (a crease)
    # A frame's depth is smoothed before its vertices and normals are taken (a bilateral filter, as KinectFusion's):
    # a (2r+1)^2 window (r = this, 0: off), Gaussian weights of this spatial sigma (pixels) and of a range sigma of
    # `bilateral_range` times the pixel's depth; neighbours across an edge (`EDGE_STEP`) take no part. Without it,
    # frame to frame lost every frame of the noisy generated 30 Hz walks at 320 x 240 (the raw normals of two frames
    # differ by more than `max_normal_angle_deg`); 3 x 3 tracked those best (docs/your-own-data.md), at 5 x 5 the
    # 160 x 120 model ATEs rose by 0.3-0.7 mm, and a range sigma of 0.5 % lost frames again
    bilateral_radius: int = 1
    bilateral_sigma_px: float = 1.5
    bilateral_range: float = 0.01
    # What each frame is tracked against: "model", the raycast of a TSDF of the frames tracked so far
    # (`engine.model_tracking`), or "frame", the last well tracked frame (`mapping.tracking` chains the steps)
    reference: str = "model"
    # The model (a voxel-block TSDF of the map's kind, `mapping.tracking.model_map_config`): voxel edge and
    # truncation (m), the half size of the cube around the first camera it covers (m), its pool of blocks ...
    model_voxel_size: float = 0.02
    # 5 voxels: at 3 (0.06) the 60-frame exact-depth walk of tests/test_track_command.py drifted 32 mm (3 mm at 5)
    model_sdf_trunc: float = 0.1
    model_extent: float = 6.0
    model_block_capacity: int = 16384
    raycast_steps: int = 64  # ... and the most samples per ray of its raycast (`engine.raycast`)
    # ... cast near the depth just fused only (a few samples a ray; the rays without depth not cast), not from
    # depth_min through the whole model
    raycast_guided: bool = True
    # The ICP and the model's raycast work from the first level of the frame's pyramid at most this many pixels wide
    # (`icp_level`; 0: the frame's own size); the bilateral filter and the model's integration take the whole
    # frame. On the noisy generated walks at 320 x 240 frame to model took 21-24 ms a frame at the frame's own size,
    # 7-10 ms from 160 x 120, at the same ATE (0.57-1.12 mm against 0.47-0.91 mm; tracking 160 x 120 frames: 1.2-2.1)
    icp_width: int = 160

    def __post_init__(self) -> None:
        if self.levels < 1 or len(self.iterations) != self.levels or min(self.iterations) < 0:
            raise ValueError(f"need one non-negative iteration count per level, got {self.iterations} for {self.levels}")
        if self.icp_width < 0 or self.bilateral_radius < 0:
            raise ValueError(f"icp_width and bilateral_radius must be >= 0: {self.icp_width}, {self.bilateral_radius}")
        if self.reference not in REFERENCES:
            raise ValueError(f"reference must be one of {REFERENCES}, got {self.reference!r}")


class FrameMaps(NamedTuple):
    """A depth frame's pyramid, finest level first: camera-frame vertices and unit normals (zero where invalid)."""

    vertices: tuple[jax.Array, ...]  # float32[Hl, Wl, 3] per level
    normals: tuple[jax.Array, ...]  # float32[Hl, Wl, 3] per level
    valid: tuple[jax.Array, ...]  # bool[Hl, Wl]: a vertex with a normal
    # float32[Hl, Wl] per level: the frame's blurred grey image in [0, 1] (`intensity_image`); empty without colour
    intensity: tuple[jax.Array, ...] = ()


class TrackResult(NamedTuple):
    """The estimated motion and how well it fits."""

    T_reference_current: jax.Array  # float32[4, 4]
    residual: jax.Array  # float32[]: RMS point-to-plane residual of the inliers (m) at the final pose, finest level
    inliers: jax.Array  # int32[]: inlier correspondences at the final pose, finest level
    inlier_share: jax.Array  # float32[]: inliers / valid current pixels
    lost: jax.Array  # bool[]: the estimate is not to be trusted (see `TrackingConfig`)


# ------------------------------------------------------------------------------------------- SE(3)


def hat(w):
    """`(3, 3)` skew matrix of `(3,)` `w`: `hat(w) @ x == cross(w, x)`."""
    zero = jnp.zeros((), w.dtype)
    return jnp.stack([jnp.stack([zero, -w[2], w[1]]), jnp.stack([w[2], zero, -w[0]]), jnp.stack([-w[1], w[0], zero])])


def _so3_coefficients(theta2):
    """`(sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3)` of `t = sqrt(theta2)`, with Taylor series near 0."""
    small = theta2 < 1e-4
    t2 = jnp.where(small, 1.0, theta2)
    t = jnp.sqrt(t2)
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(t)) / t2)
    c = jnp.where(small, 1.0 / 6.0 - theta2 / 120.0, (t - jnp.sin(t)) / (t2 * t))
    return a, b, c


def se3_exp(xi):
    """`(4, 4)` rigid transform `exp(xi)` of the twist `xi = (rho, phi)` `(6,)` (translation part first)."""
    rho, phi = xi[:3], xi[3:]
    K = hat(phi)
    a, b, c = _so3_coefficients(jnp.dot(phi, phi))
    eye = jnp.eye(3, dtype=xi.dtype)
    K2 = K @ K
    R = eye + a * K + b * K2
    V = eye + b * K + c * K2
    top = jnp.concatenate([R, (V @ rho)[:, None]], axis=1)
    return jnp.concatenate([top, jnp.array([[0.0, 0.0, 0.0, 1.0]], xi.dtype)], axis=0)


def se3_log(T):
    """`(6,)` twist `xi = (rho, phi)` with `se3_exp(xi) == T`, for a rotation angle below pi."""
    R, t = T[:3, :3], T[:3, 3]
    cos = jnp.clip((jnp.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = jnp.arccos(cos)
    vee = jnp.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    small = theta < 1e-3
    sin = jnp.where(small, 1.0, jnp.sin(theta))
    scale = jnp.where(small, 0.5 + theta**2 / 12.0, theta / (2.0 * sin))
    phi = scale * vee
    _, b, c = _so3_coefficients(jnp.dot(phi, phi))
    K = hat(phi)
    V = jnp.eye(3, dtype=T.dtype) + b * K + c * (K @ K)
    return jnp.concatenate([jnp.linalg.solve(V, t), phi])


def motion_size(T):
    """`(translation (m), rotation angle (degrees))` of a rigid transform."""
    cos = jnp.clip((jnp.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return jnp.linalg.norm(T[:3, 3]), jnp.degrees(jnp.arccos(cos))


# ------------------------------------------------------------------------------------------- maps


def icp_level(width: int, config: TrackingConfig) -> int:
    """The pyramid level that the ICP's finest level and the model's raycast work at for frames `width` pixels wide:
    the first one at most `config.icp_width` wide (0 when that is 0)."""
    level = 0
    while config.icp_width > 0 and -(-width // (1 << level)) > config.icp_width:
        level += 1
    return level


def level_intrinsics(intrinsics, level: int):
    """Intrinsics `(4,)` of pyramid level `level` (pixel `(u, v)` there is `(2^l u, 2^l v)` at full size)."""
    s = 1.0 / (1 << level)
    return jnp.asarray(intrinsics, jnp.float32) * s


def _cross(a, b):
    """Cross product of two vectors given as 3 arrays each (any one shape)."""
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _vertex_normal_map(depth, intrinsics, config: TrackingConfig):
    """Vertices, normals and validity `(Hl, Wl, 3), (Hl, Wl, 3), (Hl, Wl)` of one level's depth `(Hl, Wl)`.

    Normals are the cross product of the central differences of the neighbouring vertices, where the pixel and
    its four neighbours are valid and no neighbour's depth differs by more than `EDGE_STEP` of the pixel's;
    they face the camera. Computed per coordinate (`(Hl, Wl)` arrays, stacked at the end): 2x faster than on
    `(Hl, Wl, 3)` points on the 2-core CPU."""
    h, w = depth.shape
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    ok = (depth >= config.depth_min) & (depth <= config.depth_max)
    d = jnp.where(ok, depth, 0.0)
    u = jnp.arange(w, dtype=jnp.float32)[None, :]
    v = jnp.arange(h, dtype=jnp.float32)[:, None]
    vertex = [(u - cx) / fx * d, (v - cy) / fy * d, d]
    padded = [jnp.pad(c, 1) for c in vertex]
    right, left = [c[1:-1, 2:] for c in padded], [c[1:-1, :-2] for c in padded]
    down, up = [c[2:, 1:-1] for c in padded], [c[:-2, 1:-1] for c in padded]
    smooth = ok
    for other in (right[2], left[2], down[2], up[2]):  # the neighbours' depths
        smooth = smooth & (other > 0) & (jnp.abs(other - d) <= EDGE_STEP * d)
    n = _cross([a - b for a, b in zip(right, left)], [a - b for a, b in zip(down, up)])
    length = jnp.sqrt(_dot(n, n))
    # a crease (a wall meeting the floor) has a continuous depth but a normal between its two planes: the
    # one-sided differences disagree there
    forward = _cross([a - b for a, b in zip(right, vertex)], [a - b for a, b in zip(down, vertex)])
    backward = _cross([a - b for a, b in zip(vertex, left)], [a - b for a, b in zip(vertex, up)])
    agree = _dot(forward, backward) >= config.crease_cos * jnp.sqrt(_dot(forward, forward)) * jnp.sqrt(_dot(backward, backward))
    valid = smooth & (length > 0) & agree
    scale = 1.0 / jnp.where(valid, length, 1.0)
    scale = jnp.where(_dot(n, vertex) > 0, -scale, scale)  # facing the camera
    vertices = jnp.stack([jnp.where(valid, c, 0.0) for c in vertex], axis=-1)
    normals = jnp.stack([jnp.where(valid, c * scale, 0.0) for c in n], axis=-1)
    return vertices, normals, valid


#: Luma weights of an RGB pixel.
LUMA = (0.299, 0.587, 0.114)


def intensity_image(color):
    """float32 `(H, W)` in [0, 1] of a uint8 RGB `(H, W, 3)` image: its luma, blurred by the binomial 5-tap filter
    (sigma ~1 pixel) on both axes, so that the photometric term's gradients reach a pixel or two (the pyramid
    subsamples it as it does the depth)."""
    rgb = jnp.asarray(color, jnp.float32) / 255.0
    grey = rgb[..., 0] * LUMA[0] + rgb[..., 1] * LUMA[1] + rgb[..., 2] * LUMA[2]
    taps = (1.0 / 16, 4.0 / 16, 6.0 / 16, 4.0 / 16, 1.0 / 16)
    for axis in (0, 1):
        padded = jnp.pad(grey, [(2, 2) if a == axis else (0, 0) for a in (0, 1)], mode="edge")
        n = grey.shape[axis]
        grey = sum(tap * jax.lax.slice_in_dim(padded, k, k + n, axis=axis) for k, tap in enumerate(taps))
    return grey


def bilateral_depth(depth, radius: int, sigma_px: float, range_share: float):
    """float32 `(H, W)`: `depth` `(H, W)` (0 where invalid) smoothed by a bilateral filter over a `(2 radius + 1)^2`
    window: spatial weights `exp(-(du^2 + dv^2) / (2 sigma_px^2))`, range weights `exp(-dz^2 / (2 (range_share
    d)^2))` with `d` the pixel's depth; invalid neighbours and those across an edge (`|dz| > EDGE_STEP d`) take no
    part; invalid pixels stay 0."""
    h, w = depth.shape
    padded = jnp.pad(depth, radius)
    sigma_z = range_share * depth
    inv_two_var_z = 1.0 / jnp.where(depth > 0, 2.0 * sigma_z * sigma_z, 1.0)
    total = jnp.zeros_like(depth)
    weight = jnp.zeros_like(depth)
    for dv in range(-radius, radius + 1):
        for du in range(-radius, radius + 1):
            other = padded[radius + dv : radius + dv + h, radius + du : radius + du + w]
            dz = other - depth
            near = (other > 0) & (jnp.abs(dz) <= EDGE_STEP * depth)
            spatial = math.exp(-(du * du + dv * dv) / (2.0 * sigma_px * sigma_px))
            k = jnp.where(near, spatial * jnp.exp(-dz * dz * inv_two_var_z), 0.0)
            total = total + k * other
            weight = weight + k
    return jnp.where(depth > 0, total / jnp.where(weight > 0, weight, 1.0), 0.0)


@functools.partial(jax.jit, static_argnames=("config", "bilateral", "first_level"))
def frame_maps(depth, intrinsics, config: TrackingConfig, color=None, bilateral: bool = True, first_level: int = 0) -> FrameMaps:
    """The vertex/normal pyramid of a depth frame (and of its colour image's intensity).

    Args:
      depth: float32 `(H, W)` metres (readings outside `[depth_min, depth_max]` are invalid).
      intrinsics: float32 `(4,)` `(fx, fy, cx, cy)` of the full image.
      color: uint8 `(H, W, 3)` RGB registered to the depth, or None (no colour term).
      bilateral: static; smooth the depth first (`bilateral_depth`, `TrackingConfig.bilateral_radius`): a sensor's
        frame, not the model's raycast, whose depth is already an average of many frames.
      first_level: static; the pyramid's finest level is the image subsampled `2^first_level` times (`icp_level`:
        the ICP works from there), its `config.levels` levels below that; the filter takes the whole image.
    """
    depth = jnp.asarray(depth, jnp.float32)
    if bilateral and config.bilateral_radius > 0:
        ok = (depth >= config.depth_min) & (depth <= config.depth_max)
        depth = jnp.where(ok, depth, 0.0)
        depth = bilateral_depth(depth, config.bilateral_radius, config.bilateral_sigma_px, config.bilateral_range)
    vertices, normals, valid = [], [], []
    for level in range(first_level, first_level + config.levels):
        step = 1 << level
        v, n, ok = _vertex_normal_map(depth[::step, ::step], level_intrinsics(intrinsics, level), config)
        vertices.append(v)
        normals.append(n)
        valid.append(ok)
    intensity: tuple[jax.Array, ...] = ()
    if color is not None:
        grey = intensity_image(color)
        intensity = tuple(grey[:: 1 << level, :: 1 << level] for level in range(first_level, first_level + config.levels))
    return FrameMaps(tuple(vertices), tuple(normals), tuple(valid), intensity)


# ------------------------------------------------------------------------------------------- ICP


class NormalEquations(NamedTuple):
    """The Gauss-Newton system of one ICP iteration at one level."""

    A: jax.Array  # float32[6, 6]: J^T J
    b: jax.Array  # float32[6]: J^T r
    squared_error: jax.Array  # float32[]: sum of r^2 over the inliers
    inliers: jax.Array  # int32[]


def level_rows(vertices, normals, valid):
    """One level's maps as rows `float32[7, Hl * Wl]`: x, y, z, nx, ny, nz, valid (1 or 0).

    The ICP works on these rows (a structure of arrays): its gathers and sums over them ran 3.7x faster than over
    `(Hl, Wl, 3)` points on the 2-core CPU (1.39 -> 0.38 ms an iteration at 160 x 120)."""
    flat = vertices.shape[0] * vertices.shape[1]
    return jnp.concatenate([vertices.reshape(flat, 3).T, normals.reshape(flat, 3).T, valid.reshape(1, flat).astype(jnp.float32)])


def _project(cur_rows, intrinsics, T):
    """The current level's points in the reference frame and their projection there: `(p, z_safe, u, v, in_front)`,
    `p` 3 arrays `(N,)` (`T @ v`), `z_safe` the depth (1 behind the camera), `(u, v)` continuous pixels, `in_front`
    valid points ahead of the camera. Shared by the point-to-plane and the photometric terms."""
    R, t = T[:3, :3], T[:3, 3]
    v = cur_rows[0:3]
    p = [R[a, 0] * v[0] + R[a, 1] * v[1] + R[a, 2] * v[2] + t[a] for a in range(3)]
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    z = p[2]
    z_safe = jnp.where(z > 1e-6, z, 1.0)
    return p, z_safe, fx * p[0] / z_safe + cx, fy * p[1] / z_safe + cy, (cur_rows[6] > 0) & (z > 1e-6)


def normal_equations_of_rows(ref_rows, cur_rows, shape: tuple[int, int], intrinsics, T, config) -> NormalEquations:
    """Point-to-plane normal equations of the current level's rows against the reference's at `T_reference_current`.

    Args:
      ref_rows, cur_rows: float32 `(7, Hl * Wl)` (`level_rows`) of the reference (its camera frame) and the current
        frame (its own).
      shape: static `(Hl, Wl)`; intrinsics: float32 `(4,)` of this level; T: float32 `(4, 4)` `T_reference_current`.
    """
    h, w = shape
    R, m = T[:3, :3], cur_rows[3:6]
    n_cur = [R[a, 0] * m[0] + R[a, 1] * m[1] + R[a, 2] * m[2] for a in range(3)]
    p, _, u, v_px, in_front = _project(cur_rows, intrinsics, T)
    u, v_px = jnp.round(u), jnp.round(v_px)  # the nearest pixel's correspondence
    inside = in_front & (u >= 0) & (u <= w - 1) & (v_px >= 0) & (v_px <= h - 1)
    flat = jnp.where(inside, v_px.astype(jnp.int32) * w + u.astype(jnp.int32), 0)
    ref = ref_rows[:, flat]  # (7, N): the correspondences
    q, n = ref[0:3], ref[3:6]
    diff = [p[a] - q[a] for a in range(3)]
    cos_limit = math.cos(math.radians(config.max_normal_angle_deg))
    inlier = inside & (ref[6] > 0) & (_dot(diff, diff) <= config.max_distance**2) & (_dot(n, n_cur) >= cos_limit)
    r = jnp.where(inlier, _dot(n, diff), 0.0)
    J = jnp.where(inlier[None], jnp.stack([n[0], n[1], n[2], *_cross(p, n)]), 0.0)  # (6, N): dr/dxi
    return NormalEquations(J @ J.T, J @ r, jnp.sum(r * r), jnp.sum(inlier.astype(jnp.int32)))


def normal_equations(
    ref_vertex, ref_normal, ref_valid, cur_vertex, cur_normal, cur_valid, intrinsics, T, config
) -> NormalEquations:
    """Point-to-plane normal equations of the current level maps against the reference's at `T_reference_current`.

    Args:
      ref_vertex, ref_normal: float32 `(Hl, Wl, 3)`; ref_valid: bool `(Hl, Wl)` (reference camera frame).
      cur_vertex, cur_normal: float32 `(Hl, Wl, 3)`; cur_valid: bool `(Hl, Wl)` (current camera frame).
      intrinsics: float32 `(4,)` of this level; T: float32 `(4, 4)` `T_reference_current`.
    """
    height, width = ref_valid.shape
    return normal_equations_of_rows(
        level_rows(ref_vertex, ref_normal, ref_valid),
        level_rows(cur_vertex, cur_normal, cur_valid),
        (height, width),
        intrinsics,
        T,
        config,
    )


def _bilinear_rows(rows, shape: tuple[int, int], u, v):
    """Rows `(C, h * w)` of an `(h, w)` image at continuous pixels `(u, v)` `(N,)` (kept a pixel inside the border):
    `(C, N)`, one gather per corner for every row."""
    h, w = shape
    u0 = jnp.clip(jnp.floor(u), 0, w - 2)
    v0 = jnp.clip(jnp.floor(v), 0, h - 2)
    fu, fv = u - u0, v - v0
    corner = v0.astype(jnp.int32) * w + u0.astype(jnp.int32)
    top = rows[:, corner] * (1.0 - fu) + rows[:, corner + 1] * fu
    bottom = rows[:, corner + w] * (1.0 - fu) + rows[:, corner + w + 1] * fu
    return top * (1.0 - fv) + bottom * fv


def intensity_rows(image):
    """`(3, h * w)` rows of an intensity image `(h, w)`: the intensity and its central differences along u and v
    (one-sided copies at the border), what the photometric term samples."""
    padded = jnp.pad(image, 1, mode="edge")
    du = (padded[1:-1, 2:] - padded[1:-1, :-2]) / 2.0
    dv = (padded[2:, 1:-1] - padded[:-2, 1:-1]) / 2.0
    return jnp.stack([image, du, dv]).reshape(3, -1)


def photometric_equations(ref_rows, shape: tuple[int, int], cur_rows, cur_intensity, intrinsics, T, config):
    """`(J^T J, J^T r)` `(6, 6), (6,)` of the photometric residuals `I_ref(pi(T v)) - I_cur` of the current level's
    valid pixels at `T_reference_current`.

    Args:
      ref_rows: float32 `(3, Hl * Wl)` (`intensity_rows`) of the reference; shape: static `(Hl, Wl)`.
      cur_rows: float32 `(7, N)` (`level_rows`) of the current level; cur_intensity: float32 `(N,)` the same pixels'.
      intrinsics: float32 `(4,)` of the reference level; T: float32 `(4, 4)`.
    """
    h, w = shape
    fx, fy = intrinsics[0], intrinsics[1]
    p, z_safe, u, v_px, in_front = _project(cur_rows, intrinsics, T)
    inside = in_front & (u >= 0) & (u <= w - 1) & (v_px >= 0) & (v_px <= h - 1)
    sample = _bilinear_rows(ref_rows, shape, u, v_px)
    r = sample[0] - cur_intensity
    use = inside & (jnp.abs(r) <= config.color_max_residual)
    du, dv = sample[1], sample[2]
    # dI/dp = (dI/du, dI/dv) . d(u, v)/dp; dp/dxi = [I, -[p]x], so dI/dxi = (dI/dp, p x dI/dp)
    g = [du * fx / z_safe, dv * fy / z_safe, -(du * fx * p[0] + dv * fy * p[1]) / (z_safe * z_safe)]
    J = jnp.where(use[None], jnp.stack([g[0], g[1], g[2], *_cross(p, g)]), 0.0)
    r = jnp.where(use, r, 0.0)
    return J @ J.T, J @ r


def gauss_newton_update(system: NormalEquations, T, damping: float = 0.0):
    """`T` after one (damped) Gauss-Newton step `exp(xi) T` with `(J^T J + lambda I) xi = -J^T r`, `lambda =
    damping * trace(J^T J) / 6` (unchanged where the system is degenerate: fewer than 6 inliers or a non-finite
    solution)."""
    lam = damping * jnp.trace(system.A) / 6.0
    xi = jnp.linalg.solve(system.A + lam * jnp.eye(6, dtype=system.A.dtype), -system.b)
    usable = (system.inliers >= 6) & jnp.all(jnp.isfinite(xi))
    return jnp.where(usable, se3_exp(jnp.where(usable, xi, 0.0)) @ T, T)


@functools.partial(jax.jit, static_argnames=("config", "reference_level"))
def track_frame(
    reference: FrameMaps,
    current: FrameMaps,
    intrinsics,
    T_reference_current_guess,
    config: TrackingConfig,
    reference_level: int = 0,
) -> TrackResult:
    """`T_reference_current` by coarse-to-fine point-to-plane ICP from a guess (identity for small motions).

    Args:
      reference, current: `frame_maps` of the two frames (the same config and number of levels; either may start
        at a coarser pyramid level of the image, `frame_maps(first_level=)`: the current frame's points are 3D, and
        each is projected into the reference's level at that level's intrinsics).
      intrinsics: float32 `(4,)` of the full image.
      reference_level: static; the image's pyramid level of the reference's finest level.
      T_reference_current_guess: float32 `(4, 4)`.
    """
    T = jnp.asarray(T_reference_current_guess, jnp.float32)
    rows = [
        (
            level_rows(reference.vertices[level], reference.normals[level], reference.valid[level]),
            level_rows(current.vertices[level], current.normals[level], current.valid[level]),
        )
        for level in range(config.levels)
    ]
    with_color = config.color_weight > 0 and bool(reference.intensity) and bool(current.intensity)
    for level in reversed(range(config.levels)):
        K = level_intrinsics(intrinsics, level + reference_level)
        height, width = reference.valid[level].shape
        color = None
        if with_color:
            color = (intensity_rows(reference.intensity[level]), current.intensity[level].reshape(-1))

        def body(carry, pair=rows[level], K=K, shape=(height, width), color=color):
            i, T, _ = carry
            system = normal_equations_of_rows(*pair, shape, K, T, config)
            if color is not None:
                A, b = photometric_equations(color[0], shape, pair[1], color[1], K, T, config)
                system = system._replace(A=system.A + config.color_weight * A, b=system.b + config.color_weight * b)
            T_next = gauss_newton_update(system, T, config.damping)
            return i + 1, T_next, jnp.max(jnp.abs(T_next - T)) <= config.converged_step

        def cond(carry, level=level):
            i, _, converged = carry
            return (i < config.iterations[level]) & ~converged

        _, T, _ = jax.lax.while_loop(cond, body, (jnp.int32(0), T, jnp.bool_(False)))
    height, width = reference.valid[0].shape
    final = normal_equations_of_rows(*rows[0], (height, width), level_intrinsics(intrinsics, reference_level), T, config)
    count = jnp.maximum(final.inliers, 1).astype(jnp.float32)
    residual = jnp.sqrt(final.squared_error / count)
    share = final.inliers / jnp.maximum(jnp.sum(current.valid[0].astype(jnp.int32)), 1).astype(jnp.float32)
    translation, rotation = motion_size(T)
    lost = (
        (final.inliers < config.min_inliers)
        | (share < config.min_inlier_share)
        | (residual > config.max_residual)
        | (translation > config.max_translation)
        | (rotation > config.max_rotation_deg)
        | ~jnp.all(jnp.isfinite(T))
    )
    return TrackResult(T, residual, final.inliers, share, lost)
