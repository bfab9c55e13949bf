"""The map's update functions: the whole engine as a few jitted, pure `state -> state` steps.

`engine.frame.fuse_frame` calls, per frame:

- `integrate_frame`: global TSDF (every frame);
- `fuse_detections`: TSDF + association + instance integration + label fusion (detection frames);
- `refine`: removal of repeatedly missed instances and the online merge (on its schedule);
- `fuse_and_refine`: `fuse_detections` then `refine`, one executable (off the CPU, a detection frame the merge is
  due after);
- `fuse_geometry`: instance-geometry fusion against the global surface (on its schedule);
- `finalize`: before export, geometry fusion and the post-processing 3D-IoU merge.

Each is traced once per `(MapConfig, FusionConfig)`; every shape comes from the configs, so a run never
recompiles. `refine` and `finalize` are thin wrappers of one jitted `_merge_step` (their thresholds are
traced values), and `finalize` reuses the compiled `fuse_geometry`: nothing is compiled at the end of a
run. The state argument is donated: its buffers are reused for the result (without donation every
call would copy the whole voxel pool), so a state passed in must not be used again. All are vmappable
over a batch of independent maps (`engine.frame.fuse_frames`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from fmfusion_jax.engine import _geometry, association, detections, label_fusion, maintenance, merge, occupied_cells, support
from fmfusion_jax.engine.cell_edits import fuse_cells, remap_cells
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.detections import DetectionBatch
from fmfusion_jax.engine.instance_volume import integrate_instances_unjitted, pixel_cells, pixel_instance_slots, pixel_voxels
from fmfusion_jax.engine.occupied_cells import census as occupied_census
from fmfusion_jax.engine.saved_steps import saved_step
from fmfusion_jax.engine.state import InstanceTable, MapState, VoxelBlocks
from fmfusion_jax.engine.tsdf import integrate_tsdf

#: Fields of `FusionConfig` that choose code paths (static: a change compiles another step); every other
#: field is a threshold, traced (a change reuses the compiled step, and the thresholds can be differentiated
#: or swept without recompiling).
FUSION_MODES = (
    "association_metric",
    "association_rank",
    "label_mode",
    "contrary_vote_weight",
    "separate_min_frames",
    "floor_up",
    "floor_class",
)


@functools.partial(
    jax.tree_util.register_dataclass,
    data_fields=[
        "association_threshold",
        "min_projected_pixels",
        "depth_low",
        "depth_high",
        "merge_similarity",
        "merge_overlap",
        "remove_missed",
        "remove_min_voxels",
        "post_merge_iou",
        "post_merge_similarity",
        "geometry_min_weight",
        "reunite_min_frames",
        "floor_band",
        "floor_max_share",
    ],
    meta_fields=list(FUSION_MODES),
)
@dataclasses.dataclass(frozen=True, kw_only=True)
class FusionConfig:
    """Parameters of association, label fusion and refinement. No defaults here: every value comes from the config
    schema (`fmfusion_jax.config`, through `mapping.engine_configs.build_fusion_config`), where each knob has its one
    default.

    A pytree: the modes (`FUSION_MODES`) are static, the thresholds are leaves, traced by the jitted steps
    that take it as an ordinary argument (`fuse_detections`, `fuse_geometry`, `refine`, `finalize`).
    """

    association_metric: str  # "projection_overlap" or "iou"
    association_threshold: float
    association_rank: str  # "score" (the metric's) or "iou": the order in which the pairs above the threshold match
    min_projected_pixels: float  # full-resolution pixels for an instance to count as in view
    depth_low: float  # a detection's pixels keep depth between these quantiles of its mask
    depth_high: float
    label_mode: str  # "additive" or "bayes"
    merge_similarity: float
    merge_overlap: float
    remove_missed: int
    remove_min_voxels: int
    post_merge_iou: float
    post_merge_similarity: float
    geometry_min_weight: float  # global TSDF weight a voxel needs to support instances
    # Weight of a contrary vote: a pixel that sees an instance's voxel outside the mask of that instance's
    # detection in the same frame (0: membership by hits alone, the paper's rule). See `instance_volume`.
    # Static: 0 leaves the contrary-vote scatters out of the compiled step.
    contrary_vote_weight: float
    # Reunite instance b with a when b was covered by a's detections in at least this many detection frames
    # and in at least as many as b was detected itself (0: off, the paper's merge tests alone).
    reunite_min_frames: int
    # Never merge a and b while two different detections of one frame were fused into them in at least this
    # many frames and at least as often as one detection covered both (0: off, the paper's tests alone).
    # Static: 0 leaves the separation counts out of the compiled steps.
    separate_min_frames: int
    # The floor filter (`engine.support`): the world's up axis (a unit vector; None: off), the pixels of a
    # detection on the floor (up-facing, within `floor_band` m above it) are not the object's, and a detection
    # with more than `floor_max_share` of its pixels there is dropped, unless its labels favour `floor_class`.
    floor_up: tuple[float, float, float] | None
    floor_class: int
    floor_band: float
    floor_max_share: float


class FrameInputs(NamedTuple):
    """One frame as arrays (built on the host by `frame_inputs` as NumPy arrays; `MapBuilder` puts them on the device)."""

    depth: jax.Array | np.ndarray  # float32[H, W] metres, 0 = invalid
    color: jax.Array | np.ndarray  # uint8[H, W, 3] RGB
    T_world_camera: jax.Array | np.ndarray  # float32[4, 4]
    intrinsics: jax.Array | np.ndarray  # float32[4]: fx, fy, cx, cy
    frame_index: jax.Array | np.ndarray  # int32[]


class FrameStats(NamedTuple):
    """What one detection frame did (scalars; the loop logs them)."""

    detections: jax.Array  # int32[]: valid detections fused
    matched: jax.Array  # int32[]: detections associated with existing instances
    created: jax.Array  # int32[]: new instances
    table_overflow: jax.Array  # int32[]: detections that found no free instance row
    in_view: jax.Array  # int32[]: instances in view
    instances: jax.Array  # int32[]: live instance rows after the frame
    blocks: jax.Array  # int32[]: allocated pool blocks after the frame


class RefineStats(NamedTuple):
    removed: jax.Array  # int32[]
    merged: jax.Array  # int32[]: instances merged into another
    dropped_cells: jax.Array  # int32[]: occupied cells left out of the overlap counts (capacity)


@saved_step(static_argnames=("config",), donate_argnames=("state",))
def integrate_frame(state: MapState, frame: FrameInputs, config: MapConfig) -> MapState:
    """Integrates one frame into the global TSDF (no detections)."""
    blocks = integrate_tsdf(state.blocks, frame.depth, frame.color, frame.T_world_camera, frame.intrinsics, config)
    return state._replace(blocks=blocks, frame_index=jnp.asarray(frame.frame_index, jnp.int32))


def call_stage(name: str, stage: Callable[..., Any], *args: Any) -> Any:
    """The plain `run` hook of `detection_frame`: calls the stage (inside a jit it is traced into the caller)."""
    del name
    return stage(*args)


def detection_frame(
    state: MapState,
    frame: FrameInputs,
    batch: DetectionBatch,
    likelihood: jax.Array,
    config: MapConfig,
    fusion: FusionConfig,
    run: Callable[..., Any] = call_stage,
) -> tuple[MapState, FrameStats]:
    """The stages of one detection frame, in their order (the one place it is written): TSDF, the detection
    image, projection, association, label fusion on the table, instance votes into the voxels.

    `run(name, stage, *args)` calls each stage (names: `DETECTION_STAGES`, and `statistics`); the default calls
    it, so that `fuse_detections` jits the whole frame as one function, and `fmfusion bench` passes a hook that
    runs each stage as its own timed jit.
    """
    state = run("tsdf", integrate_frame, state, frame, config)
    det_image, up_heights = run("detections", detection_image, frame, batch, likelihood, state.blocks.up_heights, config, fusion)
    state = state._replace(blocks=state.blocks._replace(up_heights=up_heights))
    seen = run("projection", project_instances, state.blocks, frame, config)
    matches = run("association", associate, det_image, seen, batch.valid, state.instances.valid, config, fusion)
    table, update = run(
        "label_fusion", fuse_table, state.instances, matches, batch.label_scores, likelihood, frame.frame_index, config, fusion
    )
    blocks, table = run(
        "integration",
        integrate_instance_votes,
        state.blocks,
        table,
        frame,
        det_image,
        matches.assignment.instance_for_detection,
        config,
        fusion,
    )
    stats = run("statistics", frame_stats, matches, update, table, blocks)
    return state._replace(blocks=blocks, instances=table), stats


#: The stages of `detection_frame`, in order (the names its `run` hook is given, and the bench's timing keys).
DETECTION_STAGES = ("tsdf", "detections", "projection", "association", "label_fusion", "integration")


@saved_step(static_argnames=("config",), donate_argnames=("state",))
def fuse_detections(
    state: MapState, frame: FrameInputs, batch: DetectionBatch, likelihood: jax.Array, config: MapConfig, fusion: FusionConfig
) -> tuple[MapState, FrameStats]:
    """One detection frame (`detection_frame`) as one jit, so XLA fuses across the stages.

    Args:
      state: the map.
      frame: the frame's depth, colour and pose.
      batch: `N` padded detections (`masks bool[N, H, W]`, `label_scores float32[N, O]`, `valid bool[N]`).
      likelihood: float32[O, C] label likelihood (a traced argument, so it can be differentiated or swapped).
    """
    return detection_frame(state, frame, batch, likelihood, config, fusion)


# --------------------------------------------------------------------------------------------------
# The stages of `detection_frame` (pure, unjitted: traced inside `fuse_detections`, or jitted alone by the bench).

#: `detection_image` value of a pixel inside a mask whose depth filter dropped it: neither the detection's
#: pixel nor evidence against other instances.
FILTERED_PIXEL = -2


def detection_image(
    frame: FrameInputs,
    batch: DetectionBatch,
    likelihood: jax.Array,
    up_heights: jax.Array,
    config: MapConfig,
    fusion: FusionConfig,
) -> tuple[jax.Array, jax.Array]:
    """int32[Hs, Ws]: the detection each subsampled pixel belongs to (-1 none), and the floor histogram
    `up_heights` with this frame's samples.

    Removed from the masks, in this order (removed pixels are `FILTERED_PIXEL`): with the floor filter on
    (`fusion.floor_up`), the pixels on the floor, or every pixel of a detection that lies mostly on it (a box
    around a bed whose mask is the rug in front of it), except for detections whose labels say floor
    (`engine.support`); then each mask's depth outliers (mask borders that bleed onto the background would
    otherwise smear instances along the rays)."""
    stride = config.pixel_stride
    image_shape = (config.image_height, config.image_width)
    raw = detections.batch_pixel_image(batch, image_shape, stride)
    kept = raw
    if fusion.floor_up is not None:
        samples = support.surface_samples(frame.depth, frame.T_world_camera, frame.intrinsics, fusion.floor_up, config)
        up_heights = support.add_heights(up_heights, samples)
        on_floor = support.floor_pixels(samples, support.floor_height(up_heights), fusion.floor_band)
        says_floor = jnp.argmax(jnp.asarray(batch.label_scores) @ likelihood, axis=1) == fusion.floor_class
        kept = support.filter_floor_pixels(raw, on_floor, says_floor, fusion.floor_max_share, FILTERED_PIXEL)
    kept = detections.filter_detection_depth(
        kept,
        frame.depth[::stride, ::stride],
        batch.valid.shape[0],
        fusion.depth_low,
        fusion.depth_high,
        depth_max=config.depth_max,
    )
    # computed once: association, the pixel instance image and the votes all read it
    return _geometry.materialize(jnp.where((raw >= 0) & (kept < 0), FILTERED_PIXEL, kept)), up_heights


def project_instances(blocks: VoxelBlocks, frame: FrameInputs, config: MapConfig) -> list[jax.Array]:
    """S slots of int32[Hs, Ws]: the existing instances at the surface each subsampled pixel sees, strongest
    first (-1 padded; `instance_volume.pixel_instances` stacked)."""
    return pixel_instance_slots(blocks, frame.depth, frame.T_world_camera, frame.intrinsics, config)


class Matches(NamedTuple):
    """The association of a frame's `N` detections with the `K` table rows."""

    counts: association.AssociationCounts  # pixel counts: intersection [N, K], det_area [N], inst_area [K]
    valid_det: jax.Array  # bool[N]: valid detections that kept pixels after the depth filter
    assignment: association.Assignment  # row of each detection (matched or new), the new valid rows


