"""Plain data structures shared by the readers, the detectors, the simulator and the fusion loop.

These are NumPy containers, not JAX state: the jitted engine never sees them directly. The Python loop
converts them into fixed-shape arrays (see `fmfusion_jax.engine`) before calling the engine.

Conventions
- Images are row-major `(H, W)`; pixel `(u, v)` is column `u`, row `v`.
- Poses are named by their frames: `T_world_camera` maps camera coordinates to world coordinates
  (`x_world = R @ x_camera + t`), the usual ScanNet `pose/*.txt` camera-to-world matrix.
- Depth is in metres, `float32`, with 0 meaning "no measurement".
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

#: How far a pose's rotation may be from orthonormal (max |R^T R - I|) and still be taken as a camera pose.
ROTATION_TOLERANCE = 1e-2


def rotation_error(T_world_camera: np.ndarray) -> float:
    """max |R^T R - I| of a 4x4 pose's rotation block (0 for a rotation; see `ROTATION_TOLERANCE`)."""
    rotation = np.asarray(T_world_camera, np.float64)[:3, :3]
    return float(np.abs(rotation.T @ rotation - np.eye(3)).max())


def pose_problem(T_world_camera: np.ndarray) -> str | None:
    """What makes `T_world_camera` not a camera-to-world pose (not 4x4, not finite, a last row other than
    [0, 0, 0, 1], a rotation block that is not a rotation), or None: the one rule of the readers and the `Mapper`."""
    pose = np.asarray(T_world_camera, np.float64)
    if pose.shape != (4, 4):
        return f"a pose must be a 4x4 matrix, got shape {pose.shape}"
    if not np.all(np.isfinite(pose)):
        return "the pose is not finite (a lost track?)"
    if not np.allclose(pose[3], (0.0, 0.0, 0.0, 1.0), atol=1e-6):
        return (
            f"the pose is not a rigid transform: its last row is {pose[3].tolist()}, not [0, 0, 0, 1] "
            "(a transposed pose? the translation belongs in the last column)"
        )
    error = rotation_error(pose)
    if error > ROTATION_TOLERANCE:
        return f"the pose is not a rigid transform: |R^T R - I| = {error:.3g} (check the pose's convention)"
    if np.linalg.det(pose[:3, :3]) < 0:
        return f"the pose's rotation is a reflection (det R = {np.linalg.det(pose[:3, :3]):.3g}), not a camera pose"
    return None


def score_problem(label: object, score: object) -> str | None:
    """What makes `label: score` not a detection's label score (a non-empty string, a number in [0, 1]), or None:
    the one rule of the detection readers and the `Mapper`."""
    if not isinstance(label, str) or not label.strip():
        return f"label {label!r} is not a non-empty string"
    if isinstance(score, bool) or not isinstance(score, (int, float, np.integer, np.floating)) or not 0.0 <= score <= 1.0:
        return f"score of {label!r} must be a number in [0, 1], found {score!r}"
    return None


@dataclasses.dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of a `width x height` image (pixels)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 calibration matrix K, float64."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, width: int, height: int) -> "CameraIntrinsics":
        """The same camera for an image resized to `width x height`."""
        sx, sy = width / self.width, height / self.height
        return CameraIntrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)


@dataclasses.dataclass(frozen=True)
class RGBDFrame:
    """One posed RGB-D frame.

    Attributes:
      index: position of the frame in the sequence (0-based, before any stride).
      name: the frame's file stem, e.g. ``"frame-000010"``; detections are keyed by it.
      color: `(H, W, 3)` uint8, RGB order.
      depth: `(H, W)` float32 metres, 0 where invalid or beyond the truncation distance.
      T_world_camera: `(4, 4)` float64 camera-to-world transform.
      intrinsics: the depth camera (colour is registered to it).
    """

    index: int
    name: str
    color: np.ndarray
    depth: np.ndarray
    T_world_camera: np.ndarray
    intrinsics: CameraIntrinsics


@dataclasses.dataclass
class FrameDetections:
    """The foundation models' output for one frame, in open-set labels.

    The same structure is produced by the detection-file reader, by the ONNX front end (`detectors`)
    and by the simulator, and consumed by the fusion loop.

    Attributes:
      frame_name: stem of the frame the detections belong to (``"frame-000010"``).
      masks: `(N, H, W)` bool, one mask per detection.
      labels: `N` dicts open-set label -> score in [0, 1] (a detection usually has 1-3 labels).
      boxes: `(N, 4)` float32 pixel boxes ``[u0, v0, u1, v1]``.
      raw_tags: every tag the image tagger produced (before filtering to the labels of interest).
      tags: the tagger's tags kept after filtering to the open-set labels of interest.
      prompt: the labels actually sent to the open-set detector (`tags` plus prompt augmentation).
    """

    frame_name: str
    masks: np.ndarray
    labels: list[dict[str, float]]
    boxes: np.ndarray
    raw_tags: list[str] = dataclasses.field(default_factory=list)
    tags: list[str] = dataclasses.field(default_factory=list)
    prompt: list[str] = dataclasses.field(default_factory=list)

    def __post_init__(self) -> None:
        n = len(self.labels)
        if self.masks.ndim != 3 or self.masks.shape[0] != n:
            raise ValueError(f"{self.frame_name}: masks have shape {self.masks.shape}, expected ({n}, H, W) for {n} detections")
        if self.boxes.shape != (n, 4):
            raise ValueError(f"{self.frame_name}: boxes have shape {self.boxes.shape}, expected ({n}, 4)")

    @property
    def num_detections(self) -> int:
        return len(self.labels)

    @property
    def image_shape(self) -> tuple[int, int]:
        return int(self.masks.shape[1]), int(self.masks.shape[2])

    def label_score_matrix(self, open_labels: Sequence[str]) -> np.ndarray:
        """`(N, len(open_labels))` float32 scores; labels outside `open_labels` are dropped."""
        index = {name: i for i, name in enumerate(open_labels)}
        scores = np.zeros((self.num_detections, len(open_labels)), np.float32)
        for k, detection_labels in enumerate(self.labels):
            for name, score in detection_labels.items():
                if name in index:
                    scores[k, index[name]] = max(scores[k, index[name]], float(score))
        return scores

    @staticmethod
    def empty(frame_name: str, height: int, width: int) -> "FrameDetections":
        return FrameDetections(frame_name, np.zeros((0, height, width), bool), [], np.zeros((0, 4), np.float32))
