"""Fuzzing the readers of user files: whatever the content, a reader returns a well-formed result or raises
the project's own `DataError` naming the file; never another exception, a hang or a crash."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fmfusion_jax.errors import DataError
from fmfusion_jax.io import detections as detection_io
from fmfusion_jax.io.scene import read_intrinsics_matrix, read_pose

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-(10**6), 10**6))
number_text = st.lists(numbers, max_size=20).map(lambda xs: " ".join(map(str, xs)))
noise_text = st.one_of(
    number_text,
    st.text(max_size=200),
    st.lists(st.sampled_from(["1", "0", "nan", "-inf", "1e400", "x", "\n", " ", "\t", ","]), max_size=40).map("".join),
)

json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-5, 300), st.floats(allow_nan=False), st.text(max_size=12)),
    lambda children: st.one_of(st.lists(children, max_size=5), st.dictionaries(st.text(max_size=8), children, max_size=5)),
    max_leaves=30,
)
entry = st.fixed_dictionaries(
    {"value": st.one_of(st.integers(-1, 5), st.text(max_size=3))},
    optional={
        "labels": st.one_of(json_values, st.dictionaries(st.text(max_size=6), st.floats(-1, 2), max_size=3)),
        "box": st.one_of(json_values, st.lists(st.floats(-10, 700), min_size=4, max_size=4)),
    },
)
label_documents = st.one_of(
    json_values,
    st.fixed_dictionaries(
        {"mask": st.lists(entry, max_size=5)},
        optional={
            "tags": st.one_of(st.text(max_size=20), json_values),
            "raw_tags": st.one_of(st.text(max_size=20), json_values),
            "tagger_tags": json_values,
        },
    ),
)


def _reads_or_names_the_file(read, path: Path):
    try:
        return read()
    except DataError as error:
        assert str(path) in str(error), error
        return None


@FUZZ
@given(text=noise_text)
def test_pose_reader(text):
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "frame-000000.txt"
        path.write_text(text)
        pose = _reads_or_names_the_file(lambda: read_pose(path), path)
        if pose is not None:
            assert pose.shape == (4, 4)
            if np.all(np.isfinite(pose)):
                assert np.linalg.det(pose[:3, :3]) > 0


@FUZZ
@given(text=noise_text)
def test_intrinsics_reader(text):
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "intrinsic_depth.txt"
        path.write_text(text)
        matrix = _reads_or_names_the_file(lambda: read_intrinsics_matrix(path), path)
        if matrix is not None:
            assert matrix.shape == (3, 3) and matrix[0, 0] > 0 and matrix[1, 1] > 0


@FUZZ
@given(document=label_documents, mask=st.sampled_from(["none", "png", "npy", "garbage"]), count=st.integers(0, 4))
def test_detection_reader(document, mask, count):
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        (root / "f_label.json").write_text(json.dumps(document))
        rng = np.random.default_rng(count)
        if mask == "png":
            import cv2

            cv2.imwrite(str(root / "f_mask.png"), rng.integers(0, count + 1, (12, 16), dtype=np.uint8))
        elif mask == "npy":
            np.save(root / "f_mask.npy", rng.integers(0, 2, (count, 12, 16)).astype(np.uint8))
        elif mask == "garbage":
            (root / "f_mask.png").write_bytes(rng.bytes(50))
        try:
            frame = detection_io.read_frame_detections(root, "f", image_shape=(12, 16))
        except DataError as error:
            assert str(root) in str(error), error
            return
        assert frame is not None
        assert frame.masks.shape == (frame.num_detections, 12, 16) and frame.masks.dtype == bool
        assert len(frame.labels) == frame.num_detections == len(frame.boxes)
