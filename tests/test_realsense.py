"""RealSense SDK recordings (`io.realsense`, the ``realsense`` extra): recordings written by librealsense itself
(its software device and recorder: a ``.db3`` since SDK 2.58, a ``.bag`` before) from a generated room read
back as its ScanNet layout does; depth aligned to colour across a resolution change and an offset; the depth
units; dropped frames; poses from the trajectory beside the recording (`fmfusion track` writes it); the bad
recordings' errors. Skipped, saying why, without pyrealsense2 (it also needs the system's libusb-1.0)."""

from __future__ import annotations

import dataclasses
import logging
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from test_recordings import HEIGHT, NUM_FRAMES, WIDTH, Frames, bed_and_table_room, frames_of

import fmfusion_jax.cli as cli
from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io.realsense import is_realsense_recording, trajectory_path
from fmfusion_jax.io.recordings import write_tum_trajectory
from fmfusion_jax.io.scene import detect_layout, open_scene
from fmfusion_jax.types import CameraIntrinsics

try:
    import pyrealsense2 as rs

    IMPORT_ERROR = ""
except ImportError as error:  # not installed, or installed without the system's libusb-1.0
    rs, IMPORT_ERROR = None, str(error)
requires_pyrealsense2 = pytest.mark.skipif(
    rs is None,
    reason=f'pyrealsense2 cannot be imported ({IMPORT_ERROR}; the realsense extra: pip install -e ".[realsense]"; '
    "it needs libusb-1.0-0)",
)
#: The recordings' first time stamp and their frame period, milliseconds.
T0_MS, PERIOD_MS = 1000.0, 32.0  # ~30 Hz, the stamps exact in the trajectory file's 6 decimals


pytestmark = pytest.mark.usefixtures("cache_home")  # the recording cache in a temporary folder


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    return bed_and_table_room(tmp_path_factory.mktemp("realsense"), "synth0005_00")


@pytest.fixture(scope="module")
def frames(room) -> Frames:
    return frames_of(room)


# --------------------------------------------------------------------------------------------------
# Writing a recording with librealsense's software device and recorder.


def _rs_intrinsics(camera: CameraIntrinsics):
    intrinsics = rs.intrinsics()
    intrinsics.width, intrinsics.height = camera.width, camera.height
    intrinsics.fx, intrinsics.fy, intrinsics.ppx, intrinsics.ppy = camera.fx, camera.fy, camera.cx, camera.cy
    intrinsics.model, intrinsics.coeffs = rs.distortion.none, [0.0] * 5
    return intrinsics


def _add_stream(sensor, stream, uid: int, camera: CameraIntrinsics, fmt, bytes_per_pixel: int):
    video = rs.video_stream()
    video.type, video.index, video.uid, video.fps, video.fmt, video.bpp = stream, 0, uid, 30, fmt, bytes_per_pixel
    video.width, video.height, video.intrinsics = camera.width, camera.height, _rs_intrinsics(camera)
    return sensor.add_video_stream(video)


