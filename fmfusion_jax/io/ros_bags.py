"""ROS 1 (``.bag`` file) and ROS 2 (folder of ``metadata.yaml`` + ``.db3`` / ``.mcap``) bags, read through the pure
Python `rosbags` package (the ``ros`` extra: ``pip install -e ".[ros]"``; imported only when a bag is opened).

Topics, chosen by message type (the `BagTopics` overrides, i.e. the ``dataset.*_topic`` knobs, win)::

    colour       sensor_msgs/Image rgb8, bgr8, rgba8, bgra8, or sensor_msgs/CompressedImage jpeg / png
    depth        sensor_msgs/Image 16UC1 (millimetres) or 32FC1 (metres), or CompressedImage "compressedDepth png"
    camera info  sensor_msgs/CameraInfo of the depth camera: K and the image size (no distortion: rectified images)
    poses        /tf (+ /tf_static) chained from the tree's root to the camera's frame_id, else a
                 geometry_msgs/PoseStamped or nav_msgs/Odometry topic (the camera's optical frame in the world)

Depth is assumed registered to colour (e.g. RealSense's aligned_depth_to_color, preferred when present); colour is
resized to the depth size as for the other layouts. A colour image pairs with the depth image closest in header
time within ``dataset.max_time_difference`` (TUM's rule, `recordings.associate`) and its pose is interpolated at
its stamp (`recordings.pose_at`). Frames are named ``frame-000000`` by the colour message's position in its topic.

The bag is read once and its frames extracted into a cache folder (`io.recording_cache`; the key: the bag's
path, size, mtime and the topics), colour as the bag holds it (a compressed image's bytes unchanged, raw ones as
PNG), depth as millimetre PNGs, written atomically and reused by the next open: the `Scene` then reads files as for
every other layout (reader threads, random access) and a bag is decoded once, not on every run.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io.recording_cache import (
    EXTRACTED_DEPTH_SCALE,
    MANIFEST,
    cache_folder,
    extract_once,
    file_stats,
    is_extracted,
    millimetres,
)
from fmfusion_jax.io.recordings import Recording, pair_streams, pose_at, quaternion_to_matrix
from fmfusion_jax.types import CameraIntrinsics, pose_problem

logger = logging.getLogger(__name__)

#: Bump when the cache folder's content changes: older folders are then not reused.
CACHE_FORMAT = 1
IMAGE, COMPRESSED, CAMERA_INFO = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo"
POSE_STAMPED, ODOMETRY, TF = "geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry", "tf2_msgs/msg/TFMessage"
COLOR_ENCODINGS = {"rgb8": cv2.COLOR_RGB2BGR, "bgr8": None, "rgba8": cv2.COLOR_RGBA2BGR, "bgra8": cv2.COLOR_BGRA2BGR}
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")


@dataclasses.dataclass(frozen=True)
class BagTopics:
    """The user's choices of a bag's topics (None: chosen automatically); `pose_topic` may be ``/tf``;
    `pose_frame`: the tf frame whose pose is the camera's (default: the camera info's frame_id)."""

    color: str | None = None
    depth: str | None = None
    camera_info: str | None = None
    pose: str | None = None
    pose_frame: str | None = None


def is_ros2_bag(path: Path) -> bool:
    """A folder holding metadata.yaml and a .db3 or .mcap file."""
    if not (path.is_dir() and (path / "metadata.yaml").is_file()):
        return False
    return any(path.glob("*.db3")) or any(path.glob("*.mcap"))


def is_ros_bag(path: Path) -> bool:
    """A ROS 1 ``.bag`` file or a ROS 2 bag folder."""
    return (path.is_file() and path.suffix == ".bag") or (path.is_dir() and is_ros2_bag(path))


def read_bag(path: Path, max_time_difference: float, topics: BagTopics | None = None) -> Recording:
    """The frames of the bag `path` (a `Recording` of layout ``rosbag`` whose files lie in the cache folder);
    `UserError` without rosbags or for a topic override the bag lacks, `DataError` for a bag that lacks a stream."""
    topics = topics or BagTopics()
    folder = _extracted(path, topics)
    manifest = json.loads((folder / MANIFEST).read_text())
    arrays = np.load(folder / "stamps.npz")
    color_stamps, depth_stamps = arrays["color"], arrays["depth"]
    of_color, of_depth = f" of {manifest['color_topic']}", f" of {manifest['depth_topic']}"
    pairs = pair_streams(color_stamps, depth_stamps, max_time_difference, str(path), of_color, of_depth)
    colors, depths = manifest["color_files"], manifest["depth_files"]
    stamps = color_stamps[[i for i, _ in pairs]]
    chain = [(edge["label"], arrays[f"edge{k}"]) for k, edge in enumerate(manifest["pose_chain"])]

    def pose(i: int) -> tuple[np.ndarray | None, str]:
        T, where = np.eye(4), list[str]()
        for label, table in chain:
            edge: np.ndarray | None
            if len(table) == 1:  # a static transform
                edge, note = _matrix(table[0]), label
            else:
                edge, note = pose_at(table[:, 0], table[:, 1:4], table[:, 4:], float(stamps[i]), max_time_difference, label)
                if edge is None:
                    return None, note
            T, where = T @ edge, [*where, note]
        problem = pose_problem(T)
        if problem is not None:
            raise DataError(f"{path}: {' + '.join(where)}: {problem}")
        return T, " + ".join(where)

    K = manifest["camera"]

    def intrinsics() -> CameraIntrinsics:
        fx, fy, cx, cy, width, height = K["fx"], K["fy"], K["cx"], K["cy"], K["width"], K["height"]
        if not (fx > 0 and fy > 0 and 0 < cx < width and 0 < cy < height):
            raise DataError(f"{path}: {manifest['camera_info_topic']}: not a pinhole camera of the {width}x{height} images: {K}")
        return CameraIntrinsics(float(fx), float(fy), float(cx), float(cy), int(width), int(height))

    return Recording(
        "rosbag",
        [f"frame-{i:06d}" for i, _ in pairs],
        [folder / colors[i] for i, _ in pairs],
        [folder / depths[j] for _, j in pairs],
        pose,
        intrinsics,
        EXTRACTED_DEPTH_SCALE,  # 16UC1 is millimetres; 32FC1 metres are rounded to them
    )


def _matrix(row: np.ndarray) -> np.ndarray:
    """A ``t tx ty tz qx qy qz qw`` row as a 4x4."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = quaternion_to_matrix(row[4:] / np.linalg.norm(row[4:])), row[1:4]
    return T


