"""`fmfusion track REC`: camera poses for a recording without them (frame-to-model or frame-to-frame tracking of its
depth)."""

from __future__ import annotations

import argparse
from pathlib import Path

from fmfusion_jax.cli import options

#: `engine.tracking.REFERENCES` and `TrackingConfig.reference`'s default, spelled here so that the parser does not
#: import JAX (tests/test_track_command.py checks that they agree)
REFERENCES = ("model", "frame")
DEFAULT_REFERENCE = "model"
#: `apps.track.TRACK_WIDTH` and `TrackingConfig.icp_width`, likewise
DEFAULT_MAX_WIDTH = 320
DEFAULT_ICP_WIDTH = 160


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "track",
        help="estimate the camera poses of a recording without them",
        description="Estimates the camera poses of a recording that has none by tracking its depth against a TSDF "
        "of the frames tracked so far (frame to model, KinectFusion-style; or frame to frame) by projective "
        "point-to-plane ICP, coarse to fine, and writes them where its reader looks: a TUM RGB-D "
        "folder's trajectory.txt, an Open3D / Redwood folder's trajectory.log (as Open3D's RealSense and Azure Kinect "
        "recorders leave them: color/, depth/, camera_intrinsic.json), a RealSense SDK recording's REC.bag.trajectory.txt "
        "beside it. `fmfusion run REC` then fuses with them. "
        "Tracking needs small motions between frames (30 Hz video): "
        "docs/your-own-data.md, 'Without poses'.",
    )
    parser.add_argument(
        "recording",
        type=Path,
        help="a TUM RGB-D folder (rgb.txt, depth.txt), an Open3D / Redwood one, or a RealSense .bag / .db3 file",
    )
    parser.add_argument(
        "--out",
        type=Path,
        help="trajectory file to write (default: the recording's trajectory.txt or trajectory.log, or REC.bag.trajectory.txt, "
        "read by `fmfusion run`)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    parser.add_argument(
        "--reference",
        choices=REFERENCES,
        default=DEFAULT_REFERENCE,
        help="what each frame is tracked against: the raycast of a TSDF of the frames so far (model, the default: "
        "less drift on noisy depth) or the last good frame (frame: faster)",
    )
    parser.add_argument(
        "--max-width",
        type=options.positive_int,
        default=DEFAULT_MAX_WIDTH,
        metavar="PIXELS",
        help=f"track every Nth pixel so that the image is at most this wide (default {DEFAULT_MAX_WIDTH}: a 640 x 480 "
        "recording at 320 x 240; the model is fused at this size)",
    )
    parser.add_argument(
        "--icp-width",
        type=options.non_negative_int,
        default=DEFAULT_ICP_WIDTH,
        metavar="PIXELS",
        help=f"the ICP and the model's raycast work at the first pyramid level at most this wide (default "
        f"{DEFAULT_ICP_WIDTH}: 160 x 120 of a 320 x 240 image, ~10 ms a frame on a 2-core CPU; 0: the whole image, "
        "~3x slower, about half the drift on long walks)",
    )
    parser.add_argument(
        "--no-color",
        action="store_true",
        help="track the depth alone (by default the colour images add a photometric term, which holds the camera "
        "where the geometry alone does not: facing a wall)",
    )
    options.add_depth_max(parser)
    options.add_no_progress(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fmfusion_jax.apps.track import track_recording  # lazy: the command's work loads only when it runs

    track_recording(
        args.recording,
        args.out,
        depth_max=args.depth_max,
        overwrite=args.overwrite,
        progress=not args.no_progress,
        reference=args.reference,
        max_width=args.max_width,
        color=not args.no_color,
        icp_width=args.icp_width,
    )
    return 0
