"""The scene graph's relations on a room whose layout is known, queries by class, label and relation, and the
graph written with every map."""

from __future__ import annotations

import json

import networkx as nx
import numpy as np
import pytest

from fmfusion_jax import cli
from fmfusion_jax.scene_graph import FLOOR_NODE, build_scene_graph, query


def _record(i, cls, center, extent, yaw=0.0, labels=None, confidence=0.8):
    return {
        "id": i,
        "class": cls,
        "confidence": confidence,
        "open_label_histogram": labels or {cls: 1.0},
        "voxel_count": 500,
        "oriented_box": {"center": list(center), "extent": list(extent), "yaw": yaw},
    }


def room():
    """A table with a lamp and a book on it, a chair on each side of it, a sofa under the window, a cabinet
    with a box inside; the floor at z = 0. Returns the records and the true `on` and `near` relations (near:
    surfaces within 30 cm, the graph's default)."""
    records = [
        _record(0, "floor", (2, 2, -0.01), (4, 4, 0.02)),
        _record(1, "table", (1, 1, 0.375), (1.2, 0.8, 0.75)),
        _record(2, "otherfurniture", (1, 1.2, 0.95), (0.2, 0.2, 0.4), labels={"lamp": 3.0, "vase": 0.5}),
        _record(3, "picture", (1, 0.75, 0.77), (0.25, 0.2, 0.04), labels={"book": 2.0}),
        _record(4, "chair", (2.0, 1, 0.45), (0.5, 0.5, 0.9)),
        _record(5, "chair", (0.0, 1, 0.45), (0.5, 0.5, 0.9)),
        _record(6, "sofa", (3.4, 3.3, 0.4), (1.8, 0.8, 0.8)),
        _record(7, "window", (3.4, 3.85, 1.5), (1.2, 0.1, 1.0)),
        _record(8, "cabinet", (3.5, 0.4, 0.5), (0.8, 0.6, 1.0)),
        _record(9, "otherfurniture", (3.5, 0.4, 0.3), (0.3, 0.3, 0.3), labels={"box": 1.0}),
    ]
    on = {(1, FLOOR_NODE), (2, 1), (3, 1), (4, FLOOR_NODE), (5, FLOOR_NODE), (6, FLOOR_NODE), (8, FLOOR_NODE)}
    near = {(1, 4), (1, 5), (2, 3), (6, 7)}
    return records, on, near


def _precision_recall(found: set, truth: set) -> tuple[float, float]:
    hits = len(found & truth)
    return hits / max(len(found), 1), hits / max(len(truth), 1)


def test_on_and_near_edges_match_the_known_layout():
    records, on, near = room()
    graph = build_scene_graph(records)
    edges = graph["edges"]
    found_on = {(e["source"], e["target"]) for e in edges if e["relation"] == "on"}
    found_near = {tuple(sorted((e["source"], e["target"]))) for e in edges if e["relation"] == "near"}
    assert _precision_recall(found_on, on) == (1.0, 1.0)
    precision, recall = _precision_recall(found_near, near)
    assert precision >= 0.9 and recall >= 0.9, (found_near, near)
    assert {(e["source"], e["target"]) for e in edges if e["relation"] == "inside"} == {(9, 8)}
    assert all(0 < e["score"] <= 1 for e in edges)
    assert graph["floor_z"] == pytest.approx(0.0, abs=1e-6)
    assert graph["nodes"][0] == {"id": FLOOR_NODE, "class": "floor", "root": True, "z": 0.0}


def test_the_graph_does_not_depend_on_the_boxes_yaw_convention():
    """The same room turned by 90 degrees about z: the same relations."""
    records, _, _ = room()
    turned = json.loads(json.dumps(records))
    for r in turned:
        x, y, z = r["oriented_box"]["center"]
        r["oriented_box"]["center"] = [-y, x, z]
        r["oriented_box"]["yaw"] += np.pi / 2
    key = lambda g: sorted((e["source"], e["relation"], e["target"]) for e in g["edges"])  # noqa: E731
    assert key(build_scene_graph(turned)) == key(build_scene_graph(records))


def test_queries_by_class_label_synonym_and_relation():
    records, _, _ = room()
    assert [m.instance_id for m in query(records, "chair")] == [4, 5]
    assert [m.instance_id for m in query(records, "the chairs")] == [4, 5]
    assert query(records, "lamp")[0].instance_id == 2  # an open-set label it was seen as
    assert {m.instance_id for m in query(records, "something to sit on")} == {4, 5, 6}
    assert [m.instance_id for m in query(records, "lamp on the table")] == [2]
    assert [m.instance_id for m in query(records, "sofa near the window")] == [6]
    assert query(records, "sofa near the table") == []
    assert [m.instance_id for m in query(records, "box inside the cabinet")] == [9]
    assert query(records, "zebra") == []


def test_every_map_has_its_graph_labelled_points_and_fmfusion_query_finds_every_instance_of_a_class(tmp_path, capsys):
    out = tmp_path / "demo"
    assert (
        cli.main(
            ["demo", "--out", str(out), "--frames", "24", "--objects", "4", "--width", "320", "--height", "240", "--no-progress"]
        )
        == 0
    )
    capsys.readouterr()
    records = json.loads((out / "instances.json").read_text())["instances"]
    graph = json.loads((out / "scene_graph.json").read_text())
    assert len(graph["nodes"]) == len(records) + 1
    loaded = nx.read_graphml(out / "scene_graph.graphml")
    assert loaded.number_of_nodes() == len(records) + 1 and loaded.number_of_edges() == len(graph["edges"])
    # the labelled points for robotics tools: NPZ and binary PCD with the same points
    cloud = np.load(out / "labelled_points.npz")
    assert cloud["points"].shape == (len(cloud["label"]), 3) == (len(cloud["instance"]), 3)
    assert set(np.unique(cloud["instance"]).tolist()) == {r["id"] for r in records}
    raw = (out / "labelled_points.pcd").read_bytes()
    header, _, body = raw.partition(b"DATA binary\n")
    assert b"FIELDS x y z rgb label instance" in header and f"POINTS {len(cloud['label'])}".encode() in header
    rows = np.frombuffer(
        body, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4"), ("label", "<u4"), ("instance", "<i4")])
    )
    np.testing.assert_array_equal(rows["instance"], cloud["instance"])
    np.testing.assert_allclose(np.stack([rows["x"], rows["y"], rows["z"]], 1), cloud["points"])
    cls = records[0]["class"]
    picture = tmp_path / "q.png"
    assert cli.main(["query", str(out), cls, "--json", str(tmp_path / "q.json"), "--top", "100", "--picture", str(picture)]) == 0
    import cv2

    image = cv2.imread(str(picture))
    assert image is not None and (np.abs(image.astype(int) - [30, 30, 220]).sum(axis=2) < 40).any()  # red (BGR) drawn
    found = {m["id"] for m in json.loads((tmp_path / "q.json").read_text())["matches"]}
    assert {r["id"] for r in records if r["class"] == cls} <= found
