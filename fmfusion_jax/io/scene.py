"""Readers for posed RGB-D scenes: the ScanNet and SceneNN folder layouts here, TUM RGB-D, Replica (NICE-SLAM)
and Open3D / Redwood recordings in `io.recordings`, ROS bags in `io.ros_bags`, Record3D exports (iPhone / iPad
LiDAR, ``.r3d``) in `io.record3d`; `open_scene` detects which one a path is and reads each into the same `Scene`
(docs/your-own-data.md says how to bring one's own recording).

ScanNet (as exported for FM-Fusion; SensReader's plain numeric stems ``0.jpg`` also work)::

    SCENE/color/frame-000000.jpg      colour (any size; resized to the depth size)
    SCENE/depth/frame-000000.png      uint16 depth, millimetres (depth_scale 1000), 0 = invalid
    SCENE/pose/frame-000000.txt       4x4 T_world_camera (camera-to-world), metres
    SCENE/intrinsic/intrinsic_depth.txt   4x4 (or 3x3) K of the depth camera

SceneNN (as converted by the authors)::

    SCENE/image/image00000.png, SCENE/depth/depth00000.png, SCENE/pose/frame-00000.txt,
    SCENE/intrinsic/intrinsic_depth.txt; without `pose/`, a `trajectory.log` (Redwood format,
    one 4x4 camera-to-world block per image, in image order) is read instead.

TUM RGB-D (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``; depth_scale 5000), Replica (``results/``,
``traj.txt``; 6553.5) and Open3D / Redwood (``color/``, ``depth/``, ``camera_intrinsic.json``,
``trajectory.log``; 1000): see `io.recordings`. ROS bags (``.bag`` or a ROS 2 folder) and Record3D exports
(``.r3d``) are extracted once into the user cache (`io.recording_cache`; depth 1000), and so are RealSense SDK
recordings (``.bag``, ``.db3``: `io.realsense`; depth aligned to colour, in the recording's own units). A recording's own depth
scale is used unless one is given.

A frame is named by its colour image's stem (``frame-000000`` or ``image00000``): the authors' detection
files are keyed by that name. Frames whose pose holds NaN or inf (ScanNet marks lost tracking so) are
skipped with a warning and listed in `Scene.skipped` (so are a TUM recording's frames its trajectory does
not cover); a missing or unreadable file is a `DataError`.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
from tqdm import tqdm

from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io.image_file import read_image
from fmfusion_jax.io.realsense import REALSENSE_SUFFIXES, is_realsense_recording, read_realsense
from fmfusion_jax.io.record3d import DEFAULT_MIN_CONFIDENCE, is_record3d, read_record3d
from fmfusion_jax.io.recordings import (
    MAX_TIME_DIFFERENCE,
    RECORDING_MARKERS,
    PoseSource,
    Recording,
    check_files_exist,
    read_recording,
    read_trajectory_log,
    recording_layouts,
)
from fmfusion_jax.io.ros_bags import BagTopics, is_ros_bag, read_bag
from fmfusion_jax.types import CameraIntrinsics, RGBDFrame, pose_problem

if TYPE_CHECKING:
    from fmfusion_jax.config import DatasetConfig

logger = logging.getLogger(__name__)

#: Every layout `open_scene` reads (the recording formats of `io.recordings` after ScanNet and SceneNN).
LAYOUTS = ("scannet", "scenenn", *RECORDING_MARKERS, "rosbag", "record3d", "realsense")
#: The layouts whose recording may be one file (a ROS 1 bag, a Record3D export, a RealSense recording).
FILE_LAYOUTS = ("rosbag", "record3d", "realsense")


@dataclasses.dataclass(frozen=True)
class _Layout:
    """Where one layout keeps a frame's files; `stem_pattern` matches colour stems, group 1 = frame number."""

    name: str
    color_dir: str
    color_suffixes: tuple[str, ...]
    stem_pattern: str
    depth_stem_pattern: str
    required_dirs: tuple[str, ...]

    def depth_path(self, root: Path, name: str) -> Path:
        if self.name == "scenenn":
            return root / "depth" / (name.replace("image", "depth", 1) + ".png")
        return root / "depth" / f"{name}.png"

    def pose_path(self, root: Path, name: str) -> Path:
        if self.name == "scenenn":
            return root / "pose" / (name.replace("image", "frame-", 1) + ".txt")
        return root / "pose" / f"{name}.txt"


