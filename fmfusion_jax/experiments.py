"""`fmfusion experiment`: FM-Fusion against the Kimera-style baseline, and its ablations, on a set of scenes.

The paper's Sec. V in one command. Methods (`METHODS`, rows of the tables):

    kimera      Kimera + Cluster-All on the same detections (`baselines.kimera`; Table I, "G-SAM & Kimera")
    ablation-a  A: the manual 0.9/0.1 likelihood instead of the statistical one (Table II)
    ablation-b  B: no prompt augmentation; the detections are simulated without it, so the tags the
                tagger missed stay missing (Table II)
    ablation-c  C: no instance refinement: no merge, removal or geometry fusion (Table II)
    full        FM-Fusion
    full-bayes  (not run by default) FM-Fusion with the multiplicative Bayes label update

Scenes: real scenes in the ScanNet layout (read in place, config `scannet-subsampled`) and generated rooms
(`simulation.scene_sets`, config `demo` scaled to their frames and image size as `fmfusion demo` does).
Detections are simulated from each scene's ground truth (noise preset `default`, seeded) and cached, with a
second set without prompt augmentation for ablation B. Every run exports ScanNet benchmark predictions on
the scene's mesh; each method is then scored over all scenes together (`evaluate_scenes` pools them per
class, as the benchmark does over a validation set).

Outputs, under OUT:

    experiment.md          Table I (AP50 per class) and Table II (mAP, mAP50, mAP25), per-scene mAP50, the
                           paper's figures for reference
    experiment.json        every number (pooled and per scene), scenes, seed, noise models, configs, timings
    runs/<scene>/<method>/ run.json, config.yaml, instances.json, benchmark/<scene>.txt + pred_mask/
    cache/                 (default --cache) generated scenes and simulated detections, reused next time

Everything is deterministic for a seed (timings aside).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fmfusion_jax.config import PipelineConfig, detection_frame_stride, load_config
from fmfusion_jax.errors import UserError
from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, PreparedScene

if TYPE_CHECKING:
    from fmfusion_jax.baselines.kimera import KimeraResult
    from fmfusion_jax.evaluation.scannet_benchmark import BenchmarkResult
    from fmfusion_jax.io.benchmark_format import InstancePredictions
    from fmfusion_jax.io.ground_truth import SceneGroundTruth
    from fmfusion_jax.io.scene import Scene
    from fmfusion_jax.mapping.builder import FusionResult

log = logging.getLogger(__name__)

DEFAULT_OUT = Path("outputs/experiment")
#: Config of real scenes: the default a user gets without --config (its detection schedule finds that a scene
#: like ../shared/data/scannet/scene0000_00 is subsampled in time and fuses every frame).
REAL_SCENE_CONFIG = "scannet"
#: Default generated scenes: seeds 1..3, the demo's room and sequence.
DEFAULT_GENERATED = 3
DEFAULT_GENERATED_FRAMES = 120
DEFAULT_GENERATED_OBJECTS = 12
#: `--quick`: one tiny generated room, real scenes cut to a few frames.
QUICK_GENERATED = dict(count=1, num_frames=30, num_objects=5, width=320, height=240)
QUICK_REAL_FRAMES = 20
#: Detection variants: the default simulation, and the one without prompt augmentation (ablation B).
DETECTIONS_DEFAULT, DETECTIONS_NO_AUGMENTATION = "default", "noaug"
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


#: Config overrides that restore the map of v0.1 (before the robustness work): membership by hits alone, no
#: reunion of fragments, no veto of merges the detector contradicts, confidence = class probability, export of
#: any slot by the nearest point, no floor filter. (The motion schedule needs no override: the experiments' configs
#: fix the detection stride.)
PREVIOUS_MAP_OVERRIDES: tuple[str, ...] = (
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
)

METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method(
            "kimera",
            "Kimera + Cluster-All",
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

#: Table I's column titles of the 18 benchmark classes (the paper's abbreviations).
CLASS_ABBREVIATIONS = {
    "cabinet": "cab.",
    "bed": "bed",
    "chair": "cha.",
    "sofa": "sof.",
    "table": "tab.",
    "door": "door",
    "window": "win.",
    "bookshelf": "bkf.",
    "picture": "pic.",
    "counter": "cou.",
    "desk": "desk",
    "curtain": "cur.",
    "refrigerator": "ref.",
    "shower curtain": "show.",
    "toilet": "toi.",
    "sink": "sink",
    "bathtub": "bath.",
    "otherfurniture": "oth.",
}
#: The paper's Table I rows with RAM-Grounded-SAM detections (AP50 %, 30 ScanNet validation scans), the 18
#: classes in `CLASS_ABBREVIATIONS` order, then mAP50.
PAPER_TABLE_ONE = {
    "G-SAM & Kimera": (
        32.5,
        21.0,
        16.8,
        54.5,
        21.7,
        26.0,
        31.5,
        45.3,
        21.9,
        8.7,
        3.9,
        24.8,
        29.6,
        0.0,
        50.0,
        9.4,
        46.2,
        0.0,
        24.7,
    ),
    "G-SAM & Ours": (
        4.6,
        46.2,
        49.2,
        39.6,
        37.3,
        19.5,
        12.0,
        50.4,
        44.0,
        3.8,
        8.9,
        15.5,
        66.7,
        82.2,
        100.0,
        41.5,
        75.0,
        30.7,
        40.3,
    ),
}


# --------------------------------------------------------------------------------------------------
# What to run.


def resolve_methods(names: Sequence[str] | None) -> tuple[Method, ...]:
    """The `Method`s named, in `METHODS` order (the tables' row order); an unknown name is a UserError."""
    names = list(names) if names else list(DEFAULT_METHODS)
    unknown = [n for n in names if n not in METHODS]
    if unknown:
        raise UserError(f"unknown method {', '.join(repr(n) for n in unknown)}: expected some of {', '.join(METHODS)}")
    return tuple(m for m in METHODS.values() if m.name in names)


def sample_scene_dir() -> Path:
    """Where the sample ScanNet scene is expected: `$FMFUSION_SCANNET_DIR/scene0000_00`, else
    ../shared/data/scannet/scene0000_00 from the working folder (whether or not it is there)."""
    return Path(os.environ.get("FMFUSION_SCANNET_DIR", "../shared/data/scannet")) / "scene0000_00"


def default_real_scenes() -> list[Path]:
    """The sample ScanNet scene (`sample_scene_dir`) when it is there; none otherwise (logged)."""
    scene = sample_scene_dir()
    if scene.is_dir():
        return [scene]
    log.warning("no real scene: %s not found (name scenes with --scenes); running on generated scenes only", scene)
    return []


def generated_specs(
    count: int,
    num_frames: int = DEFAULT_GENERATED_FRAMES,
    num_objects: int = DEFAULT_GENERATED_OBJECTS,
    width: int = 640,
    height: int = 480,
) -> list[GeneratedSceneSpec]:
    """Generated scenes with seeds 1..count."""
    if count < 0 or num_frames < 2 or num_objects < 1:
        raise UserError(
            f"generated scenes need count >= 0, frames >= 2 and objects >= 1 (got {count}, {num_frames}, {num_objects})"
        )
    return [GeneratedSceneSpec(seed, num_objects, num_frames, width, height) for seed in range(1, count + 1)]


@dataclasses.dataclass(frozen=True)
class SceneSource:
    """One scene of the experiment: a real folder, or a generated room.

    Attributes:
      name: the scene's name (folder name).
      kind: "real" or "generated".
      path: the real scene's folder (None for a generated one until prepared).
      spec: the generated scene's parameters.
    """

    name: str
    kind: str
    path: Path | None = None
    spec: GeneratedSceneSpec | None = None

    def config(self, overrides: Sequence[str] = (), max_frames: int | None = None) -> PipelineConfig:
        """The scene's config with `overrides` (`--set`, then a method's)."""
        if self.kind == "real":
            extra = [f"dataset.max_frames={max_frames}"] if max_frames else []
            return load_config(REAL_SCENE_CONFIG, extra + list(overrides))
        from fmfusion_jax.demo import demo_config
        from fmfusion_jax.simulation.procedural import generate_scene

        spec = self.spec
        assert spec is not None  # a generated scene has its spec
        room = generate_scene(spec.seed, num_objects=spec.num_objects).room_size  # no rendering: cheap
        return demo_config(spec.num_frames, spec.width, spec.height, overrides, room_size=room)

    def noise(self, seed: int):
        """The default noise model of this scene's detections (pixel counts scaled to generated images)."""
        from fmfusion_jax.demo import demo_noise
        from fmfusion_jax.simulation.noise import NoiseModel

        if self.kind == "real":
            return NoiseModel.preset("default").replace(seed=int(seed))
        assert self.spec is not None  # a generated scene has its spec
        return demo_noise(seed, self.spec.width, self.spec.height)


def scene_sources(real_scenes: Sequence[str | Path], generated: Sequence[GeneratedSceneSpec]) -> list[SceneSource]:
    """The scenes, real first; a missing real folder, one without ground truth, or a repeated name is a
    UserError."""
    sources = []
    for path in real_scenes:
        path = Path(path)
        if not path.is_dir():
            raise UserError(f"scene folder {path} not found")
        if not (path / f"{path.name}_vh_clean_2.ply").is_file():
            raise UserError(
                f"{path} has no ground-truth mesh {path.name}_vh_clean_2.ply: the experiment scores "
                "every run against the scene's ground truth"
            )
        sources.append(SceneSource(path.name, "real", path=path))
    sources += [SceneSource(spec.name, "generated", spec=spec) for spec in generated]
    names = [s.name for s in sources]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise UserError(f"scene {', '.join(repeated)} given twice")
    if not sources:
        raise UserError("no scenes: name real scenes with --scenes or ask for generated ones with --generated N")
    return sources


# --------------------------------------------------------------------------------------------------
# Running.


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
    from fmfusion_jax.io.detections import DetectionFolder
    from fmfusion_jax.labels import load_label_sets
    from fmfusion_jax.run.outputs import OutputContext, write_files

    label_sets = load_label_sets()
    folder = DetectionFolder(detections_dir, image_shape=(scene.intrinsics.height, scene.intrinsics.width))
    if not len(folder):
        raise UserError(f"{detections_dir} holds no detections")
    source = folder
    start = time.perf_counter()
    result: KimeraResult | FusionResult
    floor = None  # the map's floor, for the transfer (FM-Fusion's maps; the baseline keeps the reference transfer)
    if method.baseline == "kimera":
        from fmfusion_jax.baselines.kimera import run_kimera

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
        from fmfusion_jax.mapping.export import extract_map_instances
        from fmfusion_jax.run.outputs import capacity_used
        from fmfusion_jax.run.scene_fusion import fuse_scene

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

    _replace_run_dir(out_dir)
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
        "benchmark_predictions": int(predictions.num_instances),
        "seconds": {"map": round(map_seconds, 2), "total": round(time.perf_counter() - start, 2)},
        **details,
        "score": score.to_json_dict(),
    }
    (out_dir / RUN_RECORD).write_text(json.dumps(summary, indent=1, default=float))
    return RunOutcome(predictions, summary, score)


