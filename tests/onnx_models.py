"""Tiny ONNX stand-ins for RAM, GroundingDINO and SAM, built with `onnx.helper` (test-only dependency).

Each has the real export's input/output names, ranks and dtypes (sizes kept small where they are free)
and outputs the tests can predict:

- tagger: ``logits = bias + weight * mean(image)`` per tag (bright and dark images get different tags);
- detector: query q's logit for a token is ``token_logits[q, input_ids[t]]`` (a query "likes" words, so
  what it detects depends on the prompt, as with the real model); boxes are fixed per query;
- SAM encoder: 16x16 average pooling of the image, copied to 256 channels (``[1, 256, 64, 64]``);
- SAM decoder: the mask logits are +10 inside the prompt box, -10 outside, at `orig_im_size` (pixel
  centres mapped to the 1024 frame by 1024 / max(H, W)) and at 256x256 in the padded frame; the predicted
  IoU is the mean of the embedding (proof that the encoder output reached it).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17
FLOAT, INT64, BOOL = TensorProto.FLOAT, TensorProto.INT64, TensorProto.BOOL

#: A small BERT-like vocabulary: special tokens, punctuation, and the words of the open-set labels with a
#: few split into WordPieces (``armchair`` -> ``arm ##chair``, ``bookshelf`` -> ``book ##shelf``).
VOCAB = [
    "[PAD]",
    "[UNK]",
    "[CLS]",
    "[SEP]",
    "[MASK]",
    ".",
    ",",
    "!",
    "?",
    "-",
    "wall",
    "tile",
    "floor",
    "carpet",
    "cabinet",
    "closet",
    "file",
    "bed",
    "dresser",
    "chair",
    "arm",
    "##chair",
    "swivel",
    "couch",
    "table",
    "side",
    "round",
    "kitchen",
    "door",
    "glass",
    "window",
    "book",
    "##shelf",
    "shelf",
    "picture",
    "frame",
    "poster",
    "counter",
    "top",
    "computer",
    "desk",
    "office",
    "curtain",
    "fridge",
    "shower",
    "toilet",
    "bowl",
    "sink",
    "bathroom",
    "bath",
    "tub",
    "bin",
    "naive",
    "room",
    "##s",
]


def _model(nodes, inputs, outputs, initializers=()) -> onnx.ModelProto:
    graph = helper.make_graph(nodes, "tiny", inputs, outputs, initializer=list(initializers))
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="fmfusion-tests")
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model


def _const(name: str, value) -> onnx.TensorProto:
    return numpy_helper.from_array(np.asarray(value), name)


def save(model: onnx.ModelProto, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(path))
    return path


def write_lines(path: Path, lines: Sequence[str]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


# --- RAM ----------------------------------------------------------------------------------------------


def tagger_model(
    bias: Sequence[float],
    weight: Sequence[float] | None = None,
    output: str = "logits",
    input_name: str = "image",
    size: int = 384,
    input_type=FLOAT,
) -> onnx.ModelProto:
    """``output[0, k] = bias[k] + weight[k] * mean(image)``."""
    bias = np.asarray(bias, np.float32).reshape(1, -1)
    weight = np.zeros_like(bias) if weight is None else np.asarray(weight, np.float32).reshape(1, -1)
    nodes = [
        helper.make_node("Cast", [input_name], ["image_f"], to=FLOAT),
        helper.make_node("ReduceMean", ["image_f"], ["mean"], keepdims=0),
        helper.make_node("Mul", ["weight", "mean"], ["scaled"]),
        helper.make_node("Add", ["bias", "scaled"], [output]),
    ]
    return _model(
        nodes,
        [helper.make_tensor_value_info(input_name, input_type, [1, 3, size, size])],
        [helper.make_tensor_value_info(output, FLOAT, [1, bias.shape[1]])],
        [_const("bias", bias), _const("weight", weight)],
    )


# --- GroundingDINO ------------------------------------------------------------------------------------


def grounding_model(
    token_logits: np.ndarray,
    boxes: np.ndarray,
    num_tokens: int | str = "num_tokens",
    image_size: tuple[int, int] | None = None,
    image_name: str = "img",
    logits_name: str = "logits",
    attention_type=BOOL,
    drop_inputs: Sequence[str] = (),
    extra_inputs: Sequence[str] = (),
) -> onnx.ModelProto:
    """Detector whose logits are ``token_logits[q, input_ids[t]]`` and whose boxes are `boxes` `(Q, 4)`.

    Extra outputs echo what it was fed (``echo_img_shape``, ``echo_input_ids``, ``echo_position_ids``,
    ``echo_text_token_mask``, ``echo_attention_mask``).
    """
    token_logits = np.asarray(token_logits, np.float32)
    boxes = np.asarray(boxes, np.float32).reshape(1, -1, 4)
    queries = token_logits.shape[0]
    height, width = image_size or ("height", "width")
    tokens = [1, num_tokens]
    specs = {
        image_name: (FLOAT, [1, 3, height, width]),
        "input_ids": (INT64, tokens),
        "attention_mask": (attention_type, tokens),
        "position_ids": (INT64, tokens),
        "token_type_ids": (INT64, tokens),
        "text_token_mask": (BOOL, [1, num_tokens, num_tokens]),
    }
    inputs = [
        helper.make_tensor_value_info(name, kind, shape) for name, (kind, shape) in specs.items() if name not in drop_inputs
    ]
    inputs += [helper.make_tensor_value_info(name, FLOAT, [1]) for name in extra_inputs]
    nodes = [
        helper.make_node("Squeeze", ["input_ids", "axis0"], ["ids"]),
        helper.make_node("Gather", ["token_logits", "ids"], ["per_token"], axis=1),  # [Q, T]
        helper.make_node("Unsqueeze", ["per_token", "axis0"], [logits_name]),
        helper.make_node("Identity", ["boxes_value"], ["boxes"]),
        helper.make_node("Shape", [image_name], ["echo_img_shape"]),
        helper.make_node("Identity", ["input_ids"], ["echo_input_ids"]),
    ]
    outputs = [
        helper.make_tensor_value_info(logits_name, FLOAT, [1, queries, num_tokens]),
        helper.make_tensor_value_info("boxes", FLOAT, [1, queries, 4]),
        helper.make_tensor_value_info("echo_img_shape", INT64, [4]),
        helper.make_tensor_value_info("echo_input_ids", INT64, tokens),
    ]
    for name in ("position_ids", "text_token_mask", "attention_mask"):
        if name not in drop_inputs:
            nodes.append(helper.make_node("Identity", [name], [f"echo_{name}"]))
            outputs.append(helper.make_tensor_value_info(f"echo_{name}", specs[name][0], specs[name][1]))
    return _model(
        nodes,
        inputs,
        outputs,
        [_const("token_logits", token_logits), _const("boxes_value", boxes), _const("axis0", np.array([0], np.int64))],
    )


def token_logit_table(
    likes: dict[int, dict[str, float]], queries: int, vocab: Sequence[str] = VOCAB, default: float = -6.0
) -> np.ndarray:
    """`(queries, len(vocab))` logits: `default` everywhere, ``likes[q][token]`` where given."""
    table = np.full((queries, len(vocab)), default, np.float32)
    for query, tokens in likes.items():
        for token, logit in tokens.items():
            table[query, list(vocab).index(token)] = logit
    return table


def logit(p: float) -> float:
    return float(np.log(p / (1 - p)))


# --- SAM ------------------------------------------------------------------------------------------------


def sam_encoder_model(input_name: str = "image", size: int = 1024, channels: int = 256) -> onnx.ModelProto:
    """``[1, 3, size, size]`` -> 16x16 average pooling -> mean over colour, copied to `channels` channels."""
    weight = np.full((channels, 3, 1, 1), 1.0 / 3.0, np.float32)
    nodes = [
        helper.make_node("AveragePool", [input_name], ["pooled"], kernel_shape=[16, 16], strides=[16, 16]),
        helper.make_node("Conv", ["pooled", "weight"], ["image_embeddings"]),
    ]
    return _model(
        nodes,
        [helper.make_tensor_value_info(input_name, FLOAT, [1, 3, size, size])],
        [helper.make_tensor_value_info("image_embeddings", FLOAT, [1, channels, size // 16, size // 16])],
        [_const("weight", weight)],
    )


def sam_decoder_model(
    batched: bool = False,
    num_masks: int = 1,
    orig_size: bool = True,
    full_masks: bool = True,
    size: int = 1024,
    low_res: int = 256,
    masks_at_low_res: bool = False,
    fixed_prompts: int | None = None,
    fixed_points: int | None = None,
) -> onnx.ModelProto:
    """Box-mask decoder with the signature of segment-anything's `export_onnx_model.py`.

    Args:
      batched: prompt axis free (``num_prompts``) instead of fixed to 1.
      num_masks: 1, or 4 like a multi-mask export: mask 0 is the box, masks 1-3 its complement, whose
        predicted "IoUs" (2.0, 1.9, 1.8) beat mask 0's (the embedding mean, below 2 for the test images).
      orig_size: take `orig_im_size` (else no full-size `masks` output: low-res only).
      full_masks: give `masks` (needs `orig_size`).
      masks_at_low_res: `masks` is a copy of `low_res_masks` (not at `orig_im_size`).
      fixed_prompts, fixed_points: fix the prompt / point axes to these sizes (the corners are points 0, 1).
    """
    prompts = fixed_prompts or ("num_prompts" if batched else 1)
    points = fixed_points or "num_points"
    inits = [
        _const("axis3", np.array([3], np.int64)),
        _const("inside_value", np.array(10.0, np.float32)),
        _const("outside_value", np.array(-10.0, np.float32)),
        _const("zero", np.array(0.0, np.float32)),
        _const("iou_shape", np.array([-1, 1], np.int64)),
        _const("low_u", ((np.arange(low_res, dtype=np.float32) + 0.5) * (size / low_res)).reshape(1, 1, 1, low_res)),
        _const("low_v", ((np.arange(low_res, dtype=np.float32) + 0.5) * (size / low_res)).reshape(1, 1, low_res, 1)),
    ]
    if num_masks > 1:
        inits.append(_const("other_ious", np.array([[2.0, 1.9, 1.8][: num_masks - 1]], np.float32)))
    nodes = []
    corners = {"x0": (0, 0), "y0": (0, 1), "x1": (1, 0), "y1": (1, 1)}
    for name, (point, axis) in corners.items():
        inits += [
            _const(f"{name}_starts", np.array([point, axis], np.int64)),
            _const(f"{name}_ends", np.array([point + 1, axis + 1], np.int64)),
        ]
        nodes += [
            helper.make_node("Slice", ["point_coords", f"{name}_starts", f"{name}_ends", "axes12"], [f"{name}_3"]),
            helper.make_node("Unsqueeze", [f"{name}_3", "axis3"], [name]),
        ]  # [B, 1, 1, 1]
    inits.append(_const("axes12", np.array([1, 2], np.int64)))

    def box_mask(u: str, v: str, out: str) -> None:
        nodes.extend(
            [
                helper.make_node("GreaterOrEqual", [u, "x0"], [f"{out}_a"]),
                helper.make_node("LessOrEqual", [u, "x1"], [f"{out}_b"]),
                helper.make_node("GreaterOrEqual", [v, "y0"], [f"{out}_c"]),
                helper.make_node("LessOrEqual", [v, "y1"], [f"{out}_d"]),
                helper.make_node("And", [f"{out}_a", f"{out}_b"], [f"{out}_ab"]),
                helper.make_node("And", [f"{out}_c", f"{out}_d"], [f"{out}_cd"]),
                helper.make_node("And", [f"{out}_ab", f"{out}_cd"], [f"{out}_in"]),
                helper.make_node("Where", [f"{out}_in", "inside_value", "outside_value"], [f"{out}_one"]),
            ]
        )
        if num_masks == 1:
            nodes.append(helper.make_node("Identity", [f"{out}_one"], [out]))
        else:
            nodes.append(helper.make_node("Neg", [f"{out}_one"], [f"{out}_neg"]))
            nodes.append(helper.make_node("Concat", [f"{out}_one"] + [f"{out}_neg"] * (num_masks - 1), [out], axis=1))

    # Predicted IoU: the embedding mean, one per prompt (plus the complements' for a multi-mask export).
    nodes += [
        helper.make_node("ReduceMean", ["image_embeddings"], ["embedding_mean"], keepdims=0),
        helper.make_node("Mul", ["x0_3", "zero"], ["zeros_b11"]),
        helper.make_node("Add", ["zeros_b11", "embedding_mean"], ["iou_b11"]),
        helper.make_node("Reshape", ["iou_b11", "iou_shape"], ["iou_first"]),
    ]
    if num_masks == 1:
        nodes.append(helper.make_node("Identity", ["iou_first"], ["iou_predictions"]))
    else:
        nodes += [
            helper.make_node("Mul", ["iou_first", "zero"], ["iou_zero"]),
            helper.make_node("Add", ["iou_zero", "other_ious"], ["iou_others"]),
            helper.make_node("Concat", ["iou_first", "iou_others"], ["iou_predictions"], axis=1),
        ]

    box_mask("low_u", "low_v", "low_res_masks")
    outputs = [
        helper.make_tensor_value_info("iou_predictions", FLOAT, [prompts, num_masks]),
        helper.make_tensor_value_info("low_res_masks", FLOAT, [prompts, num_masks, low_res, low_res]),
    ]
    inputs = [
        helper.make_tensor_value_info("image_embeddings", FLOAT, [1, 256, size // 16, size // 16]),
        helper.make_tensor_value_info("point_coords", FLOAT, [prompts, points, 2]),
        helper.make_tensor_value_info("point_labels", FLOAT, [prompts, points]),
        helper.make_tensor_value_info("mask_input", FLOAT, [1, 1, low_res, low_res]),
        helper.make_tensor_value_info("has_mask_input", FLOAT, [1]),
    ]
    if orig_size:
        inputs.append(helper.make_tensor_value_info("orig_im_size", FLOAT, [2]))
        inits += [
            _const("index0", np.array(0, np.int64)),
            _const("index1", np.array(1, np.int64)),
            _const("one", np.array(1.0, np.float32)),
            _const("half", np.array(0.5, np.float32)),
            _const("side", np.array(float(size), np.float32)),
            _const("u_shape", np.array([1, 1, 1, -1], np.int64)),
            _const("v_shape", np.array([1, 1, -1, 1], np.int64)),
        ]
        nodes += [
            helper.make_node("Gather", ["orig_im_size", "index0"], ["height"]),
            helper.make_node("Gather", ["orig_im_size", "index1"], ["width"]),
            helper.make_node("ReduceMax", ["orig_im_size"], ["longest"], keepdims=0),
            helper.make_node("Div", ["side", "longest"], ["scale"]),
            helper.make_node("Range", ["zero", "width", "one"], ["cols"]),
            helper.make_node("Range", ["zero", "height", "one"], ["rows"]),
            helper.make_node("Add", ["cols", "half"], ["cols_c"]),
            helper.make_node("Add", ["rows", "half"], ["rows_c"]),
            helper.make_node("Mul", ["cols_c", "scale"], ["cols_s"]),
            helper.make_node("Mul", ["rows_c", "scale"], ["rows_s"]),
            helper.make_node("Reshape", ["cols_s", "u_shape"], ["full_u"]),
            helper.make_node("Reshape", ["rows_s", "v_shape"], ["full_v"]),
        ]
        if full_masks and masks_at_low_res:
            nodes.append(helper.make_node("Identity", ["low_res_masks"], ["masks"]))
            nodes.append(helper.make_node("Identity", ["full_u"], ["unused_u"]))
            outputs.append(helper.make_tensor_value_info("unused_u", FLOAT, [1, 1, 1, "width"]))
            outputs.insert(0, helper.make_tensor_value_info("masks", FLOAT, [prompts, num_masks, "height", "width"]))
        elif full_masks:
            box_mask("full_u", "full_v", "masks")
            outputs.insert(0, helper.make_tensor_value_info("masks", FLOAT, [prompts, num_masks, "height", "width"]))
        else:  # orig_im_size taken but unused
            nodes.append(helper.make_node("Identity", ["full_u"], ["unused_u"]))
            outputs.append(helper.make_tensor_value_info("unused_u", FLOAT, [1, 1, 1, "width"]))
    return _model(nodes, inputs, outputs, inits)


def box_mask(box: Sequence[float], height: int, width: int) -> np.ndarray:
    """`(H, W)` bool: pixels whose centre lies in the pixel box ``[u0, v0, u1, v1]`` (what the decoder draws)."""
    u0, v0, u1, v1 = box
    u = np.arange(width) + 0.5
    v = np.arange(height) + 0.5
    return ((v[:, None] >= v0) & (v[:, None] <= v1)) & ((u[None, :] >= u0) & (u[None, :] <= u1))


# --- a whole models folder ------------------------------------------------------------------------------


def write_models_folder(
    folder: Path,
    tags: Sequence[str],
    tag_bias: Sequence[float],
    tag_weight: Sequence[float] | None,
    token_logits: np.ndarray,
    boxes: np.ndarray,
    batched_decoder: bool = False,
    vocab: Sequence[str] = VOCAB,
) -> Path:
    """The six files of a models folder (`--models DIR`), with the tiny models above."""
    folder = Path(folder)
    save(tagger_model(tag_bias, tag_weight), folder / "ram.onnx")
    write_lines(folder / "ram_tag_list.txt", tags)
    save(grounding_model(token_logits, boxes), folder / "groundingdino.onnx")
    write_lines(folder / "vocab.txt", vocab)
    save(sam_encoder_model(), folder / "sam_encoder.onnx")
    save(sam_decoder_model(batched=batched_decoder), folder / "sam_decoder.onnx")
    return folder
