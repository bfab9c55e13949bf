"""Pipeline configuration: one schema (pydantic models) with the paper's defaults, read from YAML, overridable.

Each knob is defined once, in the section models below: its name (the YAML key), default, range, what reads it
(`KINDS`) and one line of documentation; `docs/config.md` is generated from them. A YAML file may name a
`base:` file (relative to itself) whose values it overrides. Any value can be overridden on the command line
as `--set section.key=value` (value parsed as YAML). Unknown sections or keys are errors that name the closest
valid key, so a typo never silently falls back to a default; values are type- and range-checked on load and
on assignment.
"""

from __future__ import annotations

import difflib
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictFloat, StrictInt, ValidationError, model_validator

from fmfusion_jax.errors import UserError

#: What a knob is read by, as the schema records it (`Field(json_schema_extra={"kind": ...})`):
#: ``shape``: sizes of the map state and of the per-pixel grids, fixed when a map is made (a change makes
#: another map layout and recompiles); ``engine``: parameters of the jitted fusion and refinement steps (the
#: thresholds are traced values: a change reuses the compiled steps; the few that choose code paths, the modes of
#: `engine.step.FUSION_MODES`, compile other steps); ``host``: read by the Python loop, the readers or the export
#: only (no recompilation).
KINDS = ("shape", "engine", "host")

Float = StrictFloat
Int = StrictInt
Bool = StrictBool


def knob(default: Any, doc: str, kind: str = "host", **constraints: Any) -> Any:
    """One config value: its default, one line of documentation, what reads it (`KINDS`) and its range
    (pydantic's `gt`, `ge`, `lt`, `le`)."""
    assert kind in KINDS, kind
    return Field(default, description=doc, json_schema_extra={"kind": kind}, **constraints)


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class DatasetConfig(_Section):
    layout: Literal["auto", "scannet", "scenenn", "tum", "replica", "redwood", "rosbag", "record3d", "realsense"] = knob(
        "auto", "folder layout (auto: detected from the folder; docs/your-own-data.md)"
    )
    depth_scale: Float | None = knob(
        None,
        "depth png units per metre (null: the recording's own: ScanNet, SceneNN, Redwood 1000 (millimetres), "
        "TUM 5000, Replica 6553.5 or its cam_params.json's)",
        gt=0,
    )
    depth_max: Float = knob(4.0, "m; farther depth is dropped (reference: 4.0)", gt=0)
    frame_stride: Int = knob(1, "read every Nth frame", ge=1)
    max_frames: Int | None = knob(None, "stop after this many frames (null: all)", ge=1)
    max_time_difference: Float = knob(
        0.02, "s; TUM recordings, ROS bags: a colour image pairs with the depth image and pose this close in time", gt=0
    )
    color_topic: str | None = knob(
        None, "ROS bags: the colour topic (Image rgb8/bgr8/rgba8/bgra8 or CompressedImage; null: chosen and logged)"
    )
    depth_topic: str | None = knob(
        None, "ROS bags: the depth topic, registered to colour (Image 16UC1 mm or 32FC1 m; null: chosen and logged)"
    )
    camera_info_topic: str | None = knob(None, "ROS bags: the depth camera's CameraInfo topic (null: chosen and logged)")
    pose_topic: str | None = knob(
        None, "ROS bags: the camera poses, a PoseStamped or Odometry topic or /tf (null: /tf when it reaches the camera)"
    )
    pose_frame: str | None = knob(None, "ROS bags: the tf frame whose pose is the camera's (null: the camera info's frame_id)")
    min_depth_confidence: Int = knob(
        1,
        "Record3D: LiDAR depth pixels of lower ARKit confidence are dropped (0 keeps all, 1 drops the low ones, "
        "2 keeps the high ones only)",
        ge=0,
        le=2,
    )


