"""`fmfusion info SCENE`: what a scene folder holds, from its poses and a sample of its depth images."""

from __future__ import annotations

import argparse
from pathlib import Path

from fmfusion_jax.apps.info import SAMPLED_FRAMES
from fmfusion_jax.cli import options


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "info",
        help="summarize a scene folder (and a detection folder)",
        description="Summarizes a scene folder (ScanNet or SceneNN layout, or a TUM, Replica or Open3D/Redwood "
        "recording), a ROS bag, a Record3D .r3d export or a RealSense recording "
        "(docs/your-own-data.md): frames, camera, depth range, world bounds, "
        "trajectory, ground-truth files; with --detections, the detection files. Reads the poses and "
        f"{SAMPLED_FRAMES} depth images, so it takes a few seconds at most.",
    )
    parser.add_argument(
        "scene",
        type=Path,
        help="scene folder (ScanNet color/ depth/ pose/ intrinsic/, SceneNN, TUM, Replica, Redwood), ROS bag, .r3d "
        "or RealSense .bag / .db3 file",
    )
    options.add_layout(parser, help="default: auto")
    options.add_stride(parser, help="use every N-th frame (default 1)")
    options.add_depth_max(parser)
    parser.add_argument(
        "--detections", type=Path, metavar="DIR", help="folder of <frame>_label.json + <frame>_mask.{npy,png} detection files"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps.info import run_info  # lazy: the command's work loads only when it runs

    return run_info(
        scene_dir=args.scene,
        layout=args.layout,
        stride=args.stride,
        depth_max=args.depth_max,
        detections=args.detections,
    )
