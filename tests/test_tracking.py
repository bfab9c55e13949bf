"""The tracking kernel (`engine.tracking`): SE(3) maps, one Gauss-Newton step against a NumPy oracle, the
recovery of known motions on rendered depth of a generated room, and the failure signal."""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from oracles import reference_tracking as R

from fmfusion_jax.engine import tracking as tk
from fmfusion_jax.types import CameraIntrinsics

WIDTH, HEIGHT = 160, 120
INTRINSICS = CameraIntrinsics(144.4, 144.4, WIDTH / 2 - 0.5, HEIGHT / 2 - 0.5, WIDTH, HEIGHT)
K = jnp.array([INTRINSICS.fx, INTRINSICS.fy, INTRINSICS.cx, INTRINSICS.cy], jnp.float32)
CONFIG = tk.TrackingConfig()

finite = functools.partial(st.floats, allow_nan=False, allow_infinity=False)


@functools.cache
def room():
    from fmfusion_jax.simulation.procedural import add_object, empty_room

    scene = empty_room((4.0, 4.0, 2.6), seed=3)
    scene = add_object(scene, "bed", [((1.0, 1.1, 0.3), (1.4, 1.9, 0.6), 0.0)])
    return add_object(scene, "table", [((3.0, 3.0, 0.375), (1.0, 0.8, 0.75), 0.0)])


def render(T_world_camera: np.ndarray, intrinsics: CameraIntrinsics = INTRINSICS) -> np.ndarray:
    """float32 `(H, W)` depth (m, 0 where nothing is hit) of the room seen from `T_world_camera`."""
    from fmfusion_jax.simulation.raycast import raycast_boxes

    scene = room()
    depth = raycast_boxes(scene.box_arrays(), T_world_camera, intrinsics, enclosure=scene.enclosure()).depth
    return np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)


def start_pose() -> np.ndarray:
    from fmfusion_jax.simulation.procedural import look_pose

    return look_pose((2.6, 1.2, 1.45), np.radians(150), np.radians(-30))


def twist_strategy(max_rho: float, max_phi: float):
    return st.tuples(*[finite(-max_rho, max_rho)] * 3, *[finite(-max_phi, max_phi)] * 3).map(np.array)


@settings(max_examples=60, deadline=None)
@given(twist_strategy(2.0, 1.6))
def test_exp_matches_the_series_and_log_inverts_it(xi):
    T = np.asarray(tk.se3_exp(jnp.asarray(xi, jnp.float32)), np.float64)
    np.testing.assert_allclose(T, R.exp_se3(xi), atol=2e-5)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-5)
    np.testing.assert_allclose(np.asarray(tk.se3_log(jnp.asarray(T, jnp.float32))), xi, atol=2e-4)


def test_exp_and_log_near_zero():
    for scale in (0.0, 1e-7, 1e-4):
        xi = np.array([0.1, -0.2, 0.3, 1.0, -2.0, 0.5]) * scale
        T = np.asarray(tk.se3_exp(jnp.asarray(xi, jnp.float32)))
        np.testing.assert_allclose(T, R.exp_se3(xi), atol=1e-7)
        np.testing.assert_allclose(np.asarray(tk.se3_log(jnp.asarray(T))), xi, atol=1e-6)


def test_normals_face_the_camera_and_are_missing_at_edges():
    depth = render(start_pose())
    maps = tk.frame_maps(depth, K, CONFIG)
    assert [v.shape for v in maps.vertices] == [(120, 160, 3), (60, 80, 3), (30, 40, 3)]
    n, v, ok = (np.asarray(x) for x in (maps.normals[0], maps.vertices[0], maps.valid[0]))
    assert 0.8 < ok.mean() < 1.0  # the box edges and the image border have no normal
    np.testing.assert_allclose(np.linalg.norm(n[ok], axis=-1), 1.0, atol=1e-5)
    assert (np.sum(n[ok] * v[ok], axis=-1) < 0).all()
    assert not ok[0].any() and not ok[:, -1].any()


