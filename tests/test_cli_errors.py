"""Bad arguments to every subcommand end in one line `fmfusion <command>: error: ...` and exit code 2,
never a traceback; and these errors come before any slow work."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from fmfusion_jax import cli


@pytest.fixture(autouse=True)
def all_subcommands(monkeypatch):
    """Every subcommand module present, whether or not `cli.SUBCOMMANDS` lists it yet."""
    names = list(cli.SUBCOMMANDS)
    for name in ("info", "detect", "eval", "run", "demo", "simulate", "synth"):
        if name not in names and importlib.util.find_spec(f"fmfusion_jax.cli.{name}") is not None:
            names.append(name)
    monkeypatch.setattr(cli, "SUBCOMMANDS", tuple(names))
    return names


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> Path:
    """A two-frame ScanNet-layout scene of 64x48 pixels (a flat wall 2 m away), no ground truth."""
    root = tmp_path_factory.mktemp("scene") / "tiny0000_00"
    for sub in ("color", "depth", "pose", "intrinsic"):
        (root / sub).mkdir(parents=True)
    k = np.array([[60.0, 0, 32, 0], [0, 60.0, 24, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", k)
    for i in range(2):
        cv2.imwrite(str(root / "color" / f"frame-{i:06d}.jpg"), np.full((48, 64, 3), 128, np.uint8))
        cv2.imwrite(str(root / "depth" / f"frame-{i:06d}.png"), np.full((48, 64), 2000, np.uint16))
        np.savetxt(root / "pose" / f"frame-{i:06d}.txt", np.eye(4))
    return root


def _fails_in_one_line(capsys, argv: list[str], *fragments: str) -> str:
    code = cli.main(argv)
    out, err = capsys.readouterr()
    assert code == 2, (argv, out, err)
    assert "Traceback" not in err + out
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"fmfusion {argv[0]}: error: "), lines[0]
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    return lines[0]


def test_run_errors(capsys, tmp_path, tiny_scene):
    dets = tmp_path / "dets"
    dets.mkdir()
    out = str(tmp_path / "out")
    _fails_in_one_line(capsys, ["run", str(tmp_path / "missing"), "--detections", str(dets), "--out", out], "does not exist")
    wrong = tmp_path / "wrong"
    (wrong / "color").mkdir(parents=True)
    _fails_in_one_line(
        capsys,
        ["run", str(wrong), "--detections", str(dets), "--out", out],
        "unknown scene layout",
        "scannet: color/, depth/, intrinsic/",
    )
    _fails_in_one_line(
        capsys, ["run", str(tiny_scene), "--detections", str(tmp_path / "nodets"), "--out", out], "detections folder"
    )
    _fails_in_one_line(
        capsys,
        ["run", str(tiny_scene), "--detections", str(dets), "--out", out, "--set", "unknown.key=1"],
        "unknown config section 'unknown'",
    )
    _fails_in_one_line(
        capsys,
        ["run", str(tiny_scene), "--detections", str(dets), "--out", out, "--set", "detections.evry=1"],
        "did you mean 'detections.every'",
    )
    _fails_in_one_line(
        capsys,
        ["run", str(tiny_scene), "--detections", str(dets), "--out", out, "--set", "detections.every=ten"],
        "detections.every",
    )
    _fails_in_one_line(
        capsys,
        ["run", str(tiny_scene), "--detections", str(dets), "--out", out, "--set", "novalue"],
        "expected section.key=value",
    )
    _fails_in_one_line(
        capsys, ["run", str(tiny_scene), "--detections", str(dets), "--out", out, "--config", "no-such-config"], "not found"
    )
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    _fails_in_one_line(capsys, ["run", str(tiny_scene), "--detections", str(dets), "--out", str(a_file)], "is a file")
    (dets / "frame-000000_label.json").write_text("{broken")
    _fails_in_one_line(
        capsys,
        [
            "run",
            str(tiny_scene),
            "--detections",
            str(dets),
            "--out",
            out,
            "--set",
            "detections.every=1",
            "--no-progress",
            "--on-error",
            "stop",
        ],
        "frame-000000_label.json: malformed JSON",
        "--on-error skip",
    )
    # By default the frame's detections are skipped, named in a warning, in the summary and in run.json.
    assert (
        cli.main(
            ["run", str(tiny_scene), "--detections", str(dets), "--out", out, "--set", "detections.every=1", "--no-progress"]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "1 frames skipped or partly skipped" in printed and "frame-000000: detections skipped" in printed
    skipped = json.loads((Path(out) / "run.json").read_text())["skipped_frames"]
    assert skipped[0]["frame"] == "frame-000000" and "malformed JSON" in skipped[0]["reason"]
    assert "semantic.ply" in printed  # written, empty: the map has no instance


def test_info_errors(capsys, tmp_path):
    _fails_in_one_line(capsys, ["info", str(tmp_path / "missing")], "not found")
    (tmp_path / "odd" / "images").mkdir(parents=True)
    _fails_in_one_line(capsys, ["info", str(tmp_path / "odd")], "unknown scene layout")


def test_eval_errors(capsys, tmp_path, tiny_scene):
    _fails_in_one_line(capsys, ["eval", str(tmp_path / "pred.txt")], "no ground truth")
    _fails_in_one_line(capsys, ["eval", str(tmp_path / "pred.txt"), "--gt", str(tmp_path / "gt")], "no such file")
    _fails_in_one_line(capsys, ["eval", "--gt", str(tiny_scene)], "no ScanNet scene folder")
    (tmp_path / "preds").mkdir()
    gt = tmp_path / "gt.txt"
    gt.write_text("0\n")
    _fails_in_one_line(capsys, ["eval", str(tmp_path / "preds"), "--gt", str(gt)], "no prediction")


def test_demo_errors(capsys, tmp_path, all_subcommands):
    if "demo" not in all_subcommands:
        pytest.skip("fmfusion_jax.cli.demo is not there")
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "keep.txt").write_text("a user's file")
    _fails_in_one_line(capsys, ["demo", "--out", str(busy), "--no-progress"], "not empty")
    assert (busy / "keep.txt").read_text() == "a user's file"
    _fails_in_one_line(capsys, ["demo", "--out", str(tmp_path / "d"), "--set", "unknown.key=1"], "unknown config section")
    _fails_in_one_line(capsys, ["demo", "--out", str(tmp_path / "d"), "--frames", "1"], "--frames")
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    _fails_in_one_line(capsys, ["demo", "--out", str(a_file)], "is a file")


def test_argparse_errors_have_no_traceback(capsys):
    for argv in (["run"], ["eval", "--json"], ["no-such-command"]):
        with pytest.raises(SystemExit) as exit_info:
            cli.main(argv)
        assert exit_info.value.code == 2
        _, err = capsys.readouterr()
        assert "Traceback" not in err and "error:" in err


def test_run_refuses_a_detection_folder_that_matches_no_frame(tmp_path, capsys):
    """An empty or unrelated detections folder would silently give an empty map: it is an error."""
    from fmfusion_jax import cli
    from fmfusion_jax.simulation.procedural import generate_scene
    from fmfusion_jax.simulation.scannet_writer import write_scannet_scene

    scene = write_scannet_scene(
        generate_scene(1, num_objects=2), tmp_path / "synth0001_00", num_frames=2, width=80, height=60, progress=False
    )
    empty = tmp_path / "detections"
    empty.mkdir()
    code = cli.main(["run", str(scene), "--detections", str(empty), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and "holds no detection files" in err and "Traceback" not in err


def test_version_and_verbose_after_the_subcommand(capsys, tiny_scene):
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["--version"])
    assert exit_info.value.code == 0 and capsys.readouterr().out.strip().startswith("fmfusion 0.")
    parser = cli.build_parser()
    before, after = parser.parse_args(["-v", "info", str(tiny_scene)]), parser.parse_args(["info", "-vv", str(tiny_scene)])
    assert before.verbose == 1 and after.verbose_after_command == 2