def associate(
    det_image: jax.Array,
    seen: list[jax.Array],
    det_valid: jax.Array | np.ndarray,
    inst_valid: jax.Array,
    config: MapConfig,
    fusion: FusionConfig,
) -> Matches:
    """Projection-overlap association of the detections (`det_valid bool[N]`) with the live rows
    (`inst_valid bool[K]`) seen at the pixels (`project_instances`), and new rows for the unmatched ones."""
    counts = association.association_counts(det_image, seen, det_valid.shape[0], config.instance_capacity)
    valid_det = (counts.det_area > 0) & det_valid  # a mask may lose all its pixels to the depth filter
    scores = association.association_score_matrix(
        counts.intersection, counts.det_area, counts.inst_area, fusion.association_metric
    )
    rank = None
    if fusion.association_rank == "iou" and fusion.association_metric != "iou":
        rank = association.association_score_matrix(counts.intersection, counts.det_area, counts.inst_area, "iou")
    matched = association.match_detections(scores, valid_det, inst_valid, fusion.association_threshold, rank=rank)
    return Matches(counts, valid_det, association.assign_detections(matched, valid_det, inst_valid))


class TableUpdate(NamedTuple):
    """What `fuse_table` did, for the frame's statistics."""

    fused: jax.Array  # bool[N]: detections fused into a row
    in_view: jax.Array  # bool[K]: live rows (before this frame) in view


