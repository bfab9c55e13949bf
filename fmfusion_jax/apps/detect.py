"""`fmfusion detect`'s work (the parser is `cli/detect.py`)."""

from __future__ import annotations

import json
import time
from pathlib import Path

from tqdm import tqdm

from detectors import build_front_end, read_manifest
from fmfusion_jax.config import load_config
from fmfusion_jax.errors import UserError
from fmfusion_jax.io.detections import label_path, write_frame_detections
from fmfusion_jax.io.scene import open_scene
from fmfusion_jax.mapping.schedule import scheduled_positions

#: What `fmfusion detect` records in its output folder: the run's settings, so that a rerun continues (skipping
#: the frames done) only when it would make the same detections.
RECORD_FILE = "detect.json"


def run_detect(
    *,
    every: int | None,
    box_threshold: float | None,
    text_threshold: float | None,
    prompt_window: int | None,
    overrides: list[str],
    config_name: str,
    scene_dir: Path,
    layout: str,
    stride: int,
    max_frames: int | None,
    models_dir: Path,
    providers: str,
    mask_format: str,
    out: Path,
    no_progress: bool,
) -> int:

    if every is not None and every < 1:
        raise UserError(f"--every must be a positive integer, got {every}")
    flags = {"box_threshold": box_threshold, "text_threshold": text_threshold, "prompt_window": prompt_window}
    overrides = list(overrides) + [f"front_end.{key}={value}" for key, value in flags.items() if value is not None]
    config = load_config(config_name, overrides)
    scene = open_scene(scene_dir, layout=layout, stride=stride, max_frames=max_frames)
    manifest_overrides = config.front_end.manifest_overrides()
    manifest = read_manifest(models_dir, manifest_overrides)
    models = build_front_end(manifest, providers=providers)
    if every is not None:
        positions, rule = list(range(0, len(scene), every)), f"every {every} of {len(scene)} read"
    else:
        positions = scheduled_positions(scene.poses(), config)
        rule = f"the {len(positions)} of {len(scene)} frames the detection schedule fuses"
    record = {
        "scene": str(scene_dir.resolve()),
        "models": str(models_dir.resolve()),
        "front_end": manifest.front_end,
        "settings": {"overrides": manifest_overrides, "stride": stride, "mask_format": mask_format},
    }
    done = _frames_done(out, record, [scene.frame_names[p] for p in positions], label_path)
    todo = [p for p in positions if scene.frame_names[p] not in done]
    if done and manifest.front_end == "grounded_sam":
        # the prompt window needs the frames before: a continued run starts the window afresh (noted)
        print(f"continuing: {len(done)} frames already in {out}; the prompt window restarts at the first new frame")
    elif done:
        print(f"continuing: {len(done)} of {len(positions)} frames already in {out}")
    out.mkdir(parents=True, exist_ok=True)
    (out / RECORD_FILE).write_text(json.dumps(record, indent=1) + "\n")
    detections_total, started = 0, time.perf_counter()
    with tqdm(todo, desc=f"detect {scene.name}", unit="frame", disable=no_progress) as bar:
        for count, position in enumerate(bar, start=1):
            name = scene.frame_names[position]
            detections = models.detect(scene.read_color(position), name)
            write_frame_detections(out, detections, mask_format=mask_format)
            detections_total += detections.num_detections
            per_model = " ".join(f"{stage} {1000 * s / count:.0f}" for stage, s in models.timings.items())
            bar.set_postfix_str(f"{detections.num_detections} det; ms/frame {per_model}")
    elapsed = time.perf_counter() - started
    frames = max(len(todo), 1)
    stages = ", ".join(f"{stage} {1000 * seconds / frames:.0f} ms" for stage, seconds in models.timings.items())
    print(f"{len(todo)} frames of {scene.name} detected ({rule}, stride {stride}) -> {detections_total} detections in {out}")
    if todo:
        print(f"per frame: {1000 * elapsed / frames:.0f} ms ({stages}); providers {', '.join(models.providers)}")
    return 0


def _frames_done(out: Path, record: dict, names: list[str], label_path) -> set[str]:
    """The frames of `names` already written to `out` by a `fmfusion detect` with the same settings; a folder
    written with other settings (or not by `fmfusion detect`) is refused rather than mixed or overwritten."""
    if not out.exists():
        return set()
    if not out.is_dir():
        raise UserError(f"--out {out} exists and is not a folder")
    record_path = out / RECORD_FILE
    if not record_path.exists():
        if any(out.iterdir()):
            raise UserError(
                f"--out {out} is a folder that `fmfusion detect` did not write (no {RECORD_FILE}): choose a new folder"
            )
        return set()
    try:
        previous = json.loads(record_path.read_text())
    except (OSError, ValueError) as error:
        raise UserError(f"{record_path}: unreadable ({error}); choose a new --out folder") from None
    if previous != record:
        changed = sorted(k for k in set(previous) | set(record) if previous.get(k) != record.get(k))
        raise UserError(
            f"--out {out} holds detections made with other settings ({', '.join(changed)} differ): choose a new folder"
        )
    return {name for name in names if label_path(out, name).exists()}
