"""`fmfusion detect SCENE --models DIR --out DIR`: run the detection models on a scene's frames, into files."""

from __future__ import annotations

import argparse
from pathlib import Path

from fmfusion_jax.cli import HelpFormatter, options


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "detect",
        help="make detection files with the detection models (ONNX)",
        description="Runs a models folder's front end (a COCO detector + SAM + classifier, or RAM -> GroundingDINO "
        "-> SAM; see docs/detectors.md) on the frames of a scene that `fmfusion run` fuses (with the same "
        "--config and --set: by default the frames the camera-motion schedule picks; all of them on a sequence "
        "already subsampled in time) and writes one detection pair per frame (<frame>_label.json + "
        "<frame>_mask.png/.npy, the authors' format) for `fmfusion run --detections`. Rerun with the same "
        "arguments, it continues where it stopped (frames already written are kept).",
        formatter_class=HelpFormatter,
    )
    parser.add_argument(
        "scene",
        type=Path,
        help="scene folder (ScanNet or SceneNN layout, or a TUM, Replica or Redwood recording), a ROS bag, a "
        "Record3D .r3d export or a RealSense .bag / .db3 recording",
    )
    parser.add_argument(
        "--models",
        type=Path,
        required=True,
        metavar="DIR",
        help="models folder: a models.yaml naming each model's file, the shared layout (detector/, sam/, classifier/) "
        "or ram.onnx, groundingdino.onnx, sam_encoder.onnx, sam_decoder.onnx (docs/detectors.md)",
    )
    options.add_out(parser, required=True, metavar="DIR", help="detection folder to write (created)")
    options.add_layout(parser, help="scene layout")
    options.add_stride(parser, metavar="N", help="read every N-th frame of the sequence")
    parser.add_argument(
        "--every",
        type=int,
        default=None,
        metavar="N",
        help="detect on every N-th frame read instead of the frames the detection schedule fuses",
    )
    options.add_max_frames(parser, help="read at most N frames")
    parser.add_argument(
        "--providers",
        default="cpu",
        choices=("cpu", "cuda", "auto"),
        help="onnxruntime execution provider (cuda falls back to cpu when unavailable)",
    )
    parser.add_argument(
        "--mask-format", default="png", choices=("png", "npy"), help="png (overlapping masks fall back to npy) or npy"
    )
    grounded = parser.add_argument_group("RAM -> GroundingDINO -> SAM folders only (the config's front_end keys)")
    grounded.add_argument(
        "--box-threshold", type=float, metavar="T", help="GroundingDINO: a box needs a token score above this (0.35)"
    )
    grounded.add_argument(
        "--text-threshold", type=float, metavar="T", help="GroundingDINO: a label needs all its token scores above this (0.25)"
    )
    grounded.add_argument(
        "--prompt-window", type=int, metavar="N", help="detection frames whose labels augment the prompt (5; 0: none)"
    )
    options.add_config(
        parser, default="scannet", help="config of the `fmfusion run` to detect for (its schedule and front_end section)"
    )
    options.add_overrides(parser, help="override a config value, e.g. --set front_end.proposals=false (repeatable)")
    options.add_no_progress(parser, help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps.detect import run_detect  # lazy: the command's work loads only when it runs

    return run_detect(
        every=args.every,
        box_threshold=args.box_threshold,
        text_threshold=args.text_threshold,
        prompt_window=args.prompt_window,
        overrides=args.overrides,
        config_name=args.config,
        scene_dir=args.scene,
        layout=args.layout,
        stride=args.stride,
        max_frames=args.max_frames,
        models_dir=args.models,
        providers=args.providers,
        mask_format=args.mask_format,
        out=args.out,
        no_progress=args.no_progress,
    )
