"""`fmfusion demo`: generate a room, simulate detections, fuse, score; no data needed."""

from __future__ import annotations

import argparse

from fmfusion_jax.apps.demo import DEFAULT_OUT, run_demo
from fmfusion_jax.cli import HelpFormatter, options
from fmfusion_jax.errors import UserError
from fmfusion_jax.simulation.demo_setup import DEFAULT_FRAMES, DEFAULT_HEIGHT, DEFAULT_OBJECTS, DEFAULT_WIDTH


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="the whole job on a generated room: no data needed",
        description="Generates a room of furniture (seeded), renders an RGB-D loop around it in the ScanNet "
        "layout with ground truth (OUT/synth<seed>_00), simulates the foundation models' detections from "
        "the ground truth (OUT/detections, as `fmfusion simulate`), fuses them into an instance map "
        "with configs/demo.yaml, writes the map's outputs into OUT (overview.png first, then "
        "instances.json, PLY files, map_state.npz, ...) and scores it with the ScanNet benchmark. "
        "About a minute on two CPU cores at the defaults.",
        formatter_class=HelpFormatter,
    )
    options.add_out(parser, default=DEFAULT_OUT, help="output folder (a previous demo's output there is replaced)")
    options.add_seed(parser, help="seed of the room, camera path, noise and detections")
    parser.add_argument("--objects", type=int, default=DEFAULT_OBJECTS, metavar="N", help="objects in the room")
    parser.add_argument(
        "--stacked",
        type=int,
        default=0,
        metavar="N",
        help="small objects (lamps, boxes, baskets) standing on the tables, desks, counters and cabinets (default 0)",
    )
    parser.add_argument("--frames", type=int, default=DEFAULT_FRAMES, metavar="N", help="frames on the loop")
    parser.add_argument("--width", type=int, default=DEFAULT_WIDTH, help="image width")
    parser.add_argument("--height", type=int, default=DEFAULT_HEIGHT, help="image height")
    options.add_overrides(parser, help="override a value of configs/demo.yaml, e.g. --set detections.every=1 (repeatable)")
    options.add_no_progress(parser, help="no progress bars")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.frames < 2 or args.objects < 1 or args.stacked < 0:
        raise UserError(
            f"--frames must be >= 2, --objects >= 1 and --stacked >= 0 (got {args.frames}, {args.objects}, {args.stacked})"
        )
    result = run_demo(
        args.out,
        seed=args.seed,
        num_objects=args.objects,
        num_frames=args.frames,
        stacked=args.stacked,
        width=args.width,
        height=args.height,
        overrides=args.overrides,
        progress=not args.no_progress,
    )
    print(result.text)
    return 0
