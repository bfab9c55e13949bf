"""`fmfusion_jax.Mapper`: the Python API gives the map `fmfusion run` gives, snapshots leave the map alone,
the map grows from a small allocation, saves and resumes, and bad inputs are clear errors."""

from __future__ import annotations

import concurrent.futures
import dataclasses
import importlib.util
import time
import types
from pathlib import Path

import jax
import numpy as np
import pytest
from fusion_helpers import frame_block_keys

import fmfusion_jax
from fmfusion_jax.config import load_config
from fmfusion_jax.engine import growth
from fmfusion_jax.errors import UserError
from fmfusion_jax.io.detections import DetectionFolder
from fmfusion_jax.io.scene import open_scene
from fmfusion_jax.mapping.capacity import (
    FIXED_POOL_MARGIN,
    frame_block_extent,
    initial_pool_blocks,
    sample_block_count,
    scene_extent,
)
from fmfusion_jax.mapping.engine_configs import build_map_config
from fmfusion_jax.mapping.export import extract_map_instances
from fmfusion_jax.mapping.inputs import as_config
from fmfusion_jax.mapping.mapper import Mapper
from fmfusion_jax.run.scene_fusion import fuse_scene
from fmfusion_jax.simulation.demo_setup import demo_config, demo_noise
from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, generated_scene, simulated_detections
from fmfusion_jax.types import FrameDetections

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "fuse_with_mapper.py"
SPEC = GeneratedSceneSpec(seed=5, num_objects=4, num_frames=16, width=320, height=240)
ROOM_OVERRIDES = ["refinement.geometry_fusion_every=3"]


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """A generated room with simulated detections on every frame, and the config `fmfusion demo` would use."""
    root = tmp_path_factory.mktemp("mapper")
    scene_dir = generated_scene(SPEC, root)
    detections = simulated_detections(scene_dir, root / "detections", demo_noise(0, SPEC.width, SPEC.height))
    config = demo_config(SPEC.num_frames, SPEC.width, SPEC.height, ROOM_OVERRIDES)
    return scene_dir, detections, config


def _frames(scene_dir, config):
    return list(open_scene(scene_dir, depth_max=config.dataset.depth_max).frames())


def _key(instances):
    return [
        (i.instance_id, i.class_index, i.observations, i.points.tobytes()) for i in sorted(instances, key=lambda i: i.instance_id)
    ]


