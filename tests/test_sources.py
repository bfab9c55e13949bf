"""Detection sources: one chooser for a run's detections, the Mapper calling a source on due frames only, the
frames the schedule picks for the models, and `fmfusion detect`'s continue-or-refuse rule for its output folder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fmfusion_jax.apps.detect import RECORD_FILE, _frames_done
from fmfusion_jax.config import load_config
from fmfusion_jax.errors import UserError
from fmfusion_jax.io.detections import DetectionFolder, label_path
from fmfusion_jax.io.scene import open_scene
from fmfusion_jax.mapping.inputs import as_config
from fmfusion_jax.mapping.mapper import Mapper
from fmfusion_jax.mapping.schedule import scheduled_positions
from fmfusion_jax.simulation.demo_setup import demo_config, demo_noise
from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, generated_scene, simulated_detections
from fmfusion_jax.sources import ModelSource, open_detection_source

SPEC = GeneratedSceneSpec(seed=7, num_objects=3, num_frames=10, width=160, height=120)


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    root = tmp_path_factory.mktemp("sources")
    scene_dir = generated_scene(SPEC, root)
    detections = simulated_detections(scene_dir, root / "detections", demo_noise(0, SPEC.width, SPEC.height))
    config = demo_config(SPEC.num_frames, SPEC.width, SPEC.height)
    return scene_dir, detections, config


def test_one_chooser_for_files_and_clear_errors(room, tmp_path):
    scene_dir, detections, _ = room
    scene = open_scene(scene_dir)
    source = open_detection_source(scene, detections=detections)
    assert isinstance(source, DetectionFolder) and source.reads_ahead
    with pytest.raises(UserError, match="exactly one"):
        open_detection_source(scene)
    with pytest.raises(UserError, match="exactly one"):
        open_detection_source(scene, detections=detections, models=tmp_path)
    with pytest.raises(UserError, match="does not exist"):
        open_detection_source(scene, detections=tmp_path / "missing")
    with pytest.raises(UserError, match="no detection files"):
        open_detection_source(scene, detections=tmp_path)
    other = tmp_path / "other"
    other.mkdir()
    for file in Path(detections).iterdir():
        (other / file.name.replace("frame-", "image-")).write_bytes(file.read_bytes())
    with pytest.raises(UserError, match="matches a frame"):
        open_detection_source(scene, detections=other)
    with pytest.raises(UserError, match="models folder|neither"):
        open_detection_source(scene, models=tmp_path)  # an empty folder is no models folder


def test_the_mapper_calls_a_source_on_due_frames_only(room):
    scene_dir, detections, _ = room
    folder = DetectionFolder(detections)
    scene = open_scene(scene_dir)
    frames = list(scene.frames())
    config = as_config({"base": "demo", "detections": {"schedule": "every", "every": 3}})
    called: list[str] = []

    def source(frame):
        called.append(frame.name)
        return folder.get(frame.name)

    # sized as `fmfusion run` sizes a map: the layout other tests' runs of a generated room compile (no growth)
    by_source, by_detections = Mapper.for_scene(scene, config), Mapper.for_scene(scene, config)
    fused = [by_source.integrate(frame, source) for frame in frames]
    for frame in frames:
        by_detections.integrate(frame, folder.get(frame.name))
    assert called == [f.name for f in frames[::3]]
    assert fused == [i % 3 == 0 for i in range(len(frames))]
    assert [i.points.tobytes() for i in by_source.instances()] == [i.points.tobytes() for i in by_detections.instances()]
    with pytest.raises(UserError, match="detection source"):
        Mapper(config).integrate(frames[0], {"chair": 0.9})


def test_scheduled_positions_are_the_frames_the_mapper_fuses(room):
    scene_dir, detections, config = room
    scene = open_scene(scene_dir)
    motion = load_config("scannet", ["detections.schedule=motion", "detections.sparse_motion=0"])
    poses = scene.poses()
    positions = scheduled_positions(poses, motion)
    assert positions[0] == 0 and positions == sorted(set(positions))
    mapper = Mapper.for_scene(scene, config.model_copy(update={"detections": motion.detections}))
    folder = DetectionFolder(detections)
    fused = [i for i, frame in enumerate(scene.frames()) if mapper.integrate(frame, folder.get(frame.name))]
    assert fused == positions
    # a fixed stride: every 4th
    every = load_config("scannet", ["detections.schedule=every", "detections.every=4"])
    assert scheduled_positions(poses, every) == list(range(0, len(poses), 4))


def test_model_source_times_the_front_end():
    class FrontEnd:
        timings = {"detector": 0.0}

        def detect(self, frame):
            self.timings["detector"] += 0.002
            return frame

    source = ModelSource(FrontEnd())
    assert not source.reads_ahead
    assert source("a frame") == "a frame" and source("another") == "another"
    timings = source.timings_ms()
    assert source.frames == 2 and timings["detector"] == pytest.approx(2.0) and timings["front_end"] >= 0


def test_detect_continues_its_own_folder_and_refuses_others(tmp_path):
    record = {"scene": "s", "models": "m", "front_end": "closed_set", "settings": {"stride": 1}}
    out = tmp_path / "det"
    assert _frames_done(out, record, ["frame-000000"], label_path) == set()
    out.mkdir()
    (out / "thesis.tex").write_text("mine")
    with pytest.raises(UserError, match="did not write"):
        _frames_done(out, record, ["frame-000000"], label_path)
    (out / "thesis.tex").unlink()
    (out / RECORD_FILE).write_text(json.dumps(record))
    label_path(out, "frame-000000").write_text("{}")
    assert _frames_done(out, record, ["frame-000000", "frame-000001"], label_path) == {"frame-000000"}
    changed = {**record, "settings": {"stride": 2}}
    with pytest.raises(UserError, match="other settings"):
        _frames_done(out, changed, ["frame-000000"], label_path)
    assert np.array_equal(np.asarray(sorted(p.name for p in out.iterdir())), [RECORD_FILE, "frame-000000_label.json"])


def test_front_end_settings_become_manifest_overrides():
    config = load_config(
        "scannet", ["front_end.detector_score_threshold=0.3", "front_end.proposals=false", "front_end.threads=1"]
    )
    assert config.front_end.manifest_overrides() == {"threads": 1, "detector": {"score_threshold": 0.3}, "proposals": None}
    grid = load_config("scannet", ["front_end.proposal_grid=[4, 3]"]).front_end.manifest_overrides()
    assert grid == {"proposals": {"grid": [4, 3]}}
    assert load_config("scannet").front_end.manifest_overrides() == {}
    with pytest.raises(UserError):
        load_config("scannet", ["front_end.detector_score_threshold=1.5"])


def test_models_run_in_a_detection_thread_on_due_frames_in_order_and_make_the_same_map(room):
    import threading

    from fmfusion_jax.run.scene_fusion import fuse_scene

    scene_dir, detections, config = room
    motion = config.model_copy(update={"detections": load_config("scannet", ["detections.sparse_motion=0"]).detections})
    scene = open_scene(scene_dir)
    folder = DetectionFolder(detections)
    calls: list[tuple[str, str]] = []

    class Models:
        """Stands for a ModelSource: reads the files, as models would detect, in the detection thread."""

        reads_ahead, detects_ahead = False, True

        def __call__(self, frame):
            calls.append((frame.name, threading.current_thread().name))
            return folder.get(frame.name)

    by_models = fuse_scene(scene, Models(), motion, progress=False)
    by_files = fuse_scene(scene, folder, motion, progress=False)
    due = [scene.frame_names[p] for p in scheduled_positions(scene.poses(), motion)]
    assert [name for name, _ in calls] == due
    assert all(thread.startswith("fmfusion-detect") for _, thread in calls)
    assert by_models.detection_frames == by_files.detection_frames == len(due)
    for name in ("label_evidence", "observations", "valid"):
        np.testing.assert_array_equal(getattr(by_models.state.instances, name), getattr(by_files.state.instances, name))
    np.testing.assert_array_equal(by_models.state.blocks.instance_id, by_files.state.blocks.instance_id)


def test_batch_detects_each_scene_with_the_models_before_its_run(tmp_path):
    from fmfusion_jax.apps.batch import SIMULATED_DIR, Batch, run_scene

    scene = tmp_path / "scene0001_00"
    scene.mkdir()
    batch = Batch(
        [scene], tmp_path / "out", detections=None, simulate=False, models=tmp_path, run_options=("--set", "a.b=1", "--restart")
    )
    (task,) = batch.tasks
    assert task.detections == str(tmp_path / "out" / SIMULATED_DIR / "scene0001_00")
    command = task.detection_command(["fmfusion"])
    assert command == [
        "fmfusion",
        "detect",
        str(scene),
        "--models",
        str(tmp_path.resolve()),
        "--out",
        task.detections,
        "--no-progress",
        "--set",
        "a.b=1",
    ]  # fmfusion detect knows no --restart
    given = Batch([scene], tmp_path / "out", detections="{root}/det/{scene}", simulate=False)
    assert given.tasks[0].detection_command(["fmfusion"]) is None
    with pytest.raises(UserError, match="one of"):
        Batch([scene], tmp_path / "out", detections="d", simulate=False, models=tmp_path)
    record = run_scene(task)  # the scene folder is empty: the detect step fails, recorded, the run never starts
    assert record["status"] == "failed" and "detect" in json.dumps(record)


def test_grounded_sam_settings_come_from_the_config(tmp_path):
    from detectors import read_manifest

    (tmp_path / "ram.onnx").write_bytes(b"")  # the layout names the front end; nothing is loaded here
    config = load_config("scannet", ["front_end.box_threshold=0.5", "front_end.prompt_window=0"])
    overrides = config.front_end.manifest_overrides()
    assert overrides == {"grounding": {"box_threshold": 0.5, "prompt_window": 0}}
    manifest = read_manifest(tmp_path, overrides)
    assert manifest.front_end == "grounded_sam"
    assert manifest.grounding.box_threshold == 0.5 and manifest.grounding.prompt_window == 0
    assert manifest.grounding.text_threshold == 0.25  # FM-Fusion's, unless set
    (tmp_path / "models.yaml").write_text("front_end: grounded_sam\ngrounding: {nms_iou: 0.3}\n")
    with pytest.raises(UserError, match="unknown grounding key"):
        read_manifest(tmp_path)


def test_detection_files_named_like_no_frame_are_reported(room, tmp_path, caplog):
    scene_dir, detections, _ = room
    folder = tmp_path / "mixed"
    folder.mkdir()
    for file in Path(detections).iterdir():
        (folder / file.name).write_bytes(file.read_bytes())
    for file in list(folder.glob("frame-000003_*")):
        file.rename(file.with_name(file.name.replace("frame-000003", "frame-3")))
    with caplog.at_level("WARNING", logger="fmfusion_jax.sources"):
        open_detection_source(open_scene(scene_dir), detections=folder)
    assert "1 detection files" in caplog.text and "frame-3" in caplog.text


def test_numbers_yaml_reads_as_text_are_numbers():
    assert load_config("scannet", ["tsdf.voxel_size=2e-2"]).tsdf.voxel_size == 0.02
    assert load_config("scannet", ["tsdf.max_weight=1E2"]).tsdf.max_weight == 100.0
    assert load_config("scannet", ["label_fusion.likelihood=manual"]).label_fusion.likelihood == "manual"