_LAYOUTS = {
    "scannet": _Layout(
        "scannet", "color", (".jpg", ".png"), r"^(?:frame-)?(\d+)$", r"^(?:frame-)?(\d+)$", ("color", "depth", "intrinsic")
    ),
    "scenenn": _Layout("scenenn", "image", (".png", ".jpg"), r"^image(\d+)$", r"^depth(\d+)$", ("image", "depth", "intrinsic")),
}


def detect_layout(path: str | Path) -> str:
    """The layout of the scene folder `path` (one of `LAYOUTS`); `UserError` when none or several fit."""
    root = Path(path)
    if is_realsense_recording(root):  # before is_ros_bag: a RealSense .bag is a ROS 1 bag too
        return "realsense"
    if is_ros_bag(root):
        return "rosbag"
    if is_record3d(root):
        return "record3d"
    if not root.is_dir():
        raise UserError(f"{root}: scene folder not found")
    matches = [name for name, layout in _LAYOUTS.items() if all((root / d).is_dir() for d in layout.required_dirs)]
    matches += recording_layouts(root)
    if len(matches) == 1:
        return matches[0]
    expected = "; ".join(
        [f"{name}: {', '.join(d + '/' for d in layout.required_dirs)}" for name, layout in _LAYOUTS.items()]
        + [f"{name}: {', '.join(markers)}" for name, markers in RECORDING_MARKERS.items()]
        + ["rosbag: metadata.yaml and a .db3 or .mcap (ROS 2), or a .bag file (ROS 1)"]
        + ["record3d: a .r3d file (Record3D's export), or the folder it unzips to (metadata, rgbd/)"]
        + ["realsense: a RealSense SDK recording, a .bag or .db3 file"]
    )
    if not matches:
        present = sorted(p.name + "/" for p in root.iterdir() if p.is_dir())
        raise UserError(f"{root}: unknown scene layout (sub-folders {present or 'none'}); expected {expected}")
    raise UserError(f"{root}: matches several layouts {matches}; pass layout= one of them")


def read_intrinsics_matrix(path: Path) -> np.ndarray:
    """Reads a 3x3 or 4x4 calibration text file; returns the `(3, 3)` K, float64."""
    values = _read_numbers(path)
    if values.size == 16:
        matrix = values.reshape(4, 4)[:3, :3]
    elif values.size == 9:
        matrix = values.reshape(3, 3)
    else:
        raise DataError(f"{path}: expected a 3x3 or 4x4 matrix, found {values.size} numbers")
    fx, fy, cx, cy = matrix[0, 0], matrix[1, 1], matrix[0, 2], matrix[1, 2]
    if not (np.all(np.isfinite(matrix)) and fx > 0 and fy > 0 and cx > 0 and cy > 0):
        raise DataError(f"{path}: not a pinhole calibration (fx {fx}, fy {fy}, cx {cx}, cy {cy})")
    return matrix


def read_sensor_shapes(path: Path) -> dict[str, int]:
    """Reads ScanNet's `sensor_shapes.txt` (``depth_width:640`` lines) into a dict."""
    shapes = {}
    for line in path.read_text().splitlines():
        key, _, value = line.partition(":")
        if value.strip().isdigit():
            shapes[key.strip()] = int(value)
    return shapes


def read_pose(path: Path) -> np.ndarray | None:
    """Reads a 4x4 T_world_camera text file, `(4, 4)` float64; None for an empty file (no pose).

    Non-finite entries are returned as they are (the caller skips the frame); anything that is not 16
    numbers, or finite but not a rigid transform, is a `DataError`.
    """
    values = _read_numbers(path)
    if values.size == 0:
        return None
    if values.size != 16:
        raise DataError(f"{path}: expected a 4x4 pose, found {values.size} numbers")
    pose = values.reshape(4, 4)
    problem = pose_problem(pose) if np.all(np.isfinite(pose)) else None
    if problem is not None:
        raise DataError(f"{path}: {problem}")
    return pose


