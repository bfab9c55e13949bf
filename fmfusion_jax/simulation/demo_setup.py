"""The demo's setup, shared by the apps that fuse generated rooms (`fmfusion demo`, `experiment`, `likelihood`,
`bench`): the config scaled to the frame count, image size and room, and the default noise scaled to the image."""

from __future__ import annotations

from collections.abc import Sequence

from fmfusion_jax.config import PipelineConfig, load_config
from fmfusion_jax.simulation.noise import NoiseModel
from fmfusion_jax.simulation.procedural import DEFAULT_ROOM

#: Defaults of the demo (the values `configs/demo.yaml` is written for).
DEFAULT_FRAMES = 120
DEFAULT_WIDTH, DEFAULT_HEIGHT = 640, 480


DEFAULT_OBJECTS = 12


def _surface_area(room_size: Sequence[float]) -> float:
    w, d, h = room_size
    return 2 * w * d + 2 * (w + d) * h


def demo_config(
    num_frames: int = DEFAULT_FRAMES,
    width: int = DEFAULT_WIDTH,
    height: int = DEFAULT_HEIGHT,
    overrides: Sequence[str] = (),
    room_size: Sequence[float] | None = None,
) -> PipelineConfig:
    """`configs/demo.yaml` for a demo of `num_frames` frames of `width x height` (`demo_overrides`), then
    `overrides` (`--set` overrides win over the scaling)."""
    return load_config("demo", demo_overrides(num_frames, width, height, room_size) + list(overrides))


def demo_overrides(
    num_frames: int = DEFAULT_FRAMES,
    width: int = DEFAULT_WIDTH,
    height: int = DEFAULT_HEIGHT,
    room_size: Sequence[float] | None = None,
) -> list[str]:
    """The `KEY=VALUE` overrides that scale `configs/demo.yaml` to `num_frames` frames of `width x height` (what
    `demo_config` applies; `fmfusion batch --config demo` takes them as `--set`).

    demo.yaml holds the values for 120 frames of 640x480. Over a longer loop consecutive frames are
    closer, so the detection stride (detections.every; refinement is counted in detection frames) grows in
    proportion to the frame count; pixel counts (detections.min_mask_pixels, association.min_projected_pixels) follow
    the image area, and so does export.min_points below 640x480 (instance voxels come from sampled
    pixels). With `room_size` (W, D, H metres), the block pool grows with the room's surface beyond the
    default room's.
    """
    config = load_config("demo")
    frames_scale = num_frames / DEFAULT_FRAMES
    area_scale = (width * height) / (DEFAULT_WIDTH * DEFAULT_HEIGHT)
    scaled = {
        "detections.every": max(1, round(config.detections.every * frames_scale)),
        "detections.min_mask_pixels": max(20, round(config.detections.min_mask_pixels * area_scale)),
        "association.min_projected_pixels": max(20, round(config.association.min_projected_pixels * area_scale)),
        # instance voxels come from sampled pixels: fewer pixels, sparser instances
        "export.min_points": max(20, round(config.export.min_points * min(area_scale, 1.0))),
    }
    if room_size is not None:
        surface_scale = max(1.0, _surface_area(room_size) / _surface_area(DEFAULT_ROOM))
        scaled["tsdf.block_capacity"] = 1024 * -(-round(config.tsdf.block_capacity * surface_scale) // 1024)
    return [f"{key}={value}" for key, value in scaled.items()]


def demo_noise(seed: int, width: int = DEFAULT_WIDTH, height: int = DEFAULT_HEIGHT):
    """The default noise model of `fmfusion simulate`, seeded, with its pixel counts scaled to the image area
    (they are meant for 640x480)."""
    return scale_noise_to_image(NoiseModel.preset("default").replace(seed=int(seed)), width, height)


def scale_noise_to_image(noise, width: int, height: int):
    """`noise` with its pixel-count parameters scaled from 640x480 to `width x height`, as `demo_noise` scales the default
    model's (generated rooms may be rendered smaller)."""
    area_scale = (width * height) / (DEFAULT_WIDTH * DEFAULT_HEIGHT)
    return noise.replace(
        min_mask_pixels=max(10, round(noise.min_mask_pixels * area_scale)),
        small_object_pixels=max(20, round(noise.small_object_pixels * area_scale)),
    )
