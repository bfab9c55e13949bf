"""Pipeline configuration: nested dataclasses with the paper's defaults, read from YAML, overridable.

A YAML file may name a `base:` file (relative to itself) whose values it overrides. Any value can be
overridden on the command line as `--set section.key=value` (value parsed as YAML). Unknown sections or
keys are errors that name the closest valid key, so a typo never silently falls back to a default.
"""

from __future__ import annotations

import dataclasses
import difflib
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from fmfusion_jax.errors import UserError


@dataclasses.dataclass
class DatasetConfig:
    layout: str = "auto"            # scannet | scenenn | auto (detected from the folder)
    depth_scale: float = 1000.0     # depth png units per metre
    depth_max: float = 4.0          # m; farther depth is dropped (reference: 4.0)
    frame_stride: int = 1           # read every Nth frame
    max_frames: int | None = None   # stop after this many frames (None: all)


@dataclasses.dataclass
class TSDFConfig:
    voxel_size: float = 0.015625    # m; 4.0/256 as in the reference (paper: 1.5 cm)
    sdf_trunc: float = 0.04         # m; truncation distance
    block_size: int = 8             # voxels per block side (8^3 voxels, 12.5 cm blocks)
    block_capacity: int = 65536     # blocks in the pool (~14 KB each); a ScanNet room needs ~20-40k
    max_touched_blocks: int = 12288  # blocks integrated per frame (more are skipped and counted)
    max_weight: float = 255.0       # cap of the TSDF weight (keeps the map responsive)
    bounds_margin: float = 0.5      # m added around the scene bounds estimated from poses and depth


@dataclasses.dataclass
class DetectionConfig:
    schedule: str = "motion"        # motion: when the camera moved/turned enough | every: every Nth frame
    min_translation: float = 0.05   # m since the last detection frame (motion schedule)
    min_rotation: float = 5.0       # degrees since the last detection frame (motion schedule)
    sparse_motion: float = 0.5      # a sequence whose median step between frames is this share of the above is
                                    # subsampled in time: every frame is fused (motion schedule; 0: off)
    every: int = 10                 # every Nth frame (schedule `every`; paper: ScanNet 10, SceneNN 5)
    max_detections: int = 32        # detections per frame kept (highest scores first)
    min_mask_pixels: int = 1000     # smaller masks are ignored (reference Python: 1000, C++: 100)
    depth_percentiles: tuple[float, float] = (0.1, 0.9)  # keep mask depth between these quantiles


@dataclasses.dataclass
class AssociationConfig:
    metric: str = "projection_overlap"  # projection_overlap (|m∩r|/|r|, reference Python) | iou
    threshold: float = 0.5              # reference Python 0.5 (C++: IoU 0.3)
    pixel_stride: int = 2               # pixels sampled for projection, association and integration
    min_projected_pixels: int = 800     # an instance is "in view" above this many full-res pixels


@dataclasses.dataclass
class InstanceConfig:
    capacity: int = 1024            # instance table size K
    voxel_slots: int = 2            # instances one voxel can hold (overlapping instance volumes)
    contrary_vote_weight: float = 0.5  # a voxel seen outside its instance's mask while that instance is
                                    # detected loses this per pixel (0: hits alone, the paper's rule)


@dataclasses.dataclass
class LabelFusionConfig:
    mode: str = "additive"          # additive (paper's final equation) | bayes (multiplicative)
    likelihood: str = "statistical"  # statistical | manual | path to a 38x20 CSV


@dataclasses.dataclass
class RefinementConfig:
    enabled: bool = True            # merge, geometry fusion and removal (off: ablation C)
    merge_every: int = 1            # online merge every Nth detection frame
    merge_similarity: float = 0.15  # semantic similarity p_a . p_b above this
    merge_overlap: float = 0.4      # share of the smaller instance inside the larger, inflated
    geometry_fusion_every: int = 20  # detection frames (paper: 200 frames at every 10th: 20; SceneNN 60)
    remove_missed: int = 5          # remove instances missed this often while in view ...
    remove_min_voxels: int = 500    # ... when smaller than this many voxels (SceneNN 8 / 2000)
    reunite_min_frames: int = 2     # reunite b with a once a's detections covered b this often and at least
                                    # as often as b was detected itself, whatever the labels (0: off)
    separate_min_frames: int = 0    # never merge two instances while two detections of one frame showed them
                                    # apart this often and as often as one detection covered both (0: off;
                                    # off by default: split masks make it veto the reunion of parts)


