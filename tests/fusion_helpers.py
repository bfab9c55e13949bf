"""Small drivers of the mapping package that only tests use (a whole sequence through a `MapBuilder`, a saved
map's parts, the blocks a frame touches)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.mapping.builder import FusionResult, MapBuilder
from fmfusion_jax.mapping.capacity import _distinct_blocks, _sample_block_coordinates
from fmfusion_jax.mapping.inputs import DetectionSource
from fmfusion_jax.mapping.map_file import read_map_file
from fmfusion_jax.mapping.schedule import scheduled_detections
from fmfusion_jax.types import RGBDFrame


def fuse_sequence(
    frames: Iterable[RGBDFrame],
    detection_source: DetectionSource,
    builder: MapBuilder,
    progress: Callable[[int], None] | None = None,
) -> FusionResult:
    """Runs the loop over `frames` and returns the finalized map."""
    for frame, detections in scheduled_detections(frames, detection_source, builder.config):
        builder.add_frame(frame, detections)
        if progress:
            progress(1)
    return builder.result()


def load_map(path: str | Path):
    """`(MapState, MapConfig, PipelineConfig)` of a saved map."""
    saved = read_map_file(path)
    return saved.state, saved.map_config, saved.config


def resume_builder(path: str | Path) -> MapBuilder:
    """A `MapBuilder` that continues the map saved at `path`, its counts of frames, detection frames and
    counters restored (the refinement schedules count detection frames)."""
    saved = read_map_file(path)
    builder = MapBuilder(saved.config, saved.map_config, state=saved.state)
    builder.progress.restore(saved.progress)
    return builder


def frame_block_keys(frame: RGBDFrame, map_config: MapConfig) -> np.ndarray:
    """int64 `(N, 3)`: the distinct blocks (world lattice, origin 0) that the engine's block finder would
    touch for this frame, from the same strided depth samples over `[d - trunc, d + trunc]`."""
    return _distinct_blocks(_sample_block_coordinates(frame, map_config))