# --------------------------------------------------------------------------------------------------
# Choosing the topics and extracting the frames (once per bag and choice of topics).


def _rosbags() -> Any:
    try:
        from rosbags import highlevel, typesys
    except ImportError:
        raise UserError('reading ROS bags needs the rosbags package: pip install -e ".[ros]"') from None
    return highlevel, typesys


def _extracted(path: Path, topics: BagTopics) -> Path:
    """The cache folder of the bag's frames (made now unless an earlier open made it)."""
    highlevel, typesys = _rosbags()
    files = sorted(path.iterdir()) if path.is_dir() else [path]
    folder = cache_folder([CACHE_FORMAT, file_stats(files), dataclasses.astuple(topics)])
    if is_extracted(folder):
        logger.info("%s: frames read from the cache %s", path.name, folder)
        return folder
    store = typesys.get_typestore(typesys.Stores.ROS1_NOETIC if path.is_file() else typesys.Stores.ROS2_HUMBLE)
    try:
        reader = highlevel.AnyReader([path], default_typestore=store)
        reader.open()
    except Exception as error:  # rosbags raises its own errors, and OSError, struct or yaml errors on a broken bag
        raise DataError(f"{path}: not a readable ROS bag ({type(error).__name__}: {error})") from None
    with contextlib.closing(reader):
        return extract_once(folder, lambda staging: _extract_into(path, reader, topics, staging))


def _extract_into(path: Path, reader: Any, topics: BagTopics, out: Path) -> None:
    """`_extract`, its failures named by the bag: a message rosbags cannot read, an image cv2 cannot decode."""
    try:
        _extract(path, reader, topics, out)
    except (DataError, UserError):
        raise
    except Exception as error:  # noqa: BLE001 - any decoding failure of a user's bag is a DataError naming it
        raise DataError(f"{path}: reading the bag failed ({type(error).__name__}: {error})") from None


def _topic_table(reader: Any) -> str:
    return ", ".join(f"{c.topic} ({c.msgtype.replace('/msg/', '/')})" for c in sorted(reader.connections, key=lambda c: c.topic))


def _first(reader: Any, connection: Any) -> Any:
    for conn, _, raw in reader.messages(connections=[connection]):
        return reader.deserialize(raw, conn.msgtype)
    return None