def copy_run(outcome: RunOutcome, method: Method, same_as: str, src: Path, dst: Path) -> RunOutcome:
    """The outcome of an identical run (same mapper, config and detections) under another method's name."""
    _replace_run_dir(dst)
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


def _replace_run_dir(run_dir: Path) -> None:
    """Empties a run folder left by an earlier experiment (it holds run.json); refuses any other non-empty one."""
    if run_dir.is_dir() and any(run_dir.iterdir()):
        if not (run_dir / RUN_RECORD).is_file():
            raise UserError(
                f"{run_dir} is not empty and is not an experiment's run folder (no {RUN_RECORD}): choose another --out"
            )
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)


@dataclasses.dataclass
class ExperimentResult:
    """What `run_experiment` made.

    Attributes:
      out_dir: the output folder.
      methods: the methods run, in table order.
      scene_names: the scenes, in order.
      pooled: method name -> `BenchmarkResult` over all scenes.
      per_scene: scene name -> method name -> `BenchmarkResult` of that scene alone.
      markdown: the content of experiment.md.
      record: the content of experiment.json.
    """

    out_dir: Path
    methods: tuple[Method, ...]
    scene_names: tuple[str, ...]
    pooled: dict
    per_scene: dict
    markdown: str
    record: dict

    @property
    def text(self) -> str:
        """What `fmfusion experiment` prints: the two tables and where the files are."""
        return "\n".join(
            [
                table_one(self.methods, self.pooled),
                "",
                table_two(self.methods, self.pooled),
                "",
                f"AP in % over {len(self.scene_names)} scenes ({', '.join(self.scene_names)}); "
                f"written: {self.out_dir / 'experiment.md'}, {self.out_dir / 'experiment.json'}, "
                f"runs in {self.out_dir / 'runs'}",
            ]
        )


