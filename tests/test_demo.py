"""`fmfusion demo` end to end on a tiny room (160x120, 12 frames, 4 objects) through `run_demo`.

Checks that every output is written and readable (PLY files in trimesh, overview.png as a real picture),
that the saved map loads back exactly, and that a seed gives the same map twice.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import jax
import jsonschema
import numpy as np
import pytest
import trimesh
from fusion_helpers import load_map

from fmfusion_jax.apps.demo import MARKER, run_demo
from fmfusion_jax.io.ground_truth import read_ply_vertices
from fmfusion_jax.run.outputs import MAP_STATE_FILE
from fmfusion_jax.simulation.demo_setup import demo_config

TINY = dict(seed=3, num_objects=4, num_frames=12, width=160, height=120, progress=False)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    return run_demo(tmp_path_factory.mktemp("demo") / "out", **TINY)


def test_demo_writes_every_output(demo):
    out = demo.out_dir
    for name in (
        "overview.png",
        "instances.json",
        "semantic.ply",
        "instances.ply",
        "mesh.ply",
        MAP_STATE_FILE,
        "run.json",
        "report.json",
        "config.yaml",
        MARKER,
    ):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    scene = demo.scene_dir
    assert scene.parent == out and (scene / f"{scene.name}_vh_clean_2.ply").is_file()
    assert len(list((scene / "color").iterdir())) == TINY["num_frames"]
    assert list(demo.detections_dir.glob("frame-*_label.json"))
    assert (out / "benchmark" / f"{scene.name}.txt").is_file()
    run = json.loads((out / "run.json").read_text())
    assert run["frames"] == TINY["num_frames"] and run["instances"] > 0
    assert 0.0 <= run["benchmark"]["mAP25"] <= 1.0
    document = json.loads((out / "instances.json").read_text())
    jsonschema.validate(document, json.loads((Path(__file__).parents[1] / "docs" / "instances.schema.json").read_text()))
    instances = document["instances"]
    assert len(instances) == run["instances"] == len(list((out / "instances").glob("*.ply")))
    assert document["version"] == 3 and all(record["voxel_count"] >= 1 for record in instances)
    assert "AP" in demo.text and str(out / "overview.png") in demo.text
    # the config used: demo.yaml scaled to 12 frames of 160x120
    assert (out / "config.yaml").read_text() == demo.fusion.config.to_yaml()
    assert demo.fusion.config == demo_config(12, 160, 120)


def test_ply_files_open_with_points_and_colours(demo):
    out = demo.out_dir
    for path in [out / "semantic.ply", out / "instances.ply", *sorted((out / "instances").glob("*.ply"))[:3]]:
        cloud = trimesh.load(path)
        assert len(cloud.vertices) > 0, path
        colors = np.asarray(cloud.colors)
        assert colors.shape == (len(cloud.vertices), 4) and colors[:, :3].std() >= 0, path
    semantic = np.asarray(trimesh.load(out / "semantic.ply").colors)[:, :3]
    assert len(np.unique(semantic, axis=0)) >= 2  # several classes
    # ScanNet-style label and instance vertex properties, the same as instances.json says
    records = json.loads((out / "instances.json").read_text())["instances"]
    for name in ("semantic.ply", "instances.ply"):
        vertex = read_ply_vertices(out / name)
        assert len(vertex["label"]) == len(vertex["x"]) == sum(r["voxel_count"] for r in records)
        for record in records:
            mine = vertex["instance"] == record["id"]
            assert mine.sum() == record["voxel_count"]
            assert set(np.unique(vertex["label"][mine])) == {record["nyu40_id"]}
    mesh = trimesh.load(out / "mesh.ply", process=False)
    assert len(mesh.vertices) > 100 and len(mesh.faces) > 100
    assert np.asarray(mesh.visual.vertex_colors).shape[0] == len(mesh.vertices)


def test_overview_is_a_real_picture(demo):
    image = cv2.imread(str(demo.out_dir / "overview.png"))
    assert image is not None and image.ndim == 3
    height, width = image.shape[:2]
    assert width == 2 * 800 + 16 + 2 * 12  # map and ground-truth panels of 800 px side by side
    assert 300 < height < 2000
    colors = np.unique(image.reshape(-1, 3), axis=0)
    assert len(colors) > 50
    background = np.all(image >= 235, axis=2).mean()
    assert background < 0.75, background
    # both panels hold class colours (not only greys)
    saturation = cv2.cvtColor(image, cv2.COLOR_BGR2HSV)[..., 1]
    half = width // 2
    assert (saturation[:, :half] > 40).mean() > 0.01 and (saturation[:, half:] > 40).mean() > 0.01


def test_saved_map_loads_back_exactly(demo):
    state, map_config, config = load_map(demo.out_dir / MAP_STATE_FILE)
    assert map_config == demo.fusion.map_config and config == demo.fusion.config
    expected = jax.tree_util.tree_leaves_with_path(jax.device_get(demo.fusion.state))
    got = jax.tree_util.tree_leaves_with_path(jax.device_get(state))
    assert len(got) == len(expected)
    for (path, a), (_, b) in zip(got, expected):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=jax.tree_util.keystr(path))


def test_same_seed_same_map(demo, tmp_path):
    again = run_demo(tmp_path / "again", **TINY)
    assert (again.out_dir / "instances.json").read_bytes() == (demo.out_dir / "instances.json").read_bytes()
    assert again.summary["benchmark"]["mAP25"] == demo.summary["benchmark"]["mAP25"]
    # a second demo into the same folder replaces the first one's output
    third = run_demo(again.out_dir, **TINY)
    assert (third.out_dir / "instances.json").read_bytes() == (demo.out_dir / "instances.json").read_bytes()


def test_overview_without_ground_truth_and_of_an_empty_map():
    from fmfusion_jax.instances import MapInstance
    from fmfusion_jax.labels import load_label_sets
    from fmfusion_jax.viz.overview import map_overview_panel, render_overview

    labels = load_label_sets()
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(0, 4, (4000, 2)), np.zeros(4000)].astype(np.float32)
    chair = np.c_[rng.uniform(1, 1.5, (500, 2)), rng.uniform(0, 0.9, 500)].astype(np.float32)
    distribution = np.eye(labels.num_classes)[labels.class_index("chair")]
    instances = [MapInstance(3, distribution, chair, 4, np.zeros(labels.num_open))]
    panel = map_overview_panel(instances, labels, floor, None, None, 0.05)
    image = render_overview([panel], labels, "one panel")
    assert image.shape[1] == 800 + 2 * 12 and image.dtype == np.uint8
    chair_bgr = labels.class_colors[labels.class_index("chair")][::-1]
    assert np.all(image == chair_bgr, axis=2).sum() > 1000  # the chair is drawn in its class colour
    empty = map_overview_panel([], labels, np.zeros((0, 3), np.float32), None, None, 0.05)
    assert render_overview([empty], labels, "nothing").shape[1] == 824