def fuse_table(
    table: InstanceTable,
    matches: Matches,
    label_scores: jax.Array | np.ndarray,
    likelihood: jax.Array,
    frame_index: jax.Array | np.ndarray,
    config: MapConfig,
    fusion: FusionConfig,
) -> tuple[InstanceTable, TableUpdate]:
    """The instance table after the frame: new rows, label fusion (`label_scores float32[N, O]`),
    label statistics and missed counts."""
    assignment, k = matches.assignment, config.instance_capacity
    inst_for_det = assignment.instance_for_detection
    rows = maintenance.TableRows.of(table)
    rows = maintenance.reset_rows(rows._replace(valid=assignment.new_valid), assignment.created, frame_index)
    fused_ok = matches.valid_det & (inst_for_det >= 0)
    evidence = label_fusion.fuse_labels(rows.label_evidence, inst_for_det, label_scores, likelihood, fused_ok, fusion.label_mode)
    histogram, observations = label_fusion.update_label_statistics(
        rows.open_label_histogram, rows.observations, inst_for_det, label_scores, fused_ok
    )
    was_matched = maintenance.matched_instances(inst_for_det, fused_ok, k)
    in_view = maintenance.instances_in_view(
        matches.counts.inst_area, table.valid, config.pixel_stride, fusion.min_projected_pixels
    )
    rows = rows._replace(
        label_evidence=evidence,
        open_label_histogram=histogram,
        observations=observations,
        missed=maintenance.update_missed(rows.missed, table.valid, in_view, was_matched),
        last_seen_frame=maintenance.mark_seen(rows.last_seen_frame, was_matched, frame_index),
    )
    covered = count_covered(table.covered, matches, fused_ok, in_view & ~was_matched, fusion.association_threshold)
    # the separation counts only serve the cannot-link veto: not kept (and not costed) while it is off
    separated = count_separated(table.separated, inst_for_det, fused_ok) if fusion.separate_min_frames > 0 else table.separated
    table = table._replace(**rows._asdict(), covered=covered, separated=separated, overflow=table.overflow + assignment.overflow)
    return table, TableUpdate(fused_ok, in_view)


