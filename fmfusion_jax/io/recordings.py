"""Readers of the recording formats beside ScanNet and SceneNN: TUM RGB-D, Replica (NICE-SLAM) and Open3D /
Redwood (ROS bags are read by `io.ros_bags`, Record3D ``.r3d`` exports by `io.record3d`, both into a `Recording`
too). `io.scene.open_scene` detects them (`recording_layouts`) and reads them through `read_recording`;
docs/your-own-data.md says how to make each. Every reader returns a `Recording`: the frames of the whole
sequence in order (names, colour and depth paths, a pose per frame or the reason it has none), the depth
camera and the format's own depth scale.

TUM RGB-D::

    REC/rgb.txt, REC/depth.txt     lines `timestamp path` (path relative to REC), `#` comments
    REC/groundtruth.txt            lines `timestamp tx ty tz qx qy qz qw` (camera-to-world), `#` comments
    REC/rgb/..., REC/depth/...     16-bit depth PNGs, 5000 units per metre
    REC/camera_intrinsic.json or REC/intrinsics.txt   the camera (TUM ships none; see `tum_intrinsics`)

  A colour image is paired with the depth image closest in time within `max_time_difference` seconds (the
  greedy rule of TUM's associate.py); its pose is interpolated at the colour image's time stamp (translation
  linearly, rotation by slerp). Colour images without a depth image within the tolerance are left out (one
  log line says how many); frames outside the trajectory's time span, or in a gap of it (no pose within the
  tolerance and the poses around more than `MAX_POSE_GAP` apart), are skipped with the reason.
  A frame is named by its colour image's stem (``1305031102.175304``).

Replica as NICE-SLAM ships it::

    REC/results/frame000000.jpg, REC/results/depth000000.png   (depth: 6553.5 units per metre)
    REC/traj.txt                   one row-major 4x4 camera-to-world per line (16 numbers), one line per frame
    REC/cam_params.json or REC/../cam_params.json   {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}
                                   (optional: without it, Replica's 1200x680, fx = fy = 600, cx 599.5, cy 339.5)

Open3D reconstruction system / Redwood (Open3D's realsense_recorder.py, azure_kinect_recorder.py)::

    REC/color/000000.jpg (or REC/image/...), REC/depth/000000.png   (depth: 1000 units per metre)
    REC/camera_intrinsic.json (or intrinsic.json)   {"width", "height", "intrinsic_matrix": 9 numbers, column-major}
    REC/trajectory.log (or REC/scene/trajectory.log, the reconstruction system's output)   Redwood format: per
                                   frame a line `i j n` and 4 rows of a 4x4 camera-to-world, in frame order

  Colour and depth images are paired by file stem (``000000``), frames sorted by the numbers in the stem.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import re
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np

from fmfusion_jax.errors import DataError
from fmfusion_jax.io.image_file import read_image
from fmfusion_jax.types import CameraIntrinsics, pose_problem

logger = logging.getLogger(__name__)

#: Raw depth units per metre of each format (`Scene.depth_scale` unless the user sets `dataset.depth_scale`).
TUM_DEPTH_SCALE = 5000.0
REDWOOD_DEPTH_SCALE = 1000.0
#: Replica's camera as NICE-SLAM's configs/Replica/replica.yaml and the download's cam_params.json give it.
REPLICA_CAMERA = {"w": 1200, "h": 680, "fx": 600.0, "fy": 600.0, "cx": 599.5, "cy": 339.5, "scale": 6553.5}
#: Seconds between a colour image and its depth image (and pose) that still pair: TUM associate.py's default.
MAX_TIME_DIFFERENCE = 0.02
#: Seconds between two poses of a TUM trajectory that a frame's pose is still interpolated across when neither
#: is within `MAX_TIME_DIFFERENCE` of it (a trajectory at 10 Hz or faster; a longer gap is lost tracking).
MAX_POSE_GAP = 0.1
#: TUM's published calibration of the colour camera (the depth images are registered to it), used when the
#: recording's folder name says which Kinect took it (``rgbd_dataset_freiburg1_xyz``) and it holds no camera file.
TUM_FREIBURG_CAMERAS = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
#: The files (a trailing / for a folder) whose presence marks each format.
RECORDING_MARKERS = {
    "tum": ("rgb.txt", "depth.txt"),
    "replica": ("results/", "traj.txt"),
    "redwood": ("camera_intrinsic.json", "color/", "depth/"),
}
_OPEN3D_INTRINSICS = ("camera_intrinsic.json", "intrinsic.json")

#: frame i -> (its 4x4 camera-to-world, where it was read) or (None, why the frame has no pose).
PoseSource = Callable[[int], tuple["np.ndarray | None", str]]


@dataclasses.dataclass(frozen=True)
class Recording:
    """The frames of a recording folder in sequence order, as a format's reader finds them.

    Attributes:
      layout: the format's name (`Scene.layout`).
      names, color_paths, depth_paths: per frame, its name (detections are keyed by it) and image files.
      pose: `PoseSource` (a non-finite pose is returned as it is; the caller skips the frame).
      intrinsics: reads the depth camera (called once the poses have been read).
      depth_scale: the format's raw depth units per metre.
      stamps: per frame, its time stamp in seconds where the format has them (TUM), else None.
    """

    layout: str
    names: list[str]
    color_paths: list[Path]
    depth_paths: list[Path]
    pose: PoseSource
    intrinsics: Callable[[], CameraIntrinsics]
    depth_scale: float
    stamps: np.ndarray | None = None


def recording_layouts(root: Path) -> list[str]:
    """The recording formats whose marker files `root` holds (`RECORDING_MARKERS`; Redwood's intrinsics may
    also be named intrinsic.json, as Open3D's Azure Kinect tools write it, and its colour folder image/)."""
    found = []
    for name, markers in RECORDING_MARKERS.items():
        present = [(root / m).is_dir() if m.endswith("/") else (root / m).is_file() for m in markers]
        if name == "redwood":
            present[0] = any((root / file).is_file() for file in _OPEN3D_INTRINSICS)
            present[1] = present[1] or (root / "image").is_dir()
        if all(present):
            found.append(name)
    return found


def read_recording(layout: str, root: Path, stride: int, max_time_difference: float = MAX_TIME_DIFFERENCE) -> Recording:
    """Lists the frames of the recording `root` in the format `layout` (a key of `RECORDING_MARKERS`) and checks
    the files of every `stride`-th frame exist; `DataError` naming the file for anything missing or malformed."""
    if layout == "tum":
        return _read_tum(root, stride, max_time_difference)
    if layout == "replica":
        return _read_replica(root, stride)
    return _read_redwood(root, stride)


def read_trajectory_log(path: Path) -> np.ndarray:
    """Reads a Redwood/SceneNN `trajectory.log`: blocks of one header line and 4 matrix rows.

    Returns `(N, 4, 4)` float64 camera-to-world poses in file order.
    """
    if not path.is_file():
        raise DataError(f"{path}: not a regular file")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise DataError(f"{path}: unreadable ({error})") from None
    lines = [line.split() for line in text.splitlines() if line.strip()]
    if len(lines) % 5:
        raise DataError(f"{path}: {len(lines)} non-empty lines, expected blocks of 5 (header + 4x4 matrix)")
    try:
        rows = [[float(x) for x in line] for k, line in enumerate(lines) if k % 5]
    except ValueError as error:
        raise DataError(f"{path}: {error}") from None
    if any(len(row) != 4 for row in rows):
        raise DataError(f"{path}: every matrix row must hold 4 numbers")
    return np.asarray(rows, np.float64).reshape(-1, 4, 4)


def write_trajectory_log(path: Path, poses: list[np.ndarray]) -> Path:
    """Writes camera-to-world poses as a Redwood `trajectory.log` (`read_trajectory_log` reads it back)."""
    blocks = [
        f"{i} {i} {len(poses)}\n" + "\n".join(" ".join(repr(float(x)) for x in row) for row in np.asarray(pose, np.float64))
        for i, pose in enumerate(poses)
    ]
    path.write_text("\n".join(blocks) + "\n")
    return path


def check_files_exist(paths: list[Path]) -> None:
    """`DataError` naming the first missing file (one listing per folder, not one stat per file)."""
    listings: dict[Path, set[str]] = {}
    for path in paths:
        if path.parent not in listings:
            listings[path.parent] = set(p.name for p in path.parent.iterdir()) if path.parent.is_dir() else set()
        if path.name not in listings[path.parent]:
            missing = sum(1 for p in paths if p.name not in listings.get(p.parent, set()))
            raise DataError(f"{path}: file missing ({missing} of {len(paths)} such files missing)")


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """`(4,)` unit quaternion ``(qx, qy, qz, qw)`` (TUM's order) -> `(3, 3)` rotation."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """`(qx, qy, qz, qw)` (qw >= 0) of a `(3, 3)` rotation matrix."""
    m = np.asarray(R, np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s])
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = np.zeros(4)
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
        q[3] = (m[k, j] - m[j, k]) / s
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def write_tum_trajectory(path: str | Path, timestamps: Sequence[float], poses: Sequence[np.ndarray]) -> Path:
    """Writes `T_world_camera` poses as a TUM RGB-D trajectory: one `timestamp tx ty tz qx qy qz qw` line a frame."""
    if len(timestamps) != len(poses):
        raise ValueError(f"{len(timestamps)} timestamps for {len(poses)} poses")
    lines = ["# timestamp tx ty tz qx qy qz qw (T_world_camera, estimated by tracking)"]
    for stamp, T in zip(timestamps, poses):
        T = np.asarray(T, np.float64)
        values = [*T[:3, 3], *rotation_to_quaternion(T[:3, :3])]
        lines.append(f"{float(stamp):.6f} " + " ".join(f"{v:.7f}" for v in values))
    path = Path(path)
    path.write_text("\n".join(lines) + "\n")
    return path


def slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    """The unit quaternion a share `s` in [0, 1] of the shorter arc from `q0` to `q1`."""
    dot = float(np.dot(q0, q1))
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly the same rotation: a normalized lerp is exact to float precision
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1 - s) * theta) * q0 + np.sin(s * theta) * q1) / np.sin(theta)


def interpolate_pose(stamps: np.ndarray, translations: np.ndarray, quaternions: np.ndarray, t: float) -> np.ndarray:
    """The 4x4 camera-to-world at time `t` within `[stamps[0], stamps[-1]]` (sorted stamps, unit quaternions):
    translation linear, rotation slerp between the two poses around `t`."""
    k = int(np.clip(np.searchsorted(stamps, t, side="right") - 1, 0, max(len(stamps) - 2, 0)))
    pose = np.eye(4)
    if len(stamps) == 1 or t <= stamps[k]:
        pose[:3, :3], pose[:3, 3] = quaternion_to_matrix(quaternions[k]), translations[k]
        return pose
    s = min((t - stamps[k]) / (stamps[k + 1] - stamps[k]), 1.0)
    pose[:3, :3] = quaternion_to_matrix(slerp(quaternions[k], quaternions[k + 1], s))
    pose[:3, 3] = (1 - s) * translations[k] + s * translations[k + 1]
    return pose


def associate(first: np.ndarray, second: np.ndarray, max_difference: float) -> list[tuple[int, int]]:
    """TUM associate.py's pairing of two stamp lists: candidate pairs closer than `max_difference`, taken
    greedily closest first, each stamp used once; returns `(i, j)` index pairs sorted by `i`."""
    order = np.argsort(second, kind="stable")
    ordered = second[order]
    candidates = []
    for i, t in enumerate(first):
        lo, hi = np.searchsorted(ordered, t - max_difference, "left"), np.searchsorted(ordered, t + max_difference, "right")
        candidates += [(abs(float(t - ordered[k])), i, int(order[k])) for k in range(lo, hi)]
    candidates.sort()
    used_first: set[int] = set()
    used_second: set[int] = set()
    pairs = []
    for difference, i, j in candidates:
        if difference < max_difference and i not in used_first and j not in used_second:
            used_first.add(i)
            used_second.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def pair_streams(
    color_stamps: np.ndarray,
    depth_stamps: np.ndarray,
    max_time_difference: float,
    where: str,
    color_stream: str = "",
    depth_stream: str = "",
) -> list[tuple[int, int]]:
    """`associate`'s `(colour, depth)` index pairs; a DataError naming `where` (and the streams, e.g. a bag's topics)
    when no colour image has a depth image within the tolerance, and a log line saying how many colour images are
    left out without one."""
    pairs = associate(color_stamps, depth_stamps, max_time_difference)
    if not pairs:
        raise DataError(
            f"{where}: no colour image{color_stream} has a depth image{depth_stream} within {max_time_difference:g} s "
            f"(colour stamps {color_stamps.min():.3f}..{color_stamps.max():.3f}, depth {depth_stamps.min():.3f}.."
            f"{depth_stamps.max():.3f}; unsynchronised streams? dataset.max_time_difference sets the tolerance)"
        )
    if len(pairs) < len(color_stamps):
        logger.info(
            "%s: %d of %d colour images have no depth image within %g s; left out",
            where,
            len(color_stamps) - len(pairs),
            len(color_stamps),
            max_time_difference,
        )
    return pairs


def read_open3d_intrinsics(path: Path) -> CameraIntrinsics:
    """Open3D's PinholeCameraIntrinsic JSON: ``{"width", "height", "intrinsic_matrix": [9 numbers, column-major]}``."""
    data = _read_json(path)
    try:
        width, height = int(data["width"]), int(data["height"])
        K = np.asarray(data["intrinsic_matrix"], np.float64).reshape(3, 3).T
    except (KeyError, TypeError, ValueError) as error:
        raise DataError(
            f"{path}: expected Open3D's camera intrinsic JSON "
            f'{{"width": W, "height": H, "intrinsic_matrix": [fx, 0, 0, 0, fy, 0, cx, cy, 1]}} ({error!r})'
        ) from None
    return _intrinsics(path, K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height)


