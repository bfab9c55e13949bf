"""Plain NumPy reference of one point-to-plane Gauss-Newton step (test oracle of `engine.tracking`).

Written for clarity: float64, a Python loop over the current frame's pixels, the textbook formulas.
"""

from __future__ import annotations

import numpy as np


def vertex_map(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """`(H, W, 3)` camera-frame points of a depth map (metres)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([(u - cx) / fx * depth, (v - cy) / fy * depth, depth], axis=-1)


def skew(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """`exp` of the twist `(rho, phi)` by the matrix exponential's series (no closed form to share a bug with)."""
    X = np.zeros((4, 4))
    X[:3, :3] = skew(xi[3:])
    X[:3, 3] = xi[:3]
    T, term = np.eye(4), np.eye(4)
    for k in range(1, 30):
        term = term @ X / k
        T = T + term
    return T


def gauss_newton_step(
    ref_vertex,
    ref_normal,
    ref_valid,
    cur_vertex,
    cur_normal,
    cur_valid,
    intrinsics,
    T,
    max_distance: float,
    max_normal_angle_deg: float,
    damping: float,
):
    """One damped Gauss-Newton step of `T_reference_current`; returns `(A, b, inliers, T_new)`."""
    fx, fy, cx, cy = (float(x) for x in intrinsics)
    h, w = ref_valid.shape
    R, t = T[:3, :3], T[:3, 3]
    A, b, inliers = np.zeros((6, 6)), np.zeros(6), 0
    cos_limit = np.cos(np.radians(max_normal_angle_deg))
    for y in range(h):
        for x in range(w):
            if not cur_valid[y, x]:
                continue
            p = R @ cur_vertex[y, x] + t
            if p[2] <= 1e-6:
                continue
            u, v = int(np.round(fx * p[0] / p[2] + cx)), int(np.round(fy * p[1] / p[2] + cy))
            if not (0 <= u < w and 0 <= v < h) or not ref_valid[v, u]:
                continue
            q, n = ref_vertex[v, u], ref_normal[v, u]
            if np.linalg.norm(p - q) > max_distance or n @ (R @ cur_normal[y, x]) < cos_limit:
                continue
            J = np.concatenate([n, np.cross(p, n)])
            r = n @ (p - q)
            A += np.outer(J, J)
            b += J * r
            inliers += 1
    xi = np.linalg.solve(A + damping * np.trace(A) / 6 * np.eye(6), -b)
    return A, b, inliers, exp_se3(xi) @ T


def photometric_residuals(
    ref_intensity: np.ndarray,
    cur_vertices: np.ndarray,
    cur_valid: np.ndarray,
    cur_intensity: np.ndarray,
    K: np.ndarray,
    T: np.ndarray,
    max_residual: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per current pixel `(N,)`: the residual `I_ref(pi(T v)) - I_cur` (bilinear, the pixel kept one inside the
    border), its Jacobian `(N, 6)` with respect to a left twist `(rho, phi)` of `T`, and whether it is used (valid,
    projected inside the reference image, `|r| <= max_residual`). Loops over the pixels, float64."""
    h, w = ref_intensity.shape
    padded = np.pad(ref_intensity.astype(np.float64), 1, mode="edge")
    gu = (padded[1:-1, 2:] - padded[1:-1, :-2]) / 2.0
    gv = (padded[2:, 1:-1] - padded[:-2, 1:-1]) / 2.0
    fx, fy, cx, cy = K
    vertices = cur_vertices.reshape(-1, 3).astype(np.float64)
    n = len(vertices)
    r, J, used = np.zeros(n), np.zeros((n, 6)), np.zeros(n, bool)

    def sample(image, u, v):
        u0, v0 = min(max(np.floor(u), 0), w - 2), min(max(np.floor(v), 0), h - 2)
        a, b = u - u0, v - v0
        i, j = int(u0), int(v0)
        return (image[j, i] * (1 - a) + image[j, i + 1] * a) * (1 - b) + (image[j + 1, i] * (1 - a) + image[j + 1, i + 1] * a) * b

    for k in range(n):
        if not cur_valid.reshape(-1)[k]:
            continue
        p = T[:3, :3] @ vertices[k] + T[:3, 3]
        if p[2] <= 1e-6:
            continue
        u, v = fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy
        if not (0 <= u <= w - 1 and 0 <= v <= h - 1):
            continue
        r[k] = sample(ref_intensity, u, v) - cur_intensity.reshape(-1)[k]
        if abs(r[k]) > max_residual:
            continue
        d_uv = np.array([[fx / p[2], 0.0, -fx * p[0] / p[2] ** 2], [0.0, fy / p[2], -fy * p[1] / p[2] ** 2]])
        g = np.array([sample(gu, u, v), sample(gv, u, v)]) @ d_uv  # dI/dp
        J[k] = np.concatenate([g, np.cross(p, g)])  # dp/dxi = [I, -[p]x]
        used[k] = True
    return r, J, used


def bilateral_depth(depth: np.ndarray, radius: int, sigma_px: float, range_share: float, edge_step: float) -> np.ndarray:
    """The bilateral filter of `engine.tracking.bilateral_depth`, one pixel and one neighbour at a time."""
    h, w = depth.shape
    out = np.zeros((h, w))
    for v in range(h):
        for u in range(w):
            d = float(depth[v, u])
            if d <= 0:
                continue
            total = weight = 0.0
            for dv in range(-radius, radius + 1):
                for du in range(-radius, radius + 1):
                    if not (0 <= v + dv < h and 0 <= u + du < w):
                        continue
                    other = float(depth[v + dv, u + du])
                    if other <= 0 or abs(other - d) > edge_step * d:
                        continue
                    spatial = np.exp(-(du * du + dv * dv) / (2 * sigma_px**2))
                    k = spatial * np.exp(-((other - d) ** 2) / (2 * (range_share * d) ** 2))
                    total += k * other
                    weight += k
            out[v, u] = total / weight
    return out
