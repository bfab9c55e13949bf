"""RealSense SDK recordings, read through librealsense's own playback (`pyrealsense2`, the ``realsense`` extra:
``pip install -e ".[realsense]"``; imported only when a recording is opened; no camera needed)::

    REC.bag    ROS 1 bag as realsense-viewer's "Record" and rs-record write it up to SDK 2.57
    REC.db3    ROS 2 (SQLite) bag, what the SDK records from 2.58 on

Both hold RealSense's own topics (``/device_0/sensor_0/Depth_0/image/data`` ...; `is_realsense_recording` tells
them from other ROS bags by them): the depth stream in raw units (the depth sensor's "Depth Units" option
says how many metres one is), the colour stream, their intrinsics and the extrinsics between them; no
camera poses.

Depth is aligned to the colour camera by librealsense (`rs.align`: every depth pixel is projected into the
colour image, its value kept; the depth camera's z, as librealsense leaves it), so that a frame is the colour
image, its aligned depth and the colour camera's intrinsics (its lens distortion not modelled; a warning
says when the recording gives non-zero coefficients). A colour frame pairs with the depth frame closest in time within
``dataset.max_time_difference`` (`recordings.pair_streams`). Frames are named ``frame-000123`` by the colour
frame's number; gaps in the numbering (frames the camera or the recorder dropped) are logged.

The recording is played once (not in real time: no frame is dropped) and its frames extracted into the user
cache (`io.recording_cache`: colour PNG, aligned depth 16-bit PNG in the recording's units, manifest.json
with the camera, the depth units, the frame numbers and stamps), which the next open reuses.

Poses: a TUM trajectory beside the recording, `trajectory_path` (``REC.bag.trajectory.txt``: lines
``timestamp tx ty tz qx qy qz qw``, camera-to-world, the time stamps the colour frames' own in seconds), read
as TUM's (`recordings.tum_trajectory_poses`); ``fmfusion track REC.bag`` writes it.
"""

from __future__ import annotations

import collections
import json
import logging
import sqlite3
import struct
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io.recording_cache import MANIFEST, cache_folder, extract_once, file_stats, is_extracted
from fmfusion_jax.io.recordings import Recording, pair_streams, tum_trajectory_poses
from fmfusion_jax.types import CameraIntrinsics

logger = logging.getLogger(__name__)

#: Bump when the cache folder's content changes: older folders are then not reused.
CACHE_FORMAT = 1
#: Appended to the recording's file name: the trajectory the reader reads and `fmfusion track` writes.
TRAJECTORY_SUFFIX = ".trajectory.txt"
#: What marks a ROS 1 bag as RealSense's: its topics (every one under /device_N/) or message package.
_REALSENSE_MARKERS = (b"topic=/device_0/", b"type=realsense_msgs/")
#: Bytes of a ROS 1 bag's index section read to find its topics (connection records are ~200 bytes each), and of
#: its start read instead when the index is lost (a recording cut short; its first chunk, unless compressed).
_INDEX_BYTES = 1 << 20
#: The files of RealSense SDK recordings.
REALSENSE_SUFFIXES = (".bag", ".db3")
#: Depth frames kept before the first colour frame arrives (only the last few can pair with it).
_EARLY_DEPTH_FRAMES = 4
#: Seconds without a new frame after which a playback that has not ended counts as stuck.
_STALL_SECONDS = 60.0
#: Colour formats read, and the OpenCV conversion of each to BGR (None: already BGR).
_COLOR_CONVERSIONS = {
    "rgb8": cv2.COLOR_RGB2BGR,
    "bgr8": None,
    "rgba8": cv2.COLOR_RGBA2BGR,
    "bgra8": cv2.COLOR_BGRA2BGR,
    "yuyv": cv2.COLOR_YUV2BGR_YUYV,
    "uyvy": cv2.COLOR_YUV2BGR_UYVY,
}


