"""The foundation-model front end: RAM tagger, GroundingDINO detector and SAM segmenter as ONNX models.

    from detectors import FoundationModels
    models = FoundationModels.from_folder("models/", providers="cpu")
    detections = models.detect(frame)          # FrameDetections, as the detection-file reader returns

The contracts every ONNX file must meet are in `detectors.contracts` (tables and export recipes in
docs/detectors.md). Runtime needs numpy, onnxruntime and OpenCV only.
"""

from detectors.contracts import CONTRACTS, GROUNDING, SAM_DECODER, SAM_ENCODER, TAGGER, ModelContract, TensorSpec
from detectors.grounding import (
    GroundingDetector,
    GroundingResult,
    cxcywh_to_xyxy,
    grounding_input_size,
    nms,
    postprocess_grounding,
    preprocess_grounding,
)
from detectors.onnx_runtime import ContractError, ModelNotFoundError, OnnxModel, resolve_providers
from detectors.pipeline import DetectorConfig, FoundationModels
from detectors.prompt import PromptAugmenter, PromptRecord
from detectors.segmenter import (
    ImageEmbedding,
    Segmenter,
    box_prompts,
    preprocess_sam,
    sam_resized_shape,
    upsample_low_res,
)
from detectors.tagger import ImageTagger, TagResult, filter_tags, preprocess_tagger
from detectors.tokenizer import Caption, WordPieceTokenizer, build_caption, label_scores, text_self_attention

__all__ = [
    "CONTRACTS",
    "GROUNDING",
    "SAM_DECODER",
    "SAM_ENCODER",
    "TAGGER",
    "ModelContract",
    "TensorSpec",
    "GroundingDetector",
    "GroundingResult",
    "cxcywh_to_xyxy",
    "grounding_input_size",
    "nms",
    "postprocess_grounding",
    "preprocess_grounding",
    "ContractError",
    "ModelNotFoundError",
    "OnnxModel",
    "resolve_providers",
    "DetectorConfig",
    "FoundationModels",
    "PromptAugmenter",
    "PromptRecord",
    "ImageEmbedding",
    "Segmenter",
    "box_prompts",
    "preprocess_sam",
    "sam_resized_shape",
    "upsample_low_res",
    "ImageTagger",
    "TagResult",
    "filter_tags",
    "preprocess_tagger",
    "Caption",
    "WordPieceTokenizer",
    "build_caption",
    "label_scores",
    "text_self_attention",
]
