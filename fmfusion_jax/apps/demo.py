"""`fmfusion demo`: the whole job on data made on the spot, with nothing to download.

1. a procedural room (`simulation.procedural`, seeded) is rendered along a loop around it and written in
   the ScanNet layout with its ground truth (`simulation.scannet_writer`) into OUT/synth<seed>_00;
2. foundation-model detections are simulated from its ground truth with the noise model of
   `fmfusion simulate` (`simulation.simulate.simulate_scene`, authors' file format) into OUT/detections;
3. the scene is fused with `configs/demo.yaml` (`run.scene_fusion.fuse_scene`), the map written into OUT (the outputs
   of `fmfusion run`: overview.png, instances.json, PLY files, map_state.npz, ...) and scored against the
   scene's own ground truth.

Everything is deterministic for a seed. `run_demo` takes the sizes as arguments, so tests run a tiny demo
through the same code.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from fmfusion_jax.config import detection_frame_stride
from fmfusion_jax.errors import UserError
from fmfusion_jax.io.detections import DetectionFolder
from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
from fmfusion_jax.io.scene import open_dataset_scene
from fmfusion_jax.simulation.demo_setup import (
    DEFAULT_FRAMES,
    DEFAULT_HEIGHT,
    DEFAULT_OBJECTS,
    DEFAULT_WIDTH,
    demo_config,
    demo_noise,
)

if TYPE_CHECKING:  # pragma: no cover
    from fmfusion_jax.mapping.builder import FusionResult

log = logging.getLogger(__name__)

DEFAULT_OUT = Path("outputs/demo")
#: Marker file of a demo output folder: a folder holding it may be emptied and written again.
MARKER = "demo.json"
DETECTIONS_DIR = "detections"


def scene_name(seed: int) -> str:
    """The generated scene's folder and name, ScanNet-style: ``synth0000_00`` for seed 0."""
    return f"synth{seed:04d}_00"


@dataclasses.dataclass
class DemoResult:
    """What `run_demo` made."""

    out_dir: Path
    scene_dir: Path
    detections_dir: Path
    summary: dict  # the run summary (run.json)
    text: str  # what `fmfusion demo` prints
    seconds: dict[str, float]  # wall time of each stage
    fusion: FusionResult  # the fused map


def _prepare(out_dir: Path) -> None:
    """Makes `out_dir`; a previous demo's folder (it holds `demo.json`) is emptied first; any other
    non-empty folder is refused, so the demo never deletes a user's files."""
    from fmfusion_jax.run.folder import prepare_output_dir

    prepare_output_dir(out_dir)
    entries = list(out_dir.iterdir())
    if not entries:
        return
    if not (out_dir / MARKER).is_file():
        raise UserError(
            f"{out_dir} is not empty and is not a previous demo's output (no {MARKER}): choose a new or empty folder with --out"
        )
    for path in entries:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()


