"""`fmfusion synth OUT_DIR`: a procedural room rendered into a ScanNet scene folder with exact ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from fmfusion_jax.cli import options

_EPILOG = """\
OUT_DIR is the scene folder to create; its name is the scene name (e.g. OUT/synth0000_00). It receives
color/ depth/ pose/ intrinsic/ frames as ScanNet exports them, the mesh <scene>_vh_clean_2.ply with
<scene>_vh_clean_2.0.010000.segs.json, <scene>.aggregation.json and scannetv2-labels.combined.tsv (instance
ground truth per mesh vertex), and our extras gt_instances/frame-*.png (uint16 instance id per pixel,
= aggregation objectId + 1) with gt_instances/instances.json, and synthesis.json (the parameters).

The room holds walls, floor, ceiling, a door, a window and objects of the ScanNet classes (beds, chairs,
sofas, tables, desks, cabinets, bookshelves, counters, refrigerators, toilets, sinks, bathtubs, curtains,
pictures, other furniture); the camera loops around the room at 1.3-1.6 m height. Same --seed, same scene.

examples:
  fmfusion synth OUT/synth0000_00
  fmfusion synth OUT/synth0001_00 --seed 1 --objects 30 --frames 500
  fmfusion synth /tmp/tiny_00 --objects 5 --frames 20 --size 160x120 --no-noise
"""


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "synth",
        help="generate a procedural room as a ScanNet scene folder (frames + ground truth)",
        description="Generates a random room of box-shaped furniture (deterministic per seed), renders RGB-D frames\n"
        "along a camera loop and writes them with the mesh and instance ground truth in the ScanNet\n"
        "layout. 300 frames at 640x480 take well under a minute.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("out_dir", type=Path, metavar="OUT_DIR", help="scene folder to write (must be empty or new)")
    options.add_seed(parser, help="scene seed (default 0)")
    parser.add_argument(
        "--objects", type=int, default=15, metavar="N", help="objects besides walls/floor/ceiling, 1..900 (default 15)"
    )
    parser.add_argument("--frames", type=int, default=300, metavar="N", help="frames to render (default 300)")
    parser.add_argument(
        "--room",
        metavar="WxDxH",
        help="room size in metres, e.g. 5x4x2.6 (default: 5x4x2.6 up to 12 objects, larger in proportion for more)",
    )
    parser.add_argument("--size", default="640x480", metavar="WxH", help="image size in pixels (default 640x480)")
    parser.add_argument("--no-noise", action="store_true", help="exact depth (no sensor noise, holes or grazing-angle dropouts)")
    parser.add_argument("--overwrite", action="store_true", help="write into a non-empty OUT_DIR")
    parser.add_argument("--no-progress", "--quiet", dest="no_progress", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps.synth import run_synth  # lazy: the command's work loads only when it runs

    return run_synth(
        objects=args.objects,
        frames=args.frames,
        size=args.size,
        room_text=args.room,
        out_dir=args.out_dir,
        overwrite=args.overwrite,
        seed=args.seed,
        no_noise=args.no_noise,
        no_progress=args.no_progress,
    )
