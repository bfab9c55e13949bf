"""`fmfusion bench`: the fusion step timed per stage on the real scene and on generated rooms, against
Open3D peers run on the same frames (host-side glue; the engine knows nothing of it).

- `stages`: the stages of `engine.step.fuse_detections` jitted one by one, and a per-frame timer;
- `scenes`: the scenes and their simulated detections (made once into a cache folder);
- `open3d_peer`: the reference pipeline on Open3D (one TSDF volume per instance) and VoxelBlockGrid;
- `worker`: one pipeline on one scene, in a process of its own (peak memory is that pipeline's);
- `sweep`: the per-object cost, controlled: one scene fused once per cap on the detections per frame;
- `report`: medians, the per-object line fits, the Markdown table; `run`: all of it in order.
"""
