"""Fusing a scene frame by frame through the Python API (`fmfusion_jax.Mapper`), as a robot loop would.

    python examples/fuse_with_mapper.py ../shared/data/scannet/scene0000_00 --detections outputs/sim0000 \
        --out outputs/mapper0000

The same map as `fmfusion run SCENE --detections DIR` (same config, same benchmark score), but the map here
grows as the camera explores instead of being sized from the scene's bounds up front; halfway through it
looks at the instances without disturbing the map. Writes mesh.ply and map.npz into --out, and prints the
ScanNet benchmark when the scene has ground truth.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fmfusion_jax import Mapper
from fmfusion_jax.io.detections import DetectionFolder
from fmfusion_jax.io.scene import open_dataset_scene, open_scene


def fuse(scene_dir: str | Path, detections_dir: str | Path, config="scannet", progress: bool = True) -> Mapper:
    """Every frame of the scene integrated into a new Mapper, detections read on the frames it fuses."""
    mapper = Mapper(config)
    dataset = mapper.config.dataset
    scene = open_dataset_scene(scene_dir, dataset)
    folder = DetectionFolder(detections_dir, image_shape=(scene.intrinsics.height, scene.intrinsics.width))
    for position, frame in enumerate(scene.frames()):
        # ask the schedule first: the detections (here a file, on a robot the models) only when they are fused
        detections = folder.get(frame.name) if mapper.detection_due(frame.T_world_camera) else None
        mapper.integrate(frame, detections)
        if progress and position == len(scene) // 2:
            snapshot = mapper.instances()  # finalized on a copy: the map goes on unchanged
            print(f"frame {position}: {len(snapshot)} instances so far", file=sys.stderr)
    mapper.finalize()
    return mapper


def score(scene_dir: str | Path, mapper: Mapper, instances):
    """The ScanNet benchmark of `instances` against the scene's ground truth (None without one)."""
    from fmfusion_jax.run.command import load_ground_truth
    from fmfusion_jax.run.outputs import score_instances

    scene = open_scene(scene_dir, layout=mapper.config.dataset.layout)
    gt = load_ground_truth(scene)
    if gt is None or isinstance(gt, str):
        return None
    _, result = score_instances(instances, gt, scene.name, mapper.config, mapper.label_sets)
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", help="a scene folder (ScanNet layout)")
    parser.add_argument("--detections", required=True, help="detection files (fmfusion simulate / detect)")
    parser.add_argument("--config", default="scannet", help="config name or YAML path (default: scannet)")
    parser.add_argument("--out", default="outputs/mapper", help="folder for mesh.ply and map.npz")
    args = parser.parse_args(argv)

    mapper = fuse(args.scene, args.detections, args.config)
    instances = mapper.instances()
    names = mapper.label_sets.class_names
    print(
        f"{mapper.frames_integrated} frames ({mapper.detection_frames} with detections fused), "
        f"{len(instances)} instances, the map grew {mapper.growths} times"
    )
    for instance in sorted(instances, key=lambda i: -i.confidence)[:10]:
        print(
            f"  {names[instance.class_index]:>16s}  confidence {instance.confidence:.2f}  "
            f"{len(instance.points)} voxels  seen {instance.observations} times"
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    mapper.extract_mesh().export(str(out / "mesh.ply"))
    mapper.save(out / "map.npz")
    scores = score(args.scene, mapper, instances)
    if scores is not None:
        print(f"ScanNet benchmark: AP {scores.mAP:.3f}  AP50 {scores.mAP50:.3f}  AP25 {scores.mAP25:.3f}")
    print(f"written: {out / 'mesh.ply'}, {out / 'map.npz'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
