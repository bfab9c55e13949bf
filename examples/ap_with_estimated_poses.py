"""AP of a map fused with tracked poses against the same scene's given poses (docs/your-own-data.md, "AP with
estimated poses").

    fmfusion synth OUT/synth0005_00 --seed 5 --frames 1800 --size 320x240   # a one-minute 30 Hz walk
    fmfusion simulate OUT/synth0005_00 --out OUT/det
    fmfusion run OUT/synth0005_00 --detections OUT/det --out OUT/given       # the given poses' AP
    python examples/ap_with_estimated_poses.py OUT/synth0005_00 OUT/det OUT/model [--reference frame]

Tracks the scene's depth and colour as `fmfusion track` does (at most `--max-width` pixels wide, default 320, the
ICP at 160) from its first given pose (`mapping.tracking.Tracker`), prints
the ATE against the given poses, writes the estimated poses over a copy of the scene's `pose/` (ScanNet layout)
in OUT/model/, and runs `fmfusion run` on the copy with the same detections (its AP is printed by the run).
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from fmfusion_jax.apps.track import TRACK_WIDTH, subsampled_camera
from fmfusion_jax.engine.tracking import TrackingConfig
from fmfusion_jax.io.scene import open_scene
from fmfusion_jax.mapping.tracking import Tracker


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path, help="a ScanNet-layout scene with poses (e.g. from fmfusion synth)")
    parser.add_argument("detections", help="its detection folder")
    parser.add_argument("out", type=Path, help="folder for the copy with estimated poses and its map")
    parser.add_argument("--reference", choices=("model", "frame"), default=TrackingConfig.reference)
    parser.add_argument("--max-width", type=int, default=TRACK_WIDTH, help="track every Nth pixel, at most this wide")
    args = parser.parse_args()
    scene = open_scene(args.scene)
    given = scene.poses()
    step = max(1, -(-scene.intrinsics.width // args.max_width))
    tracker = Tracker(
        subsampled_camera(scene.intrinsics, step),
        dataclasses.replace(TrackingConfig(), reference=args.reference),
        T_world_first=given[0],
    )
    start = time.perf_counter()
    estimated = np.stack(
        [
            tracker.track(
                np.ascontiguousarray(f.depth[::step, ::step]), np.ascontiguousarray(f.color[::step, ::step])
            ).T_world_camera
            for f in scene.frames()
        ]
    )
    seconds = time.perf_counter() - start
    ate = float(np.sqrt(np.mean(np.sum((estimated[:, :3, 3] - given[:, :3, 3]) ** 2, axis=1))))
    print(
        f"{args.reference}: ATE {1000 * ate:.1f} mm, {tracker.frames_lost} lost, "
        f"{1000 * seconds / len(estimated):.0f} ms a frame (reading included)"
    )
    copy = args.out / args.scene.name
    if copy.exists():
        sys.exit(f"{copy}: exists; remove it first")
    shutil.copytree(args.scene, copy)
    for path, T in zip(sorted((copy / "pose").glob("*.txt")), estimated, strict=True):
        np.savetxt(path, T)
    command = [
        sys.executable,
        "-m",
        "fmfusion_jax.cli",
        "run",
        str(copy),
        "--detections",
        args.detections,
        "--out",
        str(args.out / "map"),
        "--no-progress",
    ]
    subprocess.run(command, check=True)


if __name__ == "__main__":
    main()