def tum_intrinsics(root: Path, first_depth: Path) -> CameraIntrinsics:
    """A TUM recording's camera: its camera_intrinsic.json (Open3D's format), else its intrinsics.txt (the four
    numbers ``fx fy cx cy`` in pixels of the depth image, `#` comments; the size is the first depth image's),
    else TUM's calibration of the Kinect the folder's name names (freiburg1/2/3), else a `DataError`."""
    json_path, text_path = root / "camera_intrinsic.json", root / "intrinsics.txt"
    if json_path.is_file():
        return read_open3d_intrinsics(json_path)
    height, width = read_image(first_depth, cv2.IMREAD_UNCHANGED).shape[:2]
    if text_path.is_file():
        rows = _read_rows(text_path)
        values = [value for _, row in rows for value in row]
        if len(values) != 4:
            raise DataError(f"{text_path}: expected the four numbers 'fx fy cx cy', found {len(values)}")
        fx, fy, cx, cy = _floats(text_path, rows[0][0], values)
        return _intrinsics(text_path, fx, fy, cx, cy, width, height)
    for kinect, (fx, fy, cx, cy) in TUM_FREIBURG_CAMERAS.items():
        if kinect in root.name:
            logger.info("%s: no camera file; TUM's %s calibration (fx %g fy %g cx %g cy %g)", root.name, kinect, fx, fy, cx, cy)
            return _intrinsics(root, fx, fy, cx, cy, width, height)
    raise DataError(
        f"{root}: no camera intrinsics (TUM recordings ship none): write {text_path.name} holding 'fx fy cx cy' "
        f"of the depth camera in pixels, or an Open3D {json_path.name} (docs/your-own-data.md)"
    )


