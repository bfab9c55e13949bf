"""`fmfusion experiment` (`fmfusion_jax.apps.experiments`) on a tiny generated room: every method runs, both tables
are written, every number is an AP; bad methods and scenes are clear errors."""

from __future__ import annotations

import json
import math

import pytest

from fmfusion_jax.apps.experiments import CLASS_ABBREVIATIONS, run_experiment, table_one
from fmfusion_jax.comparison.methods import DEFAULT_METHODS, METHODS, resolve_methods
from fmfusion_jax.errors import UserError
from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec

TINY = GeneratedSceneSpec(seed=3, num_objects=4, num_frames=10, width=160, height=120)


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    root = tmp_path_factory.mktemp("experiment")
    return run_experiment(root / "out", generated=[TINY], seed=0, cache_dir=root / "cache", progress=False)


def _all_scores(result_json: dict):
    for key in ("mAP", "mAP50", "mAP25"):
        yield result_json[key]
    for scores in result_json["classes"].values():
        yield from (scores["AP"], scores["AP50"], scores["AP25"])


def test_every_method_runs_and_both_tables_are_written(experiment):
    out = experiment.out_dir
    assert [m.name for m in experiment.methods] == list(DEFAULT_METHODS)
    markdown = (out / "experiment.md").read_text()
    assert markdown == experiment.markdown
    assert "Table I" in markdown and "Table II" in markdown and "G-SAM & Kimera" in markdown
    for method in experiment.methods:
        assert f"| {method.title} |" in markdown
    assert all(name in markdown for name in CLASS_ABBREVIATIONS.values())

    record = json.loads((out / "experiment.json").read_text())
    assert set(record["results"]) == set(DEFAULT_METHODS)
    assert record["seed"] == 0 and [s["name"] for s in record["scenes"]] == [TINY.name]
    noise = record["scenes"][0]["noise"]
    assert noise["default"]["prompt_augmentation"] and not noise["noaug"]["prompt_augmentation"]
    for name, result in record["results"].items():
        for scores in (result["pooled"], result["per_scene"][TINY.name]):
            for value in _all_scores(scores):
                assert value is None or 0.0 <= value <= 1.0, (name, value)
        # one scene: pooling over it is the scene's own score
        assert result["pooled"]["mAP25"] == result["per_scene"][TINY.name]["mAP25"]
        assert record["configs"][TINY.name][name]["dataset"]["layout"] == "scannet"
        run_dir = out / "runs" / TINY.name / name
        run = json.loads((run_dir / "run.json").read_text())
        assert run["method"] == name and run["frames"] == TINY.num_frames
        assert (run_dir / "benchmark" / f"{TINY.name}.txt").is_file() and (run_dir / "config.yaml").is_file()
    configs = record["configs"][TINY.name]
    assert configs["ablation-a"]["label_fusion"]["likelihood"] == "manual"
    assert configs["ablation-c"]["refinement"]["enabled"] is False
    assert configs["full"]["label_fusion"]["likelihood"] == "statistical" and configs["full"]["refinement"]["enabled"]
    assert set(record["scenes"][0]["detections"]) == {"default", "noaug"}  # ablation B's own detections
    # the table cell of a class without ground truth is "-"; the mean column is the pooled mAP50
    full = experiment.pooled["full"]
    row = next(line for line in table_one(experiment.methods, experiment.pooled).splitlines() if line.startswith("| FM-Fusion |"))
    cells = [c.strip() for c in row.strip("|").split("|")][1:]
    for value, cell in zip([*full.ap50.values(), full.mAP50], cells):
        assert cell == ("-" if math.isnan(value) else f"{100 * value:.1f}")


def test_unknown_method_is_a_clear_error():
    with pytest.raises(UserError, match="unknown method 'kimmera'.*kimera"):
        resolve_methods(["full", "kimmera"])
    assert [m.name for m in resolve_methods(["full", "kimera"])] == ["kimera", "full"]  # table order
    assert "full-bayes" in METHODS and "full-bayes" not in DEFAULT_METHODS


def test_cli_errors_name_the_problem(tmp_path, capsys):
    from fmfusion_jax.cli import main

    assert main(["experiment", "--methods", "nope", "--out", str(tmp_path / "a")]) == 2
    assert "unknown method 'nope'" in capsys.readouterr().err
    assert main(["experiment", "--scenes", str(tmp_path / "missing"), "--generated", "0", "--out", str(tmp_path / "b")]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(["experiment", "--scenes", "--generated", "0", "--out", str(tmp_path / "c")]) == 2
    assert "no scenes" in capsys.readouterr().err
    with pytest.raises(UserError, match="unknown config key"):
        run_experiment(tmp_path / "d", generated=[TINY], overrides=["tsdf.voxel=0.02"], progress=False)
    assert not (tmp_path / "d").exists()  # checked before anything is made


def test_quick_runs_tiny_generated_rooms_only(monkeypatch, tmp_path):
    import fmfusion_jax.apps.experiments as experiments
    from fmfusion_jax.cli import main

    seen = {}

    class Result:
        text = "tables"

    def fake_run(out, **kwargs):
        seen.update(kwargs, out=out)
        return Result()

    monkeypatch.setattr(experiments, "run_experiment", fake_run)
    assert main(["experiment", "--quick", "--out", str(tmp_path), "--methods", "kimera", "full"]) == 0
    assert seen["real_scenes"] == [] and len(seen["generated"]) == 1
    spec = seen["generated"][0]
    assert (spec.width, spec.height, spec.num_frames) == (320, 240, 30) and seen["methods"] == ["kimera", "full"]
    main(["experiment", "--generated", "2", "--generated-frames", "30", "--scenes", "--out", str(tmp_path)])
    assert [s.seed for s in seen["generated"]] == [1, 2] and seen["generated"][0].num_frames == 30
    assert seen["generated"][0].width == 640 and seen["real_max_frames"] is None
