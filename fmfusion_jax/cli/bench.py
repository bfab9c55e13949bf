"""`fmfusion bench`: time the fusion step per stage, against Open3D peers on the same frames."""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from fmfusion_jax.apps.bench.scenes import DEFAULT_SCENE
from fmfusion_jax.cli import HelpFormatter, options

#: The real scene used when --scene is not given (and present).


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "bench",
        help="time the fusion step per stage (like the paper's Table IV) against Open3D peers",
        description="Runs the fusion step on the real scene with simulated detections and on generated rooms of "
        "growing object count, and reports per stage (global TSDF, projection, association, label "
        "fusion, instance integration, merge, geometry fusion) the median ms per frame, the compile "
        "times and the peak memory, beside the Open3D reference pipeline (a global "
        "ScalableTSDFVolume and one volume per instance, as the authors' code) and Open3D's "
        "VoxelBlockGrid integration on the same frames; then the base + per-object cost from a "
        "controlled sweep (the main scene's first frames fused once per cap on the detections per "
        "frame: same frames, same map, only the objects fused vary), with a line across the "
        "generated rooms as context. Each pipeline runs in a process of its own. The Open3D peer "
        "needs the optional open3d-cpu==0.19.0 (and the Debian package libusb-1.0-0); without it "
        "ours is still measured. Writes bench.md and bench.json into --out. Scenes and simulated "
        "detections are made once into a cache folder.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument(
        "--scene",
        type=Path,
        default=None,
        help=f"real ScanNet scene with ground truth (default: {DEFAULT_SCENE} when present; not used by --quick unless given)",
    )
    parser.add_argument("--no-scene", action="store_true", help="generated rooms only")
    parser.add_argument(
        "--frames", type=int, default=None, metavar="N", help="frames of the real scene (default: all; --quick 6; 0: all)"
    )
    parser.add_argument(
        "--objects",
        type=int,
        nargs="*",
        default=None,
        metavar="N",
        help="object counts of the generated rooms (default 4 8 16 32; --quick 2 8; none: skip)",
    )
    parser.add_argument(
        "--generated-frames", type=int, default=None, metavar="N", help="frames of each generated room (default 40; --quick 6)"
    )
    parser.add_argument(
        "--size",
        type=int,
        nargs=2,
        default=None,
        metavar=("W", "H"),
        help="image size of the generated rooms (default 640 480; --quick 160 120)",
    )
    parser.add_argument("--no-peer", action="store_true", help="ours only (no Open3D)")
    parser.add_argument(
        "--no-whole-run",
        action="store_true",
        help="leave out `fmfusion run` end to end on the main scene (a fresh process with an empty compile cache, "
        "then with the cache it filled: wall time, its split, peak RSS)",
    )
    parser.add_argument(
        "--peer-frames",
        type=int,
        default=None,
        metavar="N",
        help="the Open3D per-instance pipeline (0.1-1 s per frame, growing with the map) runs on "
        "the first N frames of each scene; ours is compared with it on that same prefix "
        "(default: all frames; 0: all)",
    )
    parser.add_argument(
        "--sweep",
        type=int,
        nargs="*",
        default=None,
        metavar="K",
        help="caps on the detections fused per frame for the per-object sweep on the main scene "
        "(the real one, else the largest generated room): each frame keeps its K "
        "highest-scoring detections (default 1 2 4 8 16; --quick 1 4; none: skip)",
    )
    parser.add_argument(
        "--sweep-frames",
        type=int,
        default=None,
        metavar="N",
        help="the sweep (ours and the Open3D peer, once per cap) runs on the first N frames of the "
        "main scene (default 30; --quick 4; 0: all)",
    )
    parser.add_argument("--quick", action="store_true", help="tiny sizes: a smoke test in well under a minute")
    parser.add_argument("--cache", type=Path, default=None, help="folder of the prepared scenes (default OUT/cache)")
    options.add_seed(parser, help="seed of the generated rooms and simulated detections")
    options.add_out(parser, default=Path("outputs/bench"), help="output folder")
    options.add_overrides(
        parser, help="override a config value of every scene, e.g. --set instances.contrary_vote_weight=0 (repeatable)"
    )
    parser.add_argument(
        "--profile",
        type=int,
        default=0,
        metavar="N",
        help="trace the last N frames of our pass as run on the main scene with jax.profiler (left out of the figures): "
        "bench.md summarizes where each thread's time went, the trace opens in ui.perfetto.dev (default: 0, none)",
    )
    options.add_no_progress(parser, help="no progress bars")
    parser.set_defaults(func=run)


def _command_line(args: argparse.Namespace) -> str:
    """The command as given (for the report), rebuilt from the parsed options."""
    words = ["fmfusion", "bench"] + (["--quick"] if args.quick else [])
    for flag, value in (
        ("--scene", args.scene),
        ("--frames", args.frames),
        ("--generated-frames", args.generated_frames),
        ("--peer-frames", args.peer_frames),
        ("--sweep-frames", args.sweep_frames),
        ("--cache", args.cache),
        ("--out", args.out),
    ):
        if value is not None:
            words += [flag, str(value)]
    if args.objects is not None:
        words += ["--objects", *map(str, args.objects)]
    if args.sweep is not None:
        words += ["--sweep", *map(str, args.sweep)]
    if args.size is not None:
        words += ["--size", *map(str, args.size)]
    if args.seed:
        words += ["--seed", str(args.seed)]
    if args.profile:
        words += ["--profile", str(args.profile)]
    words += [
        flag
        for flag, on in (("--no-scene", args.no_scene), ("--no-peer", args.no_peer), ("--no-whole-run", args.no_whole_run))
        if on
    ]
    for override in args.overrides:
        words += ["--set", override]
    return shlex.join(words)


def run(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps.bench.run import run_bench_command  # lazy: the command's work loads only when it runs

    return run_bench_command(
        objects=args.objects,
        generated_frames=args.generated_frames,
        sweep=args.sweep,
        sweep_frames=args.sweep_frames,
        profile=args.profile,
        quick=args.quick,
        frames=args.frames,
        peer_frames=args.peer_frames,
        size=args.size,
        no_scene=args.no_scene,
        scene=args.scene,
        out=args.out,
        cache=args.cache,
        no_peer=args.no_peer,
        seed=args.seed,
        overrides=args.overrides,
        no_progress=args.no_progress,
        command=_command_line(args),
        no_whole_run=args.no_whole_run,
    )