@dataclasses.dataclass
class ExportConfig:
    min_weight: float = 2.0         # exported instance voxels need this slot weight (Kimera baseline: TSDF weight)
    min_slot_share: float = 0.5     # ... and this share of the voxel's strongest slot (0: any slot)
    structure_claims_vertices: bool = True  # wall and floor take part in the vertex transfer (then dropped),
                                    # so a floor vertex nearest to the floor is no object's
    post_merge_iou: float = 0.2     # post-processing merge: 3D IoU above this ...
    post_merge_similarity: float = 0.1  # ... and semantic similarity above this
    min_points: int = 200           # instances with fewer points are dropped
    support_observations: float = 3.0  # confidence = class probability x (1 - exp(-observations / this)),
                                    # so one-off instances rank low (0: class probability alone)
    transfer_radius: float = 0.08   # m; instance labels to mesh vertices by radius search
    transfer_neighbours: int = 8    # a vertex takes the instance of most of its nearest points (1: nearest)
    shower_curtain_radius: float = 2.0  # m; a curtain this close to a toilet/bathtub is a shower curtain
    curtain_by_context: bool = True  # ... and a shower curtain farther from them is a curtain (the matrix
                                    # cannot tell the two apart; false: the reference's first direction only)


@dataclasses.dataclass
class PipelineConfig:
    dataset: DatasetConfig = dataclasses.field(default_factory=DatasetConfig)
    tsdf: TSDFConfig = dataclasses.field(default_factory=TSDFConfig)
    detections: DetectionConfig = dataclasses.field(default_factory=DetectionConfig)
    association: AssociationConfig = dataclasses.field(default_factory=AssociationConfig)
    instances: InstanceConfig = dataclasses.field(default_factory=InstanceConfig)
    label_fusion: LabelFusionConfig = dataclasses.field(default_factory=LabelFusionConfig)
    refinement: RefinementConfig = dataclasses.field(default_factory=RefinementConfig)
    export: ExportConfig = dataclasses.field(default_factory=ExportConfig)

    def to_dict(self) -> dict[str, Any]:
        return _plain(dataclasses.asdict(self))

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return value


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


def _set_field(config: PipelineConfig, dotted_key: str, value: Any, origin: str) -> None:
    section_name, _, key = dotted_key.partition(".")
    sections = {f.name: f for f in dataclasses.fields(config)}
    if section_name not in sections:
        raise UserError(f"{origin}: unknown config section '{section_name}'{_suggest(section_name, sections)}")
    section = getattr(config, section_name)
    fields = {f.name: f for f in dataclasses.fields(section)}
    if key not in fields:
        raise UserError(f"{origin}: unknown config key '{dotted_key}'"
                        f"{_suggest(key, fields, prefix=section_name + '.')}")
    setattr(section, key, _coerce(value, getattr(section, key), dotted_key, origin))


def _coerce(value: Any, default: Any, key: str, origin: str) -> Any:
    """Checks a value against the type of the default, so `every: ten` fails early."""
    if default is None or value is None:
        return value
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
    elif isinstance(default, int):
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif isinstance(default, float):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif isinstance(default, str):
        return str(value)
    elif isinstance(default, tuple):
        if isinstance(value, (list, tuple)) and len(value) == len(default):
            return tuple(type(d)(v) for d, v in zip(default, value))
    raise UserError(f"{origin}: '{key}' must be like {default!r}, got {value!r}")


def _suggest(name: str, options: Any, prefix: str = "") -> str:
    close = difflib.get_close_matches(name, list(options), n=1)
    return f" (did you mean '{prefix}{close[0]}'?)" if close else f" (valid: {', '.join(options)})"


