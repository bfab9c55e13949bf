"""ScanNet ground truth: a synthetic scene written here, and the real scene0000_00 when available."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fmfusion_jax.errors import DataError
from fmfusion_jax.io.ground_truth import load_benchmark_gt_txt, load_scannet_ground_truth, read_ply_mesh
from fmfusion_jax.labels import BENCHMARK_NYU40_IDS

TSV = "id\tcategory\tcount\tnyu40id\n1\tchair\t10\t5\n2\tcabinet\t10\t3\n3\tstorage\t4\t\n4\twall\t9\t1\n"
SEGMENTS = [0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3, 4, 4, 4]
GROUPS = [  # (objectId, raw label, segments)
    (0, "chair", [0]),
    (1, "storage", [1]),  # empty nyu40id in the tsv -> unlabelled
    (2, "dishrack", [2]),  # not in the tsv -> unlabelled
    (7, "cabinet", [3]),  # object ids need not be contiguous; segment 4 belongs to no group
]


def write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, ascii: bool = False) -> None:
    header = [
        "ply",
        f"format {'ascii' if ascii else 'binary_little_endian'} 1.0",
        "comment synthetic",
        f"element vertex {len(vertices)}",
        "property float x",
        "property float y",
        "property float z",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
        "property uchar alpha",
        f"element face {len(faces)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    if ascii:
        rows = [
            " ".join(f"{v:.6f}" for v in p) + " " + " ".join(str(c) for c in rgb) + " 255" for p, rgb in zip(vertices, colors)
        ]
        rows += ["3 " + " ".join(str(i) for i in f) for f in faces]
        path.write_text("\n".join(header + rows) + "\n")
        return
    vertex = np.zeros(len(vertices), [("p", "<f4", 3), ("c", "u1", 3), ("a", "u1")])
    vertex["p"], vertex["c"], vertex["a"] = vertices, colors, 255
    face = np.zeros(len(faces), [("n", "u1"), ("i", "<i4", 3)])
    face["n"], face["i"] = 3, faces
    path.write_bytes(("\n".join(header) + "\n").encode() + vertex.tobytes() + face.tobytes())


def write_scene(root: Path, name: str = "scene9999_00", ascii: bool = False, tsv_in_parent: bool = True) -> Path:
    scene = root / name
    scene.mkdir(parents=True)
    rng = np.random.default_rng(0)
    vertices = rng.uniform(-1, 1, (len(SEGMENTS), 3)).astype(np.float32).astype(np.float64)
    faces = np.array([[0, 1, 2], [3, 4, 5], [12, 13, 14]])
    colors = rng.integers(0, 256, (len(SEGMENTS), 3)).astype(np.uint8)
    write_ply(scene / f"{name}_vh_clean_2.ply", vertices, faces, colors, ascii)
    (scene / f"{name}_vh_clean_2.0.010000.segs.json").write_text(json.dumps({"sceneId": name, "segIndices": SEGMENTS}))
    groups = [{"id": i, "objectId": o, "label": label, "segments": s} for i, (o, label, s) in enumerate(GROUPS)]
    (scene / f"{name}.aggregation.json").write_text(json.dumps({"sceneId": name, "segGroups": groups}))
    ((root if tsv_in_parent else scene) / "scannet-labels.combined.tsv").write_text(TSV)
    return scene


@pytest.mark.parametrize("ascii", [False, True])
def test_synthetic_scene_ids(tmp_path, ascii):
    gt = load_scannet_ground_truth(write_scene(tmp_path, ascii=ascii))
    assert gt.scene_name == "scene9999_00"
    assert gt.vertices.shape == (15, 3) and gt.vertices.dtype == np.float64
    np.testing.assert_array_equal(gt.faces, [[0, 1, 2], [3, 4, 5], [12, 13, 14]])
    assert gt.faces.dtype == np.int64 and gt.vertex_colors.dtype == np.uint8 and gt.vertex_colors.shape == (15, 3)
    np.testing.assert_array_equal(gt.instance_ids, np.repeat([1, 2, 3, 8, 0], 3))
    np.testing.assert_array_equal(gt.nyu40_ids, np.repeat([5, 0, 0, 3, 0], 3))
    np.testing.assert_array_equal(gt.benchmark_ids(), np.repeat([5001, 0, 0, 3008, 0], 3))
    assert gt.benchmark_ids().dtype == np.int64 and gt.instance_ids.dtype == np.int32
    assert gt.instance_labels == {1: "chair", 2: "storage", 3: "dishrack", 8: "cabinet"}


def test_ascii_and_binary_meshes_agree(tmp_path):
    binary = load_scannet_ground_truth(write_scene(tmp_path / "b"))
    text = load_scannet_ground_truth(write_scene(tmp_path / "a", ascii=True))
    np.testing.assert_allclose(binary.vertices, text.vertices, atol=1e-6)
    np.testing.assert_array_equal(binary.vertex_colors, text.vertex_colors)


def test_labels_tsv_in_scene_folder_or_given(tmp_path):
    scene = write_scene(tmp_path, tsv_in_parent=False)
    assert load_scannet_ground_truth(scene).nyu40_ids[0] == 5
    (scene / "scannet-labels.combined.tsv").unlink()
    with pytest.raises(DataError, match="no labels tsv"):
        load_scannet_ground_truth(scene)
    other = tmp_path / "labels.tsv"
    other.write_text(TSV.replace("\t5\n", "\t39\n"))
    assert load_scannet_ground_truth(scene, labels_tsv=other).nyu40_ids[0] == 39


def test_v2_tsv_maps_the_raw_category_column(tmp_path):
    scene = write_scene(tmp_path)
    (tmp_path / "scannet-labels.combined.tsv").unlink()
    (tmp_path / "scannetv2-labels.combined.tsv").write_text(
        "id\traw_category\tcategory\tcount\tnyu40id\n1\tchair\toffice chair\t5\t5\n2\tcabinet\tcabinet\t3\t3\n"
    )
    np.testing.assert_array_equal(load_scannet_ground_truth(scene).benchmark_ids()[::3], [5001, 0, 0, 3008, 0])


def test_missing_and_malformed_files_name_the_file(tmp_path):
    scene = write_scene(tmp_path)
    aggregation = scene / "scene9999_00.aggregation.json"
    aggregation.write_text('{"segGroups": [{"objectId": 0, "label": "chair"}]}')
    with pytest.raises(DataError, match=r"aggregation\.json: segGroups\[0\] lacks"):
        load_scannet_ground_truth(scene)
    aggregation.write_text("{not json")
    with pytest.raises(DataError, match=r"aggregation\.json: cannot read it as JSON"):
        load_scannet_ground_truth(scene)
    aggregation.unlink()
    with pytest.raises(DataError, match=r"scene9999_00\.aggregation\.json: file not found"):
        load_scannet_ground_truth(scene)

    segs = scene / "scene9999_00_vh_clean_2.0.010000.segs.json"
    segs.write_text(json.dumps({"segIndices": SEGMENTS[:-1]}))
    with pytest.raises(DataError, match=r"segs\.json: 14 segIndices but the mesh has 15 vertices"):
        load_scannet_ground_truth(scene)

    ply = scene / "scene9999_00_vh_clean_2.ply"
    ply.write_bytes(ply.read_bytes()[:-10])
    with pytest.raises(DataError, match=r"vh_clean_2\.ply: file ends inside the 'face' element"):
        read_ply_mesh(ply)
    ply.write_text("not a mesh")
    with pytest.raises(DataError, match="not a PLY file"):
        read_ply_mesh(ply)
    with pytest.raises(DataError, match="not a ScanNet scene folder"):
        load_scannet_ground_truth(tmp_path / "nowhere")


def test_benchmark_gt_txt(tmp_path):
    path = tmp_path / "scene9999_00.txt"
    path.write_text("0\n5001\n5001\n3008\n")
    ids = load_benchmark_gt_txt(path)
    np.testing.assert_array_equal(ids, [0, 5001, 5001, 3008])
    assert ids.dtype == np.int64
    path.write_text("0\n5001\nchair\n")
    with pytest.raises(DataError, match=r"scene9999_00\.txt:3: 'chair' is not a ground-truth id"):
        load_benchmark_gt_txt(path)
    path.write_text("")
    with pytest.raises(DataError, match="no ground-truth ids"):
        load_benchmark_gt_txt(path)


# ---- the real scene ---------------------------------------------------------------------------------------

#: Counted instances (benchmark class, >= 100 vertices) of scene0000_00, from the project's notes.
SCENE0000_COUNTS = {3: 6, 4: 1, 6: 1, 7: 2, 8: 1, 9: 2, 10: 1, 12: 2, 14: 1, 16: 2, 24: 1, 33: 1, 34: 1, 39: 3}


@pytest.mark.scannet
def test_real_scene_counted_instances(scannet_scene):
    gt = load_scannet_ground_truth(scannet_scene)
    assert gt.scene_name == "scene0000_00" and gt.num_vertices == 81369
    assert gt.faces.shape == (153587, 3) and gt.vertex_colors is not None
    assert len(gt.instance_labels) == 55
    ids, sizes = np.unique(gt.benchmark_ids(), return_counts=True)
    counted = ids[np.isin(ids // 1000, BENCHMARK_NYU40_IDS) & (sizes >= 100)]
    classes, per_class = np.unique(counted // 1000, return_counts=True)
    assert dict(zip(classes.tolist(), per_class.tolist())) == SCENE0000_COUNTS
    assert len(counted) == 25 and len(classes) == 14
    # "dishrack" (not in the tsv) is an instance without a class: 0 in the benchmark encoding.
    dishrack = next(i for i, label in gt.instance_labels.items() if label == "dishrack")
    assert np.all(gt.nyu40_ids[gt.instance_ids == dishrack] == 0)
    assert np.all(gt.benchmark_ids()[gt.instance_ids == dishrack] == 0)
