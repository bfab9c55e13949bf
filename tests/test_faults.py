"""Fault injection: each corrupt input is built here, and each must give the project's own error naming the
file (or a logged skip / warning naming it), never a traceback, a hang or a silently wrong result."""

from __future__ import annotations

import json
import logging
import os
import types
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_scene_io import INTRINSICS, make_scene, write_matrix

from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io import detections as detection_io
from fmfusion_jax.io.benchmark_format import read_benchmark_predictions
from fmfusion_jax.io.image_file import read_image
from fmfusion_jax.io.map_outputs import write_mesh
from fmfusion_jax.io.scene import DepthSample, open_scene
from fmfusion_jax.labels import load_label_sets
from fmfusion_jax.run.outputs import OutputContext, write_files
from fmfusion_jax.run.scene_fusion import check_depth_units

# ---------------------------------------------------------------------------------------------- scenes


def test_a_reflected_pose_is_refused_naming_its_file(tmp_path):
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])  # orthonormal, det -1: passes R^T R = I, is no camera pose
    root = make_scene(tmp_path / "s", poses=[np.eye(4), mirror, np.eye(4)], num_frames=3)
    with pytest.raises(DataError, match=r"frame-000001\.txt: the pose.s rotation is a reflection"):
        open_scene(root)


def test_the_readers_and_the_mapper_take_a_pose_by_one_rule(tmp_path):
    # a rotation a little off orthonormal (a pose file written with few digits) is read and fused; one further off is
    # refused by both, the reader naming its file, the Mapper (arrays or a frame of one's own) naming the frame
    from fmfusion_jax.mapping.inputs import checked_pose

    rounded, skewed = np.eye(4), np.eye(4)
    rounded[:3, :3] *= 1.003  # |R^T R - I| = 0.006
    skewed[:3, :3] *= 1.01  # 0.02
    root = make_scene(tmp_path / "s", poses=[np.eye(4), rounded, np.eye(4)], num_frames=3)
    assert len(open_scene(root)) == 3
    checked_pose(rounded, "frame-000001")
    with pytest.raises(UserError, match="frame-000001: T_world_camera: the pose is not a rigid transform"):
        checked_pose(skewed, "frame-000001")
    root = make_scene(tmp_path / "t", poses=[np.eye(4), skewed, np.eye(4)], num_frames=3)
    with pytest.raises(DataError, match=r"frame-000001\.txt: the pose is not a rigid transform"):
        open_scene(root)


def test_a_principal_point_outside_the_image_is_refused(tmp_path):
    root = make_scene(tmp_path / "s", num_frames=2)
    K = np.eye(4)
    K[:3, :3] = INTRINSICS.matrix
    K[0, 2] = 5000.0
    write_matrix(root / "intrinsic" / "intrinsic_depth.txt", K)
    with pytest.raises(DataError, match=r"intrinsic_depth\.txt: principal point \(5000, 11\.5\) lies outside"):
        open_scene(root)


def test_a_missing_colour_image_is_an_error_like_a_missing_depth_image(tmp_path):
    root = make_scene(tmp_path / "s", num_frames=5)
    (root / "color" / "frame-000003.jpg").unlink()
    with pytest.raises(DataError, match=r"depth/frame-000003\.png: its colour image is missing .*\(1 depth"):
        open_scene(root)


def test_an_image_path_that_is_not_utf8_reads(tmp_path):
    folder = os.fsencode(tmp_path) + b"/\xff\xfe-odd.png"
    image = np.arange(12, dtype=np.uint16).reshape(3, 4)
    ok, encoded = cv2.imencode(".png", image)
    assert ok
    with open(folder, "wb") as file:
        file.write(encoded.tobytes())
    np.testing.assert_array_equal(read_image(Path(os.fsdecode(folder))), image)


def test_special_files_are_refused_without_reading(tmp_path):
    fifo = tmp_path / "depth.png"
    os.mkfifo(fifo)  # reading it would hang
    with pytest.raises(DataError, match=r"depth\.png: not a regular file"):
        read_image(fifo)
    with pytest.raises(DataError, match="file missing"):
        read_image(tmp_path / "absent.png")


def test_a_pose_file_that_is_a_fifo_is_refused_without_hanging(tmp_path):
    root = make_scene(tmp_path / "s", num_frames=3)
    (root / "pose" / "frame-000001.txt").unlink()
    os.mkfifo(root / "pose" / "frame-000001.txt")
    with pytest.raises(DataError, match=r"frame-000001\.txt: not a regular file"):
        open_scene(root)