def write_realsense(
    path: Path,
    colors: np.ndarray,
    color_camera: CameraIntrinsics,
    depths: np.ndarray,
    depth_camera: CameraIntrinsics,
    *,
    depth_units: float = 0.001,
    depth_to_color: np.ndarray | None = None,
    numbers: list[int] | None = None,
    streams: tuple[str, ...] = ("depth", "color"),
) -> Path:
    """Records RGB `colors` `(N, H, W, 3)` and raw depth `depths` `(N, h, w)` uint16 (`depth_units` metres each)
    through librealsense's software device and recorder: a ``.bag`` where the SDK writes one (up to 2.57), else
    `path` with the suffix ``.db3``; `depth_to_color`: a 4x4 (default: the same camera); frame `k` gets the number
    `numbers[k]` (default k) and the time stamp ``T0_MS + number * PERIOD_MS``. Returns the file written."""
    numbers = list(range(len(colors))) if numbers is None else numbers
    depth_to_color = np.eye(4) if depth_to_color is None else depth_to_color
    device = rs.software_device()
    depth_sensor, color_sensor = device.add_sensor("Stereo Module"), device.add_sensor("RGB Camera")
    depth_profile = _add_stream(depth_sensor, rs.stream.depth, 0, depth_camera, rs.format.z16, 2)
    color_profile = _add_stream(color_sensor, rs.stream.color, 1, color_camera, rs.format.rgb8, 3)
    depth_sensor.add_read_only_option(rs.option.depth_units, depth_units)
    extrinsics = rs.extrinsics()
    extrinsics.rotation = [float(x) for x in depth_to_color[:3, :3].T.reshape(-1)]  # column-major
    extrinsics.translation = [float(x) for x in depth_to_color[:3, 3]]
    depth_profile.register_extrinsics_to(color_profile, extrinsics)
    try:
        recorder = rs.recorder(str(path), device)
    except RuntimeError as error:  # SDK 2.58 on: "Output file must have .db3 extension"
        if ".db3" not in str(error):
            raise
        path = path.with_suffix(".db3")
        recorder = rs.recorder(str(path), device)
    chosen = {"depth": (depth_sensor, depth_profile, depths), "color": (color_sensor, color_profile, colors)}
    recorded = [chosen[name] for name in streams]
    for sensor, profile, _ in recorded:
        sensor.open(profile)
        sensor.start(lambda frame: None)
    for k, number in enumerate(numbers):
        for sensor, profile, images in recorded:
            pixels = np.ascontiguousarray(images[k])
            frame = rs.software_video_frame()
            frame.pixels, frame.bpp = pixels, pixels.strides[1]
            frame.stride = pixels.strides[0]
            frame.timestamp, frame.domain, frame.frame_number = (
                T0_MS + number * PERIOD_MS,
                rs.timestamp_domain.hardware_clock,
                number,
            )
            frame.profile = profile.as_video_stream_profile()
            if profile == depth_profile:
                frame.depth_units = depth_units
            sensor.on_video_frame(frame)
    for sensor, _, _ in recorded:
        sensor.stop()
        sensor.close()
    del recorder  # closes the file
    return path


