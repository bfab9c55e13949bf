"""`fmfusion info`: on a tiny scene (with detections) and on the real ScanNet scene when present."""

from __future__ import annotations

import time

import numpy as np
import pytest
from test_scene_io import HEIGHT, WIDTH, make_scene, pose_at

import fmfusion_jax.cli as cli
from fmfusion_jax.io.detections import write_frame_detections
from fmfusion_jax.types import FrameDetections


@pytest.fixture(autouse=True)
def only_info(monkeypatch):
    """Builds the parser with `info` alone, so these tests do not depend on the other subcommands' modules."""
    monkeypatch.setattr(cli, "SUBCOMMANDS", ("info",))


def run_info(capsys, *args) -> tuple[int, str, str]:
    code = cli.main(["info", *map(str, args)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def lines_starting(out: str, key: str) -> list[str]:
    return [line for line in out.splitlines() if line.startswith(key)]


def test_info_on_a_tiny_scene(tmp_path, capsys):
    poses = [pose_at(0.1 * i) for i in range(6)]
    poses[4] = np.full((4, 4), -np.inf)
    scene = make_scene(tmp_path / "tiny", num_frames=6, poses=poses)
    code, out, _ = run_info(capsys, scene)
    assert code == 0
    assert lines_starting(out, "layout")[0].split() == ["layout", "scannet"]
    assert "5 usable (stride 1), 1 skipped" in lines_starting(out, "frames")[0]
    assert "frame-000004: non-finite pose" in out
    assert f"{WIDTH} x {HEIGHT}" in lines_starting(out, "image size")[0]
    assert "fx 30.00  fy 30.00  cx 15.50  cy 11.50" in out
    assert "2.00 / 2.00" in lines_starting(out, "depth")[0]
    assert lines_starting(out, "bounds") and lines_starting(out, "trajectory")[0].startswith("trajectory    0.50 m")
    assert "mesh:" in out and "absent" in out
    assert "detections" not in out

    code, out, _ = run_info(capsys, scene, "--stride", "2")
    assert "2 usable (stride 2), 1 skipped" in out  # frames 0, 2 and (bad) 4


def test_info_summarizes_a_detection_folder(tmp_path, capsys):
    scene = make_scene(tmp_path / "tiny", num_frames=6)
    masks = np.zeros((3, HEIGHT, WIDTH), bool)
    boxes = np.zeros((3, 4), np.float32)
    labels = [{"chair": 0.6, "armchair": 0.3}, {"chair": 0.5}, {"unicorn": 0.9}]
    for frame, count in (("frame-000000", 3), ("frame-000002", 1), ("frame-000004", 2), ("frame-000099", 1)):
        write_frame_detections(tmp_path / "pred", FrameDetections(frame, masks[:count], labels[:count], boxes[:count]))
    (tmp_path / "pred" / "frame-000005_label.json").write_text("{broken")
    code, out, _ = run_info(capsys, scene, "--detections", tmp_path / "pred")
    assert code == 0
    assert "4 of 6 scene frames have detection files" in out
    assert "1 files name no frame of the scene" in out and "frame-000099" in out
    assert "1 files; first:" in out and "frame-000005_label.json" in out
    assert "median 2, max 3, total 6" in out
    assert "chair 5, unicorn* 1" in lines_starting(out, "  top labels")[0]


def test_info_errors_are_one_line(tmp_path, capsys):
    (tmp_path / "nothing").mkdir()
    code, _, err = run_info(capsys, tmp_path / "nothing")
    assert code == 2 and "unknown scene layout" in err and "Traceback" not in err
    code, _, err = run_info(capsys, make_scene(tmp_path / "tiny"), "--detections", tmp_path / "absent")
    assert code == 2 and "detection folder not found" in err


def test_info_does_not_import_jax(tmp_path):
    import subprocess
    import sys

    scene = make_scene(tmp_path / "tiny")
    program = (
        "import sys; import fmfusion_jax.cli as cli; cli.SUBCOMMANDS = ('info',); "
        f"code = cli.main(['info', {str(scene)!r}]); assert 'jax' not in sys.modules; sys.exit(code)"
    )
    result = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


@pytest.mark.scannet
def test_info_on_the_real_scene(scannet_scene, capsys):
    start = time.perf_counter()
    code, out, _ = run_info(capsys, scannet_scene)
    elapsed = time.perf_counter() - start
    assert code == 0
    assert "300 usable (stride 1), 0 skipped" in out
    assert "640 x 480" in out and "fx 577.59  fy 578.73" in out
    assert "scene0000_00_vh_clean_2.ply" in out and "absent" not in out
    assert elapsed < 10, f"info took {elapsed:.1f} s"
