"""Memory handed back on a CPU host (`host_memory`): the unallocated pool rows' pages go back to the system,
and no value the engine reads changes.

Uses the analytic box room of `test_pipeline` (clean detections), 160x120 frames.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import jax
import numpy as np
import pytest
from test_pipeline import BoxRoom, build, clean_detections, make_frames, small_config

from fmfusion_jax import host_memory
from fmfusion_jax.engine import growth
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import init_map_state

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux") or jax.default_backend() != "cpu", reason="pages are given back on a Linux CPU host"
)


def _resident_mib() -> float:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * 4096 / 2**20


def _leaves(state) -> list[np.ndarray]:
    return [np.array(leaf) for leaf in jax.tree_util.tree_leaves(jax.device_get(state))]


def test_a_fresh_pool_gives_back_its_zero_rows_and_keeps_its_values():
    config = MapConfig(voxel_size=0.02, sdf_trunc=0.08, grid_shape=(8, 8, 8), block_capacity=4096, instance_capacity=8)
    state = init_map_state(config)
    before = _resident_mib()
    released = host_memory.release_unallocated_rows(state)
    after = _resident_mib()
    # weight, colour, instance weights and bits: all rows but the scratch row, page-aligned
    zero_bytes = sum(getattr(state.blocks, name).nbytes for name in host_memory.ZERO_POOL_FIELDS)
    assert released > 0.95 * zero_bytes
    assert before - after > 0.5 * released / 2**20
    for leaf, fresh in zip(_leaves(state), _leaves(init_map_state(config)), strict=True):
        np.testing.assert_array_equal(leaf, fresh)


def test_rows_that_are_not_zeros_keep_their_pages():
    config = MapConfig(voxel_size=0.02, sdf_trunc=0.08, grid_shape=(8, 8, 8), block_capacity=1024, instance_capacity=8)
    state = init_map_state(config)
    weight = state.blocks.weight.at[700, 3].set(2.0)  # an unallocated row that breaks the invariant
    state = state._replace(blocks=state.blocks._replace(weight=weight))
    released = host_memory.release_unallocated_rows(state)
    others = sum(getattr(state.blocks, name).nbytes for name in host_memory.ZERO_POOL_FIELDS if name != "weight")
    assert others * 0.95 < released <= others
    assert float(np.asarray(state.blocks.weight)[700, 3]) == 2.0


def test_a_map_fused_after_the_release_is_the_map_fused_without_it(monkeypatch):
    room = BoxRoom()
    frames = make_frames(room, 5, seed=3)
    config = small_config()

    def fuse():
        builder = build(config, room)
        for frame in frames:
            builder.add_frame(frame, clean_detections(frame, 3))
        return builder.result().state

    released = fuse()
    monkeypatch.setattr(host_memory, "release_unallocated_rows", lambda state: 0)
    kept = fuse()
    assert int(released.blocks.num_blocks) > 0
    for a, b in zip(_leaves(released), _leaves(kept), strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_batch_of_maps_is_left_alone():
    config = MapConfig(voxel_size=0.02, sdf_trunc=0.08, grid_shape=(4, 4, 4), block_capacity=64, instance_capacity=4)
    batch = jax.tree.map(lambda leaf: np.stack([leaf, leaf]), jax.device_get(init_map_state(config)))
    assert host_memory.release_unallocated_rows(batch) == 0


def test_a_grown_pool_gives_back_its_new_rows():
    # `Mapper` releases the state that growth returns: its new rows were written with their initial values
    config = MapConfig(voxel_size=0.02, sdf_trunc=0.08, grid_shape=(4, 4, 4), block_capacity=256, instance_capacity=4)
    bigger = dataclasses.replace(config, block_capacity=2048)
    grown = growth.grow_state(init_map_state(config), config, bigger)
    assert host_memory.release_unallocated_rows(grown) > 0
    for leaf, fresh in zip(_leaves(grown), _leaves(init_map_state(bigger)), strict=True):
        np.testing.assert_array_equal(leaf, fresh)


def test_compilations_count_each_new_step_once():
    before = host_memory.compilations()
    step = jax.jit(lambda x: x * 3.25 + 0.5)  # a new function: compiled (or loaded from the compile cache) once
    step(np.ones(7, np.float32)).block_until_ready()
    after_first = host_memory.compilations()
    step(np.ones(7, np.float32)).block_until_ready()
    assert after_first >= before + 1
    assert host_memory.compilations() == after_first


def test_the_command_caps_the_heap_arenas_unless_the_environment_chose():
    """`limit_malloc_arenas` (the `fmfusion` entry calls it) sets glibc's cap in a fresh process; a
    `MALLOC_ARENA_MAX` in the environment is the user's choice and is left to glibc."""
    code = "from fmfusion_jax import host_memory; print(host_memory.limit_malloc_arenas())"
    env = {key: value for key, value in os.environ.items() if key != "MALLOC_ARENA_MAX"}
    for chosen, expected in ((None, "True"), ("4", "False")):
        if chosen is not None:
            env["MALLOC_ARENA_MAX"] = chosen
        done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
        assert done.returncode == 0 and done.stdout.strip() == expected, done.stderr
