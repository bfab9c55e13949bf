"""`fmfusion likelihood summarize | calibrate`: the label likelihood from data (Appendix B), and fitted."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from fmfusion_jax.cli import HelpFormatter, options
from fmfusion_jax.errors import UserError


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


def _add_generated_arguments(parser: argparse.ArgumentParser) -> None:
    from fmfusion_jax.apps.likelihood import DEFAULT_CACHE, GeneratedSize

    size = GeneratedSize()
    group = parser.add_argument_group("generated scenes (made once, cached)")
    group.add_argument(
        "--cache", type=Path, default=DEFAULT_CACHE, help="folder of the generated scenes and simulated detections"
    )
    group.add_argument("--objects", type=int, default=size.num_objects, help="objects per generated room")
    group.add_argument("--frames", type=int, default=size.num_frames, help="frames per generated scene")
    group.add_argument("--width", type=int, default=size.width, help="image width of generated scenes")
    group.add_argument("--height", type=int, default=size.height, help="image height of generated scenes")
    options.add_no_progress(parser, help="no progress bars")


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "likelihood",
        help="summarize the label likelihood from data, or calibrate it",
        description="The label likelihood L[o, c] = p(y = o, o in prompt | c) of the label fusion: summarized "
        "from frames with ground truth and detections (paper, Appendix B), or fitted by gradient "
        "descent through the fused label distribution.",
    )
    commands = parser.add_subparsers(dest="likelihood_command", metavar="ACTION", required=True)

    summarize = commands.add_parser(
        "summarize",
        help="tagging x detection likelihood from scenes with ground truth and detections",
        description="Counts, over every detection frame of the scenes, the closed-class ground-truth instances "
        "visible in the frame (rendered from the annotated mesh at the frame's depth), the frame's "
        "prompt, and the detection matched to each instance (mask IoU >= 0.5), then writes the "
        "tagging likelihood p(o in prompt | c), the detection likelihood p(y = o | o in prompt, c) "
        "and their product, the 38 x 20 likelihood matrix: likelihood.csv (the format of "
        "configs/labels/likelihood_statistical.csv, usable as --set label_fusion.likelihood=PATH), "
        "tagging.csv, detection.csv, a heat map of each (PNG) and counts.json.",
        formatter_class=HelpFormatter,
    )
    summarize.add_argument(
        "scenes",
        type=Path,
        nargs="*",
        metavar="SCENE",
        help="ScanNet-layout scene folders with their ground truth (mesh, segs, aggregation)",
    )
    summarize.add_argument(
        "--detections",
        type=Path,
        nargs="+",
        default=None,
        metavar="DIR",
        help="detection folder of each SCENE, in order (default: detections simulated from "
        "the scene's ground truth into --cache)",
    )
    summarize.add_argument(
        "--generated", type=int, default=0, metavar="N", help="also N generated scenes (seeds 1..N) with simulated detections"
    )
    options.add_out(summarize, required=True, help="output folder (created)")
    summarize.add_argument(
        "--min-pixels",
        type=int,
        default=None,
        help="least pixels of a visible ground-truth instance (default: 400 at 640x480, scaled with the image area)",
    )
    summarize.add_argument(
        "--label-rule",
        choices=("main", "weighted"),
        default="main",
        help="main: a detection counts as its highest-score label; weighted: spread over its labels by score",
    )
    _add_generated_arguments(summarize)
    summarize.set_defaults(func=run_summarize)

    calibrate = commands.add_parser(
        "calibrate",
        help="fit the likelihood to ground-truth classes by gradient descent; compare on held-out scenes",
        description="Fuses the training scenes once with the initial likelihood, collects each instance matched "
        "to ground truth (vertex IoU >= 0.5) with its open-set label histogram h, and fits L to "
        "maximize p(true class | h @ L) under the additive fusion (Adam on logits: each column a "
        "softmax over the 38 labels and a dropped 'not detected' entry, so L >= 0 and columns sum "
        "to <= 1), with the L2 pull toward the initial logits and the number of Adam steps chosen by "
        "K-fold cross-validation over the training scenes unless given. Then fuses each held-out scene "
        "with the manual, statistical, summarized (from the training scenes) and calibrated matrices "
        "and reports label accuracy, loss and the ScanNet "
        "benchmark (mAP50): report.md, report.json, calibrated.csv, heat maps.",
        formatter_class=HelpFormatter,
    )
    calibrate.add_argument("--train", default="1-16", metavar="SEEDS", help="seeds of the generated training scenes")
    calibrate.add_argument("--test", default="17-19", metavar="SEEDS", help="seeds of the generated held-out scenes")
    calibrate.add_argument(
        "--test-real",
        type=Path,
        nargs="*",
        default=None,
        metavar="SCENE",
        help="real held-out scenes, with simulated detections (default: the shared "
        "../shared/data/scannet/scene0000_00 when present; give none to leave it out)",
    )
    calibrate.add_argument("--real-config", default="scannet-subsampled", help="config the real scenes are fused with")
    options.add_out(calibrate, required=True, help="output folder (created)")
    calibrate.add_argument(
        "--init", default="statistical", help="initial matrix: statistical, manual or a CSV path (the training runs use it)"
    )
    calibrate.add_argument(
        "--parametrization",
        choices=("column", "entry"),
        default="column",
        help="column: per class a softmax over the labels and 'not detected' (columns sum "
        "<= 1); entry: each entry a sigmoid in (0, 1)",
    )
    calibrate.add_argument(
        "--steps",
        type=int,
        default=None,
        help="Adam steps (default: chosen by cross-validation, early stopping up to --max-steps)",
    )
    calibrate.add_argument("--max-steps", type=int, default=500, help="the most steps cross-validation considers")
    calibrate.add_argument("--lr", type=float, default=0.05, help="Adam learning rate (on the logits)")
    calibrate.add_argument(
        "--l2",
        type=float,
        default=None,
        help="weight of the pull toward the initial logits (default: chosen by cross-validation from --l2-grid)",
    )
    calibrate.add_argument(
        "--l2-grid", default="0,1e-3,1e-2,1e-1,1,10,100", metavar="L2,...", help="candidate l2 weights of the cross-validation"
    )
    calibrate.add_argument(
        "--folds", type=int, default=4, help="cross-validation folds (training scenes dealt round-robin; no scene in two folds)"
    )
    calibrate.add_argument(
        "--min-class-instances", type=int, default=3, help="classes with fewer training instances keep their initial column"
    )
    _add_generated_arguments(calibrate)
    calibrate.set_defaults(func=run_calibrate)


def _size(args: argparse.Namespace):
    from fmfusion_jax.apps.likelihood import GeneratedSize

    if args.objects < 1 or args.frames < 2 or args.width < 32 or args.height < 24:
        raise UserError("generated scenes need at least 1 object, 2 frames and 32x24 pixels")
    return GeneratedSize(args.objects, args.frames, args.width, args.height)


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def run_summarize(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps import likelihood as workflow
    from fmfusion_jax.likelihood.summarize import estimate, write_summary
    from fmfusion_jax.runner import prepare_output_dir

    if not args.scenes and args.generated < 1:
        raise UserError("give SCENE folders and/or --generated N")
    if args.detections is not None and len(args.detections) != len(args.scenes):
        raise UserError(f"--detections needs one folder per SCENE ({len(args.scenes)} scenes, {len(args.detections)} folders)")
    for scene in args.scenes:
        if not scene.is_dir():
            raise UserError(f"scene folder {scene} does not exist")
    start = time.perf_counter()
    prepare_output_dir(args.out)
    progress = not args.no_progress
    detections = args.detections or [None] * len(args.scenes)
    cases = [workflow.real_case(scene, det, args.cache, progress=progress) for scene, det in zip(args.scenes, detections)]
    if args.generated:
        _say(f"preparing {args.generated} generated scenes in {args.cache} ...")
        cases += workflow.generated_cases(range(1, args.generated + 1), args.cache, _size(args), progress)
    counts = workflow.summarize_cases(cases, min_pixels=args.min_pixels, label_rule=args.label_rule, progress=progress)
    if counts.instances == 0:
        raise UserError("no ground-truth instance of a closed class was visible in any detection frame")
    write_summary(
        args.out,
        counts,
        sources=[f"{c.name}: {c.detections_dir}" for c in cases],
        settings={"label_rule": args.label_rule, "min_pixels": args.min_pixels},
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
    print(f"outputs in {args.out}: likelihood.csv/.png, tagging.csv/.png, detection.csv/.png, counts.json")
    return 0


def run_calibrate(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps import likelihood as workflow
    from fmfusion_jax.labels import load_likelihood
    from fmfusion_jax.runner import prepare_output_dir

    for name in ("steps", "max_steps"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise UserError(f"--{name.replace('_', '-')} must be >= 1")
    if args.lr <= 0 or (args.l2 is not None and args.l2 < 0):
        raise UserError("--lr must be > 0 and --l2 >= 0")
    try:
        l2_grid = tuple(float(v) for v in args.l2_grid.split(",") if v.strip())
    except ValueError:
        raise UserError(f"--l2-grid {args.l2_grid!r}: expected comma-separated numbers") from None
    if not l2_grid or min(l2_grid) < 0:
        raise UserError("--l2-grid needs at least one weight, all >= 0")
    cross_validated = args.l2 is None or args.steps is None
    if cross_validated and args.folds < 2:
        raise UserError("--folds must be >= 2")
    try:
        load_likelihood(args.init)
    except (OSError, ValueError) as error:
        raise UserError(f"--init {args.init}: {error}") from None
    train_seeds, test_seeds = parse_seeds(args.train), parse_seeds(args.test)
    if not train_seeds:
        raise UserError("--train needs at least one seed")
    if cross_validated and len(train_seeds) < 2:
        raise UserError("cross-validation needs at least 2 training seeds (or give both --l2 and --steps)")
    if set(train_seeds) & set(test_seeds):
        raise UserError(f"seeds {sorted(set(train_seeds) & set(test_seeds))} are both training and held-out scenes")
    real = args.test_real
    if real is None:
        found = workflow.default_real_scene()
        real = [found] if found is not None else []
    start = time.perf_counter()
    prepare_output_dir(args.out)
    progress = not args.no_progress
    size = _size(args)
    _say(f"preparing {len(train_seeds) + len(test_seeds)} generated scenes in {args.cache} ...")
    train = workflow.generated_cases(train_seeds, args.cache, size, progress)
    test = workflow.generated_cases(test_seeds, args.cache, size, progress)
    test += [workflow.real_case(scene, None, args.cache, args.real_config, progress) for scene in real]
    settings = workflow.CalibrationSettings(
        init=args.init,
        parametrization=args.parametrization,
        steps=args.steps,
        learning_rate=args.lr,
        l2=args.l2,
        folds=args.folds,
        l2_grid=l2_grid,
        max_steps=args.max_steps,
        min_class_instances=args.min_class_instances,
    )
    report = workflow.calibrate_and_compare(train, test, args.out, settings, progress=progress, say=_say)
    print(workflow.report_markdown(report))
    print(
        f"done in {time.perf_counter() - start:.0f} s; outputs in {args.out}: report.md, report.json, "
        "calibrated.csv/.png, difference.png, loss.csv, validation.csv, summarized/"
    )
    return 0
