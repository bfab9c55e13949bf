"""`fmfusion run` never replaces a folder it did not write: an input folder as --out, or a user's folder."""

from __future__ import annotations

import json

import pytest

from fmfusion_jax import cli
from fmfusion_jax.errors import UserError
from fmfusion_jax.run.folder import check_output_folder


@pytest.fixture
def inputs(tmp_path):
    scene, detections = tmp_path / "scene", tmp_path / "detections"
    scene.mkdir()
    detections.mkdir()
    (scene / "frame.txt").write_text("the user's data")
    (detections / "frame-000000_label.json").write_text("{}")
    return scene, detections


@pytest.mark.parametrize("which", ["scene", "detections", "parent"])
def test_an_input_folder_is_never_the_output(inputs, which, capsys):
    scene, detections = inputs
    out = {"scene": scene, "detections": detections, "parent": scene.parent}[which]
    code = cli.main(["run", str(scene), "--detections", str(detections), "--out", str(out), "--overwrite"])
    assert code == 2
    assert "holds the run's input" in capsys.readouterr().err
    assert (scene / "frame.txt").read_text() == "the user's data"
    assert (detections / "frame-000000_label.json").exists()


def test_a_users_folder_is_refused_unless_overwrite(inputs, tmp_path, capsys):
    scene, detections = inputs
    thesis = tmp_path / "thesis"
    (thesis / "chapters").mkdir(parents=True)
    (thesis / "main.tex").write_text("years of work")
    code = cli.main(["run", str(scene), "--detections", str(detections), "--out", str(thesis)])
    assert code == 2 and "--overwrite" in capsys.readouterr().err
    assert (thesis / "main.tex").read_text() == "years of work"
    check_output_folder(thesis, (scene, detections), overwrite=True)  # the user said so


def test_an_earlier_runs_folder_an_empty_one_or_a_new_one_is_fine(inputs, tmp_path):
    scene, detections = inputs
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    (earlier / "run.json").write_text(json.dumps({"scene": "scene", "frames": 3}))
    (earlier / "mesh.ply").write_text("ply")
    for out in (earlier, tmp_path / "empty", tmp_path / "new"):
        if out.name == "empty":
            out.mkdir()
        check_output_folder(out, (scene, detections))
    (earlier / "run.json").write_text("not json")
    with pytest.raises(UserError, match="not an earlier"):
        check_output_folder(earlier, (scene, detections))


def test_a_read_only_file_system_fails_before_any_work(tmp_path):
    """A real read-only mount (a private mount namespace: root ignores permissions, not a read-only mount)."""
    import os
    import shutil
    import subprocess
    import sys

    if shutil.which("unshare") is None or os.geteuid() != 0:
        pytest.skip("needs unshare and root to mount a read-only file system in a private namespace")
    scene, detections = tmp_path / "scene", tmp_path / "det"
    for folder in (scene, detections):
        folder.mkdir()
    read_only = tmp_path / "read-only"
    read_only.mkdir()
    run = f"{sys.executable} -m fmfusion_jax.cli run {scene} --detections {detections} --out {read_only}/out --no-progress"
    probe = subprocess.run(
        ["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o ro tmpfs {read_only} && {run}"], capture_output=True, text=True
    )
    if "mount" in probe.stderr and "Read-only" not in probe.stderr:
        pytest.skip(f"no private mount here: {probe.stderr.strip()}")
    assert probe.returncode == 2, probe.stderr
    assert "cannot write the output folder" in probe.stderr and "Read-only file system" in probe.stderr
    assert "Traceback" not in probe.stderr


def test_a_place_that_cannot_be_written_fails_before_any_work(tmp_path, monkeypatch):
    import errno
    import tempfile

    from fmfusion_jax.run.folder import prepare_output_dir

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkdtemp", read_only)
    with pytest.raises(UserError, match="Read-only file system"):
        prepare_output_dir(tmp_path / "out", create=False)


def test_a_map_that_cannot_fit_is_refused_before_allocation():
    import numpy as np

    from fmfusion_jax.config import load_config
    from fmfusion_jax.mapping.engine_configs import build_map_config

    tiny = load_config("scannet", ["tsdf.voxel_size=1.0e-6"])
    with pytest.raises(UserError, match="raise tsdf.voxel_size"):
        build_map_config(tiny, np.zeros(3), np.full(3, 8.0), 480, 640)
    assert build_map_config(load_config("scannet"), np.zeros(3), np.full(3, 8.0), 480, 640).memory_bytes() < 2**31


def test_a_camera_that_never_moves_is_warned(tmp_path, caplog):
    import numpy as np

    from fmfusion_jax.run.scene_fusion import warn_static_trajectory

    class Scene:
        name = "still"

        def __init__(self, poses):
            self._poses = poses

        def poses(self):
            return self._poses

    still = np.repeat(np.eye(4)[None], 20, axis=0)
    moving = still.copy()
    moving[:, 0, 3] = np.linspace(0, 1, 20)
    with caplog.at_level("WARNING", logger="fmfusion_jax.run"):
        assert warn_static_trajectory(Scene(still)) and not warn_static_trajectory(Scene(moving))
    assert "does not move" in caplog.text


def test_one_writer_per_output_folder(tmp_path, caplog):
    """The lock itself (the two-process case: below): a live owner refuses a second run, a dead one is taken over."""
    import os
    import socket
    import subprocess
    import sys

    from fmfusion_jax.run.folder import OutputLock

    out = tmp_path / "out"
    with OutputLock(out) as lock:
        assert json.loads(lock.path.read_text())["pid"] == os.getpid()
        with pytest.raises(UserError, match=f"another run \\(pid {os.getpid()}"):
            OutputLock(out).__enter__()
    assert not lock.path.exists()
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    lock.path.write_text(json.dumps({"pid": int(gone.stdout), "host": socket.gethostname()}))
    with caplog.at_level("WARNING", logger="fmfusion_jax.run"), OutputLock(out):
        assert "taking over" in caplog.text
    lock.path.write_text(json.dumps({"pid": 1, "host": "another-machine"}))  # a shared file system: never taken
    with pytest.raises(UserError, match="another-machine"):
        OutputLock(out).__enter__()


def test_a_second_run_on_the_same_output_folder_is_refused(tmp_path):
    """A real `fmfusion run` process meets the lock another process (this one) holds on its --out."""
    import os
    import subprocess
    import sys

    from fmfusion_jax.run.folder import OutputLock
    from fmfusion_jax.simulation.demo_setup import demo_noise
    from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, generated_scene, simulated_detections

    spec = GeneratedSceneSpec(seed=2, num_objects=2, num_frames=4, width=96, height=72)
    scene = generated_scene(spec, tmp_path)
    detections = simulated_detections(scene, tmp_path / "det", demo_noise(0, spec.width, spec.height))
    out = tmp_path / "out"
    command = [sys.executable, "-m", "fmfusion_jax.cli", "run", str(scene), "--detections", str(detections)]
    with OutputLock(out):
        second = subprocess.run(
            [*command, "--out", str(out), "--no-progress"],
            capture_output=True,
            text=True,
            env={**os.environ, "JAX_PLATFORMS": "cpu"},
        )
    assert second.returncode == 2, second.stderr
    assert f"being written by another run (pid {os.getpid()}" in second.stderr and "Traceback" not in second.stderr
    assert not out.exists()