def read_depth_image(path: Path, depth_scale: float, depth_max: float) -> np.ndarray:
    """Reads a uint16 depth PNG into `(H, W)` float32 metres, 0 where invalid or beyond `depth_max`."""
    raw = read_image(path, cv2.IMREAD_UNCHANGED)
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise DataError(f"{path}: expected a single-channel uint16 depth image, found {raw.dtype} {raw.shape}")
    depth = raw.astype(np.float32) * np.float32(1.0 / depth_scale)
    depth[depth > depth_max] = 0.0
    return depth


def read_color_image(path: Path) -> np.ndarray:
    """Reads a colour image into `(H, W, 3)` uint8 RGB."""
    bgr = read_image(path, cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def pixel_grid(size: int, step: int) -> np.ndarray:
    """Every `step`-th index of `range(size)`, plus the last one (so a sample reaches the image border)."""
    return np.unique(np.append(np.arange(0, size, step), size - 1))


def backproject(depth: np.ndarray, intrinsics: CameraIntrinsics, pixel_step: int = 1) -> np.ndarray:
    """Camera-frame points of the valid pixels of `depth` `(H, W)` on a `pixel_step` grid: `(M, 3)` float64."""
    rows, cols = pixel_grid(depth.shape[0], pixel_step), pixel_grid(depth.shape[1], pixel_step)
    z = depth[np.ix_(rows, cols)].astype(np.float64)
    u, v = np.meshgrid(cols, rows)
    valid = z > 0
    z, u, v = z[valid], u[valid], v[valid]
    return np.stack([(u - intrinsics.cx) * z / intrinsics.fx, (v - intrinsics.cy) * z / intrinsics.fy, z], axis=1)


def frustum_corners(intrinsics: CameraIntrinsics, depth: float) -> np.ndarray:
    """Camera centre and the 4 image corners at `depth`: `(5, 3)` camera-frame points."""
    corners = [(0.0, 0.0), (intrinsics.width, 0.0), (0.0, intrinsics.height), (intrinsics.width, intrinsics.height)]
    points = [
        ((u - intrinsics.cx) * depth / intrinsics.fx, (v - intrinsics.cy) * depth / intrinsics.fy, depth) for u, v in corners
    ]
    return np.array([(0.0, 0.0, 0.0), *points])


def transform_points(T_world_camera: np.ndarray, points_camera: np.ndarray) -> np.ndarray:
    """`(4, 4)` x `(M, 3)` -> `(M, 3)` world points."""
    return points_camera @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]


@dataclasses.dataclass(frozen=True)
class DepthSample:
    """Depth statistics and world bounds from a sample of frames (see `Scene.sample_depth`).

    Attributes:
      frame_names: the frames read.
      valid_fraction: fraction of sampled pixels with depth in (0, depth_max].
      depth_percentiles: `(5,)` metres at the 1st, 25th, 50th, 75th, 99th percentiles of valid depth.
      world_min, world_max: `(3,)` AABB of the back-projected sampled points (no margin).
      points_world: `(N, 3)` float32 the back-projected sampled points, world metres.
      ray_origins: `(N, 3)` float32 the camera centre each point was seen from.
    """

    frame_names: tuple[str, ...]
    valid_fraction: float
    depth_percentiles: np.ndarray
    world_min: np.ndarray
    world_max: np.ndarray
    points_world: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3), np.float32), repr=False)
    ray_origins: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3), np.float32), repr=False)


