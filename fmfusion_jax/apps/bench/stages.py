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
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.detections import DetectionBatch
from fmfusion_jax.engine.state import MapState
from fmfusion_jax.pipeline import StageTimer

#: Stages of one detection frame, in order (keys of the timings; `tsdf` is `step.integrate_frame`).
FUSION_STAGES = ("tsdf", "detections", "projection", "association", "label_fusion", "integration")

detection_image = jax.jit(step.detection_image, static_argnames=("config",))
project_instances = jax.jit(step.project_instances, static_argnames=("config",))
associate = jax.jit(step.associate, static_argnames=("config",))
# the table and the pool are updated in place, as inside the fused step (no copy of the voxel pool)
fuse_table = jax.jit(step.fuse_table, static_argnames=("config",), donate_argnames=("table",))
integrate_instance_votes = jax.jit(
    step.integrate_instance_votes, static_argnames=("config",), donate_argnames=("blocks", "table")
)
frame_stats = jax.jit(step.frame_stats)


def staged_fuse_detections(timer: StageTimer):
    """A function with the signature of `step.fuse_detections` that runs its stages one jit at a time,
    each timed by `timer` under its `FUSION_STAGES` name. The state is donated, as to the fused step."""

    def fuse(
        state: MapState,
        frame: step.FrameInputs,
        batch: DetectionBatch,
        likelihood: jax.Array,
        config: MapConfig,
        fusion: step.FusionConfig,
    ) -> tuple[MapState, step.FrameStats]:
        state = timer.run("tsdf", step.integrate_frame, state, frame, config)
        det_image, up_heights = timer.run(
            "detections", detection_image, frame, batch, likelihood, state.blocks.up_heights, config, fusion
        )
        state = state._replace(blocks=state.blocks._replace(up_heights=up_heights))
        seen = timer.run("projection", project_instances, state.blocks, frame, config)
        matches = timer.run("association", associate, det_image, seen, batch.valid, state.instances.valid, config, fusion)
        table, update = timer.run(
            "label_fusion",
            fuse_table,
            state.instances,
            matches,
            batch.label_scores,
            likelihood,
            frame.frame_index,
            config,
            fusion,
        )
        blocks, table = timer.run(
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
        return state._replace(blocks=blocks, instances=table), frame_stats(matches, update, table, blocks)

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
