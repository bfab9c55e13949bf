"""The scene graph's relations on a room whose layout is known, queries by class, label and relation, and the
graph written with every map."""

from __future__ import annotations

import json

import networkx as nx
import numpy as np
import pytest

from fmfusion_jax import cli
from fmfusion_jax.scene_graph import FLOOR_NODE, GraphSettings, build_scene_graph, query


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


#: Near pairs whose true gap lies within this much beyond the graph's `near_distance` count neither way (the
#: map's boxes are built from 1.5 cm voxels of noisy depth: a few cm larger or smaller than the generator's).
NEAR_TOLERANCE = 0.1


def _graph_against_generator(seed: int, tmp_path) -> tuple[dict, dict, list[dict], dict]:
    """Fuses a generated room with stacked objects (clean detections), builds its scene graph and returns the
    graph's `on` and `near` edges and the generator's, as ground-truth instance ids, over the objects the map
    holds (a relation of an object the map lost is the detector's miss, not the graph's); and the map's
    `instances.json` records with the generator's instance each one lies in."""
    from fmfusion_jax.io.detections import DetectionFolder
    from fmfusion_jax.io.map_outputs import instances_json
    from fmfusion_jax.io.scene import open_scene
    from fmfusion_jax.labels import load_label_sets
    from fmfusion_jax.mapping.export import extract_map_instances
    from fmfusion_jax.run.scene_fusion import fuse_scene
    from fmfusion_jax.simulation.demo_setup import demo_config
    from fmfusion_jax.simulation.noise import NoiseModel
    from fmfusion_jax.simulation.procedural import box_distance, generate_scene
    from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, generated_scene, simulated_detections

    spec = GeneratedSceneSpec(seed=seed, num_objects=7, num_frames=40, width=320, height=240, stacked=3)
    scene_dir = generated_scene(spec, tmp_path)
    detections = simulated_detections(scene_dir, tmp_path / f"detections{seed}", NoiseModel.preset("clean", seed=seed))
    config = demo_config(spec.num_frames, spec.width, spec.height, [])
    folder = DetectionFolder(detections)
    scene = open_scene(scene_dir, depth_max=config.dataset.depth_max)
    result = fuse_scene(scene, lambda frame: folder.get(frame.name), config, progress=False)
    instances = extract_map_instances(result)
    records = instances_json(instances, load_label_sets())

    room = generate_scene(seed, num_objects=spec.num_objects, stacked=spec.stacked)
    floor = next(i for i, info in room.instances.items() if info.kind == "floor")
    truth_of = {}  # map instance -> the generator's instance most of its points lie in
    for instance, record in zip(instances, records):
        ids = room.contains(instance.points, margin=0.03)
        if (ids > 0).any():
            values, counts = np.unique(ids[ids > 0], return_counts=True)
            truth_of[record["id"]] = int(values[counts.argmax()])
    objects = set(room.object_ids)
    mapped = set(truth_of.values()) & objects
    truth = room.relations()

    graph = build_scene_graph(records)
    as_truth = lambda node: floor if node == FLOOR_NODE else truth_of.get(node)  # noqa: E731
    on = {(as_truth(e["source"]), as_truth(e["target"])) for e in graph["edges"] if e["relation"] == "on"}
    near = {tuple(sorted((as_truth(e["source"]), as_truth(e["target"])))) for e in graph["edges"] if e["relation"] == "near"}
    found = {
        "on": {p for p in on if p[0] in objects and p[0] != p[1]},
        "near": {p for p in near if p[0] in objects and p[1] in objects and p[0] != p[1]},
    }
    limit = GraphSettings().near_distance  # the graph's own threshold
    ambiguous = {
        (a, b)
        for a, b in found["near"]
        if limit <= box_distance(room.instance_box(a), room.instance_box(b)) < limit + NEAR_TOLERANCE
    }
    found["near"] -= ambiguous
    expected = {
        "on": {p for p in truth["on"] if p[0] in mapped and (p[1] in mapped or p[1] == floor)},
        "near": {p for p in truth["near"] if p[0] in mapped and p[1] in mapped},
    }
    return found, expected, records, truth_of


def test_the_graph_of_a_fused_generated_room_matches_the_generators_relations(tmp_path):
    """Two generated rooms with lamps, boxes and baskets on tables, desks, counters and cabinets, fused from
    clean detections: the graph's `on` (floor included) and `near` edges against the generator's relations,
    pooled; precision and recall >= 0.9 each (the issue's acceptance)."""
    hits, found_total, truth_total = {"on": 0, "near": 0}, {"on": 0, "near": 0}, {"on": 0, "near": 0}
    for seed in (8, 9):
        found, expected, records, truth_of = _graph_against_generator(seed, tmp_path)
        stacked = {(a, b) for a, b in expected["on"] if b in truth_of.values() and b != 5}  # 5: the floor
        assert stacked, "the room has something standing on an object"

        # a relation query on the map: "<its class> on the <its support's class>" finds it, and only stacked things
        def name(truth: int) -> str:  # the map's class of the largest instance lying in `truth`
            return max((r for r in records if truth_of.get(r["id"]) == truth), key=lambda r: r["voxel_count"])["class"]

        for thing, support in stacked:
            answers = {truth_of[m.instance_id] for m in query(records, f"{name(thing)} on the {name(support)}")}
            assert thing in answers and answers <= {a for a, _ in stacked}, (thing, support, answers)
        for relation in ("on", "near"):
            hits[relation] += len(found[relation] & expected[relation])
            found_total[relation] += len(found[relation])
            truth_total[relation] += len(expected[relation])
    for relation in ("on", "near"):
        precision, recall = hits[relation] / found_total[relation], hits[relation] / truth_total[relation]
        assert precision >= 0.9 and recall >= 0.9, (relation, precision, recall, found_total, truth_total)
    assert truth_total["on"] >= 12 and truth_total["near"] >= 5
