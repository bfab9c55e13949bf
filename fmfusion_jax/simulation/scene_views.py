"""Views of a procedural scene: a camera path through the room (`camera_trajectory`, `look_pose`) and its
rendered frames (`render_frame`: colour, depth and the instance image, ray cast by `raycast`)."""

from __future__ import annotations

import dataclasses

import numpy as np

from fmfusion_jax.simulation.procedural import ProceduralScene
from fmfusion_jax.simulation.raycast import (
    BoxArrays,
    _face_normal_table,
    _world_points,
    camera_rays,
    lambert,
    raycast_boxes,
    texture,
)
from fmfusion_jax.types import CameraIntrinsics


@dataclasses.dataclass(frozen=True)
class RenderedFrame:
    """One rendered RGB-D frame.

    Attributes:
      color: `(H, W, 3)` uint8 RGB.
      depth: `(H, W)` float32 metres (sensor model applied when asked), 0 = invalid.
      depth_exact: `(H, W)` float32 metres, the analytic z-depth (0 where no hit or beyond `max_range`).
      instance: `(H, W)` uint16 instance ids, 0 where the (possibly noisy) depth is invalid.
    """

    color: np.ndarray
    depth: np.ndarray
    depth_exact: np.ndarray
    instance: np.ndarray


def render_frame(
    scene: "ProceduralScene",
    T_world_camera: np.ndarray,
    intrinsics: CameraIntrinsics,
    rng: np.random.Generator | None = None,
    depth_noise: bool = True,
    color_noise: bool = True,
    max_range: float = 6.0,
    min_range: float = 0.3,
    grazing_cos: float = 0.1,
    dropout: float = 0.001,
    boxes: BoxArrays | None = None,
) -> RenderedFrame:
    """Renders colour, depth and the instance image of a procedural scene.

    Depth model when `depth_noise`: Gaussian axial noise of std `0.0012 + 0.0019 (z - 0.4)^2` m (Kinect-like,
    Nguyen et al. 2012), rounding to millimetres, a `dropout` fraction of random holes, no return at grazing
    incidence (|cos| between the ray and the normal below `grazing_cos`) and none nearer than `min_range`.
    Always: 0 beyond `max_range` m. Colour: albedo x texture x (ambient + Lambert point light + headlight),
    a per-frame exposure jitter and pixel noise (std 2/255) when `color_noise`.

    Args:
      scene: a `ProceduralScene`.
      T_world_camera: `(4, 4)` camera-to-world pose.
      intrinsics: the camera.
      rng: randomness of the noise (a fixed default when None).
      boxes: `scene.box_arrays()`, when the caller already has it.
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    boxes = boxes if boxes is not None else scene.box_arrays()
    T = np.asarray(T_world_camera, np.float64)
    hits = raycast_boxes(boxes, T, intrinsics, enclosure=scene.enclosure())
    hit = hits.hit & np.isfinite(hits.depth)
    shape = hits.depth.shape
    table = _face_normal_table(boxes)
    face_index = np.where(hit, hits.box * 6 + hits.face, table.shape[0] - 1).ravel()
    normal = tuple(np.ascontiguousarray(table[:, c])[face_index] for c in range(3))
    b = np.where(hit, hits.box, 0).ravel()

    xs, ys = camera_rays(intrinsics)
    z = np.where(hit, hits.depth, np.float32(0.0)).astype(np.float32)
    points, view = _world_points(T, xs, ys, z)
    points = tuple(p.ravel() for p in points)
    view = tuple(v.ravel() for v in view)

    # Colour.
    shade = lambert(normal, points, scene.light_position, view)
    shade *= texture(boxes.materials[b], b, boxes, points)
    shade[~hit.ravel()] = 0.0
    if color_noise:
        shade *= np.float32(1.0 + rng.uniform(-0.04, 0.04))
    color = boxes.colors[b] * (shade * np.float32(255.0))[:, None]
    if color_noise:  # uniform noise of std 2 (out of 255) per channel
        color += rng.random(color.shape, dtype=np.float32) * np.float32(2 * 3**0.5 * 2) - np.float32(2 * 3**0.5)
    color_u8 = np.clip(color + np.float32(0.5), 0, 255).astype(np.uint8).reshape(shape + (3,))

    # Depth.
    exact = z
    exact[exact > max_range] = 0.0
    depth = exact
    if depth_noise:
        sigma = np.float32(0.0012) + np.float32(0.0019) * (exact - np.float32(0.4)) ** 2
        depth = exact + rng.standard_normal(shape, dtype=np.float32) * sigma
        depth = np.round(depth * np.float32(1000.0)) * np.float32(0.001)
        cos = np.abs(normal[0] * view[0] + normal[1] * view[1] + normal[2] * view[2]).reshape(shape)
        invalid = (exact == 0) | (depth < min_range) | (depth > max_range) | (cos < grazing_cos)
        if dropout > 0:
            invalid |= rng.random(shape, dtype=np.float32) < dropout
        depth[invalid] = 0.0
    ids = boxes.instance_ids.astype(np.uint16)[b].reshape(shape)
    ids[(depth <= 0) | ~hit] = 0
    return RenderedFrame(
        color=color_u8, depth=depth.astype(np.float32, copy=False), depth_exact=exact.astype(np.float32, copy=False), instance=ids
    )
