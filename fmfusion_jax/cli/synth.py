"""`fmfusion synth OUT_DIR`: a procedural room rendered into a ScanNet scene folder with exact ground truth."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from fmfusion_jax.cli import options
from fmfusion_jax.errors import UserError

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


def parse_dimensions(text: str, count: int, what: str) -> tuple[float, ...]:
    """``"5x4x2.6"`` -> `(5.0, 4.0, 2.6)`; a `UserError` naming `what` when it is not `count` positive numbers."""
    parts = text.lower().replace("*", "x").split("x")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != count or not all(v > 0 for v in values):
        example = "5x4x2.6" if count == 3 else "640x480"
        raise UserError(f"{what} {text!r}: expected {count} positive numbers joined by 'x', e.g. {example}")
    return values


def run(args: argparse.Namespace) -> int:
    if not 1 <= args.objects <= 900:
        raise UserError(f"--objects {args.objects}: expected 1..900")
    if args.frames < 1:
        raise UserError(f"--frames {args.frames}: expected a positive number")
    width, height = parse_dimensions(args.size, 2, "--size")
    if width != int(width) or height != int(height) or not (16 <= width <= 4096 and 16 <= height <= 4096):
        raise UserError(f"--size {args.size}: expected whole pixels within 16..4096, e.g. 640x480")
    room = parse_dimensions(args.room, 3, "--room") if args.room else None
    if room is not None and (min(room[:2]) < 2.0 or room[2] < 2.2 or max(room) > 100):
        raise UserError(f"--room {args.room}: width and depth must be at least 2 m, height at least 2.2 m")
    out = args.out_dir
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not args.overwrite)):
        raise UserError(f"{out}: exists and is not an empty folder (pass --overwrite, or choose another OUT_DIR)")

    from fmfusion_jax.simulation.procedural import generate_scene
    from fmfusion_jax.simulation.scannet_writer import write_scannet_scene

    started = time.perf_counter()
    try:
        scene = generate_scene(args.seed, room_size=room, num_objects=args.objects)
    except ValueError as error:
        raise UserError(str(error)) from None
    print(f"scene   {scene.summary()}")
    path = write_scannet_scene(
        scene,
        out,
        num_frames=args.frames,
        width=int(width),
        height=int(height),
        depth_noise=not args.no_noise,
        progress=not args.no_progress,
        overwrite=args.overwrite,
    )
    print(f"wrote   {path}  ({args.frames} frames {int(width)}x{int(height)}, {time.perf_counter() - started:.1f} s)")
    return 0
