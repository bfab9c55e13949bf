"""A whole run: scene + detection source -> fused map -> output files (and a score when GT exists).

Shared by `fmfusion run`, `fmfusion demo` and the experiments; the loop itself is `pipeline.py`.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.io import map_outputs
from fmfusion_jax.io.scene import Scene
from fmfusion_jax.labels import load_label_sets
from fmfusion_jax.pipeline import (DetectionSource, FusionResult, MapBuilder, build_map_config,
                                   extract_map_instances, fuse_sequence)

log = logging.getLogger(__name__)


def fuse_scene(scene: Scene, detection_source: DetectionSource, config: PipelineConfig,
               progress: bool = True) -> FusionResult:
    """Fuses every frame of `scene` (bounds estimated from its poses and depth)."""
    bounds_min, bounds_max = scene.bounds()
    map_config = build_map_config(config, bounds_min, bounds_max, scene.intrinsics.height, scene.intrinsics.width)
    log.info("map: %s", map_config.describe())
    builder = MapBuilder(config, map_config)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(scene), desc=f"fusing {scene.name}", unit="frame", dynamic_ncols=True)
    try:
        return fuse_sequence(scene.frames(), detection_source, builder, progress=bar.update if bar else None)
    finally:
        if bar:
            bar.close()


def ground_truth_mesh_path(scene: Scene) -> Path | None:
    path = scene.path / f"{scene.name}_vh_clean_2.ply"
    return path if path.is_file() else None


def write_outputs(result: FusionResult, scene: Scene, out_dir: Path) -> dict:
    """Writes every output of a run into `out_dir`; returns the run summary (also saved as run.json)."""
    from fmfusion_jax.engine import extraction

    label_sets = load_label_sets()
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "config.yaml").write_text(result.config.to_yaml())
    instances = extract_map_instances(result, label_sets)
    map_outputs.write_instances_json(out_dir / "instances.json", instances, label_sets)
    map_outputs.write_instance_clouds(out_dir, instances, label_sets)
    vertices, faces, colors = extraction.extract_mesh(result.state, result.map_config)
    map_outputs.write_mesh(out_dir / "mesh.ply", vertices, faces, colors)

    summary = {
        "scene": scene.name, "frames": result.frames_integrated, "detection_frames": result.detection_frames,
        "instances": len(instances), "counters": result.counters, "timings_ms": result.timings.summary(),
        "map": result.map_config.describe(),
    }
    gt_mesh = ground_truth_mesh_path(scene)
    if gt_mesh is not None:
        summary["benchmark"] = _export_and_score(instances, scene, result, out_dir, label_sets)
    (out_dir / "run.json").write_text(json.dumps(summary, indent=1, default=float))
    return summary


def _export_and_score(instances, scene: Scene, result: FusionResult, out_dir: Path, label_sets) -> dict:
    """Benchmark prediction files over the scene's mesh vertices, and the score when GT is complete."""
    from fmfusion_jax.evaluation.scannet_benchmark import evaluate_scenes
    from fmfusion_jax.io.benchmark_format import write_benchmark_predictions
    from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
    from fmfusion_jax.errors import DataError

    try:
        gt = load_scannet_ground_truth(scene.path)
    except DataError as error:
        log.warning("no benchmark export: %s", error)
        return {"error": str(error)}
    predictions = map_outputs.benchmark_predictions(instances, label_sets, gt.vertices,
                                                    result.config.export.transfer_radius)
    txt = write_benchmark_predictions(out_dir / "benchmark", scene.name, predictions)
    score = evaluate_scenes([(gt.benchmark_ids(), predictions)], scene_names=[scene.name])
    report = score.to_json_dict()
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    return {"predictions": str(txt), "mAP": score.mAP, "mAP50": score.mAP50, "mAP25": score.mAP25,
            "table": score.to_table()}


def run_and_export(scene: Scene, detection_source: DetectionSource, config: PipelineConfig, out_dir: Path,
                   progress: bool = True) -> str:
    """`fmfusion run`: fuse, write, and return a short human-readable summary."""
    start = time.perf_counter()
    result = fuse_scene(scene, detection_source, config, progress=progress)
    summary = write_outputs(result, scene, Path(out_dir))
    fusion = result.timings.summary().get("fusion", {})
    lines = [f"{scene.name}: {summary['frames']} frames, {summary['detection_frames']} with detections, "
             f"{summary['instances']} instances "
             f"(created {result.counters['created']}, merged {result.counters['merged']}, "
             f"removed {result.counters['removed']}) in {time.perf_counter() - start:.1f} s",
             f"fusion step: median {fusion.get('median_ms', np.nan):.1f} ms/frame "
             f"(first call incl. compile {fusion.get('first_call_ms', np.nan) / 1e3:.1f} s)",
             f"outputs in {out_dir}"]
    if "table" in summary.get("benchmark", {}):
        lines.insert(0, summary["benchmark"]["table"])
    return "\n".join(lines)