def _read_tum(root: Path, stride: int, max_time_difference: float) -> Recording:
    rgb_path, depth_path = root / "rgb.txt", root / "depth.txt"
    rgb_stamps, rgb_files = _read_tum_list(rgb_path)
    depth_stamps, depth_files = _read_tum_list(depth_path)
    pairs = pair_streams(rgb_stamps, depth_stamps, max_time_difference, f"{rgb_path}, {depth_path}")
    color_paths = [root / rgb_files[i] for i, _ in pairs]
    depth_paths = [root / depth_files[j] for _, j in pairs]
    names = [path.stem for path in color_paths]
    if len(set(names)) != len(names):
        raise DataError(f"{rgb_path}: several colour images share a file stem; frames are named by it")
    picked = range(0, len(pairs), stride)
    check_files_exist([color_paths[i] for i in picked])
    check_files_exist([depth_paths[i] for i in picked])
    stamps = rgb_stamps[[i for i, _ in pairs]]
    pose = _tum_pose_source(root, stamps, max_time_difference)
    camera = lambda: tum_intrinsics(root, depth_paths[0])  # noqa: E731
    return Recording("tum", names, color_paths, depth_paths, pose, camera, TUM_DEPTH_SCALE, stamps)


def _tum_pose_source(root: Path, frame_stamps: np.ndarray, max_time_difference: float) -> PoseSource:
    """Poses interpolated at the frames' stamps from groundtruth.txt (else trajectory.txt, e.g. a SLAM
    system's output in TUM's format)."""
    path = next((root / name for name in ("groundtruth.txt", "trajectory.txt") if (root / name).is_file()), None)
    if path is None:  # an error once a pose is asked for: the frames can still be listed (`fmfusion track`)

        def missing(i: int) -> tuple[np.ndarray | None, str]:
            raise DataError(
                f"{root / 'groundtruth.txt'}: file missing; a TUM recording needs its camera poses (groundtruth.txt "
                "or trajectory.txt, lines 'timestamp tx ty tz qx qy qz qw'); `fmfusion track "
                f"{root}` estimates them into {root / 'trajectory.txt'}"
            )

        return missing
    return tum_trajectory_poses(path, frame_stamps, max_time_difference)


