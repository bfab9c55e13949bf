"""Frame-to-model tracking (KinectFusion): each depth frame is tracked against the raycast of a TSDF of the frames
tracked so far, then fused into it, in one jitted step.

The model is a voxel-block pool of the map's kind (`state.VoxelBlocks`, integrated by `tsdf.integrate_tsdf`, the
global TSDF's own kernel) at the tracking resolution, with its own `MapConfig` (the host's `mapping.tracking`
makes it: a cube around the first camera). Per frame (`track_and_fuse`):

1. the frame's vertex/normal pyramid (`tracking.frame_maps`) is tracked by projective point-to-plane ICP
   (`tracking.track_frame`) against the reference: the model raycast from the last good pose, in that camera's
   frame, so the result is `T_reference_current` exactly as in frame-to-frame tracking;
2. unless the frame is lost, its depth is integrated at its pose `T_world_reference @ T_reference_current`;
   a lost frame leaves the model and the pose as they were (its depth is integrated as empty) and casts no
   reference (the last good one stays);
3. the model is raycast from the new pose (`raycast.raycast_tsdf`, depth only) and its depth's vertex/normal
   pyramid made as a frame's (`tracking.frame_maps`): the next frame's reference.

Pass the pool donated (the step does: `donate_argnums=0`), so XLA updates it in place.

Shapes: `(H, W)` the tracked image (= `map_config.image_height, image_width`), intrinsics float32 `(4,)` of it,
poses float32 `(4, 4)`.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from fmfusion_jax.engine import _geometry as geo
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.raycast import raycast_tsdf_unjitted
from fmfusion_jax.engine.state import VoxelBlocks
from fmfusion_jax.engine.tracking import (
    FrameMaps,
    TrackingConfig,
    TrackResult,
    frame_maps,
    icp_level,
    level_intrinsics,
    track_frame,
)
from fmfusion_jax.engine.tsdf import integrate_tsdf_unjitted


class ModelStep(NamedTuple):
    """What one frame-to-model step returns."""

    blocks: VoxelBlocks  # the model with the frame fused (unchanged but for counters where lost)
    reference: FrameMaps  # the model raycast from `T_world_camera`: the next frame's reference (empty where lost:
    # the last good one stays the reference, as `mapping.tracking.Tracker` keeps it)
    result: TrackResult  # the ICP's estimate against the old reference and its failure signal
    T_world_camera: jax.Array  # float32[4, 4]: the frame's pose (the reference's where lost)


def _fuse_and_raycast(blocks, depth, T_world_camera, intrinsics, config: TrackingConfig, map_config: MapConfig):
    blocks = integrate_tsdf_unjitted(blocks, depth, None, T_world_camera, intrinsics, map_config)  # geometry only
    level = icp_level(depth.shape[1], config)  # cast at the ICP's resolution
    depth, intrinsics = depth[:: 1 << level, :: 1 << level], level_intrinsics(intrinsics, level)
    h, w = depth.shape
    # guided by the depth just fused (`TrackingConfig.raycast_guided`), a ray looks for the model's surface near
    # it only and the rays without depth are not cast: a few samples a ray instead of a march from depth_min (a
    # lost frame fuses nothing, so nothing is cast: its reference is not used)
    guide = depth if config.raycast_guided else None
    cast = raycast_tsdf_unjitted(blocks, T_world_camera, intrinsics, map_config, h, w, config.raycast_steps, False, guide, False)
    # the reference's vertices and normals from the raycast depth as a frame's own (`frame_maps`): with the TSDF
    # gradient's normals the ICP slid along the walls of two noisy generated walks (92 and 141 mm ATE; 4.7 and 6.5 mm
    # with these), and the raycast skips six trilinear samples a ray
    # the cast depth computed once (`_geometry.materialize`): `frame_maps` reads each pixel several times, and XLA's CPU
    # fusion would redo the raycast's tail for every read (3.5 of 12 ms a frame at 160 x 120)
    return blocks, frame_maps(geo.materialize(cast.depth), intrinsics, config, bilateral=False)


def empty_reference(height: int, width: int, config: TrackingConfig, with_color: bool = False) -> FrameMaps:
    """A reference with no valid pixel, of `frame_maps`' shapes for the model's raycast of an `(height, width)` frame
    (at `icp_level`; with an intensity pyramid of zeros when `with_color`)."""
    first = icp_level(width, config)
    shapes = [(-(-height // (1 << level)), -(-width // (1 << level))) for level in range(first, first + config.levels)]
    zeros = tuple(jnp.zeros((h, w, 3), jnp.float32) for h, w in shapes)
    intensity = tuple(jnp.zeros(shape, jnp.float32) for shape in shapes) if with_color else ()
    return FrameMaps(zeros, zeros, tuple(jnp.zeros(shape, bool) for shape in shapes), intensity)


def start_model(
    blocks: VoxelBlocks, depth, T_world_camera, intrinsics, config: TrackingConfig, map_config: MapConfig, color=None
) -> tuple[VoxelBlocks, FrameMaps]:
    """The first frame fused at its given pose, and the model raycast from there (the reference of the second).

    `track_and_fuse`'s own executable with `first` set (a cold start compiles one step, not two: 3 s less at
    320 x 240 on the 2-core CPU).

    Args:
      blocks: an empty pool of `map_config` (donated).
      depth: float32 `(H, W)` metres, 0 where invalid.
      T_world_camera: float32 `(4, 4)`; intrinsics: float32 `(4,)`.
      color: uint8 `(H, W, 3)` RGB registered to the depth, or None (then every later frame has none either).
    """
    height, width = depth.shape
    reference = empty_reference(height, width, config, with_color=color is not None)
    step = track_and_fuse(blocks, reference, depth, intrinsics, T_world_camera, config, map_config, jnp.bool_(True), color)
    return step.blocks, step.reference


@functools.partial(jax.jit, static_argnames=("config", "map_config"), donate_argnums=0)
def track_and_fuse(
    blocks: VoxelBlocks,
    reference: FrameMaps,
    depth,
    intrinsics,
    T_world_reference,
    config: TrackingConfig,
    map_config: MapConfig,
    first=False,
    color=None,
) -> ModelStep:
    """One frame tracked against the model's raycast `reference` (seen from `T_world_reference`), then fused.

    Args:
      blocks: the model (donated).
      reference: `frame_maps` of the model's raycast depth from `T_world_reference` (the last step's `reference`).
      depth: float32 `(H, W)` metres of the frame, 0 where invalid.
      intrinsics: float32 `(4,)`; T_world_reference: float32 `(4, 4)`.
      first: bool `()` (traced: the same executable either way): the frame is fused at `T_world_reference` itself
        whatever the ICP found (`start_model`; its `result` is then meaningless).
      color: uint8 `(H, W, 3)` RGB of the frame, or None: with colour, the ICP adds the photometric term against the
        reference's intensity (the last good frame's: the model holds no colour) and the next reference gets this
        frame's (`TrackingConfig.color_weight`).
    """
    depth = jnp.asarray(depth, jnp.float32)
    T_world_reference = jnp.asarray(T_world_reference, jnp.float32)
    first = jnp.asarray(first, bool)
    level = icp_level(depth.shape[1], config)
    current = frame_maps(depth, intrinsics, config, color, first_level=level)
    result = track_frame(reference, current, intrinsics, jnp.eye(4, dtype=jnp.float32), config, reference_level=level)
    T_world_camera = jnp.where(result.lost | first, T_world_reference, T_world_reference @ result.T_reference_current)
    fused = jnp.where(result.lost & ~first, 0.0, depth)  # a lost frame adds nothing to the model
    blocks, reference = _fuse_and_raycast(blocks, fused, T_world_camera, intrinsics, config, map_config)
    # the raycast is seen from this frame's pose, so this frame's image is its intensity
    return ModelStep(blocks, reference._replace(intensity=current.intensity), result, T_world_camera)


__all__ = ["ModelStep", "empty_reference", "start_model", "track_and_fuse"]
