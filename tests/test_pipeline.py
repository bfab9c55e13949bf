"""The composed engine steps and the Python loop, end to end on an analytic box room.

Every surface of the room (floor, walls, boxes, sphere) is one object; clean detections are its mask
labelled with the best open-set label of a chosen class. The fused map must find each object once, with
the right class, without recompiling, and a batch of two maps must equal two separate runs.
"""

from __future__ import annotations

import dataclasses

import chex
import jax
import numpy as np
import pytest
from fusion_helpers import fuse_sequence
from oracles.reference import BoxRoom, orbit_poses, scannet_like_intrinsics

from fmfusion_jax.config import load_config
from fmfusion_jax.engine import step
from fmfusion_jax.engine.detections import pack_detections
from fmfusion_jax.engine.frame import fuse_frame, fuse_frames
from fmfusion_jax.engine.state import init_map_state
from fmfusion_jax.labels import load_label_sets, load_likelihood
from fmfusion_jax.mapping.builder import MapBuilder
from fmfusion_jax.mapping.engine_configs import build_fusion_config, build_map_config
from fmfusion_jax.mapping.export import extract_map_instances
from fmfusion_jax.mapping.inputs import frame_inputs
from fmfusion_jax.mapping.telemetry import StageTimer, joined_tree_to_host
from fmfusion_jax.types import CameraIntrinsics, FrameDetections, RGBDFrame

H, W = 120, 160
LABELS = load_label_sets()
# surface label -> (open-set label the "detector" reports, expected closed class)
SURFACE_CLASSES = {
    0: ("floor", "floor"),
    2: ("wall", "wall"),
    3: ("wall", "wall"),
    4: ("wall", "wall"),
    5: ("wall", "wall"),
    6: ("bed", "bed"),
    7: ("cabinet", "cabinet"),
    8: ("bin", "otherfurniture"),
}


SURFACE_LABELS: dict = {}  # (frame name, seed) -> per-pixel surface label (the ground truth)


def make_frames(room: BoxRoom, n: int, seed: int = 0) -> list[RGBDFrame]:
    k = scannet_like_intrinsics(W, H)
    intrinsics = CameraIntrinsics(float(k[0]), float(k[1]), float(k[2]), float(k[3]), W, H)
    frames = []
    for i, pose in enumerate(orbit_poses(room, n, seed=seed)):
        depth, color, labels = room.render(pose, k, H, W)
        frames.append(RGBDFrame(i, f"frame-{i:06d}", color, depth.astype(np.float32), pose, intrinsics))
        SURFACE_LABELS[frames[-1].name, seed] = labels
    return frames


def clean_detections(frame: RGBDFrame, seed: int = 0) -> FrameDetections:
    labels = SURFACE_LABELS[frame.name, seed]
    masks, names = [], []
    for surface, (open_label, _) in SURFACE_CLASSES.items():
        mask = labels == surface
        if mask.sum() >= 150:
            masks.append(mask)
            names.append({open_label: 0.6})
    boxes = np.array(
        [[m.nonzero()[1].min(), m.nonzero()[0].min(), m.nonzero()[1].max(), m.nonzero()[0].max()] for m in masks], np.float32
    ).reshape(-1, 4)
    return FrameDetections(frame.name, np.array(masks, bool).reshape(-1, H, W), names, boxes)


def small_config(**overrides):
    items = [
        f"{k}={v}"
        for k, v in {
            "detections.every": 1,
            "detections.min_mask_pixels": 100,
            "detections.max_detections": 12,
            "tsdf.block_capacity": 6000,
            "tsdf.max_touched_blocks": 2048,
            "instances.capacity": 64,
            "association.min_projected_pixels": 200,
            "refinement.geometry_fusion_every": 4,
            "export.min_points": 20,
            **overrides,
        }.items()
    ]
    return load_config("scannet", items)


def build(config, room):
    map_config = build_map_config(config, room.lo, room.hi, H, W)
    return MapBuilder(config, map_config)


@pytest.fixture(scope="module")
def room_frames():
    room = BoxRoom()
    return room, make_frames(room, 8)