def _stderr_report(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


@dataclasses.dataclass
class PreparedSource:
    """A scene ready to run: its detection folders per variant, the opened scene and its ground truth.

    Attributes:
      source: the scene.
      detections: variant -> `scene_sets.PreparedScene` (scene folder and detections folder).
      noise: variant -> the noise model's parameters.
      scene: the opened scene (`io.scene.Scene`) with the scene's dataset settings.
      gt: its `SceneGroundTruth`.
      seconds: wall time of the preparation.
    """

    source: SceneSource
    detections: dict[str, PreparedScene]
    noise: dict[str, dict[str, Any]]
    scene: Scene
    gt: SceneGroundTruth
    seconds: float

    def record(self) -> dict:
        """The scene's entry in experiment.json."""
        source, spec = self.source, self.source.spec
        return {
            "name": source.name,
            "kind": source.kind,
            "scene_dir": str(self.scene.path),
            "frames": len(self.scene),
            "gt_vertices": int(self.gt.num_vertices),
            "spec": dataclasses.asdict(spec) if spec else None,
            "config": REAL_SCENE_CONFIG if source.kind == "real" else "demo (scaled to the scene)",
            "detections": {v: str(p.detections_dir) for v, p in self.detections.items()},
            "noise": self.noise,
        }


def prepare_source(
    source: SceneSource,
    variants: Sequence[str],
    cache_dir: Path,
    seed: int,
    base_config: PipelineConfig,
    progress: bool,
    report: Callable[[str], None],
    given: Path | None = None,
) -> PreparedSource:
    """Makes (or finds in `cache_dir`) the scene and its simulated detections of each variant, on the
    detection frames of `base_config`, then opens the scene and reads its ground truth. `given`: a folder of
    (real) detections every variant reads instead."""
    from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
    from fmfusion_jax.io.scene import open_dataset_scene
    from fmfusion_jax.simulation.scene_sets import prepare_generated, prepare_real

    start = time.perf_counter()
    every = detection_frame_stride(base_config) * base_config.dataset.frame_stride
    default_noise = source.noise(seed)
    detections, noise = {}, {}
    for variant in variants:
        variant_noise = default_noise if variant == DETECTIONS_DEFAULT else default_noise.replace(prompt_augmentation=False)
        report(
            f"preparing {source.name}: {'scene and ' if source.kind == 'generated' else ''}{variant} detections "
            f"(cached in {cache_dir})"
        )
        if given is not None:
            assert source.path is not None  # detections are given for real scenes only
            detections[variant] = PreparedScene(source.name, source.path, given)
            noise[variant] = {"detections": str(given), "simulated": False}
            continue
        if source.kind == "real":
            assert source.path is not None  # a real scene has its folder
            detections[variant] = prepare_real(source.path, cache_dir, variant_noise, every, variant, progress)
        else:
            assert source.spec is not None  # a generated scene has its spec
            detections[variant] = prepare_generated(source.spec, cache_dir, variant_noise, every, variant, progress)
        noise[variant] = variant_noise.to_dict()
    scene_dir = next(iter(detections.values())).scene_dir
    dataset = base_config.dataset
    scene = open_dataset_scene(scene_dir, dataset)
    gt = load_scannet_ground_truth(scene_dir)
    return PreparedSource(source, detections, noise, scene, gt, round(time.perf_counter() - start, 2))


def given_detections(source: SceneSource, pattern: str | None) -> Path | None:
    """The detection folder `pattern` names for a real scene (`{scene}`: its name), checked; None otherwise."""
    if pattern is None or source.kind != "real":
        return None
    folder = Path(pattern.replace("{scene}", source.name))
    if not folder.is_dir():
        raise UserError(f"--detections {pattern}: no folder {folder} for scene {source.name}")
    return folder


def run_experiment(
    out_dir: str | Path = DEFAULT_OUT,
    real_scenes: Sequence[str | Path] = (),
    generated: Sequence[GeneratedSceneSpec] = (),
    methods: Sequence[str] | None = None,
    seed: int = 0,
    cache_dir: str | Path | None = None,
    overrides: Sequence[str] = (),
    real_max_frames: int | None = None,
    progress: bool = True,
    report: Callable[[str], None] | None = None,
    real_detections: str | None = None,
) -> ExperimentResult:
    """Runs every method on every scene, scores them, and writes experiment.md / experiment.json.

    Args:
      out_dir: output folder (created; run folders of an earlier experiment there are replaced).
      real_scenes: ScanNet-layout scene folders with ground truth (read in place).
      generated: generated scenes (made, or taken from the cache).
      methods: names of `METHODS` (default `DEFAULT_METHODS`).
      seed: seed of the simulated detections.
      cache_dir: where generated scenes and simulated detections are kept (default OUT/cache).
      overrides: `section.key=value` config overrides for every method (a method's own overrides win).
      real_max_frames: use only the first frames of real scenes (smoke tests).
      progress: progress bars and one line per run (`report`, default stderr).
      report: receives the progress lines (default: stderr when `progress`, else the log).
      real_detections: detection folder of the real scenes (`{scene}` in it is each scene's name) read by every
        method instead of simulated detections; the generated rooms keep theirs.
    """
    from fmfusion_jax.run.folder import prepare_output_dir

    chosen = resolve_methods(methods)
    sources = scene_sources(real_scenes, generated)
    report = report or (_stderr_report if progress else log.info)
    # Bad overrides fail now, not after an hour of runs (generated scenes: checked without their room size).
    for method in chosen:
        for kind in sorted({s.kind for s in sources}):
            _check_config(kind, sources, list(overrides) + list(method.overrides), real_max_frames)
    out_dir = prepare_output_dir(out_dir)
    cache_dir = Path(cache_dir) if cache_dir is not None else out_dir / "cache"
    start = time.perf_counter()
    variants = sorted({m.detections for m in chosen})

    runs: dict[str, dict[str, RunOutcome]] = {}
    gt_ids, scene_records, timings = {}, [], {}
    configs: dict[str, dict[str, dict[str, Any]]] = {}
    total_runs = len(sources) * len(chosen)
    for source in sources:
        given = given_detections(source, real_detections)
        base = source.config(overrides, real_max_frames)
        ready = prepare_source(source, variants, cache_dir, seed, base, progress, report, given)
        gt_ids[source.name] = ready.gt.benchmark_ids()
        timings[source.name] = {"prepare": ready.seconds}
        runs[source.name], configs[source.name] = {}, {}
        seen: dict[tuple[str | None, str, str], str] = {}  # (baseline, detections, config) -> first method
        for method in chosen:
            config = source.config(list(overrides) + list(method.overrides), real_max_frames)
            where = f"[{sum(map(len, runs.values())) + 1}/{total_runs}] {source.name}: {method.name}"
            report(f"{where} ({method.title})")
            detections_dir = ready.detections[method.detections].detections_dir
            run_dir = out_dir / "runs" / source.name / method.name
            key = (method.baseline, str(detections_dir), config.to_yaml())
            if key in seen:  # the same mapper on the same files (given detections): the same map
                other = seen[key]
                outcome = copy_run(runs[source.name][other], method, other, run_dir.parent / other, run_dir)
            else:
                outcome = run_method(method, ready.scene, detections_dir, config, ready.gt, run_dir, progress)
                seen[key] = method.name
            summary = outcome.summary
            how = (
                f"same mapper and detection files as {seen[key]}, map copied"
                if seen[key] != method.name
                else f"done in {summary['seconds']['total']:.1f} s"
            )
            report(
                f"{where} {how}: {summary['instances']} instances, "
                f"mAP50 {_fraction(summary['score']['mAP50'])}, mAP25 {_fraction(summary['score']['mAP25'])}"
            )
            runs[source.name][method.name] = outcome
            configs[source.name][method.name] = config.to_dict()
            timings[source.name][method.name] = summary["seconds"]["total"]
        scene_records.append(ready.record())
        del ready  # the scene's ground truth and frames are not needed any more

    names = tuple(s.name for s in sources)
    pooled, per_scene = score_methods(chosen, names, gt_ids, runs)
    seconds = round(time.perf_counter() - start, 1)
    record = {
        "seed": seed,
        "overrides": list(overrides),
        "real_max_frames": real_max_frames,
        "methods": {m.name: dataclasses.asdict(m) for m in chosen},
        "scenes": scene_records,
        "results": {
            m.name: {
                "pooled": pooled[m.name].to_json_dict(),
                "per_scene": {s: per_scene[s][m.name].to_json_dict() for s in names},
            }
            for m in chosen
        },
        "configs": configs,
        "timings_s": timings,
        "total_seconds": seconds,
        "paper": {
            "table_one_ap50": {
                row: dict(zip([*CLASS_ABBREVIATIONS.values(), "mAP50"], values)) for row, values in PAPER_TABLE_ONE.items()
            },
            "table_two_map50": {m.name: m.paper_map50 for m in METHODS.values() if m.paper_map50 is not None},
        },
        "units": "AP as fractions in [0, 1] (null: no ground truth of the class); experiment.md gives them in %",
    }
    markdown = experiment_markdown(chosen, pooled, per_scene, scene_records, seed, seconds)
    (out_dir / "experiment.json").write_text(json.dumps(record, indent=1, default=float))
    (out_dir / "experiment.md").write_text(markdown)
    log.info("experiment written into %s (%.1f s)", out_dir, seconds)
    return ExperimentResult(out_dir, chosen, names, pooled, per_scene, markdown, record)


def score_methods(methods: Sequence[Method], scene_names: Sequence[str], gt_ids: dict, runs: dict) -> tuple[dict, dict]:
    """`(pooled, per_scene)`: each method scored over all scenes together (method -> `BenchmarkResult`), and
    on each scene alone (scene -> method -> `BenchmarkResult`; the score `run_method` already made, kept in
    the run's outcome).

    Args:
      gt_ids: scene -> `(V,)` benchmark ids of its mesh vertices.
      runs: scene -> method -> `RunOutcome`.
    """
    from fmfusion_jax.evaluation.scannet_benchmark import evaluate_scenes

    names = tuple(scene_names)
    pooled = {
        m.name: evaluate_scenes([(gt_ids[s], runs[s][m.name].predictions) for s in names], scene_names=names) for m in methods
    }
    per_scene = {s: {m.name: runs[s][m.name].score for m in methods} for s in names}
    return pooled, per_scene


def _check_config(kind: str, sources: Sequence[SceneSource], overrides: list[str], max_frames: int | None) -> None:
    if kind == "real":
        SceneSource("check", "real").config(overrides, max_frames)
    else:
        from fmfusion_jax.demo import demo_config

        spec = next(s.spec for s in sources if s.kind == "generated")
        assert spec is not None  # a generated scene has its spec
        demo_config(spec.num_frames, spec.width, spec.height, overrides)


# --------------------------------------------------------------------------------------------------
# Tables.


def _percent(value: float | None) -> str:
    """AP as the paper prints it (%, one decimal); "-" where the class has no ground truth."""
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{100 * value:.1f}"


def _fraction(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def _markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]], align_first_left: bool = True) -> str:
    lines = [
        "| " + " | ".join(header) + " |",
        "|" + "|".join([":---" if align_first_left else "---:"] + ["---:"] * (len(header) - 1)) + "|",
    ]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def table_one(methods: Sequence[Method], results: dict) -> str:
    """Table I's layout: rows the methods, columns AP50 (%) of the 18 benchmark classes and mAP50.

    Args:
      methods: the rows, in order.
      results: method name -> `BenchmarkResult`.
    """
    classes = list(CLASS_ABBREVIATIONS)
    rows = []
    for method in methods:
        ap50 = results[method.name].ap50
        rows.append([method.title, *(_percent(ap50[c]) for c in classes), _percent(results[method.name].mAP50)])
    return _markdown_table(["Method", *CLASS_ABBREVIATIONS.values(), "mAP50"], rows)


