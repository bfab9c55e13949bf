"""A whole run: scene + detection source -> fused map -> output files (and a score when ground truth exists),
and its closing summary. Shared by `fmfusion run`, `fmfusion demo`, `fmfusion batch` and the experiments.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import time
from collections.abc import Callable, Collection, Sequence
from pathlib import Path

from fmfusion_jax import host_memory
from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.engine.saved_steps import clear_executables
from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
from fmfusion_jax.io.scene import Scene
from fmfusion_jax.labels import load_label_sets
from fmfusion_jax.mapping.builder import FusionResult
from fmfusion_jax.mapping.inputs import DetectionSource
from fmfusion_jax.run import outputs
from fmfusion_jax.run.checkpoint import Checkpoint
from fmfusion_jax.run.folder import OutputLock, clear_outputs, partial_dir, prepare_output_dir, replace_folder
from fmfusion_jax.run.outputs import MAP_STATE_FILE
from fmfusion_jax.run.outputs import capacity_used as capacity_used  # re-exported: experiments, likelihood, examples
from fmfusion_jax.run.outputs import score_instances as score_instances
from fmfusion_jax.run.scene_fusion import SceneFusion, progress_bar

log = logging.getLogger(__name__)


def ground_truth_mesh_path(scene: Scene) -> Path | None:
    path = scene.path / f"{scene.name}_vh_clean_2.ply"
    return path if path.is_file() else None


def write_outputs(
    result: FusionResult,
    scene: Scene,
    out_dir: Path,
    save_state: bool = True,
    skipped: list[tuple[str, str]] | None = None,
    detection_ms: dict[str, float] | None = None,
    frame_seconds: Sequence[float] = (),
    names: Collection[str] | None = None,
) -> dict:
    """Writes the outputs of a run into `out_dir` (the writers of `run.outputs.OUTPUT_WRITERS`, all or those
    in `names`; map_state.npz unless `save_state` is False); returns the run summary (also saved as run.json).

    `detection_ms`: the models' mean ms per detected frame, when a run detected online; `frame_seconds`: each
    frame's wall time as run (`SceneFusion.frame_seconds`), summarized in run.json.
    """
    label_sets = load_label_sets()
    out_dir.mkdir(parents=True, exist_ok=True)
    clear_outputs(out_dir)
    gt = load_ground_truth(scene)
    ground_truth = None if isinstance(gt, str) else gt
    context = outputs.OutputContext(
        scene,
        out_dir,
        result.config,
        label_sets,
        result=result,
        ground_truth=ground_truth,
        ground_truth_error=gt if isinstance(gt, str) else None,
        floor=None if ground_truth is None else result.floor(),
        skipped=scene.skipped if skipped is None else skipped,
        detection_ms=detection_ms,
        frame_seconds=frame_seconds,
    )
    selected = [w.name for w in outputs.select_writers(names) if save_state or w.name != MAP_STATE_FILE]
    outputs.write_files(context, selected)  # the instances are extracted there, beside the mesh and the map file
    if not context.map_instances and result.detection_frames:  # a run without detections holds geometry only
        log.warning(
            "%s: the map has no instance: instances.json lists none, semantic.ply and instances.ply are empty", scene.name
        )
    log.info("outputs of %s written into %s (seconds: %s)", scene.name, out_dir, context.timings)
    return context.summary if context.summary is not None else outputs.run_summary(context)


def load_ground_truth(scene: Scene):
    """The scene's ground truth; None without a GT mesh; the error text when GT files are incomplete."""

    if ground_truth_mesh_path(scene) is None:
        return None
    try:
        return load_scannet_ground_truth(scene.path)
    except DataError as error:
        log.warning("no benchmark export: %s", error)
        return str(error)


@dataclasses.dataclass
class RunOutcome:
    """What `run_and_export` did: `summary` (the lines to print), `complete` (False: interrupted, the map so far
    and a checkpoint are in `folder`), `folder` (where the outputs are)."""

    summary: str
    complete: bool
    folder: Path


