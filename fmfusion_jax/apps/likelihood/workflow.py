"""The work behind `fmfusion likelihood summarize | calibrate`: scene sets, fusion runs, reports.

A *case* is a scene with detections and the pipeline config it is fused with: generated scenes
(`simulation.scene_sets`, cached, fused with the demo config scaled to their size) or a real ScanNet-layout
scene with simulated (or real) detections (fused with `scannet-subsampled` unless told otherwise).

`calibrate_and_compare` does the whole calibration experiment:
1. summarizes the likelihood over the training cases (Appendix B, `summarize`);
2. fuses each training case once with the initial matrix and collects its instances matched to ground
   truth (`matching`): their open-label histograms and true classes;
3. chooses the regularization (`l2`, Adam steps) by cross-validation over the training scenes
   (`calibrate.cross_validate`: folds by scene; the held-out cases play no part) unless both are given,
   and fits the matrix on all training instances with it (`calibrate.fit_likelihood`);
4. on each held-out case, fuses once per compared matrix (manual, statistical, summarized, calibrated:
   merges depend on the likelihood, so the map itself changes) and reports the ScanNet benchmark
   (mAP, mAP50, mAP25), the label accuracy of the instances matched to ground truth in that run, and the
   label accuracy and loss of every matrix on the histograms of the initial matrix's run (the same
   instances for all matrices).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fmfusion_jax.config import PipelineConfig, detection_frame_stride, load_config
from fmfusion_jax.errors import UserError
from fmfusion_jax.evaluation.scannet_benchmark import evaluate_scenes
from fmfusion_jax.instances import drop_small_instances, postprocess_instances
from fmfusion_jax.io.detections import DetectionFolder
from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
from fmfusion_jax.io.heatmap import write_heatmap
from fmfusion_jax.io.scene import open_dataset_scene, sample_scene_dir
from fmfusion_jax.labels import LabelSets, load_label_sets, load_likelihood, write_likelihood_csv
from fmfusion_jax.simulation.demo_setup import demo_config, demo_noise
from fmfusion_jax.simulation.noise import NoiseModel

if TYPE_CHECKING:
    from fmfusion_jax.io.benchmark_format import InstancePredictions
    from fmfusion_jax.likelihood.matching import MatchedInstances

log = logging.getLogger(__name__)

#: Matrices compared on the held-out cases, in report order (the calibrated one is added when fitted).
COMPARED = ("manual", "statistical", "summarized", "calibrated")
DEFAULT_CACHE = Path("outputs/scene_sets")
#: Config of real scenes unless told otherwise: the shared sample's frames are ~18 original frames apart.
DEFAULT_REAL_CONFIG = "scannet-subsampled"


def default_real_scene() -> Path | None:
    """The shared ScanNet sample (`io.scene.sample_scene_dir`: `$FMFUSION_SCANNET_DIR/scene0000_00` or
    ../shared/data/scannet/...), if present."""

    scene = sample_scene_dir()
    return scene if scene.is_dir() else None


@dataclasses.dataclass(frozen=True)
class Case:
    """A scene, its detections and the config it is fused with."""

    name: str
    scene_dir: Path
    detections_dir: Path
    config: PipelineConfig
    generated: bool


@dataclasses.dataclass(frozen=True)
class GeneratedSize:
    """Size of generated scenes (the defaults keep a fusion run near half a minute on 2 cores)."""

    num_objects: int = 12
    num_frames: int = 120
    width: int = 320
    height: int = 240


def generated_cases(
    seeds: Sequence[int], root: str | Path = DEFAULT_CACHE, size: GeneratedSize = GeneratedSize(), progress: bool = False
) -> list[Case]:
    """Generated scenes (seeds) with simulated detections (the demo's noise model, seeded like the scene),
    cached under `root`; each fused with the demo config scaled to its size."""
    from fmfusion_jax.simulation.procedural import generate_scene  # lazy: `fmfusion --help` imports this module
    from fmfusion_jax.simulation.scene_sets import (
        GeneratedSceneSpec,  # lazy: `fmfusion --help` imports this module
        prepare_generated,  # lazy: `fmfusion --help` imports this module
    )

    cases = []
    for seed in seeds:
        spec = GeneratedSceneSpec(int(seed), size.num_objects, size.num_frames, size.width, size.height)
        room = generate_scene(spec.seed, num_objects=spec.num_objects).room_size
        config = demo_config(spec.num_frames, spec.width, spec.height, room_size=room)
        every = detection_frame_stride(config) * config.dataset.frame_stride
        prepared = prepare_generated(spec, root, demo_noise(spec.seed, spec.width, spec.height), every=every, progress=progress)
        cases.append(Case(prepared.name, prepared.scene_dir, prepared.detections_dir, config, True))
    return cases


def real_case(
    scene_dir: str | Path,
    detections_dir: str | Path | None = None,
    root: str | Path = DEFAULT_CACHE,
    config: str = DEFAULT_REAL_CONFIG,
    progress: bool = False,
) -> Case:
    """A real scene with the given detections, or with simulated ones (default noise, seed 0) cached under
    `root` when `detections_dir` is None."""
    from fmfusion_jax.simulation.scene_sets import prepare_real  # lazy: `fmfusion --help` imports this module

    scene_dir = Path(scene_dir)
    pipeline_config = load_config(config)
    if detections_dir is None:
        every = detection_frame_stride(pipeline_config) * pipeline_config.dataset.frame_stride
        detections_dir = prepare_real(
            scene_dir, root, NoiseModel.preset("default", seed=0), every=every, progress=progress
        ).detections_dir
    elif not Path(detections_dir).is_dir():
        raise UserError(f"detections folder {detections_dir} does not exist")
    return Case(scene_dir.name, scene_dir, Path(detections_dir), pipeline_config, False)


def with_likelihood(config: PipelineConfig, likelihood: str | Path) -> PipelineConfig:
    """The config with `label_fusion.likelihood` set (a packaged name or a CSV path), fused as given
    (`label_fusion.normalize_columns` off): the workflow compares and fits the matrices themselves, and the
    calibration's model (`calibrate.class_log_probs`) is the additive update with the matrix as it is."""
    update = {"likelihood": str(likelihood), "normalize_columns": False}
    label_fusion = config.label_fusion.model_copy(update=update)
    return config.model_copy(update={"label_fusion": label_fusion})


# ---------------------------------------------------------------------------------------------------
# Summarization


def summarize_cases(
    cases: Sequence[Case],
    label_sets: LabelSets | None = None,
    min_pixels: int | None = None,
    label_rule: str = "main",
    progress: bool = False,
):
    """`LikelihoodCounts` summed over the cases (each rendered at its config's depth truncation)."""
    from fmfusion_jax.likelihood.summarize import (
        LikelihoodCounts,  # lazy: `fmfusion --help` imports this module
        summarize_scene,  # lazy: `fmfusion --help` imports this module
    )

    label_sets = label_sets or load_label_sets()
    total = LikelihoodCounts.zeros(label_sets.num_open, label_sets.num_classes)
    for case in cases:
        total = total + summarize_scene(
            case.scene_dir,
            case.detections_dir,
            label_sets,
            min_pixels,
            label_rule=label_rule,
            depth_max=case.config.dataset.depth_max,
            progress=progress,
        )
    return total


# ---------------------------------------------------------------------------------------------------
# Fusion runs


@dataclasses.dataclass
class RunOutcome:
    """One fusion run of a case with one likelihood: its instances matched to ground truth and its score."""

    case: str
    likelihood: str
    matched: MatchedInstances
    predictions: InstancePredictions  # over the GT mesh vertices
    gt_benchmark_ids: np.ndarray
    scores: dict[str, float]  # mAP, mAP50, mAP25 of this scene alone
    seconds: float


def fuse_case(case: Case, likelihood: str | Path, label_sets: LabelSets | None = None, progress: bool = False) -> RunOutcome:
    """Fuses `case` with `likelihood` (packaged name or CSV), matches its instances to ground truth and
    scores its benchmark export."""
    from fmfusion_jax.likelihood.matching import match_instances  # lazy: `fmfusion --help` imports this module
    from fmfusion_jax.mapping.export import extract_map_instances  # lazy: JAX (`fmfusion --help` imports this module)
    from fmfusion_jax.run.outputs import score_instances  # lazy: JAX (`fmfusion --help` imports this module)
    from fmfusion_jax.run.scene_fusion import fuse_scene  # lazy: JAX (`fmfusion --help` imports this module)

    label_sets = label_sets or load_label_sets()
    start = time.perf_counter()
    config = with_likelihood(case.config, likelihood)
    dataset = config.dataset
    scene = open_dataset_scene(case.scene_dir, dataset)
    folder = DetectionFolder(case.detections_dir, image_shape=(scene.intrinsics.height, scene.intrinsics.width))
    result = fuse_scene(scene, folder, config, progress=progress)
    gt = load_scannet_ground_truth(case.scene_dir)
    # Unprocessed instances keep `distribution = class_distribution(h @ L)`; the small ones are dropped as
    # the export drops them. The export's are the same instances post-processed (as
    # `extract_map_instances(postprocess=True)` does; `result.config` is `config`).
    unprocessed = extract_map_instances(result, label_sets, postprocess=False)
    raw = drop_small_instances(unprocessed, config.export.min_points)
    matched = match_instances(raw, gt, case.name, label_sets, config.export.transfer_radius)
    exported = postprocess_instances(unprocessed, label_sets, config.export)
    gt_ids = gt.benchmark_ids()
    predictions, score = score_instances(exported, gt, case.name, config, label_sets, gt_ids=gt_ids)
    return RunOutcome(
        case.name,
        str(likelihood),
        matched,
        predictions,
        gt_ids,
        {"mAP": score.mAP, "mAP50": score.mAP50, "mAP25": score.mAP25},
        time.perf_counter() - start,
    )


def pooled_scores(outcomes: Sequence[RunOutcome]) -> dict[str, float]:
    """The benchmark over several scenes at once (AP pooled over their instances, as the benchmark does)."""

    if not outcomes:
        return {}
    score = evaluate_scenes([(o.gt_benchmark_ids, o.predictions) for o in outcomes], scene_names=[o.case for o in outcomes])
    return {"mAP": score.mAP, "mAP50": score.mAP50, "mAP25": score.mAP25}


# ---------------------------------------------------------------------------------------------------
# The calibration experiment


@dataclasses.dataclass
class CalibrationSettings:
    init: str = "statistical"  # matrix the fit starts from (and the training runs are fused with)
    parametrization: str = "column"
    steps: int | None = None  # Adam steps; None: chosen by cross-validation (early stopping)
    learning_rate: float = 0.05
    l2: float | None = None  # pull toward the initial logits; None: chosen by cross-validation
    folds: int = 4  # of the cross-validation, by training scene
    l2_grid: tuple[float, ...] = (0.0, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0)  # candidates when l2 is None
    max_steps: int = 500  # the most steps the cross-validation considers when steps is None
    min_class_instances: int = 3  # classes with fewer training instances keep their initial column
    label_rule: str = "main"  # of the summarization
    min_pixels: int | None = None  # of the summarization (default: scaled from 400 at 640x480)


def _fmt(value: float | None, digits: int = 3) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def calibrate_and_compare(
    train: Sequence[Case],
    test: Sequence[Case],
    out_dir: str | Path,
    settings: CalibrationSettings | None = None,
    progress: bool = False,
    say: Callable[[str], None] = print,
) -> dict:
    """The experiment of the module docstring; writes into `out_dir` and returns the report (report.json).
    `settings`: default `CalibrationSettings()`.

    Files: summarized/ (the summary of the training cases: CSVs, heat maps, counts), calibrated.csv,
    calibrated.png, difference.png (calibrated - initial, absolute), loss.csv (the loss per step),
    validation.csv (the pooled validation loss per l2 and step, when cross-validated), report.json, report.md.
    """
    import jax.numpy as jnp  # lazy: JAX (`fmfusion --help` imports this module)

    from fmfusion_jax.likelihood import calibrate as cal  # lazy: JAX (`fmfusion --help` imports this module)
    from fmfusion_jax.likelihood.matching import MatchedInstances  # lazy: `fmfusion --help` imports this module
    from fmfusion_jax.likelihood.summarize import (
        estimate,  # lazy: `fmfusion --help` imports this module
        write_summary,  # lazy: `fmfusion --help` imports this module
    )

    settings = settings or CalibrationSettings()
    if not train:
        raise UserError("calibration needs at least one training scene")
    label_sets = load_label_sets()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    clock = time.perf_counter()
    seconds: dict[str, float] = {}

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        seconds[name] = round(now - clock, 1)
        clock = now

    # 1. Summarized matrix of the training cases.
    say(f"summarizing the likelihood over {len(train)} training scenes ...")
    counts = summarize_cases(train, label_sets, settings.min_pixels, settings.label_rule, progress)
    write_summary(
        out_dir / "summarized",
        counts,
        label_sets,
        sources=[f"{c.name}: {c.detections_dir}" for c in train],
        settings={"label_rule": settings.label_rule, "min_pixels": settings.min_pixels},
    )
    summarized_path = out_dir / "summarized" / "likelihood.csv"
    lap("summarize")

    # 2. Training runs with the initial matrix.
    init_matrix = load_likelihood(settings.init)
    init_name = settings.init
    runs: list[RunOutcome] = []
    for k, case in enumerate(train):
        say(f"[train {k + 1}/{len(train)}] fusing {case.name} with the {init_name} likelihood ...")
        runs.append(fuse_case(case, init_name, label_sets, progress))
        say(f"  {len(runs[-1].matched)} instances matched to ground truth ({runs[-1].seconds:.0f} s)")
    train_set = MatchedInstances.concatenate([r.matched for r in runs], label_sets.num_open)
    if len(train_set) == 0:
        raise UserError("no fused instance of the training scenes matched a ground-truth instance")
    lap("train_runs")

    # 3. The regularization (cross-validated on the training scenes) and the fit.
    init_logits = cal.logits_from_likelihood(init_matrix, settings.parametrization)
    class_instances = np.bincount(train_set.classes, minlength=label_sets.num_classes)
    trainable = class_instances >= settings.min_class_instances
    l2, steps, validation = settings.l2, settings.steps, None
    if l2 is None or steps is None:
        grid = settings.l2_grid if l2 is None else (l2,)
        horizon = settings.max_steps if steps is None else steps
        folds = cal.scene_folds(train_set.scenes, settings.folds)
        say(
            f"cross-validating l2 in {list(grid)}"
            + (f" and 0-{horizon} Adam steps" if steps is None else "")
            + f" over {len(folds)} folds of training scenes ..."
        )
        cv = cal.cross_validate(
            init_logits,
            train_set.histograms,
            train_set.classes,
            train_set.scenes,
            grid,
            horizon,
            settings.folds,
            settings.learning_rate,
            settings.parametrization,
            settings.min_class_instances,
            early_stopping=steps is None,
        )
        l2, steps = cv.l2, cv.steps
        validation = {
            "folds": cv.folds,
            "fold_instances": cv.fold_sizes.tolist(),
            "l2_grid": cv.l2_grid.tolist(),
            "early_stopping": cv.early_stopping,
            "table": cv.table(),
            "l2": cv.l2,
            "steps": cv.steps,
            "loss": cv.loss,
        }
        (out_dir / "validation.csv").write_text(
            "step,"
            + ",".join(f"l2={v:g}" for v in cv.l2_grid)
            + "\n"
            + "".join(f"{t}," + ",".join(f"{v:.6f}" for v in cv.losses[:, t]) + "\n" for t in range(cv.losses.shape[1]))
        )
        say(f"  chosen: l2 {l2:g}, {steps} steps (validation loss {cv.loss:.4f}; {cv.losses[0, 0]:.4f} with the initial matrix)")
        lap("cross_validation")
    say(
        f"fitting the likelihood on {len(train_set)} instances ({settings.parametrization} parametrization, "
        f"{steps} Adam steps, l2 {l2:g}) ..."
    )
    say(f"  trained columns: {', '.join(n for n, t in zip(label_sets.class_names, trainable) if t) or 'none'}")
    fit = cal.fit_likelihood(
        init_logits,
        train_set.histograms,
        train_set.classes,
        steps,
        settings.learning_rate,
        l2,
        settings.parametrization,
        trainable=trainable,
    )
    calibrated = fit.likelihood
    calibrated_path = write_likelihood_csv(
        out_dir / "calibrated.csv",
        calibrated,
        label_sets,
        comment=(
            f"Calibrated with fmfusion likelihood calibrate from the {init_name} likelihood on "
            f"{len(train_set)} instances of {', '.join(c.name for c in train)}\n"
            f"parametrization {settings.parametrization}, {steps} Adam steps, learning rate "
            f"{settings.learning_rate}, l2 {l2:g}"
            + (" (cross-validated)" if validation else "")
            + f"; loss {fit.initial_loss:.4f} -> {fit.final_loss:.4f}"
        ),
    )
    write_heatmap(
        out_dir / "calibrated.png",
        calibrated,
        label_sets.open_labels,
        label_sets.class_names,
        title=f"calibrated likelihood (from {init_name}, {len(train_set)} training instances)",
    )
    write_heatmap(
        out_dir / "difference.png",
        np.abs(calibrated - init_matrix),
        label_sets.open_labels,
        label_sets.class_names,
        title=f"|calibrated - {init_name}|",
    )
    (out_dir / "loss.csv").write_text("step,loss\n" + "".join(f"{i},{v:.6f}\n" for i, v in enumerate(fit.losses)))
    lap("fit")

    matrices = {
        "manual": load_likelihood("manual"),
        "statistical": load_likelihood("statistical"),
        "summarized": estimate(counts)[2],
        "calibrated": calibrated,
    }
    sources = {
        "manual": "manual",
        "statistical": "statistical",
        "summarized": str(summarized_path),
        "calibrated": str(calibrated_path),
    }
    if init_name not in sources:
        matrices[init_name], sources[init_name] = init_matrix, init_name

    def nll(matrix: np.ndarray, data: MatchedInstances) -> float:
        if len(data) == 0:
            return float("nan")
        return float(
            cal.negative_log_likelihood(jnp.asarray(matrix, jnp.float32), jnp.asarray(data.histograms), jnp.asarray(data.classes))
        )

    train_figures = {
        name: {"loss": nll(m, train_set), "accuracy": cal.label_accuracy(m, train_set.histograms, train_set.classes)}
        for name, m in matrices.items()
    }

    # 4. Held-out runs, one per matrix.
    test_runs: dict[str, dict[str, RunOutcome]] = {}
    total = len(test) * len(sources)
    done = 0
    for case in test:
        test_runs[case.name] = {}
        for name, source in sources.items():
            done += 1
            say(f"[test {done}/{total}] fusing {case.name} with the {name} likelihood ...")
            outcome = fuse_case(case, source, label_sets, progress)
            test_runs[case.name][name] = outcome
            say(f"  mAP50 {_fmt(outcome.scores['mAP50'])}, {len(outcome.matched)} matched instances ({outcome.seconds:.0f} s)")
    lap("test_runs")

    groups = {"generated": [c.name for c in test if c.generated], "real": [c.name for c in test if not c.generated]}
    held_out: dict[str, dict] = {}
    for group, names in groups.items():
        if not names:
            continue
        fixed = MatchedInstances.concatenate([test_runs[n][init_name].matched for n in names], label_sets.num_open)
        figures = {}
        for name, matrix in matrices.items():
            own = MatchedInstances.concatenate([test_runs[n][name].matched for n in names], label_sets.num_open)
            figures[name] = {
                "loss": nll(matrix, fixed),
                "accuracy_fixed_histograms": cal.label_accuracy(matrix, fixed.histograms, fixed.classes),
                "accuracy_own_run": float(np.mean(own.predicted == own.classes)) if len(own) else float("nan"),
                "matched_own_run": len(own),
                **pooled_scores([test_runs[n][name] for n in names]),
            }
        held_out[group] = {"scenes": names, "instances_fixed_histograms": len(fixed), "matrices": figures}

    report = {
        "settings": dataclasses.asdict(settings),
        "train_scenes": [c.name for c in train],
        "test_scenes": [c.name for c in test],
        "train_instances": len(train_set),
        "train_instances_per_class": {n: int(k) for n, k in zip(label_sets.class_names, class_instances)},
        "trained_columns": [n for n, t in zip(label_sets.class_names, trainable) if t],
        "fit": {"l2": l2, "steps": steps, "cross_validated": validation is not None},
        "validation": validation,
        "loss": {"initial_raw": train_figures[init_name]["loss"], "initial": fit.initial_loss, "final": fit.final_loss},
        "train": train_figures,
        "held_out": held_out,
        "per_scene": {
            case: {
                name: {
                    **o.scores,
                    "matched": len(o.matched),
                    "accuracy_own_run": float(np.mean(o.matched.predicted == o.matched.classes)) if len(o.matched) else None,
                    "seconds": round(o.seconds, 1),
                }
                for name, o in per.items()
            }
            for case, per in test_runs.items()
        },
        "seconds": seconds,
        "summary_counts": {"frames": counts.frames, "instances": counts.instances, "matched": counts.matched},
    }
    (out_dir / "report.json").write_text(json.dumps(report, indent=1, default=_json_default) + "\n")
    (out_dir / "report.md").write_text(report_markdown(report))
    return report


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    raise TypeError(type(value).__name__)


def report_markdown(report: dict) -> str:
    """report.md: the figures of `calibrate_and_compare` as tables."""
    s, fit = report["settings"], report["fit"]
    lines = [
        "# Likelihood calibration",
        "",
        f"Training scenes: {', '.join(report['train_scenes'])} ({report['train_instances']} instances matched to "
        f"ground truth). Held-out scenes: {', '.join(report['test_scenes']) or 'none'}.",
        f"Fit: from the {s['init']} likelihood, {s['parametrization']} parametrization, {fit['steps']} Adam steps, "
        f"learning rate {s['learning_rate']}, l2 {fit['l2']:g}"
        + (" (chosen by cross-validation)" if fit["cross_validated"] else "")
        + f"; columns trained (classes with at least {s['min_class_instances']} training instances): "
        f"{', '.join(report['trained_columns']) or 'none'}.",
        "",
        f"Training loss (mean -log p(true class)): {_fmt(report['loss']['initial_raw'], 4)} with the {s['init']} "
        f"matrix as published, {_fmt(report['loss']['initial'], 4)} at the start of the fit (the matrix in the "
        f"parametrization), {_fmt(report['loss']['final'], 4)} after it.",
        "",
        "| matrix | train loss | train accuracy |",
        "|---|---|---|",
    ]
    lines += [f"| {name} | {_fmt(f['loss'], 4)} | {_fmt(f['accuracy'])} |" for name, f in report["train"].items()]
    cv = report.get("validation")
    if cv:
        lines += [
            "",
            "## Cross-validation (training scenes only)",
            "",
            f"{len(cv['folds'])} folds by scene ({', '.join(str(n) for n in cv['fold_instances'])} instances): "
            + "; ".join(", ".join(f) for f in cv["folds"])
            + ". Mean -log p(true class) of the left-out "
            "instances (pooled over folds), fitting on the other folds"
            + (" (best step: early stopping)." if cv["early_stopping"] else f" for {fit['steps']} steps."),
            "",
            "| l2 | best steps | validation loss at best | after the last step |",
            "|---|---:|---:|---:|",
        ]
        lines += [
            f"| {r['l2']:g} | {r['best_steps']} | {_fmt(r['loss_best'], 4)} | {_fmt(r['loss_last'], 4)} |" for r in cv["table"]
        ]
        lines += [
            "",
            f"Chosen: l2 {cv['l2']:g}, {cv['steps']} steps (validation loss {_fmt(cv['loss'], 4)}; "
            f"{_fmt(cv['table'][0]['loss_initial'], 4)} with the initial matrix).",
        ]
    for group, block in report["held_out"].items():
        lines += [
            "",
            f"## Held-out {group} scenes: {', '.join(block['scenes'])}",
            "",
            f"Loss and accuracy on fixed histograms: the {block['instances_fixed_histograms']} instances of the "
            f"{s['init']} run matched to ground truth, classified under each matrix. Own run: the scene fused "
            "again with the matrix (instances, merges and benchmark all change).",
            "",
            "| matrix | loss | accuracy (fixed) | accuracy (own run) | matched (own run) | mAP | mAP50 | mAP25 |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for name, f in block["matrices"].items():
            lines.append(
                f"| {name} | {_fmt(f['loss'], 4)} | {_fmt(f['accuracy_fixed_histograms'])} | "
                f"{_fmt(f['accuracy_own_run'])} | {f['matched_own_run']} | {_fmt(f.get('mAP'))} | "
                f"{_fmt(f.get('mAP50'))} | {_fmt(f.get('mAP25'))} |"
            )
    lines += ["", "Wall time (s): " + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in report["seconds"].items()), ""]
    return "\n".join(lines)
