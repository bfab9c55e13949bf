"""`fmfusion experiment --robustness`: every method against every noise model of the zoo.

The maps were developed against one simulator setting; this evaluation judges them on many
(`simulation.zoo`: one entry per failure family plus seeded random mixtures). For each zoo entry the
detections of every scene are simulated on every frame (the fusion's own schedule picks the frames it
uses) and cached under a name holding a hash of the full noise model, so a changed family definition is
simulated again. Each method maps each (scene, entry); per entry the runs are pooled over the scenes by
the ScanNet benchmark (as `fmfusion experiment` does). Per method the entries are then summarized: per
family, the mean over all entries, and the worst entry.

Outputs, under OUT:

    robustness.md     scores per zoo entry (AP, AP50, AP25 per method), AP50 per family with the best in
                      bold, the verdict line, precision per zoo entry (no-object share, instances per
                      object, AP50), scenes and the noise parameters of each entry
    robustness.json   every number (pooled per entry, AP50 per scene and entry, the summaries, the
                      precision counts), zoo, timings
    robustness.png    AP50 per zoo entry and method, with the mean and the worst (cv2: no matplotlib)
    runs/<scene>/<entry>/<method>/   run.json, config.yaml, instances.json, benchmark/ (as `fmfusion experiment`)
    cache/            (default --cache) generated scenes and simulated detections
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from fmfusion_jax.apps.robustness.report import (
    METRICS,
    _pct,
    family_table,
    pooled_precision,
    precision_counts,
    robustness_chart,
    robustness_markdown,
    summarize,
    summarize_precision,
    verdict,
    verdict_lines,
)
from fmfusion_jax.comparison.methods import (
    RunOutcome,
    check_config,
    copy_run,
    resolve_methods,
    run_method,
    score_methods,
)
from fmfusion_jax.comparison.scenes import (
    DETECTIONS_DEFAULT,
    DETECTIONS_NO_AUGMENTATION,
    REAL_SCENE_CONFIG,
    SceneSource,
    scene_sources,
)
from fmfusion_jax.comparison.tables import stderr_report
from fmfusion_jax.errors import UserError
from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
from fmfusion_jax.io.scene import open_dataset_scene
from fmfusion_jax.simulation.demo_setup import scale_noise_to_image
from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, generated_scene, prepare_generated, prepare_real
from fmfusion_jax.simulation.zoo import MIXED, ZooEntry, noise_zoo

if TYPE_CHECKING:
    from fmfusion_jax.io.ground_truth import SceneGroundTruth
    from fmfusion_jax.io.scene import Scene

log = logging.getLogger(__name__)

DEFAULT_OUT = Path("outputs/robustness")
#: Methods compared by default: the baseline, the map before the robustness work, and the current one.
DEFAULT_METHODS = ("kimera", "previous", "full")
#: Default generated rooms (seeds 1..2, the demo's room and sequence) and random mixtures of the zoo.
DEFAULT_GENERATED = 2
DEFAULT_MIXED = 2
#: `--quick`: one tiny generated room and one mixture.
QUICK_GENERATED = dict(count=1, num_frames=30, num_objects=5, width=320, height=240)
QUICK_MIXED = 1
#: Decoded frames of a scene are kept in memory across its runs below this size.
FRAME_CACHE_BYTES = 2 << 30


# --------------------------------------------------------------------------------------------------
# Noise of each (scene, zoo entry), and its cache name.


def entry_noise(source: SceneSource, entry: ZooEntry, variant: str = DETECTIONS_DEFAULT):
    """The noise model of `entry` on `source` (scaled to a generated scene's images; without prompt
    augmentation for ablation B's variant)."""
    if source.kind == "real":
        noise = entry.noise
    else:
        assert source.spec is not None  # a generated scene has its spec
        noise = scale_noise_to_image(entry.noise, source.spec.width, source.spec.height)
    return noise.replace(prompt_augmentation=False) if variant == DETECTIONS_NO_AUGMENTATION else noise


def detections_tag(entry_name: str, noise) -> str:
    """Cache name of an entry's detections: the entry and a hash of every noise parameter, so that a changed
    family definition gets a new folder (and old results are never read for it)."""
    digest = hashlib.sha1(json.dumps(noise.to_dict(), sort_keys=True).encode()).hexdigest()[:10]
    return f"zoo-{entry_name}-{digest}"


# --------------------------------------------------------------------------------------------------
# Summaries (pure functions of the pooled scores).


# --------------------------------------------------------------------------------------------------
# Reports.


# --------------------------------------------------------------------------------------------------
# Running.


def cache_frames(scene, max_bytes: int = FRAME_CACHE_BYTES) -> bool:
    """Decodes every frame of `scene` once and serves later reads from memory (read-only arrays, so a
    caller writing into a frame fails loudly instead of corrupting the next run); False, and nothing
    changed, when the frames would take more than `max_bytes`."""
    h, w = scene.intrinsics.height, scene.intrinsics.width
    if len(scene) * h * w * (4 + 3) > max_bytes:
        return False
    depths, colors = [], []
    for i in range(len(scene)):
        depth, color = scene.read_depth(i), scene.read_color(i)
        depth.setflags(write=False)
        color.setflags(write=False)
        depths.append(depth)
        colors.append(color)
    scene.read_depth, scene.read_color = depths.__getitem__, colors.__getitem__  # instance attributes win
    return True


@dataclasses.dataclass
class OpenedScene:
    """A scene ready for its runs: the opened scene (frames possibly cached), ground truth and its record."""

    source: SceneSource
    scene: Scene
    gt: SceneGroundTruth
    gt_ids: np.ndarray
    record: dict


def open_source(source: SceneSource, cache_dir: Path, config, progress: bool) -> OpenedScene:
    """Makes (or finds) a generated scene, opens the scene with the config's dataset settings, reads its
    ground truth and caches its decoded frames when they fit."""

    if source.kind == "real":
        assert source.path is not None  # a real scene has its folder
        scene_dir = source.path
    else:
        assert source.spec is not None  # a generated scene has its spec
        scene_dir = generated_scene(source.spec, cache_dir, progress)
    dataset = config.dataset
    scene = open_dataset_scene(scene_dir, dataset)
    gt = load_scannet_ground_truth(scene_dir)
    cached = cache_frames(scene)
    record = {
        "name": source.name,
        "kind": source.kind,
        "scene_dir": str(scene_dir),
        "frames": len(scene),
        "gt_vertices": int(gt.num_vertices),
        "frames_cached": cached,
        "spec": dataclasses.asdict(source.spec) if source.spec else None,
        "config": REAL_SCENE_CONFIG if source.kind == "real" else "demo (scaled to the scene)",
        "detections": {},
    }
    return OpenedScene(source, scene, gt, gt.benchmark_ids(), record)


def entry_detections(opened: OpenedScene, entry: ZooEntry, variant: str, cache_dir: Path, progress: bool) -> Path:
    """The (cached) detections of `entry` on the scene, simulated on every frame of the scene folder."""

    source = opened.source
    noise = entry_noise(source, entry, variant)
    tag = detections_tag(entry.name, noise)
    if source.kind == "real":
        assert source.path is not None  # a real scene has its folder
        prepared = prepare_real(source.path, cache_dir, noise, 1, tag, progress)
    else:
        assert source.spec is not None  # a generated scene has its spec
        prepared = prepare_generated(source.spec, cache_dir, noise, 1, tag, progress)
    opened.record["detections"][f"{entry.name}/{variant}"] = {"dir": str(prepared.detections_dir), "noise": noise.to_dict()}
    return prepared.detections_dir


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 60}m{seconds % 60:02d}s" if seconds >= 60 else f"{seconds}s"


