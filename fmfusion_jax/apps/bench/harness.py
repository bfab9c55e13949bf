"""What the bench worker's pipelines share (`worker` and the sweeps of `sweep`): the scene's frames and
detections, its map config, the device and the memory figures, whether the Open3D peer can run."""

from __future__ import annotations

import importlib
import os
import resource

import jax
from tqdm import tqdm

from fmfusion_jax.apps.bench.scenes import BenchScene
from fmfusion_jax.config import load_config
from fmfusion_jax.io.detections import DetectionFolder
from fmfusion_jax.io.scene import open_scene
from fmfusion_jax.mapping.capacity import bounded_map_config, scene_extent
from fmfusion_jax.mapping.schedule import scheduled_detections

#: Module of the Open3D peer pipelines (an optional dependency: `open3d-cpu`).
PEER_MODULE = "fmfusion_jax.apps.bench.open3d_peer"


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cpu_count() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def peer_unavailable_reason() -> str | None:
    """Why the Open3D peer cannot run here, or None."""

    try:
        peer = importlib.import_module(PEER_MODULE)
    except ImportError as error:
        return f"the Open3D peer module is missing ({error})"
    return peer.open3d_unavailable_reason()


def open_bench_scene(scene: BenchScene, frames: int | None):
    """(config, opened scene, detection folder) for the first `frames` frames of the scene."""

    config = load_config(str(scene.config_path))
    dataset = config.dataset
    limit = min(x for x in (frames, scene.frames, dataset.max_frames) if x)
    opened = open_scene(
        scene.scene_dir,
        layout=dataset.layout,
        stride=dataset.frame_stride,
        depth_max=dataset.depth_max,
        depth_scale=dataset.depth_scale,
        max_frames=limit,
    )
    folder = DetectionFolder(scene.detections_dir, image_shape=(opened.intrinsics.height, opened.intrinsics.width))
    return config, opened, folder


def frames_with_detections(opened, folder, config, progress: bool, desc: str):
    """Yields `(frame, detections or None)` on the fusion's schedule, with a progress bar on stderr."""

    frames = tqdm(
        opened.frames(), total=len(opened), desc=desc, unit="frame", disable=not progress, dynamic_ncols=True, leave=False
    )
    yield from scheduled_detections(frames, folder, config)


def device_description() -> dict:

    device = jax.devices()[0]
    return {
        "platform": device.platform,
        "device_kind": device.device_kind,
        "jax": jax.__version__,
        "cpus": cpu_count(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }


def device_memory_mb() -> float | None:
    """Peak bytes the accelerator allocator reports (GPU), MiB; None where the backend reports none (CPU)."""

    try:
        stats = jax.devices()[0].memory_stats() or {}
    except Exception:  # noqa: BLE001 - backends without memory statistics raise various errors
        return None
    peak = stats.get("peak_bytes_in_use")
    return None if peak is None else peak / 2**20


def scene_map_config(config, opened):
    """The map `fmfusion run` starts with for the opened scene (`mapping.capacity.scene_extent`, `mapper.bounded_map_config`).
    The sweep's builders keep it (they do not grow)."""

    bounds, expected = scene_extent(opened, config)
    return bounded_map_config(config, bounds, opened.intrinsics.height, opened.intrinsics.width, expected)
