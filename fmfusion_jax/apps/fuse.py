"""`fmfusion run`'s work (the parser is `cli/run.py`)."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any

from fmfusion_jax.config import load_config
from fmfusion_jax.errors import UserError
from fmfusion_jax.interrupt import StopRequest
from fmfusion_jax.io.scene import open_dataset_scene
from fmfusion_jax.mapping.inputs import DetectionSource
from fmfusion_jax.run.command import run_and_export
from fmfusion_jax.run.folder import check_output_folder, prepare_output_dir
from fmfusion_jax.run.outputs import chosen_outputs
from fmfusion_jax.sources import NoDetections, open_detection_source
from fmfusion_jax.viz.live import RerunView

log = logging.getLogger(__name__)


def run_scene(
    *,
    scene_dir: Path,
    checkpoint_every: int,
    config_name: str,
    overrides: list[str],
    out: Path,
    detections: Path | None,
    models: Path | None,
    overwrite: bool,
    providers: str,
    viewer: str | None,
    viewer_save: Path | None,
    no_progress: bool,
    on_error: str,
    resume: bool,
    restart: bool,
    verbose: Any,
    outputs: list[str] | None = None,
) -> int:

    if not scene_dir.exists():
        raise UserError(f"scene folder {scene_dir} does not exist")
    if checkpoint_every < 0:
        raise UserError(f"--checkpoint-every must be >= 0, got {checkpoint_every}")
    config = load_config(config_name, overrides)
    outputs_chosen = chosen_outputs(outputs)  # a wrong name fails now, not after the fusion
    check_output_folder(out, (scene_dir, detections, models), overwrite)
    prepare_output_dir(out, create=False)  # a bad --out fails now, not after the fusion
    scene = open_dataset_scene(scene_dir, config.dataset)
    if detections is None and models is None:
        log.warning(
            "%s: no detection source given (--detections or --models): every frame is fused into the TSDF only, so the "
            "map holds geometry alone (no instance); Mapper.load(OUT/map_state.npz) continues it later with detections",
            scene.name,
        )
        source: DetectionSource = NoDetections()
    else:
        source = open_detection_source(scene, detections=detections, models=models, providers=providers, config=config)
    observer = None
    if viewer or viewer_save:
        observer = RerunView(save=viewer_save, spawn=viewer_save is None)
    with StopRequest(
        "stopping after the frame being fused, then writing a checkpoint and the map so far (outputs "
        "already being written are finished); Ctrl-C again to exit at once"
    ) as stop:
        outcome = run_and_export(
            scene,
            source,
            config,
            out,
            progress=not no_progress,
            on_error=on_error,
            checkpoint_every=checkpoint_every,
            resume=resume,
            restart=restart,
            should_stop=stop,
            time_stages=verbose > 0,
            observer=observer,
            outputs_chosen=outputs_chosen,
            last_in_process=True,
        )
    print(outcome.summary)
    if not outcome.complete:
        print(
            f"interrupted: the map so far is in {outcome.folder}; continue with the same command plus --resume", file=sys.stderr
        )
        return stop.exit_status
    return 0