def test_fused_room_finds_each_object_with_its_class(room_frames):
    room, frames = room_frames
    config = small_config()
    result = fuse_sequence(frames, clean_detections, build(config, room))
    instances = extract_map_instances(result, LABELS)
    classes = sorted(LABELS.class_names[i.class_index] for i in instances)
    # 4 walls may merge into fewer instances (they touch at the corners) but every object class is there
    assert {"floor", "bed", "cabinet", "otherfurniture", "wall"} <= set(classes)
    for name in ("bed", "cabinet", "otherfurniture", "floor"):
        assert classes.count(name) == 1, classes
    assert result.counters["created"] >= 5
    assert result.detection_frames == len(frames)
    # each instance's points lie on the surface they came from
    for inst in instances:
        sdf = np.abs(room.signed_distance(inst.points.astype(np.float64)))
        assert np.median(sdf) < 2 * config.tsdf.voxel_size


def test_no_recompilation_after_the_first_frames(room_frames):
    room, frames = room_frames
    config = small_config()
    builder = build(config, room)
    # the same step, traced through chex's counter: every frame's inputs must hit the first trace
    counted = jax.jit(chex.assert_max_traces(step.fuse_detections.__wrapped__, n=1), static_argnames=("config",))
    from fmfusion_jax.engine.detections import pack_detections
    from fmfusion_jax.mapping.inputs import frame_inputs

    state = builder.state
    for i, frame in enumerate(frames[:4]):
        batch = pack_detections(clean_detections(frame), LABELS.open_labels, 12, 100)
        # thresholds are traced: another association threshold or depth filter reuses the compiled step
        fusion = dataclasses.replace(builder.fusion_config, association_threshold=0.5 - 0.05 * i, depth_high=0.9 + 0.02 * i)
        state, _ = counted(state, frame_inputs(frame, builder.map_config), batch, builder.likelihood, builder.map_config, fusion)
    # and the loop's own jitted steps keep one compiled version each
    builder.add_frame(frames[0], clean_detections(frames[0]))
    builder.add_frame(frames[1], None)
    # refine is a thin wrapper of the jitted _merge_step (shared with finalize)
    sizes = (step.fuse_detections._cache_size(), step.integrate_frame._cache_size(), step._merge_step._cache_size())
    for frame in frames[2:]:
        builder.add_frame(frame, clean_detections(frame))
        builder.add_frame(frame, None)
    assert (step.fuse_detections._cache_size(), step.integrate_frame._cache_size(), step._merge_step._cache_size()) == sizes


def test_one_call_per_detection_frame_makes_the_same_map(room_frames, monkeypatch):
    # untimed, a detection frame the merge is due after is one executable (fuse_and_refine; by default off the CPU);
    # timed, its two steps
    room, frames = room_frames
    config = small_config()
    timed = MapBuilder(config, build(config, room).map_config, timer=StageTimer(enabled=True), one_call_per_frame=True)
    untimed = MapBuilder(config, timed.map_config, timer=StageTimer(enabled=False), one_call_per_frame=True)
    assert MapBuilder(config, timed.map_config).one_call_per_frame == (jax.default_backend() != "cpu")
    calls = []
    one_call = step.fuse_and_refine
    monkeypatch.setattr(step, "fuse_and_refine", lambda *args: calls.append(1) or one_call(*args))
    for builder in (timed, untimed):
        for frame in frames:
            builder.add_frame(frame, clean_detections(frame))
        if builder is timed:
            assert not calls and len(timed.timer.samples_ms["refine"]) == len(frames) - 1  # the first call compiled
    assert len(calls) == len(frames)
    assert timed.counters == untimed.counters and timed.counters["created"] >= 5
    for one, other in zip(jax.tree.leaves(jax.device_get(timed.state)), jax.tree.leaves(jax.device_get(untimed.state))):
        np.testing.assert_array_equal(one, other)


def test_fusion_thresholds_go_to_the_device_once_per_config():
    fusion = dataclasses.replace(build_fusion_config(small_config()), association_threshold=0.4)
    on_device = step.fusion_on_device(fusion)
    again = dataclasses.replace(build_fusion_config(small_config()), association_threshold=0.4)
    assert step.fusion_on_device(again) is on_device  # cached per config
    assert jax.tree.structure(on_device) == jax.tree.structure(fusion)
    for leaf, value in zip(jax.tree.leaves(on_device), jax.tree.leaves(fusion)):
        assert isinstance(leaf, jax.Array) and leaf.weak_type and float(leaf) == pytest.approx(value)  # same trace
    swept = dataclasses.replace(fusion, association_threshold=jax.numpy.float32(0.3))
    assert step.fusion_on_device(swept) is swept  # array thresholds pass as they are


