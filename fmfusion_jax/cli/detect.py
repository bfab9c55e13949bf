"""`fmfusion detect SCENE --models DIR --out DIR`: run RAM + GroundingDINO + SAM on a scene's frames."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from fmfusion_jax.cli import HelpFormatter
from fmfusion_jax.errors import UserError


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "detect",
        help="make detection files with the foundation models (ONNX)",
        description="Runs the foundation-model front end (RAM tagger -> prompt augmentation -> GroundingDINO -> "
        "SAM, as ONNX models) on every N-th frame of a scene and writes one detection pair per frame "
        "(<frame>_label.json + <frame>_mask.png/.npy, the authors' format) for `fmfusion run "
        "--detections`. The models folder layout and how to export the models: docs/detectors.md.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("scene", type=Path, help="scene folder (ScanNet or SceneNN layout)")
    parser.add_argument(
        "--models",
        type=Path,
        required=True,
        metavar="DIR",
        help="folder with ram.onnx, ram_tag_list.txt, groundingdino.onnx, vocab.txt, sam_encoder.onnx, sam_decoder.onnx",
    )
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="detection folder to write (created)")
    parser.add_argument("--layout", default="auto", choices=("auto", "scannet", "scenenn"), help="scene layout")
    parser.add_argument("--stride", type=int, default=1, metavar="N", help="read every N-th frame of the sequence")
    parser.add_argument(
        "--every",
        type=int,
        default=10,
        metavar="N",
        help="detect on every N-th frame read (0, N, 2N, ...: the frames `fmfusion run` fuses with "
        "detections.every=N and the same stride)",
    )
    parser.add_argument("--max-frames", type=int, default=None, metavar="N", help="read at most N frames")
    parser.add_argument(
        "--providers",
        default="cpu",
        choices=("cpu", "cuda", "auto"),
        help="onnxruntime execution provider (cuda falls back to cpu when unavailable)",
    )
    parser.add_argument(
        "--mask-format", default="png", choices=("png", "npy"), help="png (overlapping masks fall back to npy) or npy"
    )
    parser.add_argument(
        "--box-threshold", type=float, default=0.35, metavar="T", help="GroundingDINO: a box needs a token score above this"
    )
    parser.add_argument(
        "--text-threshold",
        type=float,
        default=0.25,
        metavar="T",
        help="GroundingDINO: a label needs all its token scores above this",
    )
    parser.add_argument(
        "--prompt-window",
        type=int,
        default=5,
        metavar="N",
        help="detection frames whose labels augment the prompt (0: no augmentation)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from detectors import DetectorConfig, FoundationModels
    from fmfusion_jax.io.detections import write_frame_detections
    from fmfusion_jax.io.scene import open_scene

    if args.every < 1:
        raise UserError(f"--every must be a positive integer, got {args.every}")
    scene = open_scene(args.scene, layout=args.layout, stride=args.stride, max_frames=args.max_frames)
    config = DetectorConfig(
        box_threshold=args.box_threshold, text_threshold=args.text_threshold, prompt_window=args.prompt_window
    )
    models = FoundationModels.from_folder(args.models, providers=args.providers, config=config)
    positions = list(range(0, len(scene), args.every))
    detections_total, started = 0, time.perf_counter()
    with tqdm(positions, desc=f"detect {scene.name}", unit="frame", disable=args.no_progress) as bar:
        for position in bar:
            name = scene.frame_names[position]
            detections = models.detect(scene.read_color(position), name)
            write_frame_detections(args.out, detections, mask_format=args.mask_format)
            detections_total += detections.num_detections
            bar.set_postfix(detections=detections.num_detections)
    elapsed = time.perf_counter() - started
    frames = max(len(positions), 1)
    stages = ", ".join(f"{stage} {1000 * seconds / frames:.0f} ms" for stage, seconds in models.timings.items())
    print(
        f"{len(positions)} frames of {scene.name} (every {args.every} of {len(scene)} read, stride {args.stride}) "
        f"-> {detections_total} detections in {args.out}"
    )
    print(f"per frame: {1000 * elapsed / frames:.0f} ms ({stages}); providers {', '.join(models.providers)}")
    return 0
