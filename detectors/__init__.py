"""The foundation-model front end: RAM tagger, GroundingDINO detector and SAM segmenter as ONNX models,
or the closed-set one: a COCO detector (NanoDet / SSD), SAM and an ImageNet classifier.

    from detectors import FoundationModels, load_front_end
    models = FoundationModels.from_folder("models/", providers="cpu")
    models = load_front_end("models/")         # either front end, as the folder's models.yaml (or files) say
    detections = models.detect(frame)          # FrameDetections, as the detection-file reader returns

The contracts every ONNX file must meet are in `detectors.contracts` (tables and export recipes in
docs/detectors.md). Runtime needs numpy, onnxruntime and OpenCV only.
"""

from detectors.check import ModelsCheck, check_models_folder
from detectors.classifier import ImageClassifier, read_imagenet_labels
from detectors.closed_set import ClosedSetConfig, ClosedSetModels
from detectors.coco_detector import CocoDetections, CocoDetector, CocoLabels, per_class_nms, read_coco_labels
from detectors.contracts import (
    CLASSIFIER,
    CONTRACTS,
    GROUNDING,
    NANODET,
    SAM_DECODER,
    SAM_ENCODER,
    SSD,
    TAGGER,
    ModelContract,
    TensorSpec,
)
from detectors.grounding import (
    GroundingDetector,
    GroundingResult,
    cxcywh_to_xyxy,
    grounding_input_size,
    nms,
    postprocess_grounding,
    preprocess_grounding,
)
from detectors.manifest import FrontEnd, Manifest, build_front_end, load_front_end, read_manifest
from detectors.onnx_runtime import ContractError, ModelNotFoundError, OnnxModel, resolve_providers
from detectors.pipeline import DetectorConfig, FoundationModels
from detectors.prompt import PromptAugmenter, PromptRecord
from detectors.proposals import Proposal, ProposalConfig
from detectors.segmenter import (
    ImageEmbedding,
    Segmenter,
    box_prompts,
    point_prompts,
    preprocess_sam,
    sam_resized_shape,
    upsample_low_res,
)
from detectors.tagger import ImageTagger, TagResult, filter_tags, preprocess_tagger
from detectors.tokenizer import Caption, WordPieceTokenizer, build_caption, label_scores, text_self_attention
from detectors.vocabulary import LabelEntry, Vocabulary, load_vocabulary

__all__ = [
    "ModelsCheck",
    "check_models_folder",
    "ImageClassifier",
    "read_imagenet_labels",
    "ClosedSetConfig",
    "ClosedSetModels",
    "CocoDetections",
    "CocoDetector",
    "CocoLabels",
    "per_class_nms",
    "read_coco_labels",
    "CLASSIFIER",
    "NANODET",
    "SSD",
    "FrontEnd",
    "Manifest",
    "build_front_end",
    "load_front_end",
    "read_manifest",
    "Proposal",
    "ProposalConfig",
    "point_prompts",
    "LabelEntry",
    "Vocabulary",
    "load_vocabulary",
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
