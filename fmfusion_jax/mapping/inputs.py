"""Input adapters and frame checks, once: a user's config, intrinsics, frames and detections coerced and checked
(`as_config`, `as_frame`, ...), and the host-to-engine packing of a frame and its detections (`HostAdapter`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from fmfusion_jax.config import PipelineConfig, load_config
from fmfusion_jax.engine import step
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.detections import DetectionBatch, pack_detections
from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import LabelSets
from fmfusion_jax.types import CameraIntrinsics, FrameDetections, RGBDFrame, pose_problem, score_problem

log = logging.getLogger(__name__)


class DetectionSource(Protocol):
    """Gives the detections of a frame, or None when the frame has none (not a detection frame, no file).

    A folder of detection files (`io.detections.DetectionFolder`), models run online (`sources.ModelSource`) or
    any function of a frame. A source whose attribute `reads_ahead` is true (a folder of files: no state, cheap
    to call for a frame that turns out not due) is called by `fmfusion run`'s reader threads for the next frames;
    others (the models, whose prompt window counts the detection frames) only on due frames, in order: in a
    detection thread of their own when their attribute `detects_ahead` is true.
    `sources.open_detection_source` chooses one from a run's arguments.
    """

    def __call__(self, frame: RGBDFrame, /) -> FrameDetections | None: ...


def frame_inputs(frame: RGBDFrame, map_config: MapConfig) -> step.FrameInputs:
    """A frame as engine arrays; a wrong image size is an error naming the frame. (Its pose was checked where it
    came in: by the scene readers, or `Mapper` through `checked_pose`.)"""
    expected = (map_config.image_height, map_config.image_width)
    if frame.depth.shape != expected or frame.color.shape[:2] != expected:
        raise UserError(
            f"{frame.name}: depth {frame.depth.shape} / colour {frame.color.shape[:2]} differ from "
            f"the sequence's image size {expected}"
        )
    k = frame.intrinsics
    # host arrays (the step's call transfers them): a `jnp.asarray` that converts dispatches a jitted op each
    return step.FrameInputs(
        depth=np.asarray(frame.depth, np.float32),
        color=np.asarray(frame.color, np.uint8),
        T_world_camera=np.asarray(frame.T_world_camera, np.float32),
        intrinsics=np.asarray([k.fx, k.fy, k.cx, k.cy], np.float32),
        frame_index=np.asarray(frame.index, np.int32),
    )


@dataclasses.dataclass(frozen=True)
class HostAdapter:
    """The one joint between the host (readers, detectors, simulator: arrays of any size) and the engine
    (fixed shapes): frames become `FrameInputs`, detections a padded `DetectionBatch` (their label image at the
    fused pixel stride), each checked once against the map's image size with an error that names the frame.
    `MapBuilder` (so `Mapper` and the bench), `MapperBatch` and the Kimera baseline all go through it."""

    map_config: MapConfig
    open_labels: tuple[str, ...]
    max_detections: int
    min_mask_pixels: int

    @classmethod
    def for_map(cls, config: PipelineConfig, map_config: MapConfig, label_sets: LabelSets) -> HostAdapter:
        return cls(map_config, tuple(label_sets.open_labels), config.detections.max_detections, config.detections.min_mask_pixels)

    @property
    def image_shape(self) -> tuple[int, int]:
        return self.map_config.image_height, self.map_config.image_width

    def frame(self, frame: RGBDFrame) -> step.FrameInputs:
        return frame_inputs(frame, self.map_config)

    def detections(self, detections: FrameDetections | None) -> DetectionBatch:
        """The detections padded to `max_detections` rows (None: a batch with no valid row)."""
        if detections is None:
            detections = FrameDetections("-", np.zeros((0, *self.image_shape), bool), [], np.zeros((0, 4), np.float32))
        if detections.image_shape != self.image_shape:
            raise UserError(
                f"{detections.frame_name}: detection masks are {detections.image_shape}, frames are {self.image_shape}"
            )
        return pack_detections(
            detections,
            self.open_labels,
            self.max_detections,
            self.min_mask_pixels,
            stride=self.map_config.pixel_stride,
            as_image=True,
        )


def as_config(config: "str | Path | Mapping[str, Any] | PipelineConfig | None") -> PipelineConfig:
    """A `PipelineConfig` from a packaged name (`"scannet"`), a YAML path, a dict or a config (None: scannet).

    A dict holds overrides of the scannet config, nested (`{"detections": {"every": 1}}`) or dotted
    (`{"detections.every": 1}`); a `"base"` key names another config to start from.
    """
    if config is None:
        return load_config("scannet")
    if isinstance(config, PipelineConfig):
        return config
    if isinstance(config, (str, Path)):
        return load_config(str(config))
    if isinstance(config, Mapping):
        values = dict(config)
        base = values.pop("base", "scannet")
        overrides = []
        for key, value in values.items():
            if isinstance(value, Mapping):
                overrides += [f"{key}.{inner}={_yaml_value(v)}" for inner, v in value.items()]
            else:
                overrides.append(f"{key}={_yaml_value(value)}")
        return load_config(base, overrides)
    raise UserError(f"config: expected a config name, a YAML path, a dict or a PipelineConfig, got {type(config).__name__}")


def _yaml_value(value: Any) -> str:

    return json.dumps(list(value) if isinstance(value, tuple) else value)


def as_intrinsics(intrinsics: "CameraIntrinsics | np.ndarray | Sequence", height: int, width: int) -> CameraIntrinsics:
    """`CameraIntrinsics` from itself, a 3x3 K matrix or `(fx, fy, cx, cy)`, for `height x width` images."""
    if isinstance(intrinsics, CameraIntrinsics):
        k = intrinsics
    else:
        values = np.asarray(intrinsics, np.float64)
        if values.shape == (3, 3):
            values = values[[0, 1, 0, 1], [0, 1, 2, 2]]
        if values.shape != (4,):
            raise UserError(f"intrinsics: expected a 3x3 K matrix or (fx, fy, cx, cy), got shape {values.shape}")
        fx, fy, cx, cy = (float(v) for v in values)
        k = CameraIntrinsics(fx, fy, cx, cy, width=width, height=height)
    if (k.height, k.width) != (height, width):
        raise UserError(f"intrinsics are for {k.width}x{k.height} images, the depth image is {width}x{height}")
    if not (np.isfinite([k.fx, k.fy, k.cx, k.cy]).all() and k.fx > 0 and k.fy > 0):
        raise UserError(f"intrinsics: focal lengths must be positive and finite, got fx={k.fx}, fy={k.fy}")
    return k


def as_frame(
    frame: RGBDFrame | None = None,
    *,
    depth=None,
    color=None,
    T_world_camera=None,
    intrinsics=None,
    index: int = 0,
    name: str | None = None,
) -> RGBDFrame:
    """An `RGBDFrame` from itself or from arrays: depth `(H, W)` metres, colour `(H, W, 3)` uint8 RGB (None:
    grey), `T_world_camera` `(4, 4)` camera-to-world, intrinsics (see `as_intrinsics`). Wrong units, shapes and
    non-rigid poses are UserErrors that say what to fix."""
    if frame is not None:
        if not isinstance(frame, RGBDFrame):
            raise UserError(
                f"integrate: expected an RGBDFrame (or depth=..., T_world_camera=... arrays), got {type(frame).__name__}"
            )
        checked_pose(frame.T_world_camera, frame.name)
        return frame
    if depth is None or T_world_camera is None or intrinsics is None:
        raise UserError("integrate: give a frame, or depth=, T_world_camera= and intrinsics=")
    name = name or f"frame-{index:06d}"
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise UserError(f"{name}: depth must be an (H, W) image, got shape {depth.shape}")
    if not np.issubdtype(depth.dtype, np.floating):
        raise UserError(f"{name}: depth is {depth.dtype}; give float metres (e.g. a ScanNet uint16 PNG / 1000.0)")
    depth = depth.astype(np.float32)
    if np.any(depth < 0):
        raise UserError(f"{name}: depth has negative values ({int(np.sum(depth < 0))} pixels); give metres, 0 = no reading")
    valid = depth[np.isfinite(depth) & (depth > 0)]
    if valid.size and np.median(valid) > 50.0:
        raise UserError(f"{name}: median depth {np.median(valid):.0f}: depth must be in metres, not millimetres")
    if valid.size < 0.01 * depth.size:
        log.warning("%s: only %d of %d depth pixels are valid: the frame adds almost nothing", name, valid.size, depth.size)
    depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
    height, width = depth.shape
    if color is None:
        color = np.full((height, width, 3), 128, np.uint8)
    color = np.asarray(color)
    if color.shape != (height, width, 3) or color.dtype != np.uint8:
        raise UserError(f"{name}: colour must be ({height}, {width}, 3) uint8 RGB, got {color.shape} {color.dtype}")
    pose = checked_pose(T_world_camera, name)
    return RGBDFrame(
        index=index, name=name, color=color, depth=depth, T_world_camera=pose, intrinsics=as_intrinsics(intrinsics, height, width)
    )


def check_detections(frame_name: str, detections: FrameDetections) -> None:
    """The file reader's rules for detections given in Python: scores in [0, 1] (a UserError), and a warning when
    they are another frame's (their `frame_name` differs from `frame_name`)."""
    for k, labels in enumerate(detections.labels):
        for label, score in labels.items():
            problem = score_problem(label, score)
            if problem is not None:
                raise UserError(f"{frame_name}: detection {k}: {problem}")
    if detections.frame_name and detections.frame_name != frame_name:
        log.warning("%s: fusing the detections of %s (another frame's?)", frame_name, detections.frame_name)


