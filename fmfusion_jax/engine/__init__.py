"""The engine: the map as an immutable pytree and the jitted, pure functions that update it (no I/O).

The public engine, for code that drives it directly (the mapping loop, experiments, differentiable studies):

    from fmfusion_jax import engine
    state = engine.init_map_state(map_config)
    batch = engine.pack_detections(detections, open_labels, max_detections, min_mask_pixels)
    state, statistics = engine.fuse_frame(state, inputs, batch, likelihood, map_config, fusion, merge=False, geometry=False)

`MapConfig` holds the static sizes, `FusionConfig` the thresholds (both made from the config schema by
`mapping.engine_configs`); `engine.step` has the individual jitted steps, `engine.frame` their order.
"""

from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.detections import DetectionBatch, pack_detections
from fmfusion_jax.engine.frame import finalize_maps, fuse_frame, fuse_frames
from fmfusion_jax.engine.state import InstanceTable, MapState, VoxelBlocks, init_map_state
from fmfusion_jax.engine.step import FrameInputs, FrameStats, FusionConfig, RefineStats, finalize

__all__ = [
    "DetectionBatch",
    "FrameInputs",
    "FrameStats",
    "FusionConfig",
    "InstanceTable",
    "MapConfig",
    "MapState",
    "RefineStats",
    "VoxelBlocks",
    "finalize",
    "finalize_maps",
    "fuse_frame",
    "fuse_frames",
    "init_map_state",
    "pack_detections",
]
