"""The methods compared (`METHODS`: FM-Fusion, its ablations, the Kimera-style baseline) and one run of a method
on a prepared scene: fused, exported as benchmark predictions, scored; the scores pooled over scenes."""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from fmfusion_jax.comparison.scenes import SceneSource
from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.errors import UserError
from fmfusion_jax.evaluation.scannet_benchmark import evaluate_scenes
from fmfusion_jax.io.detections import DetectionFolder
from fmfusion_jax.labels import load_label_sets
from fmfusion_jax.simulation.demo_setup import demo_config

if TYPE_CHECKING:
    from fmfusion_jax.baselines.kimera import KimeraResult
    from fmfusion_jax.evaluation.scannet_benchmark import BenchmarkResult
    from fmfusion_jax.io.benchmark_format import InstancePredictions
    from fmfusion_jax.mapping.builder import FusionResult

from fmfusion_jax.comparison.scenes import DETECTIONS_DEFAULT, DETECTIONS_NO_AUGMENTATION

log = logging.getLogger(__name__)


#: Written into every run folder; a run folder holding it may be replaced by the next experiment.
RUN_RECORD = "run.json"


@dataclasses.dataclass(frozen=True)
class Method:
    """A row of the tables: how the scene is mapped.

    Attributes:
      name: command-line name.
      title: row title.
      overrides: `section.key=value` config overrides defining it (applied after `--set`, so they hold).
      detections: which simulated detections it reads (`DETECTIONS_DEFAULT` or `DETECTIONS_NO_AUGMENTATION`).
      baseline: "kimera" for the Kimera-style baseline, None for FM-Fusion.
      prompt_augmentation, likelihood, refine: Table II's columns.
      paper_map50: the paper's ScanNet mAP50 (%) of the corresponding row, when it has one.
    """

    name: str
    title: str
    overrides: tuple[str, ...] = ()
    detections: str = DETECTIONS_DEFAULT
    baseline: str | None = None
    prompt_augmentation: str = "yes"
    likelihood: str = "statistical"
    refine: str = "yes"
    paper_map50: float | None = None


#: Config overrides that restore the map of v0.1 (before the robustness work): matches in the reference's score
#: order, membership by hits alone, no reunion of fragments, no veto of merges the detector contradicts,
#: confidence = class probability, export of any slot by the nearest point, no floor filter, one class and one
#: mask per instance in the benchmark files. (The motion schedule needs no override: the experiments' configs fix the
#: detection stride.)
PREVIOUS_MAP_OVERRIDES: tuple[str, ...] = (
    "association.rank=score",
    "detections.floor_up_axis=none",
    "instances.contrary_vote_weight=0",
    "refinement.reunite_min_frames=0",
    "refinement.separate_min_frames=0",
    "export.support_observations=0",
    "export.existence_prior=0",
    "export.min_existence=0",
    "export.planar_thickness=0",
    "export.speck_distance=0",
    "export.min_slot_share=0",
    "export.structure_claims_vertices=false",
    "export.transfer_neighbours=1",
    "export.curtain_by_context=false",
    "export.alternative_class_probability=1",
    "export.union_confidence_factor=0",
)


METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method(
            "kimera",
            "Kimera + Cluster-All",
            # one class and one mask per instance, as the paper's baseline submits it
            ("export.alternative_class_probability=1", "export.union_confidence_factor=0"),
            baseline="kimera",
            likelihood="hard association (0.9)",
            refine="Cluster-All",
            paper_map50=24.7,
        ),
        Method(
            "ablation-a",
            "A: manual likelihood",
            ("label_fusion.likelihood=manual",),
            likelihood="manual (0.9/0.1)",
            paper_map50=35.9,
        ),
        Method(
            "ablation-b",
            "B: no prompt augmentation",
            detections=DETECTIONS_NO_AUGMENTATION,
            prompt_augmentation="no",
            paper_map50=34.1,
        ),
        Method("ablation-c", "C: no refinement", ("refinement.enabled=false",), refine="no", paper_map50=23.4),
        Method("previous", "FM-Fusion v0.1", PREVIOUS_MAP_OVERRIDES),
        Method("full", "FM-Fusion", paper_map50=40.3),
        Method("full-bayes", "FM-Fusion, Bayes update", ("label_fusion.mode=bayes",), likelihood="statistical (Bayes)"),
    )
}
#: Methods run when none are named (the paper's rows).
DEFAULT_METHODS = ("kimera", "ablation-a", "ablation-b", "ablation-c", "full")


def resolve_methods(names: Sequence[str] | None) -> tuple[Method, ...]:
    """The `Method`s named, in `METHODS` order (the tables' row order); an unknown name is a UserError."""
    names = list(names) if names else list(DEFAULT_METHODS)
    unknown = [n for n in names if n not in METHODS]
    if unknown:
        raise UserError(f"unknown method {', '.join(repr(n) for n in unknown)}: expected some of {', '.join(METHODS)}")
    return tuple(m for m in METHODS.values() if m.name in names)


@dataclasses.dataclass
class RunOutcome:
    """One (scene, method) run: its predictions on the scene's mesh, its summary (run.json) and its score on
    that scene alone."""

    predictions: InstancePredictions
    summary: dict
    score: BenchmarkResult