class Scene:
    """A posed RGB-D sequence on disk; images are read lazily, poses eagerly (they are tiny).

    Use `open_scene` to make one. Frame `i` (0 <= i < len(scene)) is the i-th usable frame after the stride,
    `max_frames` and the skipping of frames without a valid pose.

    Attributes:
      name: the scene folder's name (``scene0000_00``).
      path: the scene folder.
      layout: the folder's format, one of `LAYOUTS` (``"scannet"``, ``"scenenn"``, ``"tum"``, ...).
      intrinsics: the depth camera; colour is registered (resized) to it.
      frame_names: names of the usable frames.
      frame_indices: `(N,)` int, each usable frame's position in the whole sequence (before the stride).
      skipped: `(frame name, reason)` of the frames left out for a bad or missing pose.
      depth_max, depth_scale, stride: the reading options (depth_scale: the one given, else the format's own).
    """

    def __init__(
        self,
        path: Path,
        layout: str,
        intrinsics: CameraIntrinsics,
        frame_names: Sequence[str],
        frame_indices: Sequence[int],
        T_world_cameras: np.ndarray,
        skipped: Sequence[tuple[str, str]],
        color_paths: Sequence[Path],
        depth_paths: Sequence[Path],
        depth_scale: float,
        depth_max: float,
        stride: int,
    ):
        self.path = path
        self.name = path.name
        self.layout = layout
        self.intrinsics = intrinsics
        self.frame_names = list(frame_names)
        self.frame_indices = np.asarray(frame_indices, np.int64)
        self.skipped = list(skipped)
        self.depth_scale = depth_scale
        self.depth_max = depth_max
        self.stride = stride
        self._T_world_cameras = np.asarray(T_world_cameras, np.float64).reshape(-1, 4, 4)
        self._color_paths = list(color_paths)
        self._depth_paths = list(depth_paths)
        self._resize_noted = False

    def __len__(self) -> int:
        return len(self.frame_names)

    def __repr__(self) -> str:
        return (
            f"Scene({self.name!r}, layout={self.layout!r}, frames={len(self)}, skipped={len(self.skipped)}, "
            f"image={self.intrinsics.width}x{self.intrinsics.height})"
        )

    def poses(self) -> np.ndarray:
        """`(N, 4, 4)` float64 T_world_camera of the usable frames (a copy; no image is read)."""
        return self._T_world_cameras.copy()

    def color_path(self, i: int) -> Path:
        return self._color_paths[i]

    def depth_path(self, i: int) -> Path:
        return self._depth_paths[i]

    def read_depth(self, i: int) -> np.ndarray:
        """`(H, W)` float32 metres of frame `i`; `DataError` when unreadable or not of the intrinsics' size."""
        path = self.depth_path(i)
        depth = read_depth_image(path, self.depth_scale, self.depth_max)
        expected = (self.intrinsics.height, self.intrinsics.width)
        if depth.shape != expected:
            raise DataError(
                f"{path}: depth is {depth.shape[1]}x{depth.shape[0]}, but the intrinsics are for "
                f"{expected[1]}x{expected[0]} images"
            )
        return depth

    def read_color(self, i: int) -> np.ndarray:
        """`(H, W, 3)` uint8 RGB of frame `i`, resized to the depth size when it differs."""
        path = self._color_paths[i]
        color = read_color_image(path)
        height, width = self.intrinsics.height, self.intrinsics.width
        if color.shape[:2] != (height, width):
            shrinking = color.shape[0] > height
            if not self._resize_noted:
                self._resize_noted = True
                logger.info(
                    "%s: colour images are %dx%d, resized to the depth size %dx%d (first: %s)",
                    self.name,
                    color.shape[1],
                    color.shape[0],
                    width,
                    height,
                    path.name,
                )
            color = cv2.resize(color, (width, height), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)
        return color

    def read_frame(self, i: int) -> RGBDFrame:
        """The usable frame `i` (0 <= i < len(self))."""
        if not -len(self) <= i < len(self):
            raise IndexError(f"{self.name}: frame {i} out of range (scene has {len(self)} frames)")
        i %= len(self)
        depth = self.read_depth(i)
        color = self.read_color(i)
        return RGBDFrame(
            index=int(self.frame_indices[i]),
            name=self.frame_names[i],
            color=color,
            depth=depth,
            T_world_camera=self._T_world_cameras[i].copy(),
            intrinsics=self.intrinsics,
        )

    def frames(self, progress: bool = False) -> Iterator[RGBDFrame]:
        """Reads the usable frames one by one, in order; `progress`: with a progress bar on stderr (tqdm)."""
        indices: Iterable[int] = range(len(self))
        if progress:
            indices = tqdm(indices, desc=self.name, unit="frame", dynamic_ncols=True)
        for i in indices:
            yield self.read_frame(i)

    def sample_depth(self, max_frames: int = 30, pixel_step: int = 8) -> DepthSample:
        """Depth statistics and the AABB of back-projected depth over `max_frames` evenly spaced frames.

        Reads only depth images, each on a `pixel_step` pixel grid; unreadable ones are left out. `DataError`
        when the scene has no frame or none of the sampled depth images reads.
        """
        if len(self) == 0:
            raise DataError(f"{self.path}: no usable frame (all {len(self.skipped)} skipped)")
        picks = np.unique(np.linspace(0, len(self) - 1, min(max_frames, len(self))).round().astype(int))
        points, origins, depths, num_pixels, read = [], [], [], 0, []
        errors: list[DataError] = []
        for i in picks:
            try:
                depth = self.read_depth(int(i))
            except DataError as error:  # a bad frame is the fusion loop's to skip or stop on, not the sample's
                errors.append(error)
                continue
            read.append(int(i))
            grid = depth[np.ix_(pixel_grid(depth.shape[0], pixel_step), pixel_grid(depth.shape[1], pixel_step))]
            num_pixels += grid.size
            depths.append(grid[grid > 0])
            points.append(transform_points(self._T_world_cameras[i], backproject(depth, self.intrinsics, pixel_step)))
            origins.append(np.broadcast_to(self._T_world_cameras[i, :3, 3], points[-1].shape))
        if not read:
            raise errors[0]
        valid = np.concatenate(depths)
        world = np.concatenate(points)
        if valid.size == 0:
            raise DataError(
                f"{self.path}: no valid depth in the {len(picks)} sampled frames "
                f"(depth_scale {self.depth_scale}, depth_max {self.depth_max} m)"
            )
        return DepthSample(
            frame_names=tuple(self.frame_names[i] for i in read),
            valid_fraction=float(valid.size / num_pixels),
            depth_percentiles=np.percentile(valid, [1, 25, 50, 75, 99]),
            world_min=world.min(axis=0),
            world_max=world.max(axis=0),
            points_world=world.astype(np.float32),
            ray_origins=np.concatenate(origins).astype(np.float32),
        )

    def bounds(
        self,
        method: str = "depth",
        max_frames: int = 60,
        pixel_step: int = 8,
        margin: float = 0.25,
        sample: DepthSample | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """An axis-aligned box holding the scene in world coordinates: `(min (3,), max (3,))` float64 metres.

        Args:
          method: ``"frustum"``: the box of every usable camera's view frustum cut at `depth_max` (reads no
            image; guaranteed to hold every point the frames can see, but loose: frusta reach through walls).
            ``"depth"``: the box of the back-projected depth of `max_frames` evenly spaced frames on a
            `pixel_step` grid, grown by `margin` and cut to the frustum box (tight; the margin absorbs what the
            sample missed, so a fusion engine should still drop points outside).
          margin: metres added on every side (``"depth"`` only).
          sample: a `sample_depth` result to use instead of reading `max_frames` frames (``"depth"`` only).
        """
        if len(self) == 0:
            raise DataError(f"{self.path}: no usable frame (all {len(self.skipped)} skipped), no bounds")
        corners = frustum_corners(self.intrinsics, self.depth_max)
        world_corners = np.einsum("nij,kj->nki", self._T_world_cameras[:, :3, :3], corners)
        world_corners = (world_corners + self._T_world_cameras[:, None, :3, 3]).reshape(-1, 3)
        frustum_min, frustum_max = world_corners.min(axis=0), world_corners.max(axis=0)
        if method == "frustum":
            return frustum_min, frustum_max
        if method != "depth":
            raise UserError(f"bounds method {method!r}: expected 'depth' or 'frustum'")
        sample = sample or self.sample_depth(max_frames=max_frames, pixel_step=pixel_step)
        lower = np.maximum(sample.world_min - margin, frustum_min)
        upper = np.minimum(sample.world_max + margin, frustum_max)
        return lower, upper

    def trajectory_length(self) -> float:
        """Summed distance between consecutive usable camera positions, metres."""
        positions = self._T_world_cameras[:, :3, 3]
        return float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()) if len(positions) > 1 else 0.0

    def ground_truth_files(self) -> dict[str, Path | None]:
        """The layout's ground-truth files by role, each the path when present, else None (a recording of the
        formats of `io.recordings` has none)."""
        if self.layout == "scannet":
            names = {
                "mesh": f"{self.name}_vh_clean_2.ply",
                "labelled mesh": f"{self.name}_vh_clean_2.labels.ply",
                "segments": f"{self.name}_vh_clean_2.0.010000.segs.json",
                "aggregation": f"{self.name}.aggregation.json",
            }
        elif self.layout == "scenenn":
            names = {"mesh": f"{self.name}.ply", "annotation": f"{self.name}.xml"}
        else:
            names = {}
        return {role: (self.path / file if (self.path / file).is_file() else None) for role, file in names.items()}


