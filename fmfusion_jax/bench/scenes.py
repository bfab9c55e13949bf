"""The benchmark's scenes: the real ScanNet scene and generated rooms, each with simulated detections.

Detections are simulated once into a cache folder (`simulation.simulate.simulate_scene`, the noise
model of `fmfusion simulate`) and reused while the request fits what is there (a marker file records
what was made). Every pipeline of the benchmark reads the same frames and the same detection files.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
from pathlib import Path

log = logging.getLogger(__name__)

#: Marker file of a prepared scene in the cache (what was made, to decide whether it can be reused).
MARKER = "bench-scene.json"
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
        values = {k: (Path(v) if k in paths else v) for k, v in data.items()}
        if values.get("room_size") is not None:
            values["room_size"] = tuple(values["room_size"])
        return cls(**values)


def _read_marker(folder: Path) -> dict | None:
    try:
        return json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        return None


def prepare_real_scene(scene_dir: Path, cache_dir: Path, max_frames: int | None, seed: int = 0,
                       progress: bool = True) -> BenchScene:
    """The real scene's first `max_frames` frames (None: all) with simulated detections on every frame.

    The detections go into `cache_dir/<scene>` and are reused when a previous run simulated at least
    as many frames with the same seed.
    """
    from fmfusion_jax.config import load_config
    from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
    from fmfusion_jax.io.scene import open_scene
    from fmfusion_jax.simulation.noise import NoiseModel
    from fmfusion_jax.simulation.simulate import simulate_scene

    overrides = [f"dataset.max_frames={max_frames}"] if max_frames else []
    config = load_config(REAL_SCENE_CONFIG, overrides)
    dataset = config.dataset
    scene = open_scene(scene_dir, layout=dataset.layout, stride=dataset.frame_stride, depth_max=dataset.depth_max,
                       depth_scale=dataset.depth_scale, max_frames=dataset.max_frames)
    folder = cache_dir / scene.name
    detections_dir = folder / "detections"
    wanted = {"scene": str(Path(scene_dir).resolve()), "seed": seed, "noise": "default"}
    marker = _read_marker(folder)
    if not (marker and {k: marker.get(k) for k in wanted} == wanted and marker.get("frames", 0) >= len(scene)):
        log.info("simulating detections for %d frames of %s into %s (once; cached)", len(scene), scene.name,
                    detections_dir)
        (folder / MARKER).unlink(missing_ok=True)
        folder.mkdir(parents=True, exist_ok=True)
        gt = load_scannet_ground_truth(scene.path)
        simulate_scene(scene, gt, detections_dir, NoiseModel.preset("default", seed=seed), every=1,
                       progress=progress)
        (folder / MARKER).write_text(json.dumps({**wanted, "frames": len(scene)}, indent=1) + "\n")
    config_path = folder / f"config-{len(scene)}.yaml"
    config_path.write_text(config.to_yaml())
    return BenchScene(scene.name, "real", Path(scene_dir), detections_dir, config_path, len(scene))


def prepare_generated_scene(cache_dir: Path, objects: int, frames: int, width: int, height: int, seed: int = 0,
                            progress: bool = True) -> BenchScene:
    """A generated room with `objects` objects (its size grows with them, `procedural.default_room_size`),
    `frames` frames of `width x height` along a loop around it, and simulated detections on every frame.

    Fused with the demo's config for these sizes (`demo.demo_config`), detections on every frame.
    Everything lives in `cache_dir/synth-o<objects>-f<frames>-<W>x<H>-s<seed>` and is reused when there.
    """
    from fmfusion_jax.config import load_config
    from fmfusion_jax.demo import demo_config, demo_noise, scene_name
    from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
    from fmfusion_jax.io.scene import open_scene
    from fmfusion_jax.simulation.procedural import generate_scene
    from fmfusion_jax.simulation.scannet_writer import write_scannet_scene
    from fmfusion_jax.simulation.simulate import simulate_scene

    folder = cache_dir / f"synth-o{objects}-f{frames}-{width}x{height}-s{seed}"
    scene_dir, detections_dir, config_path = folder / scene_name(seed), folder / "detections", folder / "config.yaml"
    marker = _read_marker(folder)
    if marker is None:
        if folder.exists():
            shutil.rmtree(folder)  # an interrupted preparation
        log.info("generating a room with %d objects, %d frames of %dx%d into %s (once; cached)", objects, frames,
                    width, height, folder)
        room = generate_scene(seed, num_objects=objects)
        config = demo_config(frames, width, height, ["detections.every=1"], room_size=room.room_size)
        write_scannet_scene(room, scene_dir, num_frames=frames, width=width, height=height, seed=seed,
                            progress=progress)
        dataset = config.dataset
        opened = open_scene(scene_dir, layout=dataset.layout, stride=dataset.frame_stride,
                            depth_max=dataset.depth_max, depth_scale=dataset.depth_scale)
        simulate_scene(opened, load_scannet_ground_truth(scene_dir), detections_dir, demo_noise(seed, width, height),
                       every=1, progress=progress)
        config_path.write_text(config.to_yaml())
        marker = {"objects": objects, "frames": frames, "width": width, "height": height, "seed": seed,
                  "room_size": [float(x) for x in room.room_size]}
        (folder / MARKER).write_text(json.dumps(marker, indent=1) + "\n")
    load_config(str(config_path))  # a damaged cache fails here, naming the file
    return BenchScene(folder.name, "generated", scene_dir, detections_dir, config_path, frames, objects,
                      tuple(marker["room_size"]))