def tum_trajectory_poses(path: Path, frame_stamps: np.ndarray, max_time_difference: float) -> PoseSource:
    """The poses of the frames stamped `frame_stamps` `(N,)` (seconds), interpolated (`pose_at`) from the TUM
    trajectory file `path` (lines 'timestamp tx ty tz qx qy qz qw'); `DataError` for a malformed file or one
    whose time span holds no frame."""
    rows = _read_rows(path)
    table = np.array([_floats(path, line, row, 8) for line, row in rows]).reshape(-1, 8)
    if len(table) == 0:
        raise DataError(f"{path}: no pose (lines 'timestamp tx ty tz qx qy qz qw')")
    norms = np.linalg.norm(table[:, 4:], axis=1)
    if not np.all(norms > 1e-6):
        bad = int(np.argmin(norms > 1e-6))
        raise DataError(f"{path}: line {rows[bad][0]}: the quaternion (qx qy qz qw) is zero")
    table = table[np.argsort(table[:, 0], kind="stable")]
    stamps, translations, quaternions = table[:, 0], table[:, 1:4], table[:, 4:] / norms[:, None]
    first, last = stamps[0], stamps[-1]
    inside = (frame_stamps >= first) & (frame_stamps <= last)
    if not inside.any():
        raise DataError(
            f"{path}: the trajectory spans {first:.3f}..{last:.3f} s, but no frame lies within it "
            f"(frames {frame_stamps.min():.3f}..{frame_stamps.max():.3f} s)"
        )
    return lambda i: pose_at(stamps, translations, quaternions, float(frame_stamps[i]), max_time_difference, path.name)


