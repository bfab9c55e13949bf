"""`fmfusion simulate SCENE --out DIR`: simulated foundation-model detections from a scene's ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from fmfusion_jax.cli import options

# Kept equal to fmfusion_jax.simulation.noise.PRESETS (a test checks) without importing it at start-up.
PRESETS = (
    "clean",
    "default",
    "hard",
    "label_model",
    "partial",
    "merged",
    "border",
    "confusers",
    "persistent",
    "background",
    "texture",
)


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "simulate",
        help="simulate RAM/GroundingDINO/SAM detections from ground truth",
        description="Renders the ground-truth instances of each frame of a ScanNet scene (mesh labels looked up "
        "at the frame's depth, so occlusion is respected) and turns them into detections with the "
        "failure modes of the foundation models: open-set labels drawn from the statistical "
        "likelihood, missed tags (corrected by prompt augmentation), partial, split and merged "
        "masks, noisy borders, missed and false detections. Writes <frame>_label.json + "
        "<frame>_mask.{png,npy} in the authors' format and simulation.json (parameters, seed, "
        "statistics). Each frame is reproducible from the seed alone. See "
        "docs/simulated-detections.md for the noise model.",
    )
    parser.add_argument("scene", type=Path, help="ScanNet scene folder with its ground truth (mesh, segs, aggregation)")
    options.add_out(
        parser, required=True, metavar="DIR", help="output folder (new, empty, or a previous simulation's, which is replaced)"
    )
    options.add_seed(parser, help="random seed (default 0)")
    parser.add_argument(
        "--noise-preset",
        default="default",
        choices=PRESETS,
        help="clean: ground-truth masks with each class's most likely label; default: the "
        "documented noise; hard: more of every failure mode; label_model, partial, merged, "
        "border, confusers, persistent, background, texture: a noise family of the zoo at severity 1 "
        "(misspecified labels, partial masks, masks merged with a neighbour, borders bleeding onto floor and "
        "wall, confusers and false blobs with miscalibrated scores, phantoms fixed in the world, background "
        "taken for furniture, over-segmented textures), on top of default "
        "(default: default)",
    )
    options.add_overrides(
        parser,
        metavar="NAME=VALUE",
        help="override one noise parameter, e.g. --set missed_tag_prob=0.4 or, with "
        "--noise-preset border, --set bleed_px=8 (repeatable; value parsed as YAML)",
        dest="set",
    )
    parser.add_argument("--no-prompt-augmentation", action="store_true", help="leave missed tags uncorrected (ablation B)")
    options.add_stride(parser, help="read every N-th frame of the sequence (default 1)")
    parser.add_argument(
        "--every",
        type=int,
        default=1,
        help="simulate the frames whose index is a multiple of N: the detection frames of the "
        "fusion (default 1: all frames read)",
    )
    options.add_max_frames(parser, help="stop after N simulated frames")
    parser.add_argument(
        "--mask-format",
        default="png",
        choices=("png", "npy"),
        help="png: one uint8 label image per frame (authors' compact format); npy: (K, H, W) stack (default: png)",
    )
    parser.add_argument(
        "--render-stride",
        type=int,
        default=2,
        help="pixel stride of the ground-truth rendering, upsampled by nearest neighbour (default 2)",
    )
    parser.add_argument(
        "--max-distance",
        type=float,
        default=0.05,
        help="m; depth farther than this from the ground-truth mesh stays unlabelled (default 0.05)",
    )
    options.add_layout(parser, choices=("auto", "scannet"), help="default: auto")
    options.add_depth_max(parser)
    options.add_no_progress(parser, help="no progress bar")
    parser.add_argument("--quiet", action="store_true", help="no progress bar and no summary")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps.simulate import run_simulate  # lazy: the command's work loads only when it runs

    return run_simulate(
        max_frames=args.max_frames,
        noise_set=args.set,
        seed=args.seed,
        no_prompt_augmentation=args.no_prompt_augmentation,
        noise_preset=args.noise_preset,
        scene_dir=args.scene,
        layout=args.layout,
        stride=args.stride,
        depth_max=args.depth_max,
        out=args.out,
        render_stride=args.render_stride,
        every=args.every,
        mask_format=args.mask_format,
        max_distance=args.max_distance,
        quiet=args.quiet,
        no_progress=args.no_progress,
    )