def test_the_label_image_and_the_mask_stack_make_the_same_map(room_frames):
    # the host adapter sends a label image at the fused stride; full-resolution masks must give the same map
    room, frames = room_frames
    config = small_config()
    builder = build(config, room)

    map_config, stride = builder.map_config, builder.map_config.pixel_stride
    maps = []
    for as_image in (False, True):
        state = init_map_state(map_config)  # the step donates its state
        for frame in frames[:3]:
            batch = pack_detections(
                clean_detections(frame), LABELS.open_labels, 12, 100, stride=stride if as_image else 1, as_image=as_image
            )
            assert (batch.masks is None) == as_image
            # the builder's compiled layout (the origin in the state): the label image's step is the other tests'
            state, _ = step.fuse_detections(
                state, frame_inputs(frame, map_config), batch, builder.likelihood, builder.step_config, builder.fusion_config
            )
        maps.append(jax.device_get(state))
    assert int(maps[1].instances.valid.sum()) >= 3
    for leaf_stack, leaf_image in zip(jax.tree.leaves(maps[0]), jax.tree.leaves(maps[1])):
        np.testing.assert_array_equal(leaf_stack, leaf_image)


def test_batch_of_two_maps_equals_two_runs(room_frames):
    room, frames = room_frames
    other_room = BoxRoom(boxes=(((1.0, 1.0, 0.0), (1.8, 1.6, 0.9)),), spheres=())
    other_frames = make_frames(other_room, 3, seed=3)
    config = small_config()
    map_config = build_map_config(config, (0, 0, 0), (4.0, 3.5, 2.5), H, W)
    fusion = dataclasses.replace(build_fusion_config(config), min_projected_pixels=200.0)
    likelihood = jax.numpy.asarray(load_likelihood("statistical"), jax.numpy.float32)

    def inputs(frame, seed=0):
        batch = pack_detections(clean_detections(frame, seed), LABELS.open_labels, 12, 100)
        return frame_inputs(frame, map_config), batch

    # the engine's frame composition, one map at a time and both in lock step, the merge and the geometry fusion
    # due on alternate frames
    due = [(False, True), (True, False), (True, True)]
    separate = []
    for seq, seed in ((frames[:3], 0), (other_frames, 3)):
        state = init_map_state(map_config)
        for frame, (merge, geometry) in zip(seq, due):
            state, _ = fuse_frame(state, *inputs(frame, seed), likelihood, map_config, fusion, merge=merge, geometry=geometry)
        separate.append(jax.device_get(state))

    states = jax.tree.map(lambda *x: np.stack(x), init_map_state(map_config), init_map_state(map_config))
    both = np.ones(2, bool)
    for a, b, (merge, geometry) in zip(frames[:3], other_frames, due):
        (fa, ba), (fb, bb) = inputs(a), inputs(b, 3)
        stacked = lambda x, y: jax.tree.map(lambda *v: np.stack(v), x, y)  # noqa: E731
        states, _, _ = fuse_frames(
            states, stacked(fa, fb), stacked(ba, bb), likelihood, both, both, both & merge, both & geometry, map_config, fusion
        )
    batched = jax.device_get(states)
    for i, expected in enumerate(separate):
        got = jax.tree.map(lambda x: x[i], batched)
        for leaf_got, leaf_expected in zip(jax.tree.leaves(got), jax.tree.leaves(expected)):
            np.testing.assert_allclose(leaf_got, leaf_expected, rtol=1e-5, atol=1e-5)


