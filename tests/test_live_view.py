"""`fmfusion run --viewer-save FILE.rrd` records the live view headless; the Rerun SDK reads it back."""

from __future__ import annotations

import pytest

from fmfusion_jax import cli
from fmfusion_jax.simulation.demo_setup import demo_config, demo_noise
from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, generated_scene, simulated_detections


def test_viewer_save_records_the_camera_frames_detections_mesh_and_boxes(tmp_path):
    pytest.importorskip("rerun", reason="rerun-sdk is not installed (pip install -e '.[viewer]')")
    from rerun.chunk import RrdReader

    spec = GeneratedSceneSpec(seed=2, num_objects=3, num_frames=8, width=160, height=120)
    scene = generated_scene(spec, tmp_path)
    detections = simulated_detections(scene, tmp_path / "detections", demo_noise(0, spec.width, spec.height))
    config = tmp_path / "config.yaml"
    config.write_text(demo_config(spec.num_frames, spec.width, spec.height).to_yaml())
    recording = tmp_path / "live.rrd"
    argv = ["run", str(scene), "--detections", str(detections), "--out", str(tmp_path / "out"), "--config", str(config)]
    assert cli.main([*argv, "--viewer-save", str(recording), "--no-progress"]) == 0
    entities = {chunk.entity_path for chunk in RrdReader(recording).stream().to_chunks()}
    expected = {
        "/world/camera",
        "/world/camera/image",
        "/world/camera/image/rgb",
        "/world/camera/image/depth",
        "/world/camera/image/detections",
        "/world/camera/image/boxes",
        "/world/mesh",
        "/world/instances",
    }
    assert expected <= entities, expected - entities


def test_a_missing_viewer_is_a_one_line_error(tmp_path, capsys, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_rerun(name, *args, **kwargs):
        if name == "rerun" or name.startswith("rerun."):
            raise ImportError("no rerun here")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_rerun)
    from fmfusion_jax.errors import UserError
    from fmfusion_jax.viz.live import RerunView

    with pytest.raises(UserError, match=r"pip install -e '\.\[viewer\]'"):
        RerunView(save=tmp_path / "x.rrd")
