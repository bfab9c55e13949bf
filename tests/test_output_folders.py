"""`fmfusion run` never replaces a folder it did not write: an input folder as --out, or a user's folder."""

from __future__ import annotations

import json

import pytest

from fmfusion_jax import cli
from fmfusion_jax.errors import UserError
from fmfusion_jax.runner import check_output_folder


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