def test_a_truncated_jpeg_is_an_error_naming_it(tmp_path):
    path = tmp_path / "cut.jpg"
    ok, encoded = cv2.imencode(".jpg", np.random.default_rng(0).integers(0, 255, (64, 64, 3), np.uint8))
    assert ok
    path.write_bytes(encoded.tobytes()[: len(encoded) // 2])
    with pytest.raises(DataError, match=r"cut\.jpg: truncated JPEG"):
        read_image(path, cv2.IMREAD_COLOR)


def _sample(valid_share: float, percentiles) -> DepthSample:
    return DepthSample(("f0",), valid_share, np.asarray(percentiles, float), np.zeros(3), np.ones(3))


@pytest.mark.parametrize(
    "valid_share, percentiles, message",
    [
        (0.9, [0.001, 0.002, 0.002, 0.003, 0.004], "99% of the depth is closer than 0.004 m"),  # metres as integers
        (0.9, [0.05, 0.1, 0.2, 0.3, 0.4], "closer than 0.4 m"),  # centimetres
        (0.004, [3.9, 3.95, 3.97, 3.99, 4.0], r"only 0\.40% of the pixels"),  # 0.1 mm units
    ],
)
def test_depth_in_the_wrong_units_is_an_error_suggesting_the_scale(tmp_path, valid_share, percentiles, message):
    scene = open_scene(make_scene(tmp_path / "s", num_frames=2))
    with pytest.raises(UserError, match=message) as error:
        check_depth_units(scene, _sample(valid_share, percentiles))
    assert "dataset.depth_scale" in str(error.value)
    check_depth_units(scene, _sample(0.8, [0.4, 1.2, 2.0, 2.8, 3.9]))  # a room: fine


# ---------------------------------------------------------------------------------------------- outputs


def test_an_empty_map_writes_valid_empty_files(tmp_path):
    import trimesh

    write_mesh(tmp_path / "mesh.ply", np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8))
    context = OutputContext(types.SimpleNamespace(name="empty"), tmp_path, None, load_label_sets(), [])
    write_files(context, names=("semantic.ply", "instances.ply", "instances", "labelled_points"))
    for name in ("mesh.ply", "semantic.ply", "instances.ply"):
        assert (tmp_path / name).read_bytes().startswith(b"ply\n")
        assert "vertex 0" in (tmp_path / name).read_bytes().decode("ascii")
        assert len(trimesh.load(tmp_path / name).geometry) == 0  # a viewer opens it: nothing to show
    assert (tmp_path / "instances").is_dir() and not any((tmp_path / "instances").iterdir())


# ---------------------------------------------------------------------------------------------- detections


def _label_file(folder: Path, name: str, text: str) -> None:
    folder.mkdir(exist_ok=True)
    (folder / f"{name}_label.json").write_text(text)


def test_deeply_nested_detection_json_is_a_data_error(tmp_path):
    _label_file(tmp_path, "f", "[" * 100_000 + "]" * 100_000)
    with pytest.raises(DataError, match=r"f_label\.json: malformed JSON \(nested too deep\)"):
        detection_io.read_frame_labels(tmp_path, "f")


def test_a_detection_file_with_too_many_entries_is_refused_before_its_masks(tmp_path):
    entries = [{"value": 0, "label": "background"}] + [
        {"value": v, "labels": {"chair": 0.5}, "box": [0, 0, 1, 1]} for v in range(1, 20_001)
    ]
    _label_file(tmp_path, "f", json.dumps({"tags": "chair", "mask": entries}))
    with pytest.raises(DataError, match=r"f_label\.json: 20001 entries, more than the 1024 detections"):
        detection_io.read_frame_detections(tmp_path, "f")


def test_a_detection_file_that_is_a_fifo_is_refused(tmp_path):
    os.mkfifo(tmp_path / "f_label.json")
    with pytest.raises(DataError, match="not a regular file"):
        detection_io.read_frame_labels(tmp_path, "f")


# ---------------------------------------------------------------------------------------------- evaluation


def _predictions(folder: Path, line: str) -> Path:
    (folder / "pred_mask").mkdir(parents=True, exist_ok=True)
    (folder / "pred_mask" / "s_0.txt").write_text("0\n1\n" * 5)
    txt = folder / "s.txt"
    txt.write_text(line + "\n")
    return txt


@pytest.mark.parametrize(
    "path, message",
    [
        ("/etc/passwd", "is absolute"),
        ("../outside.txt", "leads out of"),
        ("pred_mask/../../outside.txt", "leads out of"),
    ],
)
def test_eval_reads_masks_only_inside_the_prediction_folder(tmp_path, path, message):
    (tmp_path / "outside.txt").write_text("secret-first-line\n")
    txt = _predictions(tmp_path / "preds", f"{path} 3 0.9")
    with pytest.raises(DataError, match=message) as error:
        read_benchmark_predictions(txt)
    assert "secret" not in str(error.value)


def test_eval_refuses_special_and_oversized_mask_files_and_never_prints_their_content(tmp_path):
    folder = tmp_path / "preds"
    txt = _predictions(folder, "pred_mask/fifo.txt 3 0.9")
    os.mkfifo(folder / "pred_mask" / "fifo.txt")
    with pytest.raises(DataError, match=r"fifo\.txt .*not a regular file"):
        read_benchmark_predictions(txt)
    (folder / "pred_mask" / "big.txt").write_text("0\n" * 1000)
    txt.write_text("pred_mask/big.txt 3 0.9\n")
    with pytest.raises(DataError, match=r"big\.txt .*2000 bytes, more than a mask of this mesh"):
        read_benchmark_predictions(txt, num_vertices=10)
    (folder / "pred_mask" / "text.txt").write_text("s3cr3t:x:0:0\n" * 10)
    txt.write_text("pred_mask/text.txt 3 0.9\n")
    with pytest.raises(DataError, match="not a mask value") as error:
        read_benchmark_predictions(txt)
    assert "s3cr3t" not in str(error.value)


def test_eval_warns_about_classes_it_cannot_score(tmp_path, caplog):
    txt = _predictions(tmp_path / "preds", "pred_mask/s_0.txt 999 0.9")
    with caplog.at_level(logging.WARNING):
        predictions = read_benchmark_predictions(txt)
    assert predictions.nyu40_ids.tolist() == [999]
    assert any("outside the 18 benchmark classes (999)" in record.getMessage() for record in caplog.records)