def _choose(path: Path, reader: Any, role: str, knob: str, override: str | None, candidates: list[tuple[Any, str]]) -> Any:
    """The connection for `role`: the override (which must exist and be a candidate), else the first candidate
    (they come sorted by preference); logs the choice and the others."""
    if override is not None:
        named = [c for c in reader.connections if c.topic == override]
        if not named:
            raise UserError(f"{path}: {knob} {override!r} is not a topic of the bag; its topics: {_topic_table(reader)}")
        match = [c for c, _ in candidates if c.topic == override]
        if not match:
            raise UserError(
                f"{path}: {knob} {override!r} ({named[0].msgtype}) holds no {role}; candidates: "
                f"{', '.join(c.topic for c, _ in candidates) or 'none'}"
            )
        return match[0]
    if not candidates:
        raise DataError(f"{path}: no {role} topic; the bag's topics: {_topic_table(reader)} ({knob} names one)")
    chosen, what = candidates[0]
    others = [c.topic for c, _ in candidates[1:]]
    logger.info(
        "%s: %s from %s (%s)%s", path.name, role, chosen.topic, what, f"; also {others}, {knob} picks one" if others else ""
    )
    return chosen


def _image_kind(reader: Any, connection: Any) -> tuple[str, str] | None:
    """`("color" | "depth", description)` of an image topic by its first message, None for other images."""
    message = _first(reader, connection)
    if message is None:
        return None
    if connection.msgtype == IMAGE:
        if message.encoding in COLOR_ENCODINGS:
            return "color", f"Image {message.encoding}"
        if message.encoding in DEPTH_ENCODINGS:
            return "depth", f"Image {message.encoding}"
        return None
    fmt = message.format.lower()
    if "compresseddepth" in fmt:
        return "depth", f"CompressedImage {message.format}"
    if "jpeg" in fmt or "jpg" in fmt or "png" in fmt:
        return "color", f"CompressedImage {message.format}"
    return None