def count_separated(separated: jax.Array, instance_for_detection: jax.Array, fused: jax.Array) -> jax.Array:
    """`separated int32[K, K]` plus this frame: +1 at (a, b) and (b, a) for every two detections of the frame
    fused (`fused bool[N]`) into different instances a and b. One scatter of N^2 updates."""
    k = separated.shape[0]
    inst = jnp.where(fused, instance_for_detection, -1)
    a, b = inst[:, None], inst[None, :]
    pair = (a >= 0) & (b >= 0) & (a != b)
    rows = jnp.where(pair, a, k).reshape(-1)
    cols = jnp.where(pair, b, k).reshape(-1)
    return jnp.asarray(separated).at[rows, cols].add(pair.reshape(-1).astype(separated.dtype), mode="drop")


def count_covered(covered: jax.Array, matches: Matches, fused: jax.Array, candidates: jax.Array, threshold: float) -> jax.Array:
    """`covered int32[K, K]` plus this frame: +1 at (a, b) when more than `threshold` of instance b's projection
    lies in the mask of a detection fused into a (`fused bool[N]`), b a `candidate` (`bool[K]`: in view, not
    detected itself) other than a. One row scatter of the N detections."""
    counts = matches.counts
    k = covered.shape[0]
    inst_for_det = matches.assignment.instance_for_detection
    area = counts.inst_area.astype(jnp.float32)[None, :]
    share = counts.intersection.astype(jnp.float32) / jnp.where(area > 0, area, 1.0)
    cover = (share > threshold) & candidates[None, :] & (jnp.arange(k)[None, :] != inst_for_det[:, None])
    return jnp.asarray(covered).at[jnp.where(fused, inst_for_det, k)].add(cover.astype(covered.dtype), mode="drop")