class TSDFConfig(_Section):
    voxel_size: Float = knob(0.015625, "m; 4.0/256 as in the reference (paper: 1.5 cm)", "shape", gt=0)
    sdf_trunc: Float = knob(0.04, "m; truncation distance of the TSDF (must exceed voxel_size)", "shape", gt=0)
    block_size: Int = knob(8, "voxels per block side (even; 8^3-voxel blocks are 12.5 cm)", "shape", ge=2)
    block_capacity: Int = knob(
        65536, "blocks the pool may grow to (~15 KB each; a ScanNet room uses ~20-40k; runs start smaller)", "shape", ge=2
    )
    max_touched_blocks: Int = knob(
        12288, "blocks integrated per frame (more are skipped, counted and warned about)", "shape", ge=1
    )
    max_weight: Float = knob(255.0, "cap of the TSDF weight (keeps the map responsive)", "shape", gt=0)
    bounds_margin: Float = knob(0.5, "m added around the scene bounds estimated from the poses and depth", ge=0)

    @model_validator(mode="after")
    def _check(self) -> "TSDFConfig":
        if self.block_size % 2:
            raise ValueError(f"tsdf.block_size must be even (blocks are made of 2x2x2 cells), got {self.block_size}")
        if self.sdf_trunc <= self.voxel_size:
            raise ValueError(f"tsdf.sdf_trunc ({self.sdf_trunc}) must exceed tsdf.voxel_size ({self.voxel_size})")
        return self


class DetectionConfig(_Section):
    schedule: Literal["motion", "every"] = knob(
        "motion",
        "motion: fuse a frame's detections when the camera moved or turned enough since the last "
        "detection frame; every: every Nth frame (the paper's rule)",
    )
    min_translation: Float = knob(0.05, "m moved since the last detection frame (motion schedule)", ge=0)
    min_rotation: Float = knob(5.0, "degrees turned since the last detection frame (motion schedule)", ge=0)
    sparse_motion: Float = knob(
        0.5,
        "a sequence whose median step between frames is this share of the above is "
        "subsampled in time: every frame is fused (motion schedule; 0: off)",
        ge=0,
    )
    every: Int = knob(10, "every Nth frame (schedule `every`; paper: ScanNet 10, SceneNN 5)", ge=1)
    max_detections: Int = knob(32, "detections per frame kept (highest scores first)", "shape", ge=1)
    min_mask_pixels: Int = knob(1000, "smaller masks are ignored (reference Python: 1000, its C++: 100)", ge=0)
    depth_percentiles: tuple[Float, Float] = knob(
        (0.1, 0.9), "a mask's depth outside these quantiles is dropped (mask border bleed)", "engine"
    )
    floor_up_axis: Literal["+z", "-z", "+y", "-y", "+x", "-x", "none"] = knob(
        "+z",
        "the world's up axis (ScanNet, SceneNN: +z): mask pixels on the floor are not the object's, and a "
        "detection mostly on the floor is dropped (none: no floor filter)",
        "engine",
    )
    floor_band: Float = knob(0.05, "m above the floor that still counts as floor (floor filter)", "engine", gt=0)
    floor_max_share: Float = knob(
        0.5, "a detection with more of its mask on the floor is dropped whole (floor filter)", "engine", ge=0, le=1
    )

    @model_validator(mode="after")
    def _check(self) -> "DetectionConfig":
        low, high = self.depth_percentiles
        if not 0.0 <= low < high <= 1.0:
            raise ValueError(
                f"detections.depth_percentiles must be [low, high] with 0 <= low < high <= 1, got {list(self.depth_percentiles)}"
            )
        return self


class AssociationConfig(_Section):
    metric: Literal["projection_overlap", "iou"] = knob(
        "projection_overlap", "|mask and projection| / |projection| (reference Python), or iou", "engine"
    )
    threshold: Float = knob(0.5, "match above this (reference Python: 0.5; its C++: IoU 0.3)", "engine", gt=0, le=1)
    rank: Literal["iou", "score"] = knob(
        "iou",
        "the pairs above the threshold match best first by this: iou (a mask over several instances goes to the one "
        "of its size, not to a small one inside it), or the metric's own score (reference)",
        "engine",
    )
    pixel_stride: Int = knob(2, "pixels sampled for projection, association and instance integration", "shape", ge=1)
    min_projected_pixels: Int = knob(
        800, "an instance is in view (active) above this many full-resolution pixels", "engine", ge=0
    )


class InstanceConfig(_Section):
    capacity: Int = knob(
        1024, "instance table rows (overflowing detections are dropped and warned about)", "shape", ge=2, le=32767
    )
    voxel_slots: Int = knob(2, "instances one voxel can hold (overlapping instance volumes)", "shape", ge=1)
    contrary_vote_weight: Float = knob(
        0.5,
        "a voxel seen outside the mask of its instance's detection loses this per pixel, so one mask-border "
        "hit never makes it a member (0: the paper's rule)",
        "engine",
        ge=0,
    )