def table_two(methods: Sequence[Method], results: dict) -> str:
    """Table II's layout: rows the methods with their prompt augmentation, likelihood and refinement, then
    mAP, mAP50 and mAP25 (%)."""
    rows = [
        [
            m.title,
            m.prompt_augmentation,
            m.likelihood,
            m.refine,
            _percent(results[m.name].mAP),
            _percent(results[m.name].mAP50),
            _percent(results[m.name].mAP25),
        ]
        for m in methods
    ]
    return _markdown_table(["Method", "Prm. Aug.", "Likelihood", "Refine", "mAP", "mAP50", "mAP25"], rows)


def per_scene_table(methods: Sequence[Method], per_scene: dict) -> str:
    """mAP50 (%) of each method (rows) on each scene alone (columns)."""
    scenes = list(per_scene)
    rows = [[m.title, *(_percent(per_scene[s][m.name].mAP50) for s in scenes)] for m in methods]
    return _markdown_table(["Method", *scenes], rows)


def paper_tables() -> str:
    """The paper's figures (real RAM-Grounded-SAM detections, 30 ScanNet validation scans), for reference."""
    one = _markdown_table(
        ["Method", *CLASS_ABBREVIATIONS.values(), "mAP50"],
        [[row, *(f"{v:.1f}" for v in values)] for row, values in PAPER_TABLE_ONE.items()],
    )
    two = _markdown_table(
        ["Method", "Prm. Aug.", "Likelihood", "Refine", "mAP50"],
        [
            [m.title, m.prompt_augmentation, m.likelihood, m.refine, f"{m.paper_map50:.1f}"]
            for m in METHODS.values()
            if m.paper_map50 is not None
        ],
    )
    return one + "\n\n" + two