def pose_at(
    stamps: np.ndarray, translations: np.ndarray, quaternions: np.ndarray, t: float, max_time_difference: float, label: str
) -> tuple[np.ndarray | None, str]:
    """The pose of a trajectory (sorted `stamps`, unit `quaternions`) at time `t`, interpolated (`interpolate_pose`),
    and where it came from; or None and why not: `t` outside the trajectory's span, or in a gap of it (no pose
    within `max_time_difference` and the two around more than `MAX_POSE_GAP` apart). `label` names the trajectory."""
    first, last = stamps[0], stamps[-1]
    if not first <= t <= last:
        return None, f"time stamp {t:.6f} outside the time span of {label} ({first:.3f}..{last:.3f} s)"
    around = stamps[max(np.searchsorted(stamps, t) - 1, 0) :][:2]
    if np.min(np.abs(around - t)) > max_time_difference and np.ptp(around) > MAX_POSE_GAP:
        return None, f"time stamp {t:.6f} in a {np.ptp(around):.3f} s gap of {label}"
    return interpolate_pose(stamps, translations, quaternions, t), f"{label} at {t:.6f}"


def _read_replica(root: Path, stride: int) -> Recording:
    results = root / "results"
    colors = _numbered(results, r"^frame(\d+)$", (".jpg", ".png"))
    depths = _numbered(results, r"^depth(\d+)$", (".png",))
    if not colors:
        raise DataError(f"{results}: no colour image named frame000000.jpg (or .png)")
    orphans = sorted(set(depths) - set(colors))
    if orphans:
        raise DataError(f"{depths[orphans[0]]}: its colour image is missing ({len(orphans)} depth images have none)")
    numbers = sorted(colors)
    missing = [n for n in numbers if n not in depths]
    if missing:
        example = results / f"depth{colors[missing[0]].stem.removeprefix('frame')}.png"
        raise DataError(f"{example}: file missing ({len(missing)} of {len(numbers)} depth images missing)")
    traj_path = root / "traj.txt"
    rows = _read_rows(traj_path)
    poses = np.array([_floats(traj_path, line, row, 16) for line, row in rows]).reshape(-1, 4, 4)
    if len(poses) != len(numbers):
        raise DataError(
            f"{traj_path}: {len(poses)} poses for {len(numbers)} frames in {results}; one line (16 numbers, a "
            "row-major 4x4 camera-to-world) per frame is needed"
        )
    camera, camera_path = _replica_camera(root)

    def pose(i: int) -> tuple[np.ndarray | None, str]:
        where = f"{traj_path.name} line {rows[i][0]}"
        return _checked(poses[i], traj_path, where), where

    def intrinsics() -> CameraIntrinsics:
        c = camera
        return _intrinsics(camera_path, c["fx"], c["fy"], c["cx"], c["cy"], int(c["w"]), int(c["h"]))

    names = [colors[n].stem for n in numbers]
    return Recording(
        "replica", names, [colors[n] for n in numbers], [depths[n] for n in numbers], pose, intrinsics, camera["scale"]
    )


