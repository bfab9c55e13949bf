"""fmfusion-jax: instance-aware semantic mapping with open-set foundation-model detections, in JAX.

    from fmfusion_jax import Mapper
    mapper = Mapper("scannet")
    mapper.integrate(frame, detections)      # per frame: an RGBDFrame, or depth/colour/pose/intrinsics arrays
    instances = mapper.instances()           # a snapshot (class distribution, points, confidence)

See `fmfusion_jax.mapping.mapper.Mapper` and docs/api.md. The names below are imported on first use, so
`import fmfusion_jax` stays cheap.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

#: public name -> module that defines it
_EXPORTS = {
    "Mapper": "fmfusion_jax.mapping.mapper",
    "MapperBatch": "fmfusion_jax.mapping.batch",
    "PipelineConfig": "fmfusion_jax.config",
    "load_config": "fmfusion_jax.config",
    "RGBDFrame": "fmfusion_jax.types",
    "CameraIntrinsics": "fmfusion_jax.types",
    "FrameDetections": "fmfusion_jax.types",
    "MapInstance": "fmfusion_jax.instances",
    "FusionResult": "fmfusion_jax.mapping.builder",
    "open_scene": "fmfusion_jax.io.scene",
    "DetectionFolder": "fmfusion_jax.io.detections",
    "UserError": "fmfusion_jax.errors",
}

__all__ = ["__version__", *_EXPORTS]

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs
    from fmfusion_jax.config import PipelineConfig as PipelineConfig
    from fmfusion_jax.config import load_config as load_config
    from fmfusion_jax.errors import UserError as UserError
    from fmfusion_jax.instances import MapInstance as MapInstance
    from fmfusion_jax.io.detections import DetectionFolder as DetectionFolder
    from fmfusion_jax.io.scene import open_scene as open_scene
    from fmfusion_jax.mapping.batch import MapperBatch as MapperBatch
    from fmfusion_jax.mapping.builder import FusionResult as FusionResult
    from fmfusion_jax.mapping.mapper import Mapper as Mapper
    from fmfusion_jax.types import CameraIntrinsics as CameraIntrinsics
    from fmfusion_jax.types import FrameDetections as FrameDetections
    from fmfusion_jax.types import RGBDFrame as RGBDFrame


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'fmfusion_jax' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