def run_demo(
    out_dir: str | Path = DEFAULT_OUT,
    seed: int = 0,
    num_objects: int = DEFAULT_OBJECTS,
    num_frames: int = DEFAULT_FRAMES,
    stacked: int = 0,
    width: int = DEFAULT_WIDTH,
    height: int = DEFAULT_HEIGHT,
    overrides: Sequence[str] = (),
    progress: bool = True,
    depth_noise: bool = True,
) -> DemoResult:
    """Generates a scene and its detections, fuses, writes and scores the map (see the module docstring).

    Args:
      out_dir: output folder (created; a previous demo's output there is replaced).
      seed: seed of the room, the camera path, the sensor noise and the simulated detections.
      num_objects: objects in the room (besides walls, floor, ceiling).
      num_frames: frames on the loop around the room.
      stacked: small objects (lamps, boxes, baskets) standing on the tables, desks, counters and low cabinets,
        besides `num_objects` (`generate_scene(stacked=...)`; a room with `on` relations for the scene graph).
      width, height: image size.
      overrides: `section.key=value` config overrides (applied last).
      progress: tqdm progress bars.
      depth_noise: simulate depth-sensor noise.
    """
    from fmfusion_jax.simulation.procedural import generate_scene  # lazy: `fmfusion --help` imports this module
    from fmfusion_jax.simulation.scannet_writer import write_scannet_scene  # lazy: `fmfusion --help` imports this module
    from fmfusion_jax.simulation.simulate import simulate_scene  # lazy: `fmfusion --help` imports this module

    if num_frames < 2 or num_objects < 1 or stacked < 0 or width < 32 or height < 24:
        raise UserError(
            f"demo needs at least 2 frames, 1 object and 32x24 pixels (got {num_frames} frames, "
            f"{num_objects} objects, {width}x{height})"
        )
    demo_config(num_frames, width, height, overrides)  # bad overrides fail before anything is written
    out_dir = Path(out_dir)
    _prepare(out_dir)
    from fmfusion_jax.run.command import summarize_run, write_outputs  # lazy: JAX (`fmfusion --help` imports this module)
    from fmfusion_jax.run.scene_fusion import fuse_scene  # lazy: JAX (`fmfusion --help` imports this module)

    seconds: dict[str, float] = {}
    start = clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        seconds[name] = round(now - clock, 2)
        clock = now

    record = {
        "seed": seed,
        "objects": num_objects,
        "stacked": stacked,
        "frames": num_frames,
        "width": width,
        "height": height,
        "overrides": list(overrides),
    }
    (out_dir / MARKER).write_text(json.dumps(record, indent=1) + "\n")
    try:
        scene = generate_scene(seed, num_objects=num_objects, stacked=stacked)
    except ValueError as error:
        raise UserError(f"cannot generate the room: {error}") from None
    log.info("demo room: %s", scene.summary())
    config = demo_config(num_frames, width, height, overrides, room_size=scene.room_size)
    scene_dir = write_scannet_scene(
        scene,
        out_dir / scene_name(seed),
        num_frames=num_frames,
        width=width,
        height=height,
        seed=seed,
        depth_noise=depth_noise,
        progress=progress,
    )
    lap("generate_scene")
    log.info("demo scene written into %s (%.1f s)", scene_dir, seconds["generate_scene"])

    dataset = config.dataset
    opened = open_dataset_scene(scene_dir, dataset)
    gt = load_scannet_ground_truth(scene_dir)
    noise = demo_noise(seed, width, height)
    detections_dir = out_dir / DETECTIONS_DIR
    simulate_scene(
        opened, gt, detections_dir, noise, every=detection_frame_stride(config) * dataset.frame_stride, progress=progress
    )
    lap("simulate_detections")
    log.info("detections simulated into %s (%.1f s)", detections_dir, seconds["simulate_detections"])

    folder = DetectionFolder(detections_dir, image_shape=(opened.intrinsics.height, opened.intrinsics.width))
    result = fuse_scene(opened, folder, config, progress=progress)
    lap("fuse")
    summary = write_outputs(result, opened, out_dir)
    lap("write_and_score")
    seconds["total"] = round(time.perf_counter() - start, 2)
    record.update(room=scene.summary(), seconds=seconds, scene=str(scene_dir), detections=str(detections_dir))
    (out_dir / MARKER).write_text(json.dumps(record, indent=1) + "\n")

    lines = summarize_run(summary, result, seconds["total"], out_dir).split("\n")
    stages = ", ".join(f"{name.replace('_', ' ')} {value:.1f} s" for name, value in seconds.items() if name != "total")
    lines[-1:-1] = [
        f"demo room: {scene.summary()}",
        f"demo: {seconds['total']:.1f} s in all ({stages})",
        f"scene (ScanNet layout, with ground truth) in {scene_dir}, simulated detections in {detections_dir}",
    ]
    lines.append(f"look first at {out_dir / 'overview.png'}")
    text = "\n".join(lines)
    return DemoResult(out_dir, scene_dir, detections_dir, summary, text, seconds, result)