def _replica_camera(root: Path) -> tuple[dict[str, float], Path]:
    """The camera of cam_params.json in the scene folder, else in its parent (the Replica download's root),
    else Replica's standard one."""
    for path in (root / "cam_params.json", root.parent / "cam_params.json"):
        if path.is_file():
            data = _read_json(path)
            camera = data.get("camera") if isinstance(data, dict) else None
            keys = tuple(REPLICA_CAMERA)
            if not isinstance(camera, dict) or not all(isinstance(camera.get(k), int | float) for k in keys):
                raise DataError(f'{path}: expected {{"camera": {{{", ".join(repr(k) + ": number" for k in keys)}}}}}')
            return {k: float(camera[k]) for k in keys}, path
    return {k: float(v) for k, v in REPLICA_CAMERA.items()}, root / "cam_params.json (absent: Replica's camera)"


def _read_redwood(root: Path, stride: int) -> Recording:
    color_dir = next((root / name for name in ("color", "image") if (root / name).is_dir()), None)
    if color_dir is None:
        raise DataError(f"{root}: neither a color/ nor an image/ folder (Open3D / Redwood recording)")
    depth_dir = root / "depth"
    colors = _by_stem(color_dir, (".jpg", ".png"))
    depths = _by_stem(depth_dir, (".png",))
    if not colors:
        raise DataError(f"{color_dir}: no colour image (.jpg or .png)")
    orphans = sorted(set(depths) - set(colors), key=_natural)
    if orphans:
        raise DataError(f"{depths[orphans[0]]}: its colour image is missing ({len(orphans)} depth images have none)")
    stems = sorted(colors, key=_natural)
    missing = [stem for stem in stems if stem not in depths]
    if missing:
        example = depth_dir / (missing[0] + ".png")
        raise DataError(f"{example}: file missing ({len(missing)} of {len(stems)} depth images missing)")
    log_path = next((p for p in (root / "trajectory.log", root / "scene" / "trajectory.log") if p.is_file()), None)
    json_path = next((root / name for name in _OPEN3D_INTRINSICS if (root / name).is_file()), root / _OPEN3D_INTRINSICS[0])
    if log_path is None:  # an error once a pose is asked for: the frames can still be listed (`fmfusion track`)

        def pose(i: int) -> tuple[np.ndarray | None, str]:
            raise DataError(
                f"{root / 'trajectory.log'}: file missing (nor scene/trajectory.log); the recording needs its camera "
                f"poses (Open3D's reconstruction system writes them); `fmfusion track {root}` estimates them"
            )

    else:
        trajectory = read_trajectory_log(log_path)
        if len(trajectory) != len(stems):
            raise DataError(f"{log_path}: {len(trajectory)} poses for {len(stems)} images; cannot pair them")

        def pose(i: int) -> tuple[np.ndarray | None, str]:
            where = f"{log_path.name} block {i}"
            return _checked(trajectory[i], log_path, where), where

    return Recording(
        "redwood",
        stems,
        [colors[s] for s in stems],
        [depths[s] for s in stems],
        pose,
        lambda: read_open3d_intrinsics(json_path),
        REDWOOD_DEPTH_SCALE,
    )


