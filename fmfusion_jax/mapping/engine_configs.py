"""The one translator from the config schema (`PipelineConfig`) to the engine's configs (`MapConfig`,
`FusionConfig`): every engine knob's value comes from the schema, here.
"""

from __future__ import annotations

import logging
import os

import numpy as np

from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.engine import step
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import LabelSets, load_label_sets, load_likelihood, normalize_columns

log = logging.getLogger(__name__)


def build_map_config(
    config: PipelineConfig, bounds_min, bounds_max, height: int, width: int, label_sets: LabelSets | None = None
) -> MapConfig:
    """The engine's static sizes for a scene with these world bounds and image size, and these label sets (default:
    the packaged ones); a map that could never fit in this machine's memory is a UserError naming the knobs (before
    anything is allocated)."""
    label_sets = label_sets or load_label_sets()
    map_config = MapConfig.for_bounds(
        bounds_min,
        bounds_max,
        margin=config.tsdf.bounds_margin,
        voxel_size=config.tsdf.voxel_size,
        block_size=config.tsdf.block_size,
        sdf_trunc=config.tsdf.sdf_trunc,
        depth_max=config.dataset.depth_max,
        max_weight=config.tsdf.max_weight,
        block_capacity=config.tsdf.block_capacity,
        max_touched_blocks=config.tsdf.max_touched_blocks,
        image_height=height,
        image_width=width,
        pixel_stride=config.association.pixel_stride,
        instance_capacity=config.instances.capacity,
        instance_slots=config.instances.voxel_slots,
        num_classes=label_sets.num_classes,
        num_open_labels=len(label_sets.open_labels),
    )
    check_map_fits(map_config, config)
    return map_config


def physical_memory_bytes() -> int | None:
    """This machine's memory, or None where the system does not say."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def check_map_fits(map_config: MapConfig, config: PipelineConfig) -> None:
    """A UserError when the map's block index alone, or the map at its capacities, needs more than this machine's
    memory (a voxel size in the wrong unit would otherwise ask the runtime for petabytes)."""
    memory = physical_memory_bytes()
    if memory is None:
        return
    index = map_config.num_grid_blocks * 4
    if index > memory / 2 or map_config.memory_bytes() > memory:
        raise UserError(
            f"the map would need {map_config.memory_bytes() / 2**30:.3g} GiB (its block index over the scene "
            f"{index / 2**30:.3g} GiB: {map_config.grid_shape} blocks of {config.tsdf.block_size} voxels of "
            f"{config.tsdf.voxel_size} m), more than this machine's {memory / 2**30:.1f} GiB: raise tsdf.voxel_size "
            "(metres: 0.015625 is 1.5 cm) or lower tsdf.block_capacity / instances.capacity"
        )


def build_fusion_config(config: PipelineConfig, label_sets: LabelSets | None = None) -> step.FusionConfig:
    """The engine's fusion parameters from the schema (the floor class from `label_sets`, default: the packaged)."""
    lo, hi = config.detections.depth_percentiles
    return step.FusionConfig(
        association_metric=config.association.metric,
        association_threshold=config.association.threshold,
        association_rank=config.association.rank,
        min_projected_pixels=float(config.association.min_projected_pixels),
        depth_low=lo,
        depth_high=hi,
        label_mode=config.label_fusion.mode,
        merge_similarity=config.refinement.merge_similarity,
        merge_overlap=config.refinement.merge_overlap,
        remove_missed=config.refinement.remove_missed,
        remove_min_voxels=config.refinement.remove_min_voxels,
        post_merge_iou=config.export.post_merge_iou,
        post_merge_similarity=config.export.post_merge_similarity,
        contrary_vote_weight=config.instances.contrary_vote_weight,
        reunite_min_frames=config.refinement.reunite_min_frames,
        separate_min_frames=config.refinement.separate_min_frames,
        geometry_min_weight=config.refinement.geometry_min_weight,
        floor_up=UP_AXES[config.detections.floor_up_axis],
        floor_class=floor_class_index(label_sets or load_label_sets()),
        floor_band=config.detections.floor_band,
        floor_max_share=config.detections.floor_max_share,
    )


def fusion_likelihood(config: PipelineConfig) -> np.ndarray:
    """`(O, C)` the likelihood matrix that label fusion uses: `label_fusion.likelihood`, its columns normalized
    when `label_fusion.normalize_columns` (`labels.normalize_columns`)."""
    likelihood = load_likelihood(config.label_fusion.likelihood)
    return normalize_columns(likelihood) if config.label_fusion.normalize_columns else likelihood


def floor_class_index(label_sets: LabelSets) -> int:
    """The closed class whose detections keep their floor pixels (-1: the label sets have no floor)."""
    return label_sets.class_names.index("floor") if "floor" in label_sets.class_names else -1


#: `detections.floor_up_axis` as the engine's unit vector (None: the floor filter is off).
UP_AXES: dict[str, tuple[float, float, float] | None] = {
    "+x": (1.0, 0.0, 0.0),
    "-x": (-1.0, 0.0, 0.0),
    "+y": (0.0, 1.0, 0.0),
    "-y": (0.0, -1.0, 0.0),
    "+z": (0.0, 0.0, 1.0),
    "-z": (0.0, 0.0, -1.0),
    "none": None,
}