def write_legacy_bag(
    path: Path,
    colors: np.ndarray,
    color_camera: CameraIntrinsics,
    depths: np.ndarray,
    depth_camera: CameraIntrinsics,
    *,
    depth_units: float = 0.001,
    depth_to_color: np.ndarray | None = None,
) -> Path:
    """`write_realsense`'s recording as SDK 2.57 and before wrote it (a ROS 1 bag, file format 4), written with
    rosbags after librealsense's ros_writer: the device's static description first (file version, sensor and
    stream info, camera info, the Depth Units option, each stream's extrinsics to the depth stream), then per
    frame a sensor_msgs/Image (header.seq the frame number, stamp the time stamp, frame_id the format version
    "1", and librealsense's extra trailing float32, the depth units) and its metadata."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    depth_to_color = np.eye(4) if depth_to_color is None else depth_to_color

    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("uint32 fps\nstring encoding\nbool is_recommended", "realsense_msgs/msg/StreamInfo"))
    T = store.types
    messages: list[tuple[int, str, str, bytes]] = []  # (bag time ns, topic, type, serialized)

    def add(t: int, topic: str, msgtype: str, message, trailer: bytes = b"") -> None:
        messages.append((t, topic, msgtype, bytes(store.serialize_ros1(message, msgtype)) + trailer))

    def header(seq: int, seconds: float, frame_id: str = ""):
        stamp = T["builtin_interfaces/msg/Time"](sec=int(seconds), nanosec=int(round((seconds % 1) * 1e9)))
        return T["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame_id)

    streams = {"sensor_0/Depth_0": (depth_camera, "mono16", depths), "sensor_1/Color_0": (color_camera, "rgb8", colors)}
    add(1, "/file_version", "std_msgs/msg/UInt32", T["std_msgs/msg/UInt32"](data=4))
    for sensor, name in (("sensor_0", "Stereo Module"), ("sensor_1", "RGB Camera")):
        add(
            1,
            f"/device_0/{sensor}/info",
            "diagnostic_msgs/msg/KeyValue",
            T["diagnostic_msgs/msg/KeyValue"](key="Name", value=name),
        )
    for stream, (camera, encoding, _) in streams.items():
        add(
            1,
            f"/device_0/{stream}/info",
            "realsense_msgs/msg/StreamInfo",
            T["realsense_msgs/msg/StreamInfo"](fps=30, encoding=encoding, is_recommended=False),
        )
        K = np.array([camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1], np.float64)
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        info = T["sensor_msgs/msg/CameraInfo"](
            header=header(0, 0.0),
            height=camera.height,
            width=camera.width,
            distortion_model="None",
            D=np.zeros(5),
            K=K,
            R=np.zeros(9),
            P=np.zeros(12),
            binning_x=0,
            binning_y=0,
            roi=roi,
        )
        add(1, f"/device_0/{stream}/info/camera_info", "sensor_msgs/msg/CameraInfo", info)
    add(1, "/device_0/sensor_0/option/Depth_Units/value", "std_msgs/msg/Float32", T["std_msgs/msg/Float32"](data=depth_units))
    add(
        1,
        "/device_0/sensor_0/option/Depth_Units/description",
        "std_msgs/msg/String",
        T["std_msgs/msg/String"](data="Depth Units"),
    )
    for stream, extrinsics in (("sensor_0/Depth_0", np.eye(4)), ("sensor_1/Color_0", depth_to_color)):
        qx, qy, qz, qw = Rotation.from_matrix(extrinsics[:3, :3]).as_quat()
        transform = T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=extrinsics[0, 3], y=extrinsics[1, 3], z=extrinsics[2, 3]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        )
        add(1, f"/device_0/{stream}/tf/1", "geometry_msgs/msg/Transform", transform)
    for k in range(len(colors)):
        seconds, bag_time = (T0_MS + k * PERIOD_MS) / 1000, 1_000_000 + int(k * PERIOD_MS * 1e6)
        for stream, (camera, encoding, images) in streams.items():
            pixels = np.ascontiguousarray(images[k])
            image = T["sensor_msgs/msg/Image"](
                header=header(k, seconds, "1"),
                height=camera.height,
                width=camera.width,
                encoding=encoding,
                is_bigendian=0,
                step=pixels.strides[0],
                data=pixels.reshape(-1).view(np.uint8),
            )
            add(bag_time, f"/device_0/{stream}/image/data", "sensor_msgs/msg/Image", image, struct.pack("<f", depth_units))
            for key, value in (("system_time", "0.000000"), ("timestamp_domain", "Hardware Clock")):
                add(
                    bag_time,
                    f"/device_0/{stream}/image/metadata",
                    "diagnostic_msgs/msg/KeyValue",
                    T["diagnostic_msgs/msg/KeyValue"](key=key, value=value),
                )
    with Writer(path) as writer:
        connections: dict[str, object] = {}
        for t, topic, msgtype, raw in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic], t, raw)
    return path


def record_room(frames: Frames, path: Path, **options) -> Path:
    """The room's frames recorded with the depth camera the colour camera (as `rs.align` then leaves them)."""
    return write_realsense(path, frames.colors, frames.intrinsics, frames.depths_mm, frames.intrinsics, **options)


def write_poses(recording: Path, poses: np.ndarray, numbers: list[int] | None = None) -> Path:
    """The trajectory beside the recording at its colour frames' time stamps (seconds)."""
    numbers = list(range(len(poses))) if numbers is None else numbers
    return write_tum_trajectory(trajectory_path(recording), [(T0_MS + n * PERIOD_MS) / 1000 for n in numbers], poses)


# --------------------------------------------------------------------------------------------------


