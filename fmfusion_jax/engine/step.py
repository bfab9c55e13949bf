"""The map's update functions: the whole engine as a few jitted, pure `state -> state` steps.

The Python loop (`fmfusion_jax.pipeline`) calls, per frame:

- `integrate_frame`: global TSDF (every frame);
- `fuse_detections`: TSDF + association + instance integration + label fusion (detection frames);
- `refine`: removal of repeatedly missed instances and the online merge (on its schedule);
- `fuse_geometry`: instance-geometry fusion against the global surface (on its schedule);
- `finalize`: before export, geometry fusion and the post-processing 3D-IoU merge.

Each is traced once per `(MapConfig, FusionConfig)`; every shape comes from the configs, so a run never
recompiles. The state argument is donated: its buffers are reused for the result (without donation every
call would copy the whole voxel pool), so a state passed in must not be used again. All are vmappable
over a batch of independent maps (see `batched`).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from fmfusion_jax.engine import association, detections, label_fusion, maintenance, merge
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.detections import DetectionBatch
from fmfusion_jax.engine.instance_volume import (
    fuse_instance_geometry, instance_overlap_counts, instance_voxel_counts, integrate_instances,
    pixel_instances, remap_instances)
from fmfusion_jax.engine.state import MapState
from fmfusion_jax.engine.tsdf import integrate_tsdf


@dataclasses.dataclass(frozen=True)
class FusionConfig:
    """Static parameters of association, label fusion and refinement (paper / reference defaults)."""

    association_metric: str = "projection_overlap"  # or "iou"
    association_threshold: float = 0.5
    min_projected_pixels: float = 800.0  # full-resolution pixels for an instance to count as in view
    depth_low: float = 0.1  # a detection's pixels keep depth between these quantiles of its mask
    depth_high: float = 0.9
    label_mode: str = "additive"  # or "bayes"
    merge_similarity: float = 0.15
    merge_overlap: float = 0.4
    remove_missed: int = 5
    remove_min_voxels: int = 500
    post_merge_iou: float = 0.2
    post_merge_similarity: float = 0.1
    geometry_min_weight: float = 1.0  # global TSDF weight a voxel needs to support instances


class FrameInputs(NamedTuple):
    """One frame as arrays (built on the host by `frame_inputs`)."""

    depth: jax.Array  # float32[H, W] metres, 0 = invalid
    color: jax.Array  # uint8[H, W, 3] RGB
    T_world_camera: jax.Array  # float32[4, 4]
    intrinsics: jax.Array  # float32[4]: fx, fy, cx, cy
    frame_index: jax.Array  # int32[]


class FrameStats(NamedTuple):
    """What one detection frame did (scalars; the loop logs them)."""

    detections: jax.Array  # int32[]: valid detections fused
    matched: jax.Array  # int32[]: detections associated with existing instances
    created: jax.Array  # int32[]: new instances
    table_overflow: jax.Array  # int32[]: detections that found no free instance row
    in_view: jax.Array  # int32[]: instances in view


class RefineStats(NamedTuple):
    removed: jax.Array  # int32[]
    merged: jax.Array  # int32[]: instances merged into another
    dropped_cells: jax.Array  # int32[]: occupied cells left out of the overlap counts (capacity)


def _distribution(state: MapState, fusion: FusionConfig) -> jax.Array:
    return label_fusion.class_distribution(state.instances.label_evidence, fusion.label_mode)


@functools.partial(jax.jit, static_argnames=("config",), donate_argnames=("state",))
def integrate_frame(state: MapState, frame: FrameInputs, config: MapConfig) -> MapState:
    """Integrates one frame into the global TSDF (no detections)."""
    blocks = integrate_tsdf(state.blocks, frame.depth, frame.color, frame.T_world_camera, frame.intrinsics,
                            config)
    return state._replace(blocks=blocks, frame_index=frame.frame_index)


@functools.partial(jax.jit, static_argnames=("config", "fusion"), donate_argnames=("state",))
def fuse_detections(state: MapState, frame: FrameInputs, batch: DetectionBatch, likelihood: jax.Array,
                    config: MapConfig, fusion: FusionConfig) -> tuple[MapState, FrameStats]:
    """One detection frame: TSDF, projection, association, instance integration and label fusion.

    Args:
      state: the map.
      frame: the frame's depth, colour and pose.
      batch: `N` padded detections (`masks bool[N, H, W]`, `label_scores float32[N, O]`, `valid bool[N]`).
      likelihood: float32[O, C] label likelihood (a traced argument, so it can be differentiated or swapped).
    """
    state = integrate_frame(state, frame, config)
    table = state.instances
    n_max, k, stride = batch.valid.shape[0], config.instance_capacity, config.pixel_stride

    # Detections as one per-pixel image, with each mask's depth outliers removed (mask borders that
    # bleed onto the background would otherwise smear instances along the rays).
    det_image = detections.detection_pixel_image(batch.masks, batch.valid, stride)
    depth_s = frame.depth[::stride, ::stride]
    det_image = detections.filter_detection_depth(det_image, depth_s, n_max, fusion.depth_low, fusion.depth_high,
                                                  depth_max=config.depth_max)

    # Projection of the existing instances (what each pixel's surface voxel holds) and association.
    seen = pixel_instances(state.blocks, frame.depth, frame.T_world_camera, frame.intrinsics, config)
    counts = association.association_scores(det_image, seen, n_max, k)
    valid_det = batch.valid & (counts.det_area > 0)  # a mask may lose all its pixels to the depth filter
    scores = association.association_score_matrix(counts.intersection, counts.det_area, counts.inst_area,
                                                   fusion.association_metric)
    matched = association.match_detections(scores, valid_det, table.valid, fusion.association_threshold)
    assignment = association.assign_detections(matched, valid_det, table.valid)
    inst_for_det = assignment.instance_for_detection

    # Instance table: new rows, label fusion, statistics, missed counts.
    rows = maintenance.TableRows.of(table)
    rows = maintenance.reset_rows(rows._replace(valid=assignment.new_valid), assignment.created, frame.frame_index)
    fused_ok = valid_det & (inst_for_det >= 0)
    evidence = label_fusion.fuse_labels(rows.label_evidence, inst_for_det, batch.label_scores, likelihood,
                                        fused_ok, fusion.label_mode)
    histogram, observations = label_fusion.update_label_statistics(
        rows.open_label_histogram, rows.observations, inst_for_det, batch.label_scores, fused_ok)
    was_matched = maintenance.matched_instances(inst_for_det, fused_ok, k)
    in_view = maintenance.instances_in_view(counts.inst_area, table.valid, stride, fusion.min_projected_pixels)
    rows = rows._replace(
        label_evidence=evidence, open_label_histogram=histogram, observations=observations,
        missed=maintenance.update_missed(rows.missed, table.valid, in_view, was_matched),
        last_seen_frame=maintenance.mark_seen(rows.last_seen_frame, was_matched, frame.frame_index))
    table = table._replace(**rows._asdict(), overflow=table.overflow + assignment.overflow)

    # Instance volumes: every detection pixel votes for its instance in the voxel it sees.
    pixel_instance = association.instance_pixel_image(det_image, inst_for_det)
    blocks = integrate_instances(state.blocks, frame.depth, frame.T_world_camera, frame.intrinsics,
                                 pixel_instance, config)

    stats = FrameStats(
        detections=jnp.sum(fused_ok).astype(jnp.int32),
        matched=jnp.sum(fused_ok & ~assignment.is_new).astype(jnp.int32),
        created=jnp.sum(assignment.is_new).astype(jnp.int32),
        table_overflow=assignment.overflow.astype(jnp.int32),
        in_view=jnp.sum(in_view).astype(jnp.int32),
    )
    return state._replace(blocks=blocks, instances=table), stats


def _refresh_voxel_counts(state: MapState, config: MapConfig) -> MapState:
    counts = instance_voxel_counts(state.blocks, config).counts
    return state._replace(instances=state.instances._replace(voxel_count=counts))


def _apply_new_ids(state: MapState, rows: maintenance.TableRows, new_id: jax.Array, config: MapConfig) -> MapState:
    state = state._replace(blocks=remap_instances(state.blocks, new_id),
                           instances=state.instances._replace(**rows._asdict()))
    return _refresh_voxel_counts(state, config)


@functools.partial(jax.jit, static_argnames=("config", "fusion"), donate_argnames=("state",))
def refine(state: MapState, config: MapConfig, fusion: FusionConfig) -> tuple[MapState, RefineStats]:
    """Online refinement: remove repeatedly missed small instances, then merge over-segmentation.

    Merge test for all pairs at once (paper, Sec. IV-A): semantic similarity of the normalized
    distributions above `merge_similarity`, and more than `merge_overlap` of the smaller instance's
    voxels inside the larger one's inflated volume.
    """
    state = _refresh_voxel_counts(state, config)
    rows = maintenance.TableRows.of(state.instances)
    remove = maintenance.instances_to_remove(rows.missed, rows.voxel_count, rows.valid, fusion.remove_missed,
                                             fusion.remove_min_voxels)
    removal = maintenance.remove_instances(rows, remove)
    state = _apply_new_ids(state, removal.rows, removal.new_id, config)

    rows = maintenance.TableRows.of(state.instances)
    overlap = instance_overlap_counts(state.blocks, config, inflate=True)
    similarity = merge.semantic_similarity(_distribution(state, fusion))
    pairs = merge.merge_pairs(similarity, overlap.counts, rows.voxel_count, rows.valid, fusion.merge_similarity,
                              fusion.merge_overlap)
    representative = merge.merge_groups(pairs, rows.valid, rows.voxel_count)
    merged = merge.merge_instance_table(rows, representative, fusion.label_mode)
    n_before = jnp.sum(rows.valid)
    state = _apply_new_ids(state, merged.rows, merged.new_id, config)
    stats = RefineStats(removed=jnp.sum(remove).astype(jnp.int32),
                        merged=(n_before - jnp.sum(state.instances.valid)).astype(jnp.int32),
                        dropped_cells=overlap.dropped_cells)
    return state, stats


@functools.partial(jax.jit, static_argnames=("config", "fusion"), donate_argnames=("state",))
def fuse_geometry(state: MapState, config: MapConfig, fusion: FusionConfig) -> MapState:
    """Instance-geometry fusion: drop instance voxels the global surface does not support."""
    blocks = fuse_instance_geometry(state.blocks, config, fusion.geometry_min_weight)
    return _refresh_voxel_counts(state._replace(blocks=blocks), config)


@functools.partial(jax.jit, static_argnames=("config", "fusion"), donate_argnames=("state",))
def finalize(state: MapState, config: MapConfig, fusion: FusionConfig) -> tuple[MapState, RefineStats]:
    """Before export: geometry fusion, then the post-processing merge (3D IoU and similarity)."""
    state = fuse_geometry(state, config, fusion)
    rows = maintenance.TableRows.of(state.instances)
    overlap = instance_overlap_counts(state.blocks, config, inflate=False)
    similarity = merge.semantic_similarity(_distribution(state, fusion))
    pairs = merge.post_merge_pairs(similarity, overlap.counts, rows.voxel_count, rows.valid,
                                   fusion.post_merge_similarity, fusion.post_merge_iou)
    representative = merge.merge_groups(pairs, rows.valid, rows.voxel_count)
    merged = merge.merge_instance_table(rows, representative, fusion.label_mode)
    n_before = jnp.sum(rows.valid)
    state = _apply_new_ids(state, merged.rows, merged.new_id, config)
    stats = RefineStats(removed=jnp.zeros((), jnp.int32),
                        merged=(n_before - jnp.sum(state.instances.valid)).astype(jnp.int32),
                        dropped_cells=overlap.dropped_cells)
    return state, stats


def class_distribution(state: MapState, fusion: FusionConfig) -> jax.Array:
    """float32[K, C] normalized class distribution of every row (meaningful where `valid`)."""
    return _distribution(state, fusion)


def batched(step, **static):
    """A step vmapped over a leading batch axis of its array arguments (states, frames, detections).

    The likelihood is shared by the batch. Example::

        fuse = batched(fuse_detections, config=map_config, fusion=fusion_config)
        states, stats = fuse(states, frames, batches, likelihood)
    """
    fn = functools.partial(step, **static)
    if step is fuse_detections:
        return jax.jit(jax.vmap(fn, in_axes=(0, 0, 0, None)))
    return jax.jit(jax.vmap(fn))
