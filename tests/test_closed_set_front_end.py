"""The closed-set front end (`detectors.closed_set`): COCO detector -> vocabulary -> SAM (+ classifier, proposals).

Two kinds of test: on made-up arrays and tiny ONNX stand-ins (always run), and on real ScanNet frames with the
real pretrained models of ../shared/models (NanoDet-g, SSD MobileNetV2, MobileSAM, EfficientNet-Lite3; skipped
with the reason when the folder or the frames are absent; $FMFUSION_MODELS_DIR points elsewhere).
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("onnx")

import onnx_models as om  # noqa: E402
from onnx import TensorProto, helper  # noqa: E402

import fmfusion_jax.cli as cli  # noqa: E402
from detectors import (  # noqa: E402
    ClosedSetModels,
    CocoDetector,
    ContractError,
    FoundationModels,
    ProposalConfig,
    check_models_folder,
    load_front_end,
    load_vocabulary,
    per_class_nms,
    read_manifest,
)
from detectors.coco_detector import decode_nanodet, letterbox, unletterbox  # noqa: E402
from detectors.manifest import merge  # noqa: E402
from detectors.proposals import grid_points, mask_iou, stability_score  # noqa: E402
from fmfusion_jax.errors import UserError  # noqa: E402
from fmfusion_jax.labels import load_label_sets  # noqa: E402

SHARED_MODELS = Path(os.environ.get("FMFUSION_MODELS_DIR", Path(__file__).parents[1].parent / "shared" / "models"))
OPEN_LABELS = set(load_label_sets().open_labels)


# --- tiny stand-ins: an SSD and a classifier with constant answers ---------------------------------------------


def _constant_model(input_name: str, input_type, input_shape, outputs: dict[str, np.ndarray], cast_uint8=()):
    """A model whose outputs are constants (plus 0 x the input's mean, so that the input is used)."""
    nodes = [
        helper.make_node("Cast", [input_name], ["x"], to=TensorProto.FLOAT),
        helper.make_node("ReduceMean", ["x"], ["mean"], keepdims=0),
        helper.make_node("Mul", ["mean", "zero"], ["nothing"]),
    ]
    inits = [om._const("zero", np.array(0.0, np.float32))]
    infos = []
    for name, value in outputs.items():
        inits.append(om._const(f"{name}_value", value.astype(np.float32)))
        target = f"{name}_f" if name in cast_uint8 else name
        nodes.append(helper.make_node("Add", [f"{name}_value", "nothing"], [target]))
        if name in cast_uint8:
            nodes.append(helper.make_node("Cast", [target], [name], to=TensorProto.UINT8))
        infos.append(
            helper.make_tensor_value_info(name, TensorProto.UINT8 if name in cast_uint8 else TensorProto.FLOAT, value.shape)
        )
    return om._model(nodes, [helper.make_tensor_value_info(input_name, input_type, input_shape)], infos, inits)


#: Stand-in COCO ids: our class index -> (ssd category id, name).
TINY_COCO = {0: (1, "person"), 56: (62, "chair"), 57: (63, "couch"), 60: (67, "dining table"), 61: (70, "toilet")}
#: The stand-in SSD's detections: (name, score, pixel box in a 64x48 image).
TINY_DETECTIONS = [("couch", 0.8, (4, 8, 28, 40)), ("person", 0.9, (30, 2, 40, 30)), ("dining table", 0.5, (34, 20, 60, 44))]


def write_tiny_closed_set(folder: Path, classifier_probs: dict[int, float]) -> Path:
    """A closed-set models folder: stand-in SSD (TINY_DETECTIONS), SAM box decoder, constant classifier."""
    lines = ["nanodet_id\tssd_id\tname"]
    lines += [f"{k}\t{TINY_COCO[k][0]}\t{TINY_COCO[k][1]}" if k in TINY_COCO else f"{k}\t{100 + k}\tclass {k}" for k in range(80)]
    om.write_lines(folder / "detector" / "coco_labels.txt", lines)
    ids = {name: cid for cid, name in TINY_COCO.values()}
    boxes, scores, classes = np.zeros((1, 100, 4)), np.zeros((1, 100)), np.zeros((1, 100))
    for k, (name, score, (u0, v0, u1, v1)) in enumerate(TINY_DETECTIONS):
        boxes[0, k] = (v0 / 48, u0 / 64, v1 / 48, u1 / 64)
        scores[0, k], classes[0, k] = score, ids[name]
    outputs = {
        "detection_boxes": boxes,
        "detection_scores": scores,
        "detection_classes": classes,
        "num_detections": np.array([len(TINY_DETECTIONS)]),
    }
    om.save(_constant_model("image_tensor", TensorProto.UINT8, [1, "h", "w", 3], outputs), folder / "detector" / "ssd.onnx")
    probs = np.zeros((1, 1000))
    for k, p in classifier_probs.items():
        probs[0, k] = round(p * 256)
    model = _constant_model("images", TensorProto.UINT8, [1, 280, 280, 3], {"Softmax": probs}, cast_uint8=("Softmax",))
    om.save(model, folder / "classifier" / "tiny_classifier.onnx")
    names = {0: "studio couch, day bed", 1: "dining table, board", 2: "barber chair"}
    om.write_lines(folder / "classifier" / "imagenet_labels.txt", [names.get(k, f"thing {k}") for k in range(1000)])
    om.save(om.sam_encoder_model(input_name="input"), folder / "sam" / "tiny_encoder.onnx")
    om.save(om.sam_decoder_model(), folder / "sam" / "tiny_decoder.onnx")
    return folder


@pytest.fixture(scope="module")
def tiny_folder(tmp_path_factory) -> Path:
    return write_tiny_closed_set(tmp_path_factory.mktemp("closed_set"), {0: 0.3, 1: 0.5})


def test_stand_in_front_end_maps_drops_before_sam_and_adds_agreeing_labels(tiny_folder, monkeypatch):
    models = load_front_end(tiny_folder)
    assert isinstance(models, ClosedSetModels) and models.detector.kind == "ssd"
    assert models.segmenter.fixed_batch == 1  # the decoder's prompt axis is fixed: one call per box
    decoded = []
    original = models.segmenter.decode
    monkeypatch.setattr(models.segmenter, "decode", lambda e, c, lab: decoded.append(len(c)) or original(e, c, lab))
    image = np.full((48, 64, 3), 120, np.uint8)
    found = models.detect(image, "frame-000000")
    # person maps to nothing: dropped before SAM (2 boxes decoded, then the 24 grid points of the proposals)
    assert decoded[0] == 2
    assert [max(d, key=d.__getitem__) for d in found.labels] == ["couch", "table"]
    # the classifier's dining table -> kitchen table agrees with COCO's table (same closed class) and joins it at
    # 0.5 x 0.5; its studio couch -> couch (0.15) never lowers the couch's 0.8; nothing joins across classes
    assert found.labels[0] == {"couch": pytest.approx(0.8)}
    assert found.labels[1] == {"table": pytest.approx(0.5), "kitchen table": pytest.approx(0.25, abs=0.01)}
    # detector classes, then the classifier names behind kept labels (its dining table is COCO's name too)
    assert found.raw_tags == ["person", "couch", "dining table", "studio couch"]
    assert found.tags == found.prompt == ["couch", "table", "kitchen table"]
    np.testing.assert_allclose(found.boxes, [[4, 8, 28, 40], [34, 20, 60, 44]], atol=1e-3)
    for mask, box in zip(found.masks, found.boxes):
        np.testing.assert_array_equal(mask, om.box_mask(box, 48, 64))
    assert set(models.timings) == {"detector", "sam_encoder", "sam_decoder", "classifier"} and models.frames == 1
    models.reset()
    assert models.frames == 0 and not any(models.timings.values())


def test_stand_in_without_classification_or_proposals(tiny_folder):
    models = load_front_end(tiny_folder, overrides={"classifier": {"classify_boxes": False}, "proposals": None})
    found = models.detect(np.full((48, 64, 3), 120, np.uint8), "frame-000000")
    assert found.labels == [{"couch": pytest.approx(0.8)}, {"table": pytest.approx(0.5)}]
    assert found.raw_tags == ["person", "couch", "dining table"]
    assert models.timings["classifier"] == 0.0


# --- NanoDet decoding and per-class NMS on made-up arrays -------------------------------------------------------


def test_per_class_nms_suppresses_within_a_class_only():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [0, 0, 10, 10], [50, 50, 60, 60], [2, 0, 12, 10]], np.float32)
    scores = np.array([0.9, 0.8, 0.7, 0.6, 0.95], np.float32)
    classes = np.array([3, 3, 5, 3, 5])
    # class 3: 0 beats 1 (IoU 0.68); class 5: 4 beats 2 (IoU 0.67); 3 overlaps nothing
    np.testing.assert_array_equal(per_class_nms(boxes, scores, classes, 0.6), [4, 0, 3])
    np.testing.assert_array_equal(per_class_nms(boxes, scores, classes, 0.6, max_detections=2), [4, 0])
    np.testing.assert_array_equal(per_class_nms(boxes, scores, classes, 0.7), [4, 0, 1, 2, 3])
    assert per_class_nms(np.zeros((0, 4)), np.zeros(0), np.zeros(0, int), 0.6).size == 0


