"""`fmfusion track REC`: a TUM folder without poses gets its trajectory.txt by tracking, and then reads as a posed
scene (`fmfusion run REC` fuses it); refusals are one-line errors."""

from __future__ import annotations

import numpy as np
import pytest
from test_recordings import Frames, write_redwood, write_tum
from test_tracker import INTRINSICS, sequence

import fmfusion_jax.cli as cli
from fmfusion_jax.errors import DataError
from fmfusion_jax.io.scene import open_scene


def _walk() -> tuple[Frames, np.ndarray]:
    truth, depths = sequence(1)
    frames = Frames(
        colors=np.full((*depths.shape, 3), 128, np.uint8),
        depths_mm=np.round(depths * 1000).astype(np.uint16),
        poses=truth,
        intrinsics=INTRINSICS,
    )
    return frames, truth


def _ate(estimated: np.ndarray, truth: np.ndarray) -> float:
    aligned = truth[0] @ np.linalg.inv(estimated[0]) @ estimated
    return float(np.sqrt(np.mean(np.sum((aligned[:, :3, 3] - truth[:, :3, 3]) ** 2, axis=1))))


def _tum_without_poses(tmp_path):
    frames, truth = _walk()
    root = write_tum(frames, tmp_path / "walk")
    (root / "groundtruth.txt").unlink()
    return root, truth


def test_track_writes_the_trajectory_that_run_reads(tmp_path, capsys):
    root, truth = _tum_without_poses(tmp_path)
    with pytest.raises(DataError, match="fmfusion track"):  # without poses: the error says what to do
        open_scene(root)
    assert cli.main(["track", str(root), "--no-progress", "--reference", "frame"]) == 0
    assert "60 frames tracked" in (out := capsys.readouterr().out) and (root / "trajectory.txt").is_file()
    assert "; depth and colour)" in out
    scene = open_scene(root)
    assert scene.layout == "tum" and len(scene) == len(truth)
    estimated = scene.poses()
    np.testing.assert_allclose(estimated[0], np.eye(4), atol=1e-9)
    assert _ate(estimated, truth) < 0.005  # the walk at 30 Hz, millimetre depth (measured: 0.35 mm)
    # frame to model (the default) on the same exact depth: its 2 cm TSDF is coarser than the rendered depth
    # (measured 3.2 mm over these 60 frames; it wins on noisy depth, tests/test_tracker.py)
    assert cli.main(["track", str(root), "--no-progress", "--overwrite"]) == 0
    assert "against the model" in capsys.readouterr().out
    assert _ate(open_scene(root).poses(), truth) < 0.01
    # an existing trajectory is never replaced without --overwrite
    assert cli.main(["track", str(root), "--no-progress"]) == 2
    assert "exists" in capsys.readouterr().err


def test_track_writes_the_trajectory_log_of_an_open3d_recording(tmp_path, capsys):
    """Open3D's RealSense / Azure Kinect recorders leave color/, depth/ and camera_intrinsic.json, no poses."""
    frames, truth = _walk()
    root = write_redwood(frames, tmp_path / "realsense")
    (root / "trajectory.log").unlink()
    with pytest.raises(DataError, match="fmfusion track"):
        open_scene(root)
    assert cli.main(["track", str(root), "--no-progress", "--reference", "frame"]) == 0
    scene = open_scene(root)
    assert scene.layout == "redwood" and len(scene) == len(truth)
    assert _ate(scene.poses(), truth) < 0.005


def test_the_parser_spells_the_engine_choices():
    from fmfusion_jax.cli import track
    from fmfusion_jax.engine.tracking import REFERENCES, TrackingConfig

    assert track.REFERENCES == REFERENCES and track.DEFAULT_REFERENCE == TrackingConfig.reference
    from fmfusion_jax.apps.track import TRACK_WIDTH

    assert track.DEFAULT_MAX_WIDTH == TRACK_WIDTH and track.DEFAULT_ICP_WIDTH == TrackingConfig.icp_width


def test_track_at_a_chosen_width(tmp_path, capsys):
    root, truth = _tum_without_poses(tmp_path)
    assert cli.main(["track", str(root), "--no-progress", "--max-width", "80", "--no-color"]) == 0
    assert "at 80x60 (ICP at 80x60; depth alone)" in capsys.readouterr().out
    assert len(open_scene(root).poses()) == len(truth)  # tracked, coarsely (80 x 60: 73 mm ATE, 0.35 mm at 160 x 120)
    with pytest.raises(SystemExit):
        cli.main(["track", str(root), "--max-width", "0"])
    assert "must be at least 1" in capsys.readouterr().err


def test_track_refuses_what_it_cannot_read(tmp_path, capsys):
    assert cli.main(["track", str(tmp_path / "absent")]) == 2
    assert "not found" in capsys.readouterr().err
    (tmp_path / "redwood").mkdir()
    assert cli.main(["track", str(tmp_path / "redwood")]) == 2
    assert "TUM" in capsys.readouterr().err
