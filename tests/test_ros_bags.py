"""ROS 1 and ROS 2 bags (`io.ros_bags`, the `ros` extra): a generated room in the ScanNet layout written into bags
(raw and compressed colour, 16UC1, 32FC1 and compressedDepth depth, camera info, poses on a PoseStamped topic or
on /tf + /tf_static) reads back as the ScanNet scene does; the extraction cache; the bad bags' errors."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_recordings import Frames, frames_of

from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io.ros_bags import BagTopics
from fmfusion_jax.io.scene import detect_layout, open_scene

rosbags = pytest.importorskip("rosbags", reason='rosbags is not installed (the ros extra: pip install -e ".[ros]")')
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

NUM_FRAMES, WIDTH, HEIGHT = 8, 96, 72
T0, DT = 1700000000.0, 1 / 30
#: base_link -> camera optical frame, a mounting that is not the identity (/tf_static)
MOUNT = np.eye(4)
MOUNT[:3, :3] = Rotation.from_euler("xyz", (-90, 0, -90), degrees=True).as_matrix()
MOUNT[:3, 3] = (0.1, 0.02, 1.2)


pytestmark = pytest.mark.usefixtures("cache_home")  # the recording cache in a temporary folder


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    from fmfusion_jax.simulation.procedural import add_object, empty_room
    from fmfusion_jax.simulation.scannet_writer import write_scannet_scene

    room = add_object(empty_room((4.0, 4.0, 2.6), seed=3), "table", [((2.0, 2.0, 0.375), (1.0, 0.8, 0.75), 0.0)])
    root = tmp_path_factory.mktemp("ros")
    return write_scannet_scene(room, root / "synth0004_00", num_frames=NUM_FRAMES, width=WIDTH, height=HEIGHT, progress=False)


@pytest.fixture(scope="module")
def frames(room) -> Frames:
    return frames_of(room)


def _time(ts, t: float):
    sec = int(t)
    return ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)))


def _header(ts, ros1: bool, t: float, frame_id: str):
    Header = ts.types["std_msgs/msg/Header"]
    return Header(seq=0, stamp=_time(ts, t), frame_id=frame_id) if ros1 else Header(stamp=_time(ts, t), frame_id=frame_id)


def _pose_parts(ts, T: np.ndarray):
    qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
    quaternion = ts.types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)
    return T[:3, 3], quaternion


def _transform(ts, ros1: bool, t: float, parent: str, child: str, T: np.ndarray):
    (x, y, z), q = _pose_parts(ts, T)
    transform = ts.types["geometry_msgs/msg/Transform"](
        translation=ts.types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z), rotation=q
    )
    return ts.types["geometry_msgs/msg/TransformStamped"](
        header=_header(ts, ros1, t, parent), child_frame_id=child, transform=transform
    )


def write_bag(
    frames: Frames,
    path: Path,
    *,
    ros1: bool,
    color: str = "rgb8",
    depth: str = "16UC1",
    poses: str | None = "pose",
    camera_info: bool = True,
    depth_offset: float = 0.004,
) -> Path:
    """A bag of the frames: colour ``rgb8``/``bgr8``/``jpeg``/``png``, depth ``16UC1``/``32FC1``/``compressedDepth``,
    poses ``pose`` (PoseStamped), ``tf`` (/tf world->base_link + /tf_static base_link->camera) or None."""
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in ts.types:  # ROS 1's store lacks it
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    T = ts.types
    camera_frame = "camera_color_optical_frame"
    messages: list[tuple[float, str, str, object]] = []

    def raw_image(stamp: float, pixels: np.ndarray, encoding: str):
        """A sensor_msgs/Image of `pixels` (H, W[, 3])."""
        return T["sensor_msgs/msg/Image"](
            header=_header(ts, ros1, stamp, camera_frame),
            height=HEIGHT,
            width=WIDTH,
            encoding=encoding,
            is_bigendian=0,
            step=WIDTH * pixels.itemsize * (pixels.shape[2] if pixels.ndim == 3 else 1),
            data=np.frombuffer(np.ascontiguousarray(pixels).tobytes(), np.uint8),
        )

    for i in range(len(frames.poses)):
        t = T0 + i * DT
        rgb = frames.colors[i]
        if color in ("rgb8", "bgr8"):
            pixels = rgb if color == "rgb8" else rgb[..., ::-1]
            image = raw_image(t, pixels, color)
            messages.append((t, "/camera/color/image_raw", "sensor_msgs/msg/Image", image))
        else:
            ok, data = cv2.imencode("." + ("jpg" if color == "jpeg" else "png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            image = T["sensor_msgs/msg/CompressedImage"](
                header=_header(ts, ros1, t, camera_frame), format=f"bgr8; {color} compressed bgr8", data=data.reshape(-1)
            )
            messages.append((t, "/camera/color/image_raw/compressed", "sensor_msgs/msg/CompressedImage", image))
        td, mm = t + depth_offset, frames.depths_mm[i]
        if depth == "compressedDepth":
            ok, png = cv2.imencode(".png", mm)
            data = np.concatenate([np.zeros(12, np.uint8), png.reshape(-1)])
            image = T["sensor_msgs/msg/CompressedImage"](
                header=_header(ts, ros1, td, camera_frame), format="16UC1; compressedDepth png", data=data
            )
            messages.append((td, "/camera/aligned_depth_to_color/image_raw/compressedDepth", image.__msgtype__, image))
        else:
            values = mm if depth == "16UC1" else mm.astype(np.float32) / 1000.0
            image = raw_image(td, values, depth)
            messages.append((td, "/camera/aligned_depth_to_color/image_raw", "sensor_msgs/msg/Image", image))
        if camera_info:
            K = frames.intrinsics
            k = np.array([K.fx, 0, K.cx, 0, K.fy, K.cy, 0, 0, 1], np.float64)
            fields = dict(
                header=_header(ts, ros1, td, camera_frame),
                height=HEIGHT,
                width=WIDTH,
                distortion_model="plumb_bob",
                binning_x=0,
                binning_y=0,
                roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
            )
            matrices = {"d": np.zeros(5), "k": k, "r": np.eye(3).reshape(-1), "p": np.zeros(12)}
            fields.update({(name.upper() if ros1 else name): value for name, value in matrices.items()})
            messages.append((td, "/camera/aligned_depth_to_color/camera_info", CAMERA_INFO, T[CAMERA_INFO](**fields)))
        if poses == "pose":
            (x, y, z), q = _pose_parts(ts, frames.poses[i])
            pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=y, z=z), orientation=q)
            stamped = T["geometry_msgs/msg/PoseStamped"](header=_header(ts, ros1, t, "world"), pose=pose)
            messages.append((t, "/camera_pose", "geometry_msgs/msg/PoseStamped", stamped))
        elif poses == "tf":
            base = frames.poses[i] @ np.linalg.inv(MOUNT)
            tf = T["tf2_msgs/msg/TFMessage"](transforms=[_transform(ts, ros1, t, "world", "base_link", base)])
            messages.append((t, "/tf", "tf2_msgs/msg/TFMessage", tf))
            if i == 0:
                static = T["tf2_msgs/msg/TFMessage"](transforms=[_transform(ts, ros1, t, "base_link", camera_frame, MOUNT)])
                messages.append((t, "/tf_static", "tf2_msgs/msg/TFMessage", static))
    messages.sort(key=lambda m: m[0])
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    writer = Writer1(path) if ros1 else Writer2(path, version=9)
    with writer:
        connections = {}
        for _, topic, msgtype, _ in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        for t, topic, msgtype, message in messages:
            writer.write(connections[topic], int(round(t * 1e9)), serialize(message, msgtype))
    return path


CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
CASES = {
    "ros2 rgb8 16UC1 PoseStamped": dict(ros1=False, color="rgb8", depth="16UC1", poses="pose"),
    "ros1 jpeg 32FC1 tf": dict(ros1=True, color="jpeg", depth="32FC1", poses="tf"),
    "ros2 png compressedDepth tf": dict(ros1=False, color="png", depth="compressedDepth", poses="tf"),
    "ros1 bgr8 16UC1 PoseStamped": dict(ros1=True, color="bgr8", depth="16UC1", poses="pose"),
}


@pytest.mark.parametrize("case", CASES)
def test_a_bag_reads_back_as_the_scannet_scene(room, frames, tmp_path, cache_home, case, caplog):
    options = CASES[case]
    bag = write_bag(frames, tmp_path / ("room.bag" if options["ros1"] else "room"), **options)
    assert detect_layout(bag) == "rosbag"
    with caplog.at_level(logging.INFO, logger="fmfusion_jax.io.ros_bags"):
        scene = open_scene(bag, depth_max=10.0)
    reference = open_scene(room, depth_max=10.0)
    assert scene.layout == "rosbag" and len(scene) == NUM_FRAMES and not scene.skipped
    assert scene.frame_names == reference.frame_names  # frame-000000, ...: detections of the ScanNet copy apply
    assert scene.intrinsics == reference.intrinsics and scene.depth_scale == 1000.0
    np.testing.assert_allclose(scene.poses(), reference.poses(), atol=1e-6)
    for i in (0, NUM_FRAMES - 1):
        ours, theirs = scene.read_frame(i), reference.read_frame(i)
        np.testing.assert_allclose(ours.depth, theirs.depth, atol=1e-6, rtol=0)
        if options["color"] == "jpeg":
            assert np.abs(ours.color.astype(int) - theirs.color).mean() < 3
        else:
            np.testing.assert_array_equal(ours.color, theirs.color)
    assert "colour images from /camera/color" in caplog.text and "depth images from /camera/aligned" in caplog.text
    # extracted once into the cache, never beside the bag; the next open reads the cache
    assert len(list((cache_home / "fmfusion-jax" / "recordings").iterdir())) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache", bag.name]
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="fmfusion_jax.io.ros_bags"):
        again = open_scene(bag, stride=3)
    assert "from the cache" in caplog.text and "extracted" not in caplog.text
    np.testing.assert_allclose(again.poses(), reference.poses()[::3], atol=1e-6)


def test_topic_overrides_and_several_candidates(frames, tmp_path, caplog):
    bag = write_bag(frames, tmp_path / "room", ros1=False, poses="tf")
    with pytest.raises(
        UserError, match=r"dataset.color_topic '/nope' is not a topic of the bag; its topics: .*/tf \(tf2_msgs/TFMessage\)"
    ):
        open_scene(bag, topics=BagTopics(color="/nope"))
    with pytest.raises(UserError, match="dataset.depth_topic '/camera/color/image_raw'.*holds no depth images"):
        open_scene(bag, topics=BagTopics(depth="/camera/color/image_raw"))
    frames_listed = r"'no_such_frame' \(tf frames: \['base_link', 'camera_color_optical_frame', 'world'\]\)"
    with pytest.raises(DataError, match="no camera poses.*" + frames_listed):
        open_scene(bag, topics=BagTopics(pose_frame="no_such_frame"))
    # chaining to base_link instead of the camera gives the poses without the mounting
    scene = open_scene(bag, topics=BagTopics(pose_frame="base_link"))
    np.testing.assert_allclose(scene.poses(), frames.poses @ np.linalg.inv(MOUNT), atol=1e-6)
    # raw and compressed colour: raw is chosen and the other named; the override picks the compressed one
    jpeg = write_bag(frames, tmp_path / "jpeg", ros1=False, color="jpeg")
    both = tmp_path / "both"
    topics = ("/camera/color/image_raw", "/camera/aligned_depth_to_color/image_raw", "/camera/aligned_depth_to_color/camera_info")
    _drop_topics(bag, both, (*topics, "/tf", "/tf_static"), also=(jpeg, "/camera/color/image_raw/compressed"))
    with caplog.at_level(logging.INFO, logger="fmfusion_jax.io.ros_bags"):
        raw = open_scene(both)
    assert "colour images from /camera/color/image_raw (Image rgb8); also ['/camera/color/image_raw/compressed']" in caplog.text
    compressed = open_scene(both, topics=BagTopics(color="/camera/color/image_raw/compressed"))
    assert compressed.color_path(0).suffix == ".jpg" and raw.color_path(0).suffix == ".png"
    np.testing.assert_allclose(compressed.poses(), frames.poses, atol=1e-6)


@pytest.mark.parametrize(
    "options, error",
    [
        (dict(depth="none"), r"no depth images topic; the bag.s topics: .*/camera/color/image_raw \(sensor_msgs/Image\)"),
        (dict(camera_info=False), r"no camera info topic; the bag's topics: .*/camera_pose \(geometry_msgs/PoseStamped\)"),
        (dict(poses=None), r"no camera poses: no PoseStamped or Odometry topic.*'camera_color_optical_frame'"),
        (dict(depth_offset=0.5), r"no colour image of /camera/color/image_raw has a depth image .* within 0.02 s"),
    ],
)
def test_a_partial_bag_is_a_clear_error(frames, tmp_path, options, error):
    if options.get("depth") == "none":
        bag = write_bag(
            Frames(frames.colors[:2], frames.depths_mm[:2], frames.poses[:2], frames.intrinsics), tmp_path / "b", ros1=False
        )
        _drop_topics(
            bag,
            tmp_path / "partial",
            keep=("/camera/color/image_raw", "/camera/aligned_depth_to_color/camera_info", "/camera_pose"),
        )
        bag = tmp_path / "partial"
    else:
        bag = write_bag(frames, tmp_path / "partial", ros1=False, **options)
    with pytest.raises(DataError, match=error) as raised:
        open_scene(bag)
    assert str(bag) in str(raised.value)


def _drop_topics(source: Path, target: Path, keep: tuple[str, ...], also: tuple[Path, str] | None = None) -> None:
    """Copies the topics `keep` of the ROS 2 bag `source` into `target` (and the topic `also[1]` of the bag `also[0]`)."""
    from rosbags.highlevel import AnyReader

    with Writer2(target, version=9) as writer:
        for bag, topics in [(source, keep), *([(also[0], (also[1],))] if also else [])]:
            with AnyReader([bag]) as reader:
                connections = {}
                for conn in reader.connections:
                    if conn.topic in topics:
                        connections[conn.id] = writer.add_connection(conn.topic, conn.msgtype, typestore=reader.typestore)
                for conn, t, raw in reader.messages():
                    if conn.id in connections:
                        writer.write(connections[conn.id], t, raw)


def test_without_rosbags_the_error_says_how_to_install(frames, tmp_path, monkeypatch):
    import builtins

    bag = write_bag(frames, tmp_path / "room.bag", ros1=True)
    real_import = builtins.__import__

    def no_rosbags(name, *args, **kwargs):
        if name.startswith("rosbags"):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_rosbags)
    with pytest.raises(UserError, match=r'pip install -e "\.\[ros\]"'):
        open_scene(bag)


def test_a_broken_bag_is_a_data_error(tmp_path):
    bag = tmp_path / "broken.bag"
    bag.write_bytes(b"#ROSBAG V2.0\nnot a bag at all")
    with pytest.raises(DataError, match="broken.bag: not a readable ROS bag"):
        open_scene(bag)


def test_fmfusion_run_on_a_bag_without_detections(frames, tmp_path, capsys):
    """The whole command on a ROS 1 bag, geometry only (no detection source); a forced folder layout is refused."""
    from fmfusion_jax import cli

    bag = write_bag(frames, tmp_path / "room.bag", ros1=True, color="jpeg", depth="32FC1", poses="tf")
    out = tmp_path / "out"
    assert cli.main(["run", str(bag), "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert f"room.bag: {NUM_FRAMES} frames" in printed and "geometry only" in printed
    assert (out / "mesh.ply").is_file() and (out / "map_state.npz").is_file()
    assert cli.main(["run", str(bag), "--out", str(out), "--set", "dataset.layout=scannet"]) == 2
    assert "a ROS bag, but the layout asked for is 'scannet'" in capsys.readouterr().err