def integrate_instance_votes(
    blocks: VoxelBlocks,
    table: InstanceTable,
    frame: FrameInputs,
    det_image: jax.Array,
    instance_for_detection: jax.Array,
    config: MapConfig,
    fusion: FusionConfig,
) -> tuple[VoxelBlocks, InstanceTable]:
    """Instance volumes: every detection pixel votes for its row (`instance_for_detection int32[N]`) in the
    voxel it sees; with `fusion.contrary_vote_weight`, every pixel also votes against the instances detected
    in this frame whose voxel it sees outside their mask.

    The table's kept census (`occupied_cells.KeptCensus`) and the blocks' `instance_bits` follow the votes:
    the cells they touch are read before, the votes report which cells they changed, and those are counted out
    (as read before) and in (as read after) (a census that cannot be kept is never valid: its update is wasted,
    but cheap). Returns `(blocks, table)`.
    """
    pixel_instance = association.instance_pixel_image(det_image, instance_for_detection)
    k = config.instance_capacity
    detected = jnp.zeros((k + 1,), bool).at[jnp.where(instance_for_detection >= 0, instance_for_detection, k)].set(True)[:k]
    voxels = pixel_voxels(blocks, frame.depth, frame.T_world_camera, frame.intrinsics, config)
    cells = pixel_cells(voxels)
    old_entries = occupied_cells.gather_cell_ids(occupied_cells.pool_cell_ids(blocks), cells)
    blocks, changed = integrate_instances_unjitted(
        blocks,
        frame.depth,
        frame.T_world_camera,
        frame.intrinsics,
        pixel_instance,
        config,
        detected,
        det_image == FILTERED_PIXEL,
        fusion.contrary_vote_weight,
        old_entries,  # the votes read their ids there: XLA then reads the cells before writing in place
        voxels,
        report_changes=True,
    )
    kept, blocks = occupied_cells.census_after_votes(
        occupied_cells.KeptCensus.of(table), blocks, cells, old_entries, changed, config
    )
    return blocks, table._replace(**kept.fields())


def frame_stats(matches: Matches, update: TableUpdate, table: InstanceTable, blocks: VoxelBlocks) -> FrameStats:
    """The frame's counts (the loop logs them; the Mapper's growth check reads the map's sizes after it)."""
    assignment = matches.assignment
    return FrameStats(
        detections=jnp.sum(update.fused).astype(jnp.int32),
        matched=jnp.sum(update.fused & ~assignment.is_new).astype(jnp.int32),
        created=jnp.sum(assignment.is_new).astype(jnp.int32),
        table_overflow=assignment.overflow.astype(jnp.int32),
        in_view=jnp.sum(update.in_view).astype(jnp.int32),
        instances=jnp.sum(table.valid).astype(jnp.int32),
        blocks=jnp.asarray(blocks.num_blocks, jnp.int32),
    )


def _apply_new_ids(blocks, census, new_id: jax.Array, config: MapConfig, counts, kept, listed_ok):
    """Renames the instance ids in the voxels (`remap_instances`); returns `(blocks, voxel counts, kept)`.

    `counts` are the voxel counts before the renaming (complete when `census.dropped_cells` is 0), and
    `census` the pass that counted them, whose list of the occupied cells is used when `listed_ok`. The pass
    costs nothing when no id held by a voxel changes (its loops run zero times), half of the refinements
    on scene0000_00; otherwise it rewrites only the cells holding a changed id, brings the kept census
    up to date, and derives the new counts from the old ones: changed ids drop to 0, and a
    representative gains the voxels of its merged instances that it did not hold. With an incomplete
    census (cell capacity exceeded) the counts are recounted instead, as the old recount did.
    """
    k = new_id.shape[0]
    changed = new_id != jnp.arange(k, dtype=new_id.dtype)
    can_drop = config.cell_capacity < blocks.instance_id.shape[0] * blocks.instance_id.shape[1] // 8  # static
    complete = (census.dropped_cells == 0) if can_drop else jnp.asarray(True)
    needed = jnp.any(changed & (counts > 0)) | ~complete
    listed = None
    if census.cells.shape[0]:  # the census' list of the occupied cells, unless there were too many
        listed = (
            census.cells,
            census.tags,
            census.occupied,
            (census.occupied <= config.cell_list_capacity) & complete & listed_ok,
        )
    # a no-op unless needed; without the census' list, it visits the blocks whose bits name a changed id
    blocks, gained, kept = remap_cells(blocks, new_id, config, active=needed, listed=listed, kept=kept, held=counts > 0)
    updated = jnp.where(changed, 0, counts) + gained
    if can_drop:
        updated = jax.lax.cond(complete, lambda: updated, lambda: occupied_census(blocks, config).counts)
    return blocks, updated, kept


