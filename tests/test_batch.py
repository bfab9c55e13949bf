"""`fmfusion batch`: three generated rooms through the local executor, the vmapped one (and Ray where it is
installed) give the same per-scene results; the pooled score equals `fmfusion eval` over the three prediction
folders; a failed scene is recorded and the others go on; `--resume` skips the finished ones."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
from pathlib import Path

import pytest

from fmfusion_jax import cli
from fmfusion_jax.simulation.demo_setup import demo_config, demo_overrides
from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, generated_scene

SPECS = [GeneratedSceneSpec(seed=seed, num_objects=3, num_frames=12, width=160, height=120) for seed in (1, 2, 3)]
# demo.yaml's pixel counts are for 640 x 480: unscaled, these rooms map nothing
CONFIG = ["--config", "demo"] + [item for override in demo_overrides(12, 160, 120) for item in ("--set", override)]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("batch") / "data"
    root.mkdir()
    for spec in SPECS:
        generated_scene(spec, root)
    (root / "split.txt").write_text("\n".join(sorted(p.name for p in root.iterdir() if p.is_dir())) + "\n# the end\n")
    return root


@pytest.fixture(scope="module")
def local_run(dataset, tmp_path_factory) -> tuple[Path, str]:
    """The split file through the local executor, two workers: `(OUT, what it printed)`."""
    out = tmp_path_factory.mktemp("local") / "out"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = cli.main(["batch", str(dataset / "split.txt"), "--simulate", "--out", str(out), "--workers", "2", *CONFIG])
    assert code == 0
    return out, printed.getvalue()


def _records(out: Path) -> dict[str, dict]:
    return {r["scene"]: r for r in json.loads((out / "batch.json").read_text())["scenes"]}


def _key(record: dict) -> tuple:
    return record["status"], record["frames"], record["instances"], record["mAP50"]


def test_local_batch_pools_like_eval_and_resumes(dataset, local_run, tmp_path, capsys):
    out, printed = local_run
    records = _records(out)
    assert sorted(records) == sorted(p.name for p in dataset.iterdir() if p.is_dir())
    assert all(r["status"] == "ok" and r["frames"] == 12 for r in records.values())
    assert all(r["instances"] > 0 for r in records.values())  # the executors are compared on maps with instances
    assert "3 scenes: 3 ok, 0 failed" in printed and (out / "batch.md").is_file() and (out / "batch.csv").is_file()

    # the pooled score is `fmfusion eval` over the three prediction folders together
    eval_json = tmp_path / "eval.json"
    predictions = [str(out / name / "benchmark") for name in records]
    scenes = [str(dataset / name) for name in records]
    assert cli.main(["eval", *predictions, "--gt", *scenes, "--json", str(eval_json)]) == 0
    pooled = json.loads(eval_json.read_text())
    assert f"mAP50 {100 * pooled['mAP50']:.1f}" in printed

    # --resume runs nothing again
    capsys.readouterr()
    first = sorted(records)[0]
    stamp = (out / first / "run.json").stat().st_mtime_ns
    assert cli.main(["batch", str(dataset), "--simulate", "--out", str(out), *CONFIG, "--resume"]) == 0
    assert "3 scenes, 0 to run (3 done before)" in capsys.readouterr().err
    assert (out / first / "run.json").stat().st_mtime_ns == stamp


def test_a_failed_scene_is_recorded_and_the_batch_goes_on(dataset, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    broken = sorted(p for p in data.iterdir() if p.is_dir())[0]
    for pose in (broken / "pose").iterdir():
        pose.write_text("not a pose")
    out = tmp_path / "out"
    assert cli.main(["batch", str(data), "--simulate", "--out", str(out), *CONFIG, "--no-progress"]) == 1
    records = _records(out)
    assert records[broken.name]["status"] == "failed" and "not a list of numbers" in records[broken.name]["error"]
    assert sum(r["status"] == "ok" for r in records.values()) == 2
    assert "## Failures" in (out / "batch.md").read_text()


def test_scene_time_and_memory_limits_stop_a_scene_and_say_why(dataset, tmp_path):
    out = tmp_path / "out"
    argv = ["batch", str(dataset), "--simulate", "--out", str(out)]  # each scene runs for seconds, in 100s of MiB
    assert cli.main([*argv, *CONFIG, "--no-progress", "--scene-memory", "0.05"]) == 1
    assert {r["status"] for r in _records(out).values()} == {"memory"}  # a JAX process alone holds more
    assert "over the scene memory limit (51 MiB)" in (out / "batch.md").read_text()
    assert cli.main([*argv, *CONFIG, "--no-progress", "--scene-timeout", "0.5"]) == 1
    assert {r["status"] for r in _records(out).values()} == {"timeout"}


def test_vmapped_executor_gives_the_local_results(dataset, local_run, tmp_path, caplog):
    """--batch 3: the three rooms fused in one vmapped step (one block layout covering all three); on a CPU, with
    a warning that one process per scene is faster there."""
    import jax

    out = tmp_path / "vmapped"
    argv = ["batch", str(dataset), "--simulate", "--out", str(out), *CONFIG, "--batch", "3", "--no-progress"]
    assert cli.main(argv) == 0
    records = _records(out)
    assert all(len(r["batched_with"]) == 3 for r in records.values())
    assert {k: _key(r) for k, r in records.items()} == {k: _key(r) for k, r in _records(local_run[0]).items()}
    assert ("built for a GPU: on this CPU it is slower" in caplog.text) == (jax.default_backend() == "cpu")
    # the pool sized to the scenes (each vmapped step walks every map's whole pool), not the config's, and no
    # block dropped: the same maps as the local runs'
    config_pool = demo_config(12, 160, 120).tsdf.block_capacity
    for record in records.values():
        used = json.loads((Path(record["out"]) / "run.json").read_text())["capacity_used"]
        assert used["dropped_blocks"] == 0 and used["blocks"] < used["block_capacity"] < config_pool


def test_ray_executor_gives_the_local_results(dataset, local_run, tmp_path):
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install -e '.[cluster]')")
    distributed = tmp_path / "ray"
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        argv = ["batch", str(dataset), "--simulate", "--out", str(distributed), *CONFIG, "--ray", "auto"]
        assert cli.main([*argv, "--no-progress"]) == 0
    finally:
        ray.shutdown()
    local = _records(local_run[0])
    assert {k: _key(r) for k, r in local.items()} == {k: _key(r) for k, r in _records(distributed).items()}


def test_scenes_run_together_share_the_device(monkeypatch):
    """Several scene processes at once: JAX's GPU preallocation off in their environment (a process would
    otherwise take 75 % of the device, and the third or fourth could not start); a user's own setting is kept."""
    from fmfusion_jax.apps.batch import PREALLOCATE_ENV, child_environment

    monkeypatch.delenv(PREALLOCATE_ENV, raising=False)
    assert child_environment(4)[PREALLOCATE_ENV] == "false"
    assert PREALLOCATE_ENV not in child_environment(1)
    assert child_environment(1)["PYTHONUNBUFFERED"] == "1"
    monkeypatch.setenv(PREALLOCATE_ENV, "true")
    assert child_environment(4)[PREALLOCATE_ENV] == "true"


def test_recording_files_are_scenes_of_a_dataset(dataset, tmp_path):
    """A folder of recordings lists its bag and Record3D files beside the scene folders; other files are not scenes."""
    from fmfusion_jax.apps.batch import list_scenes

    folder = tmp_path / "mixed"
    shutil.copytree(next(p for p in dataset.iterdir() if p.is_dir()), folder / "room")
    (folder / "walk.bag").write_bytes(b"#ROSBAG V2.0\n")
    (folder / "kitchen.r3d").write_bytes(b"PK")
    (folder / "walk.bag.trajectory.txt").write_text("0 0 0 0 0 0 0 1\n")
    (folder / "README.md").write_text("notes\n")
    assert [p.name for p in list_scenes(folder)] == ["kitchen.r3d", "room", "walk.bag"]
    (folder / "split.txt").write_text("walk.bag\nroom\n")
    assert [p.name for p in list_scenes(folder / "split.txt")] == ["walk.bag", "room"]