def is_realsense_recording(path: Path) -> bool:
    """A RealSense SDK recording: a ``.db3`` file (what the SDK records since 2.58; a ROS 2 bag is a folder), or
    a ``.bag`` file whose topics are RealSense's (found in the bag's index, which is never compressed, or in its
    first chunk when the index is lost)."""
    if not path.is_file():
        return False
    if path.suffix == ".db3":
        return True
    return path.suffix == ".bag" and any(marker in _ros1_index(path) for marker in _REALSENSE_MARKERS)


def trajectory_path(path: Path) -> Path:
    """The trajectory file of the recording `path` (``REC.bag`` -> ``REC.bag.trajectory.txt``)."""
    return path.with_name(path.name + TRAJECTORY_SUFFIX)


def read_realsense(path: Path, max_time_difference: float) -> Recording:
    """The frames of the RealSense recording `path` (a `Recording` of layout ``realsense`` whose files lie in the
    cache folder); `UserError` without pyrealsense2, `DataError` naming the file for a recording that cannot be
    played or lacks a depth or colour stream."""
    folder = _extracted(path)
    manifest = json.loads((folder / MANIFEST).read_text())
    color, depth = manifest["color"], manifest["depth"]
    color_stamps, depth_stamps = np.asarray(color["stamps"]), np.asarray(depth["stamps"])
    pairs = pair_streams(
        color_stamps, depth_stamps, max_time_difference, str(path), " of the colour stream", " of the depth stream"
    )
    for stream in ("color", "depth"):
        _log_dropped(path, stream, manifest[stream]["numbers"])
    numbers = [color["numbers"][i] for i, _ in pairs]
    names = [f"frame-{n:06d}" for n in numbers]
    if len(set(names)) != len(names):  # the camera restarted its counter: name the frames by position
        logger.info("%s: colour frame numbers repeat; frames named by their position instead", path.name)
        names = [f"frame-{k:06d}" for k in range(len(pairs))]
    stamps = color_stamps[[i for i, _ in pairs]]
    trajectory = trajectory_path(path)
    if trajectory.is_file():
        pose = tum_trajectory_poses(trajectory, stamps, max_time_difference)
    else:  # an error once a pose is asked for: the frames can still be listed (`fmfusion track`)

        def pose(i: int) -> tuple[np.ndarray | None, str]:
            raise DataError(
                f"{trajectory}: file missing; a RealSense recording holds no camera poses: `fmfusion track {path}` "
                "estimates them into it (or write one: lines 'timestamp tx ty tz qx qy qz qw', the colour frames' "
                "time stamps in seconds)"
            )

    camera = manifest["camera"]

    def intrinsics() -> CameraIntrinsics:
        fx, fy, cx, cy, width, height = (camera[k] for k in ("fx", "fy", "cx", "cy", "width", "height"))
        if not (fx > 0 and fy > 0 and 0 < cx < width and 0 < cy < height):
            raise DataError(f"{path}: the colour stream's intrinsics are not a pinhole camera of its images: {camera}")
        return CameraIntrinsics(float(fx), float(fy), float(cx), float(cy), int(width), int(height))

    return Recording(
        "realsense",
        names,
        [folder / color["files"][i] for i, _ in pairs],
        [folder / depth["files"][j] for _, j in pairs],
        pose,
        intrinsics,
        manifest["depth_scale"],
        stamps,
    )


def _extracted(path: Path) -> Path:
    """The cache folder of the recording's frames (made now unless an earlier open made it)."""
    folder = cache_folder(["realsense", CACHE_FORMAT, file_stats([path])])
    if is_extracted(folder):
        logger.info("%s: frames read from the cache %s", path.name, folder)
        return folder
    return extract_once(folder, lambda staging: _extract(path, staging))


def _log_dropped(path: Path, stream: str, numbers: list[int]) -> None:
    """Logs the gaps in a stream's frame numbers: frames the camera or the recorder dropped."""
    steps = np.diff(np.asarray(numbers, np.int64))
    gaps = np.flatnonzero(steps > 1)
    if len(gaps):
        first = int(gaps[0])
        logger.info(
            "%s: %d %s frames dropped while recording (%d gaps in the frame numbers, the first after frame %d)",
            path.name,
            int(np.sum(steps[gaps] - 1)),
            "colour" if stream == "color" else stream,
            len(gaps),
            numbers[first],
        )


