"""Saving a map and loading it back: exact leaves, the pool invariant, and fusion continued from the file.

Uses the analytic box room of `test_pipeline` (clean detections), 160x120 frames.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from fusion_helpers import load_map, resume_builder
from test_pipeline import BoxRoom, build, clean_detections, make_frames, small_config

from fmfusion_jax.engine.serialization import SCRATCH_SUFFIX, state_from_arrays, state_to_arrays
from fmfusion_jax.engine.state import init_map_state
from fmfusion_jax.errors import DataError
from fmfusion_jax.mapping.builder import FusionResult, MapBuilder
from fmfusion_jax.mapping.map_file import read_state_file, save_map, write_state_file


@pytest.fixture(scope="module")
def room_frames():
    room = BoxRoom()
    return room, make_frames(room, 6, seed=11)


def _detections(frame):
    return clean_detections(frame, 11)


def _assert_same_state(a, b):
    a, b = jax.device_get(a), jax.device_get(b)
    paths_a = jax.tree_util.tree_leaves_with_path(a)
    paths_b = jax.tree_util.tree_leaves_with_path(b)
    assert [p for p, _ in paths_a] == [p for p, _ in paths_b]
    for (path, x), (_, y) in zip(paths_a, paths_b):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape, path
        np.testing.assert_array_equal(x, y, err_msg=jax.tree_util.keystr(path))


def _fuse(builder, frames):
    for frame in frames:
        builder.add_frame(frame, _detections(frame))
    return builder


def _result(builder) -> FusionResult:
    return FusionResult(
        builder.state,
        builder.map_config,
        builder.fusion_config,
        builder.config,
        builder.timer,
        builder.frames_integrated,
        builder.detection_frames,
        dict(builder.counters),
    )


def test_unallocated_pool_slots_stay_at_their_initial_values(room_frames):
    room, frames = room_frames
    config = small_config(**{"refinement.geometry_fusion_every": 2})
    builder = _fuse(build(config, room), frames)
    result = builder.result()  # merges, removals, geometry fusion, post-merge: every pass ran
    state = jax.device_get(result.state)
    initial = jax.device_get(init_map_state(result.map_config))
    n, capacity = int(state.blocks.num_blocks), result.map_config.block_capacity
    assert 0 < n < capacity - 1
    for name in ("block_coords", "tsdf", "weight", "color", "instance_id", "instance_weight"):
        np.testing.assert_array_equal(
            getattr(state.blocks, name)[n : capacity - 1], getattr(initial.blocks, name)[n : capacity - 1], err_msg=name
        )
    # so only the allocated rows and the scratch row are kept
    arrays = state_to_arrays(result.state, result.map_config)
    assert arrays["blocks.tsdf"].shape[0] == n and arrays["blocks.tsdf" + SCRATCH_SUFFIX].shape[0] == 1
    _assert_same_state(state_from_arrays(arrays, result.map_config), result.state)
    # without the config the layout comes from the shapes
    _assert_same_state(state_from_arrays(state_to_arrays(result.state), result.map_config), result.state)


def test_a_pool_array_breaking_the_invariant_is_saved_whole(room_frames):
    room, frames = room_frames
    builder = _fuse(build(small_config(), room), frames[:2])
    state = jax.device_get(builder.state)
    n = int(state.blocks.num_blocks)
    tsdf = np.array(state.blocks.tsdf)
    tsdf[n + 1, 3] = 0.25  # an unallocated slot that is not at its initial value
    odd = state._replace(blocks=state.blocks._replace(tsdf=tsdf))
    arrays = state_to_arrays(odd, builder.map_config)
    assert arrays["blocks.tsdf"].shape[0] == builder.map_config.block_capacity
    assert "blocks.tsdf" + SCRATCH_SUFFIX not in arrays
    assert arrays["blocks.weight"].shape[0] == n
    _assert_same_state(state_from_arrays(arrays, builder.map_config), odd)


def test_save_load_round_trip_is_exact_and_keeps_the_configs(room_frames, tmp_path):
    room, frames = room_frames
    config = small_config()
    result = _fuse(build(config, room), frames).result()
    path = save_map(tmp_path / "map_state.npz", result)
    state, map_config, loaded_config = load_map(path)
    _assert_same_state(state, result.state)
    assert map_config == result.map_config and hash(map_config) == hash(result.map_config)
    assert loaded_config == config
    # an ordinary npz: numpy opens it without pickle
    with np.load(path, allow_pickle=False) as data:
        assert "blocks.tsdf" in data.files and "__metadata__" in data.files


def test_continuing_from_a_saved_map_equals_fusing_without_a_break(room_frames, tmp_path):
    room, frames = room_frames
    config = small_config(**{"refinement.geometry_fusion_every": 2, "refinement.merge_every": 2})
    straight = _fuse(build(config, room), frames).result()

    first = _fuse(build(config, room), frames[:3])  # stops between the schedules' events
    save_map(tmp_path / "half.npz", _result(first))
    resumed = resume_builder(tmp_path / "half.npz")
    assert (resumed.frames_integrated, resumed.detection_frames) == (3, 3)
    continued = _fuse(resumed, frames[3:]).result()
    _assert_same_state(continued.state, straight.state)
    assert continued.counters == straight.counters

    # the plain API: MapBuilder(state=...) from load_map
    state, map_config, loaded_config = load_map(tmp_path / "half.npz")
    builder = MapBuilder(loaded_config, map_config, state=state)
    builder.progress.frames_integrated, builder.progress.detection_frames = 3, 3
    _assert_same_state(_fuse(builder, frames[3:]).result().state, straight.state)


def test_a_map_saved_before_the_kept_census_loads_and_continues_to_the_same_map(room_frames):
    """Older files lack the blocks' instance bits, their geometry-stale flags and the merge's kept census: the bits
    are rebuilt from the ids, every block loads stale (the next geometry fusion visits all) and the census as not
    valid (the next merge step counts it); fusion then goes on to the same map."""
    from test_pipeline import assert_same_map

    room, frames = room_frames
    config = small_config()
    straight = _fuse(build(config, room), frames).result()
    first = _result(_fuse(build(config, room), frames[:3]))  # as it stands after 3 frames (not finalized)
    arrays = state_to_arrays(first.state, first.map_config)
    assert bool(arrays["instances.census_valid"]) and "blocks.cell_owner" not in arrays
    assert "blocks.geometry_stale" in arrays
    old_keys = ("instances.census_", "blocks.instance_bits", "blocks.geometry_stale")
    old = {k: v for k, v in arrays.items() if not k.startswith(old_keys)}
    loaded = state_from_arrays(old, first.map_config)
    assert not bool(loaded.instances.census_valid) and np.asarray(loaded.blocks.geometry_stale).all()
    bits, ids = np.asarray(loaded.blocks.instance_bits), np.asarray(loaded.blocks.instance_id).astype(np.int64)
    block, voxel, slot = np.nonzero(ids >= 0)
    assert bits[block, ids[block, voxel, slot] % bits.shape[1]].all()
    assert bits.sum() == len({(b, i % bits.shape[1]) for b, i in zip(block, ids[block, voxel, slot])})  # exactly those
    builder = MapBuilder(config, first.map_config, state=loaded)
    builder.progress.frames_integrated, builder.progress.detection_frames = 3, 3
    continued = _fuse(builder, frames[3:]).result().state
    assert_same_map(continued, straight.state)
    assert bool(continued.instances.census_valid)


def test_bad_state_files_are_data_errors(tmp_path, room_frames):
    with pytest.raises(DataError, match="no such file"):
        load_map(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(DataError, match="not a readable"):
        load_map(tmp_path / "junk.npz")
    write_state_file(tmp_path / "other.npz", {"x": np.zeros(3)}, {"format": "something else"})
    with pytest.raises(DataError, match="not a map state file"):
        load_map(tmp_path / "other.npz")
    arrays, metadata = read_state_file(tmp_path / "other.npz")
    assert metadata == {"format": "something else"} and np.array_equal(arrays["x"], np.zeros(3))
    # a state whose arrays do not fit its config
    room, frames = room_frames
    result = _fuse(build(small_config(), room), frames[:1]).result()
    path = save_map(tmp_path / "map.npz", result)
    arrays, metadata = read_state_file(path)
    metadata["map_config"]["instance_capacity"] += 1
    write_state_file(tmp_path / "bad.npz", arrays, metadata)
    with pytest.raises(DataError, match="instances.valid"):
        load_map(tmp_path / "bad.npz")