def test_decode_nanodet_bins_and_letterbox():
    cells = [(416 // s) ** 2 for s in (8, 16, 32)]
    scores = [np.zeros((n, 80), np.float32) for n in cells]
    regression = [np.zeros((n, 44), np.float32) for n in cells]
    # stride 8, cell (x 10, y 5): centre (84, 44); one-hot bins: left 3, top 2, right 5, bottom 10 -> x 8
    cell = 5 * 52 + 10
    scores[0][cell, 57] = 0.8
    scores[0][cell + 1, 57] = 0.2  # below the threshold: not decoded
    for side, bin_ in enumerate((3, 2, 5, 10)):
        regression[0][cell, side * 11 + bin_] = 50.0
    boxes, kept, classes = decode_nanodet(scores, regression, 0.35)
    np.testing.assert_allclose(boxes, [[84 - 24, 44 - 16, 84 + 40, min(44 + 80, 416)]], atol=1e-3)
    assert kept.tolist() == [pytest.approx(0.8)] and classes.tolist() == [57]
    # a 640x480 frame is scaled by 0.65 and centred vertically (52 px bands)
    transform = letterbox(480, 640)
    np.testing.assert_allclose(transform, [[0.65, 0, 0], [0, 0.65, 52]], atol=1e-6)
    np.testing.assert_allclose(unletterbox(np.array([[0, 52, 416, 364]]), transform, 480, 640), [[0, 0, 640, 480]], atol=1e-3)
    np.testing.assert_allclose(unletterbox(np.array([[-5, 0, 420, 40]]), transform, 480, 640), [[0, 0, 640, 0]], atol=1e-3)


def test_proposal_helpers():
    np.testing.assert_allclose(grid_points(40, 60, (3, 2)), [[10, 10], [30, 10], [50, 10], [10, 30], [30, 30], [50, 30]])
    logits = np.array([[-2.0, -0.5, 0.5, 2.0]])
    assert stability_score(logits) == pytest.approx(1 / 3)
    a, b = np.zeros((4, 4), bool), np.zeros((4, 4), bool)
    a[:2], b[1:3] = True, True
    assert mask_iou(a, b) == pytest.approx(4 / 12)
    with pytest.raises(UserError, match="grid"):
        ProposalConfig(grid=(0, 4))
    with pytest.raises(UserError, match="min_stability"):
        ProposalConfig(min_stability=1.5)


# --- the vocabulary table ---------------------------------------------------------------------------------------


def test_vocabulary_loads_and_maps():
    vocabulary = load_vocabulary()
    coco = {name: vocabulary.entry("coco", name) for name in vocabulary.tables["coco"]}
    assert len(coco) == 80
    expected = {"couch": "couch", "bed": "bed", "chair": "chair", "dining table": "table", "toilet": "toilet bowl"}
    expected.update({"sink": "sink", "refrigerator": "fridge"})
    assert {name: coco[name].label for name in expected} == expected  # type: ignore[union-attr]
    assert all(coco[name] is None for name in ("tv", "book", "laptop", "person"))
    imagenet = {
        "studio couch": "couch",
        "four-poster": "bed",
        "barber chair": "swivel chair",
        "desk": "office desk",
        "dining table": "kitchen table",
        "bookcase": "bookshelf",
        "wardrobe": "closet",
        "file": "file cabinet",
        "toilet seat": "toilet bowl",
        "washbasin": "sink",
        "ashcan": "bin",
    }
    assert {name: vocabulary.entry("imagenet", name).label for name in imagenet} == imagenet  # type: ignore[union-attr]
    entries = [e for table in vocabulary.tables.values() for e in table.values() if e is not None]
    assert {e.label for e in entries} <= OPEN_LABELS and all(0 < e.weight <= 1 for e in entries)
    # score x weight, the max over the names of one label; unknown names are dropped
    mapped = vocabulary.map_scores({"quilt": 0.6, "four-poster": 0.2, "toaster": 0.9, "desk": 0.1}, "imagenet")
    assert mapped == {"bed": pytest.approx(0.3), "office desk": pytest.approx(0.1)}
    assert vocabulary.map_scores([("couch", 0.7), ("tv", 0.9)], "coco") == {"couch": pytest.approx(0.7)}


def test_vocabulary_errors_name_the_entry(tmp_path):
    path = tmp_path / "table.yaml"
    cases = [
        ("imagenet:\n  quilt: {label: beds, weight: 0.5}\n", "imagenet entry 'quilt' -> 'beds': not an open-set label"),
        ("coco:\n  couch: {label: couch, weight: 0}\n", "coco entry 'couch': weight 0"),
        ("coco:\n  couch: [couch]\n", "coco entry 'couch': expected an open-set label"),
        ("objects365:\n  sofa: couch\n", "unknown section"),
        ("coco: [1, 2\n", "not valid YAML"),
    ]
    for text, message in cases:
        path.write_text(text)
        with pytest.raises(UserError, match=message):
            load_vocabulary(path)
    with pytest.raises(UserError, match="cannot read"):
        load_vocabulary(tmp_path / "missing.yaml")


# --- manifests ---------------------------------------------------------------------------------------------------


def _manifest_folder(tmp_path: Path, text: str) -> Path:
    folder = write_tiny_closed_set(tmp_path / "models", {0: 0.3})
    (folder / "models.yaml").write_text(text)
    return folder


GOOD = """front_end: closed_set
detector: {file: detector/ssd.onnx, labels: detector/coco_labels.txt}
segmenter: {encoder: sam/tiny_encoder.onnx, decoder: sam/tiny_decoder.onnx}
classifier: {file: classifier/tiny_classifier.onnx}
proposals: {grid: [3, 2]}
"""


def test_manifest_read_and_inferred(tmp_path, tiny_folder):
    manifest = read_manifest(_manifest_folder(tmp_path, GOOD))
    assert manifest.front_end == "closed_set" and manifest.source is not None and manifest.threads == 2
    assert manifest.proposals == ProposalConfig(grid=(3, 2)) and manifest.detector.kind is None  # type: ignore[union-attr]
    inferred = read_manifest(tiny_folder)
    assert inferred.source is None and inferred.detector.file.name == "ssd.onnx"  # type: ignore[union-attr]
    assert inferred.proposals == ProposalConfig() and inferred.classifier is not None
    # the grounded_sam layout (no models.yaml) stays FoundationModels
    grounded = om.write_models_folder(
        tmp_path / "grounded", ["chair"], [1.0], None, np.zeros((1, len(om.VOCAB))), np.zeros((1, 4))
    )
    assert read_manifest(grounded).front_end == "grounded_sam"
    assert isinstance(load_front_end(grounded, overrides={"threads": 1, "proposals": None}), FoundationModels)
    # settings of a model the folder lacks are ignored; an override naming files adds the model
    assert merge({"classifier": None}, {"classifier": {"classify_boxes": False}}) == {"classifier": None}
    assert merge({"classifier": None}, {"classifier": {"file": "c.onnx"}, "proposals": {}}) == {
        "classifier": {"file": "c.onnx"},
        "proposals": {},
    }
    off = read_manifest(tiny_folder, {"classifier": None, "proposals": None, "threads": 1})
    assert off.classifier is None and off.proposals is None and off.threads == 1


@pytest.mark.parametrize(
    "edit, message",
    [
        (("detector/ssd.onnx", "detector/missing.onnx"), "detector file 'detector/missing.onnx'.*not found"),
        (("front_end: closed_set", "front_end: open_set"), "front_end 'open_set': expected one of"),
        (("labels: detector/coco_labels.txt}", "labels: detector/coco_labels.txt, kind: yolo}"), "detector kind 'yolo'"),
        (("labels: detector/coco_labels.txt}", "labels: detector/coco_labels.txt, score_threshold: 1.5}"), "score_threshold 1.5"),
        (("proposals: {grid: [3, 2]}", "proposals: {grid: [3, 2], min_stability: 2}"), "min_stability 2"),
        (("proposals: {grid: [3, 2]}", "proposals: {grid: [3, 2], colour: red}"), "unknown proposals key"),
        (("front_end: closed_set", "front_end: closed_set\ntagger: ram.onnx"), r"unknown key\(s\) \['tagger'\]"),
        (("segmenter: {encoder: sam/tiny_encoder.onnx, ", "segmenter: {"), "segmenter encoder must name a file"),
        (("classifier: {file: classifier/tiny_classifier.onnx}", "classifier: null"), "proposals need a classifier"),
    ],
)
def test_manifest_errors_name_the_file_and_the_problem(tmp_path, edit, message):
    folder = _manifest_folder(tmp_path, GOOD.replace(*edit))
    with pytest.raises(UserError, match=message) as error:
        load_front_end(folder)
    assert str(folder / "models.yaml") in str(error.value)


def test_manifest_wrong_tensor_names_and_empty_folders(tmp_path):
    folder = _manifest_folder(tmp_path, GOOD.replace("file: detector/ssd.onnx", "file: sam/tiny_encoder.onnx"))
    with pytest.raises(ContractError, match="neither NanoDet's") as error:
        load_front_end(folder)
    assert "models.yaml: detector:" in str(error.value)
    (folder / "models.yaml").write_text(GOOD.replace("labels: detector/coco_labels.txt}", "kind: nanodet}"))
    with pytest.raises(ContractError, match="NanoDet COCO detector contract"):
        load_front_end(folder)
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="neither a grounded_sam folder .* nor the closed-set layout"):
        load_front_end(tmp_path / "empty")
    with pytest.raises(UserError, match="models folder not found"):
        load_front_end(tmp_path / "nowhere")


def test_check_reports_problems_of_a_broken_folder(tmp_path, tiny_folder):
    broken = _manifest_folder(tmp_path, GOOD.replace("classifier/tiny_classifier.onnx", "classifier/gone.onnx"))
    result = check_models_folder(broken)
    assert not result.ok and "classifier file 'classifier/gone.onnx'" in result.problems[0]
    assert "problem(s)" in result.report()
    good = check_models_folder(tiny_folder, image=np.full((48, 64, 3), 90, np.uint8))
    assert good.ok, good.problems
    assert set(good.timings_ms) == {"generated 640x480 image", "the given image"}
    assert {"detector", "sam_encoder", "sam_decoder", "classifier", "total"} <= set(good.timings_ms["the given image"])
    unreadable = check_models_folder(tiny_folder, image=tmp_path / "missing.jpg")
    assert any("cannot read this image" in p for p in unreadable.problems)


def test_models_check_command(tmp_path, tiny_folder, capsys, monkeypatch):
    monkeypatch.setattr(cli, "SUBCOMMANDS", ("models",))
    assert cli.main(["models", "check", str(tiny_folder)]) == 0
    assert "ok: the folder is usable" in capsys.readouterr().out
    broken = _manifest_folder(tmp_path, GOOD.replace("front_end: closed_set", "front_end: clever"))
    assert cli.main(["models", "check", str(broken)]) == 1
    assert "front_end 'clever'" in capsys.readouterr().out


# --- the real models on real ScanNet frames ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def shared_models() -> Path:
    if not (SHARED_MODELS / "sam" / "mobile_sam_encoder.onnx").is_file():
        pytest.skip(f"shared pretrained models not found at {SHARED_MODELS} (never part of the repo; set FMFUSION_MODELS_DIR)")
    return SHARED_MODELS


@pytest.fixture(scope="module")
def frames(scannet_root) -> dict[int, np.ndarray]:
    color = scannet_root / "scene0000_00" / "color"
    return {i: np.ascontiguousarray(cv2.imread(str(color / f"frame-{i:06d}.jpg"))[:, :, ::-1]) for i in (20, 100, 200)}


@pytest.fixture(scope="module")
def real_detections(shared_models, frames):
    models = load_front_end(shared_models)
    assert isinstance(models, ClosedSetModels) and models.detector.kind == "ssd"  # SSD preferred over NanoDet
    return models, {i: models.detect(image, f"frame-{i:06d}") for i, image in frames.items()}


def test_real_frames_give_valid_detections(real_detections, frames):
    models, results = real_detections
    assert models.frames == 3 and models.timings["sam_encoder"] > 0
    for i, found in results.items():
        height, width = frames[i].shape[:2]
        assert found.num_detections > 0 and found.masks.shape == (found.num_detections, height, width)
        assert np.all(found.boxes[:, :2] >= 0) and np.all(found.boxes[:, 2] <= width) and np.all(found.boxes[:, 3] <= height)
        assert np.all(found.boxes[:, 2:] > found.boxes[:, :2])
        for mask, box, labels in zip(found.masks, found.boxes, found.labels):
            u0, v0, u1, v1 = np.round(box).astype(int)
            assert mask.sum() > 0 and mask[v0 : v1 + 1, u0 : u1 + 1].sum() >= 0.9 * mask.sum(), (i, labels, box)
            assert labels and set(labels) <= OPEN_LABELS and all(0 < s <= 1 for s in labels.values())
        assert found.tags == found.prompt and set(found.tags) == {k for d in found.labels for k in d}


def test_real_frames_find_the_expected_objects(real_detections):
    _, results = real_detections
    best = {i: {k: max((d.get(k, 0.0) for d in found.labels), default=0.0) for k in OPEN_LABELS} for i, found in results.items()}
    assert best[20]["bed"] > 0.5  # frame 20: a bed (SSD 0.88)
    assert best[100]["couch"] > 0.5  # frame 100: a blue couch (SSD 0.73)
    assert best[200]["toilet bowl"] > 0.8  # frame 200: a toilet (SSD 0.97)
    assert "toilet" in results[200].raw_tags and "couch" in results[100].raw_tags


def test_real_sam_box_masks_match_a_direct_decoder_call(real_detections, frames):
    """The decoder's prompt batch is fixed to 1: Segmenter goes box by box; its masks equal a direct call."""
    models, results = real_detections
    segmenter = models.segmenter
    assert segmenter.fixed_batch == 1 and segmenter.num_points is None
    embedding = segmenter.embed(frames[100])
    box = results[100].boxes[0]
    scale = 1024 / 640
    masks, iou, _ = segmenter.decoder.session.run(
        None,
        {
            "image_embeddings": embedding.embedding,
            "point_coords": (box.reshape(1, 2, 2) * scale).astype(np.float32),
            "point_labels": np.array([[2, 3]], np.float32),
            "mask_input": np.zeros((1, 1, 256, 256), np.float32),
            "has_mask_input": np.zeros(1, np.float32),
            "orig_im_size": np.array([480, 640], np.float32),
        },
    )
    ours, quality = segmenter.segment(embedding, results[100].boxes[:1])
    assert mask_iou(ours[0], masks[0, 0] > 0) == 1.0 and quality[0] == pytest.approx(float(iou[0, 0]))
    np.testing.assert_array_equal(ours[0], results[100].masks[0])


def test_real_nanodet_finds_the_toilet(shared_models, frames):
    detector = CocoDetector.from_files(
        shared_models / "detector" / "nanodet_g_coco.onnx", shared_models / "detector" / "coco_labels.txt"
    )
    assert detector.kind == "nanodet" and detector.score_threshold == 0.35  # the kind from the file's inputs
    found = detector(frames[200])
    assert found.names[0] == "toilet" and found.scores[0] > 0.6
    np.testing.assert_allclose(found.boxes[0], [358, 125, 529, 331], atol=3)


def test_real_models_folder_checks_out(shared_models):
    result = check_models_folder(shared_models)
    assert result.ok, result.report()
    assert result.timings_ms["generated 640x480 image"]["sam_encoder"] > 0