def experiment_markdown(
    methods: Sequence[Method], pooled: dict, per_scene: dict, scenes: Sequence[dict], seed: int, seconds: float
) -> str:
    """experiment.md: the two tables, per-scene mAP50, the scenes, and the paper's figures."""
    scene_lines = []
    for s in scenes:
        what = (
            "real ScanNet scene"
            if s["kind"] == "real"
            else f"generated room, seed {s['spec']['seed']}, {s['spec']['num_objects']} objects, "
            f"{s['spec']['width']}x{s['spec']['height']}"
        )
        given = next((n["detections"] for n in s["noise"].values() if n.get("simulated") is False), None)
        if given:
            what += f", detections read from `{given}` (every method the same files)"
        scene_lines.append(f"- `{s['name']}`: {what}, {s['frames']} frames, config {s['config']}")
    simulated = all(n.get("simulated", True) for s in scenes for n in s["noise"].values())
    detections = (
        "detections simulated from each scene's ground truth"
        if simulated
        else "detections as listed per scene (real scenes may read given detection files; generated rooms simulate)"
    )
    return "\n".join(
        [
            "# FM-Fusion: baseline and ablations",
            "",
            f"Scenes ({len(scenes)}); {detections} (noise preset `default`, "
            f"seed {seed}; ablation B: the same without prompt augmentation):",
            "",
            *scene_lines,
            "",
            "ScanNet 3D instance benchmark, each method scored over all scenes together (per class, then the mean "
            'over the classes with ground truth). AP in %; "-": no ground truth of the class in these scenes.',
            "",
            "## Table I: AP50 per class",
            "",
            table_one(methods, pooled),
            "",
            "## Table II: baseline and ablations",
            "",
            table_two(methods, pooled),
            "",
            "## mAP50 per scene",
            "",
            per_scene_table(methods, per_scene),
            "",
            "## The paper's figures, for reference",
            "",
            "Real RAM-Grounded-SAM detections on 30 ScanNet validation scans (Tables I and II of the paper). The "
            "numbers above come from simulated detections on a few scenes: compare the order of the methods, not "
            "the values.",
            "",
            paper_tables(),
            "",
            f"Total time: {seconds:.0f} s (per run: experiment.json, `timings_s`; they include JIT compilation).",
            "",
        ]
    )
