"""`fmfusion batch DATASET --out OUT`: `fmfusion run` over many scenes, with one pooled benchmark."""

from __future__ import annotations

import argparse
from pathlib import Path

from fmfusion_jax.cli import HelpFormatter, options


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "batch",
        help="fuse and score many scenes (a folder of scenes or a split file), locally or on Ray",
        description="Runs `fmfusion run` on every scene of a dataset, each scene in a process of its own "
        "(a scene that fails or runs past --scene-timeout is recorded and the batch goes on), writes each "
        "scene's outputs into OUT/<scene>/, and at the end the ScanNet benchmark pooled over all scored scenes "
        "with a per-scene table (OUT/batch.md, batch.csv, batch.json). --resume skips the scenes already done.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument(
        "dataset",
        type=Path,
        help="a folder of scenes (scene folders, recording folders and files: .bag, .db3, .r3d), or a split file of scene ids",
    )
    parser.add_argument("--root", type=Path, help="folder of the scenes of a split file (default: the file's folder)")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--detections", metavar="PATTERN", help="each scene's detection folder: {scene} is its name, {root} its parent"
    )
    source.add_argument("--simulate", action="store_true", help="simulate each scene's detections from its ground truth")
    source.add_argument(
        "--models",
        type=Path,
        metavar="DIR",
        help="detect with the models of DIR (`fmfusion detect`, into OUT/_detections/<scene>, continued on --resume)",
    )
    options.add_out(parser, required=True, help="output folder")
    parser.add_argument("--workers", type=int, default=1, help="scenes fused at once on this machine (default 1)")
    parser.add_argument("--ray", metavar="ADDRESS", help="run one Ray task per scene on this cluster (auto, local or an address)")
    parser.add_argument("--ray-cpus", type=float, default=1.0, metavar="N", help="CPUs a scene's Ray task declares")
    parser.add_argument("--ray-gpus", type=float, default=0.0, metavar="N", help="GPUs a scene's Ray task declares")
    parser.add_argument(
        "--batch",
        type=int,
        metavar="K",
        help="fuse K scenes at once in this process, vmapped on one device (built for a GPU: on a CPU, --workers is faster)",
    )
    parser.add_argument("--resume", action="store_true", help="skip the scenes whose outputs are complete")
    parser.add_argument("--scene-timeout", type=float, metavar="S", help="stop a scene after S seconds (recorded as timeout)")
    parser.add_argument(
        "--scene-memory",
        type=float,
        metavar="GIB",
        help="stop a scene whose process holds more than this resident memory (recorded as memory)",
    )
    options.add_config(parser, help="config of every scene's run (default: scannet)")
    options.add_overrides(parser, help="override a config value of every scene's run (repeatable)")
    options.add_no_progress(parser, help="no progress lines (a line per finished scene, and how far running scenes got)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps.batch import run_batch  # lazy: the command's work loads only when it runs

    return run_batch(
        workers=args.workers,
        scene_timeout=args.scene_timeout,
        scene_memory=args.scene_memory,
        config=args.config,
        overrides=args.overrides,
        dataset=args.dataset,
        root=args.root,
        out=args.out,
        detections=args.detections,
        simulate=args.simulate,
        models=args.models,
        resume=args.resume,
        no_progress=args.no_progress,
        batch_size=args.batch,
        ray=args.ray,
        ray_cpus=args.ray_cpus,
        ray_gpus=args.ray_gpus,
    )