@requires_pyrealsense2
def test_a_recording_reads_back_as_the_scannet_scene(room, frames, tmp_path, cache_home, caplog):
    recording = record_room(frames, tmp_path / "room.bag")
    assert detect_layout(recording) == "realsense" and is_realsense_recording(recording)
    with caplog.at_level(logging.INFO, logger="fmfusion_jax.io"):
        with pytest.raises(DataError, match=f"a RealSense recording holds no camera poses: `fmfusion track {recording}`"):
            open_scene(recording)  # the frames are extracted, then the first pose is asked for
    assert "12 colour and 12 depth frames (aligned to colour) extracted" in caplog.text
    write_poses(recording, frames.poses)
    scene = open_scene(recording, depth_max=10.0)
    reference = open_scene(room, depth_max=10.0)
    assert scene.layout == "realsense" and len(scene) == NUM_FRAMES and not scene.skipped
    assert scene.frame_names == reference.frame_names  # frame-000000 ...: named by the colour frame numbers
    assert scene.depth_scale == 1000.0  # the Depth Units option, 0.001 m
    # the intrinsics are float32 in the recording (the generated camera's 144.397674 is 144.39767 there)
    camera, expected = dataclasses.astuple(scene.intrinsics), dataclasses.astuple(reference.intrinsics)
    np.testing.assert_allclose(camera, expected, rtol=1e-7, atol=0)
    np.testing.assert_allclose(scene.poses(), reference.poses(), atol=1e-6)
    for i in (0, NUM_FRAMES - 1):
        ours, theirs = scene.read_frame(i), reference.read_frame(i)
        np.testing.assert_array_equal(ours.color, theirs.color)
        # aligned onto itself, each depth pixel is that of the same pixel or a neighbour (rs.align maps pixel
        # corners, rounded); the last row and column have no corner inside the image and are left empty
        raw = cv2.imread(str(scene.depth_path(i)), cv2.IMREAD_UNCHANGED).astype(np.int64)
        padded = np.pad(frames.depths_mm[i].astype(np.int64), 1)
        neighbours = np.stack(
            [padded[1 + dy : 1 + dy + HEIGHT, 1 + dx : 1 + dx + WIDTH] for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
        )
        assert np.all((raw == 0) | np.any(neighbours == raw, axis=0))
        assert np.mean(raw[:-1, :-1] > 0) > 0.9 and np.mean(raw == frames.depths_mm[i]) > 0.9
    # extracted once into the cache, never beside the recording; the next open reads the cache
    assert len(list((cache_home / "fmfusion-jax" / "recordings").iterdir())) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["cache", recording.name, trajectory_path(recording).name])
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="fmfusion_jax.io"):
        again = open_scene(recording, stride=3)
    assert "from the cache" in caplog.text and "extracted" not in caplog.text
    np.testing.assert_allclose(again.poses(), reference.poses()[::3], atol=1e-6)


@requires_pyrealsense2
@pytest.mark.parametrize("writer", ["librealsense", "legacy bag"])
def test_depth_is_aligned_to_the_colour_camera(tmp_path, writer):
    """A depth camera of another size, focal length and position (5 cm beside the colour camera, 1 cm below) sees
    a 20 cm square at 1.5 m before a wall at 3 m: aligned, the square's centre lies at the colour pixel its 3D
    point projects to, with its depth; the depth units (0.5 mm) give the scale. Recorded by librealsense (what
    the SDK installed writes: a .db3 since 2.58) and as a ROS 1 .bag as SDK 2.57 and before wrote it (the
    recordings most people have; librealsense 2.58 on still plays them)."""
    color_camera = CameraIntrinsics(120.0, 120.0, 79.5, 59.5, 160, 120)
    depth_camera = CameraIntrinsics(200.0, 200.0, 128.0, 100.0, 256, 200)
    depth_to_color = np.eye(4)
    depth_to_color[:3, 3] = (-0.05, 0.01, 0.0)
    units = 0.0005
    centre = np.array([0.11, -0.05, 1.5])  # the square's centre, depth camera coordinates (metres)
    v, u = np.mgrid[0 : depth_camera.height, 0 : depth_camera.width]
    x, y = (u - depth_camera.cx) / depth_camera.fx, (v - depth_camera.cy) / depth_camera.fy
    inside = (np.abs(x * centre[2] - centre[0]) < 0.1) & (np.abs(y * centre[2] - centre[1]) < 0.1)
    depth = np.where(inside, centre[2], 3.0) / units
    colors = np.full((2, color_camera.height, color_camera.width, 3), 90, np.uint8)
    depths = np.stack([np.round(depth).astype(np.uint16)] * 2)
    if writer == "legacy bag":
        pytest.importorskip("rosbags", reason='the legacy .bag is written with rosbags (the ros extra: pip install -e ".[ros]")')
    write = write_realsense if writer == "librealsense" else write_legacy_bag
    recording = write(
        tmp_path / "offset.bag", colors, color_camera, depths, depth_camera, depth_units=units, depth_to_color=depth_to_color
    )
    assert detect_layout(recording) == "realsense"  # a legacy .bag: by the /device_0/ topics in its index
    write_poses(recording, np.stack([np.eye(4)] * 2))
    scene = open_scene(recording, depth_max=10.0)
    assert scene.depth_scale == 2000.0 and scene.intrinsics == color_camera
    frame = scene.read_frame(0)
    assert frame.depth.shape == (color_camera.height, color_camera.width)
    point = centre + depth_to_color[:3, 3]  # the colour camera's axes are the depth camera's: z is the same
    column = int(round(color_camera.fx * point[0] / point[2] + color_camera.cx))
    row = int(round(color_camera.fy * point[1] / point[2] + color_camera.cy))
    assert frame.depth[row, column] == pytest.approx(1.5, abs=1e-6)
    # the square spans 0.2 m * 120 / 1.5 = 16 colour pixels around that point, the wall lies beyond it
    square = np.argwhere(np.abs(frame.depth - 1.5) < 1e-6)
    np.testing.assert_allclose(square.mean(axis=0), (row, column), atol=1.0)
    assert 14 <= np.ptp(square[:, 1]) <= 18 and frame.depth[row, column + 14] == pytest.approx(3.0, abs=1e-6)
    # without alignment the square would sit at the depth camera's own pixel of its centre, elsewhere
    unaligned = (
        int(round(depth_camera.fy * centre[1] / centre[2] + depth_camera.cy)),
        int(round(depth_camera.fx * centre[0] / centre[2] + depth_camera.cx)),
    )
    assert unaligned != (row, column)


