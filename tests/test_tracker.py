"""The host tracker (`mapping.tracking`): accuracy on a generated room along a smooth 30 Hz path, frame to frame
on exact depth and frame to model on noisy depth, the skip of a lost frame, and the TUM trajectory it writes."""

from __future__ import annotations

import functools
import time

import numpy as np
import pytest

from fmfusion_jax.engine.tracking import TrackingConfig
from fmfusion_jax.io.recordings import quaternion_to_matrix, rotation_to_quaternion, write_tum_trajectory
from fmfusion_jax.mapping.tracking import Tracker, track_depths
from fmfusion_jax.types import CameraIntrinsics

WIDTH, HEIGHT = 160, 120
INTRINSICS = CameraIntrinsics(144.4, 144.4, WIDTH / 2 - 0.5, HEIGHT / 2 - 0.5, WIDTH, HEIGHT)
NUM_FRAMES = 60
#: The generator's closed loop drawn over this many frames is a one-minute walk at 30 Hz: 3 mm (9 cm/s) and up to
#: 1.7 degrees (50 degrees/s) between frames (the loop over a few dozen frames, as the mapping tests draw it, is
#: far faster).
LOOP_FRAMES = 1800
FRAME = TrackingConfig(reference="frame")
MODEL = TrackingConfig(reference="model")


