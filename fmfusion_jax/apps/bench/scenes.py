"""The benchmark's scenes: the real ScanNet scene and generated rooms, each with simulated detections.

Rooms are generated and detections simulated once into a cache folder (`simulation.scene_sets`, the
noise model of `fmfusion simulate`), and reused while they match the request. Every pipeline of the
benchmark reads the same frames and the same detection files.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any, cast

from fmfusion_jax.config import load_config
from fmfusion_jax.io.scene import open_dataset_scene
from fmfusion_jax.simulation.demo_setup import demo_config, demo_noise
from fmfusion_jax.simulation.noise import NoiseModel

#: The real scene `fmfusion bench` runs when none is given (when present).
DEFAULT_SCENE = Path("../shared/data/scannet/scene0000_00")

#: Config the real scene is fused with (its frames are ~18 original frames apart: detections on every frame).
REAL_SCENE_CONFIG = "scannet-subsampled"


@dataclasses.dataclass(frozen=True)
class BenchScene:
    """A scene ready to benchmark: frames, detections and the config to fuse them with (all files)."""

    name: str
    kind: str  # "real" or "generated"
    scene_dir: Path
    detections_dir: Path
    config_path: Path  # PipelineConfig YAML, loadable by `config.load_config`
    frames: int  # frames to fuse (the first ones of the scene)
    objects: int | None = None  # generated rooms: objects besides walls, floor and ceiling
    room_size: tuple[float, float, float] | None = None  # generated rooms: W, D, H metres

    def to_json(self) -> dict:
        return {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_json(cls, data: dict) -> "BenchScene":
        paths = {"scene_dir", "detections_dir", "config_path"}
        values: dict[str, Any] = {k: (Path(v) if k in paths else v) for k, v in data.items()}
        if values.get("room_size") is not None:
            values["room_size"] = tuple(values["room_size"])
        return cls(**values)


def prepare_real_scene(
    scene_dir: Path, cache_dir: Path, max_frames: int | None, seed: int = 0, progress: bool = True, overrides: Sequence[str] = ()
) -> BenchScene:
    """The real scene's first `max_frames` frames (None: all), with detections simulated on every frame of
    the scene into `cache_dir/<scene>/detections` (once: any frame count reuses them)."""
    from fmfusion_jax.simulation.scene_sets import simulated_detections  # lazy: `fmfusion --help` imports this module

    config = load_config(REAL_SCENE_CONFIG, [*([f"dataset.max_frames={max_frames}"] if max_frames else []), *overrides])
    dataset = config.dataset
    scene = open_dataset_scene(scene_dir, dataset)
    folder = cache_dir / scene.name
    detections_dir = simulated_detections(
        scene_dir, folder / "detections", NoiseModel.preset("default", seed=seed), every=1, progress=progress
    )
    config_path = folder / f"config-{len(scene)}.yaml"
    config_path.write_text(config.to_yaml())
    return BenchScene(scene.name, "real", Path(scene_dir), detections_dir, config_path, len(scene))


def prepare_generated_scene(
    cache_dir: Path,
    objects: int,
    frames: int,
    width: int,
    height: int,
    seed: int = 0,
    progress: bool = True,
    overrides: Sequence[str] = (),
) -> BenchScene:
    """A generated room with `objects` objects (its size grows with them, `procedural.default_room_size`),
    `frames` frames of `width x height` along a loop around it, and simulated detections on every frame.

    Fused with the demo's config for these sizes (`demo_setup.demo_config`), detections on every frame and geometry
    fusion timed however short the run.
    Everything lives in `cache_dir/synth-o<objects>-f<frames>-<W>x<H>-s<seed>` and is reused when there.
    """
    from fmfusion_jax.simulation.scene_sets import (
        GeneratedSceneSpec,  # lazy: `fmfusion --help` imports this module
        generated_scene,  # lazy: `fmfusion --help` imports this module
        simulated_detections,  # lazy: `fmfusion --help` imports this module
    )

    folder = cache_dir / f"synth-o{objects}-f{frames}-{width}x{height}-s{seed}"
    scene_dir = generated_scene(GeneratedSceneSpec(seed, objects, frames, width, height), folder, progress)
    detections_dir = simulated_detections(
        scene_dir, folder / "detections", demo_noise(seed, width, height), every=1, progress=progress
    )
    room_size = cast(
        "tuple[float, float, float]",  # W, D, H
        tuple(float(x) for x in json.loads((scene_dir / "synthesis.json").read_text())["room_size"]),
    )
    # detections on every frame; geometry fusion timed however short the run: in runs of under 10 frames on
    # every frame, so that its compilation falls in the first frame, which the medians leave out
    geometry_fusion_every = 1 if frames < 10 else min(load_config("demo").refinement.geometry_fusion_every, frames // 2)
    config = demo_config(
        frames,
        width,
        height,
        ["detections.every=1", f"refinement.geometry_fusion_every={geometry_fusion_every}", *overrides],
        room_size=room_size,
    )
    config_path = folder / "config.yaml"
    config_path.write_text(config.to_yaml())
    return BenchScene(folder.name, "generated", scene_dir, detections_dir, config_path, frames, objects, room_size)