def test_capacity_exhausted_warns_and_keeps_a_consistent_map(room_frames, caplog):
    room, frames = room_frames
    config = small_config(**{"tsdf.block_capacity": 64, "instances.capacity": 3})
    with caplog.at_level("WARNING"):
        result = fuse_sequence(frames[:3], clean_detections, build(config, room))
    text = caplog.text
    assert "raise tsdf.block_capacity" in text and "raise instances.capacity" in text
    state = jax.device_get(result.state)
    assert int(state.blocks.num_blocks) <= 63
    assert int(state.instances.valid.sum()) <= 3
    ids = state.blocks.instance_id
    assert ids.max() < 3  # no voxel refers to an instance row that does not exist


def sequential_merge(state, map_config, fusion, final: bool):
    """The refinement as first written, step by step from the public kernels: recount; remove (rename,
    recount); count the overlaps; merge (rename, recount). `refine` and `finalize` must decide and
    produce exactly the same."""
    from fmfusion_jax.engine import cell_edits, label_fusion, maintenance, merge
    from fmfusion_jax.engine import occupied_cells as oc

    def recount(s):
        counts = oc.instance_voxel_counts(s.blocks, map_config).counts
        return s._replace(instances=s.instances._replace(voxel_count=counts))

    def apply(s, rows, new_id):
        table = s.instances
        folded = {name: merge.fold_pair_counts(getattr(table, name), new_id, table.valid) for name in ("covered", "separated")}
        s = s._replace(
            blocks=cell_edits.remap_instances(s.blocks, new_id, map_config), instances=table._replace(**rows._asdict(), **folded)
        )
        return recount(s)

    if final:
        fused = cell_edits.fuse_instance_geometry(state.blocks, map_config, fusion.geometry_min_weight)
        state = recount(state._replace(blocks=fused))
    else:
        state = recount(state)
        rows = maintenance.TableRows.of(state.instances)
        remove = maintenance.instances_to_remove(
            rows.missed, rows.voxel_count, rows.valid, fusion.remove_missed, fusion.remove_min_voxels
        )
        removal = maintenance.remove_instances(rows, remove)
        state = apply(state, removal.rows, removal.new_id)
    rows = maintenance.TableRows.of(state.instances)
    overlap = oc.instance_overlap_counts(state.blocks, map_config, inflate=not final).counts
    similarity = merge.semantic_similarity(label_fusion.class_distribution(rows.label_evidence, fusion.label_mode))
    if final:
        pairs = merge.post_merge_pairs(
            similarity, overlap, rows.voxel_count, rows.valid, fusion.post_merge_similarity, fusion.post_merge_iou
        )
    else:
        pairs = merge.merge_pairs(
            similarity, overlap, rows.voxel_count, rows.valid, fusion.merge_similarity, fusion.merge_overlap
        )
    table = state.instances
    pairs = pairs | merge.reunion_pairs(table.covered, rows.observations, rows.valid, fusion.reunite_min_frames)
    pairs = pairs & ~merge.separated_pairs(table.separated, table.covered, fusion.separate_min_frames)
    merged = merge.merge_instance_table(rows, merge.merge_groups(pairs, rows.valid, rows.voxel_count), fusion.label_mode)
    return apply(state, merged.rows, merged.new_id)


#: Fields the steps keep for themselves (the merge's kept census and its scratch), which `sequential_merge` does not,
#: and the blocks' id filter, whose exact bits depend on the renaming's path (`assert_kept_census_is_a_recount`
#: checks that it covers every id a block holds).
KEPT_FIELDS = {"census_counts", "census_overlap", "census_overfull", "census_valid", "cell_owner", "instance_bits"}


def assert_same_map(got, expected):
    """The maps are equal, field by field, apart from `KEPT_FIELDS`."""
    for part in ("blocks", "instances"):
        a, b = getattr(got, part), getattr(expected, part)
        for name in a._fields:
            if name not in KEPT_FIELDS:
                np.testing.assert_array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)), err_msg=name)
    np.testing.assert_array_equal(np.asarray(got.frame_index), np.asarray(expected.frame_index))


