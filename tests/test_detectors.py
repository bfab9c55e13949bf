"""The ONNX front end (`detectors`): preprocessing, tokens, boxes, masks, prompts, contracts, files, CLI.

The models are the tiny stand-ins of `onnx_models.py` (real signatures, predictable outputs): no weights of
RAM, GroundingDINO or SAM exist here.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("onnx")

import onnx_models as om  # noqa: E402

import fmfusion_jax.cli as cli  # noqa: E402
from detectors import (  # noqa: E402
    CONTRACTS,
    GROUNDING,
    SAM_ENCODER,
    TAGGER,
    ContractError,
    DetectorConfig,
    FoundationModels,
    GroundingDetector,
    ImageTagger,
    ModelNotFoundError,
    OnnxModel,
    PromptAugmenter,
    Segmenter,
    WordPieceTokenizer,
    box_prompts,
    build_caption,
    cxcywh_to_xyxy,
    grounding_input_size,
    label_scores,
    nms,
    postprocess_grounding,
    preprocess_grounding,
    preprocess_sam,
    preprocess_tagger,
    resolve_providers,
    sam_resized_shape,
    text_self_attention,
    upsample_low_res,
)
from detectors.contracts import markdown_table  # noqa: E402
from detectors.tokenizer import basic_tokenize  # noqa: E402
from fmfusion_jax.errors import UserError  # noqa: E402
from fmfusion_jax.io.detections import DetectionFolder, read_frame_detections, write_frame_detections  # noqa: E402
from fmfusion_jax.labels import load_label_sets  # noqa: E402
from fmfusion_jax.types import CameraIntrinsics, RGBDFrame  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
MEAN = np.array([0.485, 0.456, 0.406], np.float32)
STD = np.array([0.229, 0.224, 0.225], np.float32)
WIDTH, HEIGHT = 64, 48  # 1024 / 64 = 16 exactly: SAM's resized frame is 1024 x 768
BRIGHT, DARK = 200, 40

# Tagger: chair, room, floor always on; table on bright images, door on dark ones; armchair, white never.
TAGS = ["chair", "armchair", "room", "table", "floor", "white", "door"]
TAG_BIAS = [3.0, -3.0, 3.0, 0.0, 3.0, -3.0, 0.0]
TAG_WEIGHT = [0.0, 0.0, 0.0, 2.0, 0.0, 0.0, -2.0]

# Detector queries: pixel box and the words the query responds to (logit).
QUERIES = [
    ([8, 8, 24, 32], {"chair": 2.0}),  # chair, p 0.881
    ([32, 8, 56, 24], {"table": 1.5}),  # table, p 0.818
    ([0, 36, 64, 48], {"floor": 1.0}),  # floor strip: full width but not full height -> kept, p 0.731
    ([9, 8, 25, 32], {"chair": 1.0}),  # duplicate chair, lower score -> removed by NMS
    ([0, 0, 64, 48], {"floor": 3.0}),  # the whole image -> dropped (> 0.95 in width and height)
    ([36, 26, 60, 35], {"door": 1.2}),  # door, p 0.769
]


def normalized_boxes(pixel_boxes, width=WIDTH, height=HEIGHT) -> np.ndarray:
    boxes = np.asarray(pixel_boxes, np.float64)
    return np.stack(
        [
            (boxes[:, 0] + boxes[:, 2]) / 2 / width,
            (boxes[:, 1] + boxes[:, 3]) / 2 / height,
            (boxes[:, 2] - boxes[:, 0]) / width,
            (boxes[:, 3] - boxes[:, 1]) / height,
        ],
        1,
    ).astype(np.float32)


def sigmoid(x):
    return float(1 / (1 + np.exp(-x)))


def constant_image(value: int, height=HEIGHT, width=WIDTH) -> np.ndarray:
    return np.full((height, width, 3), value, np.uint8)


@pytest.fixture(scope="module")
def models_dir(tmp_path_factory) -> Path:
    table = om.token_logit_table({q: likes for q, (_, likes) in enumerate(QUERIES)}, len(QUERIES))
    boxes = normalized_boxes([box for box, _ in QUERIES])
    return om.write_models_folder(tmp_path_factory.mktemp("models"), TAGS, TAG_BIAS, TAG_WEIGHT, table, boxes)


@pytest.fixture(scope="module")
def models(models_dir) -> FoundationModels:
    return FoundationModels.from_folder(models_dir)


@pytest.fixture(scope="module")
def tokenizer() -> WordPieceTokenizer:
    return WordPieceTokenizer(om.VOCAB)


# --- preprocessing ---------------------------------------------------------------------------------------


def test_tagger_preprocessing_resizes_to_384_and_normalizes():
    image = np.zeros((48, 64, 3), np.uint8)
    image[:, :32] = (255, 0, 10)
    image[:, 32:] = (0, 128, 255)
    batch = preprocess_tagger(image)
    assert batch.shape == (1, 3, 384, 384) and batch.dtype == np.float32
    left = (np.array([255, 0, 10]) / 255 - MEAN) / STD
    right = (np.array([0, 128, 255]) / 255 - MEAN) / STD
    np.testing.assert_allclose(batch[0, :, :, :189].reshape(3, -1).T, np.tile(left, (384 * 189, 1)), atol=1e-5)
    np.testing.assert_allclose(batch[0, :, :, 195:].reshape(3, -1).T, np.tile(right, (384 * 189, 1)), atol=1e-5)
    with pytest.raises(ValueError, match="uint8"):
        preprocess_tagger(image.astype(np.float32))


def test_grounding_input_size_and_normalization():
    assert grounding_input_size(480, 640) == (800, 1066)  # ScanNet: shorter side 800
    assert grounding_input_size(640, 480) == (1066, 800)  # portrait
    assert grounding_input_size(500, 500) == (800, 800)
    assert grounding_input_size(1000, 3000) == (444, 1332)  # longer side capped: 1333 * 1000 / 3000 -> 444
    assert grounding_input_size(1000, 3000, longest=0) == (800, 2400)
    batch = preprocess_grounding(constant_image(BRIGHT), 800, 1066)
    assert batch.shape == (1, 3, 800, 1066)
    np.testing.assert_allclose(batch[0, :, 400, 500], (BRIGHT / 255 - MEAN) / STD, atol=1e-5)


def test_sam_preprocessing_resizes_the_longest_side_and_pads_with_zeros():
    assert sam_resized_shape(480, 640) == (768, 1024)
    assert sam_resized_shape(480, 641) == (767, 1024)  # int(480 * 1024 / 641 + 0.5)
    assert sam_resized_shape(1000, 10) == (1024, 10)
    batch, resized = preprocess_sam(constant_image(BRIGHT))
    assert resized == (768, 1024) and batch.shape == (1, 3, 1024, 1024)
    expected = (BRIGHT - 255 * MEAN) / (255 * STD)
    np.testing.assert_allclose(batch[0, :, :768, :].reshape(3, -1).min(axis=1), expected, atol=1e-4)
    np.testing.assert_allclose(batch[0, :, :768, :].reshape(3, -1).max(axis=1), expected, atol=1e-4)
    assert not batch[0, :, 768:, :].any()
    coords, labels = box_prompts(np.array([[8, 8, 24, 32]]), (48, 64), (768, 1024))
    np.testing.assert_allclose(coords, [[[128, 128], [384, 512]]])
    np.testing.assert_array_equal(labels, [[2, 3]])


# --- boxes -----------------------------------------------------------------------------------------------


def test_cxcywh_to_pixel_boxes_is_clipped_to_the_image():
    boxes = cxcywh_to_xyxy([[0.5, 0.5, 0.5, 0.5], [0.0, 0.0, 0.2, 0.2], [1.0, 1.0, 0.5, 0.5]], 640, 480)
    np.testing.assert_allclose(boxes, [[160, 120, 480, 360], [0, 0, 64, 48], [480, 360, 640, 480]])
    assert boxes.dtype == np.float32


def test_nms_keeps_the_best_of_overlapping_boxes():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [20, 20, 30, 30], [0, 0, 10, 10]], np.float32)
    scores = np.array([0.9, 0.8, 0.7, 0.95])
    np.testing.assert_array_equal(nms(boxes, scores, 0.5), [3, 2])  # IoU(3, 1) = 81/119 = 0.68
    np.testing.assert_array_equal(nms(boxes, scores, 0.7), [3, 1, 2])
    np.testing.assert_array_equal(nms(boxes[:2], np.array([0.5, 0.5]), 0.5), [0])  # tie: lower index
    assert nms(np.zeros((0, 4)), np.zeros(0)).shape == (0,)


# --- text ------------------------------------------------------------------------------------------------


def test_basic_and_wordpiece_tokenization(tokenizer):
    assert basic_tokenize("Hello, Wörld!  naïve\tCHAIR\x00") == ["hello", ",", "world", "!", "naive", "chair"]
    assert tokenizer.tokenize("Armchairs bookshelf xyz") == ["arm", "##chair", "##s", "book", "##shelf", "[UNK]"]
    assert tokenizer.encode("chair.") == [2, 19, 5, 3]


def test_caption_token_spans_and_grounding_text_masks(tokenizer):
    caption = build_caption(["chair", "armchair", "table", "chair", "Side  Table"], tokenizer)
    assert caption.text == "chair . armchair . table . side table ."
    assert caption.labels == ("chair", "armchair", "table", "side table")
    assert caption.tokens == ("[CLS]", "chair", ".", "arm", "##chair", ".", "table", ".", "side", "table", ".", "[SEP]")
    assert caption.spans == ((1, 2), (3, 5), (6, 7), (8, 10))
    breaks = [tokenizer.ids[t] for t in ("[CLS]", "[SEP]", ".", "?")]
    padded = np.concatenate([caption.input_ids, np.zeros(3, np.int64)])  # 3 [PAD]
    mask, positions = text_self_attention(padded, breaks)
    np.testing.assert_array_equal(positions, [0, 0, 1, 0, 1, 2, 0, 1, 0, 1, 2, 0, 0, 0, 0])
    expected = np.zeros((15, 15), bool)
    for start, stop in ((0, 1), (1, 3), (3, 6), (6, 8), (8, 11), (11, 12), (12, 13), (13, 14), (14, 15)):
        expected[start:stop, start:stop] = True
    np.testing.assert_array_equal(mask, expected)
    short = build_caption(["chair", "armchair", "table", "side table"], tokenizer, max_tokens=8)
    assert short.labels == ("chair", "armchair") and short.dropped == ("table", "side table")
    assert short.num_tokens == 7


def test_label_scores_need_every_token_over_the_text_threshold(tokenizer):
    caption = build_caption(["chair", "armchair"], tokenizer)  # [CLS] chair . arm ##chair . [SEP]
    probs = np.array([[0.1, 0.9, 0.1, 0.6, 0.3, 0.1, 0.1], [0.1, 0.2, 0.1, 0.8, 0.2, 0.1, 0.1]], np.float32)
    assert label_scores(probs, caption, 0.25) == [{"chair": pytest.approx(0.9), "armchair": pytest.approx(0.6)}, {}]
    assert label_scores(probs, caption, 0.15) == [
        {"chair": pytest.approx(0.9), "armchair": pytest.approx(0.6)},
        {"chair": pytest.approx(0.2), "armchair": pytest.approx(0.8)},
    ]


def test_grounding_postprocessing_thresholds_filters_and_nms(tokenizer):
    caption = build_caption(["chair", "armchair"], tokenizer)

    def row(chair, arm, piece, dot=0.05):
        return [np.log(p / (1 - p)) for p in (0.01, chair, dot, arm, piece, dot, 0.01)] + [-30.0] * 3

    logits = np.array(
        [
            row(0.9, 0.6, 0.3),  # chair 0.9 + armchair 0.6
            row(0.3, 0.5, 0.2),  # box score 0.5; chair passes (0.3), armchair fails (0.2 < 0.25)
            row(0.3, 0.3, 0.3),  # box score 0.3 < 0.35: not a detection
            row(0.8, 0.1, 0.1),  # whole image: dropped
            row(0.85, 0.1, 0.1),  # overlaps the first box: suppressed
            row(0.1, 0.1, 0.1, dot=0.7),  # only a '.' scores: no label -> dropped
        ],
        np.float32,
    )
    boxes = normalized_boxes([[8, 8, 24, 32], [30, 30, 50, 40], [0, 0, 5, 5], [0, 0, 64, 48], [9, 8, 25, 32], [40, 0, 60, 10]])
    result = postprocess_grounding(logits, boxes, caption, HEIGHT, WIDTH)
    assert result.labels == [{"chair": pytest.approx(0.9), "armchair": pytest.approx(0.6)}, {"chair": pytest.approx(0.3)}]
    np.testing.assert_allclose(result.scores, [0.9, 0.5], atol=1e-6)
    np.testing.assert_allclose(result.boxes, [[8, 8, 24, 32], [30, 30, 50, 40]], atol=1e-4)
    loose = postprocess_grounding(logits, boxes, caption, HEIGHT, WIDTH, max_box_fraction=1.0, nms_iou=0.95)
    assert len(loose.labels) == 4


# --- masks -----------------------------------------------------------------------------------------------


def test_low_res_masks_are_taken_back_to_the_frame():
    box = [8, 8, 24, 32]  # pixels [u0, v0, u1, v1]; in the 1024 frame u 128..384, v 128..512
    centres = (np.arange(256) + 0.5) * 4
    inside = ((centres[:, None] >= 128) & (centres[:, None] <= 512)) & ((centres[None] >= 128) & (centres[None] <= 384))
    low = np.where(inside, 10.0, -10.0).astype(np.float32)[None]
    logits = upsample_low_res(low, (HEIGHT, WIDTH), (768, 1024))
    assert logits.shape == (1, HEIGHT, WIDTH)
    np.testing.assert_array_equal(logits[0] > 0, om.box_mask(box, HEIGHT, WIDTH))


@pytest.mark.parametrize(
    "variant",
    ["single", "batched-first", "batched-best", "low-res", "orig-size-low-res", "masks-wrong-size", "fixed-2-prompts-3-points"],
)
def test_segmenter_decoder_variants(tmp_path, variant):
    om.save(om.sam_encoder_model(input_name="input_image"), tmp_path / "sam_encoder.onnx")  # samexporter's name
    decoder = {
        "single": om.sam_decoder_model(),
        "batched-first": om.sam_decoder_model(batched=True, num_masks=4),
        "batched-best": om.sam_decoder_model(batched=True, num_masks=4),
        "low-res": om.sam_decoder_model(orig_size=False),
        "orig-size-low-res": om.sam_decoder_model(full_masks=False),
        "masks-wrong-size": om.sam_decoder_model(masks_at_low_res=True),
        "fixed-2-prompts-3-points": om.sam_decoder_model(fixed_prompts=2, fixed_points=3),
    }[variant]
    om.save(decoder, tmp_path / "sam_decoder.onnx")
    segmenter = Segmenter.from_folder(tmp_path, mask_choice="best" if variant == "batched-best" else "first", batch_size=2)
    assert segmenter.fixed_batch == (None if variant.startswith("batched") else 2 if variant.startswith("fixed") else 1)
    boxes = np.array([[8, 8, 24, 32], [32, 8, 56, 24], [0, 36, 64, 48]], np.float32)
    masks, quality = segmenter(constant_image(BRIGHT), boxes)
    expected = np.stack([om.box_mask(box, HEIGHT, WIDTH) for box in boxes])
    assert masks.shape == (3, HEIGHT, WIDTH) and masks.dtype == bool
    if variant == "batched-best":
        np.testing.assert_array_equal(masks, ~expected)  # the complements claim a higher IoU
        np.testing.assert_allclose(quality, 2.0)
    else:
        np.testing.assert_array_equal(masks, expected)
        # The decoder's "IoU" is the embedding mean: 3/4 of the padded square is the normalized image.
        image_mean = np.mean((BRIGHT - 255 * MEAN) / (255 * STD))
        np.testing.assert_allclose(quality, 0.75 * image_mean, atol=2e-3)
    empty_masks, empty_quality = segmenter(constant_image(BRIGHT), np.zeros((0, 4)))
    assert empty_masks.shape == (0, HEIGHT, WIDTH) and empty_quality.shape == (0,)


# --- prompt augmentation ---------------------------------------------------------------------------------


def test_prompt_augmentation_window_exclusions_and_reset():
    labels = load_label_sets()
    augmenter = PromptAugmenter(window=5, excluded=labels.prompt_augmentation_excluded, open_labels=labels.open_labels)
    assert augmenter.prompt("f0", ["chair"]) == ["chair"]
    augmenter.observe(["chair", "table", "floor", "door"])
    # floor is tagged this frame: it stays, although augmentation would never add it.
    assert augmenter.prompt("f1", ["floor"]) == ["floor", "chair", "table"]
    augmenter.observe(["sink"])
    assert augmenter.prompt("f2", []) == ["chair", "table", "sink"]  # door, floor excluded; L_o order
    augmenter.observe([])
    for name in ("f3", "f4", "f5"):
        assert augmenter.prompt(name, ["bed"]) == ["bed", "chair", "table", "sink"]
        augmenter.observe([])
    assert augmenter.prompt("f6", []) == ["sink"]  # f0's labels are 6 frames old: expired
    # f6 is never observed: it counts as a frame without detections.
    for name in ("f7", "f8", "f9", "f10"):
        augmenter.prompt(name, [])
    assert augmenter.prompt("f11", []) == []
    record = augmenter.history[1]
    assert (record.frame_name, record.tags, record.added, record.prompt) == (
        "f1",
        ("floor",),
        ("chair", "table"),
        ("floor", "chair", "table"),
    )
    assert len(augmenter.history) == 12
    augmenter.reset()
    assert augmenter.history == [] and augmenter.candidates() == []

    off = PromptAugmenter(window=0)
    off.prompt("a", ["chair"])
    off.observe(["table"])
    assert off.prompt("b", ["bed"]) == ["bed"]


# --- contracts and files ---------------------------------------------------------------------------------


def test_contract_mismatch_lists_expected_and_found(tmp_path):
    table = om.token_logit_table({0: {"chair": 1.0}}, 1)
    path = om.save(
        om.grounding_model(
            table,
            normalized_boxes([[0, 0, 8, 8]]),
            image_name="pixel_values",
            logits_name="scores",
            drop_inputs=("position_ids",),
        ),
        tmp_path / "g.onnx",
    )
    with pytest.raises(ContractError) as raised:
        OnnxModel(path, GROUNDING)
    message = str(raised.value)
    for text in (
        "does not match the GroundingDINO open-set detector contract",
        "input 'img' missing",
        "input 'position_ids' missing",
        "input 'pixel_values' is not one the front end can feed",
        "output 'logits' missing",
        "expected inputs:",
        "img (or samples, images, image) [1, 3, height, width]",
        "found inputs:",
        "pixel_values [1, 3, height, width] float32",
        "found outputs:",
        "scores [1, 1, num_tokens] float32",
        "docs/detectors.md",
    ):
        assert text in message, f"{text!r} not in:\n{message}"
    assert isinstance(raised.value, UserError)

    wrong = om.save(om.tagger_model([0.0, 1.0], size=224, input_type=om.INT64), tmp_path / "ram.onnx")
    with pytest.raises(ContractError) as raised:
        OnnxModel(wrong, TAGGER)
    assert "input 'image' has element type int64, expected float32 or float16" in str(raised.value)
    assert "input 'image' has size 224 on axis 2, expected 384" in str(raised.value)

    decoder = om.save(om.sam_decoder_model(), tmp_path / "dec.onnx")
    with pytest.raises(ContractError, match="none of the outputs|output 'image_embeddings' missing"):
        OnnxModel(decoder, SAM_ENCODER)


def test_public_export_names_and_fixed_sizes_are_accepted(tmp_path, tokenizer):
    """Aliases (samples, pred_logits), int64 attention mask, fixed 256 tokens and a fixed 800x800 image."""
    table = om.token_logit_table({0: {"chair": 2.0}}, 1)
    path = om.save(
        om.grounding_model(
            table,
            normalized_boxes([[8, 8, 24, 32]]),
            num_tokens=256,
            image_size=(800, 800),
            image_name="samples",
            logits_name="pred_logits",
            attention_type=om.INT64,
        ),
        tmp_path / "groundingdino.onnx",
    )
    detector = GroundingDetector(OnnxModel(path, GROUNDING), tokenizer)
    assert detector.fixed_tokens == 256 and detector.fixed_size == (800, 800)
    feeds, caption = detector.prepare(constant_image(BRIGHT), ["chair", "table"])
    assert feeds["img"].shape == (1, 3, 800, 800) and feeds["input_ids"].shape == (1, 256)
    assert feeds["attention_mask"].sum() == caption.num_tokens == 6
    assert feeds["text_token_mask"].shape == (1, 256, 256)
    echoed = detector.model.session.run(
        ["echo_input_ids", "echo_img_shape"],
        {detector.model.inputs[k].name: v.astype(detector.model.inputs[k].numpy_dtype) for k, v in feeds.items()},
    )
    np.testing.assert_array_equal(echoed[0], feeds["input_ids"])
    np.testing.assert_array_equal(echoed[1], [1, 3, 800, 800])
    result = detector(constant_image(BRIGHT), ["chair", "table"])
    assert result.labels == [{"chair": pytest.approx(sigmoid(2.0))}]
    np.testing.assert_allclose(result.boxes, [[8, 8, 24, 32]], atol=1e-4)  # in the frame's pixels, not 800x800


def test_missing_files_are_named_with_how_to_make_them(tmp_path, models_dir):
    with pytest.raises(UserError, match="models folder not found"):
        FoundationModels.from_folder(tmp_path / "nowhere")
    partial = tmp_path / "partial"
    partial.mkdir()
    for file in models_dir.iterdir():
        if file.name != "sam_decoder.onnx":
            (partial / file.name).write_bytes(file.read_bytes())
    with pytest.raises(ModelNotFoundError) as raised:
        FoundationModels.from_folder(partial)
    message = str(raised.value)
    assert str(partial / "sam_decoder.onnx") in message and "export_onnx_model.py" in message
    assert "docs/detectors.md" in message
    (partial / "vocab.txt").unlink()
    with pytest.raises(ModelNotFoundError, match=r"vocab\.txt.*bert-base-uncased"):
        GroundingDetector.from_folder(partial)
    (partial / "ram.onnx").write_bytes(b"not a model")
    with pytest.raises(UserError, match="onnxruntime cannot load"):
        ImageTagger.from_folder(partial)


def test_tagger_outputs_thresholds_and_vocabulary(tmp_path):
    om.write_lines(tmp_path / "ram_tag_list.txt", TAGS)
    om.save(om.tagger_model(TAG_BIAS, TAG_WEIGHT), tmp_path / "ram.onnx")
    tagger = ImageTagger.from_folder(tmp_path)
    open_labels = load_label_sets().open_labels
    bright, dark = tagger(constant_image(BRIGHT), open_labels), tagger(constant_image(DARK), open_labels)
    assert bright.raw_tags == ["chair", "room", "table", "floor"] and bright.tags == ["chair", "table", "floor"]
    assert dark.raw_tags == ["chair", "room", "floor", "door"] and dark.tags == ["chair", "floor", "door"]
    assert bright.raw_scores[0] == pytest.approx(sigmoid(3.0), abs=1e-6)
    # RAM's per-class thresholds beside the model: room needs 0.99 now.
    om.write_lines(tmp_path / "ram_tag_list_threshold.txt", ["0.68", "0.68", "0.99", "0.68", "0.68", "0.68", "0.68"])
    strict = ImageTagger.from_folder(tmp_path)(constant_image(BRIGHT), open_labels)
    assert strict.raw_tags == ["chair", "table", "floor"]
    # An export that thresholds inside (X-AnyLabeling's img -> targets) is taken as it is.
    om.save(om.tagger_model([1, 0, 1, 0, 0, 0, 1], output="targets", input_name="img"), tmp_path / "ram.onnx")
    assert ImageTagger.from_folder(tmp_path)(constant_image(BRIGHT), open_labels).raw_tags == ["chair", "room", "door"]
    om.write_lines(tmp_path / "ram_tag_list.txt", TAGS[:3])
    with pytest.raises(ContractError, match="scores 7 tags but its vocabulary"):
        ImageTagger.from_folder(tmp_path)


def test_providers():
    assert resolve_providers("cpu") == ["CPUExecutionProvider"]
    assert resolve_providers("auto")[-1] == "CPUExecutionProvider"
    with pytest.raises(UserError, match="expected 'cpu', 'cuda', 'auto'"):
        resolve_providers("gpu")
    with pytest.raises(UserError, match="not available"):
        resolve_providers(["NoSuchExecutionProvider"])
    import onnxruntime

    cuda = resolve_providers("cuda")
    if "CUDAExecutionProvider" in onnxruntime.get_available_providers():
        assert cuda == ["CUDAExecutionProvider", "CPUExecutionProvider"]
    else:
        assert cuda == ["CPUExecutionProvider"]


def test_docs_hold_every_contract_table():
    text = (REPO / "docs" / "detectors.md").read_text()
    for contract in CONTRACTS:
        assert markdown_table(contract) in text, f"docs/detectors.md: the {contract.key} table is out of date"
        assert contract.filename in text


# --- the whole front end -----------------------------------------------------------------------------------


def test_detect_end_to_end_and_the_files_read_back_identically(models, tmp_path):
    models.reset()
    frame = RGBDFrame(
        index=0,
        name="frame-000000",
        color=constant_image(BRIGHT),
        depth=np.ones((HEIGHT, WIDTH), np.float32),
        T_world_camera=np.eye(4),
        intrinsics=CameraIntrinsics(50, 50, 32, 24, WIDTH, HEIGHT),
    )
    detections = models.detect(frame)
    assert detections.frame_name == "frame-000000"
    assert detections.raw_tags == ["chair", "room", "table", "floor"]
    assert detections.tags == ["chair", "table", "floor"] and detections.prompt == ["chair", "table", "floor"]
    assert detections.labels == [
        {"chair": pytest.approx(sigmoid(2.0))},
        {"table": pytest.approx(sigmoid(1.5))},
        {"floor": pytest.approx(sigmoid(1.0))},
    ]
    np.testing.assert_allclose(detections.boxes, [QUERIES[0][0], QUERIES[1][0], QUERIES[2][0]], atol=1e-4)
    np.testing.assert_array_equal(detections.masks, np.stack([om.box_mask(QUERIES[i][0], HEIGHT, WIDTH) for i in range(3)]))
    assert all(seconds > 0 for seconds in models.timings.values())

    for mask_format in ("png", "npy"):
        folder = tmp_path / mask_format
        write_frame_detections(folder, detections, mask_format=mask_format)
        back = read_frame_detections(folder, "frame-000000", image_shape=(HEIGHT, WIDTH))
        np.testing.assert_array_equal(back.masks, detections.masks)
        np.testing.assert_array_equal(back.boxes, detections.boxes)
        assert back.labels == detections.labels
        assert (back.raw_tags, back.tags, back.prompt) == (detections.raw_tags, detections.tags, detections.prompt)

    # The next frame is dark: table is no longer tagged but the augmentation brings it back (floor is excluded
    # from augmentation but tagged); door is tagged and found.
    dark = models.detect(constant_image(DARK), "frame-000010")
    assert dark.tags == ["chair", "floor", "door"] and dark.prompt == ["chair", "floor", "door", "table"]
    assert [max(labels, key=labels.get) for labels in dark.labels] == ["chair", "table", "door", "floor"]
    assert models.prompts.history[-1].added == ("table",)
    models.reset()
    assert models.detect(constant_image(DARK), "x").prompt == ["chair", "floor", "door"]


def test_detect_on_an_image_without_labels_of_interest(tmp_path):
    table = om.token_logit_table({0: {"chair": 2.0}}, 1)
    folder = om.write_models_folder(
        tmp_path, ["room", "white"], [3.0, 3.0], None, table, normalized_boxes([[8, 8, 24, 32]]), batched_decoder=True
    )
    models = FoundationModels.from_folder(folder, config=DetectorConfig(prompt_window=0))
    detections = models.detect(constant_image(BRIGHT), "frame-000000")
    assert detections.raw_tags == ["room", "white"] and detections.tags == [] and detections.prompt == []
    assert detections.num_detections == 0 and detections.masks.shape == (0, HEIGHT, WIDTH)
    assert models.timings["sam_encoder"] == 0.0  # nothing to segment: the encoder did not run


def make_scene(root: Path, colours: list[int]) -> Path:
    """A ScanNet-layout scene: color/, depth/, pose/, intrinsic/intrinsic_depth.txt."""
    for folder in ("color", "depth", "pose", "intrinsic"):
        (root / folder).mkdir(parents=True, exist_ok=True)
    for i, value in enumerate(colours):
        cv2.imwrite(str(root / "color" / f"frame-{i:06d}.png"), constant_image(value))
        cv2.imwrite(str(root / "depth" / f"frame-{i:06d}.png"), np.full((HEIGHT, WIDTH), 1000, np.uint16))
        pose = np.eye(4)
        pose[0, 3] = 0.05 * i
        np.savetxt(root / "pose" / f"frame-{i:06d}.txt", pose)
    np.savetxt(
        root / "intrinsic" / "intrinsic_depth.txt",
        np.array([[50, 0, 32, 0], [0, 50, 24, 0], [0, 0, 1, 0], [0, 0, 0, 1]], np.float64),
    )
    return root


def test_cli_detect_writes_the_authors_format(tmp_path, models_dir, monkeypatch, capsys):
    monkeypatch.setattr(cli, "SUBCOMMANDS", ("detect",))
    scene = make_scene(tmp_path / "scene0000_00", [BRIGHT, BRIGHT, DARK, DARK, BRIGHT, BRIGHT])
    out = tmp_path / "prediction"
    code = cli.main(["detect", str(scene), "--models", str(models_dir), "--out", str(out), "--every", "2", "--no-progress"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "3 frames of scene0000_00" in captured.out and "-> 10 detections" in captured.out
    folder = DetectionFolder(out, image_shape=(HEIGHT, WIDTH))
    assert folder.frame_names == ["frame-000000", "frame-000002", "frame-000004"]
    first, second, third = (folder.get(name) for name in folder.frame_names)
    assert first.prompt == ["chair", "table", "floor"] and first.num_detections == 3
    assert second.tags == ["chair", "floor", "door"] and second.prompt == ["chair", "floor", "door", "table"]
    assert second.num_detections == 4
    assert third.prompt == ["chair", "table", "floor"]  # door is excluded from augmentation
    assert [max(labels, key=labels.get) for labels in third.labels] == ["chair", "table", "floor"]
    document = json.loads((out / "frame-000002_label.json").read_text())
    assert document["raw_tags"] == "chair. room. floor. door" and document["tags"] == "chair. floor. door. table"
    assert (out / "frame-000002_mask.png").is_file()
    np.testing.assert_array_equal(first.masks[0], om.box_mask(QUERIES[0][0], HEIGHT, WIDTH))

    code = cli.main(["detect", str(scene), "--models", str(tmp_path / "none"), "--out", str(out)])
    assert code == 2 and "fmfusion detect: error:" in capsys.readouterr().err


def test_cuda_request_falls_back_to_cpu_with_a_warning(caplog):
    import onnxruntime

    if "CUDAExecutionProvider" in onnxruntime.get_available_providers():
        pytest.skip("CUDA is available here")
    with caplog.at_level(logging.WARNING, logger="detectors.onnx_runtime"):
        assert resolve_providers("cuda") == ["CPUExecutionProvider"]
    assert "CUDAExecutionProvider is not available" in caplog.text


def test_cli_run_calls_the_front_end_online(tmp_path, models_dir, monkeypatch, capsys):
    """`fmfusion run --models` fuses the front end's detections without writing detection files."""
    monkeypatch.setattr(cli, "SUBCOMMANDS", ("run",))
    scene = make_scene(tmp_path / "scene0000_00", [BRIGHT, BRIGHT, DARK, BRIGHT])
    out = tmp_path / "map"
    code = cli.main(
        [
            "run",
            str(scene),
            "--models",
            str(models_dir),
            "--out",
            str(out),
            "--config",
            "scannet",
            "--set",
            "detections.every=1",
            "--set",
            "detections.min_mask_pixels=10",
            "--set",
            "tsdf.block_capacity=4000",
            "--set",
            "export.min_points=1",
            "--no-progress",
        ]
    )
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "4 frames, 4 with detections" in captured.out
    run = json.loads((out / "run.json").read_text())
    assert run["counters"]["detections"] > 0 and run["counters"]["created"] > 0
