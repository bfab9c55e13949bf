"""Detection files: round trips in both mask formats, the authors' format, and every validation error."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io.detections import (
    DetectionFolder,
    list_detection_frames,
    read_frame_detections,
    read_frame_labels,
    write_frame_detections,
)
from fmfusion_jax.types import FrameDetections

H, W = 12, 16
FRAME = "frame-000010"

#: The authors' JSON, as in the reference notes (box scaled to a 16x12 image).
AUTHORS_JSON = """{"raw_tags": "armchair. chair. floor. room. table",
 "tags": "armchair. chair. floor. table",
 "mask": [{"value": 0, "label": "background"},
          {"value": 1, "labels": {"chair": 0.52, "armchair": 0.38}, "box": [1.5, 2.0, 6.25, 9.0]},
          {"value": 2, "labels": {"floor": 0.9}, "box": [0, 8, 16, 12]}]}"""


def box_masks(*boxes) -> np.ndarray:
    """`(K, H, W)` bool masks filling integer boxes (u0, v0, u1, v1)."""
    masks = np.zeros((len(boxes), H, W), bool)
    for k, (u0, v0, u1, v1) in enumerate(boxes):
        masks[k, v0:v1, u0:u1] = True
    return masks


def make_detections(overlapping: bool = False) -> FrameDetections:
    boxes = [(1, 1, 5, 6), (6, 2, 12, 10), (3, 4, 9, 8) if overlapping else (12, 0, 15, 3)]
    return FrameDetections(
        frame_name=FRAME,
        masks=box_masks(*boxes),
        labels=[{"chair": 0.52, "armchair": 0.375}, {"table": 0.8}, {"unicorn lamp": 0.3, "lamp": 1.0}],
        boxes=np.array(boxes, np.float32) + np.float32(0.25),
        raw_tags=["armchair", "chair", "room", "table", "glass door"],
        tags=["armchair", "chair", "table"],
        prompt=["armchair", "chair", "table", "lamp"],
    )


def assert_same(a: FrameDetections, b: FrameDetections) -> None:
    assert a.frame_name == b.frame_name
    np.testing.assert_array_equal(a.masks, b.masks)
    assert a.masks.dtype == b.masks.dtype == bool
    assert a.labels == b.labels
    np.testing.assert_array_equal(a.boxes, b.boxes)
    assert b.boxes.dtype == np.float32
    assert (a.raw_tags, a.tags, a.prompt) == (b.raw_tags, b.tags, b.prompt)


@pytest.mark.parametrize("mask_format", ["png", "npy"])
def test_round_trip(tmp_path, mask_format):
    detections = make_detections()
    written = write_frame_detections(tmp_path, detections, mask_format=mask_format)
    assert sorted(p.name for p in written) == sorted([f"{FRAME}_mask.{mask_format}", f"{FRAME}_label.json"])
    assert_same(detections, read_frame_detections(tmp_path, FRAME, image_shape=(H, W)))
    assert list_detection_frames(tmp_path) == [FRAME]
    # the authors' reader sees the prompt as `tags`
    assert json.loads((tmp_path / f"{FRAME}_label.json").read_text())["tags"] == "armchair. chair. table. lamp"


def test_overlapping_masks_requested_as_png_are_written_as_npy(tmp_path, caplog):
    detections = make_detections(overlapping=True)
    write_frame_detections(tmp_path, make_detections(), mask_format="png")  # an older png of the same frame
    with caplog.at_level(logging.INFO, logger="fmfusion_jax.io.detections"):
        written = write_frame_detections(tmp_path, detections, mask_format="png")
    assert written[0].name == f"{FRAME}_mask.npy" and "overlap" in caplog.text
    assert not (tmp_path / f"{FRAME}_mask.png").exists()  # the stale png is gone
    assert_same(detections, read_frame_detections(tmp_path, FRAME))


def test_empty_frame_round_trip(tmp_path):
    for mask_format in ("png", "npy"):
        empty = FrameDetections.empty(FRAME, H, W)
        write_frame_detections(tmp_path / mask_format, empty, mask_format=mask_format)
        assert_same(empty, read_frame_detections(tmp_path / mask_format, FRAME))


def test_reads_the_authors_format_with_npy_masks(tmp_path):
    (tmp_path / f"{FRAME}_label.json").write_text(AUTHORS_JSON)
    masks = np.zeros((2, H, W), np.int64)  # the authors save 0/1 ints
    masks[0, 2:9, 2:6] = 1
    masks[1, 8:, :] = 1
    np.save(tmp_path / f"{FRAME}_mask.npy", masks)
    detections = read_frame_detections(tmp_path, FRAME)
    assert detections.num_detections == 2
    assert detections.labels == [{"chair": 0.52, "armchair": 0.38}, {"floor": 0.9}]
    np.testing.assert_array_equal(detections.boxes, np.array([[1.5, 2, 6.25, 9], [0, 8, 16, 12]], np.float32))
    np.testing.assert_array_equal(detections.masks, masks.astype(bool))
    assert detections.raw_tags == ["armchair", "chair", "floor", "room", "table"]
    assert detections.tags == detections.prompt == ["armchair", "chair", "floor", "table"]


def test_reads_the_authors_format_with_png_masks(tmp_path):
    (tmp_path / f"{FRAME}_label.json").write_text(AUTHORS_JSON)
    label_image = np.zeros((H, W), np.uint8)
    label_image[2:9, 2:6] = 1
    label_image[9:, :] = 2
    cv2.imwrite(str(tmp_path / f"{FRAME}_mask.png"), label_image)
    detections = DetectionFolder(tmp_path).get(FRAME)
    np.testing.assert_array_equal(detections.masks, np.stack([label_image == 1, label_image == 2]))
    assert detections.tags == detections.prompt


def test_frame_without_files_reads_as_none(tmp_path):
    write_frame_detections(tmp_path, make_detections())
    assert read_frame_detections(tmp_path, "frame-000020") is None
    folder = DetectionFolder(tmp_path)
    assert len(folder) == 1 and FRAME in folder and folder.get("frame-000020") is None
    with pytest.raises(UserError, match="not found"):
        list_detection_frames(tmp_path / "absent")


def test_labels_outside_the_open_set_are_kept(tmp_path):
    write_frame_detections(tmp_path, make_detections())
    assert read_frame_detections(tmp_path, FRAME).labels[2] == {"unicorn lamp": 0.3, "lamp": 1.0}


def test_box_slightly_outside_the_image_is_clipped(tmp_path):
    data = json.loads(AUTHORS_JSON)
    data["mask"][2]["box"] = [-0.4, 7.5, 16.5, 12.3]
    _write_authors_frame(tmp_path, data)
    np.testing.assert_array_equal(read_frame_detections(tmp_path, FRAME).boxes[1], [0, 7.5, 16, 12])


def test_masks_that_lose_every_pixel_in_a_png_keep_their_detection(tmp_path):
    data = json.loads(AUTHORS_JSON)
    (tmp_path / f"{FRAME}_label.json").write_text(json.dumps(data))
    label_image = np.zeros((H, W), np.uint8)
    label_image[9:, :] = 2  # detection 1 painted over entirely
    cv2.imwrite(str(tmp_path / f"{FRAME}_mask.png"), label_image)
    detections = read_frame_detections(tmp_path, FRAME)
    assert detections.num_detections == 2 and detections.masks[0].sum() == 0


def test_writing_a_tag_that_cannot_round_trip_is_refused(tmp_path):
    detections = make_detections()
    detections.prompt = ["st. patrick's day"]
    with pytest.raises(ValueError, match="st. patrick"):
        write_frame_detections(tmp_path, detections)
    with pytest.raises(UserError, match="mask_format"):
        write_frame_detections(tmp_path, make_detections(), mask_format="jpg")


def _write_authors_frame(folder: Path, data, mask_format: str = "png", masks: np.ndarray | None = None) -> None:
    """Writes a JSON (dict or raw text) and masks: by default one box-free png with values 1 and 2."""
    text = data if isinstance(data, str) else json.dumps(data)
    (folder / f"{FRAME}_label.json").write_text(text)
    if masks is None:
        masks = box_masks((2, 2, 6, 9), (0, 9, 16, 12))
    if mask_format == "npy":
        np.save(folder / f"{FRAME}_mask.npy", masks)
    else:
        label_image = np.zeros(masks.shape[1:], np.uint8)
        for k, mask in enumerate(masks):
            label_image[mask] = k + 1
        cv2.imwrite(str(folder / f"{FRAME}_mask.png"), label_image)


def _edited(edit) -> dict:
    data = json.loads(AUTHORS_JSON)
    edit(data)
    return data


def _set_detection(key, value, index=1):
    return lambda data: data["mask"][index].__setitem__(key, value)


INVALID_JSON_CASES = {
    "malformed JSON": ('{"mask": [', "malformed JSON"),
    "not an object": ("[1, 2]", "expected a JSON object"),
    "no mask list": ({"tags": "chair"}, "'mask' must be a list"),
    "score as string": (_edited(_set_detection("labels", {"chair": "0.5"})), "score of 'chair'"),
    "score above 1": (_edited(_set_detection("labels", {"chair": 1.5})), r"number in \[0, 1\]"),
    "score as bool": (_edited(_set_detection("labels", {"chair": True})), "score of 'chair'"),
    "labels as list": (_edited(_set_detection("labels", ["chair"])), "'labels' must be an object"),
    "labels missing": (_edited(lambda d: d["mask"][1].pop("labels")), "'labels' must be an object"),
    "empty label": (_edited(_set_detection("labels", {"": 0.5})), "non-empty string"),
    "box of 3": (_edited(_set_detection("box", [1, 2, 3])), "4 finite numbers"),
    "box with NaN": (_edited(_set_detection("box", [1, 2, float("nan"), 4])), "4 finite numbers"),
    "box with a string": (_edited(_set_detection("box", [1, 2, "3", 4])), "4 finite numbers"),
    "box reversed": (_edited(_set_detection("box", [6, 2, 1, 9])), "u0 > u1"),
    "box outside": (_edited(_set_detection("box", [100, 200, 300, 400])), "outside the 16x12 image"),
    "value as string": (_edited(_set_detection("value", "1")), "'value' must be a non-negative integer"),
    "duplicate values": (_edited(_set_detection("value", 2)), r"values \[2\] appear more than once"),
    "box on background": (_edited(_set_detection("box", [0, 0, 1, 1], index=0)), "value 0 is the background"),
    "detection without box": (_edited(lambda d: d["mask"][1].pop("box")), "has no 'box'"),
    "tags of numbers": (_edited(lambda d: d.__setitem__("tags", [1, 2])), "'tags' must be"),
    "tagger_tags not a list": (_edited(lambda d: d.__setitem__("tagger_tags", "chair")), "'tagger_tags' must be"),
}


@pytest.mark.parametrize("case", INVALID_JSON_CASES)
def test_invalid_json_is_a_data_error_naming_the_file(tmp_path, case):
    data, message = INVALID_JSON_CASES[case]
    _write_authors_frame(tmp_path, data)
    with pytest.raises(DataError, match=f"{FRAME}_label.json.*{message}"):
        read_frame_detections(tmp_path, FRAME)


def test_mask_count_must_match_the_json(tmp_path):
    _write_authors_frame(tmp_path, AUTHORS_JSON, "npy", masks=box_masks((1, 1, 3, 3)))
    with pytest.raises(DataError, match=f"{FRAME}_mask.npy: 1 masks for 2 detections"):
        read_frame_detections(tmp_path, FRAME)


def test_npy_values_must_index_the_masks(tmp_path):
    data = _edited(_set_detection("value", 5))
    _write_authors_frame(tmp_path, data, "npy")
    with pytest.raises(DataError, match=r"_mask.npy: detection values \[2, 5\] must be 1..2"):
        read_frame_detections(tmp_path, FRAME)


def test_npy_masks_must_be_zero_one(tmp_path):
    _write_authors_frame(tmp_path, AUTHORS_JSON, "npy", masks=box_masks((2, 2, 6, 9), (0, 9, 16, 12)) * 7)
    with pytest.raises(DataError, match="_mask.npy: masks hold values other than 0 and 1"):
        read_frame_detections(tmp_path, FRAME)


def test_npy_masks_must_be_three_dimensional(tmp_path):
    (tmp_path / f"{FRAME}_label.json").write_text(AUTHORS_JSON)
    np.save(tmp_path / f"{FRAME}_mask.npy", np.zeros((H, W)))
    with pytest.raises(DataError, match=r"must be \(K, H, W\)"):
        read_frame_detections(tmp_path, FRAME)


def test_corrupt_npy_is_a_data_error(tmp_path):
    (tmp_path / f"{FRAME}_label.json").write_text(AUTHORS_JSON)
    (tmp_path / f"{FRAME}_mask.npy").write_bytes(b"garbage")
    with pytest.raises(DataError, match="_mask.npy: unreadable"):
        read_frame_detections(tmp_path, FRAME)


def test_png_value_without_a_json_entry_is_a_data_error(tmp_path):
    _write_authors_frame(tmp_path, AUTHORS_JSON, masks=box_masks((2, 2, 6, 9), (0, 9, 16, 12), (10, 0, 12, 2)))
    with pytest.raises(DataError, match=r"_mask.png: pixel values \[3\] have no detection"):
        read_frame_detections(tmp_path, FRAME)


def test_corrupt_or_colour_png_is_a_data_error(tmp_path):
    (tmp_path / f"{FRAME}_label.json").write_text(AUTHORS_JSON)
    (tmp_path / f"{FRAME}_mask.png").write_bytes(b"garbage")
    with pytest.raises(DataError, match="_mask.png: unreadable"):
        read_frame_detections(tmp_path, FRAME)
    cv2.imwrite(str(tmp_path / f"{FRAME}_mask.png"), np.zeros((H, W, 3), np.uint8))
    with pytest.raises(DataError, match="_mask.png: expected a single-channel"):
        read_frame_detections(tmp_path, FRAME)


def test_missing_mask_file_is_a_data_error(tmp_path):
    (tmp_path / f"{FRAME}_label.json").write_text(AUTHORS_JSON)
    with pytest.raises(DataError, match=f"{FRAME}_mask.npy: mask file missing"):
        read_frame_detections(tmp_path, FRAME)


@pytest.mark.parametrize("mask_format", ["png", "npy"])
def test_mask_size_must_match_the_image(tmp_path, mask_format):
    _write_authors_frame(tmp_path, AUTHORS_JSON, mask_format)
    assert read_frame_detections(tmp_path, FRAME, image_shape=(H, W)) is not None
    with pytest.raises(DataError, match=f"_mask.{mask_format}: masks are 16x12, the images are 32x24"):
        read_frame_detections(tmp_path, FRAME, image_shape=(24, 32))


def test_read_frame_labels_skips_the_masks(tmp_path):
    (tmp_path / f"{FRAME}_label.json").write_text(AUTHORS_JSON)  # no mask file: labels still read
    parsed = read_frame_labels(tmp_path, FRAME)
    assert parsed["values"] == [1, 2] and parsed["labels"][1] == {"floor": 0.9}
    assert read_frame_labels(tmp_path, "frame-000099") is None


def test_random_frames_round_trip_exactly(tmp_path):
    """Random masks (overlapping or not), labels, scores and boxes survive both formats bit for bit."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    label_names = st.text(alphabet="abcdefgh xyz", min_size=1, max_size=8).map(str.strip).filter(bool)
    scores = st.floats(0.0, 1.0, allow_nan=False)

    @settings(max_examples=30, deadline=None)
    @given(
        count=st.integers(0, 5),
        seed=st.integers(0, 2**31),
        mask_format=st.sampled_from(["png", "npy"]),
        labels=st.lists(st.dictionaries(label_names, scores, min_size=1, max_size=3), min_size=5, max_size=5),
    )
    def round_trip(count, seed, mask_format, labels):
        rng = np.random.default_rng(seed)
        corners = rng.uniform(0, [W, H], (count, 2, 2)).astype(np.float32)
        boxes = np.concatenate([corners.min(1), corners.max(1)], axis=1)
        detections = FrameDetections(
            FRAME, rng.random((count, H, W)) < 0.3, labels[:count], boxes, raw_tags=["a b", "c"], tags=["c"], prompt=["c", "d"]
        )
        folder = tmp_path / f"{seed}-{mask_format}"
        write_frame_detections(folder, detections, mask_format=mask_format)
        assert_same(detections, read_frame_detections(folder, FRAME))

    round_trip()
