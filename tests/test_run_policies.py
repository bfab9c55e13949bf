"""`fmfusion run` as a long job: outputs replaced as a whole, bad frames skipped and listed, a stop between
frames that leaves a checkpoint, a resume that gives the uninterrupted map, and Ctrl-C in a real process."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fmfusion_jax.cli import main
from fmfusion_jax.errors import UserError
from fmfusion_jax.io.detections import DetectionFolder
from fmfusion_jax.io.scene import open_scene
from fmfusion_jax.run.checkpoint import Checkpoint
from fmfusion_jax.run.command import run_and_export
from fmfusion_jax.run.folder import partial_dir
from fmfusion_jax.run.outputs import chosen_outputs
from fmfusion_jax.run.scene_fusion import SceneFusion
from fmfusion_jax.simulation.demo_setup import demo_config, demo_noise
from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, generated_scene, simulated_detections

SPEC = GeneratedSceneSpec(seed=3, num_objects=4, num_frames=14, width=160, height=120)


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    root = tmp_path_factory.mktemp("policies")
    scene_dir = generated_scene(SPEC, root)
    detections = simulated_detections(scene_dir, root / "detections", demo_noise(0, SPEC.width, SPEC.height))
    config = demo_config(SPEC.num_frames, SPEC.width, SPEC.height, ["refinement.geometry_fusion_every=3"])
    return scene_dir, detections, config


def _run(room, out: Path, **options):
    scene_dir, detections, config = room
    scene = open_scene(scene_dir, depth_max=config.dataset.depth_max)
    folder = DetectionFolder(detections)
    return run_and_export(scene, lambda frame: folder.get(frame.name), config, out, progress=False, **options)


def _instances(out: Path) -> list:
    return json.loads((out / "instances.json").read_text())["instances"]


def _stop_after(frames: int):
    calls = []

    def should_stop() -> bool:
        calls.append(1)
        return len(calls) > frames

    return should_stop


def test_a_stopped_run_resumes_to_the_uninterrupted_map(room, tmp_path):
    reference = _run(room, tmp_path / "whole")
    assert reference.complete and not partial_dir(tmp_path / "whole").exists()

    out = tmp_path / "resumed"
    stopped = _run(room, out, should_stop=_stop_after(5))
    staging = partial_dir(out)
    assert not stopped.complete and stopped.folder == staging and not out.exists()
    assert Checkpoint(staging).info()["position"] == 5
    assert (staging / "instances.json").is_file()  # the map so far, to look at
    with pytest.raises(UserError, match="unfinished run .*frame 5 of 14.*--resume"):
        _run(room, out)
    resumed = _run(room, out, resume=True)
    assert resumed.complete and not staging.exists()
    assert _instances(out) == _instances(tmp_path / "whole")
    run = json.loads((out / "run.json").read_text())
    assert run["frames"] == json.loads((tmp_path / "whole" / "run.json").read_text())["frames"] == 14
    assert not (out / Checkpoint.MAP_FILE).exists()


def test_periodic_checkpoints_and_restart(room, tmp_path):
    out = tmp_path / "out"
    stopped = _run(room, out, checkpoint_every=4, should_stop=_stop_after(9))
    assert not stopped.complete and Checkpoint(partial_dir(out)).info()["position"] == 9
    with pytest.raises(UserError, match="another config"):
        scene_dir, detections, config = room
        other = (scene_dir, detections, demo_config(SPEC.num_frames, SPEC.width, SPEC.height))
        _run(other, out, resume=True)
    assert _run(room, out, restart=True).complete
    with pytest.raises(UserError, match="nothing to resume"):
        _run(room, out, resume=True)


def test_a_long_run_checkpoints_by_time_without_being_asked(room, tmp_path, monkeypatch):
    """Without --checkpoint-every, a run checkpoints once it has gone AUTO_CHECKPOINT_AFTER_S since the last one (so
    a SIGKILL loses at most that): here 0 s, so every frame; the checkpoint's cost spaces the next ones."""
    scene_dir, detections, config = room
    folder = DetectionFolder(detections)
    checkpoint = Checkpoint(tmp_path / "partial", 0)
    monkeypatch.setattr(SceneFusion, "AUTO_CHECKPOINT_AFTER_S", 0.0)
    saved: list[int] = []
    original = Checkpoint.save
    monkeypatch.setattr(
        Checkpoint,
        "save",
        lambda self, mapper, scene, position, skipped: (saved.append(position), original(self, mapper, scene, position, skipped)),
    )
    fusion = SceneFusion(open_scene(scene_dir), lambda frame: folder.get(frame.name), config, checkpoint=checkpoint)
    assert fusion.run()
    assert saved and saved[0] == 1 and checkpoint.exists()
    monkeypatch.setattr(SceneFusion, "AUTO_CHECKPOINT_AFTER_S", 3600.0)  # the default's scale: a short run never does
    saved.clear()
    assert SceneFusion(
        open_scene(scene_dir), lambda frame: folder.get(frame.name), config, checkpoint=Checkpoint(tmp_path / "p2", 0)
    ).run()
    assert saved == []


