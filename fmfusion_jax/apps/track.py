"""`fmfusion track REC`: camera poses for a recording without them, by tracking its depth frame to model (or frame
to frame: `--reference frame`; `mapping.tracking.Tracker`), written as the recording's own trajectory file (TUM:
trajectory.txt; Open3D / Redwood: trajectory.log; a RealSense SDK recording REC.bag: REC.bag.trajectory.txt beside
it) so that `fmfusion run REC` fuses with them.

Tracks at a reduced resolution (every `step`-th pixel, so that the image is at most `TRACK_WIDTH` wide, or
`max_width`), the ICP and the model's raycast at half that (`icp_width`): frame to model then takes 7-10 ms a frame
at 320 x 240 on a 2-core CPU (21-24 ms with the ICP at 320 x 240; docs/your-own-data.md), the next frames decoded
meanwhile. Reads the formats whose frames are listed without
poses: TUM (rgb.txt and depth.txt), Open3D / Redwood (color/, depth/ and camera_intrinsic.json, as Open3D's
RealSense and Azure Kinect recorders write them) and RealSense SDK recordings (.bag, .db3: `io.realsense`, which
never hold poses).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from fmfusion_jax.engine.tracking import TrackingConfig, icp_level
from fmfusion_jax.errors import UserError
from fmfusion_jax.io.realsense import is_realsense_recording, read_realsense
from fmfusion_jax.io.realsense import trajectory_path as realsense_trajectory
from fmfusion_jax.io.recordings import (
    MAX_TIME_DIFFERENCE,
    Recording,
    read_recording,
    recording_layouts,
    write_trajectory_log,
    write_tum_trajectory,
)
from fmfusion_jax.io.scene import read_color_image, read_depth_image
from fmfusion_jax.mapping.tracking import Tracker
from fmfusion_jax.run.scene_fusion import read_ahead
from fmfusion_jax.types import CameraIntrinsics

log = logging.getLogger(__name__)

#: Widest image tracked by default (pixels): larger depth images are subsampled by an integer step down to it.
TRACK_WIDTH = 320
#: Depth frames decoded ahead of the one tracked.
READ_AHEAD = 2
#: The trajectory file each format's reader reads (`io.recordings`), which `track` writes.
TRAJECTORY_FILES = {"tum": "trajectory.txt", "redwood": "trajectory.log"}


def subsampled_camera(intrinsics: CameraIntrinsics, step: int) -> CameraIntrinsics:
    """The camera of every `step`-th pixel (pixel `(u, v)` of the subsampled image is `(step u, step v)`)."""
    return dataclasses.replace(
        intrinsics,
        fx=intrinsics.fx / step,
        fy=intrinsics.fy / step,
        cx=intrinsics.cx / step,
        cy=intrinsics.cy / step,
        width=-(-intrinsics.width // step),
        height=-(-intrinsics.height // step),
    )


def track_recording(
    path: str | Path,
    out: str | Path | None = None,
    depth_max: float = 4.0,
    overwrite: bool = False,
    progress: bool = True,
    reference: str = TrackingConfig.reference,
    max_width: int = TRACK_WIDTH,
    color: bool = True,
    icp_width: int = TrackingConfig.icp_width,
) -> Path:
    """Tracks the recording at `path` (a TUM or an Open3D / Redwood folder, a RealSense SDK recording) and writes
    its trajectory to `out` (default: the file the recording's reader reads when it has no other poses: TUM's
    trajectory.txt, Redwood's trajectory.log, a RealSense recording's REC.bag.trajectory.txt); returns the file
    written. `reference`: "model" (frame-to-model) or "frame" (frame-to-frame), `TrackingConfig.reference`;
    `max_width`: every Nth pixel is tracked so that the image is at most this wide; `color`: the colour images
    are read too, for the ICP's colour term (`TrackingConfig.color_weight`); `icp_width`: the ICP and the model's
    raycast work at the first pyramid level of the tracked image at most this wide (0: the whole image;
    `TrackingConfig.icp_width`)."""
    root = Path(path)
    default, read = _trajectory_and_reader(root)
    target = Path(out) if out is not None else default
    if target.exists() and not overwrite:
        raise UserError(f"{target}: exists; pass --overwrite to replace it, or --out another file")
    recording = read()
    camera = recording.intrinsics()
    step = max(1, -(-camera.width // max_width))
    tracked = subsampled_camera(camera, step)
    tracker = Tracker(tracked, dataclasses.replace(TrackingConfig(), reference=reference, icp_width=icp_width))

    def read_frame(index: int) -> tuple[np.ndarray, np.ndarray | None]:
        full = read_depth_image(recording.depth_paths[index], recording.depth_scale, depth_max)
        depth = np.ascontiguousarray(full[::step, ::step])
        if not color:
            return depth, None
        rgb = read_color_image(recording.color_paths[index])
        if rgb.shape[:2] != full.shape:  # registered to the depth, at another size
            rgb = cv2.resize(rgb, (full.shape[1], full.shape[0]), interpolation=cv2.INTER_AREA)
        return depth, np.ascontiguousarray(rgb[::step, ::step])

    poses, start = [], time.perf_counter()
    # the next frames are decoded while one is tracked (a 640 x 480 PNG takes a few ms)
    with concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="fmfusion-read") as reader:
        decoded = read_ahead(read_frame, range(len(recording.depth_paths)), reader, READ_AHEAD)
        frames = tqdm(decoded, total=len(recording.depth_paths), desc=f"tracking {root.name}", unit="frame", disable=not progress)
        for depth, rgb in frames:
            poses.append(tracker.track(depth, rgb).T_world_camera)
    seconds = time.perf_counter() - start
    target.parent.mkdir(parents=True, exist_ok=True)
    if recording.stamps is not None:  # TUM, RealSense
        write_tum_trajectory(target, [float(t) for t in recording.stamps], poses)
    else:
        write_trajectory_log(target, poses)
    level = icp_level(tracked.width, tracker.config)
    icp_size = f"{-(-tracked.width // (1 << level))}x{-(-tracked.height // (1 << level))}"
    print(
        f"{root.name}: {len(poses)} frames tracked against the {reference} at {tracked.width}x{tracked.height} "
        f"(ICP at {icp_size}; {'depth and colour' if color else 'depth alone'}) "
        f"in {seconds:.1f} s "
        f"({1000 * seconds / max(len(poses), 1):.0f} ms a frame, reading included), {tracker.frames_lost} lost "
        f"(they keep the last good pose)\ntrajectory written to {target}"
    )
    if tracker.frames_lost:
        log.warning("%s: tracking was lost on %d of %d frames: check the trajectory", root.name, tracker.frames_lost, len(poses))
    return target


def _trajectory_and_reader(root: Path) -> tuple[Path, Callable[[], Recording]]:
    """The trajectory file the reader of the recording `root` reads when it has no other poses, and that reader
    (called once the file is known not to exist: extracting a RealSense recording takes a while)."""
    if is_realsense_recording(root):
        return realsense_trajectory(root), lambda: read_realsense(root, MAX_TIME_DIFFERENCE)
    if not root.is_dir():
        raise UserError(f"{root}: recording folder (or RealSense .bag / .db3 file) not found")
    layouts = [layout for layout in recording_layouts(root) if layout in TRAJECTORY_FILES]
    if len(layouts) != 1:
        raise UserError(
            f"{root}: not a TUM RGB-D folder (rgb.txt, depth.txt) nor an Open3D / Redwood one (color/, depth/, "
            "camera_intrinsic.json): `fmfusion track` reads these two formats and RealSense SDK recordings today"
        )
    layout = layouts[0]
    return root / TRAJECTORY_FILES[layout], lambda: read_recording(layout, root, stride=1)