# --------------------------------------------------------------------------------------------------
# Telling a RealSense bag from another ROS 1 bag without reading it whole.


def _ros1_index(path: Path) -> bytes:
    """The start of a ROS 1 bag's index section (its connection records: topics and message types), found
    through the file header's ``index_pos``; the bag's start when the index is missing (a recording cut short:
    its first chunk's records, unless compressed); b"" when the file is no ROS 1 bag."""
    try:
        with path.open("rb") as file:
            if file.read(13) != b"#ROSBAG V2.0\n":
                return b""
            (length,) = struct.unpack("<I", file.read(4))
            index_pos = _record_fields(file.read(length)).get(b"index_pos", b"")
            position = struct.unpack("<Q", index_pos)[0] if len(index_pos) == 8 else 0
            file.seek(position if 0 < position < path.stat().st_size else 0)
            return file.read(_INDEX_BYTES)
    except (OSError, struct.error):
        return b""


def _record_fields(header: bytes) -> dict[bytes, bytes]:
    """The ``name=value`` fields of a ROS 1 bag record header (each preceded by its length, 4 bytes)."""
    fields, offset = {}, 0
    while offset + 4 <= len(header):
        (length,) = struct.unpack_from("<I", header, offset)
        name, _, value = header[offset + 4 : offset + 4 + length].partition(b"=")
        fields[name] = value
        offset += 4 + length
    return fields


# --------------------------------------------------------------------------------------------------
# Playing the recording once and writing its frames.


def _pyrealsense2(path: Path) -> Any:
    try:
        import pyrealsense2 as rs
    except ImportError as error:
        if "libusb" in str(error):
            raise UserError(f"{path}: pyrealsense2 cannot load libusb-1.0 ({error}): apt-get install libusb-1.0-0") from None
        raise UserError(
            f'{path}: a RealSense SDK recording; reading it needs pyrealsense2: pip install -e ".[realsense]"'
        ) from None
    return rs


def _extract(path: Path, out: Path) -> None:
    """Plays the recording `path` into the folder `out`: color/, depth/ and the manifest (last)."""
    rs = _pyrealsense2(path)
    if path.suffix == ".db3":
        _check_db3_topics(path)
    try:
        device = rs.context().load_device(str(path))
    except RuntimeError as error:
        raise DataError(f"{path}: not a playable RealSense recording ({error})") from None
    playback = device.as_playback()
    playback.set_real_time(False)  # the reader waits for each frame's callback: none is dropped
    depth, color = _choose_streams(rs, path, device)
    depth_units = _depth_units(path, depth[0])
    try:
        depth[1].get_extrinsics_to(color[1])
    except RuntimeError as error:
        raise DataError(f"{path}: no extrinsics from the depth to the colour stream ({error}); depth cannot be aligned") from None
    intrin = color[1].as_video_stream_profile().get_intrinsics()
    if intrin.model != rs.distortion.none and any(abs(c) > 1e-6 for c in intrin.coeffs):
        logger.warning(
            "%s: the colour stream has lens distortion %s %s; frames are used as pinhole", path.name, intrin.model, intrin.coeffs
        )
    (out / "color").mkdir()
    (out / "depth").mkdir()
    writer = _FrameWriter(rs, out, color[1].format().name)
    _play(rs, path, playback, [depth, color], writer)
    if writer.error is not None:
        raise DataError(f"{path}: reading a frame failed ({type(writer.error).__name__}: {writer.error})")
    for stream, frames in (("colour", writer.colors), ("depth", writer.depths)):
        if not frames:
            raise DataError(f"{path}: the {stream} stream holds no frame")
    camera = {"fx": intrin.fx, "fy": intrin.fy, "cx": intrin.ppx, "cy": intrin.ppy}
    camera = {**{k: _decimal(v) for k, v in camera.items()}, "width": intrin.width, "height": intrin.height}
    manifest = {
        "recording": str(path),
        "camera": camera,
        "depth_units": depth_units,
        "depth_scale": 1.0 / depth_units,  # raw units per metre
        "streams": {"depth": _describe(depth[1]), "color": _describe(color[1])},
        **{name: _table(frames) for name, frames in (("color", writer.colors), ("depth", writer.depths))},
    }
    (out / MANIFEST).write_text(json.dumps(manifest))  # last: its presence marks a complete folder
    logger.info(
        "%s: %d colour and %d depth frames (aligned to colour) extracted into %s",
        path.name,
        len(writer.colors),
        len(writer.depths),
        out,
    )