class LabelFusionConfig(_Section):
    mode: Literal["additive", "bayes"] = knob(
        "additive", "the paper's weighted additive update (final equation of Sec. III-D), or bayes", "engine"
    )
    likelihood: str = knob("statistical", "statistical (the summarized 38x20 matrix), manual (ablation A), or a CSV path")
    normalize_columns: Bool = knob(
        False,
        "scale each class's column of the likelihood to sum 1 before fusing, p(label | class, detected) (walls' "
        "column sums to 0.43 in the statistical matrix, and they fuse as doors and bookshelves); off by default: "
        "+2.9 AP50 over the zoo of noise seed 0, -1.2 over that of seed 1 (docs/experiments.md)",
    )


class RefinementConfig(_Section):
    enabled: Bool = knob(True, "online merge, geometry fusion and removal (false: ablation C)")
    merge_every: Int = knob(1, "online merge test every Nth detection frame", ge=1)
    merge_similarity: Float = knob(0.15, "merge needs semantic similarity p_a . p_b above this ...", "engine", ge=0)
    merge_overlap: Float = knob(
        0.4, "... and this share of the smaller instance inside the larger one inflated 2x", "engine", ge=0, le=1
    )
    geometry_fusion_every: Int = knob(
        20,
        "detection frames between geometry fusions (paper: 200 frames at every "
        "10th): drop instance voxels the global surface does not support",
        ge=1,
    )
    geometry_min_weight: Float = knob(
        1.0, "global TSDF weight a voxel needs to support instance voxels in geometry fusion", "engine", ge=0
    )
    remove_missed: Int = knob(5, "remove an instance missed this many detection frames while in view ...", "engine", ge=1)
    remove_min_voxels: Int = knob(500, "... when it has fewer voxels than this", "engine", ge=0)
    reunite_min_frames: Int = knob(
        2,
        "reunite fragments: b joins a once a's detections covered b in this many detection frames and at least "
        "as often as b was detected itself (0: off)",
        "engine",
        ge=0,
    )
    separate_min_frames: Int = knob(
        0,
        ">0: never merge a and b while two detections of one frame showed them apart this often and at least "
        "as often as one detection covered both (off: split masks would veto the reunion of parts)",
        "engine",
        ge=0,
    )


class ExportConfig(_Section):
    min_weight: Float = knob(2.0, "exported instance voxels need this slot weight", ge=0)
    min_slot_share: Float = knob(
        0.5,
        "... and this share of the voxel's strongest slot: a smear on a well-observed "
        "floor, or a table over a chair it swallowed, is dropped (0: any slot)",
        ge=0,
        le=1,
    )
    structure_claims_vertices: Bool = knob(
        True,
        "wall and floor instances take part in the vertex transfer (then "
        "dropped): a floor vertex nearest to the floor is no object's",
    )
    post_merge_iou: Float = knob(0.2, "post-processing merge: 3D IoU above this ...", "engine", ge=0, le=1)
    post_merge_similarity: Float = knob(0.1, "... and semantic similarity above this", "engine", ge=0)
    min_points: Int = knob(200, "instances with fewer points are dropped", ge=0)
    speck_distance: Float = knob(
        0.2, "m; pieces of an instance farther than this from its largest piece are dropped (0: kept)", ge=0
    )
    support_observations: Float = knob(
        3.0,
        "existence = (1 - exp(-observations / this)) x the hit-rate factor: one-off instances rank low "
        "(0: no such factor); confidence = class probability x existence",
        ge=0,
    )
    existence_prior: Float = knob(
        4.0,
        "pseudo-frames at the detector's own hit rate that an instance's hit rate (detected / in view) is "
        "shrunk towards; a rate below the detector's lowers the existence (0: hit rates not used)",
        ge=0,
    )
    min_existence: Float = knob(0.3, "instances of a lower existence are not exported (0: every instance)", ge=0, le=1)
    alternative_class_probability: Float = knob(
        0.1,
        "benchmark: an instance is also submitted under each other class it has at least this probability of, "
        "at confidence probability x existence, as the benchmark ranks class hypotheses (1: its most likely class only)",
        ge=0,
        le=1,
    )
    union_confidence_factor: Float = knob(
        0.25,
        "benchmark: two touching instances of one class (a mesh edge joins them; the class of either one's class "
        "hypothesis) are also submitted as one, at this times the lower of their confidences: an object the map "
        "holds in two pieces is found (0: off)",
        ge=0,
        le=1,
    )
    planar_thickness: Float = knob(
        1.3,
        "voxels; an instance of a volumetric class at most this thick is a sheet (of wall, floor or "
        "counter front, or a cabinet seen from the front only) (0: no sheets)",
        ge=0,
    )
    structure_label_factor: Float = knob(
        2.5,
        "a surface whose existence x (1 - this x the share of its open-set label scores that name a wall or the "
        "floor, each label split over the classes as its likelihood row, beyond the share an object of its class "
        "shows under the likelihood's column) falls below min_existence is exported as the wall or floor: a patch "
        "of wall fused as a bookshelf (0: labels not used)",
        ge=0,
        le=10,
    )
    surface_thickness: Float = knob(
        3.0,
        "voxels; an instance at most this thick is a surface, which may be a piece of a wall or the floor: only "
        "then do its structure labels count against it (structure_label_factor)",
        ge=0,
    )
    sheet_factor: Float = knob(0.5, "a sheet's existence is multiplied by this (0: sheets are never exported)", ge=0, le=1)
    flat_classes: tuple[str, ...] = knob(
        ("wall", "floor", "door", "window", "picture", "curtain", "shower curtain"),
        "classes whose objects may be flat (not subject to planar_thickness)",
    )
    transfer_radius: Float = knob(0.08, "m; instance labels to the mesh vertices by radius search (benchmark)", gt=0)
    transfer_neighbours: Int = knob(
        8, "a vertex takes the instance of most of its nearest points within the radius (1: the nearest point decides)", ge=1
    )
    shower_curtain_radius: Float = knob(2.0, "m; a curtain this close to a toilet or bathtub is a shower curtain", ge=0)
    curtain_by_context: Bool = knob(
        True,
        "... and a shower curtain farther from them a curtain (the matrix weighs "
        "the label alike under both; false: the reference's first direction only)",
    )


