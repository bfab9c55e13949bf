"""Camera poses for a recording without them: tracking on the host, one jitted step per frame.

`Tracker.track(depth, color=None)` returns each frame's `T_world_camera`: the first frame's is the identity (or a given
initial pose), every later one `T_world_reference @ T_reference_current` (chained in float64). What a frame is
tracked against is `TrackingConfig.reference`:

- "model" (the default; KinectFusion): the raycast of a TSDF into which every well tracked frame is fused
  (`engine.model_tracking`; the TSDF is a voxel-block pool of the map's kind, `model_map_config`), seen from
  the last good pose. The error does not pile up step by step: a frame is placed against everything seen so far.
- "frame": the last frame that tracked well. Every step's error stays in the chain: it drifts with the path.

A frame whose tracking is lost (`TrackResult.lost`) is logged, keeps the last good pose and is not fused; the
next frame is tried against the reference of the last good pose (the model raycast from there, or the last good
frame): a re-localisation that recovers when the camera comes back near that pose, not from a long gap
elsewhere. Its recovery is logged too.

The trajectory files are written beside their readers: `io.recordings.write_tum_trajectory` (TUM),
`io.recordings.write_trajectory_log` (Redwood).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable

import jax.numpy as jnp
import numpy as np

from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.model_tracking import start_model, track_and_fuse
from fmfusion_jax.engine.state import VoxelBlocks, init_voxel_blocks
from fmfusion_jax.engine.tracking import FrameMaps, TrackingConfig, frame_maps, icp_level, track_frame
from fmfusion_jax.types import CameraIntrinsics

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class TrackedFrame:
    """One frame's estimated pose and how well its tracking went."""

    T_world_camera: np.ndarray  # float64 (4, 4)
    lost: bool  # tracking failed: the pose is the last good frame's
    residual: float  # RMS point-to-plane residual (m); 0 for the first frame
    inlier_share: float  # share of the frame's valid pixels that found a correspondence; 1 for the first frame


def _model_first_rotation() -> np.ndarray:
    """`T_model_first`: the first camera's pose in the model's frame, a fixed rotation about a generic axis.

    A camera whose axes are the voxel grid's sees each row of voxels project onto one row of pixels, and the
    integration's nearest-pixel lookup then errs alike over whole planes of voxels: the raycast of one frame
    of a generated room was off by 1.7 mm (median; 6 mm at the 90th percentile, a quarter of the pixels
    invalid) with the grid on the camera's axes, 0.7 mm (2.5 mm; a tenth invalid) with it turned."""
    angle = np.radians(37.0)
    axis = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K
    return T


#: The first camera's pose in frame-to-model tracking's TSDF (see `_model_first_rotation`).
T_MODEL_FIRST = _model_first_rotation()


def model_map_config(intrinsics: CameraIntrinsics, config: TrackingConfig) -> MapConfig:
    """The `MapConfig` of frame-to-model tracking's TSDF: `config.model_*` voxels over a cube of half size
    `model_extent` around the first camera (at the origin of the model's frame, `T_MODEL_FIRST`), frames of the
    tracked image's size, one instance slot (unused). The same for every recording of one image size: one
    compiled step."""
    extent = config.model_extent
    return MapConfig.for_bounds(
        (-extent,) * 3,
        (extent,) * 3,
        voxel_size=config.model_voxel_size,
        sdf_trunc=config.model_sdf_trunc,
        depth_min=config.depth_min,
        depth_max=config.depth_max,
        block_capacity=config.model_block_capacity,
        max_touched_blocks=min(config.model_block_capacity, 4096),
        alloc_pixel_stride=2,
        image_height=intrinsics.height,
        image_width=intrinsics.width,
        instance_capacity=1,
        instance_slots=1,
        num_classes=1,
        num_open_labels=1,
    )


