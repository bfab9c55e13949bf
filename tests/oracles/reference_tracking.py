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