@requires_pyrealsense2
def test_the_same_map_as_the_scannet_layout(room, frames, tmp_path):
    """The Mapper over the recording (with the room's poses beside it) builds the map it builds from the ScanNet
    layout, to what rs.align changes: the same instances of the same classes, the same surface (rs.align moves
    an edge pixel's depth to its neighbour and leaves the last row and column empty)."""
    from fmfusion_jax.io.detections import DetectionFolder
    from fmfusion_jax.mapping.mapper import Mapper
    from fmfusion_jax.simulation.demo_setup import demo_config

    recording = record_room(frames, tmp_path / "room.bag")
    write_poses(recording, frames.poses)
    folder = DetectionFolder(room.parent / "detections", image_shape=(HEIGHT, WIDTH))
    results = []
    for path in (room, recording):
        scene = open_scene(path)
        mapper = Mapper(demo_config(NUM_FRAMES, WIDTH, HEIGHT), bounds=scene.bounds())
        for frame in scene.frames():
            mapper.integrate(frame, folder.get(frame.name))  # the same frame names: the detections apply as they are
        mapper.finalize()
        classes = sorted(instance.class_index for instance in mapper.instances())
        results.append((classes, mapper.extract_point_cloud()[0]))
    (classes, points), (recorded_classes, recorded_points) = results
    assert len(classes) >= 2 and recorded_classes == classes
    assert abs(len(recorded_points) - len(points)) < 0.1 * len(points)  # measured: 4.5 % fewer
    for ours, theirs in ((recorded_points, points), (points, recorded_points)):
        distances, _ = cKDTree(theirs).query(ours)
        assert np.median(distances) < 1e-4 and np.quantile(distances, 0.9) < 0.01  # measured: 5e-6 and 3.4 mm


@requires_pyrealsense2
def test_dropped_frames_are_logged_and_frames_keep_their_numbers(frames, tmp_path, caplog):
    numbers = [0, 1, 2, 5, 6, 7, 8, 9, 10, 11, 12, 20]  # 2 + 7 frames dropped while recording
    recording = record_room(frames, tmp_path / "dropped.bag", numbers=numbers)
    write_poses(recording, frames.poses, numbers)
    with caplog.at_level(logging.INFO, logger="fmfusion_jax.io"):
        scene = open_scene(recording)
    assert scene.frame_names == [f"frame-{n:06d}" for n in numbers]
    assert "9 colour frames dropped while recording (2 gaps in the frame numbers, the first after frame 2)" in caplog.text
    np.testing.assert_allclose(scene.poses(), frames.poses, atol=1e-6)


