"""The merge step and the geometry fusion compiled ahead (`mapping.compile_ahead`) are the executables their jitted
calls run: nothing is compiled again at the call."""

from __future__ import annotations

import dataclasses

import jax.monitoring

from fmfusion_jax.config import load_config
from fmfusion_jax.engine import step
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import init_map_state
from fmfusion_jax.mapping.compile_ahead import CompileAhead
from fmfusion_jax.mapping.engine_configs import build_fusion_config

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


def _compiles_of_calls(config: MapConfig, ahead: bool) -> list[str]:
    """The executables compiled while `refine` and `fuse_geometry` are called on an empty map of `config` (after
    they were compiled ahead for it, when `ahead`)."""
    fusion = build_fusion_config(load_config())
    state = init_map_state(config)
    if ahead:
        CompileAhead(state, config, fusion).wait_all()
    compiled: list[str] = []

    def listen(event: str, seconds: float, **kwargs) -> None:
        if event.endswith("backend_compile_duration"):
            compiled.append(str(kwargs.get("fun_name")))

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        state, _ = step.refine(state, config, fusion)
        step.fuse_geometry(state, config, step.fusion_on_device(fusion)).blocks.tsdf.block_until_ready()
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    return compiled


def test_the_steps_compiled_ahead_are_not_compiled_again_at_their_first_call():
    # capacities no other test uses: nothing compiled for them in this process yet
    fresh = dataclasses.replace(BASE, block_capacity=520, instance_capacity=12)
    assert _compiles_of_calls(fresh, ahead=True) == []
    # the control: without compiling ahead, the first calls compile both
    other = dataclasses.replace(BASE, block_capacity=528, instance_capacity=12)
    compiled = _compiles_of_calls(other, ahead=False)
    assert any("_merge_step" in name for name in compiled) and any("fuse_geometry" in name for name in compiled), compiled