def open_scene(
    path: str | Path,
    layout: str = "auto",
    stride: int = 1,
    depth_max: float = 4.0,
    depth_scale: float | None = None,
    max_frames: int | None = None,
    max_time_difference: float = MAX_TIME_DIFFERENCE,
    topics: BagTopics | None = None,
    min_depth_confidence: int = DEFAULT_MIN_CONFIDENCE,
) -> Scene:
    """Opens a scene folder: lists its frames, reads the intrinsics and the poses, checks every file exists.

    Args:
      path: the scene folder (or a ROS 1 ``.bag`` file, a Record3D ``.r3d`` file, a RealSense SDK ``.bag`` / ``.db3``
        recording).
      layout: ``"auto"`` or one of `LAYOUTS`.
      stride: keep every `stride`-th frame of the sequence (counted before skipping bad poses).
      depth_max: metres; farther depth reads as 0.
      depth_scale: raw depth units per metre; None: the format's own (ScanNet, SceneNN, Redwood 1000, TUM 5000,
        Replica 6553.5 or its cam_params.json's).
      max_frames: keep at most this many usable frames (after the stride), or all.
      max_time_difference: seconds; a TUM recording's or a ROS bag's colour image pairs with a depth image (and
        a pose) this close in time.
      topics: a ROS bag's topics, when not the ones chosen automatically (`io.ros_bags`).
      min_depth_confidence: a Record3D export's depth pixels of lower ARKit confidence (0, 1, 2) are dropped.

    Raises:
      UserError: bad arguments or an unknown layout.
      DataError: a missing or malformed file (named), or no frame at all.
    """
    root = Path(path)
    if layout == "auto":
        layout = detect_layout(root)
    elif layout not in LAYOUTS:
        raise UserError(f"layout {layout!r}: expected 'auto' or one of {list(LAYOUTS)}")
    elif layout == "realsense" and not (root.is_file() and root.suffix in REALSENSE_SUFFIXES):
        raise UserError(f"{root}: not a RealSense SDK recording (a .bag or .db3 file)")
    elif layout not in ("rosbag", "realsense") and is_ros_bag(root):
        raise UserError(f"{root}: a ROS bag, but the layout asked for is {layout!r} (use auto or rosbag)")
    elif layout != "record3d" and is_record3d(root):
        raise UserError(f"{root}: a Record3D export, but the layout asked for is {layout!r} (use auto or record3d)")
    elif not (root.is_dir() or (layout in FILE_LAYOUTS and root.is_file())):
        raise UserError(f"{root}: scene folder not found")
    if not (isinstance(stride, int) and stride >= 1):
        raise UserError(f"stride must be a positive integer, got {stride!r}")
    if max_frames is not None and not (isinstance(max_frames, int) and max_frames >= 1):
        raise UserError(f"max_frames must be a positive integer or None, got {max_frames!r}")
    if not (depth_max > 0 and (depth_scale is None or depth_scale > 0)):
        raise UserError(f"depth_max ({depth_max}) and depth_scale ({depth_scale}) must be positive")
    if not max_time_difference > 0:
        raise UserError(f"max_time_difference must be positive, got {max_time_difference!r}")
    if layout in _LAYOUTS:
        recording = _read_folder_layout(root, _LAYOUTS[layout], stride)
    elif layout == "rosbag":
        recording = read_bag(root, max_time_difference, topics)
    elif layout == "record3d":
        recording = read_record3d(root, min_depth_confidence)
    elif layout == "realsense":
        recording = read_realsense(root, max_time_difference)
    else:
        recording = read_recording(layout, root, stride, max_time_difference)

    all_names = recording.names
    names: list[str] = []
    indices: list[int] = []
    poses: list[np.ndarray] = []
    skipped: list[tuple[str, str]] = []
    for i in range(0, len(all_names), stride):
        if max_frames is not None and len(names) >= max_frames:
            break
        pose, where = recording.pose(i)
        if pose is None or not np.all(np.isfinite(pose)):
            reason = where if pose is None else f"non-finite pose in {where}"
            logger.warning("%s: skipping frame %s: %s", root.name, all_names[i], reason)
            skipped.append((all_names[i], reason))
            continue
        names.append(all_names[i])
        indices.append(i)
        poses.append(pose)

    intrinsics = recording.intrinsics()
    return Scene(
        root,
        layout,
        intrinsics,
        names,
        indices,
        np.array(poses).reshape(-1, 4, 4),
        skipped,
        [recording.color_paths[i] for i in indices],
        [recording.depth_paths[i] for i in indices],
        recording.depth_scale if depth_scale is None else depth_scale,
        depth_max,
        stride,
    )