def assert_kept_census_is_a_recount(state, map_config):
    """A valid kept census equals a full inflated census of the voxels, exactly; the scratches are clear."""
    from fmfusion_jax.engine import occupied_cells as oc

    table = state.instances
    if bool(table.census_valid):
        full = oc.census(jax.tree.map(jax.numpy.asarray, state.blocks), map_config, "inflated")
        np.testing.assert_array_equal(np.asarray(table.census_counts), np.asarray(full.counts))
        np.testing.assert_array_equal(np.asarray(table.census_overlap), np.asarray(full.overlap))
        assert int(table.census_overfull) == int(full.overfull)
    assert (np.asarray(state.blocks.cell_owner) == -1).all()
    # the scratch block (the pool's last) holds no instance: reads of "no cell" or "no voxel" land there
    assert (np.asarray(state.blocks.instance_id)[-1] == -1).all() and (np.asarray(state.blocks.instance_weight)[-1] == 0).all()
    # every id a block holds has its bit set (the renaming visits only those blocks)
    ids = np.asarray(state.blocks.instance_id).astype(np.int64)
    bits = np.asarray(state.blocks.instance_bits)
    block, voxel, slot = np.nonzero(ids >= 0)
    assert bits[block, ids[block, voxel, slot] % bits.shape[1]].all()


