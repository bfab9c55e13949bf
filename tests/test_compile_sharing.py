"""Maps whose block index lies elsewhere share the compiled steps: the state carries the index's origin
(`VoxelBlocks.origin_block`), the steps are compiled for `MapConfig.compiled_layout()`, and the map is the one
the config's own origin gives, bit for bit."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from fmfusion_jax.engine import step
from fmfusion_jax.engine.config import GRID_SHAPE_BUCKET, MapConfig
from fmfusion_jax.engine.state import init_map_state

BASE = MapConfig(
    voxel_size=0.05,
    block_size=8,
    sdf_trunc=0.15,
    grid_origin=(-2.0, -2.0, -1.2),
    grid_shape=(12, 12, 8),
    block_capacity=512,
    max_touched_blocks=256,
    image_height=48,
    image_width=64,
    instance_capacity=8,
)


def _frame(config: MapConfig) -> step.FrameInputs:
    """A wall 1.5 m ahead of a camera at the world origin, with a bump, seen at 64x48."""
    rows, cols = np.mgrid[0 : config.image_height, 0 : config.image_width]
    depth = (1.5 + 0.2 * np.exp(-((rows - 24.0) ** 2 + (cols - 30.0) ** 2) / 60.0)).astype(np.float32)
    color = np.stack([rows * 4, cols * 3, np.full_like(rows, 90)], -1).astype(np.uint8)
    return step.FrameInputs(
        depth=depth,
        color=color,
        T_world_camera=np.eye(4, dtype=np.float32),
        intrinsics=np.array([50.0, 50.0, 32.0, 24.0], np.float32),
        frame_index=np.int32(0),
    )


def _integrate(config: MapConfig, compiled: MapConfig):
    return step.integrate_frame(init_map_state(config), _frame(config), compiled).blocks


def test_an_index_elsewhere_shares_the_compiled_step_and_gives_the_same_map():
    moved = dataclasses.replace(BASE, grid_origin=(-2.4, -1.6, -1.2))  # one block along -x, one along +y
    assert BASE.compiled_layout() == moved.compiled_layout() and BASE != moved
    compiled_before = step.integrate_frame._cache_size()
    here = _integrate(BASE, BASE.compiled_layout())
    there = _integrate(moved, moved.compiled_layout())
    assert step.integrate_frame._cache_size() - compiled_before <= 1  # one program for both (none if compiled before)
    n = int(here.num_blocks)
    assert n > 0 and int(there.num_blocks) == n and int(here.out_of_bounds) == int(there.out_of_bounds) == 0
    # the same world blocks in the same slots: index coordinates differ by the origins' offset
    np.testing.assert_array_equal(np.asarray(there.block_coords)[:n], np.asarray(here.block_coords)[:n] + [1, -1, 0])
    for name in ("tsdf", "weight", "color"):
        np.testing.assert_array_equal(np.asarray(getattr(there, name)), np.asarray(getattr(here, name)))
    # and the step compiled with the config's own origin (a constant) makes the same map
    own = _integrate(moved, moved)
    for name in ("block_coords", "tsdf", "weight", "color", "origin_block"):
        np.testing.assert_array_equal(np.asarray(getattr(own, name)), np.asarray(getattr(there, name)))


def test_an_origin_off_the_block_lattice_stays_compiled_in():
    odd = dataclasses.replace(BASE, grid_origin=(-2.03, -2.0, -1.2))
    assert not odd.origin_on_lattice and odd.compiled_layout() is odd
    blocks = _integrate(odd, odd.compiled_layout())
    assert int(blocks.num_blocks) > 0 and int(blocks.out_of_bounds) == 0


def test_for_bounds_rounds_the_index_shape_up_to_buckets():
    a = MapConfig.for_bounds((0.0, 0.0, 0.0), (3.1, 2.0, 1.0))
    b = MapConfig.for_bounds((5.0, -1.0, 0.3), (8.0, 0.9, 1.2))
    assert all(s % GRID_SHAPE_BUCKET == 0 for s in a.grid_shape) and a.grid_shape == b.grid_shape
    assert a.compiled_layout() == b.compiled_layout()
    lo, hi = a.grid_bounds
    assert np.all(lo <= 0.0) and np.all(hi >= (3.1, 2.0, 1.0))


def test_a_map_saved_before_the_state_carried_its_origin_loads():
    from fmfusion_jax.engine.serialization import state_from_arrays, state_to_arrays

    moved = dataclasses.replace(BASE, grid_origin=(-2.4, -1.6, -1.2))
    state = jax.device_get(step.integrate_frame(init_map_state(moved), _frame(moved), moved.compiled_layout()))
    arrays = state_to_arrays(state, moved)
    old = {k: v for k, v in arrays.items() if k != "blocks.origin_block"}
    loaded = state_from_arrays(old, moved)
    np.testing.assert_array_equal(np.asarray(loaded.blocks.origin_block), [-6, -4, -3])
    np.testing.assert_array_equal(np.asarray(loaded.blocks.tsdf), np.asarray(state.blocks.tsdf))