def open_dataset_scene(path: str | Path, dataset: "DatasetConfig") -> Scene:
    """`open_scene` with the reading options of a config's `dataset` section (layout, stride, depth range,
    depth scale, frame limit, time tolerance, a ROS bag's topics, a Record3D export's depth confidence)."""
    return open_scene(
        path,
        layout=dataset.layout,
        stride=dataset.frame_stride,
        depth_max=dataset.depth_max,
        depth_scale=dataset.depth_scale,
        max_frames=dataset.max_frames,
        max_time_difference=dataset.max_time_difference,
        topics=BagTopics(
            dataset.color_topic, dataset.depth_topic, dataset.camera_info_topic, dataset.pose_topic, dataset.pose_frame
        ),
        min_depth_confidence=dataset.min_depth_confidence,
    )


def _read_folder_layout(root: Path, spec: _Layout, stride: int) -> Recording:
    """The frames of a ScanNet or SceneNN folder (every `stride`-th one's files checked to exist)."""
    for folder in spec.required_dirs:
        if not (root / folder).is_dir():
            raise DataError(f"{root / folder}: folder missing (layout {spec.name} needs {', '.join(spec.required_dirs)})")
    color_paths = _list_color_images(root / spec.color_dir, spec)
    _check_every_depth_has_color(root, spec, color_paths)
    all_names = [p.stem for p in color_paths]
    picked = list(range(0, len(all_names), stride))
    depth_paths = [spec.depth_path(root, name) for name in all_names]
    check_files_exist([depth_paths[i] for i in picked])
    pose_source = _pose_source(root, spec, all_names, picked)
    return Recording(
        spec.name,
        all_names,
        color_paths,
        depth_paths,
        pose_source,
        lambda: _read_intrinsics(root, spec, all_names[0]),
        1000.0,
    )


