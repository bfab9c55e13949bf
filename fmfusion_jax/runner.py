"""A whole run: scene + detection source -> fused map -> output files (and a score when GT exists).

Shared by `fmfusion run`, `fmfusion demo` and the experiments; the loop itself is `pipeline.py`.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.errors import UserError
from fmfusion_jax.io import map_outputs
from fmfusion_jax.io.scene import Scene
from fmfusion_jax.labels import load_label_sets
from fmfusion_jax.map_file import MAP_STATE_FILE, save_map
from fmfusion_jax.pipeline import DetectionSource, FusionResult, extract_map_instances
from fmfusion_jax.viz import overview

log = logging.getLogger(__name__)


def fuse_scene(scene: Scene, detection_source: DetectionSource, config: PipelineConfig,
               progress: bool = True) -> FusionResult:
    """Fuses every frame of `scene` through a `Mapper` whose block index covers the scene's bounds
    (estimated from its poses and depth); detections are read only for the frames the schedule fuses."""
    from fmfusion_jax.mapper import Mapper

    mapper = Mapper(config, bounds=scene.bounds())

    def fuse(update=None) -> FusionResult:
        for frame in scene.frames():
            detections = detection_source(frame) if mapper.detection_due(frame.T_world_camera) else None
            mapper.integrate(frame, detections)
            if update:
                update(1)
        return mapper.finalize()

    if not progress:
        return fuse()
    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm

    # Log lines (with -v) go above the bar instead of into it.
    with logging_redirect_tqdm(), tqdm(total=len(scene), desc=f"fusing {scene.name}", unit="frame",
                                       dynamic_ncols=True) as bar:
        return fuse(bar.update)


def ground_truth_mesh_path(scene: Scene) -> Path | None:
    path = scene.path / f"{scene.name}_vh_clean_2.ply"
    return path if path.is_file() else None


def write_outputs(result: FusionResult, scene: Scene, out_dir: Path, save_state: bool = True) -> dict:
    """Writes every output of a run into `out_dir`; returns the run summary (also saved as run.json).

    Outputs: config.yaml, instances.json, semantic.ply, instances.ply, instances/*.ply, mesh.ply,
    map_state.npz (the map, for `load_map`; unless `save_state` is False), overview.png, run.json, and
    with ground truth the benchmark prediction files, report.json and the error analysis explain.md,
    explain.json, explain.png.
    """
    from fmfusion_jax.engine import extraction

    label_sets = load_label_sets()
    out_dir.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name] = round(now - clock, 3)
        clock = now

    (out_dir / "config.yaml").write_text(result.config.to_yaml())
    instances = extract_map_instances(result, label_sets)
    lap("extract_instances")
    map_outputs.write_instances_json(out_dir / "instances.json", instances, label_sets)
    map_outputs.write_instance_clouds(out_dir, instances, label_sets)
    lap("write_instances")
    vertices, faces, colors = extraction.extract_mesh(result.state, result.map_config)
    map_outputs.write_mesh(out_dir / "mesh.ply", vertices, faces, colors)
    lap("mesh")
    if save_state:
        save_map(out_dir / MAP_STATE_FILE, result)
        lap("map_state")

    summary: dict[str, Any] = {
        "scene": scene.name, "frames": result.frames_integrated, "detection_frames": result.detection_frames,
        "instances": len(instances), "counters": result.counters, "timings_ms": result.timings.summary(),
        "map": result.map_config.describe(), "capacity_used": capacity_used(result),
    }
    gt = load_ground_truth(scene)
    if isinstance(gt, str):
        summary["benchmark"] = {"error": gt}
        gt = None
    elif gt is not None:
        summary["benchmark"] = _export_and_score(instances, gt, scene, result, out_dir, label_sets)
        lap("benchmark")
    _write_overview(out_dir / "overview.png", scene.name, instances, (vertices, faces, colors), gt, result,
                    summary.get("benchmark", {}), label_sets)
    lap("overview")
    summary["export_seconds"] = timings
    (out_dir / "run.json").write_text(json.dumps(summary, indent=1, default=float))
    log.info("outputs of %s written into %s (seconds: %s)", scene.name, out_dir, timings)
    return summary


def capacity_used(result: FusionResult) -> dict[str, int]:
    """How full the fixed capacities got (to size tsdf.block_capacity and instances.capacity)."""
    blocks, table = result.state.blocks, result.state.instances
    return {"blocks": int(blocks.num_blocks), "block_capacity": result.map_config.block_capacity,
            "dropped_blocks": int(blocks.dropped_blocks), "touched_overflow": int(blocks.touched_overflow),
            "instances_live": int(table.valid.sum()), "instance_capacity": result.map_config.instance_capacity,
            "table_overflow": int(table.overflow)}


def load_ground_truth(scene: Scene):
    """The scene's ground truth; None without a GT mesh; the error text when GT files are incomplete."""
    from fmfusion_jax.errors import DataError
    from fmfusion_jax.io.ground_truth import load_scannet_ground_truth

    if ground_truth_mesh_path(scene) is None:
        return None
    try:
        return load_scannet_ground_truth(scene.path)
    except DataError as error:
        log.warning("no benchmark export: %s", error)
        return str(error)


def _write_overview(path: Path, scene_name: str, instances, mesh, gt, result: FusionResult, benchmark: dict,
                    label_sets) -> None:
    vertices, faces, colors = mesh
    panels = [overview.map_overview_panel(instances, label_sets, vertices, colors, faces,
                                             result.map_config.voxel_size)]
    if gt is not None:
        panels.append(overview.ground_truth_overview_panel(gt.vertices, gt.faces, gt.vertex_colors, gt.nyu40_ids,
                                                              gt.instance_ids, label_sets))
    title = f"{scene_name}: {result.frames_integrated} frames"
    if "mAP" in benchmark:
        title += (f"  |  AP {benchmark['mAP']:.3f}   AP50 {benchmark['mAP50']:.3f}   "
                  f"AP25 {benchmark['mAP25']:.3f}")
    try:
        overview.write_overview(path, panels, label_sets, title)
    except OSError as error:
        log.warning("no overview: %s", error)


def score_instances(instances, gt, scene_name: str, config: PipelineConfig, label_sets, gt_ids=None):
    """`(predictions, BenchmarkResult)`: the ScanNet benchmark predictions of `instances` over the scene's
    mesh vertices (transfer radius `config.export.transfer_radius`), and their score on this scene alone.

    Args:
      gt: the scene's `SceneGroundTruth`.
      gt_ids: `gt.benchmark_ids()` when the caller already has it (computed here otherwise).
    """
    from fmfusion_jax.evaluation.scannet_benchmark import evaluate_scenes

    predictions = map_outputs.benchmark_predictions(instances, label_sets, gt.vertices, config.export.transfer_radius,
                                                    config.export.structure_claims_vertices,
                                                    config.export.transfer_neighbours)
    gt_ids = gt.benchmark_ids() if gt_ids is None else gt_ids
    return predictions, evaluate_scenes([(gt_ids, predictions)], scene_names=[scene_name])


def _export_and_score(instances, gt, scene: Scene, result: FusionResult, out_dir: Path, label_sets) -> dict:
    """Benchmark prediction files over the scene's mesh vertices, and the score against its GT."""
    from fmfusion_jax.io.benchmark_format import write_benchmark_predictions

    gt_ids = gt.benchmark_ids()
    predictions, score = score_instances(instances, gt, scene.name, result.config, label_sets, gt_ids=gt_ids)
    txt = write_benchmark_predictions(out_dir / "benchmark", scene.name, predictions)
    report = score.to_json_dict()
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    return {"predictions": str(txt), "mAP": score.mAP, "mAP50": score.mAP50, "mAP25": score.mAP25,
            "table": score.to_table(), "explain": _explain(gt, gt_ids, predictions, scene.name, out_dir)}


def _explain(gt, gt_ids, predictions, scene_name: str, out_dir: Path) -> dict:
    """The error analysis beside report.json (explain.md, explain.json, explain.png); its counts for run.json.

    It reads the predictions already scored; it does not run the benchmark again.
    """
    from fmfusion_jax.evaluation.explain import explain_scene, write_explanation

    start = time.perf_counter()
    explanation = explain_scene(gt_ids, predictions, gt.vertices, scene_name=scene_name)
    write_explanation(out_dir, explanation, gt_ids, predictions, gt.vertices, gt.faces)
    return {"objects": explanation.status_counts(), "predictions": explanation.kind_counts(),
            "seconds": round(time.perf_counter() - start, 3)}


def prepare_output_dir(out_dir: str | Path) -> Path:
    """Creates the output folder up front (before minutes of fusion); a path that cannot be one is a
    UserError."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"--out {out_dir} is a file, not a folder")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise UserError(f"cannot create the output folder {out_dir}: {error.strerror or error}") from None
    return out_dir


def run_and_export(scene: Scene, detection_source: DetectionSource, config: PipelineConfig, out_dir: Path,
                   progress: bool = True) -> str:
    """`fmfusion run`: fuse, write, and return a short human-readable summary."""
    start = time.perf_counter()
    out_dir = prepare_output_dir(out_dir)
    result = fuse_scene(scene, detection_source, config, progress=progress)
    try:
        summary = write_outputs(result, scene, out_dir)
    except OSError as error:
        raise UserError(f"cannot write the outputs into {out_dir}: {error}") from None
    return summarize_run(summary, result, time.perf_counter() - start, out_dir)


def summarize_run(summary: dict, result: FusionResult, seconds: float, out_dir: Path) -> str:
    """The lines `fmfusion run` / `fmfusion demo` print at the end: AP table, counts, timings, outputs."""
    lines = [f"{summary['scene']}: {summary['frames']} frames, {summary['detection_frames']} with detections, "
             f"{summary['instances']} instances "
             f"(created {result.counters['created']}, merged {result.counters['merged']}, "
             f"removed {result.counters['removed']}) in {seconds:.1f} s"]
    timings = result.timings.summary()
    stage = "fusion" if "fusion" in timings else "tsdf"
    if stage in timings:
        frames_per_s = summary["frames"] / max(seconds, 1e-9)
        lines.append(f"{'fusion' if stage == 'fusion' else 'integration'} step: median "
                     f"{timings[stage]['median_ms']:.1f} ms/frame (first call incl. compile "
                     f"{timings[stage]['first_call_ms'] / 1e3:.1f} s); {frames_per_s:.1f} frames/s overall")
    if result.detection_frames == 0:
        lines.append("warning: no frame had detections, so the map has no instances: check the detections folder")
    benchmark = summary.get("benchmark", {})
    if "table" in benchmark:
        lines.insert(0, benchmark["table"])
    elif "error" in benchmark:
        lines.append(f"not scored: {benchmark['error']}")
    lines.append(f"outputs in {out_dir}: overview.png, instances.json, semantic.ply, instances.ply, mesh.ply, "
                 f"{MAP_STATE_FILE}, run.json"
                 + (", report.json, explain.md/.json/.png" if "table" in benchmark else ""))
    return "\n".join(lines)
