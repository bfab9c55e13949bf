"""`fmfusion experiment`: the Kimera-style baseline, the ablations and FM-Fusion on a set of scenes, scored
in the layout of the paper's Tables I and II; with `--robustness`, the methods against the noise zoo."""

from __future__ import annotations

import argparse
from pathlib import Path

from fmfusion_jax.apps import experiments, robustness
from fmfusion_jax.apps.experiments import (
    DEFAULT_GENERATED,
    DEFAULT_GENERATED_FRAMES,
    DEFAULT_GENERATED_OBJECTS,
    DEFAULT_OUT,
    QUICK_GENERATED,
    QUICK_REAL_FRAMES,
    default_real_scenes,
    generated_specs,
)
from fmfusion_jax.cli import options
from fmfusion_jax.comparison.methods import DEFAULT_METHODS, METHODS, resolve_methods
from fmfusion_jax.errors import UserError


def register(subparsers) -> None:
    methods = "; ".join(f"{m.name}: {m.title}" for m in METHODS.values())
    parser = subparsers.add_parser(
        "experiment",
        help="baseline (Kimera + Cluster-All) and ablations vs FM-Fusion on several scenes",
        description="Runs the Kimera-style baseline, ablations A (manual likelihood), B (no prompt augmentation) "
        "and C (no refinement) and FM-Fusion on real ScanNet-layout scenes and generated rooms, with "
        "detections simulated from each scene's ground truth (cached), and scores every method over "
        "all scenes with the ScanNet benchmark. Writes OUT/experiment.md (Table I: AP50 per class; "
        "Table II: mAP, mAP50, mAP25), OUT/experiment.json (every number, per scene too, configs, "
        "noise, timings) and OUT/runs/<scene>/<method>/ (run.json, benchmark predictions). "
        "With --robustness: every method against every noise model of the noise zoo instead "
        "(OUT/robustness.md, .json, .png; runs in OUT/runs/<scene>/<zoo entry>/<method>/). "
        f"Methods: {methods}.",
    )
    parser.add_argument(
        "--scenes",
        nargs="*",
        type=Path,
        default=None,
        metavar="PATH",
        help="real scenes (ScanNet layout, with ground truth); default: "
        "../shared/data/scannet/scene0000_00 when present (not with --quick); "
        "`--scenes` alone: none",
    )
    parser.add_argument(
        "--detections",
        type=str,
        default=None,
        metavar="DIR",
        help="detection files of the real scenes instead of simulated ones (real detections made with `fmfusion "
        "detect`): a folder, or a pattern with {scene} for several scenes; every method reads the same files "
        "(ablation B too: their prompts are whatever the detector used); not with --robustness",
    )
    parser.add_argument(
        "--generated",
        type=int,
        default=None,
        metavar="N",
        help=f"generated rooms, seeds 1..N (default {DEFAULT_GENERATED}, with --robustness "
        f"{robustness.DEFAULT_GENERATED}; --quick: {QUICK_GENERATED['count']})",
    )
    parser.add_argument(
        "--generated-frames",
        type=int,
        default=None,
        metavar="N",
        help=f"frames of each generated room (default {DEFAULT_GENERATED_FRAMES}; --quick: {QUICK_GENERATED['num_frames']})",
    )
    parser.add_argument(
        "--generated-objects",
        type=int,
        default=None,
        metavar="N",
        help=f"objects in each generated room (default {DEFAULT_GENERATED_OBJECTS}; --quick: {QUICK_GENERATED['num_objects']})",
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        default=None,
        metavar="NAME",
        help=f"methods to run, some of: {', '.join(METHODS)} (default: {' '.join(DEFAULT_METHODS)}; "
        f"with --robustness: {' '.join(robustness.DEFAULT_METHODS)})",
    )
    options.add_seed(
        parser, default=None, help="seed of the simulated detections (default 0; with --robustness use --noise-seed)"
    )
    options.add_out(
        parser, default=None, help=f"output folder (default {DEFAULT_OUT}; with --robustness {robustness.DEFAULT_OUT})"
    )
    parser.add_argument(
        "--robustness",
        action="store_true",
        help="robustness evaluation: each method on each scene crossed with the noise zoo "
        "(one noise model per failure family plus --mixed random mixtures), scored per zoo "
        "entry, summarized per family, mean and worst entry",
    )
    parser.add_argument(
        "--mixed",
        type=int,
        default=None,
        metavar="N",
        help=f"with --robustness: random mixtures of the noise families in the zoo (default "
        f"{robustness.DEFAULT_MIXED}; --quick: {robustness.QUICK_MIXED})",
    )
    parser.add_argument(
        "--noise-seed",
        type=int,
        default=None,
        metavar="S",
        help="with --robustness: seed of the zoo's mixtures and of every simulated detection (default 0)",
    )
    parser.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="folder of the generated scenes and simulated detections, reused between experiments (default: OUT/cache)",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"smoke test: generated rooms of {QUICK_GENERATED['num_frames']} frames at "
        f"{QUICK_GENERATED['width']}x{QUICK_GENERATED['height']}, real scenes (only those named) "
        f"cut to {QUICK_REAL_FRAMES} frames; with --robustness also a zoo of one mixture",
    )
    options.add_overrides(
        parser,
        help="override a config value for every method, e.g. --set detections.every=2 "
        "(repeatable; a method's own setting, such as ablation A's likelihood, wins)",
    )
    options.add_no_progress(parser, help="no progress bars or per-run lines")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.detections is not None and args.robustness:
        raise UserError("--detections: the robustness evaluation simulates its detections (the noise zoo)")
    if args.robustness:
        if args.seed is not None:
            raise UserError("--seed is the plain experiment's; with --robustness the zoo's seed is --noise-seed")
        if args.mixed is not None and args.mixed < 0:
            raise UserError(f"--mixed must be >= 0 (got {args.mixed})")
        if args.noise_seed is not None and args.noise_seed < 0:
            raise UserError(f"--noise-seed must be >= 0 (got {args.noise_seed})")
    else:
        given = [flag for flag, value in (("--mixed", args.mixed), ("--noise-seed", args.noise_seed)) if value is not None]
        if given:
            raise UserError(f"{' and '.join(given)}: only with --robustness")
    resolve_methods(args.methods or (robustness.DEFAULT_METHODS if args.robustness else None))  # fail early
    quick = (robustness.QUICK_GENERATED if args.robustness else QUICK_GENERATED) if args.quick else {}
    default_count = robustness.DEFAULT_GENERATED if args.robustness else DEFAULT_GENERATED
    count = args.generated if args.generated is not None else quick.get("count", default_count)
    frames = args.generated_frames or quick.get("num_frames", DEFAULT_GENERATED_FRAMES)
    objects = args.generated_objects or quick.get("num_objects", DEFAULT_GENERATED_OBJECTS)
    if args.generated_frames is not None and args.generated_frames < 2:
        raise UserError(f"--generated-frames must be >= 2 (got {args.generated_frames})")
    if args.generated_objects is not None and args.generated_objects < 1:
        raise UserError(f"--generated-objects must be >= 1 (got {args.generated_objects})")
    specs = generated_specs(count, frames, objects, quick.get("width", 640), quick.get("height", 480))
    if args.scenes is None:
        real = [] if args.quick else default_real_scenes()
    else:
        real = args.scenes
    if args.robustness:
        mixed = args.mixed if args.mixed is not None else (robustness.QUICK_MIXED if args.quick else robustness.DEFAULT_MIXED)
        robust = robustness.run_robustness(
            args.out or robustness.DEFAULT_OUT,
            real_scenes=real,
            generated=specs,
            methods=args.methods,
            noise_seed=args.noise_seed or 0,
            mixed=mixed,
            cache_dir=args.cache,
            overrides=args.overrides,
            real_max_frames=QUICK_REAL_FRAMES if args.quick else None,
            progress=not args.no_progress,
        )
        print(robust.text)
        return 0
    result = experiments.run_experiment(
        args.out or DEFAULT_OUT,
        real_scenes=real,
        generated=specs,
        methods=args.methods,
        seed=args.seed or 0,
        cache_dir=args.cache,
        overrides=args.overrides,
        real_max_frames=QUICK_REAL_FRAMES if args.quick else None,
        progress=not args.no_progress,
        real_detections=args.detections,
    )
    print(result.text)
    return 0