def test_a_second_run_replaces_the_first_runs_outputs_as_a_whole(room, tmp_path):
    out = tmp_path / "out"
    assert _run(room, out).complete
    (out / "instances" / "9999_stale.ply").write_text("from an earlier run")
    (out / "report.json").write_text("{}")
    assert _run(room, out).complete
    assert not (out / "instances" / "9999_stale.ply").exists() and "mAP50" in (out / "report.json").read_text()
    assert sorted(p.name for p in (out / "instances").iterdir()) == sorted(
        f"{i['id']:04d}_{i['class'].replace(' ', '_')}.ply" for i in _instances(out)
    )
    # run.json is true after the rename: its paths are inside OUT, and the frames' times are recorded as run
    run = json.loads((out / "run.json").read_text())
    assert (out / run["benchmark"]["predictions"]).is_file()
    assert run["frame_ms_as_run"]["frames"] == SPEC.num_frames and run["frame_ms_as_run"]["median"] > 0
    assert not (out.with_name(out.name + ".lock")).exists()  # the lock goes with the run


def test_a_run_writes_only_the_outputs_asked_for(room, tmp_path, capsys):
    """`--outputs`: the writers named (and run.json, the run's record); a name that is no output fails before any
    frame is fused."""
    out = tmp_path / "out"
    assert _run(room, out, outputs_chosen=chosen_outputs(["instances.json", "mesh.ply"])).complete
    assert sorted(p.name for p in out.iterdir()) == ["instances.json", "mesh.ply", "run.json"]
    assert len(_instances(out)) == json.loads((out / "run.json").read_text())["instances"]
    with pytest.raises(UserError, match="--outputs: unknown outputs mesh.obj .known: config.yaml, instances.json"):
        chosen_outputs(["mesh.obj"])
    scene_dir, detections, _ = room

    status = main(
        ["run", str(scene_dir), "--detections", str(detections), "--out", str(tmp_path / "cli"), "--outputs", "mesh.obj"]
    )
    assert status == 2 and "unknown outputs mesh.obj" in capsys.readouterr().err
    assert not (tmp_path / "cli").exists()


#: Run in a fresh process: a saved map's outputs written after `preload_writer_modules`, printing the modules that
#: the writing itself imported (outside the standard library).
_WRITER_IMPORTS = """
import sys
from pathlib import Path
from fmfusion_jax.io.scene import open_scene
from fmfusion_jax.mapping.builder import FusionResult
from fmfusion_jax.mapping.engine_configs import build_fusion_config
from fmfusion_jax.mapping.map_file import read_map_file
from fmfusion_jax.mapping.telemetry import StageTimer
from fmfusion_jax.run import outputs
from fmfusion_jax.run.command import write_outputs

scene_dir, map_file, out = sys.argv[1:]
saved = read_map_file(map_file)
result = FusionResult(saved.state, saved.map_config, build_fusion_config(saved.config), saved.config,
                      StageTimer(enabled=False), 14, 14, {})
scene = open_scene(Path(scene_dir))
result.floor()  # compiled here: not an import of the writers
outputs.preload_writer_modules().join()
before = set(sys.modules)
write_outputs(result, scene, Path(out))
new = {m.split(".")[0] for m in set(sys.modules) - before} - set(sys.stdlib_module_names)
print("new:", " ".join(sorted(n for n in new if not n.startswith("_"))))
"""


def test_the_writers_import_nothing_once_their_modules_are_preloaded(room, tmp_path):
    """`fmfusion run` imports the writers' modules while it fuses (`outputs.preload_writer_modules`): a module a
    writer imports that `WRITER_MODULES` lacks would be imported on the outputs' critical path again."""
    out = tmp_path / "out"
    assert _run(room, out).complete
    command = [sys.executable, "-c", _WRITER_IMPORTS, str(room[0]), str(out / "map_state.npz"), str(tmp_path / "again")]
    done = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "JAX_PLATFORMS": "cpu"}, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "new:"
    assert (tmp_path / "again" / "overview.png").is_file() and (tmp_path / "again" / "report.json").is_file()