def run_and_export(
    scene: Scene,
    detection_source: DetectionSource,
    config: PipelineConfig,
    out_dir: Path,
    progress: bool = True,
    *,
    on_error: str = "skip",
    checkpoint_every: int = 0,
    resume: bool = False,
    restart: bool = False,
    should_stop: Callable[[], bool] | None = None,
    time_stages: bool = False,
    observer: Callable[..., None] | None = None,
    outputs_chosen: Collection[str] | None = None,
    last_in_process: bool = False,
) -> RunOutcome:
    """`fmfusion run`: fuse, write, and summarize.

    The outputs are built in `OUT.partial` and renamed to `OUT` when complete, replacing an earlier run's
    folder as a whole (never mixing two runs). When `should_stop()` turns true, fusion stops between frames:
    a checkpoint and the outputs of what was fused are written into `OUT.partial`, and `resume=True` later
    continues from the checkpoint (the map equals an uninterrupted run's). `checkpoint_every` frames also
    writes one. An unfinished `OUT.partial` is continued (`resume`) or discarded (`restart`), never silently.
    `outputs_chosen`: the writers to run (`run.outputs.chosen_outputs`; None: all). `last_in_process`: no other
    map is fused in this process afterwards (`fmfusion run`), so the compiled steps are dropped before the outputs
    are written (they hold ~100 MiB; another run would load them from the compile cache again).
    """
    start = time.perf_counter()
    out_dir = prepare_output_dir(out_dir, create=False)
    outputs.preload_writer_modules()  # beside the compile and the reading, off the outputs' critical path
    with OutputLock(out_dir):
        staging = partial_dir(out_dir)
        checkpoint = Checkpoint(staging, checkpoint_every)
        if staging.exists() and not resume:
            if checkpoint.exists() and not restart:
                info = checkpoint.info()
                raise UserError(
                    f"{staging} holds an unfinished run (checkpoint at frame {info.get('position')} of "
                    f"{info.get('frames')}): add --resume to continue it, or --restart to discard it"
                )
            shutil.rmtree(staging)  # a run that failed before its first checkpoint: nothing to keep
        fusion = SceneFusion(
            scene,
            detection_source,
            config,
            on_error=on_error,
            checkpoint=checkpoint,
            resume=resume,
            time_stages=time_stages,
            observer=observer,
        )
        staging.mkdir(parents=True, exist_ok=True)
        with progress_bar(len(scene), f"fusing {scene.name}", progress) as update:
            complete = fusion.run(update, should_stop)
        if observer is not None and hasattr(observer, "close"):
            observer.close(fusion.mapper)
        if not complete:
            log.warning("interrupted at frame %d of %d: writing the map so far into %s", fusion.position, len(scene), staging)
        result = fusion.finalize()  # trims the C heap (`Mapper.finalize`)
        if last_in_process:
            clear_executables()
            host_memory.trim_heap()  # the compiled steps just dropped, before the outputs' temporaries
        try:
            timings_ms = getattr(detection_source, "timings_ms", None)
            detection_ms = timings_ms() if callable(timings_ms) else None
            summary = write_outputs(
                result,
                scene,
                staging,
                skipped=fusion.skipped,
                detection_ms=detection_ms,
                frame_seconds=fusion.frame_seconds,
                names=outputs_chosen,
            )
            if complete:
                checkpoint.remove()
                replace_folder(staging, out_dir)
        except OSError as error:
            raise UserError(f"cannot write the outputs into {staging}: {error}") from None
        folder = out_dir if complete else staging
        geometry_only = bool(getattr(detection_source, "geometry_only", False))
        text = summarize_run(summary, result, time.perf_counter() - start, folder, geometry_only=geometry_only)
        return RunOutcome(text, complete, folder)


def summarize_run(summary: dict, result: FusionResult, seconds: float, out_dir: Path, geometry_only: bool = False) -> str:
    """The lines `fmfusion run` / `fmfusion demo` print at the end: AP table, counts, timings, outputs
    (`geometry_only`: the run had no detection source, so no instance is expected)."""
    lines = [
        f"{summary['scene']}: {summary['frames']} frames, {summary['detection_frames']} with detections, "
        f"{summary['instances']} instances "
        f"(created {result.counters['created']}, merged {result.counters['merged']}, "
        f"removed {result.counters['removed']}) in {seconds:.1f} s"
    ]
    timings = result.timings.summary()
    stage = "fusion" if "fusion" in timings else "tsdf"
    frames_per_s = summary["frames"] / max(seconds, 1e-9)
    if stage in timings:
        lines.append(
            f"{'fusion' if stage == 'fusion' else 'integration'} step: median "
            f"{timings[stage]['median_ms']:.1f} ms/frame (first call incl. compile "
            f"{timings[stage]['first_call_ms'] / 1e3:.1f} s); {frames_per_s:.1f} frames/s overall"
        )
    else:
        lines.append(f"{frames_per_s:.1f} frames/s overall, reading and writing included (-v times each engine step)")
    models_ms = summary.get("detection_ms_per_frame")
    if models_ms:
        parts = ", ".join(f"{name} {ms:.0f}" for name, ms in models_ms.items() if name != "front_end")
        lines.append(f"models: {models_ms['front_end']:.0f} ms per detected frame ({parts})")
    skipped = summary.get("skipped_frames", [])
    if skipped:
        lines.append(
            f"warning: {len(skipped)} frames skipped or partly skipped for bad input (listed in run.json; "
            f"first: {skipped[0]['frame']}: {skipped[0]['reason']})"
        )
    if geometry_only:
        lines.append("geometry only: no detection source was given (--detections or --models), so the map has no instance")
    elif result.detection_frames == 0:
        lines.append("warning: no frame had detections, so the map has no instances: check the detections folder")
    benchmark = summary.get("benchmark", {})
    if "table" in benchmark:
        lines.insert(0, benchmark["table"])
    elif "error" in benchmark:
        lines.append(f"not scored: {benchmark['error']}")
    if summary["instances"] == 0 and result.detection_frames:
        lines.append("warning: the map has no instance although detections were fused")
    written = outputs.listed_outputs(out_dir)
    lines.append(f"outputs in {out_dir}: {', '.join(written)}")
    return "\n".join(lines)