@pytest.mark.parametrize("contrary", [0.5, 0.0])
def test_kept_census_equals_a_recount_after_every_step(room_frames, contrary):
    """Votes (with contrary votes and without: slots are emptied both ways), removals, merges and geometry fusion
    all keep the merge's census exactly (re-segmented and noisy detections, loose merge thresholds, geometry
    fusion every other frame)."""
    room, frames = room_frames
    config = small_config(
        **{
            "instances.contrary_vote_weight": contrary,
            "refinement.merge_similarity": 0.02,
            "refinement.merge_overlap": 0.1,
            "refinement.remove_missed": 1,
            "refinement.remove_min_voxels": 100000,
            "refinement.geometry_fusion_every": 2,
        }
    )
    builder = build(config, room)
    rng = np.random.default_rng(5)

    def detections(frame):
        det = clean_detections(frame)
        keep = rng.random(len(det.masks)) < 0.8  # missed now and then: removals
        masks = [m for m, k in zip(det.masks, keep) if k]
        masks += [m & (np.arange(W) < W // 2 + 10 * frame.index) for m in det.masks[:3]]  # fragments
        labels = [lab for lab, k in zip(det.labels, keep) if k] + det.labels[:3]
        boxes = np.concatenate([det.boxes[keep], det.boxes[:3]])
        return FrameDetections(det.frame_name, np.array(masks), labels, boxes)

    for i, frame in enumerate(frames):
        builder.add_frame(frame, detections(frame))
        builder.flush()
        state = jax.device_get(builder.state)
        assert_kept_census_is_a_recount(state, builder.map_config)
        assert bool(state.instances.census_valid) or i == 0  # the first merge step counted it; kept since
        # the renaming (by the blocks' instance bits) left no merged-away or removed id in a voxel
        held = np.unique(state.blocks.instance_id[state.blocks.instance_id >= 0])
        assert state.instances.valid[held].all(), held[~state.instances.valid[held]]
    counters = builder.counters
    merged, removed = counters.get("merged", 0), counters.get("removed", 0)
    assert merged > 0 and removed > 0, counters


@pytest.mark.parametrize("ids_per_cell, separate", [(1, 0), (4, 0), (4, 2)])
def test_refine_and_finalize_decide_as_the_sequential_refinement(room_frames, ids_per_cell, separate):
    import dataclasses

    from fmfusion_jax.engine.occupied_cells import instance_voxel_counts

    room, frames = room_frames
    # matched in the reference's score order, the half masks below grow the halves of the objects into duplicates
    # of them: the overlapping instances whose merges this test compares
    config = small_config(**{"refinement.enabled": False, "association.rank": "score"})
    builder = build(config, room)
    builder.map_config = dataclasses.replace(builder.map_config, overlap_ids_per_cell=ids_per_cell)

    # re-segment every other frame (split the floor and the walls differently): overlapping instances
    def detections(frame):
        det = clean_detections(frame)
        if frame.index % 2:
            masks = [m for m in det.masks] + [m & (np.arange(W) < W // 2) for m in det.masks[:2]]
            det = FrameDetections(
                det.frame_name, np.array(masks), det.labels + det.labels[:2], np.concatenate([det.boxes, det.boxes[:2]])
            )
        return det

    result = fuse_sequence(frames, detections, builder)
    state = jax.device_get(result.state)
    table = state.instances
    valid = np.flatnonzero(table.valid)
    assert len(valid) >= 6
    # some instances missed often enough to be removed if small; loose merge thresholds
    missed = np.where(np.isin(np.arange(len(table.valid)), valid[::2]), 9, 0).astype(np.int32)
    state = state._replace(instances=table._replace(missed=missed))
    counts = np.asarray(instance_voxel_counts(result.state.blocks, builder.map_config).counts)
    fusion = dataclasses.replace(
        builder.fusion_config,
        merge_similarity=0.02,
        merge_overlap=0.1,
        remove_min_voxels=int(np.median(counts[valid])),
        post_merge_iou=0.0,
        post_merge_similarity=0.0,
        separate_min_frames=separate,
    )
    fresh = lambda: jax.tree.map(jax.numpy.asarray, state)  # noqa: E731  (steps donate their state)
    got, stats = step.refine(fresh(), builder.map_config, fusion)
    expected = sequential_merge(fresh(), builder.map_config, fusion, final=False)
    assert int(stats.removed) > 0 and (int(stats.merged) > 0 or ids_per_cell == 1)
    if ids_per_cell == 1:  # cells beyond it exist: the removal then makes refine count the overlaps again
        assert int(stats.dropped_cells) > 0
    assert_same_map(got, expected)
    assert_kept_census_is_a_recount(got, builder.map_config)
    assert bool(got.instances.census_valid) == (ids_per_cell > 1)  # one id per cell: not a sum of cells, not kept
    got, stats = step.finalize(jax.tree.map(jax.numpy.asarray, jax.device_get(got)), builder.map_config, fusion)
    expected = sequential_merge(expected, builder.map_config, fusion, final=True)
    assert int(stats.merged) > 0 or ids_per_cell == 1 or separate  # the split halves are kept apart with it
    assert_same_map(got, expected)
    assert_kept_census_is_a_recount(got, builder.map_config)


def _walk(steps: int, metres_per_step: float, degrees_per_step: float) -> list[np.ndarray]:
    """Poses of a camera moving along x and turning about z at a constant rate."""
    poses = []
    for i in range(steps):
        angle = np.radians(degrees_per_step * i)
        pose = np.eye(4)
        pose[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
        pose[0, 3] = metres_per_step * i
        poses.append(pose)
    return poses


def _due_positions(poses, config, available=lambda i: True) -> list[int]:
    from fmfusion_jax.mapping.schedule import DetectionSchedule

    schedule, due = DetectionSchedule(config), []
    for i, pose in enumerate(poses):
        assert schedule.due(i, pose) == schedule.due(i, pose)  # asking does not change the schedule
        if schedule.due(i, pose) and available(i):
            schedule.fused(pose)
            due.append(i)
        schedule.advance(pose)
    return due


def test_motion_schedule_follows_the_camera_not_the_frame_rate():
    """The same path recorded at 30 Hz and subsampled 18x: about the paper's every 10th frame at 30 Hz,
    every frame of the subsampled sequence, and the same detection poses per metre walked."""
    config = load_config("scannet")
    assert config.detections.schedule == "motion"
    full_rate = _walk(18 * 30, 0.116 / 18, 6.3 / 18)  # the shared scene's median motion per 18 frames
    fused = _due_positions(full_rate, config)
    gaps = np.diff(fused)
    assert 6 <= np.median(gaps) <= 15
    subsampled = full_rate[::18]
    assert _due_positions(subsampled, config) == list(range(len(subsampled)))
    assert _due_positions(_walk(20, 0.0, 0.0), config) == [0]  # a camera standing still: one frame


def test_motion_schedule_fuses_every_frame_of_a_subsampled_sequence_through_camera_pauses():
    """A sequence subsampled in time keeps fusing while the camera pauses (its frames are keyframes already,
    as with a fixed stride of 1); at 30 Hz the same pause is one frame, and so is a subsampled camera that
    stands still throughout."""
    config = load_config("scannet")
    subsampled = _walk(40, 0.12, 6.0)
    subsampled = subsampled[:30] + [subsampled[29]] * 15 + subsampled[30:]  # a pause shorter than the past
    assert _due_positions(subsampled, config) == list(range(len(subsampled)))
    full_rate = _walk(300, 0.004, 0.3)
    full_rate = full_rate[:150] + [full_rate[149]] * 100 + full_rate[150:]
    fused = _due_positions(full_rate, config)
    assert not any(150 <= i < 250 for i in fused)
    off = load_config("scannet", ["detections.sparse_motion=0"])
    assert len(_due_positions(subsampled, off)) == 40


def test_a_due_frame_without_detections_keeps_the_schedule_due():
    config = load_config("scannet")
    poses = _walk(40, 0.0101, 0.0)  # 5 cm every 5 frames
    dense = _due_positions(poses, config)
    sparse = _due_positions(poses, config, available=lambda i: i % 7 == 0)  # detection files every 7th
    assert dense == list(range(0, 40, 5))
    assert sparse == [0, 7, 14, 21, 28, 35]  # the first available frame once the camera moved enough


def test_fixed_stride_schedule_is_the_papers():
    config = load_config("scannet", ["detections.schedule=every", "detections.every=10"])
    assert _due_positions(_walk(35, 1.0, 30.0), config) == [0, 10, 20, 30]


def test_count_covered_counts_candidates_mostly_inside_another_instances_detection():
    from fmfusion_jax.engine import association

    k = 5
    intersection = np.array([[40, 30, 2, 0, 9], [0, 0, 0, 20, 0]], np.int32)  # detections x instances
    inst_area = np.array([50, 40, 10, 25, 10], np.int32)
    counts = association.AssociationCounts(intersection, np.array([80, 30], np.int32), inst_area)
    assignment = association.Assignment(
        np.array([0, 3], np.int32), np.zeros(2, bool), np.zeros(k, bool), np.ones(k, bool), np.int32(0)
    )
    matches = step.Matches(counts, np.ones(2, bool), assignment)
    candidates = np.array([False, True, True, False, True])  # in view, not detected: 1, 2, 4
    got = np.asarray(step.count_covered(np.zeros((k, k), np.int32), matches, np.array([True, True]), candidates, 0.5))
    expected = np.zeros((k, k), np.int32)
    expected[0, 1] = 1  # 30 / 40 of instance 1 inside detection 0 (fused into 0); 2: 2/10; 4: 9/10 -> also
    expected[0, 4] = 1
    assert np.array_equal(got, expected)
    not_fused = np.asarray(step.count_covered(np.zeros((k, k), np.int32), matches, np.array([False, True]), candidates, 0.5))
    assert not not_fused.any()


def test_count_separated_counts_each_pair_of_distinct_instances_once_per_frame():
    k = 6
    inst_for_det = np.array([2, 4, 2, -1, 5], np.int32)  # detections 0 and 2 both fused into 2
    fused = np.array([True, True, True, False, False])
    got = np.asarray(step.count_separated(np.zeros((k, k), np.int32), inst_for_det, fused))
    expected = np.zeros((k, k), np.int32)
    expected[2, 4] = expected[4, 2] = 2  # (det 0, det 1) and (det 2, det 1): two detection pairs
    assert np.array_equal(got, expected)


def test_a_tree_joined_on_the_device_reads_back_leaf_for_leaf():
    """The statistics' read off a GPU (`small_tree_to_host` there): leaves joined per dtype on the device, copied
    once per dtype and split again, each leaf its value, dtype and shape, None kept."""
    tree = {
        "stats": (jax.numpy.asarray(3, np.int32), jax.numpy.asarray([-1, 7], np.int32)),
        "mean": jax.numpy.asarray([[0.5, 1.5]], np.float32),
        "flags": jax.numpy.asarray([True, False, True]),
        "refine": None,
        "last": jax.numpy.asarray(2**30 + 1, np.int32),
    }
    host = joined_tree_to_host(tree)
    assert jax.tree.structure(host) == jax.tree.structure(tree) and host["refine"] is None
    for got, want in zip(jax.tree.leaves(host), jax.tree.leaves(tree)):
        assert isinstance(got, np.ndarray) and got.dtype == want.dtype and got.shape == want.shape
        np.testing.assert_array_equal(got, np.asarray(want))
    assert joined_tree_to_host((None, None)) == (None, None)