def run_method(
    method: Method, scene, detections_dir: Path, config: PipelineConfig, gt, out_dir: Path, progress: bool = True
) -> RunOutcome:
    """Maps an opened `scene` with `method`, exports its benchmark predictions into `out_dir`, scores them on
    this scene alone, and writes run.json, config.yaml and instances.json.

    Args:
      method: the method.
      scene: the opened scene (`io.scene.Scene`).
      detections_dir: its simulated detections (the method's variant).
      config: the full config of this run.
      gt: the scene's `SceneGroundTruth`.
      out_dir: the run's folder (replaced).
    """
    from fmfusion_jax.run.outputs import OutputContext, write_files  # lazy: JAX (`fmfusion --help` imports this module)

    label_sets = load_label_sets()
    folder = DetectionFolder(detections_dir, image_shape=(scene.intrinsics.height, scene.intrinsics.width))
    if not len(folder):
        raise UserError(f"{detections_dir} holds no detections")
    source = folder
    start = time.perf_counter()
    result: KimeraResult | FusionResult
    floor = None  # the map's floor, for the transfer (FM-Fusion's maps; the baseline keeps the reference transfer)
    if method.baseline == "kimera":
        from fmfusion_jax.baselines.kimera import run_kimera  # lazy: JAX (`fmfusion --help` imports this module)

        result = run_kimera(scene, source, config, progress=progress, label_sets=label_sets)
        instances = result.instances
        details = {
            "frames": result.frames_integrated,
            "detection_frames": result.detection_frames,
            "counters": result.counters,
            "label_seconds": result.seconds,
            "timings_ms": result.geometry.timings.summary(),
        }
    else:
        from fmfusion_jax.mapping.export import extract_map_instances  # lazy: JAX (`fmfusion --help`)
        from fmfusion_jax.run.outputs import capacity_used  # lazy: JAX (`fmfusion --help` imports this module)
        from fmfusion_jax.run.scene_fusion import fuse_scene  # lazy: JAX (`fmfusion --help` imports this module)

        result = fuse_scene(scene, source, config, progress=progress, time_stages=True)
        instances = extract_map_instances(result, label_sets)
        floor = result.floor()
        details = {
            "frames": result.frames_integrated,
            "detection_frames": result.detection_frames,
            "counters": result.counters,
            "timings_ms": result.timings.summary(),
            "capacity_used": capacity_used(result),
        }
    map_seconds = time.perf_counter() - start
    del result  # the map (up to ~1 GB for a ScanNet room) is not needed any more

    replace_run_dir(out_dir)
    written = OutputContext(scene, out_dir, config, label_sets, instances, ground_truth=gt, floor=floor)
    write_files(written, names=("config.yaml", "instances.json", "benchmark"))
    _, predictions, score = written.scored
    summary = {
        "scene": scene.name,
        "method": method.name,
        "title": method.title,
        "detections": str(detections_dir),
        "overrides": list(method.overrides),
        "instances": len(instances),
        "benchmark_predictions": int(predictions.num_predictions),
        "benchmark_instances": int(predictions.num_instances),
        "seconds": {"map": round(map_seconds, 2), "total": round(time.perf_counter() - start, 2)},
        **details,
        "score": score.to_json_dict(),
    }
    (out_dir / RUN_RECORD).write_text(json.dumps(summary, indent=1, default=float))
    return RunOutcome(predictions, summary, score)


def copy_run(outcome: RunOutcome, method: Method, same_as: str, src: Path, dst: Path) -> RunOutcome:
    """The outcome of an identical run (same mapper, config and detections) under another method's name."""
    replace_run_dir(dst)
    shutil.rmtree(dst)
    shutil.copytree(src, dst)
    summary = {
        **outcome.summary,
        "method": method.name,
        "title": method.title,
        "overrides": list(method.overrides),
        "same_run_as": same_as,
    }
    (dst / RUN_RECORD).write_text(json.dumps(summary, indent=1, default=float))
    return RunOutcome(outcome.predictions, summary, outcome.score)


def replace_run_dir(run_dir: Path) -> None:
    """Empties a run folder left by an earlier experiment (it holds run.json); refuses any other non-empty one."""
    if run_dir.is_dir() and any(run_dir.iterdir()):
        if not (run_dir / RUN_RECORD).is_file():
            raise UserError(
                f"{run_dir} is not empty and is not an experiment's run folder (no {RUN_RECORD}): choose another --out"
            )
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)


def score_methods(methods: Sequence[Method], scene_names: Sequence[str], gt_ids: dict, runs: dict) -> tuple[dict, dict]:
    """`(pooled, per_scene)`: each method scored over all scenes together (method -> `BenchmarkResult`), and
    on each scene alone (scene -> method -> `BenchmarkResult`; the score `run_method` already made, kept in
    the run's outcome).

    Args:
      gt_ids: scene -> `(V,)` benchmark ids of its mesh vertices.
      runs: scene -> method -> `RunOutcome`.
    """

    names = tuple(scene_names)
    pooled = {
        m.name: evaluate_scenes([(gt_ids[s], runs[s][m.name].predictions) for s in names], scene_names=names) for m in methods
    }
    per_scene = {s: {m.name: runs[s][m.name].score for m in methods} for s in names}
    return pooled, per_scene


def check_config(kind: str, sources: Sequence[SceneSource], overrides: list[str], max_frames: int | None) -> None:
    if kind == "real":
        SceneSource("check", "real").config(overrides, max_frames)
    else:
        spec = next(s.spec for s in sources if s.kind == "generated")
        assert spec is not None  # a generated scene has its spec
        demo_config(spec.num_frames, spec.width, spec.height, overrides)


#: Methods run when none are named (the paper's rows).
