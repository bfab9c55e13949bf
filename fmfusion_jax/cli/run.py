"""`fmfusion run`: fuse a scene's frames and detections into an instance map and write its outputs."""

from __future__ import annotations

import argparse
from pathlib import Path

from fmfusion_jax.cli import HelpFormatter, options
from fmfusion_jax.run.outputs import output_names, outputs_help


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "run",
        help="fuse a scene and its detections into an instance map",
        description="Fuses an RGB-D scene (ScanNet or SceneNN layout, a TUM, Replica or Open3D/Redwood "
        "recording, a ROS bag, a Record3D .r3d export or a RealSense recording: "
        "docs/your-own-data.md) and its open-set detections (authors' "
        "file format) into a map of 3D instances, then writes the map into --out. With ground truth (the scene's "
        "_vh_clean_2.ply mesh), it also scores the map (report.json). Without --detections or --models it builds the "
        "geometry alone: every frame into the TSDF, no instance (mesh.ply, map_state.npz, an empty instances.json).",
        epilog=outputs_help(),
        formatter_class=HelpFormatter,
    )
    parser.add_argument("scene", type=Path, help="scene folder")
    source = parser.add_mutually_exclusive_group()
    source.add_argument(
        "--detections", type=Path, help="folder of precomputed detections (frame-XXXXXX_label.json + _mask.png/.npy)"
    )
    source.add_argument(
        "--models", type=Path, help="run the foundation models online instead: folder of ONNX exports (see docs/detectors.md)"
    )
    # neither: the map of the geometry alone (every frame into the TSDF, no instance)
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
    parser.add_argument(
        "--outputs",
        nargs="+",
        metavar="NAME",
        help="write only these outputs (their names: " + ", ".join(output_names()) + "; run.json always; default: all)",
    )
    options.add_no_progress(parser, help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps.fuse import run_scene  # lazy: the command's work loads only when it runs

    return run_scene(
        scene_dir=args.scene,
        checkpoint_every=args.checkpoint_every,
        config_name=args.config,
        overrides=args.overrides,
        out=args.out,
        detections=args.detections,
        models=args.models,
        overwrite=args.overwrite,
        providers=args.providers,
        viewer=args.viewer,
        viewer_save=args.viewer_save,
        no_progress=args.no_progress,
        on_error=args.on_error,
        resume=args.resume,
        restart=args.restart,
        verbose=args.verbose,
        outputs=args.outputs,
    )
