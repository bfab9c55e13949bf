"""`fmfusion models check DIR`: validate a models folder and time its front end on this machine."""

from __future__ import annotations

import argparse
from pathlib import Path

from fmfusion_jax.cli import HelpFormatter


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "models",
        help="check a folder of foundation models (ONNX)",
        description="Commands on a models folder (the RAM + GroundingDINO + SAM layout, or the closed-set one: "
        "COCO detector + SAM + ImageNet classifier, with an optional models.yaml; see docs/detectors.md).",
    )
    commands = parser.add_subparsers(dest="models_command", metavar="ACTION", required=True)
    check = commands.add_parser(
        "check",
        help="validate the manifest and the models, run the front end once and time it",
        description="Reads the folder's models.yaml (or infers it from the files), opens every model against its "
        "contract, checks the vocabulary table, runs the whole front end on a generated image (and on "
        "--image) and prints the milliseconds per model. Exit status 1 when there is a problem.",
        formatter_class=HelpFormatter,
    )
    check.add_argument("models", type=Path, metavar="DIR", help="the models folder")
    check.add_argument("--image", type=Path, default=None, metavar="FILE", help="an image to run the front end on too")
    check.add_argument("--providers", default="cpu", choices=("cpu", "cuda", "auto"), help="onnxruntime execution provider")
    check.set_defaults(func=run_check)


def run_check(args: argparse.Namespace) -> int:
    from detectors.check import check_models_folder  # lazy: the command's work loads only when it runs

    result = check_models_folder(args.models, image=args.image, providers=args.providers)
    print(result.report())
    return 0 if result.ok else 1
