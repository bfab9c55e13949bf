"""TUM RGB-D, Replica and Open3D/Redwood recordings (`io.recordings`): a generated room written in the ScanNet
layout and copied into each format by the small writers below reads back as the ScanNet scene does (poses,
camera, depth to the format's quantisation, colour); the same map from the TUM copy; the bad recordings'
errors; the pose interpolation."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation, Slerp

import fmfusion_jax.cli as cli
from fmfusion_jax.cli.options import LAYOUT_CHOICES
from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io.recordings import interpolate_pose
from fmfusion_jax.io.scene import LAYOUTS, detect_layout, open_scene
from fmfusion_jax.types import CameraIntrinsics

NUM_FRAMES, WIDTH, HEIGHT = 12, 160, 120
T0, DT = 1305031102.0, 1 / 30  # TUM-like time stamps (seconds since 1970), 30 Hz


@dataclasses.dataclass
class Frames:
    """A sequence to write: RGB uint8 `(N, H, W, 3)`, uint16 millimetres `(N, H, W)`, camera-to-world `(N, 4, 4)`."""

    colors: np.ndarray
    depths_mm: np.ndarray
    poses: np.ndarray
    intrinsics: CameraIntrinsics


def _number(x: float) -> str:
    return repr(float(x))  # reads back to the same float


def write_tum(frames: Frames, out: Path, depth_offset: float = 0.004, gt_frames: slice = slice(None)) -> Path:
    """TUM layout: rgb/ and depth/ PNGs named by stamp (depth 5000 per metre, `depth_offset` s after the colour),
    rgb.txt, depth.txt, groundtruth.txt at the colour stamps of `gt_frames`, intrinsics.txt."""
    (out / "rgb").mkdir(parents=True)
    (out / "depth").mkdir()
    rgb, depth, gt = ["# color images", "# timestamp filename"], ["# depth maps", "# timestamp filename"], ["# ground truth"]
    for i, (color, depth_mm, pose) in enumerate(zip(frames.colors, frames.depths_mm, frames.poses)):
        t, td = T0 + i * DT, T0 + i * DT + depth_offset
        cv2.imwrite(str(out / "rgb" / f"{t:.6f}.png"), cv2.cvtColor(color, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(out / "depth" / f"{td:.6f}.png"), (depth_mm.astype(np.uint32) * 5).astype(np.uint16))
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth.append(f"{td:.6f} depth/{td:.6f}.png")
        qx, qy, qz, qw = Rotation.from_matrix(pose[:3, :3]).as_quat()
        gt.append(" ".join([f"{t:.6f}"] + [_number(x) for x in (*pose[:3, 3], qx, qy, qz, qw)]))
    (out / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (out / "depth.txt").write_text("\n".join(depth) + "\n")
    (out / "groundtruth.txt").write_text("\n".join(gt[:1] + gt[1:][gt_frames]) + "\n")
    K = frames.intrinsics
    (out / "intrinsics.txt").write_text(f"# fx fy cx cy\n{_number(K.fx)} {_number(K.fy)} {_number(K.cx)} {_number(K.cy)}\n")
    return out


def write_replica(frames: Frames, out: Path) -> Path:
    """NICE-SLAM's Replica layout: results/frame%06d.png + depth%06d.png (6553.5 per metre), traj.txt,
    cam_params.json (this camera, not Replica's)."""
    (out / "results").mkdir(parents=True)
    lines = []
    for i, (color, depth_mm, pose) in enumerate(zip(frames.colors, frames.depths_mm, frames.poses)):
        cv2.imwrite(str(out / "results" / f"frame{i:06d}.png"), cv2.cvtColor(color, cv2.COLOR_RGB2BGR))
        raw = np.round(depth_mm.astype(np.float64) * 6.5535).astype(np.uint16)
        cv2.imwrite(str(out / "results" / f"depth{i:06d}.png"), raw)
        lines.append(" ".join(_number(x) for x in pose.reshape(-1)))
    (out / "traj.txt").write_text("\n".join(lines) + "\n")
    K = frames.intrinsics
    camera = {"w": K.width, "h": K.height, "fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy, "scale": 6553.5}
    (out / "cam_params.json").write_text(json.dumps({"camera": camera}))
    return out


def write_redwood(frames: Frames, out: Path, color_dir: str = "color") -> Path:
    """Open3D's recorder layout: color/%06d.png, depth/%06d.png (millimetres), camera_intrinsic.json
    (column-major), trajectory.log (Redwood format)."""
    (out / color_dir).mkdir(parents=True)
    (out / "depth").mkdir()
    blocks = []
    for i, (color, depth_mm, pose) in enumerate(zip(frames.colors, frames.depths_mm, frames.poses)):
        cv2.imwrite(str(out / color_dir / f"{i:06d}.png"), cv2.cvtColor(color, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(out / "depth" / f"{i:06d}.png"), depth_mm)
        blocks.append(f"{i} {i} {len(frames.poses)}\n" + "\n".join(" ".join(_number(x) for x in row) for row in pose))
    (out / "trajectory.log").write_text("\n".join(blocks) + "\n")
    K = frames.intrinsics
    matrix = [K.fx, 0.0, 0.0, 0.0, K.fy, 0.0, K.cx, K.cy, 1.0]
    (out / "camera_intrinsic.json").write_text(json.dumps({"width": K.width, "height": K.height, "intrinsic_matrix": matrix}))
    return out


WRITERS = {"tum": write_tum, "replica": write_replica, "redwood": write_redwood}
#: Depth quantisation of each format, metres (half a raw unit; TUM's 5 units per mm and Redwood's mm are exact).
DEPTH_TOLERANCE = {"tum": 1e-6, "replica": 0.5 / 6553.5 + 1e-6, "redwood": 1e-6}


def frames_of(scene_dir: Path) -> Frames:
    """The frames of a ScanNet-layout scene, as stored (raw millimetres)."""
    scene = open_scene(scene_dir, depth_max=100.0)
    colors = np.stack([scene.read_color(i) for i in range(len(scene))])
    depths = np.stack([cv2.imread(str(scene.depth_path(i)), cv2.IMREAD_UNCHANGED) for i in range(len(scene))])
    return Frames(colors, depths, scene.poses(), scene.intrinsics)


def tiny_frames(num_frames: int = 6, width: int = 32, height: int = 24) -> Frames:
    """A camera sliding along x and turning about y in front of a flat wall 2 m away."""
    poses = np.stack([np.eye(4)] * num_frames)
    for i in range(num_frames):
        poses[i, :3, :3] = Rotation.from_euler("y", 3.0 * i, degrees=True).as_matrix()
        poses[i, 0, 3] = 0.1 * i
    colors = np.full((num_frames, height, width, 3), (200, 100, 50), np.uint8)
    depths = np.full((num_frames, height, width), 2000, np.uint16) + np.arange(num_frames, dtype=np.uint16)[:, None, None]
    intrinsics = CameraIntrinsics(30.0, 30.0, width / 2 - 0.5, height / 2 - 0.5, width, height)
    return Frames(colors, depths, poses, intrinsics)


def bed_and_table_room(root: Path, name: str) -> Path:
    """A generated room (a bed and a table) of `NUM_FRAMES` frames at `WIDTH` x `HEIGHT` written in the ScanNet
    layout as `root/name`, with simulated clean detections in `root/detections`: the scene every recording format's
    tests write in their format and compare with."""
    from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
    from fmfusion_jax.simulation.noise import NoiseModel
    from fmfusion_jax.simulation.procedural import add_object, empty_room
    from fmfusion_jax.simulation.scannet_writer import write_scannet_scene
    from fmfusion_jax.simulation.simulate import simulate_scene

    room = empty_room((4.0, 4.0, 2.6), seed=3)
    room = add_object(room, "bed", [((1.0, 1.1, 0.3), (1.4, 1.9, 0.6), 0.0)])
    room = add_object(room, "table", [((3.0, 3.0, 0.375), (1.0, 0.8, 0.75), 0.0)])
    scene_dir = write_scannet_scene(room, root / name, num_frames=NUM_FRAMES, width=WIDTH, height=HEIGHT, progress=False)
    noise = NoiseModel.preset("clean", seed=0, min_mask_pixels=10, small_object_pixels=20)
    simulate_scene(open_scene(scene_dir), load_scannet_ground_truth(scene_dir), root / "detections", noise, progress=False)
    return scene_dir


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    return bed_and_table_room(tmp_path_factory.mktemp("recordings"), "synth0003_00")


# --------------------------------------------------------------------------------------------------
# Each format reads back as the ScanNet layout of the same room.


@pytest.mark.parametrize("layout", ["tum", "replica", "redwood"])
def test_a_copy_reads_back_as_the_scannet_scene(room, tmp_path, layout):
    copy = WRITERS[layout](frames_of(room), tmp_path / f"rec_{layout}")
    assert detect_layout(copy) == layout
    reference, scene = open_scene(room, depth_max=10.0), open_scene(copy, depth_max=10.0)
    assert scene.layout == layout and len(scene) == len(reference) == NUM_FRAMES and not scene.skipped
    assert scene.depth_scale == {"tum": 5000.0, "replica": 6553.5, "redwood": 1000.0}[layout]
    assert scene.intrinsics == reference.intrinsics
    np.testing.assert_allclose(scene.poses(), reference.poses(), atol=1e-6)
    np.testing.assert_array_equal(scene.frame_indices, np.arange(NUM_FRAMES))
    for i in (0, 5, NUM_FRAMES - 1):
        ours, theirs = scene.read_frame(i), reference.read_frame(i)
        np.testing.assert_array_equal(ours.color, theirs.color)
        np.testing.assert_allclose(ours.depth, theirs.depth, atol=DEPTH_TOLERANCE[layout], rtol=0)
        assert ours.intrinsics == theirs.intrinsics
    # the user's depth scale wins over the format's own; the stride and the frame limit work as for ScanNet
    assert open_scene(copy, depth_scale=1000.0).depth_scale == 1000.0
    strided = open_scene(copy, stride=3, max_frames=3)
    np.testing.assert_array_equal(strided.frame_indices, [0, 3, 6])
    np.testing.assert_allclose(strided.poses(), reference.poses()[[0, 3, 6]], atol=1e-6)


def test_the_same_map_from_the_tum_copy(room, tmp_path):
    """The Mapper over the TUM copy's frames (detections looked up by the ScanNet frame of the same index)
    builds the map it builds from the ScanNet layout."""
    from fmfusion_jax.io.detections import DetectionFolder
    from fmfusion_jax.mapping.mapper import Mapper
    from fmfusion_jax.simulation.demo_setup import demo_config

    copy = write_tum(frames_of(room), tmp_path / "rec_tum")
    folder = DetectionFolder(room.parent / "detections", image_shape=(HEIGHT, WIDTH))
    reference_names = open_scene(room).frame_names
    results = []
    for path in (room, copy):
        scene = open_scene(path)
        mapper = Mapper(demo_config(NUM_FRAMES, WIDTH, HEIGHT), bounds=scene.bounds())
        for frame in scene.frames():
            detections = folder.get(reference_names[frame.index])
            if detections is not None:
                detections = dataclasses.replace(detections, frame_name=frame.name)
            mapper.integrate(frame, detections)
        mapper.finalize()
        results.append((len(mapper.instances()), mapper.extract_point_cloud()[0]))
    (count, points), (tum_count, tum_points) = results
    assert count >= 2 and tum_count == count
    assert tum_points.shape == points.shape
    # the same surface: every point has its twin within float32 noise (the order of the points may differ)
    distances, _ = cKDTree(points).query(tum_points)
    assert distances.max() < 1e-4  # measured: 5e-5 m at most, median 1e-7


def test_fmfusion_info_reads_each_format(room, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(cli, "SUBCOMMANDS", ("info",))
    frames = frames_of(room)
    for layout, writer in WRITERS.items():
        copy = writer(frames, tmp_path / layout)
        assert cli.main(["info", str(copy)]) == 0
        out = capsys.readouterr().out
        assert f"layout        {layout}" in out and f"{NUM_FRAMES} usable" in out and "Traceback" not in out


def test_the_layout_choices_are_the_readers():
    assert LAYOUT_CHOICES == ("auto", *LAYOUTS)


# --------------------------------------------------------------------------------------------------
# TUM specifics: association, interpolation, the trajectory's span, the camera.


def test_tum_pairs_by_time_and_interpolates_poses(tmp_path):
    frames = tiny_frames(6)
    root = write_tum(frames, tmp_path / "rec", depth_offset=0.012)
    gt = (root / "groundtruth.txt").read_text().splitlines()
    (root / "groundtruth.txt").write_text("\n".join(gt[:1] + gt[1::2]) + "\n")  # poses of frames 0, 2, 4 only
    with open(root / "depth.txt", "a") as depth_list:  # a depth image with no colour image near it: ignored
        depth_list.write(f"{T0 + 100:.6f} depth/{T0 + 0.012:.6f}.png\n")
    scene = open_scene(root)
    assert scene.frame_names == [f"{T0 + i * DT:.6f}" for i in range(5)]
    assert len(scene.skipped) == 1 and scene.skipped[0][0] == f"{T0 + 5 * DT:.6f}"
    assert "outside the time span of groundtruth.txt" in scene.skipped[0][1]
    poses = scene.poses()
    np.testing.assert_allclose(poses[[0, 2, 4]], frames.poses[[0, 2, 4]], atol=1e-6)
    # between two poses: translation linear, rotation slerp (a constant turn); to the microsecond stamps' precision
    np.testing.assert_allclose(poses[[1, 3]], frames.poses[[1, 3]], atol=1e-5)
    assert scene.read_frame(2).depth[0, 0] == pytest.approx(2.002)


def test_tum_tolerance_and_unsynchronised_streams(tmp_path):
    root = write_tum(tiny_frames(4), tmp_path / "rec", depth_offset=0.5)  # depth 0.5 s late: the streams miss
    with pytest.raises(DataError, match=r"rgb.txt.*depth.txt.*no colour image has a depth image within 0.02 s"):
        open_scene(root)
    scene = open_scene(root, max_time_difference=0.6)
    assert len(scene) == 4 and not scene.skipped


def test_tum_camera_files_and_freiburg_defaults(tmp_path):
    frames = tiny_frames(2, width=640, height=480)
    root = write_tum(frames, tmp_path / "rec")
    (root / "intrinsics.txt").unlink()
    with pytest.raises(DataError, match="no camera intrinsics.*intrinsics.txt"):
        open_scene(root)
    (root / "intrinsics.txt").write_text("500 500 319.5\n")
    with pytest.raises(DataError, match=r"intrinsics.txt: expected the four numbers 'fx fy cx cy', found 3"):
        open_scene(root)
    (root / "intrinsics.txt").unlink()
    K = frames.intrinsics
    json_camera = {"width": K.width, "height": K.height, "intrinsic_matrix": [K.fx, 0, 0, 0, K.fy, 0, K.cx, K.cy, 1]}
    (root / "camera_intrinsic.json").write_text(json.dumps(json_camera))
    assert open_scene(root).intrinsics == K
    (root / "camera_intrinsic.json").unlink()
    freiburg = root.rename(tmp_path / "rgbd_dataset_freiburg3_long_office_household")
    camera = open_scene(freiburg).intrinsics
    assert (camera.fx, camera.fy, camera.cx, camera.cy, camera.width) == (535.4, 539.2, 320.1, 247.6, 640)


@pytest.mark.parametrize(
    "break_it, message",
    [
        (lambda root: (root / "groundtruth.txt").unlink(), "groundtruth.txt: file missing.*poses"),
        (lambda root: (root / "rgb.txt").write_text("# nothing\n"), "rgb.txt: no entry"),
        (lambda root: _append(root / "rgb.txt", "1305031200.0\n"), r"rgb.txt: line 7: expected 'timestamp path'"),
        (lambda root: _append(root / "depth.txt", "soon depth/x.png\n"), r"depth.txt: line 7: could not convert"),
        (lambda root: _append(root / "groundtruth.txt", "1 2 3\n"), r"groundtruth.txt: line 6: expected 8 numbers"),
        (lambda root: _append(root / "groundtruth.txt", f"{T0 + 9:.6f} 0 0 0 0 0 0 0\n"), "quaternion .* is zero"),
        (lambda root: next((root / "depth").iterdir()).unlink(), r"depth/.*\.png: file missing"),
        (lambda root: _shift_stamps(root / "groundtruth.txt", 100.0), "the trajectory spans .* no frame lies within it"),
    ],
)
def test_bad_tum_recordings_are_named_errors(tmp_path, break_it, message):
    root = write_tum(tiny_frames(4), tmp_path / "rec")
    break_it(root)
    with pytest.raises(DataError, match=message):
        open_scene(root)


def _append(path: Path, line: str) -> None:
    path.write_text(path.read_text() + line)


def _shift_stamps(path: Path, seconds: float) -> None:
    lines = [line.split() for line in path.read_text().splitlines() if not line.startswith("#")]
    path.write_text("\n".join(" ".join([f"{float(f[0]) + seconds:.6f}", *f[1:]]) for f in lines) + "\n")


@settings(max_examples=30, deadline=None)
@given(
    rotations=st.lists(st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: np.linalg.norm(q) > 0.1), min_size=2, max_size=5),
    steps=st.lists(st.floats(0.005, 0.5), min_size=4, max_size=4),
    share=st.floats(0, 1),
)
def test_interpolation_meets_the_poses_at_their_stamps_and_slerps_between(rotations, steps, share):
    quaternions = np.array([q / np.linalg.norm(q) for q in rotations])
    stamps = 100.0 + np.concatenate([[0.0], np.cumsum(steps[: len(quaternions) - 1])])
    translations = np.arange(len(quaternions) * 3, dtype=np.float64).reshape(-1, 3)
    for k, t in enumerate(stamps):
        pose = interpolate_pose(stamps, translations, quaternions, float(t))
        np.testing.assert_allclose(pose[:3, :3], Rotation.from_quat(quaternions[k]).as_matrix(), atol=1e-9)
        np.testing.assert_allclose(pose[:3, 3], translations[k], atol=1e-9)
    t = stamps[0] + share * (stamps[1] - stamps[0])
    share = (t - stamps[0]) / (stamps[1] - stamps[0])  # of the rounded t
    pose = interpolate_pose(stamps, translations, quaternions, float(t))
    expected = Slerp([stamps[0], stamps[1]], Rotation.from_quat(quaternions[:2]))([t]).as_matrix()[0]
    np.testing.assert_allclose(pose[:3, :3], expected, atol=1e-6)
    np.testing.assert_allclose(pose[:3, 3], translations[0] + share * (translations[1] - translations[0]), atol=1e-6)


# --------------------------------------------------------------------------------------------------
# Replica and Redwood specifics.


def test_replica_without_cam_params_uses_replicas_camera(tmp_path):
    frames = tiny_frames(3, width=1200, height=680)
    root = write_replica(frames, tmp_path / "Replica" / "room0")
    (root / "cam_params.json").rename(tmp_path / "Replica" / "cam_params.json")  # the download keeps it in its root
    assert open_scene(root).intrinsics == frames.intrinsics
    (tmp_path / "Replica" / "cam_params.json").unlink()
    scene = open_scene(root)
    assert (scene.intrinsics.fx, scene.intrinsics.cx, scene.intrinsics.cy, scene.depth_scale) == (600.0, 599.5, 339.5, 6553.5)


@pytest.mark.parametrize(
    "break_it, message",
    [
        (lambda root: _drop_last_line(root / "traj.txt"), r"traj.txt: 2 poses for 3 frames"),
        (lambda root: (root / "traj.txt").write_text("1 0 0\n" * 3), r"traj.txt: line 1: expected 16 numbers"),
        (lambda root: (root / "results" / "depth000001.png").unlink(), r"depth000001.png: file missing \(1 of 3"),
        (lambda root: (root / "results" / "frame000002.png").unlink(), r"depth000002.png: its colour image is missing"),
        (lambda root: (root / "cam_params.json").write_text('{"camera": {"w": 32}}'), r"cam_params.json: expected"),
        (lambda root: (root / "traj.txt").write_text(("2 " * 16 + "\n") * 3), r"traj.txt: line 1: the pose is not a rigid"),
    ],
)
def test_bad_replica_recordings_are_named_errors(tmp_path, break_it, message):
    root = write_replica(tiny_frames(3), tmp_path / "room0")
    break_it(root)
    with pytest.raises(DataError, match=message):
        open_scene(root)


def test_a_replica_folder_without_its_trajectory(tmp_path):
    root = write_replica(tiny_frames(3), tmp_path / "room0")
    (root / "traj.txt").unlink()
    with pytest.raises(UserError, match=r"unknown scene layout .* replica: results/, traj.txt"):
        open_scene(root)
    with pytest.raises(DataError, match=r"traj.txt: file missing"):
        open_scene(root, layout="replica")


def _drop_last_line(path: Path) -> None:
    path.write_text("\n".join(path.read_text().splitlines()[:-1]) + "\n")


def test_redwood_image_folder_and_reconstruction_trajectory(tmp_path):
    frames = tiny_frames(3)
    root = write_redwood(frames, tmp_path / "rec", color_dir="image")
    (root / "scene").mkdir()
    (root / "trajectory.log").rename(root / "scene" / "trajectory.log")  # where Open3D's reconstruction writes it
    (root / "camera_intrinsic.json").rename(root / "intrinsic.json")  # as Open3D's Azure Kinect tools name it
    scene = open_scene(root)
    assert scene.layout == "redwood" and scene.frame_names == ["000000", "000001", "000002"]
    np.testing.assert_allclose(scene.poses(), frames.poses, atol=1e-12)


@pytest.mark.parametrize(
    "break_it, message",
    [
        (lambda root: _drop_block(root / "trajectory.log"), r"trajectory.log: 2 poses for 3 images"),
        (lambda root: (root / "trajectory.log").unlink(), r"trajectory.log: file missing .*poses"),
        (lambda root: (root / "camera_intrinsic.json").write_text("{"), r"camera_intrinsic.json: not JSON"),
        (lambda root: (root / "camera_intrinsic.json").write_text('{"width": 32}'), r"camera_intrinsic.json: expected Open3D"),
        (lambda root: (root / "depth" / "000001.png").unlink(), r"depth/000001.png: file missing"),
        (lambda root: (root / "color" / "000001.png").unlink(), r"000001.png: its colour image is missing"),
    ],
)
def test_bad_redwood_recordings_are_named_errors(tmp_path, break_it, message):
    root = write_redwood(tiny_frames(3), tmp_path / "rec")
    break_it(root)
    with pytest.raises(DataError, match=message):
        open_scene(root)


def _drop_block(path: Path) -> None:
    path.write_text("\n".join(path.read_text().splitlines()[:-5]) + "\n")


def test_an_explicit_layout_must_fit_and_two_formats_in_one_folder_are_refused(tmp_path):
    root = write_redwood(tiny_frames(3), tmp_path / "rec")
    with pytest.raises(DataError, match="rgb.txt: file missing"):
        open_scene(root, layout="tum")
    with pytest.raises(UserError, match="layout 'kitti'"):
        open_scene(root, layout="kitti")
    (root / "rgb.txt").write_text("")
    (root / "depth.txt").write_text("")
    with pytest.raises(UserError, match=r"matches several layouts \['tum', 'redwood'\]"):
        open_scene(root)


def test_a_bad_recording_is_one_line_from_the_cli(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(cli, "SUBCOMMANDS", ("info",))
    root = write_tum(tiny_frames(3), tmp_path / "rec")
    (root / "intrinsics.txt").unlink()
    assert cli.main(["info", str(root)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and "no camera intrinsics" in err
