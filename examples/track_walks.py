"""Tracking on generated 30 Hz walks: writes each walk's true and estimated trajectories as TUM files for `evo`,
frame-to-frame and frame-to-model, and prints the warm milliseconds per frame.

    python examples/track_walks.py OUT [--rooms 3] [--frames 300] [--size 160x120] [--noise] [--no-color] [--bilateral R]
        [--icp-width PIXELS]

For each room seed `s` (0, 1, ...): `fmfusion synth`'s room of that seed (`generate_scene(s)`), the generator's
loop drawn over 1800 frames (a one-minute walk at 30 Hz), its first `--frames` frames rendered (with the
Kinect-like depth noise of `fmfusion synth` when `--noise`); OUT/room{s}/gt.txt and OUT/room{s}/{frame,model}.txt
(the first pose given: the estimate starts on the truth). Then, per file (evo is not needed here, only to read
the files: `pip install evo` in a venv of its own). The rendered colour images are tracked too (the ICP's colour
term) unless `--no-color`:

    evo_ape tum OUT/room0/gt.txt OUT/room0/model.txt -a      # ATE RMSE after an SE(3) alignment
    evo_rpe tum OUT/room0/gt.txt OUT/room0/model.txt -a --delta 1 --delta_unit f   # RPE per frame
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from fmfusion_jax.engine.tracking import TrackingConfig
from fmfusion_jax.io.recordings import write_tum_trajectory
from fmfusion_jax.mapping.tracking import Tracker
from fmfusion_jax.simulation.procedural import camera_trajectory, generate_scene
from fmfusion_jax.simulation.scannet_writer import scene_intrinsics
from fmfusion_jax.simulation.scene_views import render_frame

#: The generator's loop drawn over this many frames is a one-minute walk at 30 Hz.
LOOP_FRAMES = 1800


def walk(seed: int, frames: int, width: int, height: int, noise: bool, with_color: bool = False):
    """`(T_world_camera (N, 4, 4), depth (N, H, W) float32, intrinsics)` of room `seed`'s walk (and its colour
    images `(N, H, W, 3)` uint8 last, with `with_color`)."""
    scene = generate_scene(seed)
    intrinsics = scene_intrinsics(width, height)
    poses = camera_trajectory(scene, LOOP_FRAMES)[:frames]
    boxes = scene.box_arrays()
    depths, colors = [], []
    for k, T in enumerate(poses):
        frame = render_frame(scene, T, intrinsics, rng=np.random.default_rng([seed, k]), depth_noise=noise, boxes=boxes)
        depths.append(np.where(np.isfinite(frame.depth), frame.depth, 0.0).astype(np.float32))
        colors.append(frame.color)
    if with_color:
        return poses, np.stack(depths), intrinsics, np.stack(colors)
    return poses, np.stack(depths), intrinsics


def aligned_ate(estimated: list[np.ndarray], truth: np.ndarray) -> float:
    """RMS distance (m) of the camera centres after the rigid motion that best aligns them (Umeyama without scale,
    as `evo_ape -a`)."""
    P = np.array([T[:3, 3] for T in estimated], np.float64)
    Q = np.asarray(truth, np.float64)[:, :3, 3]
    P0, Q0 = P - P.mean(0), Q - Q.mean(0)
    U, _, Vt = np.linalg.svd(P0.T @ Q0)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return float(np.sqrt(np.mean(np.sum((P0 @ R.T - Q0) ** 2, axis=1))))


def track(
    depths, intrinsics, reference: str, T_world_first, colors=None, bilateral: int | None = None, icp_width: int | None = None
) -> tuple[list[np.ndarray], float, int]:
    """The estimated poses, the warm ms per frame (after the first 3 frames, which compile) and the lost count;
    with `colors`, the ICP's colour term too; `bilateral` the bilateral depth filter's radius and `icp_width` the
    ICP's width (`TrackingConfig`'s; None: its default)."""
    config = dataclasses.replace(TrackingConfig(), reference=reference)
    if bilateral is not None:
        config = dataclasses.replace(config, bilateral_radius=bilateral)
    if icp_width is not None:
        config = dataclasses.replace(config, icp_width=icp_width)
    tracker = Tracker(intrinsics, config, T_world_first=T_world_first)
    images = colors if colors is not None else [None] * len(depths)
    poses = [tracker.track(d, c).T_world_camera for d, c in zip(depths[:3], images[:3])]
    start = time.perf_counter()
    poses += [tracker.track(d, c).T_world_camera for d, c in zip(depths[3:], images[3:])]
    ms = (time.perf_counter() - start) / max(len(depths) - 3, 1) * 1e3
    return poses, ms, tracker.frames_lost


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path)
    parser.add_argument("--rooms", type=int, default=3)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--noise", action="store_true", help="Kinect-like depth noise, holes and dropouts")
    parser.add_argument("--references", default="frame,model")
    parser.add_argument("--no-color", action="store_true", help="depth alone (no colour term)")
    parser.add_argument("--bilateral", type=int, help="the bilateral depth filter's radius (pixels, 0: off)")
    parser.add_argument("--icp-width", type=int, help="the ICP's most pixels wide (0: the whole image)")
    args = parser.parse_args()
    width, height = (int(x) for x in args.size.split("x"))
    for seed in range(args.rooms):
        truth, depths, intrinsics, colors = walk(seed, args.frames, width, height, args.noise, with_color=True)
        folder = args.out / f"room{seed}"
        folder.mkdir(parents=True, exist_ok=True)
        stamps = np.arange(len(truth)) / 30.0
        write_tum_trajectory(folder / "gt.txt", stamps, list(truth))
        for reference in args.references.split(","):
            colour = None if args.no_color else colors
            poses, ms, lost = track(depths, intrinsics, reference, truth[0], colour, args.bilateral, args.icp_width)
            write_tum_trajectory(folder / f"{reference}.txt", stamps, poses)
            end = np.linalg.norm(poses[-1][:3, 3] - truth[-1][:3, 3])
            print(
                f"room{seed} {reference}: {ms:.1f} ms/frame at {width}x{height}, {lost} lost, "
                f"ATE {aligned_ate(poses, truth) * 1e3:.2f} mm (aligned), last pose {end * 1e3:.1f} mm off"
            )


if __name__ == "__main__":
    main()