class FrontEndConfig(_Section):
    """Settings of the models a run detects with (`fmfusion run --models`, `fmfusion detect`): null keeps what the
    models folder's models.yaml (or the folder's layout) says; see docs/detectors.md."""

    detector_score_threshold: Float | None = knob(
        None, "COCO detector: boxes scoring below this are dropped (null: 0.35 NanoDet-g, 0.4 SSD)", ge=0, le=1
    )
    proposals: Bool | None = knob(
        None,
        "class-agnostic SAM proposals named by the classifier, for objects a COCO detector cannot name (null: as the folder)",
    )
    proposal_grid: tuple[Int, Int] | None = knob(None, "point prompts across x down of the proposals (null: 6 x 4)")
    classify_boxes: Bool | None = knob(
        None, "the classifier also names each detector box; agreeing labels are added at box_label_weight (null: true)"
    )
    threads: Int | None = knob(None, "onnxruntime threads per model (null: 2)", ge=1)
    box_threshold: Float | None = knob(
        None, "GroundingDINO: a box needs a token score above this (null: 0.35, FM-Fusion's)", ge=0, le=1
    )
    text_threshold: Float | None = knob(
        None, "GroundingDINO: a label needs all its token scores above this (null: 0.25)", ge=0, le=1
    )
    prompt_window: Int | None = knob(None, "detection frames whose labels augment RAM's prompt (0: none; null: 5)", ge=0)

    def manifest_overrides(self) -> dict[str, Any]:
        """The settings that are set, as `models.yaml` keys (`detectors.read_manifest`'s overrides)."""
        overrides: dict[str, Any] = {}
        if self.threads is not None:
            overrides["threads"] = self.threads
        if self.detector_score_threshold is not None:
            overrides["detector"] = {"score_threshold": self.detector_score_threshold}
        if self.classify_boxes is not None:
            overrides["classifier"] = {"classify_boxes": self.classify_boxes}
        grounding = {key: getattr(self, key) for key in ("box_threshold", "text_threshold", "prompt_window")}
        if any(value is not None for value in grounding.values()):
            overrides["grounding"] = {key: value for key, value in grounding.items() if value is not None}
        if self.proposals is False:
            overrides["proposals"] = None
        elif self.proposals or self.proposal_grid is not None:
            overrides["proposals"] = {} if self.proposal_grid is None else {"grid": list(self.proposal_grid)}
        return overrides


