"""The stages of `engine.step.fuse_detections` jitted one by one, and a timer that keeps each frame's times.

`fuse_detections` is one jit over the stage functions of `engine.step`; here each stage is its own jit,
so that its time can be taken alone (`jax.block_until_ready` after each). Composed in the same order
they give the same map as the fused step (tests/test_bench.py checks it), only slower: every stage
boundary is a materialized array and a dispatch. The fused step is the figure that counts; the stages
say where its time goes.
"""

from __future__ import annotations

import dataclasses

import jax

from fmfusion_jax.engine import step
from fmfusion_jax.mapping.telemetry import StageTimer

#: Stages of one detection frame, in order (keys of the timings; `tsdf` is `step.integrate_frame`).
FUSION_STAGES = step.DETECTION_STAGES

#: Each stage of `step.detection_frame` as its own jit, by the name its `run` hook is given. The table and the
#: pool are updated in place, as inside the fused step (no copy of the voxel pool).
STAGE_JITS = {
    "tsdf": step.integrate_frame,
    "detections": jax.jit(step.detection_image, static_argnames=("config",)),
    "projection": jax.jit(step.project_instances, static_argnames=("config",)),
    "association": jax.jit(step.associate, static_argnames=("config",)),
    "label_fusion": jax.jit(step.fuse_table, static_argnames=("config",), donate_argnames=("table",)),
    "integration": jax.jit(step.integrate_instance_votes, static_argnames=("config",), donate_argnames=("blocks", "table")),
    "statistics": jax.jit(step.frame_stats),
}


def staged_fuse_detections(timer: StageTimer):
    """A function with the signature of `step.fuse_detections` that runs the stages of `step.detection_frame` one
    jit at a time, each timed by `timer` under its `FUSION_STAGES` name (the statistics untimed). The state is
    donated, as to the fused step."""

    def run(name: str, stage, *args):
        del stage  # its jit in STAGE_JITS
        if name in FUSION_STAGES:
            return timer.run(name, STAGE_JITS[name], *args)
        return STAGE_JITS[name](*args)

    def fuse(state, frame, batch, likelihood, config, fusion):
        return step.detection_frame(state, frame, batch, likelihood, config, fusion, run=run)

    return fuse


@dataclasses.dataclass
class FrameTimer(StageTimer):
    """A `StageTimer` that also keeps each frame's stage times, to compare pipelines frame by frame.

    `frames[i]` maps a stage name to its milliseconds in frame `i` (summed when it ran more than once);
    the calls that compiled (a stage's first, and its first after the map grew) are kept apart, in `compiled[i]`.
    """

    frames: list[dict[str, float]] = dataclasses.field(default_factory=list)
    compiled: list[dict[str, float]] = dataclasses.field(default_factory=list)

    def start_frame(self) -> None:
        self.frames.append({})
        self.compiled.append({})

    def record(self, name: str, elapsed_ms: float, compiled: bool) -> None:
        super().record(name, elapsed_ms, compiled)
        where = self.compiled[-1] if compiled else self.frames[-1]
        where[name] = where.get(name, 0.0) + elapsed_ms


__all__ = ["FUSION_STAGES", "FrameTimer", "staged_fuse_detections"]
