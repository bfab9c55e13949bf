"""The Open3D peers of `fmfusion bench` on an analytic box room: working pipelines, not only timers.

A camera sweeps an arc in front of the floor, a bed, a cabinet and a ball; clean detections are each object's
true mask labelled with an open-set label of its class. The per-instance-volume pipeline must find each
object once, on the object, with its class; the VoxelBlockGrid must put its surface on the true surface.
Skipped (with the fix) where open3d 0.19 is not installed.
"""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest
from oracles.reference import BoxRoom, look_at, scannet_like_intrinsics

from fmfusion_jax.apps.bench import open3d_peer
from fmfusion_jax.apps.bench.open3d_peer import STAGES, Open3DInstancePipeline, VoxelBlockGridTSDF
from fmfusion_jax.config import load_config
from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import load_label_sets, load_likelihood
from fmfusion_jax.types import CameraIntrinsics, FrameDetections, RGBDFrame

REASON = open3d_peer.open3d_unavailable_reason()
needs_open3d = pytest.mark.skipif(REASON is not None, reason=REASON or "")

H, W = 120, 160
LABELS = load_label_sets()
ROOM = BoxRoom()
# surface label of `BoxRoom.render` -> (open-set label the "detector" reports, true closed class)
OBJECTS = {0: ("floor", "floor"), 6: ("bed", "bed"), 7: ("cabinet", "cabinet"), 8: ("bin", "otherfurniture")}


def object_distance(surface: int, points: np.ndarray) -> np.ndarray:
    """`(P,)` distance of world points to the surface of one object of `ROOM`."""
    points = np.asarray(points, np.float64)
    if surface == 0:
        return np.abs(points[:, 2] - ROOM.lo[2])
    if surface - 6 < len(ROOM.boxes):
        lo, hi = (np.asarray(x) for x in ROOM.boxes[surface - 6])
        q = np.maximum(lo - points, points - hi)
        return np.abs(np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0))
    centre, radius = ROOM.spheres[surface - 6 - len(ROOM.boxes)]
    return np.abs(np.linalg.norm(points - np.asarray(centre), axis=1) - radius)


def make_sequence(n: int = 6) -> list[tuple[RGBDFrame, FrameDetections]]:
    """Frames on a 70-degree arc looking at the room centre, with clean detections of `OBJECTS`."""
    k = scannet_like_intrinsics(W, H)
    intrinsics = CameraIntrinsics(float(k[0]), float(k[1]), float(k[2]), float(k[3]), W, H)
    centre = np.array([2.0, 1.75, 0.5])
    out = []
    for i, angle in enumerate(np.linspace(-np.pi / 2 - 0.6, -np.pi / 2 + 0.6, n)):
        eye = centre + np.array([1.55 * np.cos(angle), 1.55 * np.sin(angle), 1.1])
        T_world_camera = look_at(eye, centre)
        depth, color, labels = ROOM.render(T_world_camera, k, H, W)
        frame = RGBDFrame(i, f"frame-{i:06d}", color, depth.astype(np.float32), T_world_camera, intrinsics)
        masks = [labels == s for s in OBJECTS if np.count_nonzero(labels == s) >= 150]
        names = [{OBJECTS[s][0]: 0.6} for s in OBJECTS if np.count_nonzero(labels == s) >= 150]
        boxes = np.zeros((len(masks), 4), np.float32)
        out.append((frame, FrameDetections(frame.name, np.array(masks, bool).reshape(-1, H, W), names, boxes)))
    return out


def small_config(*overrides: str):
    return load_config(
        "scannet-subsampled", ["detections.min_mask_pixels=100", "association.min_projected_pixels=200", *overrides]
    )


@pytest.fixture(scope="module")
def sequence():
    return make_sequence()


def run_pipeline(sequence, config, first_detections=None):
    pipeline = Open3DInstancePipeline(config, sequence[0][0].intrinsics, load_likelihood("statistical"), LABELS)
    counts, timings = [], []
    for i, (frame, detections) in enumerate(sequence):
        timings.append(pipeline.add_frame(frame, first_detections if i == 0 and first_detections else detections))
        counts.append(pipeline.num_instances)
    return pipeline, counts, timings


@pytest.fixture(scope="module")
def fused(sequence):
    return run_pipeline(sequence, small_config())


def assert_objects_found(pipeline, sequence, voxel_size):
    """Each instance lies on one object (a different one each), has its class, and every object is found."""
    found = {}
    for points, distribution in pipeline.instance_points():
        assert points.dtype == np.float32 and points.shape[1] == 3 and len(points) > 50
        median = {s: float(np.median(object_distance(s, points))) for s in OBJECTS}
        surface = min(median, key=median.get)
        assert median[surface] < voxel_size, median
        assert np.mean(object_distance(surface, points) < 3 * voxel_size) > 0.95
        assert LABELS.class_names[int(np.argmax(distribution))] == OBJECTS[surface][1]
        assert distribution.shape == (LABELS.num_classes,) and abs(float(distribution.sum()) - 1) < 1e-5
        assert surface not in found, f"two instances on surface {surface}"
        found[surface] = len(points)
    seen = {next(s for s in OBJECTS if OBJECTS[s][0] in labels) for _, detections in sequence for labels in detections.labels}
    assert set(found) == seen == set(OBJECTS)