def _list_color_images(folder: Path, spec: _Layout) -> list[Path]:
    """Colour images of the layout's naming, sorted by frame number."""
    pattern = re.compile(spec.stem_pattern)
    found = []
    for entry in folder.iterdir():
        match = pattern.match(entry.stem)
        if match and entry.suffix.lower() in spec.color_suffixes:
            found.append((int(match.group(1)), entry.name, entry))
    if not found:
        raise DataError(
            f"{folder}: no colour image named like {spec.stem_pattern!r} with suffix {' or '.join(spec.color_suffixes)}"
        )
    found.sort()
    numbers = [number for number, _, _ in found]
    if len(set(numbers)) != len(numbers):
        raise DataError(f"{folder}: several colour images share a frame number (e.g. both .jpg and .png)")
    return [entry for _, _, entry in found]


def _check_every_depth_has_color(root: Path, spec: _Layout, color_paths: list[Path]) -> None:
    """`DataError` naming the first depth image whose colour image is missing (frames are listed by colour, so
    a missing colour image would otherwise silently shorten the sequence)."""
    pattern = re.compile(spec.depth_stem_pattern)
    color_numbers = {int(re.match(spec.stem_pattern, p.stem).group(1)) for p in color_paths}  # type: ignore[union-attr]
    orphans = sorted(
        (int(m.group(1)), entry.name)
        for entry in (root / "depth").iterdir()
        if entry.suffix.lower() == ".png" and (m := pattern.match(entry.stem)) and int(m.group(1)) not in color_numbers
    )
    if orphans:
        raise DataError(
            f"{root / 'depth' / orphans[0][1]}: its colour image is missing from {root / spec.color_dir} "
            f"({len(orphans)} depth images have none)"
        )


