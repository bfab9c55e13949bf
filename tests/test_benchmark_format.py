"""The benchmark prediction format: writing, reading back, and the errors a user sees."""

from __future__ import annotations

import numpy as np
import pytest

from fmfusion_jax.errors import DataError
from fmfusion_jax.io.benchmark_format import (
    InstancePredictions,
    export_ground_truth_as_predictions,
    read_benchmark_predictions,
    read_mask_file,
    write_benchmark_predictions,
)


def sample(num_vertices: int = 150) -> InstancePredictions:
    rng = np.random.default_rng(1)
    return InstancePredictions(
        rng.random((3, num_vertices)) < 0.3, np.array([3, 39, 5]), np.array([0.123456789012345, 1.0, 1e-7])
    )


def test_round_trip(tmp_path):
    preds = sample()
    txt = write_benchmark_predictions(tmp_path / "out", "scene0000_00", preds)
    assert txt == tmp_path / "out" / "scene0000_00.txt"
    assert txt.read_text().splitlines()[1] == "pred_mask/scene0000_00_1.txt 39 1.0"
    mask_lines = (tmp_path / "out" / "pred_mask" / "scene0000_00_0.txt").read_text().splitlines()
    assert len(mask_lines) == 150 and set(mask_lines) <= {"0", "1"}
    back = read_benchmark_predictions(txt, num_vertices=150)
    np.testing.assert_array_equal(back.masks, preds.masks)
    np.testing.assert_array_equal(back.nyu40_ids, preds.nyu40_ids)
    np.testing.assert_array_equal(back.confidences, preds.confidences)  # exact: confidence order and ties survive
    assert read_benchmark_predictions(txt).num_vertices == 150  # inferred from the masks


def test_empty_and_blank_lines(tmp_path):
    txt = write_benchmark_predictions(tmp_path, "s", InstancePredictions.empty(10))
    assert txt.read_text() == ""
    assert read_benchmark_predictions(txt, num_vertices=10).masks.shape == (0, 10)
    txt = write_benchmark_predictions(tmp_path, "t", sample(10))
    txt.write_text("\n" + txt.read_text().replace("\n", "\n\n"))
    assert read_benchmark_predictions(txt).num_instances == 3


def test_mask_with_crlf_and_a_path_inside_the_folder_but_not_an_absolute_one(tmp_path):
    mask = tmp_path / "m.txt"
    mask.write_bytes(b"0\r\n1\r\n1\r\n")
    np.testing.assert_array_equal(read_mask_file(mask), [False, True, True])
    txt = tmp_path / "scene.txt"
    txt.write_text("./m.txt 3 0.5\n")
    assert read_benchmark_predictions(txt, 3).masks.tolist() == [[False, True, True]]
    txt.write_text(f"{mask} 3 0.5\n")
    with pytest.raises(DataError, match="is absolute"):
        read_benchmark_predictions(txt, 3)


@pytest.mark.parametrize(
    "line, message",
    [
        ("pred_mask/s_0.txt 3", r"s\.txt:1: expected 'MASK_PATH NYU40_ID CONFIDENCE'"),
        ("pred_mask/s_0.txt 3.5 0.9", r"s\.txt:1: nyu40 id '3\.5' is not an integer"),
        ("pred_mask/s_0.txt 3 high", r"s\.txt:1: confidence 'high' is not a number"),
        ("pred_mask/s_0.txt 3 nan", r"s\.txt:1: confidence 'nan' is not finite"),
        ("pred_mask/missing.txt 3 0.9", r"missing\.txt \(listed at .*s\.txt:1\): mask file not found"),
        ("pred_mask/s_0.txt 3 0.9\npred_mask/s_0.txt 4 0.8", r"s\.txt:2: mask pred_mask/s_0\.txt is already listed on line 1"),
    ],
)
def test_malformed_lines_name_file_and_line(tmp_path, line, message):
    write_benchmark_predictions(tmp_path, "s", sample(10))
    (tmp_path / "s.txt").write_text(line + "\n")
    with pytest.raises(DataError, match=message):
        read_benchmark_predictions(tmp_path / "s.txt")


def test_mask_length_and_values_are_checked(tmp_path):
    txt = write_benchmark_predictions(tmp_path, "s", sample(10))
    with pytest.raises(DataError, match=r"s_0\.txt \(listed at .*s\.txt:1\): 10 lines but the mesh has 12 vertices"):
        read_benchmark_predictions(txt, num_vertices=12)
    mask = tmp_path / "pred_mask" / "s_1.txt"
    mask.write_text("0\n1\n2\n" + "0\n" * 7)
    with pytest.raises(DataError, match=r"s_1\.txt:3 \(listed at .*s\.txt:2\): not a mask value"):
        read_benchmark_predictions(txt)
    mask.write_text("0\n" * 9)  # one line short: the masks disagree with each other
    with pytest.raises(DataError, match=r"s_1\.txt .*: 9 lines but the mesh has 10 vertices"):
        read_benchmark_predictions(txt)
    with pytest.raises(DataError, match=r"nothing\.txt: prediction file not found"):
        read_benchmark_predictions(tmp_path / "nothing.txt")


def test_predictions_validate_shapes():
    with pytest.raises(ValueError, match=r"2 masks but 1 nyu40 ids"):
        InstancePredictions(np.zeros((2, 5), bool), np.array([3]), np.array([1.0, 1.0]))
    with pytest.raises(ValueError, match=r"masks must be \(P, V\)"):
        InstancePredictions(np.zeros(5, bool), np.array([3]), np.array([1.0]))


def test_export_ground_truth_as_predictions():
    ids = np.array([0, 3001, 3001, 1002, 5003, 5003, 3004, 0, 7])
    preds = export_ground_truth_as_predictions(ids)
    # Benchmark classes only (1 = wall and the class-less 7 are left out), in increasing id order.
    np.testing.assert_array_equal(preds.nyu40_ids, [3, 3, 5])
    np.testing.assert_array_equal(preds.confidences, [1.0, 1.0, 1.0])
    np.testing.assert_array_equal(preds.masks, [ids == 3001, ids == 3004, ids == 5003])