@settings(max_examples=40, deadline=None)
@given(
    st.integers(0, 2**31 - 1),
    st.integers(0, 3),
    finite(0.5, 3.0),
    finite(0.002, 0.05),
)
def test_the_bilateral_depth_filter_matches_the_numpy_oracle(seed, radius, sigma_px, range_share):
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.5, 4.0, (7, 9)) * (rng.random((7, 9)) > 0.2)  # some holes
    depth[:, 5:] = depth[:, 5:] * 0.0 + 1.0 + 0.003 * rng.standard_normal((7, 4))  # a noisy plane beside the clutter
    depth = depth.astype(np.float32)
    got = np.asarray(tk.bilateral_depth(jnp.asarray(depth), radius, sigma_px, range_share))
    want = R.bilateral_depth(depth.astype(np.float64), radius, sigma_px, range_share, tk.EDGE_STEP)
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-6)
    assert np.all(got[depth == 0] == 0)


def test_the_bilateral_filter_steadies_the_normals_of_noisy_depth():
    """A wall seen head-on at 2 m with 3 mm of noise a pixel at 320 x 240 (the noise of a Kinect-like camera there):
    the per-pixel normals of the raw depth scatter by tens of degrees, which fails the ICP's 30 degree test between two
    frames (frame-to-frame tracking of the noisy generated walks at 320 x 240 lost every frame); the filtered ones
    stay within a few degrees (3 x 3 filter: median 6 degrees)."""
    width, height = 320, 240
    K320 = jnp.array([288.8, 288.8, width / 2 - 0.5, height / 2 - 0.5], jnp.float32)
    rng = np.random.default_rng(0)
    depth = (2.0 + 0.003 * rng.standard_normal((height, width))).astype(np.float32)
    angles = {}
    for name, config in (("raw", tk.TrackingConfig(bilateral_radius=0)), ("filtered", CONFIG)):
        maps = tk.frame_maps(depth, K320, config)
        n, ok = np.asarray(maps.normals[0]), np.asarray(maps.valid[0])
        angles[name] = np.degrees(np.arccos(np.clip(-n[ok][:, 2], -1.0, 1.0)))
    assert np.median(angles["raw"]) > 15.0, np.median(angles["raw"])
    assert np.median(angles["filtered"]) < 8.0, np.median(angles["filtered"])
    assert np.mean(angles["filtered"] < 15.0) > 0.95  # two frames' normals then agree within the ICP's 30 degrees


def test_one_gauss_newton_step_matches_the_numpy_oracle():
    """On the coarsest level of two rendered frames 3 cm / 2 degrees apart, from the identity."""
    T_world_ref = start_pose()
    motion = R.exp_se3(np.array([0.02, -0.01, 0.02, 0.01, 0.03, -0.01]))
    T_world_cur = T_world_ref @ motion
    level = 2
    maps = [tk.frame_maps(render(T), K, CONFIG) for T in (T_world_ref, T_world_cur)]
    args = [np.asarray(x[level], np.float64) for m in maps for x in (m.vertices, m.normals)]
    ref_v, ref_n, cur_v, cur_n = args
    ref_ok, cur_ok = (np.asarray(m.valid[level]) for m in maps)
    Kl = np.asarray(tk.level_intrinsics(K, level), np.float64)
    T0 = np.eye(4)
    A, b, inliers, T1 = R.gauss_newton_step(
        ref_v, ref_n, ref_ok, cur_v, cur_n, cur_ok, Kl, T0, CONFIG.max_distance, CONFIG.max_normal_angle_deg, CONFIG.damping
    )
    system = tk.normal_equations(
        *(maps[0].vertices[level], maps[0].normals[level], maps[0].valid[level]),
        *(maps[1].vertices[level], maps[1].normals[level], maps[1].valid[level]),
        jnp.asarray(Kl, jnp.float32),
        jnp.eye(4),
        CONFIG,
    )
    assert abs(int(system.inliers) - inliers) <= 2 and inliers > 500  # pixel-rounding ties may differ
    np.testing.assert_allclose(np.asarray(system.A), A, rtol=5e-3, atol=1e-2 * np.abs(A).max() / 100)
    np.testing.assert_allclose(np.asarray(system.b), b, atol=2e-3 * np.abs(b).max())
    step = np.asarray(tk.gauss_newton_update(system, jnp.eye(4), CONFIG.damping))
    np.testing.assert_allclose(step, T1, atol=1e-4)
    # the step goes towards the true motion
    assert np.linalg.norm(T1[:3, 3] - motion[:3, 3]) < np.linalg.norm(motion[:3, 3])


