"""The detection schedule: which frames are detection frames (every `detection.every`-th, or by camera
motion for sparse sequences).
"""

from __future__ import annotations

import collections
import logging
import math
from collections.abc import Iterable, Iterator
from statistics import median
from typing import Any

import numpy as np

from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.mapping.inputs import DetectionSource
from fmfusion_jax.types import FrameDetections, RGBDFrame

log = logging.getLogger(__name__)


def camera_motion(T_world_a: np.ndarray, T_world_b: np.ndarray) -> tuple[float, float]:
    """`(metres, degrees)`: translation and rotation angle of camera b relative to camera a (4x4 rigid poses).

    Without forming `inv(T_world_a) @ T_world_b` (the schedule asks this three times a frame, in the thread that
    calls the steps): its translation is `R_a^T (t_b - t_a)`, as long as `t_b - t_a`, and the trace of its rotation
    `R_a^T R_b` is the sum of `R_a * R_b`."""
    a, b = np.asarray(T_world_a, np.float64), np.asarray(T_world_b, np.float64)
    cos = min(1.0, max(-1.0, (float(np.sum(a[:3, :3] * b[:3, :3])) - 1.0) / 2.0))
    return math.dist(a[:3, 3], b[:3, 3]), math.degrees(math.acos(cos))


def scheduled_positions(poses: np.ndarray, config: PipelineConfig) -> list[int]:
    """Positions of the frames (of `poses`, `(N, 4, 4)` T_world_camera in reading order) whose detections the
    detection schedule fuses when every frame has detections: the frames worth running the models on."""
    schedule, positions = DetectionSchedule(config), []
    for position, pose in enumerate(np.asarray(poses, np.float64)):
        if schedule.due(position, pose):
            schedule.fused(pose)
            positions.append(position)
        schedule.advance(pose)
    return positions


class DetectionSchedule:
    """Which frames have their detections fused.

    `detections.schedule = motion` (default): a frame is due when the camera has moved at least
    `min_translation` metres or turned `min_rotation` degrees since the last frame whose detections were
    fused (the first frame is always due). The rule follows the camera, not the frame rate: on a 30 Hz
    ScanNet sequence (typically 0.4 cm and 0.35 degrees per frame) it fuses about every 8th-15th frame, near
    the paper's every 10th. A sequence already subsampled in time (its median step between consecutive
    frames is at least `sparse_motion` of a detection step) has every frame fused, as a fixed stride of 1
    would, pauses of the camera included: its frames are keyframes already. A due frame without detections
    (no detection file) leaves the schedule due, so the next frame with detections is taken.
    `schedule = every`: every `every`-th frame read (the paper's rule).

    Call `due` (pure) before a frame, `fused` when its detections were fused and `advance` once per frame
    read, in that order.
    """

    #: consecutive-frame steps the sequence's rate is judged on (a pause shorter than half of it does not
    #: change the judgement)
    RATE_WINDOW = 100

    def __init__(self, config: PipelineConfig):
        self.detections = config.detections
        self._last_pose: np.ndarray | None = None  # T_world_camera of the last detection frame fused
        self._previous_pose: np.ndarray | None = None  # T_world_camera of the last frame read
        self._steps: collections.deque[float] = collections.deque(maxlen=self.RATE_WINDOW)

    def due(self, position: int, T_world_camera: np.ndarray) -> bool:
        """Whether the frame read at `position` (0, 1, ...) with this pose should have detections fused."""
        det = self.detections
        if det.schedule == "every":
            return position % det.every == 0
        if self._last_pose is None:
            return True
        if self.sparse_sequence(T_world_camera):
            return True
        return self._detection_steps(self._last_pose, T_world_camera) >= 1.0

    def sparse_sequence(self, T_world_camera: np.ndarray | None = None) -> bool:
        """Whether the sequence read so far (and a next frame at `T_world_camera`) is subsampled in time."""
        if self.detections.sparse_motion <= 0:
            return False
        steps = list(self._steps)
        if T_world_camera is not None and self._previous_pose is not None:
            steps.append(self._detection_steps(self._previous_pose, T_world_camera))
        return bool(steps) and median(steps) >= self.detections.sparse_motion

    def fused(self, T_world_camera: np.ndarray) -> None:
        """Records that a frame's detections were fused at this pose."""
        self._last_pose = np.asarray(T_world_camera, np.float64)

    def advance(self, T_world_camera: np.ndarray) -> None:
        """Records a frame read (detections fused or not) at this pose."""
        pose = np.asarray(T_world_camera, np.float64)
        if self._previous_pose is not None:
            self._steps.append(self._detection_steps(self._previous_pose, pose))
        self._previous_pose = pose

    def _detection_steps(self, T_world_a: np.ndarray, T_world_b: np.ndarray) -> float:
        """Camera motion from a to b in detection steps: 1.0 = `min_translation` or `min_rotation`."""
        metres, degrees = camera_motion(T_world_a, T_world_b)
        det = self.detections
        return max(
            metres / det.min_translation if det.min_translation > 0 else np.inf,
            degrees / det.min_rotation if det.min_rotation > 0 else np.inf,
        )

    def state(self) -> dict[str, Any]:
        """The schedule's memory as plain JSON values (for saved maps)."""
        pose = lambda p: None if p is None else np.asarray(p).tolist()  # noqa: E731
        return {
            "last_detection_pose": pose(self._last_pose),
            "previous_pose": pose(self._previous_pose),
            "steps": list(self._steps),
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Continues from `state()` (a map saved before the schedule kept its rate has the detection pose only)."""
        pose = lambda p: None if p is None else np.asarray(p, np.float64)  # noqa: E731
        self._last_pose = pose(state.get("last_detection_pose"))
        self._previous_pose = pose(state.get("previous_pose"))
        self._steps = collections.deque((float(s) for s in state.get("steps", [])), maxlen=self.RATE_WINDOW)


def scheduled_detections(
    frames: Iterable[RGBDFrame], detection_source: DetectionSource, config: PipelineConfig
) -> Iterator[tuple[RGBDFrame, "FrameDetections | None"]]:
    """`(frame, detections or None)` for every frame, the detections read only on due frames
    (`DetectionSchedule`)."""
    schedule = DetectionSchedule(config)
    for position, frame in enumerate(frames):
        detections = detection_source(frame) if schedule.due(position, frame.T_world_camera) else None
        if detections is not None:
            schedule.fused(frame.T_world_camera)
        schedule.advance(frame.T_world_camera)
        yield frame, detections
