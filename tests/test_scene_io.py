"""Scene readers: tiny synthetic scenes in both layouts, and the real ScanNet scene when present."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io.scene import backproject, open_scene, read_trajectory_log
from fmfusion_jax.types import CameraIntrinsics

WIDTH, HEIGHT = 32, 24
INTRINSICS = CameraIntrinsics(fx=30.0, fy=30.0, cx=15.5, cy=11.5, width=WIDTH, height=HEIGHT)
#: BGR as written by cv2 -> RGB (200, 100, 50) when read back.
BGR = (50, 100, 200)


def pose_at(x: float) -> np.ndarray:
    """A camera at (x, 0, 0) looking along world +z (identity rotation)."""
    pose = np.eye(4)
    pose[0, 3] = x
    return pose


def depth_mm(frame: int) -> np.ndarray:
    """uint16 depth: 2000 + frame mm, a 0 (invalid) pixel and a far 5000 mm pixel."""
    depth = np.full((HEIGHT, WIDTH), 2000 + frame, np.uint16)
    depth[0, 0] = 0
    depth[1, 1] = 5000
    return depth


def write_matrix(path: Path, matrix: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(" ".join(f"{x:f}" for x in row) for row in matrix) + "\n")


def make_scene(
    root: Path,
    layout: str = "scannet",
    num_frames: int = 6,
    color_size=(WIDTH, HEIGHT),
    poses: list[np.ndarray] | None = None,
    pose_files: bool = True,
) -> Path:
    """Writes a tiny scene of `num_frames` frames in `layout` under `root`; returns `root`."""
    color_dir, color_name, depth_name, pose_name = {
        "scannet": ("color", "frame-{:06d}.jpg", "frame-{:06d}.png", "frame-{:06d}.txt"),
        "scenenn": ("image", "image{:05d}.png", "depth{:05d}.png", "frame-{:05d}.txt"),
    }[layout]
    for folder in (color_dir, "depth", "intrinsic"):
        (root / folder).mkdir(parents=True, exist_ok=True)
    K = np.eye(4)
    K[:3, :3] = INTRINSICS.matrix
    write_matrix(root / "intrinsic" / "intrinsic_depth.txt", K)
    poses = poses if poses is not None else [pose_at(0.1 * i) for i in range(num_frames)]
    color = np.zeros((color_size[1], color_size[0], 3), np.uint8)
    color[:] = BGR
    for i in range(num_frames):
        cv2.imwrite(str(root / color_dir / color_name.format(i)), color)
        cv2.imwrite(str(root / "depth" / depth_name.format(i)), depth_mm(i))
        if pose_files:
            write_matrix(root / "pose" / pose_name.format(i), poses[i])
    return root


@pytest.mark.parametrize("layout", ["scannet", "scenenn"])
def test_reads_both_layouts(tmp_path, layout):
    scene = open_scene(make_scene(tmp_path / "room", layout))
    assert scene.layout == layout and scene.name == "room" and len(scene) == 6
    assert scene.intrinsics == INTRINSICS  # image size taken from the first depth image
    expected_names = [f"frame-{i:06d}" for i in range(6)] if layout == "scannet" else [f"image{i:05d}" for i in range(6)]
    assert scene.frame_names == expected_names
    assert scene.poses().shape == (6, 4, 4)
    frames = list(scene.frames())
    frame = frames[3]
    assert frame.index == 3 and frame.name == expected_names[3]
    assert frame.color.shape == (HEIGHT, WIDTH, 3) and frame.color.dtype == np.uint8
    np.testing.assert_allclose(frame.color.reshape(-1, 3).mean(0), (200, 100, 50), atol=3)  # RGB order
    assert frame.depth.dtype == np.float32 and frame.depth.shape == (HEIGHT, WIDTH)
    assert frame.depth[5, 5] == pytest.approx(2.003)
    np.testing.assert_array_equal(frame.T_world_camera, pose_at(0.3))
    assert frame.intrinsics == INTRINSICS


def test_depth_truncation_and_scale(tmp_path):
    scene = open_scene(make_scene(tmp_path / "s"), depth_max=4.0)
    depth = scene.read_frame(0).depth
    assert depth[0, 0] == 0 and depth[1, 1] == 0  # invalid stays 0, 5 m > depth_max becomes 0
    assert open_scene(tmp_path / "s", depth_max=6.0).read_frame(0).depth[1, 1] == pytest.approx(5.0)
    assert open_scene(tmp_path / "s", depth_scale=500.0, depth_max=6.0).read_frame(0).depth[5, 5] == pytest.approx(4.0)


def test_stride_and_max_frames(tmp_path):
    make_scene(tmp_path / "s", num_frames=7)
    scene = open_scene(tmp_path / "s", stride=3)
    assert scene.frame_names == ["frame-000000", "frame-000003", "frame-000006"]
    assert [frame.index for frame in scene.frames()] == [0, 3, 6]
    scene = open_scene(tmp_path / "s", stride=2, max_frames=2)
    assert scene.frame_names == ["frame-000000", "frame-000002"] and len(scene) == 2
    with pytest.raises(UserError, match="stride"):
        open_scene(tmp_path / "s", stride=0)


@pytest.mark.parametrize("bad", [np.nan, -np.inf])
def test_non_finite_pose_is_skipped_with_a_warning(tmp_path, caplog, bad):
    poses = [pose_at(0.1 * i) for i in range(4)]
    poses[2] = np.full((4, 4), bad)
    make_scene(tmp_path / "s", num_frames=4, poses=poses)
    with caplog.at_level(logging.WARNING, logger="fmfusion_jax.io.scene"):
        scene = open_scene(tmp_path / "s")
    assert scene.frame_names == ["frame-000000", "frame-000001", "frame-000003"]
    assert [f.index for f in scene.frames()] == [0, 1, 3]
    assert [name for name, _ in scene.skipped] == ["frame-000002"]
    assert "frame-000002" in caplog.text and "non-finite" in caplog.text
    # max_frames counts usable frames
    assert open_scene(tmp_path / "s", max_frames=3).frame_names[-1] == "frame-000003"


def test_missing_depth_file_is_a_data_error_naming_it(tmp_path):
    make_scene(tmp_path / "s")
    (tmp_path / "s" / "depth" / "frame-000004.png").unlink()
    with pytest.raises(DataError, match="frame-000004.png"):
        open_scene(tmp_path / "s")
    # a stride that leaves that frame out does not need it
    assert len(open_scene(tmp_path / "s", stride=3)) == 2


def test_missing_pose_file_is_a_data_error_naming_it(tmp_path):
    make_scene(tmp_path / "s")
    (tmp_path / "s" / "pose" / "frame-000001.txt").unlink()
    with pytest.raises(DataError, match="frame-000001.txt"):
        open_scene(tmp_path / "s")


@pytest.mark.parametrize(
    "content, message", [("1 2 3", "4x4"), ("a b c", "numbers"), ("2 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1", "rigid")]
)
def test_malformed_pose_is_a_data_error(tmp_path, content, message):
    make_scene(tmp_path / "s")
    (tmp_path / "s" / "pose" / "frame-000002.txt").write_text(content)
    with pytest.raises(DataError, match=f"frame-000002.txt.*{message}"):
        open_scene(tmp_path / "s")


@pytest.mark.parametrize("which", ["color/frame-000002.jpg", "depth/frame-000002.png"])
def test_corrupt_image_is_a_data_error_naming_it(tmp_path, which):
    make_scene(tmp_path / "s")
    (tmp_path / "s" / which).write_bytes(b"not an image at all")
    scene = open_scene(tmp_path / "s")
    scene.read_frame(1)
    with pytest.raises(DataError, match=Path(which).name):
        scene.read_frame(2)


def test_colour_of_another_size_is_resized_with_one_note(tmp_path, caplog):
    make_scene(tmp_path / "s", color_size=(2 * WIDTH, 2 * HEIGHT))
    scene = open_scene(tmp_path / "s")
    with caplog.at_level(logging.INFO, logger="fmfusion_jax.io.scene"):
        frames = list(scene.frames())
    assert all(frame.color.shape == (HEIGHT, WIDTH, 3) for frame in frames)
    np.testing.assert_allclose(frames[0].color.reshape(-1, 3).mean(0), (200, 100, 50), atol=3)
    assert sum("resized" in record.message for record in caplog.records) == 1


def test_depth_of_another_size_than_the_intrinsics_is_a_data_error(tmp_path):
    make_scene(tmp_path / "s")
    (tmp_path / "s" / "intrinsic" / "sensor_shapes.txt").write_text(
        "color_width:64\ncolor_height:48\ndepth_width:64\ndepth_height:48\n"
    )
    scene = open_scene(tmp_path / "s")
    assert (scene.intrinsics.width, scene.intrinsics.height) == (64, 48)
    with pytest.raises(DataError, match="frame-000000.png.*intrinsics"):
        scene.read_frame(0)


def test_depth_must_be_uint16(tmp_path):
    make_scene(tmp_path / "s")
    cv2.imwrite(str(tmp_path / "s" / "depth" / "frame-000001.png"), np.zeros((HEIGHT, WIDTH), np.uint8))
    with pytest.raises(DataError, match="frame-000001.png.*uint16"):
        open_scene(tmp_path / "s").read_frame(1)


def test_unknown_layout_lists_what_was_expected(tmp_path):
    (tmp_path / "s" / "rgb").mkdir(parents=True)
    with pytest.raises(UserError, match="unknown scene layout.*scannet: color/.*scenenn: image/"):
        open_scene(tmp_path / "s")
    with pytest.raises(UserError, match="not found"):
        open_scene(tmp_path / "absent")
    with pytest.raises(UserError, match="layout 'kinect'"):
        open_scene(make_scene(tmp_path / "ok"), layout="kinect")


def test_missing_intrinsics_is_a_data_error(tmp_path):
    make_scene(tmp_path / "s")
    (tmp_path / "s" / "intrinsic" / "intrinsic_depth.txt").unlink()
    with pytest.raises(DataError, match="intrinsic_depth.txt"):
        open_scene(tmp_path / "s")


def test_scenenn_trajectory_log_replaces_pose_files(tmp_path):
    poses = [pose_at(0.2 * i) for i in range(3)]
    root = make_scene(tmp_path / "nn", "scenenn", num_frames=3, pose_files=False)
    blocks = [f"{i} {i} {i + 1}\n" + "\n".join(" ".join(f"{x:f}" for x in row) for row in pose) for i, pose in enumerate(poses)]
    (root / "trajectory.log").write_text("\n".join(blocks) + "\n")
    scene = open_scene(root)
    assert scene.layout == "scenenn" and len(scene) == 3
    np.testing.assert_allclose(scene.poses(), np.array(poses))
    assert read_trajectory_log(root / "trajectory.log").shape == (3, 4, 4)


def test_bounds_hold_the_observed_points(tmp_path):
    scene = open_scene(make_scene(tmp_path / "s"))
    lower, upper = scene.bounds(margin=0.0, pixel_step=1)
    # cameras at x = 0..0.5 looking along +z at a wall ~2 m away
    assert lower[2] == pytest.approx(2.0, abs=0.01) and upper[2] == pytest.approx(2.005, abs=0.01)
    half_width = 2.005 * (WIDTH - 1 - INTRINSICS.cx) / INTRINSICS.fx
    assert upper[0] == pytest.approx(0.5 + half_width, abs=0.01)
    frustum_lower, frustum_upper = scene.bounds(method="frustum")
    assert np.all(frustum_lower <= lower) and np.all(upper <= frustum_upper)
    assert frustum_lower[2] == 0.0 and frustum_upper[2] == pytest.approx(4.0)
    lower_m, upper_m = scene.bounds(margin=0.25)
    assert np.all(lower_m <= lower) and np.all(upper_m >= upper)


def test_backproject_inverts_the_pinhole_projection():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 3.0, (HEIGHT, WIDTH)).astype(np.float32)
    depth[3, 4] = 0
    points = backproject(depth, INTRINSICS)
    assert points.shape == (HEIGHT * WIDTH - 1, 3)
    uv = points[:, :2] / points[:, 2:] * [INTRINSICS.fx, INTRINSICS.fy] + [INTRINSICS.cx, INTRINSICS.cy]
    v, u = np.nonzero(depth)
    np.testing.assert_allclose(uv, np.stack([u, v], 1), atol=1e-6)


@pytest.mark.scannet
def test_real_scannet_scene(scannet_scene):
    scene = open_scene(scannet_scene)
    assert scene.layout == "scannet" and len(scene) == 300 and not scene.skipped
    assert (scene.intrinsics.width, scene.intrinsics.height) == (640, 480)
    assert scene.intrinsics.fx == pytest.approx(577.59, abs=0.01)
    assert scene.intrinsics.fy == pytest.approx(578.73, abs=0.01)
    frame = scene.read_frame(100)
    assert frame.name == "frame-000100" and frame.color.shape == (480, 640, 3)
    assert 0 < frame.depth.max() <= 4.0
    assert np.all(np.isfinite(scene.poses()))
    assert all(scene.ground_truth_files().values())


@pytest.mark.scannet
def test_real_depth_lands_on_the_ground_truth_mesh(scannet_scene):
    """Back-projected depth of a few frames lies within a few cm of the mesh (poses, scale, K consistent)."""
    trimesh = pytest.importorskip("trimesh")
    from scipy.spatial import cKDTree

    scene = open_scene(scannet_scene, stride=100)
    mesh = trimesh.load(scene.ground_truth_files()["mesh"], process=False)
    tree = cKDTree(np.asarray(mesh.vertices))
    for frame in scene.frames():
        points = backproject(frame.depth, frame.intrinsics, pixel_step=8)
        world = points @ frame.T_world_camera[:3, :3].T + frame.T_world_camera[:3, 3]
        distances, _ = tree.query(world)
        assert np.median(distances) < 0.05, frame.name
    lower, upper = open_scene(scannet_scene).bounds()  # from 60 of the 300 frames
    assert np.all(lower <= mesh.bounds[0] + 0.3) and np.all(upper >= mesh.bounds[1] - 0.3)


def test_scannet_sensreader_numeric_names(tmp_path):
    """ScanNet's SensReader export names frames 0.jpg, 1.jpg, ... 10.jpg: ordered by number, not as text."""
    root = make_scene(tmp_path / "s", num_frames=11)
    for folder, suffix in (("color", ".jpg"), ("depth", ".png"), ("pose", ".txt")):
        for i in range(11):
            (root / folder / f"frame-{i:06d}{suffix}").rename(root / folder / f"{i}{suffix}")
    scene = open_scene(root)
    assert scene.frame_names == [str(i) for i in range(11)]
    np.testing.assert_allclose(scene.read_frame(10).T_world_camera, pose_at(1.0))