def _pose_source(root: Path, spec: _Layout, names: list[str], picked: list[int]) -> PoseSource:
    """A function `i -> (pose or None, where)` for frame `i` of `names`: from `pose/`, else `trajectory.log`."""
    log_path = root / "trajectory.log"
    if spec.name == "scenenn" and not (root / "pose").is_dir() and log_path.is_file():
        trajectory = read_trajectory_log(log_path)
        if len(trajectory) != len(names):
            raise DataError(f"{log_path}: {len(trajectory)} poses for {len(names)} images; cannot pair them")
        logger.info("%s: poses read from %s (one per image, in order)", root.name, log_path)
        return lambda i: (trajectory[i], f"{log_path.name} block {i}")
    paths = [spec.pose_path(root, name) for name in names]
    check_files_exist([paths[i] for i in picked])

    def pose(i: int) -> tuple[np.ndarray | None, str]:
        pose = read_pose(paths[i])
        return pose, (paths[i].name if pose is not None else f"empty pose file {paths[i].name}")

    return pose


def _read_intrinsics(root: Path, spec: _Layout, first_name: str) -> CameraIntrinsics:
    """Depth intrinsics; the image size from `sensor_shapes.txt` when it says, else the first depth image."""
    matrix_path = root / "intrinsic" / "intrinsic_depth.txt"
    if not matrix_path.is_file():
        raise DataError(f"{matrix_path}: file missing (depth camera intrinsics)")
    K = read_intrinsics_matrix(matrix_path)
    shapes_path = root / "intrinsic" / "sensor_shapes.txt"
    shapes = read_sensor_shapes(shapes_path) if shapes_path.is_file() else {}
    if "depth_width" in shapes and "depth_height" in shapes:
        width, height = shapes["depth_width"], shapes["depth_height"]
    else:
        first_depth = spec.depth_path(root, first_name)
        height, width = read_image(first_depth, cv2.IMREAD_UNCHANGED).shape[:2]
    if not (0 < K[0, 2] < width and 0 < K[1, 2] < height):
        raise DataError(
            f"{matrix_path}: principal point ({K[0, 2]:g}, {K[1, 2]:g}) lies outside the "
            f"{width}x{height} depth image (intrinsics of another camera or resolution?)"
        )
    return CameraIntrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height))


def _read_numbers(path: Path) -> np.ndarray:
    """All whitespace-separated numbers of a text file (``inf``/``nan`` allowed), float64."""
    if path.exists() and not path.is_file():
        raise DataError(f"{path}: not a regular file")
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise DataError(f"{path}: file missing") from None
    except (OSError, UnicodeDecodeError) as error:
        raise DataError(f"{path}: unreadable ({error})") from None
    try:
        return np.array([float(x) for x in text.split()], np.float64)
    except ValueError as error:
        raise DataError(f"{path}: not a list of numbers ({error})") from None


def sample_scene_dir() -> Path:
    """Where the sample ScanNet scene is expected: `$FMFUSION_SCANNET_DIR/scene0000_00`, else
    ../shared/data/scannet/scene0000_00 from the working folder (whether or not it is there)."""
    return Path(os.environ.get("FMFUSION_SCANNET_DIR", "../shared/data/scannet")) / "scene0000_00"
