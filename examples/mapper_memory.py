"""Memory of a small map against a whole room's: a growing Mapper after N frames vs one sized up front.

    python examples/mapper_memory.py ../shared/data/scannet/scene0000_00 --frames 3

Each case runs in a process of its own and reports its peak resident memory (RSS) and the map state's
device bytes: (a) a growing `Mapper` fed the first N frames, (b) the same frames into the Mapper `fmfusion run`
makes (`Mapper.for_scene`: the whole scene's bounds, the pool sized from a sample of its depth), (c) the
growing Mapper over every frame of the scene. No detections: geometry only (the instance table is small either way).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys


def measure(scene_dir: str, frames: int | None, sized: bool, config: str) -> dict:
    from fmfusion_jax import Mapper, load_config, open_scene

    pipeline_config = load_config(config)
    dataset = pipeline_config.dataset
    scene = open_scene(scene_dir, layout=dataset.layout, depth_max=dataset.depth_max, max_frames=frames)
    if sized:  # sized from the whole scene, fed its first frames
        whole = open_scene(scene_dir, layout=dataset.layout, depth_max=dataset.depth_max)
        mapper = Mapper.for_scene(whole, pipeline_config)
    else:
        mapper = Mapper(config)
    for frame in scene.frames():
        mapper.integrate(frame)
    return {
        "frames": mapper.frames_integrated,
        "map_state_mib": mapper.map_config.memory_bytes() / 2**20,
        "blocks": int(mapper.state.blocks.num_blocks),
        "growths": mapper.growths,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene")
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--config", default="scannet")
    parser.add_argument("--case", choices=("small", "sized", "whole"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.case:
        frames = None if args.case == "whole" else args.frames
        print(json.dumps(measure(args.scene, frames, args.case == "sized", args.config)))
        return 0
    rows = {}
    for case in ("small", "sized", "whole"):
        out = subprocess.run(
            [sys.executable, __file__, args.scene, "--frames", str(args.frames), "--config", args.config, "--case", case],
            check=True,
            capture_output=True,
            text=True,
        ).stdout
        rows[case] = json.loads(out.strip().splitlines()[-1])
    titles = {
        "small": f"growing Mapper, {args.frames} frames",
        "sized": f"sized for the room, {args.frames} frames",
        "whole": "growing Mapper, every frame",
    }
    print("| map | frames | blocks | map state, MiB | peak RSS, MiB | growths |\n|---|---:|---:|---:|---:|---:|")
    for case, row in rows.items():
        print(
            f"| {titles[case]} | {row['frames']} | {row['blocks']} | {row['map_state_mib']:.0f} | "
            f"{row['peak_rss_mib']:.0f} | {row['growths']} |"
        )
    small, sized = rows["small"], rows["sized"]
    print(
        f"\n{args.frames}-frame map: {small['map_state_mib'] / sized['map_state_mib']:.1%} of the sized map's state, "
        f"{small['peak_rss_mib'] / sized['peak_rss_mib']:.1%} of its peak RSS"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
