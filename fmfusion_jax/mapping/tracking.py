"""Camera poses for a recording without them: frame-to-frame tracking on the host (`engine.tracking` per frame).

`Tracker.track(depth)` returns each frame's `T_world_camera`: the first frame's is the identity (or a given
initial pose), every later one `T_world_reference @ T_reference_current` with the reference the last frame that
tracked well. A frame whose tracking is lost (`TrackResult.lost`) is logged and keeps the last good pose; it
does not become the reference, so the next frame is tried against the last good frame (a simple
re-localisation that recovers from a single bad frame, not from a long gap). Frame-to-frame tracking drifts:
the error grows with the path.

The trajectory files are written beside their readers: `io.recordings.write_tum_trajectory` (TUM),
`io.recordings.write_trajectory_log` (Redwood).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable

import jax.numpy as jnp
import numpy as np

from fmfusion_jax.engine.tracking import FrameMaps, TrackingConfig, frame_maps, track_frame
from fmfusion_jax.types import CameraIntrinsics

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class TrackedFrame:
    """One frame's estimated pose and how well its tracking went."""

    T_world_camera: np.ndarray  # float64 (4, 4)
    lost: bool  # tracking failed: the pose is the last good frame's
    residual: float  # RMS point-to-plane residual (m); 0 for the first frame
    inlier_share: float  # share of the frame's valid pixels that found a correspondence; 1 for the first frame


class Tracker:
    """Frame-to-frame tracking of a depth sequence of one camera (one compiled kernel for the image size)."""

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        config: TrackingConfig | None = None,
        T_world_first: np.ndarray | None = None,
    ) -> None:
        self.config = config if config is not None else TrackingConfig()
        self._intrinsics = intrinsics
        self._K = jnp.array([intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy], jnp.float32)
        self._T_world_first = np.eye(4) if T_world_first is None else np.asarray(T_world_first, np.float64)
        self._reference: FrameMaps | None = None
        self._T_world_reference = self._T_world_first
        self.frames_tracked = 0
        self.frames_lost = 0

    def track(self, depth: np.ndarray) -> TrackedFrame:
        """The next frame's pose from its depth (float32 `(H, W)` metres at the intrinsics' size, 0 = invalid)."""
        if depth.shape != (self._intrinsics.height, self._intrinsics.width):
            raise ValueError(f"depth of shape {depth.shape}, the camera is {self._intrinsics.width}x{self._intrinsics.height}")
        maps = frame_maps(np.asarray(depth, np.float32), self._K, self.config)
        index = self.frames_tracked + self.frames_lost
        if self._reference is None:
            self._reference = maps
            self.frames_tracked += 1
            return TrackedFrame(self._T_world_first.copy(), False, 0.0, 1.0)
        result = track_frame(self._reference, maps, self._K, jnp.eye(4, dtype=jnp.float32), self.config)
        residual, share = float(result.residual), float(result.inlier_share)
        if bool(result.lost):
            self.frames_lost += 1
            log.warning(
                "tracking lost at frame %d (residual %.1f mm, %.0f%% inliers): it keeps the last good pose",
                index,
                residual * 1e3,
                share * 100,
            )
            return TrackedFrame(self._T_world_reference.copy(), True, residual, share)
        T_reference_current = np.asarray(result.T_reference_current, np.float64)
        self._T_world_reference = self._T_world_reference @ T_reference_current
        self._reference = maps
        self.frames_tracked += 1
        return TrackedFrame(self._T_world_reference.copy(), False, residual, share)


def track_depths(
    depths: Iterable[np.ndarray],
    intrinsics: CameraIntrinsics,
    config: TrackingConfig | None = None,
    T_world_first: np.ndarray | None = None,
) -> list[TrackedFrame]:
    """`Tracker.track` over a sequence of depth frames."""
    tracker = Tracker(intrinsics, config, T_world_first)
    return [tracker.track(depth) for depth in depths]
