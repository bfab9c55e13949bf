"""`fmfusion run`: fuse a scene's frames and detections into an instance map and write its outputs."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fmfusion_jax.cli import HelpFormatter, options
from fmfusion_jax.errors import UserError


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "run",
        help="fuse a scene and its detections into an instance map",
        description="Fuses an RGB-D scene (ScanNet or SceneNN layout) and its open-set detections (authors' "
        "file format) into a map of 3D instances, then writes the map: instances.json, PLY clouds "
        "(semantic.ply, instances.ply, one per instance), mesh.ply, the ScanNet benchmark "
        "prediction files (when the scene has its _vh_clean_2.ply mesh), the config used and "
        "run.json with timings. With ground truth, it also scores the map (report.json).",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("scene", type=Path, help="scene folder")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--detections", type=Path, help="folder of precomputed detections (frame-XXXXXX_label.json + _mask.png/.npy)"
    )
    source.add_argument(
        "--models", type=Path, help="run the foundation models online instead: folder of ONNX exports (see docs/detectors.md)"
    )
    parser.add_argument(
        "--providers", default="cpu", choices=("cpu", "cuda", "auto"), help="onnxruntime execution providers for --models"
    )
    options.add_out(
        parser,
        required=True,
        help="output folder (created; an earlier run's output folder is replaced, any other folder with files is "
        "refused unless --overwrite, and never one holding the scene, the detections or the models)",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="replace --out even when it is not an earlier run's output folder"
    )
    options.add_config(parser, default="scannet", help="config file, or a packaged one: scannet, scannet-subsampled, scenenn")
    options.add_overrides(parser, help="override a config value, e.g. --set detections.every=1 (repeatable)")
    parser.add_argument(
        "--on-error",
        choices=("skip", "stop"),
        default="skip",
        help="a frame whose image or detection file cannot be read: skip it with a warning naming "
        "the file (listed in run.json), or stop the run",
    )
    parser.add_argument(
        "--checkpoint-every",
        type=int,
        default=0,
        metavar="N",
        help="write a checkpoint every N frames into OUT.partial (always on Ctrl-C, SIGTERM, SIGHUP); 0: by time, "
        "after 2 minutes and at most 3 %% of the run",
    )
    resume = parser.add_mutually_exclusive_group()
    resume.add_argument(
        "--resume", action="store_true", help="continue an interrupted run from its checkpoint in OUT.partial (same arguments)"
    )
    resume.add_argument("--restart", action="store_true", help="discard an interrupted run's checkpoint")
    parser.add_argument("--viewer", choices=("rerun",), help="show the fusion live in a Rerun viewer (the viewer extra)")
    parser.add_argument(
        "--viewer-save",
        type=Path,
        metavar="FILE.rrd",
        help="record the live view to a Rerun file instead of opening a window (headless)",
    )
    options.add_no_progress(parser, help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fmfusion_jax.cli.interrupt import StopRequest
    from fmfusion_jax.config import load_config
    from fmfusion_jax.io.scene import open_dataset_scene
    from fmfusion_jax.runner import check_output_folder, prepare_output_dir, run_and_export
    from fmfusion_jax.sources import open_detection_source

    if not args.scene.is_dir():
        raise UserError(f"scene folder {args.scene} does not exist")
    if args.checkpoint_every < 0:
        raise UserError(f"--checkpoint-every must be >= 0, got {args.checkpoint_every}")
    config = load_config(args.config, args.overrides)
    check_output_folder(args.out, (args.scene, args.detections, args.models), args.overwrite)
    prepare_output_dir(args.out, create=False)  # a bad --out fails now, not after the fusion
    scene = open_dataset_scene(args.scene, config.dataset)
    source = open_detection_source(scene, detections=args.detections, models=args.models, providers=args.providers, config=config)
    observer = None
    if args.viewer or args.viewer_save:
        from fmfusion_jax.viz.live import RerunView

        observer = RerunView(save=args.viewer_save, spawn=args.viewer_save is None)
    with StopRequest(
        "stopping after the frame being fused, then writing a checkpoint and the map so far (outputs "
        "already being written are finished); Ctrl-C again to exit at once"
    ) as stop:
        outcome = run_and_export(
            scene,
            source,
            config,
            args.out,
            progress=not args.no_progress,
            on_error=args.on_error,
            checkpoint_every=args.checkpoint_every,
            resume=args.resume,
            restart=args.restart,
            should_stop=stop,
            time_stages=args.verbose > 0,
            observer=observer,
        )
    print(outcome.summary)
    if not outcome.complete:
        print(
            f"interrupted: the map so far is in {outcome.folder}; continue with the same command plus --resume", file=sys.stderr
        )
        return stop.exit_status
    return 0