class _MergeParams(NamedTuple):
    """Traced parameters of `_merge_step`, so that `refine` and `finalize` share one compiled step
    (host scalars, traced arrays inside the jit)."""

    final: ArrayLike  # bool[]: the final merge (plain overlap, 3D IoU, no removal) instead of the online one
    remove_missed: ArrayLike  # int32[]
    remove_min_voxels: ArrayLike  # int32[]
    similarity: ArrayLike  # float32[]: semantic similarity threshold
    overlap: ArrayLike  # float32[]: overlap ratio (online) or 3D IoU (final) threshold
    reunite: ArrayLike  # int32[]: `FusionConfig.reunite_min_frames` (0: off)
    separate: ArrayLike  # int32[]: `FusionConfig.separate_min_frames` (0: off)


@saved_step(static_argnames=("config", "label_mode", "veto"), donate_argnames=("state",))
def _merge_step(
    state: MapState, params: _MergeParams, config: MapConfig, label_mode: str, veto: bool
) -> tuple[MapState, RefineStats]:
    """Removal and merge (online, or the final post-processing merge), see `refine` and `finalize`.

    Online, the voxel counts and overlaps are the census kept in the table (`occupied_cells.KeptCensus`),
    which the steps that change ids keep up to date; the removal is applied to the voxels first (a renaming
    that visits the removed instances' blocks and updates the census), then the merge is decided on the
    census after it and applied by a second renaming. Each renaming only runs when an id held by a voxel
    changes, and visits the blocks whose `instance_bits` name a changed id.

    Without a valid kept census (the first merge step, a loaded map, and the final merge, which needs plain
    overlaps), one pass over the voxels counts them (online: the census then kept); the removal and the
    merge are then decided on the table and applied to the voxels together, in one renaming. This decides
    exactly as removing (rename and recount), then counting the overlaps and merging (rename and recount)
    would:
    - the removal renames no kept id, so the kept ids' counts are unchanged and the removed ids' are 0;
    - the overlaps after the removal are those of the census except in the removed ids' rows and
      columns (which the pair tests ignore: the rows are invalid) and in (inflated) cells with more than
      `overlap_ids_per_cell` distinct ids, where a removed id may have been among the largest: when a
      removed id held voxels and such cells exist, the overlaps are recounted with the removed ids
      masked out (a second pass, in removal frames only);
    - the voxel counts after the merge follow from those before (see `_apply_new_ids`).

    `veto` (static: `separate_min_frames > 0`) turns on the cannot-link veto and the folding of its
    separation counts (two K x K passes that are skipped while it is off).
    """
    blocks = state.blocks
    final = jnp.asarray(params.final, bool)
    k = config.instance_capacity
    # The online merge reads the kept census when it is valid; otherwise (and for the final merge, which
    # needs plain overlaps) one pass over the voxels counts it, the occupied cells listed for the renaming.
    # A census that cannot be kept (`census_can_be_kept`, static) is never made valid.
    kept = occupied_cells.KeptCensus.of(state.instances)
    use_kept = kept.valid & ~final
    counted = blocks._replace(num_blocks=jnp.where(use_kept, 0, blocks.num_blocks))  # zero trips when kept
    census = occupied_census(counted, config, final, list_cells=True)
    counts = jnp.where(use_kept, kept.counts, census.counts)
    rows = maintenance.TableRows.of(state.instances)
    remove = (
        maintenance.instances_to_remove(rows.missed, counts, rows.valid, params.remove_missed, params.remove_min_voxels) & ~final
    )
    rows = maintenance.remove_instances(rows._replace(voxel_count=counts), remove).rows
    keep = rows.valid  # the ids that stay in the voxels (the renaming deletes every other id)
    rows = rows._replace(voxel_count=jnp.where(keep, counts, 0))
    removes_voxels = jnp.any((counts > 0) & ~keep)
    # With the kept census the removal is applied first (a renaming of the removed instances' blocks): the
    # census is then exactly that of the voxels after the removal, as the merge test needs.
    removal_id = jnp.where(keep, jnp.arange(k, dtype=jnp.int32), -1)
    blocks, _, kept = remap_cells(blocks, removal_id, config, active=use_kept & removes_voxels, kept=kept, held=counts > 0)
    counts = jnp.where(use_kept, kept.counts, counts)
    census_overlap = jnp.where(use_kept, kept.overlap, census.overlap)
    census_overfull = jnp.where(use_kept, kept.overfull, census.overfull)
    # kept as it was, or (online) the census just counted; the final merge leaves an invalid one invalid
    counted_now = occupied_cells.kept_from_census(census, occupied_cells.census_can_be_kept(config))
    kept = jax.tree_util.tree_map(lambda a, b: jnp.where(use_kept | final, a, b), kept, counted_now)

    def recount():
        again = occupied_census(blocks, config, final, keep)
        return again.overlap, again.overfull

    def as_counted():  # the removed ids' rows and columns are left in: the pair tests mask invalid rows
        return census_overlap, census_overfull

    # Counted by the pass: the overlaps after the removal are the census' except in cells with more ids than
    # the overlap keeps, where a removed id may have been among those kept: then they are counted again.
    redo = ~use_kept & removes_voxels & (census_overfull > 0)
    overlap, overfull = jax.lax.cond(redo, recount, as_counted)

    similarity = merge.semantic_similarity(label_fusion.class_distribution(rows.label_evidence, label_mode))
    test = (similarity, overlap, rows.voxel_count, rows.valid, params.similarity, params.overlap)
    pairs = jax.lax.cond(final, merge.post_merge_pairs, merge.merge_pairs, *test)
    table = state.instances
    pairs = pairs | merge.reunion_pairs(table.covered, rows.observations, rows.valid, params.reunite)
    if veto:
        pairs = pairs & ~merge.separated_pairs(table.separated, table.covered, params.separate)
    representative = merge.merge_groups(pairs, rows.valid, rows.voxel_count)
    merged = merge.merge_instance_table(rows, representative, label_mode)
    # merged.new_id is -1 for the removed rows too: one renaming applies the removal and the merge
    blocks, voxel_count, kept = _apply_new_ids(blocks, census, merged.new_id, config, counts, kept, ~use_kept)
    covered = merge.fold_pair_counts(table.covered, merged.new_id, table.valid)
    separated = merge.fold_pair_counts(table.separated, merged.new_id, table.valid) if veto else table.separated
    table = table._replace(
        **merged.rows._replace(voxel_count=voxel_count)._asdict(), **kept.fields(), covered=covered, separated=separated
    )
    stats = RefineStats(
        removed=jnp.sum(remove).astype(jnp.int32),
        merged=(jnp.sum(rows.valid) - jnp.sum(table.valid)).astype(jnp.int32),
        dropped_cells=census.dropped_cells + overfull,
    )
    return state._replace(blocks=blocks, instances=table), stats