def _extract(path: Path, reader: Any, topics: BagTopics, out: Path) -> None:
    images = [c for c in reader.connections if c.msgtype in (IMAGE, COMPRESSED)]
    kinds = {c.topic: _image_kind(reader, c) for c in images}
    by_kind: dict[str, list[tuple[Any, str]]] = {"color": [], "depth": []}
    for c in images:
        kind = kinds[c.topic]
        if kind is not None:
            by_kind[kind[0]].append((c, kind[1]))
    by_kind["color"].sort(key=lambda c: (c[0].msgtype != IMAGE, "depth" in c[0].topic, c[0].topic))
    by_kind["depth"].sort(key=lambda c: ("aligned" not in c[0].topic, c[0].msgtype != IMAGE, c[0].topic))
    color = _choose(path, reader, "colour images", "dataset.color_topic", topics.color, by_kind["color"])
    depth = _choose(path, reader, "depth images", "dataset.depth_topic", topics.depth, by_kind["depth"])
    depth_ns = depth.topic.rsplit("/", 1)[0]
    infos = sorted(
        ((c, "CameraInfo") for c in reader.connections if c.msgtype == CAMERA_INFO),
        key=lambda c: (c[0].topic.rsplit("/", 1)[0] != depth_ns, "depth" not in c[0].topic, c[0].topic),
    )
    info = _choose(path, reader, "camera info", "dataset.camera_info_topic", topics.camera_info, infos)

    (out / "color").mkdir()
    (out / "depth").mkdir()
    color_stamps: list[float] = []
    depth_stamps: list[float] = []
    color_files: list[str] = []
    depth_files: list[str] = []
    camera: dict[str, Any] | None = None
    tf: dict[tuple[str, str], list[list[float]]] = {}
    static: dict[tuple[str, str], list[float]] = {}
    tf_topics = {c.topic for c in reader.connections if c.msgtype == TF and c.topic in ("/tf", "/tf_static")}
    pose_topics = [c for c in reader.connections if c.msgtype in (POSE_STAMPED, ODOMETRY)]
    pose_rows: dict[str, list[list[float]]] = {c.topic: [] for c in pose_topics}
    wanted = [color, depth, info, *pose_topics, *(c for c in reader.connections if c.topic in tf_topics)]
    for conn, log_time, raw in reader.messages(connections=wanted):
        message = reader.deserialize(raw, conn.msgtype)
        if conn.topic in tf_topics:
            for transform in message.transforms:
                edge = (transform.header.frame_id.lstrip("/"), transform.child_frame_id.lstrip("/"))
                row = [_stamp(transform.header, log_time), *_vector(transform.transform.translation)]
                row += _quaternion(transform.transform.rotation)
                if conn.topic == "/tf_static":
                    static[edge] = row
                else:
                    tf.setdefault(edge, []).append(row)
        elif conn.topic in pose_rows:
            pose = message.pose.pose if conn.msgtype == ODOMETRY else message.pose
            pose_rows[conn.topic].append(
                [_stamp(message.header, log_time), *_vector(pose.position), *_quaternion(pose.orientation)]
            )
        elif conn is info and camera is None:
            K = np.asarray(getattr(message, "k", None) if hasattr(message, "k") else message.K, np.float64)
            camera = {"fx": K[0], "fy": K[4], "cx": K[2], "cy": K[5], "width": message.width, "height": message.height}
            camera["frame_id"] = message.header.frame_id.lstrip("/")
        elif conn is color:
            name = f"color/{len(color_files):06d}"
            color_files.append(_write_color(path, conn, message, out / name))
            color_stamps.append(_stamp(message.header, log_time))
        elif conn is depth:
            name = f"depth/{len(depth_files):06d}.png"
            _write_depth(path, conn, message, out / name)
            depth_files.append(name)
            depth_stamps.append(_stamp(message.header, log_time))
    if camera is None or not color_files or not depth_files:
        raise DataError(
            f"{path}: {info.topic if camera is None else color.topic if not color_files else depth.topic}: no message"
        )
    first_depth: Any = cv2.imread(str(out / depth_files[0]), cv2.IMREAD_UNCHANGED)
    if first_depth.shape != (camera["height"], camera["width"]):
        raise DataError(
            f"{path}: the depth images of {depth.topic} are {first_depth.shape[1]}x{first_depth.shape[0]}, but the camera "
            f"info of {info.topic} is for {camera['width']}x{camera['height']} (dataset.camera_info_topic picks another)"
        )
    chain = _pose_chain(path, reader, topics, camera["frame_id"], tf, static, pose_rows)
    arrays: dict[str, Any] = {"color": np.asarray(color_stamps), "depth": np.asarray(depth_stamps)}
    manifest_chain = []
    for k, (label, rows) in enumerate(chain):
        table = np.asarray(rows, np.float64).reshape(-1, 8)
        norms = np.linalg.norm(table[:, 4:], axis=1)
        if not np.all(norms > 1e-6):
            raise DataError(f"{path}: {label}: a zero quaternion (orientation)")
        table[:, 4:] /= norms[:, None]
        arrays[f"edge{k}"] = table[np.argsort(table[:, 0], kind="stable")]
        manifest_chain.append({"label": label})
    np.savez(out / "stamps.npz", **arrays)
    manifest = {
        "bag": str(path),
        "color_topic": color.topic,
        "depth_topic": depth.topic,
        "camera_info_topic": info.topic,
        "camera": {k: (float(v) if k not in ("frame_id",) else v) for k, v in camera.items()},
        "color_files": color_files,
        "depth_files": depth_files,
        "pose_chain": manifest_chain,
    }
    (out / MANIFEST).write_text(json.dumps(manifest))  # last: its presence marks a complete folder
    logger.info("%s: %d colour and %d depth images extracted into %s", path.name, len(color_files), len(depth_files), out)