class PipelineConfig(BaseModel):
    """The whole configuration: one section per part of the system, each knob defined once (`knob`)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    dataset: DatasetConfig = Field(default_factory=DatasetConfig, description="reading the RGB-D sequence")
    tsdf: TSDFConfig = Field(default_factory=TSDFConfig, description="the global TSDF and the voxel block pool")
    detections: DetectionConfig = Field(
        default_factory=DetectionConfig, description="which frames' detections are fused, and how they are cleaned"
    )
    association: AssociationConfig = Field(default_factory=AssociationConfig, description="projection-overlap data association")
    instances: InstanceConfig = Field(default_factory=InstanceConfig, description="instance volumes in the voxels")
    label_fusion: LabelFusionConfig = Field(default_factory=LabelFusionConfig, description="the probabilistic label update")
    refinement: RefinementConfig = Field(
        default_factory=RefinementConfig, description="merging, geometry fusion and removal of instances"
    )
    export: ExportConfig = Field(default_factory=ExportConfig, description="post-processing and the benchmark export")
    front_end: FrontEndConfig = Field(
        default_factory=FrontEndConfig, description="the models a run detects with (--models), over the models folder's settings"
    )

    def to_dict(self) -> dict[str, Any]:
        return _plain(self.model_dump())

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return value


def config_schema() -> dict[str, dict[str, Any]]:
    """Every knob by section: `{section: {key: {"default", "doc", "kind", "range", "type"}}}`."""
    schema: dict[str, dict[str, Any]] = {}
    for section, section_field in PipelineConfig.model_fields.items():
        model = section_field.annotation
        assert isinstance(model, type) and issubclass(model, BaseModel)
        schema[section] = {}
        for key, field in model.model_fields.items():
            bounds = []
            for item in field.metadata:
                for name, symbol in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
                    if getattr(item, name, None) is not None:
                        bounds.append(f"{symbol} {getattr(item, name)}")
            extra = field.json_schema_extra if isinstance(field.json_schema_extra, dict) else {}
            schema[section][key] = {
                "default": _plain(field.default),
                "doc": field.description or "",
                "kind": extra.get("kind", "host"),
                "range": ", ".join(bounds),
                "type": _type_name(field.annotation),
            }
    return schema


def _type_name(annotation: Any) -> str:
    if getattr(annotation, "__origin__", None) is Literal:
        return " / ".join(f"`{value}`" for value in annotation.__args__)
    text = str(annotation).replace("typing.", "")
    for long, short in (
        ("Annotated[float, Strict(strict=True)]", "float"),
        ("Annotated[int, Strict(strict=True)]", "int"),
        ("Annotated[bool, Strict(strict=True)]", "bool"),
        ("<class 'str'>", "str"),
    ):
        text = text.replace(long, short)
    return text


def config_reference_markdown() -> str:
    """`docs/config.md`: every knob with its default, range, kind and documentation, from the schema."""
    lines = [
        "# Configuration reference",
        "",
        "Generated from the schema in `fmfusion_jax/config.py` (`config_reference_markdown()`; a test keeps this",
        "page equal to it). Every value can be set in a YAML config (`configs/scannet.yaml` is the default) or",
        'on the command line as `--set section.key=value`, or from Python as `Mapper({"section": {"key": value}})`.',
        "Kinds: `shape` fixes the map's sizes (a change makes another map layout and recompiles), `engine` is read",
        "by the jitted steps (a threshold is a traced value: a change reuses the compiled steps; the few knobs that",
        "choose code paths, such as `label_fusion.mode`, compile other steps), `host` is read by the Python loop,",
        "the readers or the export.",
        "",
    ]
    descriptions = {name: field.description for name, field in PipelineConfig.model_fields.items()}
    for section, knobs in config_schema().items():
        lines += [
            f"## `{section}`: {descriptions[section]}",
            "",
            "| key | default | range | kind | meaning |",
            "|---|---|---|---|---|",
        ]
        for key, info in knobs.items():
            default = yaml.safe_dump(info["default"], default_flow_style=True).strip().removesuffix("...").strip()
            lines.append(
                f"| `{key}` | `{default}` | {info['range'] or info['type']} | {info['kind']} | {info['doc'].replace('|', '/')} |"
            )
        lines.append("")
    return "\n".join(lines)


def configs_dir() -> Path:
    """Folder of the packaged configs (`configs/` of the source tree)."""
    return Path(str(resources.files("fmfusion_jax.configs")))


def resolve_config_path(name_or_path: str) -> Path:
    """A config file path, or the name of a packaged config (`scannet`, `scenenn`, ...)."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    packaged = configs_dir() / f"{name_or_path.removesuffix('.yaml')}.yaml"
    if packaged.is_file():
        return packaged
    available = sorted(p.stem for p in configs_dir().glob("*.yaml"))
    raise UserError(f"config '{name_or_path}' not found: give a YAML file or one of {available}")