@requires_pyrealsense2
@pytest.mark.parametrize(
    "streams, error",
    [
        (("color",), "no depth stream \\(z16\\) in the recording; its streams: Color 160x120 rgb8"),
        (("depth",), "no colour stream"),
    ],
)
def test_a_recording_without_a_stream_is_a_data_error(frames, tmp_path, streams, error):
    recording = record_room(frames, tmp_path / "partial.bag", streams=streams)
    with pytest.raises(DataError, match=error) as raised:
        open_scene(recording)
    assert str(recording) in str(raised.value)


@requires_pyrealsense2
@pytest.mark.parametrize("writer", ["librealsense", "legacy bag"])
def test_a_truncated_recording_is_a_data_error(frames, tmp_path, writer):
    """A recording cut short (the recorder killed, a copy interrupted): a .db3's database is malformed, a .bag has
    lost its index (it is still told from other ROS bags by its first chunk's topics) and librealsense refuses it."""
    if writer == "legacy bag":
        pytest.importorskip("rosbags", reason='the legacy .bag is written with rosbags (the ros extra: pip install -e ".[ros]")')
        recording = write_legacy_bag(tmp_path / "room.bag", frames.colors, frames.intrinsics, frames.depths_mm, frames.intrinsics)
    else:
        recording = record_room(frames, tmp_path / "room.bag")
    cut = recording.with_name("cut" + recording.suffix)
    cut.write_bytes(recording.read_bytes()[: recording.stat().st_size // 2])
    assert detect_layout(cut) == "realsense"
    with pytest.raises(DataError, match=f"{cut}: not a (playable|readable) RealSense recording"):
        open_scene(cut)


@requires_pyrealsense2
def test_a_bad_recording_is_one_line_from_the_cli(frames, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(cli, "SUBCOMMANDS", ("info",))
    recording = record_room(frames, tmp_path / "colour_only.bag", streams=("color",))
    assert cli.main(["info", str(recording)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and "no depth stream" in err


def test_a_db3_that_is_no_realsense_recording(tmp_path):
    import sqlite3

    database = tmp_path / "other.db3"
    with sqlite3.connect(database) as db:
        db.execute("CREATE TABLE topics (id INTEGER, name TEXT)")
        db.execute("INSERT INTO topics VALUES (1, '/camera/color/image_raw')")
    assert detect_layout(database) == "realsense"  # the SDK's own recordings are lone .db3 files
    if rs is not None:
        with pytest.raises(DataError, match="not a RealSense recording \\(no /device_0/ topic.*give its folder"):
            open_scene(database)


def test_without_pyrealsense2_the_error_says_how_to_install(tmp_path, monkeypatch):
    import builtins

    recording = tmp_path / "room.db3"
    recording.write_bytes(b"SQLite format 3\x00")
    real_import = builtins.__import__

    def no_pyrealsense2(name, *args, **kwargs):
        if name.startswith("pyrealsense2"):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_pyrealsense2)
    with pytest.raises(
        UserError, match=r'room.db3: a RealSense SDK recording; reading it needs pyrealsense2: pip install -e "\.\[realsense\]"'
    ):
        open_scene(recording)


@requires_pyrealsense2
def test_fmfusion_track_writes_the_trajectory_the_reader_reads(tmp_path, capsys):
    """A RealSense recording holds no poses: `fmfusion track REC` writes REC's trajectory beside it (TUM format, at
    the colour frames' stamps), `fmfusion run REC` then reads it; it is never replaced without --overwrite."""
    from test_track_command import _ate, _walk

    walk, truth = _walk()
    recording = record_room(walk, tmp_path / "walk.bag")
    assert cli.main(["track", str(recording), "--no-progress", "--reference", "frame"]) == 0  # exact depth: frame to frame
    printed = capsys.readouterr().out
    assert f"{len(truth)} frames tracked" in printed and f"trajectory written to {trajectory_path(recording)}" in printed
    scene = open_scene(recording)
    assert scene.layout == "realsense" and len(scene) == len(truth)
    np.testing.assert_allclose(scene.poses()[0], np.eye(4), atol=1e-6)
    assert _ate(scene.poses(), truth) < 0.005  # measured: 0.38 mm (0.35 mm from the TUM copy)
    assert cli.main(["track", str(recording), "--no-progress"]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert cli.main(["track", str(recording), "--no-progress", "--overwrite"]) == 0
