"""The `fmfusion likelihood` commands: their arguments checked, the scenes prepared, the workflow run and
reported."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from fmfusion_jax.apps.likelihood.workflow import (
    CalibrationSettings,
    GeneratedSize,
    calibrate_and_compare,
    default_real_scene,
    generated_cases,
    real_case,
    report_markdown,
    summarize_cases,
)
from fmfusion_jax.comparison.tables import stderr_report
from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import load_likelihood
from fmfusion_jax.likelihood.summarize import estimate, write_summary
from fmfusion_jax.run.folder import prepare_output_dir

if TYPE_CHECKING:
    pass

log = logging.getLogger(__name__)


def checked_size(objects: int, frames: int, width: int, height: int) -> GeneratedSize:
    """The size of the generated scenes given on the command line; a `UserError` when too small."""
    if objects < 1 or frames < 2 or width < 32 or height < 24:
        raise UserError("generated scenes need at least 1 object, 2 frames and 32x24 pixels")
    return GeneratedSize(objects, frames, width, height)


def run_summarize(
    scenes: Sequence[Path],
    detections: Sequence[Path] | None,
    generated: int,
    out: Path,
    cache: Path,
    objects: int,
    frames: int,
    width: int,
    height: int,
    min_pixels: int | None = None,
    label_rule: str = "main",
    progress: bool = True,
) -> int:
    """`fmfusion likelihood summarize`: the likelihood summarized from real `scenes` (their detection folders, or
    simulated detections) and `generated` rooms, written to `out` and reported. Returns the exit status."""

    if not scenes and generated < 1:
        raise UserError("give SCENE folders and/or --generated N")
    if detections is not None and len(detections) != len(scenes):
        raise UserError(f"--detections needs one folder per SCENE ({len(scenes)} scenes, {len(detections)} folders)")
    for scene in scenes:
        if not scene.is_dir():
            raise UserError(f"scene folder {scene} does not exist")
    start = time.perf_counter()
    prepare_output_dir(out)
    folders: Sequence[Path | None] = list(detections) if detections else [None] * len(scenes)
    cases = [real_case(scene, det, cache, progress=progress) for scene, det in zip(scenes, folders)]
    if generated:
        stderr_report(f"preparing {generated} generated scenes in {cache} ...")
        cases += generated_cases(range(1, generated + 1), cache, checked_size(objects, frames, width, height), progress)
    counts = summarize_cases(cases, min_pixels=min_pixels, label_rule=label_rule, progress=progress)
    if counts.instances == 0:
        raise UserError("no ground-truth instance of a closed class was visible in any detection frame")
    write_summary(
        out,
        counts,
        sources=[f"{c.name}: {c.detections_dir}" for c in cases],
        settings={"label_rule": label_rule, "min_pixels": min_pixels},
    )
    _, _, likelihood = estimate(counts)
    seen = counts.frames_observing > 0
    observed = int(seen.sum())
    sums = likelihood[:, seen].sum(axis=0)
    print(
        f"summarized {counts.frames} frames of {len(cases)} scenes: {counts.instances} visible instances, "
        f"{counts.matched} matched to a detection ({100.0 * counts.matched / counts.instances:.0f}%), "
        f"{observed} of {len(counts.frames_observing)} classes observed, in {time.perf_counter() - start:.1f} s"
    )
    print(
        f"likelihood: {int((likelihood > 0).sum())} non-zero entries, column sums "
        f"{sums.min():.2f} - {sums.max():.2f} over the observed classes"
        if observed
        else "likelihood: empty"
    )
    print(f"outputs in {out}: likelihood.csv/.png, tagging.csv/.png, detection.csv/.png, counts.json")
    return 0


def run_calibrate(
    train: str,
    test: str,
    test_real: Sequence[Path] | None,
    real_config: str,
    out: Path,
    cache: Path,
    objects: int,
    frames: int,
    width: int,
    height: int,
    init: str = "statistical",
    parametrization: str = "column",
    steps: int | None = None,
    max_steps: int = 500,
    lr: float = 0.05,
    l2: float | None = None,
    l2_grid: str = "0,1e-3,1e-2,1e-1,1,10,100",
    folds: int = 4,
    min_class_instances: int = 3,
    progress: bool = True,
) -> int:
    """`fmfusion likelihood calibrate`: the likelihood fitted on the generated training rooms and compared with
    the others on the held-out scenes; report and matrices written to `out`. Returns the exit status."""

    for name, value in (("steps", steps), ("max_steps", max_steps)):
        if value is not None and value < 1:
            raise UserError(f"--{name.replace('_', '-')} must be >= 1")
    if lr <= 0 or (l2 is not None and l2 < 0):
        raise UserError("--lr must be > 0 and --l2 >= 0")
    try:
        l2_weights = tuple(float(v) for v in l2_grid.split(",") if v.strip())
    except ValueError:
        raise UserError(f"--l2-grid {l2_grid!r}: expected comma-separated numbers") from None
    if not l2_weights or min(l2_weights) < 0:
        raise UserError("--l2-grid needs at least one weight, all >= 0")
    cross_validated = l2 is None or steps is None
    if cross_validated and folds < 2:
        raise UserError("--folds must be >= 2")
    try:
        load_likelihood(init)
    except (OSError, ValueError) as error:
        raise UserError(f"--init {init}: {error}") from None
    train_seeds, test_seeds = parse_seeds(train), parse_seeds(test)
    if not train_seeds:
        raise UserError("--train needs at least one seed")
    if cross_validated and len(train_seeds) < 2:
        raise UserError("cross-validation needs at least 2 training seeds (or give both --l2 and --steps)")
    if set(train_seeds) & set(test_seeds):
        raise UserError(f"seeds {sorted(set(train_seeds) & set(test_seeds))} are both training and held-out scenes")
    real = test_real
    if real is None:
        found = default_real_scene()
        real = [found] if found is not None else []
    start = time.perf_counter()
    prepare_output_dir(out)
    size = checked_size(objects, frames, width, height)
    stderr_report(f"preparing {len(train_seeds) + len(test_seeds)} generated scenes in {cache} ...")
    train_cases = generated_cases(train_seeds, cache, size, progress)
    test_cases = generated_cases(test_seeds, cache, size, progress)
    test_cases += [real_case(scene, None, cache, real_config, progress) for scene in real]
    settings = CalibrationSettings(
        init=init,
        parametrization=parametrization,
        steps=steps,
        learning_rate=lr,
        l2=l2,
        folds=folds,
        l2_grid=l2_weights,
        max_steps=max_steps,
        min_class_instances=min_class_instances,
    )
    report = calibrate_and_compare(train_cases, test_cases, out, settings, progress=progress, say=stderr_report)
    print(report_markdown(report))
    print(
        f"done in {time.perf_counter() - start:.0f} s; outputs in {out}: report.md, report.json, "
        "calibrated.csv/.png, difference.png, loss.csv, validation.csv, summarized/"
    )
    return 0


def parse_seeds(text: str) -> list[int]:
    """``"1-6"`` -> [1..6]; ``"1,3,7-9"`` -> [1, 3, 7, 8, 9]; ``""`` or ``"none"`` -> []."""
    if text.strip().lower() in ("", "none"):
        return []
    seeds: list[int] = []
    try:
        for part in text.split(","):
            lo, sep, hi = part.strip().partition("-")
            seeds += list(range(int(lo), int(hi) + 1)) if sep else [int(lo)]
    except ValueError:
        raise UserError(f"seeds {text!r}: expected e.g. 1-6 or 1,3,7-9") from None
    return seeds