@functools.cache
def sequence(stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth `T_world_camera` `(N, 4, 4)` and rendered depth `(N, H, W)` of the first `2 * stride` s of the
    walk, every `stride`-th frame (30 / stride Hz)."""
    from fmfusion_jax.simulation.procedural import add_object, camera_trajectory, empty_room
    from fmfusion_jax.simulation.raycast import raycast_boxes

    room = empty_room((4.0, 4.0, 2.6), seed=3)
    room = add_object(room, "bed", [((1.0, 1.1, 0.3), (1.4, 1.9, 0.6), 0.0)])
    room = add_object(room, "table", [((3.0, 3.0, 0.375), (1.0, 0.8, 0.75), 0.0)])
    poses = camera_trajectory(room, LOOP_FRAMES)[: NUM_FRAMES * stride : stride]
    depths = [raycast_boxes(room.box_arrays(), T, INTRINSICS, enclosure=room.enclosure()).depth for T in poses]
    return poses, np.stack([np.where(np.isfinite(d), d, 0.0) for d in depths]).astype(np.float32)


def ate_rmse(estimated: np.ndarray, truth: np.ndarray) -> float:
    """RMS distance (m) of the camera centres after putting the first estimated pose on the first true one."""
    aligned = truth[0] @ np.linalg.inv(estimated[0]) @ estimated
    return float(np.sqrt(np.mean(np.sum((aligned[:, :3, 3] - truth[:, :3, 3]) ** 2, axis=1))))


@pytest.mark.parametrize(("stride", "max_ate"), [(1, 0.002), (4, 0.02)])
def test_a_smooth_walk_is_tracked_within_a_few_millimetres(stride, max_ate):
    """At 30 Hz (3 mm and up to 1.9 degrees between frames) and at 7.5 Hz (12 mm, up to 7.5 degrees)."""
    truth, depths = sequence(stride)
    steps = np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1)
    assert 0.002 * stride < steps.mean() < 0.004 * stride
    frames = track_depths(depths, INTRINSICS, FRAME)
    assert not any(f.lost for f in frames)
    estimated = np.stack([f.T_world_camera for f in frames])
    np.testing.assert_array_equal(estimated[0], np.eye(4))
    assert ate_rmse(estimated, truth) < max_ate  # measured: 0.41 mm at 30 Hz, 5.9 mm at 7.5 Hz over the 60 frames
    assert max(f.residual for f in frames) < 1e-3


def test_a_given_first_pose_starts_the_chain():
    truth, depths = sequence()
    frames = track_depths(depths[:10], INTRINSICS, FRAME, T_world_first=truth[0])
    estimated = np.stack([f.T_world_camera for f in frames])
    assert np.abs(estimated[:, :3, 3] - truth[:10, :3, 3]).max() < 2e-3


def test_a_lost_frame_keeps_the_last_pose_and_the_next_one_tracks_against_the_last_good_frame(caplog):
    truth, depths = sequence()
    broken = depths[:12].copy()
    broken[6] = 0.0  # a frame without depth: nothing to track
    tracker = Tracker(INTRINSICS, FRAME)
    with caplog.at_level("WARNING"):
        frames = [tracker.track(d) for d in broken]
    assert [f.lost for f in frames] == [i == 6 for i in range(12)]
    assert "tracking lost at frame 6" in caplog.text
    np.testing.assert_array_equal(frames[6].T_world_camera, frames[5].T_world_camera)
    assert tracker.frames_lost == 1 and tracker.frames_tracked == 11
    estimated = np.stack([f.T_world_camera for i, f in enumerate(frames) if i != 6])
    assert ate_rmse(estimated, np.delete(truth[:12], 6, axis=0)) < 2e-3  # frame 7 tracked against frame 5


@pytest.mark.parametrize("reference", ["model", "frame"])
def test_a_320_x_240_walk_is_tracked_with_the_icp_at_160_x_120_or_at_its_own_size(reference):
    """The ICP (and the model's raycast) at the first pyramid level at most `icp_width` wide: half the frame here by
    default, the whole frame with 0; both follow the noisy walk, depth alone (measured over these 45 frames: model 2.4 /
    3.7 mm, frame 0.7 / 0.5 mm with the ICP at 160 / 320 pixels wide)."""
    intrinsics = INTRINSICS.scaled(320, 240)
    truth, depths = noisy_sequence(45, intrinsics, noise_seed=5)
    for icp_width, level in ((160, 1), (0, 0)):
        config = TrackingConfig(reference=reference, icp_width=icp_width)
        tracker = Tracker(intrinsics, config, T_world_first=truth[0])
        frames = [tracker.track(d) for d in depths]
        assert tracker.frames_lost == 0
        assert tracker._reference is not None and tracker._reference.valid[0].shape == (240 >> level, 320 >> level)
        assert ate_rmse(np.stack([f.T_world_camera for f in frames]), truth) < 0.006, (reference, icp_width)


@functools.cache
def noisy_sequence(
    frames: int = 150, intrinsics: CameraIntrinsics = INTRINSICS, noise_seed: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """The walk's first `frames` frames (5 s at 30 Hz) with Kinect-like depth noise, holes and dropouts."""
    from fmfusion_jax.simulation.procedural import add_object, camera_trajectory, empty_room
    from fmfusion_jax.simulation.scene_views import render_frame

    room = empty_room((4.0, 4.0, 2.6), seed=3)
    room = add_object(room, "bed", [((1.0, 1.1, 0.3), (1.4, 1.9, 0.6), 0.0)])
    room = add_object(room, "table", [((3.0, 3.0, 0.375), (1.0, 0.8, 0.75), 0.0)])
    poses = camera_trajectory(room, LOOP_FRAMES)[:frames]
    rngs = [np.random.default_rng([noise_seed, k]) for k in range(len(poses))]
    depths = [render_frame(room, T, intrinsics, rng=rng).depth for T, rng in zip(poses, rngs)]
    return poses, np.stack([np.where(np.isfinite(d), d, 0.0) for d in depths]).astype(np.float32)


def test_frame_to_model_drifts_less_than_frame_to_frame_on_a_noisy_walk():
    truth, depths = noisy_sequence()
    model = track_depths(depths, INTRINSICS, MODEL, T_world_first=truth[0])
    frame = track_depths(depths, INTRINSICS, FRAME, T_world_first=truth[0])
    assert not any(f.lost for f in model)
    errors = {}
    for name, frames in (("model", model), ("frame", frame)):
        estimated = np.stack([f.T_world_camera for f in frames])
        errors[name] = ate_rmse(estimated, truth)
    # measured: 45 mm frame to model (41 mm without the bilateral depth filter, 150 mm with the TSDF gradient's normals), 81 mm
    # frame to frame (803 mm, lost near the end, without the bilateral depth filter); the 2 cm target is not met on this small
    # room's walk at 160 x 120 without the colour term
    assert errors["model"] < 0.1, errors
    assert errors["model"] < errors["frame"], errors


def test_a_lost_frame_is_logged_skipped_and_not_fused_by_frame_to_model_tracking(caplog):
    truth, depths = noisy_sequence()
    broken = depths[:12].copy()
    broken[6] = 0.0
    tracker = Tracker(INTRINSICS, MODEL, T_world_first=truth[0])
    weights = []
    with caplog.at_level("WARNING"):
        frames = []
        for d in broken:
            frames.append(tracker.track(d))
            model = tracker.model
            assert model is not None
            weights.append(float(np.asarray(model[0].weight).sum()))
    assert [f.lost for f in frames] == [i == 6 for i in range(12)]
    assert "tracking lost at frame 6" in caplog.text and "found again at frame 7 after 1 lost" in caplog.text
    np.testing.assert_array_equal(frames[6].T_world_camera, frames[5].T_world_camera)
    assert weights[6] == weights[5] < weights[7]  # the lost frame added nothing to the model
    estimated = np.stack([f.T_world_camera for i, f in enumerate(frames) if i != 6])
    # measured 14 mm (55 mm with the TSDF gradient's normals): over its first frames the model is thin and noisy
    assert ate_rmse(estimated, np.delete(truth[:12], 6, axis=0)) < 0.05


def test_the_wrong_image_size_is_refused():
    with pytest.raises(ValueError, match="the camera is 160x120"):
        Tracker(INTRINSICS).track(np.zeros((10, 10), np.float32))


def test_the_tum_trajectory_reads_back(tmp_path):
    truth, _ = sequence()
    rng = np.random.default_rng(0)
    poses = list(truth[:5])
    for _ in range(20):  # rotations of every kind, also near 180 degrees (the quaternion's other branches)
        q = rng.normal(size=4)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = quaternion_to_matrix(q / np.linalg.norm(q)), rng.normal(size=3)
        poses.append(T)
    for axis in np.eye(3):
        T = np.eye(4)
        T[:3, :3] = 2 * np.outer(axis, axis) - np.eye(3)  # 180 degrees about an axis
        poses.append(T)
    stamps = 1000.0 + np.arange(len(poses)) / 30
    path = write_tum_trajectory(tmp_path / "trajectory_tum.txt", stamps, poses)
    rows = np.loadtxt(path)
    assert rows.shape == (len(poses), 8)
    np.testing.assert_allclose(rows[:, 0], stamps, atol=1e-6)
    for row, T in zip(rows, poses):
        np.testing.assert_allclose(row[1:4], T[:3, 3], atol=1e-6)
        np.testing.assert_allclose(quaternion_to_matrix(row[4:]), T[:3, :3], atol=1e-6)
    np.testing.assert_allclose(rotation_to_quaternion(np.eye(3)), [0, 0, 0, 1])


@pytest.mark.slow
def test_tracking_time_per_frame():
    """Warm ms per frame at 160x120 (printed; run with -s): maps of the frame plus the ICP, host sync included."""
    truth, depths = sequence()
    for config in (FRAME, MODEL):
        track_depths(depths[:3], INTRINSICS, config)  # compile
        start = time.perf_counter()
        track_depths(depths, INTRINSICS, config)
        ms = (time.perf_counter() - start) / (len(depths) - 1) * 1e3
        print(f"tracking {WIDTH}x{HEIGHT} against the {config.reference}: {ms:.1f} ms per frame over {len(depths)} frames")
        assert ms < 1000


def test_frame_to_model_compiles_one_step(caplog):
    """The first frame runs the later frames' executable (`start_model` is `track_and_fuse` with `first`): a cold
    start compiles one step, and the first frame is fused at its given pose."""
    import jax

    truth, depths = sequence()
    config = TrackingConfig(reference="model", raycast_steps=61)  # a config no other test compiles
    jax.config.update("jax_log_compiles", True)
    try:
        with caplog.at_level("WARNING", logger="jax"):
            frames = track_depths(depths[:4], INTRINSICS, config, T_world_first=truth[0])
    finally:
        jax.config.update("jax_log_compiles", False)
    compiled = [r.getMessage() for r in caplog.records if r.getMessage().startswith("Compiling jit(")]
    assert sum("track_and_fuse" in m for m in compiled) == 1, compiled
    assert not any("start_model" in m for m in compiled)
    np.testing.assert_allclose(frames[0].T_world_camera, truth[0])
    assert not any(f.lost for f in frames) and ate_rmse(np.stack([f.T_world_camera for f in frames]), truth[:4]) < 1e-3


def test_frame_to_model_with_colour_follows_a_walk_along_a_flat_wall():
    """Sliding 5 mm a frame along a textured wall: the depth alone sees no motion, the colour term follows it."""
    from test_tracking import INTRINSICS as WALL_CAMERA
    from test_tracking import _textured_wall

    truth = [np.eye(4) for _ in range(20)]
    for k, T in enumerate(truth):
        T[0, 3] = 0.005 * k
    frames = [_textured_wall(T) for T in truth]
    with_color, depth_only = Tracker(WALL_CAMERA, MODEL), Tracker(WALL_CAMERA, MODEL)
    for depth, color in frames:
        followed = with_color.track(depth, color)
        stood = depth_only.track(depth)
    assert abs(followed.T_world_camera[0, 3] - truth[-1][0, 3]) < 0.005 and with_color.frames_lost == 0
    assert abs(stood.T_world_camera[0, 3]) < 0.03  # the last of 9.5 cm not seen
    with pytest.raises(ValueError, match="colour of shape"):
        with_color.track(frames[0][0], frames[0][1][:10])