@settings(max_examples=12, deadline=None)
@given(twist_strategy(0.03, 0.04))
def test_a_small_rigid_motion_is_recovered(xi):
    """Up to 3 cm per axis and 2.3 degrees per axis (beyond a 30 Hz hand-held step), from the identity."""
    T_world_ref = start_pose()
    motion = R.exp_se3(xi)
    maps = [tk.frame_maps(render(T), K, CONFIG) for T in (T_world_ref, T_world_ref @ motion)]
    result = tk.track_frame(maps[0], maps[1], K, jnp.eye(4), CONFIG)
    assert not bool(result.lost)
    T = np.asarray(result.T_reference_current, np.float64)
    assert np.abs(T[:3, 3] - motion[:3, 3]).max() < 2e-3
    assert np.abs(T[:3, :3] - motion[:3, :3]).max() < 2e-3
    assert float(result.residual) < 2e-3 and float(result.inlier_share) > 0.8


def test_lost_when_the_frames_do_not_overlap():
    T_world_ref = start_pose()
    turned = T_world_ref @ R.exp_se3(np.array([0.0, 0.0, 0.0, 0.0, np.pi, 0.0]))  # looking the other way
    maps = [tk.frame_maps(render(T), K, CONFIG) for T in (T_world_ref, turned)]
    result = tk.track_frame(maps[0], maps[1], K, jnp.eye(4), CONFIG)
    assert bool(result.lost)
    empty = tk.frame_maps(np.zeros((HEIGHT, WIDTH), np.float32), K, CONFIG)
    result = tk.track_frame(maps[0], empty, K, jnp.eye(4), CONFIG)
    assert bool(result.lost) and int(result.inliers) == 0
    np.testing.assert_array_equal(np.asarray(result.T_reference_current), np.eye(4))


def test_the_icp_works_at_the_first_level_at_most_icp_width_wide():
    assert [tk.icp_level(w, CONFIG) for w in (80, 160, 161, 320, 640, 1280)] == [0, 0, 1, 1, 2, 3]
    assert tk.icp_level(640, tk.TrackingConfig(icp_width=0)) == 0
    assert tk.icp_level(640, tk.TrackingConfig(icp_width=320)) == 1
    with pytest.raises(ValueError, match="icp_width"):
        tk.TrackingConfig(icp_width=-1)


def test_the_config_is_checked():
    with pytest.raises(ValueError, match="iteration count per level"):
        tk.TrackingConfig(levels=2)