def _scalar(value, dtype):
    """A threshold as an argument of a jitted step: a NumPy scalar for a Python number (no dispatch on the
    host, as `jnp.asarray` costs per call), itself when traced or already an array."""
    return jnp.asarray(value, dtype) if isinstance(value, jax.Array) else np.asarray(value, dtype)


def _online_params(fusion: FusionConfig) -> _MergeParams:
    """The online merge's `_MergeParams` (see `FusionConfig` for each threshold)."""
    return _MergeParams(
        final=np.bool_(False),
        remove_missed=_scalar(fusion.remove_missed, jnp.int32),
        remove_min_voxels=_scalar(fusion.remove_min_voxels, jnp.int32),
        similarity=_scalar(fusion.merge_similarity, jnp.float32),
        overlap=_scalar(fusion.merge_overlap, jnp.float32),
        reunite=_scalar(fusion.reunite_min_frames, jnp.int32),
        separate=_scalar(fusion.separate_min_frames, jnp.int32),
    )


def _once_per_config(unhashable):
    """Decorator: `make(fusion)` computed once per `FusionConfig` of plain numbers (cached on the config); for one
    that cannot be hashed (array or traced thresholds: a sweep, a vmapped batch, a gradient), `unhashable(fusion)`
    on every call."""

    def decorate(make):
        cached = functools.lru_cache(maxsize=16)(make)

        @functools.wraps(make)
        def get(fusion: FusionConfig):
            try:
                return cached(fusion)
            except TypeError:
                return unhashable(fusion)

        return get

    return decorate


@_once_per_config(unhashable=lambda fusion: fusion)
def fusion_on_device(fusion: FusionConfig) -> FusionConfig:
    """`fusion` with its thresholds put on the device once per config (weak types kept: the same compiled
    steps). Passed as Python numbers, its twelve thresholds are converted on every call of a jitted step
    (~0.5 ms each call of `fuse_detections` on the CPU). Array thresholds pass as they are."""
    return jax.device_put(fusion)