@dataclasses.dataclass
class RobustnessResult:
    """What `run_robustness` made: the folder, the zoo, the scores (entry -> method -> metric -> fraction),
    the summaries, the verdict, robustness.md's text and robustness.json's content."""

    out_dir: Path
    entries: list
    methods: tuple
    scores: dict
    summary: dict
    verdict: dict
    markdown: str
    record: dict

    @property
    def text(self) -> str:
        """What the command prints: the per-family table, the verdict and where the files are."""
        return "\n".join(
            [
                family_table(self.summary, self.methods),
                "",
                *verdict_lines(self.verdict),
                "",
                f"written: {self.out_dir / 'robustness.md'}, {self.out_dir / 'robustness.json'}, "
                f"{self.out_dir / 'robustness.png'}, runs in {self.out_dir / 'runs'}",
            ]
        )


def run_robustness(
    out_dir: str | Path = DEFAULT_OUT,
    real_scenes: Sequence[str | Path] = (),
    generated: Sequence[GeneratedSceneSpec] = (),
    methods: Sequence[str] | None = None,
    entries: Sequence[ZooEntry] | None = None,
    noise_seed: int = 0,
    mixed: int = DEFAULT_MIXED,
    cache_dir: str | Path | None = None,
    overrides: Sequence[str] = (),
    real_max_frames: int | None = None,
    progress: bool = True,
    report: Callable[[str], None] | None = None,
) -> RobustnessResult:
    """Runs every method on every (scene, zoo entry), scores and summarizes them, and writes the reports.

    Args:
      out_dir: output folder (run folders of an earlier evaluation there are replaced).
      real_scenes, generated: the scenes (as `experiments.run_experiment`).
      methods: names of `comparison.methods.METHODS` (default `DEFAULT_METHODS`).
      entries: the zoo (default `noise_zoo(mixed, noise_seed)`).
      noise_seed, mixed: the zoo's seed and number of random mixtures, when `entries` is not given.
      cache_dir: generated scenes and simulated detections (default OUT/cache).
      overrides: config overrides for every method (a method's own win).
      real_max_frames: use only the first frames of real scenes (smoke tests).
      progress: one line per run with the running total and an ETA (`report`, default stderr).
    """
    from fmfusion_jax.run.folder import prepare_output_dir

    if mixed < 0 or noise_seed < 0:
        raise UserError(f"--mixed and --noise-seed must be >= 0 (got {mixed}, {noise_seed})")
    chosen = resolve_methods(methods or DEFAULT_METHODS)
    sources = scene_sources(real_scenes, generated)
    entries = list(entries) if entries is not None else noise_zoo(mixed=mixed, seed=noise_seed)
    if not entries:
        raise UserError("the noise zoo is empty")
    names = [e.name for e in entries]
    if len(set(names)) != len(names):
        raise UserError(f"zoo entry names repeat: {names}")
    report = report or (stderr_report if progress else log.info)
    for method in chosen:  # bad overrides fail before anything is made
        for kind in sorted({s.kind for s in sources}):
            check_config(kind, sources, list(overrides) + list(method.overrides), real_max_frames)
    out_dir = prepare_output_dir(out_dir)
    cache_dir = Path(cache_dir) if cache_dir is not None else out_dir / "cache"

    start = time.perf_counter()
    total, done = len(sources) * len(entries) * len(chosen), 0
    runs: dict = {e.name: {} for e in entries}  # entry -> scene -> method -> RunOutcome
    gt_ids, scene_records = {}, []
    timings: dict[str, dict[str, float]] = {}
    for source in sources:
        opened = open_source(source, cache_dir, source.config(overrides, real_max_frames), progress=False)
        gt_ids[source.name] = opened.gt_ids
        timings[source.name] = {}
        for entry in entries:
            outcomes: dict[str, RunOutcome] = {}
            seen: dict[tuple[str | None, str, str], str] = {}  # (baseline, detections, config) -> first method
            runs[entry.name][source.name] = outcomes
            detections = {}
            for method in chosen:
                if method.detections not in detections:
                    what = "detections" if method.detections == DETECTIONS_DEFAULT else "detections without prompt augmentation"
                    report(f"{source.name} / {entry.name}: {what} (simulated once, cached in {cache_dir})")
                    detections[method.detections] = entry_detections(opened, entry, method.detections, cache_dir, progress=False)
                config = source.config(list(overrides) + list(method.overrides), real_max_frames)
                run_dir = out_dir / "runs" / source.name / entry.name / method.name
                key = (method.baseline, method.detections, config.to_yaml())
                if key in seen:  # the same mapper on the same inputs: the same map
                    other = seen[key]
                    outcome = copy_run(outcomes[other], method, other, run_dir.parent / other, run_dir)
                else:
                    outcome = run_method(
                        method, opened.scene, detections[method.detections], config, opened.gt, run_dir, progress=False
                    )
                    seen[key] = method.name
                outcomes[method.name] = outcome
                timings[source.name][f"{entry.name}/{method.name}"] = outcome.summary["seconds"]["total"]
                done += 1
                elapsed = time.perf_counter() - start
                what = (
                    f"{outcome.summary['seconds']['total']:.1f} s"
                    if seen[key] == method.name
                    else f"same config and detections as {seen[key]}, map copied"
                )
                report(
                    f"[{done}/{total}] {source.name} / {entry.name} / {method.name}: {what}, "
                    f"mAP50 {_pct(outcome.score.mAP50)} %; elapsed {_duration(elapsed)}, "
                    f"ETA {_duration(elapsed / done * (total - done))}"
                )
        scene_records.append(opened.record)
        del opened  # its frames and ground truth are not needed any more

    scene_names = tuple(s.name for s in sources)
    scores, pooled_json, per_scene_ap50, precision = {}, {}, {}, {}
    counts: dict = {}  # (scene, entry, method) -> precision_counts; a copied run shares its original's
    for entry in entries:
        for s in scene_names:
            for m in chosen:
                same = runs[entry.name][s][m.name].summary.get("same_run_as", m.name)
                key = (s, entry.name, same)
                if key not in counts:
                    counts[key] = precision_counts(gt_ids[s], runs[entry.name][s][same].predictions)
                counts[(s, entry.name, m.name)] = counts[key]
    for entry in entries:
        pooled, per_scene = score_methods(chosen, scene_names, gt_ids, runs[entry.name])
        scores[entry.name] = {
            m.name: {metric: _as_fraction(getattr(pooled[m.name], attr)) for metric, attr in METRICS} for m in chosen
        }
        pooled_json[entry.name] = {m.name: pooled[m.name].to_json_dict() for m in chosen}
        per_scene_ap50[entry.name] = {s: {m.name: _as_fraction(per_scene[s][m.name].mAP50) for m in chosen} for s in scene_names}
        precision[entry.name] = {
            m.name: pooled_precision([counts[(s, entry.name, m.name)] for s in scene_names], scores[entry.name][m.name]["AP50"])
            for m in chosen
        }
    method_names = [m.name for m in chosen]
    precision_summary = summarize_precision(entries, precision, method_names)
    summary = summarize(entries, scores, method_names)
    verdict_record = verdict(summary, method_names)
    seconds = round(time.perf_counter() - start, 1)
    record = {
        "noise_seed": entries[0].noise.seed,
        "mixed": sum(e.family == MIXED for e in entries),
        "overrides": list(overrides),
        "real_max_frames": real_max_frames,
        "methods": {m.name: dataclasses.asdict(m) for m in chosen},
        "zoo": [{"name": e.name, "family": e.family, "noise": e.noise.to_dict()} for e in entries],
        "scenes": scene_records,
        "scores": scores,
        "per_scene_ap50": per_scene_ap50,
        "pooled": pooled_json,
        "summary": summary,
        "verdict": verdict_record,
        "precision": precision,
        "precision_summary": precision_summary,
        "timings_s": timings,
        "runs": total,
        "total_seconds": seconds,
        "units": "AP and the no-object share as fractions in [0, 1] (null: no score); robustness.md gives them in %",
    }
    markdown = robustness_markdown(
        entries,
        scores,
        summary,
        verdict_record,
        chosen,
        scene_records,
        entries[0].noise.seed,
        seconds,
        total,
        precision,
        precision_summary,
    )
    write_reports(out_dir, markdown, record, robustness_chart(entries, scores, summary, method_names))
    log.info("robustness evaluation written into %s (%.1f s)", out_dir, seconds)
    return RobustnessResult(out_dir, entries, chosen, scores, summary, verdict_record, markdown, record)


def _as_fraction(value: float) -> float | None:
    return None if value is None or math.isnan(value) else float(value)


def write_reports(out_dir: Path, markdown: str, record: dict, chart: np.ndarray) -> None:
    """robustness.md, robustness.json and robustness.png into `out_dir`."""

    (out_dir / "robustness.md").write_text(markdown)
    (out_dir / "robustness.json").write_text(json.dumps(record, indent=1, default=float))
    if not cv2.imwrite(str(out_dir / "robustness.png"), chart):
        raise UserError(f"cannot write {out_dir / 'robustness.png'}")
