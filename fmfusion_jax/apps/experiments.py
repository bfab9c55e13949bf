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
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from fmfusion_jax.comparison.methods import (
    METHODS,
    Method,
    RunOutcome,
    check_config,
    copy_run,
    resolve_methods,
    run_method,
    score_methods,
)
from fmfusion_jax.comparison.scenes import (
    given_detections,
    prepare_source,
    scene_sources,
)
from fmfusion_jax.comparison.tables import fraction, markdown_table, percent, scene_kind, stderr_report
from fmfusion_jax.errors import UserError
from fmfusion_jax.io.scene import sample_scene_dir
from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec

log = logging.getLogger(__name__)

DEFAULT_OUT = Path("outputs/experiment")
#: Default generated scenes: seeds 1..3, the demo's room and sequence.
DEFAULT_GENERATED = 3
DEFAULT_GENERATED_FRAMES = 120
DEFAULT_GENERATED_OBJECTS = 12
#: `--quick`: one tiny generated room, real scenes cut to a few frames.
QUICK_GENERATED = dict(count=1, num_frames=30, num_objects=5, width=320, height=240)
QUICK_REAL_FRAMES = 20


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


# --------------------------------------------------------------------------------------------------
# Running.


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
    report = report or (stderr_report if progress else log.info)
    # Bad overrides fail now, not after an hour of runs (generated scenes: checked without their room size).
    for method in chosen:
        for kind in sorted({s.kind for s in sources}):
            check_config(kind, sources, list(overrides) + list(method.overrides), real_max_frames)
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
                f"mAP50 {fraction(summary['score']['mAP50'])}, mAP25 {fraction(summary['score']['mAP25'])}"
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


# --------------------------------------------------------------------------------------------------
# Tables.


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
        rows.append([method.title, *(percent(ap50[c]) for c in classes), percent(results[method.name].mAP50)])
    return markdown_table(["Method", *CLASS_ABBREVIATIONS.values(), "mAP50"], rows)


def table_two(methods: Sequence[Method], results: dict) -> str:
    """Table II's layout: rows the methods with their prompt augmentation, likelihood and refinement, then
    mAP, mAP50 and mAP25 (%)."""
    rows = [
        [
            m.title,
            m.prompt_augmentation,
            m.likelihood,
            m.refine,
            percent(results[m.name].mAP),
            percent(results[m.name].mAP50),
            percent(results[m.name].mAP25),
        ]
        for m in methods
    ]
    return markdown_table(["Method", "Prm. Aug.", "Likelihood", "Refine", "mAP", "mAP50", "mAP25"], rows)


def per_scene_table(methods: Sequence[Method], per_scene: dict) -> str:
    """mAP50 (%) of each method (rows) on each scene alone (columns)."""
    scenes = list(per_scene)
    rows = [[m.title, *(percent(per_scene[s][m.name].mAP50) for s in scenes)] for m in methods]
    return markdown_table(["Method", *scenes], rows)


def paper_tables() -> str:
    """The paper's figures (real RAM-Grounded-SAM detections, 30 ScanNet validation scans), for reference."""
    one = markdown_table(
        ["Method", *CLASS_ABBREVIATIONS.values(), "mAP50"],
        [[row, *(f"{v:.1f}" for v in values)] for row, values in PAPER_TABLE_ONE.items()],
    )
    two = markdown_table(
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
        what = scene_kind(s)
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