def _pose_chain(
    path: Path,
    reader: Any,
    topics: BagTopics,
    camera_frame: str,
    tf: dict[tuple[str, str], list[list[float]]],
    static: dict[tuple[str, str], list[float]],
    pose_rows: dict[str, list[list[float]]],
) -> list[tuple[str, list[list[float]]]]:
    """The transforms whose product is the camera's pose, root first: `(label, rows t tx ty tz qx qy qz qw)`;
    one row: a static transform."""
    frame = (topics.pose_frame or camera_frame).lstrip("/")
    parents = {child: (parent, rows) for (parent, child), rows in tf.items()}
    parents.update({child: (parent, [row]) for (parent, child), row in static.items() if child not in parents})
    use_tf = topics.pose == "/tf" or (topics.pose is None and frame in parents)
    if use_tf:
        if frame not in parents:
            frames = sorted({f for edge in [*tf, *static] for f in edge})
            raise DataError(
                f"{path}: the tf frame {frame!r} (the camera's; dataset.pose_frame names another) is not in /tf or "
                f"/tf_static (frames: {frames or 'none'})"
            )
        chain: list[tuple[str, list[list[float]]]] = []
        seen = {frame}
        while frame in parents:
            parent, rows = parents[frame]
            chain.insert(0, (f"/tf {parent}->{frame}", rows))
            if parent in seen:
                raise DataError(f"{path}: /tf holds a loop through {parent!r}")
            seen.add(parent)
            frame = parent
        logger.info("%s: poses from /tf: %s", path.name, " + ".join(label for label, _ in chain))
        return chain
    candidates = sorted(
        ((c, c.msgtype.rsplit("/", 1)[-1]) for c in reader.connections if c.topic in pose_rows),
        key=lambda c: (c[0].msgtype != POSE_STAMPED, c[0].topic),
    )
    if topics.pose is None and not candidates:
        frames = sorted({f for edge in [*tf, *static] for f in edge})
        raise DataError(
            f"{path}: no camera poses: no PoseStamped or Odometry topic, and /tf does not reach the camera's frame "
            f"{frame!r} (tf frames: {frames or 'none'}); the bag's topics: {_topic_table(reader)} (dataset.pose_topic / "
            "dataset.pose_frame choose them)"
        )
    chosen = _choose(path, reader, "camera poses", "dataset.pose_topic", topics.pose, candidates)
    if not pose_rows[chosen.topic]:
        raise DataError(f"{path}: {chosen.topic}: no message")
    return [(chosen.topic, pose_rows[chosen.topic])]


def _stamp(header: Any, log_time: int) -> float:
    """The header's time in seconds, or the bag's time of the message when the header has none."""
    seconds = header.stamp.sec + header.stamp.nanosec * 1e-9
    return seconds if seconds > 0 else log_time * 1e-9


def _vector(v: Any) -> list[float]:
    return [float(v.x), float(v.y), float(v.z)]


def _quaternion(q: Any) -> list[float]:
    return [float(q.x), float(q.y), float(q.z), float(q.w)]


def _pixels(message: Any, dtype: Any, channels: int) -> np.ndarray:
    """An Image message's pixels `(H, W[, C])` (rows padded to `step` bytes, big-endian data swapped)."""
    dt = np.dtype(dtype).newbyteorder(">" if message.is_bigendian else "<")
    row = np.frombuffer(np.asarray(message.data, np.uint8).tobytes(), dt).reshape(message.height, -1)
    pixels = row[:, : message.width * channels].astype(dt.newbyteorder("="))
    return pixels.reshape(message.height, message.width, channels) if channels > 1 else pixels


def _write_color(path: Path, conn: Any, message: Any, stem: Path) -> str:
    """Writes a colour message beside `stem` (its own bytes when compressed, else a PNG); returns the file's name
    relative to the cache folder."""
    if conn.msgtype == COMPRESSED:
        suffix = ".png" if "png" in message.format.lower() else ".jpg"
        stem.with_suffix(suffix).write_bytes(np.asarray(message.data, np.uint8).tobytes())
    else:
        channels = 4 if message.encoding.endswith("a8") else 3
        pixels = _pixels(message, np.uint8, channels)
        code = COLOR_ENCODINGS[message.encoding]
        suffix = ".png"
        cv2.imwrite(str(stem.with_suffix(suffix)), pixels if code is None else cv2.cvtColor(pixels, code))
    return f"{stem.parent.name}/{stem.name}{suffix}"


def _write_depth(path: Path, conn: Any, message: Any, file: Path) -> None:
    """A depth message as a millimetre uint16 PNG (0: no depth)."""
    if conn.msgtype == COMPRESSED:
        data = np.asarray(message.data, np.uint8).tobytes()
        png = data if data[:8] == b"\x89PNG\r\n\x1a\n" else data[12:]  # compressedDepth's 12-byte header
        if "png" not in message.format.lower() or png[:8] != b"\x89PNG\r\n\x1a\n":
            raise DataError(f"{path}: {conn.topic}: compressed depth {message.format!r} is not supported (only PNG)")
        raw: Any = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
        if message.format.startswith("32FC1"):  # inverse depth quantised: depth = a / (v - b)
            a, b = np.frombuffer(data[4:12], "<f4")
            metres = np.where(raw > 0, a / np.maximum(raw.astype(np.float32) - b, 1e-6), 0)
            raw = millimetres(metres)
    elif message.encoding == "32FC1":
        raw = millimetres(_pixels(message, np.float32, 1))
    else:
        raw = _pixels(message, np.uint16, 1)
    cv2.imwrite(str(file), raw.astype(np.uint16))
