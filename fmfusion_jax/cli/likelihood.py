"""`fmfusion likelihood summarize | calibrate`: the label likelihood from data (Appendix B), and fitted."""

from __future__ import annotations

import argparse
from pathlib import Path

from fmfusion_jax.apps.likelihood.workflow import DEFAULT_CACHE, GeneratedSize
from fmfusion_jax.cli import HelpFormatter, options


def _add_generated_arguments(parser: argparse.ArgumentParser) -> None:
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


def run_summarize(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps.likelihood.commands import (
        run_summarize as summarize,  # lazy: the command's work loads only when it runs
    )

    return summarize(
        args.scenes,
        args.detections,
        args.generated,
        args.out,
        args.cache,
        args.objects,
        args.frames,
        args.width,
        args.height,
        min_pixels=args.min_pixels,
        label_rule=args.label_rule,
        progress=not args.no_progress,
    )


def run_calibrate(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps.likelihood.commands import (
        run_calibrate as calibrate,  # lazy: the command's work loads only when it runs
    )

    return calibrate(
        args.train,
        args.test,
        args.test_real,
        args.real_config,
        args.out,
        args.cache,
        args.objects,
        args.frames,
        args.width,
        args.height,
        init=args.init,
        parametrization=args.parametrization,
        steps=args.steps,
        max_steps=args.max_steps,
        lr=args.lr,
        l2=args.l2,
        l2_grid=args.l2_grid,
        folds=args.folds,
        min_class_instances=args.min_class_instances,
        progress=not args.no_progress,
    )
