"""Where a run's detections come from, chosen in one place: a folder of detection files, or models run online.

Every source is a `mapping.DetectionSource`: called with a frame, it gives the frame's `FrameDetections` (or
None). `open_detection_source` is what `fmfusion run` (and so `fmfusion batch`, whose scenes each run it) calls
with its `--detections` / `--models` arguments; the demo, the experiments and the likelihood summary read
folders the simulator wrote (`fmfusion simulate`), so simulated detections reach the map through the same
`DetectionFolder`. A `Mapper` takes a source too: `mapper.integrate(frame, source)` calls it on due frames only.

    source = open_detection_source(scene, detections="outputs/sim0000")       # files
    source = open_detection_source(scene, models="../shared/models")          # models.yaml or a known layout

`fmfusion run` without `--detections` or `--models` fuses through `NoDetections`: every frame's depth and colour
into the TSDF, no instance (the geometry alone; `Mapper.load` continues such a map later, with detections).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.errors import UserError
from fmfusion_jax.io.detections import DetectionFolder
from fmfusion_jax.io.scene import Scene
from fmfusion_jax.mapping.inputs import DetectionSource
from fmfusion_jax.types import FrameDetections, RGBDFrame

log = logging.getLogger(__name__)


class ModelSource:
    """Detections made by a front end of `detectors` (`detectors.load_front_end`) on the frames it is called with.

    Not read ahead with the frames: a front end may keep state across the detection frames of a sequence
    (GroundingDINO's prompt window), so it is called on due frames only, in order. `fmfusion run` calls it in a
    detection thread of its own (`detects_ahead`), on the frames a copy of the detection schedule says are due,
    while the main thread fuses the frames before.

    Attributes:
      front_end: the models (`detectors.FrontEnd`).
      seconds: cumulative wall time of the calls.
      frames: frames detected.
    """

    reads_ahead = False
    detects_ahead = True

    def __init__(self, front_end: Any, folder: Path | None = None):
        self.front_end, self.folder = front_end, folder
        self.seconds, self.frames = 0.0, 0

    def __call__(self, frame: RGBDFrame) -> FrameDetections | None:
        start = time.perf_counter()
        detections = self.front_end.detect(frame)
        self.seconds += time.perf_counter() - start
        self.frames += 1
        return detections

    def timings_ms(self) -> dict[str, float]:
        """Mean ms per detected frame of each model, and of the whole front end."""
        frames = max(self.frames, 1)
        per_model = {name: 1000.0 * seconds / frames for name, seconds in getattr(self.front_end, "timings", {}).items()}
        return {**per_model, "front_end": 1000.0 * self.seconds / frames}

    def __repr__(self) -> str:
        return f"ModelSource({str(self.folder)!r}, frames={self.frames})"


class NoDetections:
    """The source of a run given no detections: no frame has any, so every frame is integrated into the TSDF only
    (`Mapper.integrate(frame, None)`) and the map holds geometry alone. Stateless, so read ahead with the frames."""

    reads_ahead = True
    detects_ahead = False
    geometry_only = True

    def __call__(self, frame: RGBDFrame) -> FrameDetections | None:
        return None

    def __repr__(self) -> str:
        return "NoDetections()"


def open_detection_source(
    scene: Scene,
    *,
    detections: str | Path | None = None,
    models: str | Path | None = None,
    providers: str = "cpu",
    config: PipelineConfig | None = None,
) -> DetectionSource:
    """The detection source of a run of `scene`: `detections` (a folder of detection files) or `models` (a models
    folder: `models.yaml`, or a layout `detectors` knows, see docs/detectors.md), exactly one. `config`'s
    `front_end` section tunes the models. Problems are UserErrors that say what to do."""
    if (detections is None) == (models is None):
        raise UserError("give exactly one detection source: a folder of detection files, or a models folder")
    if models is not None:
        from detectors import load_front_end  # onnxruntime: only when models are run

        overrides = config.front_end.manifest_overrides() if config is not None else None
        front_end = load_front_end(Path(models), providers=providers, overrides=overrides)
        log.info("%s: detecting with %s (%s)", scene.name, type(front_end).__name__, models)
        return ModelSource(front_end, Path(models))
    assert detections is not None
    folder_path = Path(detections)
    if not folder_path.is_dir():
        raise UserError(
            f"detections folder {folder_path} does not exist (make one with `fmfusion simulate` or `fmfusion detect`)"
        )
    folder = DetectionFolder(folder_path, image_shape=(scene.intrinsics.height, scene.intrinsics.width))
    if not len(folder):
        raise UserError(
            f"{folder_path} holds no detection files (frame-XXXXXX_label.json + mask); "
            "make them with `fmfusion simulate` or `fmfusion detect`"
        )
    if not any(name in folder for name in scene.frame_names):
        raise UserError(
            f"no detection file in {folder_path} matches a frame of {scene.name} "
            f"(first frame: {scene.frame_names[0]}, first detection: {folder.frame_names[0]})"
        )
    frames = set(scene.frame_names) | {name for name, _ in scene.skipped}
    unmatched = [name for name in folder.frame_names if name not in frames]
    if unmatched:
        log.warning(
            "%d detection files in %s match no frame of %s by name and are not used (first: %s; frames are named like %s)",
            len(unmatched),
            folder_path,
            scene.name,
            unmatched[0],
            scene.frame_names[0],
        )
    return folder


__all__ = ["ModelSource", "NoDetections", "open_detection_source"]