def test_bad_frames_are_skipped_and_listed_or_stop_the_run(room, tmp_path):
    scene_dir, detections, config = room
    broken = tmp_path / "scene"
    shutil.copytree(scene_dir, broken)
    (broken / "depth" / "frame-000004.png").write_bytes(b"not a png")
    out = tmp_path / "out"
    outcome = _run((broken, detections, config), out)
    assert outcome.complete and "1 frames skipped" in outcome.summary
    run = json.loads((out / "run.json").read_text())
    assert run["frames"] == 13
    assert run["skipped_frames"] == [
        {"frame": "frame-000004", "reason": f"{broken / 'depth' / 'frame-000004.png'}: unreadable or corrupt image"}
    ]
    with pytest.raises(UserError, match=r"frame-000004\.png: unreadable or corrupt image"):
        _run((broken, detections, config), tmp_path / "stop", on_error="stop")


def test_a_folder_is_read_ahead_and_other_sources_only_on_due_frames(room, tmp_path, monkeypatch):
    """A detection folder (`reads_ahead`) is read by the run's reader threads (three here, as on a GPU's host):
    a corrupt file is reported only if its frame is due. Any other source (the detectors: their prompt window
    counts the detection frames) is called on the due frames alone, in order. Both make the same map."""
    scene_dir, detections, config = room
    config = config.model_copy(update={"detections": config.detections.model_copy(update={"schedule": "every", "every": 2})})
    scene = open_scene(scene_dir, depth_max=config.dataset.depth_max)
    broken = tmp_path / "detections"
    shutil.copytree(detections, broken)
    for name in ("frame-000003", "frame-000006"):  # frame 3 is not due, frame 6 is
        (broken / f"{name}_label.json").write_text("{not json")
    folder, clean = DetectionFolder(broken), DetectionFolder(detections)
    calls: list[str] = []

    def detector(frame):
        calls.append(frame.name)
        return None if frame.name == "frame-000006" else clean.get(frame.name)

    monkeypatch.setattr(SceneFusion, "READ_WORKERS", 3)
    read_ahead = run_and_export(scene, folder, config, tmp_path / "ahead", progress=False)
    in_order = run_and_export(scene, detector, config, tmp_path / "order", progress=False)
    assert calls == [f"frame-{i:06d}" for i in range(0, SPEC.num_frames, 2)]
    skipped = json.loads((tmp_path / "ahead" / "run.json").read_text())["skipped_frames"]
    assert [entry["frame"] for entry in skipped] == ["frame-000006"] and "detections skipped" in skipped[0]["reason"]
    assert read_ahead.complete and in_order.complete
    assert _instances(tmp_path / "ahead") == _instances(tmp_path / "order")


@pytest.fixture(scope="module")
def long_room(tmp_path_factory):
    """A room of 240 frames: seconds of fusion after the first frames, so that a signal sent then always finds the
    run under way."""
    root = tmp_path_factory.mktemp("long")
    spec = GeneratedSceneSpec(seed=4, num_objects=3, num_frames=240, width=160, height=120)
    scene_dir = generated_scene(spec, root)
    detections = simulated_detections(scene_dir, root / "detections", demo_noise(0, spec.width, spec.height))
    config_path = root / "config.yaml"
    config_path.write_text(demo_config(spec.num_frames, spec.width, spec.height).to_yaml())
    return scene_dir, detections, config_path


@pytest.mark.parametrize(("signum", "status"), [(signal.SIGINT, 130), (signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_a_stop_signal_stops_between_frames_writes_a_checkpoint_and_exits_128_plus_it(tmp_path, long_room, signum, status):
    """A real SIGINT (Ctrl-C), SIGTERM (docker stop, systemd, schedulers) or SIGHUP to a real `fmfusion run`
    process: status 128 + the signal, no traceback or crash, a checkpoint to resume from."""
    scene_dir, detections, config_path = long_room
    out = tmp_path / "out"
    command = [
        sys.executable,
        "-m",
        "fmfusion_jax.cli",
        "run",
        str(scene_dir),
        "--detections",
        str(detections),
        "--out",
        str(out),
        "--config",
        str(config_path),
        "--no-progress",
        "-v",
    ]
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "JAX_PLATFORMS": "cpu"}
    )
    started = time.monotonic()
    stderr_lines = []
    assert process.stderr is not None
    for line in process.stderr:  # wait until fusion is under way (each detection frame is logged at -v)
        stderr_lines.append(line)
        if ("detections," in line and "frame-000000" not in line) or time.monotonic() - started > 120:
            break
    process.send_signal(signum)
    stdout, rest = process.communicate(timeout=300)
    stderr = "".join(stderr_lines) + rest
    assert process.returncode == status, stderr  # 0 would mean the run ended before the signal: the room is too short
    assert "Traceback" not in stderr and "Segmentation" not in stderr
    assert "--resume" in stderr
    assert Checkpoint(partial_dir(out)).exists()