class Tracker:
    """Tracking of a depth sequence of one camera (one compiled kernel for the image size): frame-to-model
    (`TrackingConfig.reference == "model"`, the default) or frame-to-frame ("frame")."""

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        config: TrackingConfig | None = None,
        T_world_first: np.ndarray | None = None,
    ) -> None:
        self.config = config if config is not None else TrackingConfig()
        self._intrinsics = intrinsics
        self._K = jnp.array([intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy], jnp.float32)
        self._level = icp_level(intrinsics.width, self.config)  # frame to frame's (the model's step finds its own)
        self._T_world_first = np.eye(4) if T_world_first is None else np.asarray(T_world_first, np.float64)
        self._reference: FrameMaps | None = None
        self._T_world_reference = self._T_world_first
        self.frames_tracked = 0
        self.frames_lost = 0
        self._lost_run = 0  # frames lost since the last good one
        self._model: VoxelBlocks | None = None
        self._map_config: MapConfig | None = None
        if self.config.reference == "model":
            self._map_config = model_map_config(intrinsics, self.config)
        # the model's frame: the first camera at `T_MODEL_FIRST` (the ICP's relative poses are the same in any frame)
        self._T_model_world = T_MODEL_FIRST @ np.linalg.inv(self._T_world_first)

    @property
    def T_model_world(self) -> np.ndarray:
        """float64 `(4, 4)`: the world in the model's frame (the first camera at `T_MODEL_FIRST` there)."""
        return self._T_model_world.copy()

    @property
    def model(self) -> tuple[VoxelBlocks, MapConfig] | None:
        """Frame-to-model tracking's TSDF and its config (None before the first frame or when tracking frame to
        frame), e.g. for `engine.extraction`'s mesh; in the model's frame (`T_model_world`)."""
        if self._model is None or self._map_config is None:
            return None
        return self._model, self._map_config

    def track(self, depth: np.ndarray, color: np.ndarray | None = None) -> TrackedFrame:
        """The next frame's pose from its depth (float32 `(H, W)` metres at the intrinsics' size, 0 = invalid) and
        colour (uint8 `(H, W, 3)` RGB registered to it: the ICP's colour term, `TrackingConfig.color_weight`; give it
        for every frame or for none)."""
        if depth.shape != (self._intrinsics.height, self._intrinsics.width):
            raise ValueError(f"depth of shape {depth.shape}, the camera is {self._intrinsics.width}x{self._intrinsics.height}")
        if color is not None and color.shape != (*depth.shape, 3):
            raise ValueError(f"colour of shape {color.shape}, the depth is {depth.shape}")
        depth = np.asarray(depth, np.float32)
        index = self.frames_tracked + self.frames_lost
        if self._reference is None:
            if self._map_config is not None:
                blocks = init_voxel_blocks(self._map_config)
                self._model, self._reference = start_model(
                    blocks, depth, T_MODEL_FIRST.astype(np.float32), self._K, self.config, self._map_config, color
                )
            else:
                self._reference = frame_maps(depth, self._K, self.config, color, first_level=self._level)
            self.frames_tracked += 1
            return TrackedFrame(self._T_world_first.copy(), False, 0.0, 1.0)
        if self._map_config is not None:
            assert self._model is not None
            step = track_and_fuse(
                self._model,
                self._reference,
                depth,
                self._K,
                (self._T_model_world @ self._T_world_reference).astype(np.float32),
                self.config,
                self._map_config,
                np.bool_(False),  # start_model's executable (`first` is traced)
                color,
            )
            self._model, result = step.blocks, step.result
            next_reference = step.reference
        else:
            next_reference = frame_maps(depth, self._K, self.config, color, first_level=self._level)
            eye = jnp.eye(4, dtype=jnp.float32)
            result = track_frame(self._reference, next_reference, self._K, eye, self.config, reference_level=self._level)
        residual, share = float(result.residual), float(result.inlier_share)
        if bool(result.lost):
            self.frames_lost += 1
            self._lost_run += 1
            log.warning(
                "tracking lost at frame %d (residual %.1f mm, %.0f%% inliers): it keeps the last good pose and is not "
                "fused; the next frame is tracked against the %s from the last good pose",
                index,
                residual * 1e3,
                share * 100,
                "model" if self._map_config is not None else "last good frame",
            )
            return TrackedFrame(self._T_world_reference.copy(), True, residual, share)
        if self._lost_run:
            log.warning("tracking found again at frame %d after %d lost frames", index, self._lost_run)
            self._lost_run = 0
        # chained in float64 on the host (the step's own float32 product only places the frame in the model)
        self._T_world_reference = self._T_world_reference @ np.asarray(result.T_reference_current, np.float64)
        self._reference = next_reference
        self.frames_tracked += 1
        return TrackedFrame(self._T_world_reference.copy(), False, residual, share)


def track_depths(
    depths: Iterable[np.ndarray],
    intrinsics: CameraIntrinsics,
    config: TrackingConfig | None = None,
    T_world_first: np.ndarray | None = None,
    colors: Iterable[np.ndarray] | None = None,
) -> list[TrackedFrame]:
    """`Tracker.track` over a sequence of depth frames (and their colour images: the ICP's colour term)."""
    tracker = Tracker(intrinsics, config, T_world_first)
    if colors is None:
        return [tracker.track(depth) for depth in depths]
    return [tracker.track(depth, color) for depth, color in zip(depths, colors, strict=True)]