def checked_pose(T_world_camera, name: str) -> np.ndarray:
    """float64 `(4, 4)` camera-to-world pose; one that is not (`types.pose_problem`) is a UserError naming frame
    `name` (a NaN pose would otherwise size the map from NaN block coordinates)."""
    problem = pose_problem(T_world_camera)
    if problem is not None:
        raise UserError(f"{name}: T_world_camera: {problem}")
    return np.asarray(T_world_camera, np.float64)


@dataclasses.dataclass(frozen=True)
class PreparedFrame:
    """A frame (and its detections) with the host work that needs only the config done ahead (`Mapper.prepare`):
    its `frame_block_extent`, which the growth check needs before the frame's step, the detections packed, and they
    and the frame's arrays sent to the device. `fmfusion run` prepares the next frames in its reader threads, so that
    this work overlaps the fusion of the frame before."""

    frame: RGBDFrame
    block_extent: tuple[int, np.ndarray, np.ndarray]
    #: `_extent_parameters` of the config the extent was counted with (a map with others counts again)
    extent_parameters: tuple
    detections: FrameDetections | None = None
    #: `detections` packed (`HostAdapter.detections`) at the config's pixel stride (None without detections)
    batch: DetectionBatch | None = None
    #: the frame as engine arrays (`HostAdapter.frame`), put on the device with `batch` (None: made at `integrate`)
    inputs: step.FrameInputs | None = None
