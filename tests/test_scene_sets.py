"""Cached generated scenes and simulated detections (`simulation.scene_sets`)."""

import json

from fmfusion_jax.simulation.noise import NoiseModel
from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, prepare_generated


def test_prepared_scene_is_made_once_and_remade_when_its_parameters_change(tmp_path):
    spec = GeneratedSceneSpec(seed=5, num_objects=3, num_frames=4, width=96, height=72)
    noise = NoiseModel.preset("default", seed=1, min_mask_pixels=10)
    first = prepare_generated(spec, tmp_path, noise)
    assert (first.scene_dir / "pose" / "frame-000003.txt").is_file()
    assert json.loads((first.detections_dir / "simulation.json").read_text())["seed"] == 1
    stamp = (first.scene_dir / "scene_set.json").stat().st_mtime_ns
    detections_stamp = (first.detections_dir / "simulation.json").stat().st_mtime_ns

    again = prepare_generated(spec, tmp_path, noise)  # cached: nothing rewritten
    assert again == first
    assert (first.scene_dir / "scene_set.json").stat().st_mtime_ns == stamp
    assert (first.detections_dir / "simulation.json").stat().st_mtime_ns == detections_stamp

    longer = prepare_generated(GeneratedSceneSpec(5, 3, 6, 96, 72), tmp_path, noise.replace(missed_tag_prob=0.0))
    assert (longer.scene_dir / "pose" / "frame-000005.txt").is_file()
    record = json.loads((longer.detections_dir / "simulation.json").read_text())
    assert record["noise"]["missed_tag_prob"] == 0.0 and len(record["frames"]) == 6


def test_detections_of_part_of_the_scene_are_simulated_again(tmp_path):
    from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
    from fmfusion_jax.io.scene import open_scene
    from fmfusion_jax.simulation.scene_sets import generated_scene, simulated_detections
    from fmfusion_jax.simulation.simulate import simulate_scene

    scene_dir = generated_scene(GeneratedSceneSpec(seed=2, num_objects=2, num_frames=4, width=96, height=72), tmp_path)
    noise = NoiseModel.preset("default", seed=0, min_mask_pixels=10)
    out = tmp_path / "detections"
    simulate_scene(
        open_scene(scene_dir), load_scannet_ground_truth(scene_dir), out, noise, max_frames=2, progress=False
    )  # e.g. `fmfusion simulate --max-frames 2`
    simulated_detections(scene_dir, out, noise)
    assert len(json.loads((out / "simulation.json").read_text())["frames"]) == 4