def _checked(pose: np.ndarray, path: Path, where: str) -> np.ndarray:
    """`pose`, or a `DataError` when it is finite but no rigid transform (a non-finite one is the caller's to skip)."""
    problem = pose_problem(pose) if np.all(np.isfinite(pose)) else None
    if problem is not None:
        raise DataError(f"{path}: {where.removeprefix(path.name + ' ')}: {problem}")
    return pose


def _intrinsics(where: Path, fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> CameraIntrinsics:
    values = np.array([fx, fy, cx, cy], np.float64)
    if not (np.all(np.isfinite(values)) and fx > 0 and fy > 0 and width > 0 and height > 0):
        raise DataError(f"{where}: not a pinhole camera (fx {fx}, fy {fy}, cx {cx}, cy {cy}, {width}x{height})")
    if not (0 < cx < width and 0 < cy < height):
        raise DataError(
            f"{where}: principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} depth image "
            "(intrinsics of another camera or resolution?)"
        )
    return CameraIntrinsics(float(fx), float(fy), float(cx), float(cy), int(width), int(height))


def _read_text(path: Path) -> str:
    if path.exists() and not path.is_file():
        raise DataError(f"{path}: not a regular file")
    try:
        return path.read_text()
    except FileNotFoundError:
        raise DataError(f"{path}: file missing") from None
    except (OSError, UnicodeDecodeError) as error:
        raise DataError(f"{path}: unreadable ({error})") from None


def _read_json(path: Path):
    try:
        return json.loads(_read_text(path))
    except json.JSONDecodeError as error:
        raise DataError(f"{path}: not JSON ({error})") from None


def _read_rows(path: Path) -> list[tuple[int, list[str]]]:
    """`(line number, fields)` of the lines of a text file that are neither empty nor `#` comments."""
    rows = []
    for number, line in enumerate(_read_text(path).splitlines(), 1):
        fields = line.split()
        if fields and not fields[0].startswith("#"):
            rows.append((number, fields))
    return rows


def _floats(path: Path, line: int, fields: list[str], count: int | None = None) -> list[float]:
    """The numbers of one line; a `DataError` naming the file and line for any other content."""
    if count is not None and len(fields) != count:
        raise DataError(f"{path}: line {line}: expected {count} numbers, found {len(fields)} fields")
    try:
        return [float(x) for x in fields]
    except ValueError as error:
        raise DataError(f"{path}: line {line}: {error}") from None


def _read_tum_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """A TUM `rgb.txt`/`depth.txt`: `(stamps (N,), relative paths)`; each line `timestamp path`."""
    rows = _read_rows(path)
    if not rows:
        raise DataError(f"{path}: no entry (lines 'timestamp path')")
    stamps, files = [], []
    for number, fields in rows:
        if len(fields) != 2:
            raise DataError(f"{path}: line {number}: expected 'timestamp path', found {len(fields)} fields")
        stamps.append(_floats(path, number, fields[:1])[0])
        files.append(fields[1])
    return np.asarray(stamps, np.float64), files


def _numbered(folder: Path, pattern: str, suffixes: tuple[str, ...]) -> dict[int, Path]:
    """Files of `folder` whose stem matches `pattern` (group 1 the frame number) by number."""
    if not folder.is_dir():
        raise DataError(f"{folder}: folder missing")
    regex, found = re.compile(pattern), {}
    for entry in folder.iterdir():
        match = regex.match(entry.stem)
        if match and entry.suffix.lower() in suffixes:
            if int(match.group(1)) in found:
                raise DataError(f"{entry}: another file has the frame number {int(match.group(1))}")
            found[int(match.group(1))] = entry
    return found


def _by_stem(folder: Path, suffixes: tuple[str, ...]) -> dict[str, Path]:
    if not folder.is_dir():
        raise DataError(f"{folder}: folder missing")
    found: dict[str, Path] = {}
    for entry in folder.iterdir():
        if entry.suffix.lower() in suffixes:
            if entry.stem in found:
                raise DataError(f"{entry}: another image has the stem {entry.stem!r} (e.g. both .jpg and .png)")
            found[entry.stem] = entry
    return found


def _natural(stem: str) -> tuple:
    """Sort key: the numbers in a file stem compare as numbers (``frame2`` before ``frame10``)."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", stem))
