"""The mapping loop above the engine: frames and detections in, the jitted steps on their schedules, a map out.

By concern: `inputs` (a user's frames, intrinsics, detections and config coerced and checked, once; the packing
for the engine), `engine_configs` (the schema's values into the engine's configs), `schedule` (which frames
are detection frames), `capacity` (sizes ahead of the frames, growth, capacity warnings), `telemetry`
(stage timings, small device-to-host copies), `builder` (`MapBuilder`: one map, frame by frame), `mapper`
(`Mapper`, the map object of notebooks and robot loops), `batch` (`MapperBatch`: maps in lock step),
`export` (the instances out of a fused map) and `map_file` (`.npz` map files).
"""

from fmfusion_jax.mapping.batch import MapperBatch
from fmfusion_jax.mapping.builder import FusionProgress, FusionResult, MapBuilder
from fmfusion_jax.mapping.export import extract_map_instances
from fmfusion_jax.mapping.inputs import DetectionSource, PreparedFrame, as_config, as_frame, as_intrinsics
from fmfusion_jax.mapping.mapper import Mapper
from fmfusion_jax.mapping.schedule import DetectionSchedule

__all__ = [
    "DetectionSchedule",
    "DetectionSource",
    "FusionProgress",
    "FusionResult",
    "MapBuilder",
    "Mapper",
    "MapperBatch",
    "PreparedFrame",
    "as_config",
    "as_frame",
    "as_intrinsics",
    "extract_map_instances",
]