def _read_yaml_with_bases(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    path = path.resolve()
    if path in seen:
        raise UserError(f"{path}: circular 'base:' chain")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as error:
        raise UserError(f"{path}: not valid YAML ({error})") from None
    if not isinstance(data, dict):
        raise UserError(f"{path}: a config must be a mapping of sections")
    base = data.pop("base", None)
    if base is None:
        return data
    base_path = path.parent / base if (path.parent / base).is_file() else resolve_config_path(base)
    merged = _read_yaml_with_bases(base_path, seen + (path,))
    for section, values in data.items():
        if isinstance(values, dict) and isinstance(merged.get(section), dict):
            merged[section].update(values)
        else:
            merged[section] = values
    return merged


def _merge(base: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    merged = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    for section, values in changes.items():
        if isinstance(values, dict) and isinstance(merged.get(section), dict):
            merged[section].update(values)
        else:
            merged[section] = values
    return merged


def config_from_dict(values: dict[str, Any], origin: str) -> PipelineConfig:
    """A `PipelineConfig` from nested `{section: {key: value}}` (missing keys take their defaults); any
    problem is one `UserError` naming `origin` and the key, with the closest valid key for a typo."""
    try:
        return PipelineConfig.model_validate(values)
    except ValidationError as error:
        raise UserError(f"{origin}: {_describe(error.errors()[0], values)}") from None


def _describe(error: Any, values: dict[str, Any]) -> str:
    loc = [str(part) for part in error["loc"]]
    sections = PipelineConfig.model_fields
    if error["type"] == "extra_forbidden" and len(loc) == 1:
        return f"unknown config section '{loc[0]}'{_suggest(loc[0], sections)}"
    if error["type"] == "extra_forbidden" and len(loc) == 2:
        keys = sections[loc[0]].annotation.model_fields  # type: ignore[union-attr]
        return f"unknown config key '{'.'.join(loc)}'{_suggest(loc[1], keys, prefix=loc[0] + '.')}"
    if error["type"] in ("model_type", "model_attributes_type") and len(loc) == 1:
        return f"section '{loc[0]}' must be a mapping of keys, got {values.get(loc[0])!r}"
    message = str(error["msg"]).replace("Input should be", "must be").removeprefix("Value error, ")
    if len(loc) >= 2 and error["type"] != "value_error":
        key = ".".join(loc[:2])
        default = sections[loc[0]].annotation.model_fields[loc[1]].default  # type: ignore[union-attr]
        return f"'{key}' {message} (default {_plain(default)!r}), got {error.get('input')!r}"
    return message


def _suggest(name: str, options: Any, prefix: str = "") -> str:
    close = difflib.get_close_matches(name, list(options), n=1)
    return f" (did you mean '{prefix}{close[0]}'?)" if close else f" (valid: {', '.join(options)})"


def load_config(name_or_path: str | None = None, overrides: list[str] | None = None) -> PipelineConfig:
    """Reads a config (file or packaged name; None: the defaults) and applies `section.key=value` overrides
    (values parsed as YAML). Errors name the file or the `--set` item."""
    values: dict[str, Any] = {}
    if name_or_path:
        path = resolve_config_path(name_or_path)
        values = _read_yaml_with_bases(path)
        config_from_dict(values, str(path))
    for item in overrides or []:
        key, sep, text = item.partition("=")
        section, dot, name = key.strip().partition(".")
        if not sep or not dot:
            raise UserError(f"--set {item!r}: expected section.key=value, e.g. detections.every=1")
        try:
            value = _number_as_number(yaml.safe_load(text))
        except yaml.YAMLError as error:
            raise UserError(f"--set {item!r}: the value is not valid YAML ({str(error).splitlines()[0]})") from None
        values = _merge(values, {section: {name: value}})
        config_from_dict(values, f"--set {item}")
    return config_from_dict(values, str(name_or_path or "defaults"))


def _number_as_number(value: Any) -> Any:
    """A number YAML 1.1 reads as text (``2e-2``, ``1E3``: no dot) as the float it writes; anything else as read."""
    if isinstance(value, str):
        try:
            number = float(value)
        except ValueError:
            return value
        if value.strip().lower() not in ("nan", "inf", "-inf", "+inf", "infinity", "-infinity"):
            return number
    return value


def detection_frame_stride(config: PipelineConfig) -> int:
    """Frames read per possible detection frame: `every` on the fixed schedule, 1 on the motion schedule
    (any frame may be due), e.g. for simulating detections only where the fusion can use them."""
    return config.detections.every if config.detections.schedule == "every" else 1