def _textured_wall(T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth and colour `(H, W)`, `(H, W, 3)` of a flat wall at z = 2 m with a smooth texture fixed to it: geometry
    that leaves the translation along the wall unconstrained."""
    u, v = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    rays = np.stack([(u - INTRINSICS.cx) / INTRINSICS.fx, (v - INTRINSICS.cy) / INTRINSICS.fy, np.ones_like(u, float)], -1)
    directions = rays @ T_world_camera[:3, :3].T
    t = (2.0 - T_world_camera[2, 3]) / directions[..., 2]
    points = T_world_camera[:3, 3] + t[..., None] * directions
    depth = (t * (rays[..., 2])).astype(np.float32)  # z in the camera frame (the camera faces the wall)
    x, y = points[..., 0], points[..., 1]
    texture = 0.5 + 0.2 * np.sin(9.0 * x + 2.0) * np.cos(7.0 * y) + 0.15 * np.sin(5.0 * x - 11.0 * y)
    grey = np.clip(np.round(255 * texture), 0, 255).astype(np.uint8)
    return depth, np.repeat(grey[..., None], 3, axis=-1)


def test_the_colour_term_holds_the_camera_where_the_geometry_does_not():
    """Facing a flat textured wall, a 1.5 cm step along it: depth alone cannot see it (the ICP stays put), the colour
    term recovers it to a millimetre."""
    motion = np.eye(4)
    motion[:3, 3] = [0.015, -0.01, 0.0]
    maps = [tk.frame_maps(depth, K, CONFIG, color) for depth, color in (_textured_wall(T) for T in (np.eye(4), motion))]
    depth_only = [m._replace(intensity=()) for m in maps]
    without = np.asarray(tk.track_frame(*depth_only, K, jnp.eye(4), CONFIG).T_reference_current)
    with_color = tk.track_frame(*maps, K, jnp.eye(4), CONFIG)
    T = np.asarray(with_color.T_reference_current)
    assert np.abs(without[:2, 3]).max() < 3e-3  # the wall alone does not move the estimate along it
    assert not bool(with_color.lost)
    np.testing.assert_allclose(T[:3, 3], motion[:3, 3], atol=1e-3)
    np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=2e-3)


def test_the_intensity_of_a_uniform_image_is_its_luma():
    color = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    color[...] = (200, 100, 50)
    luma = (0.299 * 200 + 0.587 * 100 + 0.114 * 50) / 255
    np.testing.assert_allclose(np.asarray(tk.intensity_image(color)), luma, atol=1e-6)
    maps = tk.frame_maps(np.ones((HEIGHT, WIDTH), np.float32), K, CONFIG, color)
    assert [i.shape for i in maps.intensity] == [(120, 160), (60, 80), (30, 40)]
    assert tk.frame_maps(np.ones((HEIGHT, WIDTH), np.float32), K, CONFIG).intensity == ()


def test_the_photometric_equations_match_the_numpy_oracle_and_the_finite_differences():
    """On the textured wall's coarsest level, 1 cm and a degree off: `photometric_equations` against the per-pixel
    NumPy oracle, and the oracle's Jacobian against finite differences of its residuals."""
    level = 2
    T_world_cur = np.eye(4)
    T_world_cur[:3, 3] = [0.01, -0.005, 0.0]
    ref, cur = (tk.frame_maps(depth, K, CONFIG, color) for depth, color in map(_textured_wall, (np.eye(4), T_world_cur)))
    T = R.exp_se3(np.array([0.0, 0.0, 0.0, 0.0, 0.0, np.radians(1.0)]))
    Kl = np.asarray(tk.level_intrinsics(K, level), np.float64)
    args = (np.asarray(ref.intensity[level]), np.asarray(cur.vertices[level]), np.asarray(cur.valid[level]))
    cur_intensity = np.asarray(cur.intensity[level])
    r, J, used = R.photometric_residuals(*args, cur_intensity, Kl, T, CONFIG.color_max_residual)
    assert used.sum() > 500
    A, b = tk.photometric_equations(
        tk.intensity_rows(ref.intensity[level]),
        ref.intensity[level].shape,
        tk.level_rows(cur.vertices[level], cur.normals[level], cur.valid[level]),
        jnp.asarray(cur_intensity.reshape(-1)),
        jnp.asarray(Kl, jnp.float32),
        jnp.asarray(T, jnp.float32),
        CONFIG,
    )
    np.testing.assert_allclose(np.asarray(A), J[used].T @ J[used], rtol=2e-3, atol=1e-3 * np.abs(J[used].T @ J[used]).max())
    np.testing.assert_allclose(np.asarray(b), J[used].T @ r[used], atol=2e-3 * np.abs(J[used].T @ r[used]).max())
    # the Jacobian samples central differences of the image, the residual's own derivative is the bilinear
    # interpolant's: they agree up to the texture's curvature within a pixel, not pixel by pixel
    for axis in range(6):
        step = np.zeros(6)
        step[axis] = 1e-4
        ahead, _, _ = R.photometric_residuals(*args, cur_intensity, Kl, R.exp_se3(step) @ T, CONFIG.color_max_residual)
        behind, _, _ = R.photometric_residuals(*args, cur_intensity, Kl, R.exp_se3(-step) @ T, CONFIG.color_max_residual)
        numeric, analytic = (ahead - behind)[used] / 2e-4, J[used, axis]
        assert np.corrcoef(numeric, analytic)[0, 1] > 0.95, axis  # measured 0.98 on every axis
        assert 0.9 < np.dot(numeric, analytic) / np.dot(analytic, analytic) < 1.1, axis  # measured 1.02-1.05