def _load_example():
    spec = importlib.util.spec_from_file_location("fuse_with_mapper", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_top_level_exports():
    assert fmfusion_jax.Mapper is Mapper and "Mapper" in dir(fmfusion_jax)
    with pytest.raises(AttributeError):
        fmfusion_jax.NotAThing  # noqa: B018


def test_example_gives_the_map_of_fmfusion_run(room):
    """The example's Mapper without bounds and `fmfusion run`'s map sized from the scene's bounds: identical
    instances. Its first frame sized it for a room: it never grew in this one, and it holds less than the config's
    capacities."""
    scene_dir, detections, config = room
    mapper = _load_example().fuse(scene_dir, detections, config, progress=False)
    scene = open_scene(scene_dir, depth_max=config.dataset.depth_max)
    folder = DetectionFolder(detections)
    reference = fuse_scene(scene, lambda frame: folder.get(frame.name), config, progress=False)
    expected = extract_map_instances(reference)
    assert len(expected) >= 3
    assert _key(mapper.instances()) == _key(expected)
    assert mapper.detection_frames == reference.detection_frames and mapper.growths == 0
    full = build_map_config(config, *open_scene(scene_dir).bounds(), SPEC.height, SPEC.width)
    assert mapper.map_config.memory_bytes() < full.memory_bytes()
    assert mapper.frames_integrated == SPEC.num_frames


def test_a_map_without_bounds_starts_room_sized_from_its_first_frame(room, monkeypatch):
    """The first frame sizes a growing map for the room around it (every growth recompiles the steps): an index
    reaching two depth ranges beyond the frame's blocks and a pool of eight times them. Every block the room's
    frames touch fits, so this room never grows; a smaller ceiling caps the pool."""
    import fmfusion_jax.mapping.capacity as capacity

    scene_dir, _, config = room
    frames = _frames(scene_dir, config)
    layout = build_map_config(config, np.zeros(3), np.ones(3), SPEC.height, SPEC.width)
    count, lo, hi = frame_block_extent(frames[0], layout)
    first = capacity.growing_map_config(layout, count, lo, hi, 256)
    room_blocks = np.unique(np.concatenate([frame_block_keys(frame, layout) for frame in frames]), axis=0)
    index_lo, index_hi = growth.bounds_block_range(first)
    reach = int(np.ceil(2 * layout.depth_max / layout.block_length))
    np.testing.assert_array_equal(index_lo, lo - reach)
    np.testing.assert_array_equal(index_hi, hi + reach)
    assert (room_blocks >= index_lo).all() and (room_blocks < index_hi).all()
    assert first.block_capacity == 8192 >= 8 * count and first.block_capacity > len(room_blocks) > 4 * count
    assert first.instance_capacity == 256 and first.grid_origin == tuple((index_lo * layout.block_length).tolist())
    far = capacity.growing_map_config(dataclasses.replace(layout, depth_max=12.0), count, lo, hi, 256)  # 24 m reach
    assert np.prod(far.grid_shape) <= capacity.FIRST_INDEX_CELLS < np.prod(np.asarray(far.grid_shape) + 2)
    small_ceiling = dataclasses.replace(layout, block_capacity=4096)
    assert capacity.growing_map_config(small_ceiling, count, lo, hi, 256).block_capacity == 4096
    monkeypatch.setattr(capacity, "FIRST_POOL_FACTOR", 2)
    assert capacity.growing_map_config(layout, count, lo, hi, 256).block_capacity == 2048
    assert capacity.growing_map_config(layout, 0, np.zeros(3), np.zeros(3), 256).block_capacity == capacity.MIN_POOL_BLOCKS


def test_for_scene_is_the_map_fmfusion_run_fuses_into(room):
    """`Mapper.for_scene`: sized up front as `fmfusion run` sizes its map (same layout: the same compiled steps), it
    does not grow, and its instances are `fmfusion run`'s."""
    scene_dir, detections, config = room
    scene = open_scene(scene_dir, depth_max=config.dataset.depth_max)
    folder = DetectionFolder(detections)
    mapper = Mapper.for_scene(scene, config)
    for frame in scene.frames(progress=True):
        mapper.integrate(frame, folder.get(frame.name))
    reference = fuse_scene(scene, lambda frame: folder.get(frame.name), config, progress=False)
    assert mapper.growths == 0 and mapper.map_config == reference.map_config
    assert _key(mapper.instances()) == _key(extract_map_instances(reference))


def test_a_bounded_map_grows_its_pool_from_the_expected_blocks_to_the_same_map(room):
    """With bounds and a (far too small) expected block count, the pool starts small and doubles before a frame
    that might not fit: the same map, voxel for voxel, as the pool allocated at the config's capacity."""
    scene_dir, detections, config = room
    folder = DetectionFolder(detections)
    scene = open_scene(scene_dir, depth_max=config.dataset.depth_max)
    bounds = scene.bounds()
    # 5,357 blocks used: `fixed` starts at 8,192 and never grows, `sized` starts at 4,096 (a shared compile)
    fixed, sized = Mapper(config, bounds=bounds, expected_blocks=6000), Mapper(config, bounds=bounds, expected_blocks=2000)
    for frame in scene.frames():
        fixed.integrate(frame, folder.get(frame.name))
        sized.integrate(frame, folder.get(frame.name))
    used = int(fixed.state.blocks.num_blocks)
    assert int(sized.state.blocks.num_blocks) == used and int(sized.state.blocks.dropped_blocks) == 0
    assert fixed.growths == 0 and sized.growths == 1 and used < sized.map_config.block_capacity == fixed.map_config.block_capacity
    for name in ("tsdf", "weight", "color", "instance_id", "instance_weight", "block_coords"):
        np.testing.assert_array_equal(
            np.asarray(getattr(sized.state.blocks, name))[:used], np.asarray(getattr(fixed.state.blocks, name))[:used]
        )
    assert _key(sized.instances()) == _key(fixed.instances())


@pytest.mark.parametrize("expected_blocks, direct_reads", [(2000, False), (6000, False), (6000, True)])
def test_the_growth_checks_bounds_never_fall_below_the_maps_sizes(room, expected_blocks, direct_reads):
    """The growth check bounds the pool's blocks and the table's rows by the sizes of a frame or two back (from the
    statistics, or a direct read near a capacity) plus a bound per frame since: after every frame, with frames
    without detections in between (they send no statistics), the bounds hold the map's true sizes. With
    `direct_reads` the sizes are forgotten before every frame, so the check reads the device each time and the
    statistics of an older frame arrive after it (they must not replace the newer sizes)."""
    scene_dir, detections, config = room
    folder = DetectionFolder(detections)
    scene = open_scene(scene_dir, depth_max=config.dataset.depth_max)
    mapper = Mapper(config, bounds=scene.bounds(), expected_blocks=expected_blocks)
    checked = 0
    for frame in scene.frames():
        if direct_reads and mapper._builder is not None:
            mapper._builder.sizes_after = None
        mapper.integrate(frame, folder.get(frame.name) if frame.index % 3 else None)
        bounds = mapper._size_bounds(mapper._builder)
        if bounds is None:
            continue
        # every frame after the known sizes has its bound in (none lost when older statistics arrive late)
        known = mapper._builder.sizes_after
        assert [entry[0] for entry in mapper._recent] == list(range(known.position + 1, mapper.frames_integrated)), frame.name
        state = mapper.state
        assert bounds[0] >= int(state.blocks.num_blocks) and bounds[1] >= int(state.instances.valid.sum()), frame.name
        checked += 1
    assert checked >= len(scene) - 2 and int(mapper.state.blocks.dropped_blocks) == 0


def test_a_bounded_map_grows_its_instance_table_to_the_same_map(room, monkeypatch):
    """With bounds the instance table starts small too and doubles before a frame whose detections might not fit
    (the merge's K^2 tests cost what the map holds, not the ceiling): the same instances as a table that never
    grows, and the timer leaves the calls that recompiled after the growth out of its samples."""
    import fmfusion_jax.mapping.capacity as mapper_module

    scene_dir, detections, config = room
    folder = DetectionFolder(detections)
    scene = open_scene(scene_dir, depth_max=config.dataset.depth_max)
    config = config.model_copy(update={"detections": config.detections.model_copy(update={"max_detections": 4})})
    frames = list(scene.frames())
    # the big table starts at the size the small one grows to (one layout compiled for both): it never grows here
    monkeypatch.setattr(mapper_module, "INITIAL_INSTANCE_ROWS", 32)
    big = Mapper(config, bounds=scene.bounds(), expected_blocks=6000)
    for frame in frames:
        big.integrate(frame, folder.get(frame.name))
    monkeypatch.setattr(mapper_module, "INITIAL_INSTANCE_ROWS", 16)
    assert mapper_module.initial_instance_rows(4, 1024) == 16
    small = Mapper(config, bounds=scene.bounds(), expected_blocks=6000, time_stages=True)
    for frame in frames:
        small.integrate(frame, folder.get(frame.name))
    assert big.growths == 0 and big.map_config.instance_capacity == 32
    assert small.growths >= 1 and small.map_config.instance_capacity > 16
    assert len(big.instances()) >= 2 and _key(small.instances()) == _key(big.instances())
    timer = small.finalize().timings
    fused = len(timer.samples_ms["fusion"])
    assert fused == small.detection_frames - 1 - small.growths  # each growth's first fusion call compiled


def test_the_timed_stages_of_a_frame_add_up_to_the_whole_integrate_call(room):
    """What `fmfusion bench` calls the whole frame is all of `Mapper.integrate`: the steps, the builder's host work
    (packing, sending, statistics) and the Mapper's own (checks, schedule, growth check), each timed once."""
    from fmfusion_jax.apps.bench.stages import FrameTimer

    scene_dir, detections, config = room
    folder = DetectionFolder(detections)
    scene = open_scene(scene_dir, depth_max=config.dataset.depth_max)
    timer = FrameTimer()
    mapper = Mapper.for_scene(scene, config, timer=timer)  # `fmfusion run`'s layout: compiled by a test before
    walls = []
    for frame in scene.frames():
        detections = folder.get(frame.name)
        timer.start_frame()
        start = time.perf_counter()
        mapper.integrate(frame, detections)
        walls.append((time.perf_counter() - start) * 1e3)
    untimed = []
    for wall, stages, compiled in zip(walls, timer.frames, timer.compiled):
        assert {"host", "mapper"} <= set(stages) | set(compiled)
        accounted = sum(stages.values()) + sum(compiled.values())
        assert accounted <= wall + 1e-6, (wall, stages, compiled)
        untimed.append(wall - accounted)
    assert np.median(untimed) < 0.2, untimed  # a few statements (a garbage collection may land in one)


def test_frame_block_extent_counts_the_distinct_blocks_of_a_frame(room):
    """The growth check's count and box of a frame's blocks (a bitmap, not a sort) are those of its keys."""
    scene_dir, _, config = room
    scene = open_scene(scene_dir, depth_max=config.dataset.depth_max)
    layout = build_map_config(config, *scene.bounds(), SPEC.height, SPEC.width)
    for frame in list(scene.frames())[::5]:
        keys = frame_block_keys(frame, layout)
        assert len(keys) > 0 and len(np.unique(keys, axis=0)) == len(keys)
        count, lo, hi = frame_block_extent(frame, layout)
        assert count == len(keys)
        np.testing.assert_array_equal(lo, keys.min(axis=0))
        np.testing.assert_array_equal(hi, keys.max(axis=0) + 1)
    blank = dataclasses.replace(frame, depth=np.zeros_like(frame.depth))
    assert frame_block_extent(blank, layout)[0] == 0 and len(frame_block_keys(blank, layout)) == 0


def test_frames_prepared_in_a_reader_thread_make_the_same_map(room, monkeypatch):
    """`Mapper.prepare` counts the growth check's block extent and packs the detections ahead, in other threads as
    `fmfusion run`'s readers do: the map is the one plain frames make. A frame prepared under other block
    parameters (here a wider truncation band) is counted again: the first frame sizes the map, so its stale extent
    would size it wrong. Frames prepared without detections take them at `integrate`, never twice."""
    import fmfusion_jax.mapping.capacity as capacity

    scene_dir, detections, config = room
    folder = DetectionFolder(detections)
    frames = _frames(scene_dir, config)
    # a first pool too small for this room, so that the growth check reads the prepared extents too (it grows
    # into the layout the room-sized first pool has: one more layout to compile, not two)
    monkeypatch.setattr(capacity, "FIRST_POOL_FACTOR", 2)
    plain, fed_prepared = Mapper(config), Mapper(config)
    wider = config.model_copy(update={"tsdf": config.tsdf.model_copy(update={"sdf_trunc": 3 * config.tsdf.sdf_trunc})})
    with concurrent.futures.ThreadPoolExecutor(max_workers=2) as reader:
        # odd frames prepared with their detections, even ones without (given to integrate)
        prepared = list(reader.map(lambda f: fed_prepared.prepare(f, folder(f) if f.index % 2 else None), frames))
    assert prepared[1].batch is not None and prepared[0].batch is None
    assert all(isinstance(leaf, jax.Array) for leaf in jax.tree.leaves((prepared[1].inputs, prepared[1].batch)))  # sent
    stale = Mapper(wider).prepare(frames[0])
    assert stale.block_extent[0] > prepared[0].block_extent[0]
    prepared[0] = stale
    with pytest.raises(UserError, match="detections given twice"):
        Mapper(config).integrate(prepared[1], folder(frames[1]))
    for frame, ready in zip(frames, prepared):
        plain.integrate(frame, folder.get(frame.name))
        fed_prepared.integrate(ready, None if ready.detections is not None else folder(frame))
    assert fed_prepared.detection_frames == plain.detection_frames == len(frames)
    assert fed_prepared.growths == plain.growths >= 1 and fed_prepared.map_config == plain.map_config
    for a, b in zip(jax.tree.leaves(fed_prepared.state), jax.tree.leaves(plain.state)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert _key(fed_prepared.instances()) == _key(plain.instances())


def test_sample_block_count_matches_the_frames_it_samples(room):
    """The runner's pool estimate from sampled depth: the blocks of the sampled frames, within the sampling's
    coarseness (every 8th pixel there, every 4th in the engine's block finder)."""
    scene_dir, _, config = room
    scene = open_scene(scene_dir, depth_max=config.dataset.depth_max)
    sample = scene.sample_depth(max_frames=len(scene), pixel_step=8)
    layout = build_map_config(config, *scene.bounds(sample=sample), SPEC.height, SPEC.width)
    estimate = sample_block_count(sample.points_world, sample.ray_origins, layout)
    keys = np.concatenate([frame_block_keys(frame, layout) for frame in scene.frames()])
    truth = len(np.unique(keys, axis=0))
    assert 0.7 * truth <= estimate <= 1.05 * truth, (estimate, truth)
    assert initial_pool_blocks(estimate, 1 << 16) >= 1.25 * estimate
    assert initial_pool_blocks(10**9, 4096) == 4096


def test_snapshot_mid_sequence_leaves_the_map_unchanged(room):
    scene_dir, detections, config = room
    folder = DetectionFolder(detections)
    frames = _frames(scene_dir, config)
    plain, looked_at = Mapper(config), Mapper(config)
    for position, frame in enumerate(frames):
        plain.integrate(frame, folder.get(frame.name))
        looked_at.integrate(frame, folder.get(frame.name))
        if position in (4, 9):
            snapshot = looked_at.instances()
            assert snapshot and all(np.isclose(i.distribution.sum(), 1.0) for i in snapshot)
    for a, b in zip(jax.tree.leaves(plain.state), jax.tree.leaves(looked_at.state)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert _key(plain.instances()) == _key(looked_at.instances())
    plain.finalize()
    with pytest.raises(UserError, match="finalized"):
        plain.integrate(frames[0])


def test_save_mid_sequence_and_resume(room, tmp_path):
    scene_dir, detections, config = room
    folder = DetectionFolder(detections)
    frames = _frames(scene_dir, config)
    whole, first = Mapper(config), Mapper(config)
    for frame in frames:
        whole.integrate(frame, folder.get(frame.name))
    for frame in frames[:7]:
        first.integrate(frame, folder.get(frame.name))
    first.save(tmp_path / "map.npz")
    resumed = Mapper.load(tmp_path / "map.npz")
    assert resumed.frames_integrated == 7 and resumed.detection_frames == first.detection_frames
    for frame in frames[7:]:
        resumed.integrate(frame, folder.get(frame.name))
    assert _key(resumed.instances()) == _key(whole.instances())
    mesh = resumed.extract_mesh()
    points, colors = resumed.extract_point_cloud()
    assert len(mesh.vertices) > 1000 and len(mesh.faces) > 1000 and points.shape[1] == 3 and len(colors) == len(points)


def test_arrays_are_a_frame(room):
    """Depth/colour/pose/K arrays integrate exactly as the reader's RGBDFrame."""
    scene_dir, detections, config = room
    frames = _frames(scene_dir, config)[:3]
    folder = DetectionFolder(detections)
    by_frame, by_arrays = Mapper(config), Mapper(config, intrinsics=frames[0].intrinsics.matrix)
    for frame in frames:
        by_frame.integrate(frame, folder.get(frame.name))
        fused = by_arrays.integrate(
            detections=folder.get(frame.name),
            depth=frame.depth,
            color=frame.color,
            T_world_camera=frame.T_world_camera,
            name=frame.name,
        )
        assert fused
    assert _key(by_frame.instances()) == _key(by_arrays.instances())


def test_detection_schedule_is_applied(room):
    """With the motion schedule, a frame taken where the last detections were fused is not due."""
    scene_dir, detections, config = room
    frame = _frames(scene_dir, config)[0]
    detections_0 = DetectionFolder(detections).get(frame.name)
    mapper = Mapper(as_config({"base": "demo", "detections": {"schedule": "motion"}}))
    assert mapper.detection_due(frame.T_world_camera)
    assert mapper.integrate(frame, detections_0)
    assert not mapper.detection_due(frame.T_world_camera)
    assert not mapper.integrate(frame, detections_0)  # same pose: ignored
    assert mapper.detection_frames == 1 and mapper.frames_integrated == 2


def test_bad_inputs_are_clear_errors(room):
    scene_dir, _, config = room
    frame = _frames(scene_dir, config)[0]
    mapper = Mapper(config, intrinsics=frame.intrinsics)
    with pytest.raises(UserError, match="float metres"):
        mapper.integrate(depth=(frame.depth * 1000).astype(np.uint16), T_world_camera=frame.T_world_camera)
    with pytest.raises(UserError, match="millimetres"):
        mapper.integrate(depth=frame.depth * 1000, T_world_camera=frame.T_world_camera)
    skewed = frame.T_world_camera.copy()
    skewed[:3, :3] *= 2.0
    with pytest.raises(UserError, match="not a rigid transform"):
        mapper.integrate(depth=frame.depth, T_world_camera=skewed)
    with pytest.raises(UserError, match="intrinsics are for"):
        Mapper(config, intrinsics=frame.intrinsics).integrate(depth=frame.depth[:100], T_world_camera=frame.T_world_camera)
    with pytest.raises(UserError, match="empty"):
        Mapper(config).instances()
    with pytest.raises(UserError, match="prepare: expected an RGBDFrame"):
        mapper.prepare(frame.depth)
    lost = dataclasses.replace(frame, T_world_camera=np.full((4, 4), np.nan))  # checked before it can size the map
    for call in (mapper.prepare, mapper.integrate):
        with pytest.raises(UserError, match="T_world_camera: the pose is not finite"):
            call(lost)
    with pytest.raises(UserError, match="detection masks are"):  # masks of another image size
        mapper.prepare(frame, FrameDetections("x", np.zeros((1, 8, 8), bool), [{"chair": 0.9}], np.zeros((1, 4), np.float32)))
    with pytest.raises(UserError):
        as_config({"detections": {"no_such_knob": 1}})


def test_silent_api_inputs_are_refused_or_warned(room, caplog):
    """The Python API applies the file readers' rules: a transposed pose, negative depth and scores outside [0, 1]
    are UserErrors; an empty depth image, another frame's detections and labels outside the vocabulary warn."""
    scene_dir, detections, config = room
    frame = _frames(scene_dir, config)[0]
    mapper = Mapper(config, intrinsics=frame.intrinsics)
    with pytest.raises(UserError, match="transposed"):
        mapper.integrate(depth=frame.depth, T_world_camera=frame.T_world_camera.T)
    with pytest.raises(UserError, match="negative"):
        mapper.integrate(depth=-frame.depth, T_world_camera=frame.T_world_camera)
    good = DetectionFolder(detections).get(frame.name)
    assert good is not None and good.num_detections
    scored = dataclasses.replace(good, labels=[{name: 7.0 for name in labels} for labels in good.labels])
    with pytest.raises(UserError, match=r"score of .* must be a number in \[0, 1\]"):
        mapper.integrate(frame, scored)
    with caplog.at_level("WARNING", logger="fmfusion_jax.mapping"):
        mapper.integrate(depth=np.full_like(frame.depth, np.nan), T_world_camera=frame.T_world_camera)
        other = dataclasses.replace(good, frame_name="frame-999999")
        renamed = dataclasses.replace(other, labels=[{"sofa-bed": 0.8} for _ in other.labels])
        Mapper(config).integrate(frame, renamed)
    text = caplog.text
    assert "depth pixels are valid" in text and "another frame" in text and "'sofa-bed' is not one of" in text


def test_config_from_a_dict():
    nested = as_config({"detections": {"every": 3, "schedule": "every"}, "tsdf.max_weight": 100.0})
    assert nested.detections.every == 3 and nested.detections.schedule == "every" and nested.tsdf.max_weight == 100.0
    assert as_config(None) == load_config("scannet") and as_config("scenenn") == load_config("scenenn")


def test_grow_state_keeps_every_voxel_and_row(room):
    """A state copied into a wider index and bigger pool and table holds the same blocks and instances."""
    scene_dir, detections, config = room
    frames = _frames(scene_dir, config)[:4]
    folder = DetectionFolder(detections)
    mapper = Mapper(config)
    for frame in frames:
        mapper.integrate(frame, folder.get(frame.name))
    old = mapper.map_config
    lo, hi = growth.bounds_block_range(old)
    new = growth.config_for_block_range(old, lo - np.array([3, 0, 1]), hi + np.array([0, 2, 0]))
    new = dataclasses.replace(new, block_capacity=2 * old.block_capacity, instance_capacity=2 * old.instance_capacity)
    grown = growth.grow_state(mapper.state, old, new)
    state, n = mapper.state, int(mapper.state.blocks.num_blocks)
    np.testing.assert_array_equal(np.asarray(grown.blocks.tsdf)[:n], np.asarray(state.blocks.tsdf)[:n])
    np.testing.assert_array_equal(
        np.asarray(grown.blocks.block_coords)[:n], np.asarray(state.blocks.block_coords)[:n] + np.array([3, 0, 1])
    )
    index = np.asarray(grown.blocks.block_index)
    assert sorted(index[index >= 0].tolist()) == list(range(n))
    assert np.all(np.asarray(grown.blocks.weight)[n:] == 0) and np.all(np.asarray(grown.blocks.instance_id)[n:] == -1)
    k = old.instance_capacity
    np.testing.assert_array_equal(np.asarray(grown.instances.valid)[:k], np.asarray(state.instances.valid))
    assert not np.asarray(grown.instances.valid)[k:].any()
    with pytest.raises(ValueError, match="cannot shrink"):
        growth.grow_state(grown, new, old)
    shifted = dataclasses.replace(new, grid_origin=tuple(x + 0.001 for x in new.grid_origin))
    with pytest.raises(ValueError, match="whole blocks"):
        growth.block_offset(old, shifted)
    assert build_map_config(config, np.zeros(3), np.ones(3), 240, 320).block_capacity == config.tsdf.block_capacity


def test_batch_of_maps_equals_one_mapper_per_map(room, tmp_path):
    """Two rooms of different lengths fused in lock step by `MapperBatch` (one vmapped step, per-map schedules;
    the shorter room waits with None frames) give each room the map a `Mapper` of the same layout gives."""
    from fmfusion_jax.mapping.batch import MapperBatch

    scene_dir, detections, config = room
    # pools sized to these rooms (~5,400 blocks): each vmapped step selects whole pools, so their size sets its time
    config = demo_config(
        SPEC.num_frames, SPEC.width, SPEC.height, [*ROOM_OVERRIDES, "tsdf.block_capacity=6144", "tsdf.max_touched_blocks=3072"]
    )
    other_spec = dataclasses.replace(SPEC, seed=6, num_frames=10)
    other_dir = generated_scene(other_spec, tmp_path)
    other_detections = simulated_detections(other_dir, tmp_path / "detections", demo_noise(1, SPEC.width, SPEC.height))
    rooms = [
        (_frames(scene_dir, config), DetectionFolder(detections)),
        (_frames(other_dir, config), DetectionFolder(other_detections)),
    ]
    scenes = [open_scene(d, depth_max=config.dataset.depth_max).bounds() for d in (scene_dir, other_dir)]
    bounds = (np.minimum(scenes[0][0], scenes[1][0]), np.maximum(scenes[0][1], scenes[1][1]))

    batch = MapperBatch(config, 2, bounds=bounds, image_shape=(SPEC.height, SPEC.width))
    for t in range(SPEC.num_frames):
        frames = [seq[t] if t < len(seq) else None for seq, _ in rooms]
        batch.integrate(frames, [folder.get(f.name) if f is not None else None for f, (_, folder) in zip(frames, rooms)])
    results = batch.finalize()
    for i, (frames, folder) in enumerate(rooms):
        single = Mapper(config, bounds=bounds)
        for frame in frames:
            single.integrate(frame, folder.get(frame.name))
        expected = single.instances()
        assert len(expected) >= 2
        got = extract_map_instances(results[i])
        assert [(m.instance_id, m.class_index, m.observations) for m in got] == [
            (m.instance_id, m.class_index, m.observations) for m in expected
        ]
        for a, b in zip(got, expected):
            np.testing.assert_array_equal(a.points, b.points)
        assert results[i].detection_frames == single.detection_frames
        blocks = results[i].state.blocks
        assert int(blocks.dropped_blocks) == int(blocks.touched_overflow) == 0
        assert results[i].frames_integrated == len(frames)
        assert _key(batch.mapper(i).instances()) == _key(got)
    # sized for the blocks a map is expected to use, with the margin of a pool that cannot grow; `for_scenes` counts
    # them from a sample of each scene's frames, as `fmfusion batch --batch` does
    opened = [open_scene(d, depth_max=config.dataset.depth_max) for d in (scene_dir, other_dir)]
    expected = max(scene_extent(scene, config)[1] for scene in opened)
    pool = initial_pool_blocks(expected, 6144, FIXED_POOL_MARGIN)
    assert MapperBatch.for_scenes(opened, config).map_config == dataclasses.replace(batch.map_config, block_capacity=pool)
    sized = MapperBatch(config, 2, bounds=bounds, image_shape=(SPEC.height, SPEC.width), expected_blocks=2000)
    assert sized.map_config.block_capacity == 4096 == initial_pool_blocks(2000, 6144, FIXED_POOL_MARGIN)
    assert initial_pool_blocks(3000, 6144, FIXED_POOL_MARGIN) == 6144  # at most the config's
    assert sized.map_config == dataclasses.replace(batch.map_config, block_capacity=4096)
    with pytest.raises(UserError, match="expected 2 frames"):
        sized.integrate([None])


def test_a_batch_of_scenes_of_other_image_sizes_is_refused_before_anything_is_allocated():
    from fmfusion_jax.mapping.batch import MapperBatch

    scenes = [types.SimpleNamespace(intrinsics=types.SimpleNamespace(height=h, width=w)) for h, w in ((120, 160), (240, 320))]
    with pytest.raises(UserError, match=r"different image sizes \[\(120, 160\), \(240, 320\)\]"):
        MapperBatch.for_scenes(scenes, "demo")