def _check_db3_topics(path: Path) -> None:
    """`DataError` for a .db3 file that is no RealSense recording (a ROS 2 bag's database, say)."""
    try:
        with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
            topics = [row[0] for row in db.execute("SELECT name FROM topics")]
    except sqlite3.Error as error:
        raise DataError(f"{path}: not a readable RealSense recording (its SQLite database: {error}; cut short?)") from None
    if not any(topic.startswith("/device_") for topic in topics):
        raise DataError(
            f"{path}: not a RealSense recording (no /device_0/ topic; topics: {sorted(topics)[:8]}); for a ROS 2 bag, "
            "give its folder (with metadata.yaml)"
        )


def _describe(profile: Any) -> str:
    video = profile.as_video_stream_profile()
    return f"{profile.stream_name()} {video.width()}x{video.height()} {profile.format().name} {profile.fps()} fps"


def _choose_streams(rs: Any, path: Path, device: Any) -> tuple[tuple[Any, Any], tuple[Any, Any]]:
    """`(sensor, profile)` of the recording's depth stream (z16) and of its colour stream."""
    found = [(sensor, profile) for sensor in device.query_sensors() for profile in sensor.get_stream_profiles()]
    streams = ", ".join(_describe(p) for _, p in found if p.is_video_stream_profile()) or "none"
    depth = [(s, p) for s, p in found if p.stream_type() == rs.stream.depth and p.format() == rs.format.z16]
    color = [(s, p) for s, p in found if p.stream_type() == rs.stream.color]
    if not depth:
        raise DataError(f"{path}: no depth stream (z16) in the recording; its streams: {streams}")
    if not color:
        raise DataError(f"{path}: no colour stream in the recording (depth is aligned to it); its streams: {streams}")
    if color[0][1].format().name not in _COLOR_CONVERSIONS:
        raise DataError(
            f"{path}: the colour stream's format {color[0][1].format().name} is not read "
            f"({', '.join(_COLOR_CONVERSIONS)} are); record colour as rgb8"
        )
    return depth[0], color[0]


def _depth_units(path: Path, depth_sensor: Any) -> float:
    """Metres per raw depth unit: the depth sensor's "Depth Units" option as recorded."""
    try:
        units = float(depth_sensor.as_depth_sensor().get_depth_scale())
    except RuntimeError as error:
        raise DataError(f"{path}: the depth sensor's Depth Units option is not in the recording ({error})") from None
    if not (np.isfinite(units) and 0 < units < 1):
        raise DataError(f"{path}: the depth sensor's Depth Units {units} m is not a depth unit")
    return _decimal(units)  # 0.001, whose reciprocal is 1000 units per metre (not 999.99995)


def _decimal(value: float) -> float:
    """The shortest decimal of the float32 `value`: the number the SDK was given (its options and intrinsics are
    float32s: a depth unit 0.001 reads back as 0.0010000000475, a focal length 615.3 as 615.2999878)."""
    return float(str(np.float32(value)))


def _table(frames: list[tuple[int, float, str]]) -> dict[str, list]:
    numbers, stamps, files = zip(*frames)
    return {"numbers": list(numbers), "stamps": list(stamps), "files": list(files)}