@needs_open3d
def test_one_instance_per_object_with_its_class(sequence, fused):
    pipeline, counts, _ = fused
    seen_so_far = set()
    for (_, detections), count in zip(sequence, counts):
        seen_so_far |= {tuple(labels) for labels in detections.labels}
        assert count == len(seen_so_far)  # later views associate to the instances made by the first ones
    assert pipeline.counters["created"] == len(OBJECTS) and pipeline.counters["merged"] == 0
    assert pipeline.counters["matched"] == pipeline.counters["detections"] - len(OBJECTS)
    assert_objects_found(pipeline, sequence, pipeline.config.tsdf.voxel_size)


@needs_open3d
def test_iou_association_finds_the_same_objects(sequence):
    sequence = sequence[:3]
    # IoU is lower than the projection overlap (the percentile filter trims the masks): the authors' C++ threshold
    pipeline, counts, _ = run_pipeline(sequence, small_config("association.metric=iou", "association.threshold=0.3"))
    assert counts[-1] == len(OBJECTS)
    assert_objects_found(pipeline, sequence, pipeline.config.tsdf.voxel_size)


@needs_open3d
def test_duplicate_detections_merge(sequence):
    sequence = sequence[:3]
    frame, detections = sequence[0]
    # the bed reported twice: two new instances on one volume, which the online merge folds into one once
    # their class distributions are peaked enough to pass the similarity test (one or two frames)
    doubled = FrameDetections(
        frame.name,
        np.concatenate([detections.masks, detections.masks[1:2]]),
        detections.labels + [{"bed": 0.5}],
        np.zeros((len(detections.labels) + 1, 4), np.float32),
    )
    pipeline, counts, _ = run_pipeline(sequence, small_config(), first_detections=doubled)
    assert pipeline.counters["created"] == len(OBJECTS) + 1 and pipeline.counters["merged"] == 1
    assert counts[0] == len(OBJECTS) + 1 and counts[2:] == [len(OBJECTS)] * (len(sequence) - 2)
    assert_objects_found(pipeline, sequence, pipeline.config.tsdf.voxel_size)


@needs_open3d
def test_add_frame_returns_stage_times(sequence, fused):
    _, _, timings = fused
    for ms in timings:
        assert tuple(ms) == STAGES
        assert all(isinstance(v, float) and v >= 0 for v in ms.values())
    config = small_config("refinement.enabled=false")
    pipeline = Open3DInstancePipeline(config, sequence[0][0].intrinsics, load_likelihood("statistical"))
    assert tuple(pipeline.add_frame(sequence[0][0], None)) == ("tsdf",)
    assert tuple(pipeline.add_frame(*sequence[1])) == tuple(s for s in STAGES if s != "merge")
    assert pipeline.num_instances == len(sequence[1][1].labels)


@needs_open3d
def test_voxel_block_grid_surface_on_the_room(sequence):
    config = small_config()
    grid = VoxelBlockGridTSDF(
        config.tsdf.voxel_size, config.tsdf.sdf_trunc, config.dataset.depth_max, sequence[0][0].intrinsics, block_count=4000
    )
    for frame, _ in sequence[:3]:
        ms = grid.integrate(frame)
        assert isinstance(ms, float) and ms > 0
    points = grid.extract_points()
    assert grid.extract_point_count() == len(points) > 5000
    error = np.abs(ROOM.signed_distance(points.astype(np.float64)))
    assert np.median(error) < 0.5 * config.tsdf.voxel_size and np.quantile(error, 0.99) < 2 * config.tsdf.voxel_size


def test_reason_names_the_fix_when_open3d_is_missing(monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # `import open3d` raises ImportError
    reason = open3d_peer.open3d_unavailable_reason()
    assert reason is not None and "\n" not in reason
    assert 'pip install -e ".[bench]"' in reason and "apt-get install libusb-1.0-0" in reason
    with pytest.raises(UserError, match="libusb"):
        VoxelBlockGridTSDF(0.02, 0.06, 4.0, CameraIntrinsics(100.0, 100.0, 80.0, 60.0, W, H))
    monkeypatch.setitem(sys.modules, "open3d", types.SimpleNamespace(__version__="0.18.0"))
    reason = open3d_peer.open3d_unavailable_reason()
    assert "0.18.0" in reason and "0.19" in reason and "pip install" in reason
