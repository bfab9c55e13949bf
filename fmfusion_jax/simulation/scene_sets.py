"""Sets of scenes with simulated detections, made once and reused (experiments, calibration, benchmarks).

A *prepared scene* is a scene folder in the ScanNet layout with its ground truth, plus a folder of
simulated detections for it. Generated scenes (`generated_scene`) and simulated detections
(`simulated_detections`) are cached: each folder records the parameters that made it, and is made again
only when they differ, so a second experiment over the same scenes starts at once.

    root/synth0003_00/                 generated scene (seed 3), `synthesis.json` records its parameters
    root/detections/synth0003_00-default-s0/   its detections, `simulation.json` records the noise model
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
from pathlib import Path

import numpy as np

from fmfusion_jax.errors import UserError
from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
from fmfusion_jax.io.scene import open_scene
from fmfusion_jax.simulation.noise import NoiseModel
from fmfusion_jax.simulation.procedural import generate_scene

log = logging.getLogger(__name__)

#: Written into a generated scene folder once it is complete (a half-written folder has none).
_SCENE_RECORD = "scene_set.json"


@dataclasses.dataclass(frozen=True)
class GeneratedSceneSpec:
    """What defines a generated scene: the room's seed and size, and the recorded sequence."""

    seed: int
    num_objects: int = 12
    num_frames: int = 120
    width: int = 640
    height: int = 480
    stacked: int = 0  # small objects on tables, desks, counters and cabinets (`generate_scene(stacked=...)`)

    @property
    def name(self) -> str:
        """ScanNet-style name, ``synth0003_00`` for seed 3."""
        return f"synth{self.seed:04d}_00"


@dataclasses.dataclass(frozen=True)
class PreparedScene:
    """A scene folder (ScanNet layout, with ground truth) and a folder of detections for it."""

    name: str
    scene_dir: Path
    detections_dir: Path


def generated_scene(spec: GeneratedSceneSpec, root: str | Path, progress: bool = False) -> Path:
    """The folder of the generated scene `spec` under `root`, rendered unless already there."""
    from fmfusion_jax.simulation.scannet_writer import write_scannet_scene  # lazy: `fmfusion --help` imports this module

    scene_dir = Path(root) / spec.name
    record = dataclasses.asdict(spec)
    if not spec.stacked:  # the record of a scene rendered before the option: its cache stays valid
        del record["stacked"]
    if _read_record(scene_dir / _SCENE_RECORD) == record:
        return scene_dir
    if scene_dir.exists():
        shutil.rmtree(scene_dir)  # made with other parameters, or interrupted
    try:
        scene = generate_scene(spec.seed, num_objects=spec.num_objects, stacked=spec.stacked)
    except ValueError as error:
        raise UserError(f"cannot generate {spec.name}: {error}") from None
    log.info("rendering %s: %s", spec.name, scene.summary())
    write_scannet_scene(
        scene, scene_dir, num_frames=spec.num_frames, width=spec.width, height=spec.height, seed=spec.seed, progress=progress
    )
    (scene_dir / _SCENE_RECORD).write_text(json.dumps(record, indent=1) + "\n")
    return scene_dir


def simulated_detections(
    scene_dir: str | Path, out_dir: str | Path, noise: NoiseModel, every: int = 1, progress: bool = False, likelihood=None
) -> Path:
    """Detections simulated for the scene in `out_dir` with `noise`, unless the folder already holds them.

    Args:
      scene_dir: a ScanNet-layout scene with ground truth (a real or a generated one).
      out_dir: the detections folder.
      noise: the noise model (its seed included).
      every: simulate the frames whose index is a multiple of this (the fusion's detection frames).
      likelihood: float[O, C] likelihood the labels are drawn from (default: the statistical one); a
        custom one is never taken from the cache.
    """
    from fmfusion_jax.simulation.simulate import simulate_scene  # lazy: `fmfusion --help` imports this module

    out_dir = Path(out_dir)
    scene = open_scene(scene_dir)
    expected = int(np.count_nonzero(np.asarray(scene.frame_indices) % every == 0))
    done = _read_record(out_dir / "simulation.json")
    if (
        likelihood is None
        and done
        and done.get("noise") == noise.to_dict()
        and done.get("every") == every
        and done.get("likelihood") == "statistical"
        and len(done.get("frames", ())) == expected
    ):
        return out_dir
    gt = load_scannet_ground_truth(scene.path)
    simulate_scene(scene, gt, out_dir, noise, every=every, progress=progress, likelihood=likelihood)
    return out_dir


def prepare_generated(
    spec: GeneratedSceneSpec, root: str | Path, noise: NoiseModel, every: int = 1, tag: str = "default", progress: bool = False
) -> PreparedScene:
    """A generated scene and its simulated detections (`tag` names the detection variant in the folder)."""
    scene_dir = generated_scene(spec, root, progress)
    detections_dir = Path(root) / "detections" / f"{spec.name}-{tag}-s{noise.seed}"
    simulated_detections(scene_dir, detections_dir, noise, every, progress)
    return PreparedScene(spec.name, scene_dir, detections_dir)


def prepare_real(
    scene_dir: str | Path, root: str | Path, noise: NoiseModel, every: int = 1, tag: str = "default", progress: bool = False
) -> PreparedScene:
    """A real scene (read in place, never copied) and its simulated detections under `root`."""
    scene_dir = Path(scene_dir)
    if not scene_dir.is_dir():
        raise UserError(f"{scene_dir}: scene folder not found")
    detections_dir = Path(root) / "detections" / f"{scene_dir.name}-{tag}-s{noise.seed}"
    simulated_detections(scene_dir, detections_dir, noise, every, progress)
    return PreparedScene(scene_dir.name, scene_dir, detections_dir)


def _read_record(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None