@_once_per_config(unhashable=_online_params)
def _online_params_on_device(fusion: FusionConfig) -> _MergeParams:
    """`_online_params(fusion)`, put on the device once per config: sent with every call, seven host scalars
    cost the merge step's call ~0.3 ms."""
    return jax.device_put(_online_params(fusion))


def refine(state: MapState, config: MapConfig, fusion: FusionConfig) -> tuple[MapState, RefineStats]:
    """Online refinement: remove repeatedly missed small instances, then merge over-segmentation.

    Merge test for all pairs at once (paper, Sec. IV-A): semantic similarity of the normalized
    distributions above `merge_similarity`, and more than `merge_overlap` of the smaller instance's
    voxels inside the larger one's inflated volume. The state is donated.

    One jitted step (`_merge_step`, shared with `finalize`, whose thresholds are traced values): a
    pass over the voxels for the counts and overlaps, the decisions on the table, and a renaming of
    the voxels only when an instance is removed or merged.
    """
    params = _online_params_on_device(fusion)
    return _merge_step(state, params, config=config, label_mode=fusion.label_mode, veto=fusion.separate_min_frames > 0)


@saved_step(static_argnames=("config",), donate_argnames=("state",))
def fuse_and_refine(
    state: MapState, frame: FrameInputs, batch: DetectionBatch, likelihood: jax.Array, config: MapConfig, fusion: FusionConfig
) -> tuple[MapState, jax.Array]:
    """`fuse_detections`, then `refine`: the same map, from one executable instead of two.

    On a GPU each executable's call costs the host thread about a millisecond (its CUDA graph updated and
    launched) while the device works for far less: a detection frame the merge is due after is one call, and
    its statistics one int32 vector (`unpack_statistics`), read with one copy and no further executable.
    `fusion` as for `fuse_detections` (`fusion_on_device`); the merge's thresholds are read from it on the device.
    """
    state, stats = fuse_detections(state, frame, batch, likelihood, config, fusion)
    params = _online_params(fusion)
    state, refine_stats = _merge_step(
        state, params, config=config, label_mode=fusion.label_mode, veto=fusion.separate_min_frames > 0
    )
    return state, jnp.stack([jnp.asarray(x, jnp.int32) for x in (*stats, *refine_stats)])


def unpack_statistics(packed: np.ndarray) -> tuple[FrameStats, RefineStats]:
    """`fuse_and_refine`'s int32[10] statistics (on the host) as the two steps' `FrameStats` and `RefineStats`."""
    frame_fields = len(FrameStats._fields)
    return FrameStats(*packed[:frame_fields]), RefineStats(*packed[frame_fields:])


@saved_step(static_argnames=("config",), donate_argnames=("state",))
def fuse_geometry(state: MapState, config: MapConfig, fusion: FusionConfig) -> MapState:
    """Instance-geometry fusion: drop instance voxels the global surface does not support.

    The kept census follows the emptied slots; the table's `voxel_count` is left as it was: the next merge
    step (`refine`, or `finalize` right after this) reads the census before deciding anything, and nothing
    else reads it.
    """
    kept = occupied_cells.KeptCensus.of(state.instances)
    blocks, kept = fuse_cells(state.blocks, config, fusion.geometry_min_weight, kept)
    return state._replace(blocks=blocks, instances=state.instances._replace(**kept.fields()))


def finalize(state: MapState, config: MapConfig, fusion: FusionConfig) -> tuple[MapState, RefineStats]:
    """Before export: geometry fusion, then the post-processing merge (3D IoU and similarity).

    Runs the compiled `fuse_geometry` and `_merge_step` of the online loop (nothing new to compile at
    the end of a run); the merge step here uses the plain overlaps, the 3D IoU test and no removal.
    The state is donated.
    """
    state = fuse_geometry(state, config, fusion)
    params = _MergeParams(
        final=np.bool_(True),
        remove_missed=np.int32(np.iinfo(np.int32).max),
        remove_min_voxels=np.int32(0),
        similarity=_scalar(fusion.post_merge_similarity, jnp.float32),
        overlap=_scalar(fusion.post_merge_iou, jnp.float32),
        reunite=_scalar(fusion.reunite_min_frames, jnp.int32),
        separate=_scalar(fusion.separate_min_frames, jnp.int32),
    )
    return _merge_step(state, params, config=config, label_mode=fusion.label_mode, veto=fusion.separate_min_frames > 0)


def class_distribution(state: MapState, fusion: FusionConfig) -> jax.Array:
    """float32[K, C] normalized class distribution of every row (meaningful where `valid`)."""
    return label_fusion.class_distribution(state.instances.label_evidence, fusion.label_mode)