def load_config(name_or_path: str | None = None, overrides: list[str] | None = None) -> PipelineConfig:
    """Reads a config (file or packaged name; None: the defaults) and applies `key=value` overrides."""
    config = PipelineConfig()
    if name_or_path:
        path = resolve_config_path(name_or_path)
        for section, values in _read_yaml_with_bases(path).items():
            if not isinstance(values, dict):
                raise UserError(f"{path}: section '{section}' must be a mapping")
            for key, value in values.items():
                _set_field(config, f"{section}.{key}", value, str(path))
    for item in overrides or []:
        key, sep, text = item.partition("=")
        if not sep or "." not in key:
            raise UserError(f"--set {item!r}: expected section.key=value, e.g. detections.every=1")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError as error:
            raise UserError(f"--set {item!r}: the value is not valid YAML ({str(error).splitlines()[0]})") from None
        _set_field(config, key.strip(), value, f"--set {item}")
    validate_config(config)
    return config


def detection_frame_stride(config: PipelineConfig) -> int:
    """Frames read per possible detection frame: `every` on the fixed schedule, 1 on the motion schedule
    (any frame may be due), e.g. for simulating detections only where the fusion can use them."""
    return config.detections.every if config.detections.schedule == "every" else 1


def validate_config(config: PipelineConfig) -> None:
    """Range checks that would otherwise surface as wrong maps or shape errors deep inside JAX."""
    checks = [
        (config.label_fusion.mode in ("additive", "bayes"), "label_fusion.mode must be additive or bayes"),
        (config.association.metric in ("projection_overlap", "iou"),
         "association.metric must be projection_overlap or iou"),
        (0.0 < config.association.threshold <= 1.0, "association.threshold must be in (0, 1]"),
        (config.tsdf.voxel_size > 0 and config.tsdf.sdf_trunc > config.tsdf.voxel_size,
         "tsdf.sdf_trunc must exceed tsdf.voxel_size > 0"),
        (config.detections.every >= 1 and config.dataset.frame_stride >= 1, "strides must be >= 1"),
        (config.detections.schedule in ("motion", "every"), "detections.schedule must be motion or every"),
        (config.detections.min_translation >= 0 and config.detections.min_rotation >= 0,
         "detections.min_translation and min_rotation must be >= 0"),
        (config.detections.sparse_motion >= 0, "detections.sparse_motion must be >= 0"),
        (config.instances.capacity >= 2 and config.instances.voxel_slots >= 1, "instance capacities too small"),
        (config.instances.contrary_vote_weight >= 0, "instances.contrary_vote_weight must be >= 0"),
        (config.export.transfer_neighbours >= 1, "export.transfer_neighbours must be >= 1"),
        (config.refinement.reunite_min_frames >= 0 and config.refinement.separate_min_frames >= 0,
         "refinement.reunite_min_frames and separate_min_frames must be >= 0"),
        (config.tsdf.block_capacity >= 2 and config.tsdf.max_touched_blocks >= 1, "block capacities too small"),
        (config.tsdf.block_size >= 2 and config.tsdf.block_size % 2 == 0, "tsdf.block_size must be even and >= 2"),
        (config.tsdf.bounds_margin >= 0, "tsdf.bounds_margin must be >= 0 (metres added around the scene)"),
        (config.tsdf.max_weight > 0, "tsdf.max_weight must be > 0"),
        (config.association.pixel_stride >= 1, "association.pixel_stride must be >= 1"),
        (config.detections.max_detections >= 1 and config.detections.min_mask_pixels >= 0,
         "detections.max_detections must be >= 1 and min_mask_pixels >= 0"),
        (len(config.detections.depth_percentiles) == 2
         and 0.0 <= config.detections.depth_percentiles[0] < config.detections.depth_percentiles[1] <= 1.0,
         "detections.depth_percentiles must be [low, high] with 0 <= low < high <= 1"),
        (config.refinement.merge_every >= 1 and config.refinement.geometry_fusion_every >= 1,
         "refinement.merge_every and geometry_fusion_every must be >= 1 (detection frames)"),
        (config.export.transfer_radius > 0 and config.export.min_points >= 0,
         "export.transfer_radius must be > 0 and export.min_points >= 0"),
    ]
    for ok, message in checks:
        if not ok:
            raise UserError(f"invalid config: {message}")
