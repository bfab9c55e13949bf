"""`fmfusion run SCENE --out OUT` without `--detections` or `--models`: the map of the geometry alone (every frame
into the TSDF, no instance), its outputs, and `Mapper.load` continuing it with detections."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import yaml

from fmfusion_jax import cli
from fmfusion_jax.io.detections import DetectionFolder
from fmfusion_jax.io.scene import open_scene
from fmfusion_jax.mapping.mapper import Mapper
from fmfusion_jax.simulation.demo_setup import demo_config, demo_noise
from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, generated_scene, simulated_detections

SPEC = GeneratedSceneSpec(seed=5, num_objects=3, num_frames=8, width=128, height=96)


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    root = tmp_path_factory.mktemp("geometry_only")
    scene_dir = generated_scene(SPEC, root)
    return scene_dir, root


def test_a_run_without_detections_builds_the_geometry_alone(room, tmp_path, capsys, caplog):
    scene_dir, root = room
    out, config = tmp_path / "out", tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(demo_config(SPEC.num_frames, SPEC.width, SPEC.height).to_dict()))
    with caplog.at_level(logging.WARNING):
        code = cli.main(["run", str(scene_dir), "--out", str(out), "--config", str(config), "--no-progress"])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    assert "no detection source given" in caplog.text and "geometry alone" in caplog.text
    assert "geometry only: no detection source was given" in printed.out
    assert "check the detections folder" not in printed.out
    for name in ("mesh.ply", "map_state.npz", "run.json", "config.yaml", "instances.json"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "run.json").read_text())
    assert summary["frames"] == SPEC.num_frames and summary["detection_frames"] == 0 and summary["instances"] == 0
    instances = json.loads((out / "instances.json").read_text())
    assert not (instances if isinstance(instances, list) else instances.get("instances"))
    header = (out / "mesh.ply").read_bytes()[:400].decode("ascii", "replace")
    faces = int(header.split("element face ")[1].split()[0])
    assert faces > 100  # the room's walls and objects

    # the saved map continues: Mapper.load, then frames with detections give instances
    detections = DetectionFolder(
        simulated_detections(scene_dir, root / "detections", demo_noise(0, SPEC.width, SPEC.height)),
        image_shape=(SPEC.height, SPEC.width),
    )
    mapper = Mapper.load(out / "map_state.npz")
    assert mapper.frames_integrated == SPEC.num_frames and mapper.detection_frames == 0
    scene = open_scene(scene_dir)
    for frame in scene.frames():
        mapper.integrate(frame, detections.get(frame.name))
    mapper.finalize()
    assert mapper.detection_frames > 0 and len(mapper.instances()) >= 1
    assert np.isfinite(mapper.extract_point_cloud()[0]).all()