def _play(rs: Any, path: Path, playback: Any, streams: list[tuple[Any, Any]], writer: _FrameWriter) -> None:
    """Streams `streams` into `writer` until the playback reaches the file's end."""
    ended = threading.Event()
    playback.set_status_changed_callback(lambda status: ended.set() if status == rs.playback_status.stopped else None)
    by_sensor: dict[int, tuple[Any, list[Any]]] = {}
    for sensor, profile in streams:  # a sensor opens all its streams at once (D405's colour is on the depth sensor)
        by_sensor.setdefault(id(sensor), (sensor, []))[1].append(profile)
    started: list[Any] = []
    try:
        playback.pause()  # reading starts with the first sensor: the others would miss the first frames
        for sensor, profiles in by_sensor.values():
            sensor.open(profiles)
            sensor.start(writer.on_frame)
            started.append(sensor)
        playback.resume()
        while not ended.wait(1.0):
            if time.monotonic() - writer.last_frame > _STALL_SECONDS:
                raise DataError(f"{path}: the playback stopped delivering frames for {_STALL_SECONDS:.0f} s before the end")
    finally:
        for sensor in started:
            for step in (sensor.stop, sensor.close):
                try:
                    step()
                except RuntimeError:  # the playback may have stopped it already at the file's end
                    pass


class _FrameWriter:
    """Writes the frames as the playback hands them over (on its threads, one at a time): colour as PNG, depth
    aligned to the colour camera as 16-bit PNG; keeps `(frame number, stamp s, file)` per stream.

    Aligning needs a frameset of a depth and a colour frame, but not the colour frame of the same instant (only
    its stream's intrinsics and extrinsics count): each depth frame is paired with the first colour frame, so that
    no frame is held waiting for its partner; depth frames before that one wait for it (the last few)."""

    def __init__(self, rs: Any, out: Path, color_format: str) -> None:
        self.rs, self.out, self.conversion = rs, out, _COLOR_CONVERSIONS[color_format]
        self.lock = threading.Lock()
        self.colors: list[tuple[int, float, str]] = []
        self.depths: list[tuple[int, float, str]] = []
        self.error: BaseException | None = None
        self.last_frame = time.monotonic()
        self.reference_color: Any = None
        self.early_depths: collections.deque = collections.deque(maxlen=_EARLY_DEPTH_FRAMES)
        self.align = rs.align(rs.stream.color)
        self.pair: list[Any] = []
        self.framesets = rs.frame_queue(1, keep_frames=True)
        self.compose = rs.processing_block(lambda frame, source: source.frame_ready(source.allocate_composite_frame(self.pair)))
        self.compose.start(self.framesets)

    def on_frame(self, frame: Any) -> None:
        with self.lock:
            self.last_frame = time.monotonic()
            if self.error is not None:
                return
            try:
                if frame.get_profile().stream_type() == self.rs.stream.color:
                    self._write_color(frame)
                elif self.reference_color is None:
                    self.early_depths.append(frame)
                else:
                    self._write_depth(frame)
            except Exception as error:  # noqa: BLE001 - raised on the caller's thread once the playback ends
                self.error = error

    def _write_color(self, frame: Any) -> None:
        video = frame.as_video_frame()
        pixels = np.asanyarray(video.get_data()).reshape(video.get_height(), video.get_width(), -1)
        name = f"color/{len(self.colors):06d}.png"
        cv2.imwrite(str(self.out / name), pixels if self.conversion is None else cv2.cvtColor(pixels, self.conversion))
        self.colors.append((frame.get_frame_number(), frame.get_timestamp() / 1000.0, name))
        if self.reference_color is None:
            self.reference_color = frame
            while self.early_depths:
                self._write_depth(self.early_depths.popleft())

    def _write_depth(self, frame: Any) -> None:
        self.pair = [frame, self.reference_color]
        self.compose.invoke(frame)
        aligned = self.align.process(self.framesets.wait_for_frame().as_frameset()).get_depth_frame()
        name = f"depth/{len(self.depths):06d}.png"
        cv2.imwrite(str(self.out / name), np.asanyarray(aligned.get_data()))
        self.depths.append((frame.get_frame_number(), frame.get_timestamp() / 1000.0, name))
