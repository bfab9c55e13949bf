"""`fmfusion simulate`'s work (the parser is `cli/simulate.py`)."""

from __future__ import annotations

import collections
from pathlib import Path

import yaml

from fmfusion_jax.errors import UserError
from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
from fmfusion_jax.io.scene import open_scene
from fmfusion_jax.simulation.noise import NoiseModel
from fmfusion_jax.simulation.simulate import simulate_scene


def run_simulate(
    *,
    max_frames: int | None,
    noise_set: list[str],
    seed: int,
    no_prompt_augmentation: bool,
    noise_preset: str,
    scene_dir: Path,
    layout: str,
    stride: int,
    depth_max: float,
    out: Path,
    render_stride: int,
    every: int,
    mask_format: str,
    max_distance: float,
    quiet: bool,
    no_progress: bool,
) -> int:

    for name, value in (("stride", stride), ("every", every), ("render_stride", render_stride)):
        if value < 1:
            raise UserError(f"--{name.replace('_', '-')} must be >= 1, got {value}")
    if max_frames is not None and max_frames < 1:
        raise UserError(f"--max-frames must be >= 1, got {max_frames}")
    overrides = parse_overrides(noise_set)
    overrides["seed"] = seed
    if no_prompt_augmentation:
        overrides["prompt_augmentation"] = False
    noise = NoiseModel.preset(noise_preset, **overrides)

    scene = open_scene(scene_dir, layout=layout, stride=stride, depth_max=depth_max)
    if scene.layout != "scannet":
        raise UserError(f"{scene_dir}: simulation needs ScanNet instance ground truth; this is a {scene.layout} scene")
    gt = load_scannet_ground_truth(scene.path)
    summary = simulate_scene(
        scene,
        gt,
        out,
        noise,
        render_stride=render_stride,
        every=every,
        max_frames=max_frames,
        mask_format=mask_format,
        max_distance=max_distance,
        progress=not (quiet or no_progress),
    )
    if not quiet:
        frames = len(summary.frame_names)
        rate = frames / summary.seconds if summary.seconds > 0 else float("inf")
        print(f"simulated {frames} frames of {scene.name} in {summary.seconds:.1f} s ({rate:.1f} frames/s) -> {summary.out_dir}")
        print(f"detections per frame: median {summary.median_detections:g}, total {sum(summary.detections_per_frame)}")
        top = collections.Counter(summary.label_counts).most_common(12)
        print("main labels: " + ", ".join(f"{name} {count}" for name, count in top))
    return 0


def parse_overrides(items: list[str]) -> dict:
    """``["a=1", "b=true"]`` -> ``{"a": 1, "b": True}`` (values parsed as YAML)."""

    overrides = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise UserError(f"--set {item!r}: expected NAME=VALUE")
        try:
            overrides[name.strip()] = yaml.safe_load(value)
        except yaml.YAMLError as error:
            raise UserError(f"--set {item!r}: value is not valid YAML ({error})") from None
    return overrides
