"""Which front end a models folder holds, and which file plays which role: the `models.yaml` manifest.

A models folder may hold a small `models.yaml`:

    front_end: closed_set        # or grounded_sam (RAM -> GroundingDINO -> SAM; the folder layout of docs/detectors.md)
    threads: 2                   # onnxruntime intra-op threads per model (closed_set); null: onnxruntime's default
    detector: {file: detector/ssd_mobilenet_v2_coco.onnx, kind: ssd, labels: detector/coco_labels.txt,
               score_threshold: 0.4, nms_iou: 0.6, max_detections: 100}
    segmenter: {encoder: sam/mobile_sam_encoder.onnx, decoder: sam/mobile_sam_decoder.onnx, mask_choice: first}
    classifier: {file: classifier/efficientnet_lite3.onnx, labels: classifier/imagenet_labels.txt,
                 top_k: 5, classify_boxes: true, box_label_weight: 0.5, box_label_min_score: 0.05}
    proposals: {grid: [6, 4], min_predicted_iou: 0.8, min_stability: 0.85}   # null: no proposals
    vocabulary: null             # null: the packaged configs/labels/model_vocabulary.yaml; else a path in the folder

Paths are relative to the folder. Only `front_end` and, for closed_set, `detector.file` and the segmenter's
two files are required; every other key has the default shown (`kind`: from the file's inputs;
`score_threshold`: 0.35 NanoDet, 0.4 SSD; `proposals`: see `proposals.ProposalConfig`).

Without models.yaml the folder's files decide: RAM / GroundingDINO files (ram.onnx, groundingdino.onnx) make
it grounded_sam as before; the shared layout (detector/*.onnx, sam/*encoder*.onnx + sam/*decoder*.onnx,
optionally classifier/*.onnx) makes it closed_set, with SSD as the detector when both COCO detectors are
there: on the ScanNet frames measured it found the bed of frame 20 (0.88) that NanoDet-g calls a couch, did
not call frame 100's couch a bed, and scored the true objects higher (toilet 0.97 vs 0.75, couch 0.73 vs
0.55), at about the same CPU time (NanoDet found more of the bar stools of frame 280).

Every problem is a `UserError` naming models.yaml (or the folder) and what is wrong.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import yaml

from detectors.classifier import ImageClassifier
from detectors.closed_set import ClosedSetConfig, ClosedSetModels
from detectors.coco_detector import DEFAULT_MAX_DETECTIONS, DEFAULT_NMS_IOU, CocoDetector
from detectors.coco_detector import KINDS as COCO_KINDS
from detectors.contracts import GROUNDING, SAM_DECODER, SAM_ENCODER, SSD, TAGGER
from detectors.onnx_runtime import OnnxModel
from detectors.pipeline import DetectorConfig, FoundationModels
from detectors.proposals import ProposalConfig
from detectors.segmenter import Segmenter
from detectors.vocabulary import Vocabulary, load_vocabulary
from fmfusion_jax.errors import UserError
from fmfusion_jax.types import FrameDetections, RGBDFrame

MANIFEST_FILE = "models.yaml"
#: The grounded_sam front end's settings a manifest (section `grounding`) may set: `pipeline.DetectorConfig`'s.
GROUNDING_KEYS = ("box_threshold", "text_threshold", "prompt_window")
FRONT_ENDS = ("closed_set", "grounded_sam")
DETECTOR_KINDS = tuple(COCO_KINDS)
#: The closed-set settings a manifest leaves out (`ClosedSetConfig` defines them).
CLOSED_SET_DEFAULTS = ClosedSetConfig()
#: Keys each section takes (with `file` / `encoder` etc. required where said in the module docstring).
SECTION_KEYS = {
    "detector": ("file", "kind", "labels", "score_threshold", "nms_iou", "max_detections"),
    "segmenter": ("encoder", "decoder", "mask_choice"),
    "classifier": ("file", "labels", "top_k", "classify_boxes", "box_label_weight", "box_label_min_score"),
    "proposals": tuple(f.name for f in dataclasses.fields(ProposalConfig)),
    "grounding": GROUNDING_KEYS,
}
TOP_KEYS = ("front_end", "threads", *SECTION_KEYS, "vocabulary")
#: The keys naming a section's model files (an override without them cannot create the section).
SECTION_FILES = {"detector": ("file",), "segmenter": ("encoder", "decoder"), "classifier": ("file",)}
#: Detector files of the shared layout, in order of preference (see the module docstring).
SHARED_DETECTORS = (SSD.filename, "detector/nanodet_g_coco.onnx")


class FrontEnd(Protocol):
    """What `fmfusion detect` needs of a front end: `FoundationModels` and `ClosedSetModels` both are one."""

    timings: dict[str, float]
    frames: int

    @property
    def providers(self) -> list[str]: ...

    def detect(self, frame: RGBDFrame | np.ndarray, frame_name: str | None = None) -> FrameDetections: ...

    def reset(self) -> None: ...


@dataclasses.dataclass(frozen=True)
class DetectorEntry:
    file: Path
    labels: Path
    kind: str | None
    score_threshold: float | None
    nms_iou: float
    max_detections: int


@dataclasses.dataclass(frozen=True)
class SegmenterEntry:
    encoder: Path
    decoder: Path
    mask_choice: str = "first"


@dataclasses.dataclass(frozen=True)
class ClassifierEntry:
    file: Path
    labels: Path
    top_k: int
    classify_boxes: bool
    box_label_weight: float
    box_label_min_score: float


@dataclasses.dataclass(frozen=True)
class Manifest:
    """A checked manifest (paths resolved against the folder).

    Attributes:
      folder: the models folder.
      source: its models.yaml, or None when inferred from the files.
      front_end: ``"closed_set"`` or ``"grounded_sam"`` (then the sections below are None).
      threads: onnxruntime intra-op threads per model, or None (onnxruntime's default).
      proposals: None when off.
      vocabulary: a vocabulary table, or None for the packaged one.
    """

    folder: Path
    source: Path | None
    front_end: str
    threads: int | None = 2
    detector: DetectorEntry | None = None
    segmenter: SegmenterEntry | None = None
    classifier: ClassifierEntry | None = None
    proposals: ProposalConfig | None = None
    vocabulary: Path | None = None
    grounding: DetectorConfig | None = None  # grounded_sam's thresholds and prompt window

    @property
    def where(self) -> str:
        return str(self.source) if self.source else f"{self.folder} (no {MANIFEST_FILE}; inferred from the files)"


def read_manifest(models_dir: str | Path, overrides: Mapping[str, Any] | None = None) -> Manifest:
    """The folder's manifest: its models.yaml, or one inferred from its files; `overrides` merged in first.

    `overrides` has the manifest's layout (e.g. ``{"proposals": None}``, ``{"detector": {"kind": "nanodet"}}``);
    a section given as a dict is merged key by key, anything else replaces (`merge`). A grounded_sam folder
    ignores them (they are the closed-set models' settings).
    """
    folder = Path(models_dir)
    if not folder.is_dir():
        raise UserError(f"{folder}: models folder not found")
    path = folder / MANIFEST_FILE
    if path.is_file():
        try:
            data = yaml.safe_load(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError) as error:
            raise UserError(f"{path}: cannot read the manifest ({getattr(error, 'strerror', None) or error})") from None
        except yaml.YAMLError as error:
            raise UserError(f"{path}: not valid YAML ({str(error).splitlines()[0]})") from None
        if not isinstance(data, dict):
            raise UserError(f"{path}: expected a mapping with front_end and the model roles, got {type(data).__name__}")
        source: Path | None = path
    else:
        data, source = infer_manifest_data(folder), None
    merged = merge(data, overrides or {})
    if merged.get("front_end") == "grounded_sam":
        # overrides tune the closed-set models (a run's config may set them for any folder): none applies here
        merged = {key: value for key, value in merged.items() if key in data or key in ("front_end", "grounding")}
    return parse_manifest(merged, folder, source)


def merge(data: Mapping[str, Any], overrides: Mapping[str, Any]) -> dict[str, Any]:
    """`data` with `overrides` applied: dict sections merged key by key, other values replaced.

    Settings for a model the manifest does not have (e.g. ``{"classifier": {"classify_boxes": False}}`` on a
    folder without a classifier) are ignored: a section is only created by an override naming its file(s).
    """
    out = dict(data)
    for key, value in overrides.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = {**out[key], **value}
        elif isinstance(value, Mapping) and key in SECTION_FILES and not any(k in value for k in SECTION_FILES[key]):
            continue
        else:
            out[key] = value
    return out


def infer_manifest_data(folder: Path) -> dict[str, Any]:
    """The manifest a folder without models.yaml implies (module docstring); `UserError` when none fits."""
    if any((folder / c.filename).exists() for c in (TAGGER, GROUNDING)):
        return {"front_end": "grounded_sam"}
    detectors = sorted(p.relative_to(folder).as_posix() for p in folder.glob("detector/*.onnx"))
    encoders = sorted(p.relative_to(folder).as_posix() for p in folder.glob("sam/*encoder*.onnx"))
    decoders = sorted(p.relative_to(folder).as_posix() for p in folder.glob("sam/*decoder*.onnx"))
    classifiers = sorted(p.relative_to(folder).as_posix() for p in folder.glob("classifier/*.onnx"))
    if not detectors or not encoders or not decoders:
        raise UserError(
            f"{folder}: neither a grounded_sam folder (ram.onnx, groundingdino.onnx, sam_encoder.onnx, "
            "sam_decoder.onnx) nor the closed-set layout (detector/*.onnx, sam/*encoder*.onnx, sam/*decoder*.onnx, "
            f"classifier/*.onnx), and no {MANIFEST_FILE} saying which file is which (see docs/detectors.md)"
        )
    for role, found in (
        ("detector", detectors),
        ("SAM encoder", encoders),
        ("SAM decoder", decoders),
        ("classifier", classifiers),
    ):
        preferred = [name for name in SHARED_DETECTORS if name in found] if role == "detector" else []
        if len(found) > 1 and not preferred:
            raise UserError(f"{folder}: several {role} files {found}; write a {MANIFEST_FILE} naming the one to use")
    detector = next((name for name in SHARED_DETECTORS if name in detectors), detectors[0])
    data: dict[str, Any] = {
        "front_end": "closed_set",
        "detector": {"file": detector, "labels": "detector/coco_labels.txt"},
        "segmenter": {"encoder": encoders[0], "decoder": decoders[0]},
        "classifier": None,
        "proposals": None,
    }
    if classifiers:
        data["classifier"] = {"file": classifiers[0], "labels": "classifier/imagenet_labels.txt"}
        data["proposals"] = {}
    return data


def parse_manifest(data: Mapping[str, Any], folder: Path, source: Path | None) -> Manifest:
    """Checks the manifest's fields; `UserError` naming `source` (or the folder) and the key."""
    where = str(source) if source else f"{folder} (inferred manifest)"
    unknown = [key for key in data if key not in TOP_KEYS]
    if unknown:
        raise UserError(f"{where}: unknown key(s) {unknown}; expected {', '.join(TOP_KEYS)}")
    front_end = data.get("front_end", "grounded_sam" if source is None else None)
    if front_end not in FRONT_ENDS:
        raise UserError(f"{where}: front_end {front_end!r}: expected one of {', '.join(FRONT_ENDS)}")
    if front_end == "grounded_sam":
        extra = [key for key in data if key not in ("front_end", "grounding") and data[key] is not None]
        if extra:
            raise UserError(f"{where}: {extra} only apply to front_end closed_set (grounded_sam uses the fixed file names)")
        grounding = _section(data, "grounding", where, required=False) or {}
        try:
            detector_config = DetectorConfig(**grounding)
        except UserError as error:
            raise UserError(f"{where}: grounding: {error}") from None
        return Manifest(folder, source, front_end, threads=None, grounding=detector_config)
    threads = data.get("threads", 2)
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise UserError(f"{where}: threads {threads!r} must be an integer >= 1 or null")
    detector = _section(data, "detector", where, required=True)
    segmenter = _section(data, "segmenter", where, required=True)
    classifier = _section(data, "classifier", where, required=False)
    proposals = _section(data, "proposals", where, required=False)
    assert detector is not None and segmenter is not None
    detector_entry = DetectorEntry(
        file=_file(folder, detector, "file", where, "detector"),
        labels=_file(folder, {"labels": detector.get("labels", "detector/coco_labels.txt")}, "labels", where, "detector"),
        kind=_choice(detector.get("kind"), DETECTOR_KINDS, f"{where}: detector kind", optional=True),
        score_threshold=_fraction(detector.get("score_threshold"), f"{where}: detector score_threshold", optional=True),
        nms_iou=_fraction(detector.get("nms_iou", DEFAULT_NMS_IOU), f"{where}: detector nms_iou"),
        max_detections=_count(detector.get("max_detections", DEFAULT_MAX_DETECTIONS), f"{where}: detector max_detections"),
    )
    segmenter_entry = SegmenterEntry(
        encoder=_file(folder, segmenter, "encoder", where, "segmenter"),
        decoder=_file(folder, segmenter, "decoder", where, "segmenter"),
        mask_choice=_choice(segmenter.get("mask_choice", "first"), ("first", "best"), f"{where}: segmenter mask_choice"),
    )
    classifier_entry = None
    if classifier is not None:
        classify_boxes = classifier.get("classify_boxes", CLOSED_SET_DEFAULTS.classify_boxes)
        if not isinstance(classify_boxes, bool):
            raise UserError(f"{where}: classifier classify_boxes {classify_boxes!r} must be true or false")
        weight = _fraction(
            classifier.get("box_label_weight", CLOSED_SET_DEFAULTS.box_label_weight), f"{where}: classifier box_label_weight"
        )
        if weight == 0:
            raise UserError(f"{where}: classifier box_label_weight must be above 0")
        classifier_entry = ClassifierEntry(
            file=_file(folder, classifier, "file", where, "classifier"),
            labels=_file(
                folder, {"labels": classifier.get("labels", "classifier/imagenet_labels.txt")}, "labels", where, "classifier"
            ),
            top_k=_count(classifier.get("top_k", CLOSED_SET_DEFAULTS.top_k), f"{where}: classifier top_k"),
            classify_boxes=classify_boxes,
            box_label_weight=weight,
            box_label_min_score=_fraction(
                classifier.get("box_label_min_score", CLOSED_SET_DEFAULTS.box_label_min_score), f"{where}: classifier min score"
            ),
        )
    proposal_config = None
    if proposals is not None:
        if classifier_entry is None:
            raise UserError(
                f"{where}: proposals need a classifier to name them (add a classifier section or set proposals: null)"
            )
        try:
            proposal_config = ProposalConfig(**proposals)
        except UserError as error:
            raise UserError(f"{where}: {error}") from None
        except TypeError as error:
            raise UserError(f"{where}: proposals: {error}") from None
    vocabulary = data.get("vocabulary")
    vocabulary_path = _file(folder, {"vocabulary": vocabulary}, "vocabulary", where, "vocabulary") if vocabulary else None
    return Manifest(
        folder, source, front_end, threads, detector_entry, segmenter_entry, classifier_entry, proposal_config, vocabulary_path
    )


def _section(data: Mapping[str, Any], key: str, where: str, required: bool) -> dict[str, Any] | None:
    """`data[key]` checked to be a mapping of known keys (None / false when absent and not `required`)."""
    value = data.get(key)
    if value is None or value is False:
        if required:
            raise UserError(f"{where}: the {key} section is missing (front_end closed_set needs it)")
        return None
    if not isinstance(value, Mapping):
        raise UserError(f"{where}: {key} must be a mapping ({', '.join(SECTION_KEYS[key])}), got {value!r}")
    unknown = [k for k in value if k not in SECTION_KEYS[key]]
    if unknown:
        raise UserError(f"{where}: unknown {key} key(s) {unknown}; expected {', '.join(SECTION_KEYS[key])}")
    return dict(value)


def _file(folder: Path, section: Mapping[str, Any], key: str, where: str, role: str) -> Path:
    """The existing file `section[key]` names, relative to `folder`."""
    name = section.get(key)
    if not isinstance(name, str) or not name:
        raise UserError(f"{where}: {role} {key} must name a file in the folder, got {name!r}")
    path = folder / name
    if not path.is_file():
        raise UserError(f"{where}: {role} {key} {name!r}: {path} not found")
    return path


def _fraction(value: Any, what: str, optional: bool = False) -> Any:
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value <= 1.0:
        raise UserError(f"{what} {value!r} must be a number in [0, 1]")
    return float(value)


def _count(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise UserError(f"{what} {value!r} must be an integer >= 1")
    return value


def _choice(value: Any, choices: Sequence[str], what: str, optional: bool = False) -> Any:
    if value is None and optional:
        return None
    if value not in choices:
        raise UserError(f"{what} {value!r}: expected one of {', '.join(choices)}")
    return value


def build_front_end(manifest: Manifest, providers: str | Sequence[str] = "cpu") -> FrontEnd:
    """Loads the models a manifest names; a model file that does not fit its role is a `UserError` naming it."""
    if manifest.front_end == "grounded_sam":
        return FoundationModels.from_folder(manifest.folder, providers, config=manifest.grounding)
    parts = {role: load_role(manifest, role, providers) for role in CLOSED_SET_ROLES}
    return assemble_closed_set(manifest, **parts)


#: What a closed_set manifest loads, in order.
CLOSED_SET_ROLES = ("detector", "segmenter", "classifier", "vocabulary")


def load_role(manifest: Manifest, role: str, providers: str | Sequence[str] = "cpu") -> Any:
    """One role of a closed_set manifest loaded: a `CocoDetector`, `Segmenter`, `ImageClassifier` (or None),
    or `Vocabulary`. Errors name the manifest and the role."""
    d, s, c, threads = manifest.detector, manifest.segmenter, manifest.classifier, manifest.threads
    with _role(manifest, role):
        if role == "detector":
            assert d is not None
            return CocoDetector.from_files(
                d.file,
                d.labels,
                d.kind,
                providers,
                threads,
                score_threshold=d.score_threshold,
                nms_iou=d.nms_iou,
                max_detections=d.max_detections,
            )
        if role == "segmenter":
            assert s is not None
            encoder = OnnxModel(s.encoder, SAM_ENCODER, providers, threads)
            return Segmenter(encoder, OnnxModel(s.decoder, SAM_DECODER, providers, threads), s.mask_choice)
        if role == "classifier":
            return ImageClassifier.from_files(c.file, c.labels, providers, threads) if c else None
        if role == "vocabulary":
            return load_vocabulary(manifest.vocabulary)
    raise ValueError(f"unknown role {role!r}")


def assemble_closed_set(
    manifest: Manifest,
    detector: CocoDetector,
    segmenter: Segmenter,
    classifier: ImageClassifier | None,
    vocabulary: Vocabulary,
) -> ClosedSetModels:
    """The `ClosedSetModels` of a manifest from its loaded roles."""
    c = manifest.classifier
    if c is None:  # no classifier: the boxes keep the detector's names
        config = ClosedSetConfig(classify_boxes=False, proposals=manifest.proposals)
    else:
        config = ClosedSetConfig(
            classify_boxes=c.classify_boxes,
            box_label_weight=c.box_label_weight,
            box_label_min_score=c.box_label_min_score,
            top_k=c.top_k,
            proposals=manifest.proposals,
        )
    return ClosedSetModels(detector, segmenter, classifier, vocabulary, config)


@contextlib.contextmanager
def _role(manifest: Manifest, role: str) -> Iterator[None]:
    """Prefixes a `UserError` raised while loading `role` with the manifest and the role."""
    try:
        yield
    except UserError as error:
        raise type(error)(f"{manifest.where}: {role}: {error}") from None


def load_front_end(
    models_dir: str | Path, providers: str | Sequence[str] = "cpu", overrides: Mapping[str, Any] | None = None
) -> FrontEnd:
    """The front end of a models folder: `FoundationModels` (grounded_sam) or `ClosedSetModels` (closed_set).

    `providers`: ``"cpu"``, ``"cuda"``, ``"auto"`` or onnxruntime provider names; `overrides`: see `read_manifest`.
    """
    return build_front_end(read_manifest(models_dir, overrides), providers)
