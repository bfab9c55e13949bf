"""Writers of a fused map's outputs: PLY point clouds and meshes, instances.json and benchmark files
(`overview.png` is drawn by `fmfusion_jax.viz.overview`).

They take plain arrays and `MapInstance`s; nothing here knows the engine.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from fmfusion_jax.instances import STRUCTURE_CLASSES, MapInstance
from fmfusion_jax.io.benchmark_format import InstancePredictions
from fmfusion_jax.io.vertex_transfer import points_to_vertex_masks
from fmfusion_jax.labels import LabelSets
from fmfusion_jax.npz_files import write_npz


def instance_colors(num: int, seed: int = 7) -> np.ndarray:
    """`(num, 3)` uint8 well-separated random colours (golden-ratio hues), stable for a given seed."""
    hues = (np.arange(num) * 0.618033988749895 + seed * 0.1) % 1.0
    rgb = np.stack([np.abs(hues * 6 - 3) - 1, 2 - np.abs(hues * 6 - 2), 2 - np.abs(hues * 6 - 4)], axis=1)
    return (np.clip(rgb, 0, 1) * 200 + 40).astype(np.uint8)


#: A PLY property: `(name, NumPy type, PLY type, values)`.
PlyColumn = tuple[str, Any, str, Any]


def _ply_columns(points: np.ndarray, colors: np.ndarray | None, channels: tuple[str, ...]) -> list[PlyColumn]:
    """x, y, z as float32, then `channels` of `colors` (uint8; a fourth channel without colour values is opaque)."""
    columns: list[PlyColumn] = [(axis, "<f4", "float", np.asarray(points, np.float32)[:, i]) for i, axis in enumerate("xyz")]
    if colors is not None:
        rgb = np.asarray(colors, np.uint8)
        columns += [(c, "u1", "uchar", rgb[:, i] if i < rgb.shape[1] else 255) for i, c in enumerate(channels)]
    return columns


def _write_ply(path: Path, comment: str, elements: list[tuple[str, int, list[PlyColumn]]]) -> None:
    """A binary little-endian PLY of `(element name, count, columns)`; a PLY type `list uchar int` is a list property
    (its NumPy type holds the count and the items). Each element's rows are packed and written in turn, straight
    from the packed array: a mesh's blocks are tens of MiB, and no two are held at once."""
    header = ["ply", "format binary_little_endian 1.0", f"comment {comment}"]
    for element, count, columns in elements:
        header.append(f"element {element} {count}")
        header += [f"property {ply_type} {name}" for name, _, ply_type, _ in columns]
    with open(path, "wb") as stream:
        stream.write(("\n".join([*header, "end_header"]) + "\n").encode("ascii"))
        for _, count, columns in elements:
            block = np.empty(count, np.dtype([(name, code) for name, code, _, _ in columns]))
            for name, _, _, values in columns:
                block[name] = values
            stream.write(block.view(np.uint8).data)
            del block


def write_point_cloud(
    path: Path, points: np.ndarray, colors: np.ndarray, label: np.ndarray | None = None, instance: np.ndarray | None = None
) -> None:
    """A binary PLY point cloud with RGB colours (opens in MeshLab, CloudCompare, Open3D, trimesh).

    Args:
      points: `(N, 3)` world points, metres.
      colors: `(N, 3)` uint8.
      label: optional `(N,)` NYU40 ids, written as the `ushort label` vertex property of ScanNet's
        `*_vh_clean_2.labels.ply`.
      instance: optional `(N,)` instance ids, written as an `int instance` vertex property.
    """
    columns = _ply_columns(points, colors, ("red", "green", "blue"))
    if label is not None:
        columns.append(("label", "<u2", "ushort", label))
    if instance is not None:
        columns.append(("instance", "<i4", "int", instance))
    _write_ply(path, "written by fmfusion-jax", [("vertex", len(points), columns)])


def write_mesh(path: Path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None) -> None:
    """A binary PLY triangle mesh, vertex colours RGBA; an empty mesh is written as a valid PLY with no vertex and no
    face."""
    comment = "written by fmfusion-jax"
    if len(vertices) == 0 or len(faces) == 0:
        vertices, faces, colors, comment = np.zeros((0, 3)), np.zeros((0, 3), np.int32), None, comment + " (empty mesh)"
    face_type = np.dtype([("count", "u1"), ("items", "<i4", (3,))])  # a PLY list: its length, then its items
    face_lists = np.empty(len(faces), face_type)
    face_lists["count"], face_lists["items"] = 3, faces
    vertex_columns = _ply_columns(vertices, colors, ("red", "green", "blue", "alpha"))
    face_columns: list[PlyColumn] = [("vertex_indices", face_type, "list uchar int", face_lists)]
    _write_ply(path, comment, [("vertex", len(vertices), vertex_columns), ("face", len(faces), face_columns)])


def write_labelled_points(out_dir: Path, points: np.ndarray, colors: np.ndarray, label: np.ndarray, instance: np.ndarray) -> None:
    """The instance points with their labels for robotics tools: `labelled_points.npz` (arrays `points` float32
    (N, 3) world metres, `colors` uint8 (N, 3), `label` uint16 NYU40 ids, `instance` int32 ids) and
    `labelled_points.pcd` (PCD v0.7, binary; fields x y z rgb label instance, as PCL and ROS read them)."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    colors = np.asarray(colors, np.uint8).reshape(-1, 3)
    write_npz(
        out_dir / "labelled_points.npz",
        [
            ("points", points),
            ("colors", colors),
            ("label", np.asarray(label, np.uint16)),
            ("instance", np.asarray(instance, np.int32)),
        ],
    )
    rgb = (colors[:, 0].astype(np.uint32) << 16) | (colors[:, 1].astype(np.uint32) << 8) | colors[:, 2].astype(np.uint32)
    rows = np.empty(
        len(points), np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4"), ("label", "<u4"), ("instance", "<i4")])
    )
    rows["x"], rows["y"], rows["z"] = points[:, 0], points[:, 1], points[:, 2]
    rows["rgb"], rows["label"], rows["instance"] = rgb, np.asarray(label, np.uint32), np.asarray(instance, np.int32)
    header = [
        "# .PCD v0.7 - written by fmfusion-jax",
        "VERSION 0.7",
        "FIELDS x y z rgb label instance",
        "SIZE 4 4 4 4 4 4",
        "TYPE F F F U U I",
        "COUNT 1 1 1 1 1 1",
        f"WIDTH {len(points)}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {len(points)}",
        "DATA binary",
    ]
    (out_dir / "labelled_points.pcd").write_bytes(("\n".join(header) + "\n").encode("ascii") + rows.tobytes())


@dataclasses.dataclass(frozen=True)
class InstancePoints:
    """The points of all instances, concatenated in instance order (empty arrays without instances): `points`
    float32 (N, 3), `class_colors` and `instance_colors` uint8 (N, 3) (by class, NYU40 palette; by instance,
    `instance_colors`), `label` uint16 NYU40 ids, `instance` int32 instance ids (the `id` of instances.json)."""

    points: np.ndarray
    class_colors: np.ndarray
    instance_colors: np.ndarray
    label: np.ndarray
    instance: np.ndarray


def instance_points(instances: list[MapInstance], label_sets: LabelSets) -> InstancePoints:
    """The points of `instances` with their colours, NYU40 labels and ids (semantic.ply, instances.ply and
    labelled_points.* are written from them; without instances they are empty, and so valid empty files)."""
    if not instances:
        colors = np.zeros((0, 3), np.uint8)
        return InstancePoints(np.zeros((0, 3), np.float32), colors, colors, np.zeros(0, np.uint16), np.zeros(0, np.int32))
    palette = instance_colors(len(instances))
    return InstancePoints(
        points=np.concatenate([inst.points for inst in instances]),
        class_colors=np.concatenate(
            [np.repeat(label_sets.class_colors[inst.class_index][None], len(inst.points), 0) for inst in instances]
        ),
        instance_colors=np.concatenate([np.repeat(palette[i][None], len(inst.points), 0) for i, inst in enumerate(instances)]),
        label=np.concatenate(
            [np.full(len(inst.points), label_sets.nyu40_ids[inst.class_index], np.uint16) for inst in instances]
        ),
        instance=np.concatenate([np.full(len(inst.points), inst.instance_id, np.int32) for inst in instances]),
    )


def write_instance_folder(folder: Path, instances: list[MapInstance], label_sets: LabelSets) -> None:
    """One PLY per instance, `NNNN_<class>.ply`, in its instance colour (the folder is empty without instances)."""
    folder.mkdir(exist_ok=True)
    palette = instance_colors(len(instances))
    for i, inst in enumerate(instances):
        name = label_sets.class_names[inst.class_index].replace(" ", "_")
        write_point_cloud(
            folder / f"{inst.instance_id:04d}_{name}.ply", inst.points, np.repeat(palette[i][None], len(inst.points), 0)
        )


def oriented_box(points: np.ndarray) -> dict:
    """A gravity-aligned oriented box (yaw only; z up), the usual box of indoor scenes."""
    if len(points) < 3:
        return {"center": points.mean(0).tolist() if len(points) else [0, 0, 0], "extent": [0, 0, 0], "yaw": 0.0}
    xy = points[:, :2] - points[:, :2].mean(0)
    _, vectors = np.linalg.eigh(xy.T @ xy)
    axis = vectors[:, -1]
    yaw = float(np.arctan2(axis[1], axis[0]))
    rotation = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])
    local = points[:, :2] @ rotation.T
    lo, hi = np.concatenate([local.min(0), points[:, 2:].min(0)]), np.concatenate([local.max(0), points[:, 2:].max(0)])
    centre_local = (lo + hi) / 2
    centre_xy = rotation.T @ centre_local[:2]
    return {
        "center": [float(centre_xy[0]), float(centre_xy[1]), float(centre_local[2])],
        "extent": (hi - lo).astype(float).tolist(),
        "yaw": yaw,
    }


def instances_json(instances: list[MapInstance], label_sets: LabelSets) -> list[dict]:
    """One record per instance: class, confidence, existence, distribution, detection counts, label histogram, size, box."""
    records = []
    for inst in instances:
        histogram = {label_sets.open_labels[i]: round(float(v), 4) for i, v in enumerate(inst.open_label_histogram) if v > 0}
        records.append(
            {
                "id": inst.instance_id,
                "class": label_sets.class_names[inst.class_index],
                "nyu40_id": int(label_sets.nyu40_ids[inst.class_index]),
                "confidence": round(inst.confidence, 6),
                "distribution": {name: round(float(p), 6) for name, p in zip(label_sets.class_names, inst.distribution)},
                "existence": round(inst.existence, 6),
                "observations": inst.observations,
                "missed": inst.missed,
                "open_label_histogram": dict(sorted(histogram.items(), key=lambda kv: -kv[1])),
                "voxel_count": int(len(inst.points)),
                "oriented_box": oriented_box(inst.points),
            }
        )
    return records


#: `schema` and `version` of instances.json (docs/instances.schema.json describes every field).
INSTANCES_SCHEMA = "fmfusion-jax instances"
INSTANCES_SCHEMA_VERSION = 3


def write_instances_json(path: Path, records: list[dict]) -> None:
    """instances.json: a header saying what the numbers mean, then the records of `instances_json`."""
    document = {
        "schema": INSTANCES_SCHEMA,
        "version": INSTANCES_SCHEMA_VERSION,
        "units": "metres",
        "frame": "world: the frame the camera poses map into (T_world_camera); ScanNet's world is z up",
        "instances": records,
    }
    path.write_text(json.dumps(document, indent=1))


def benchmark_predictions(
    instances: list[MapInstance],
    label_sets: LabelSets,
    vertices: np.ndarray,
    radius: float,
    structure_claims_vertices: bool = False,
    neighbours: int = 1,
    floor_vertices: np.ndarray | None = None,
    alternative_class_probability: float = 1.0,
    faces: np.ndarray | None = None,
    union_confidence_factor: float = 0.0,
) -> InstancePredictions:
    """Instances transferred to mesh vertices by radius search, with nyu40 ids and confidences.

    Each instance is one prediction under its most likely class (confidence `MapInstance.confidence`), then,
    after all of those, one more under each other benchmark class it has at least
    `alternative_class_probability` of (`alternative_class_hypotheses`), then, with the mesh's `faces` and a
    `union_confidence_factor` above 0, the union of each two touching lines of one class, one of them an instance's
    most likely class (`union_hypotheses`).

    Wall and floor are not benchmark classes and are left out of the predictions. With
    `structure_claims_vertices` they first take part in the transfer (each vertex goes to its nearest
    instance point), so the floor vertices around an object's base go to the floor rather than to the
    object's lowest points; a point held by an object and by the wall or floor stays the object's.
    `neighbours`: see `io.vertex_transfer.points_to_vertex_masks`. `floor_vertices` `(V,)` bool: vertices
    on the map's floor (`io.vertex_transfer.floor_vertices`), which no object claims.
    """

    structure = [inst for inst in instances if label_sets.class_names[inst.class_index] in STRUCTURE_CLASSES]
    keep = [inst for inst in instances if label_sets.class_names[inst.class_index] not in STRUCTURE_CLASSES]
    if not keep:
        return InstancePredictions.empty(len(vertices))
    claimants = keep + (structure if structure_claims_vertices else [])
    masks = points_to_vertex_masks(vertices, [inst.points for inst in claimants], radius=radius, neighbours=neighbours)[
        : len(keep)
    ]
    if floor_vertices is not None:
        masks &= ~np.asarray(floor_vertices, bool)[None, :]
    rows, classes, confidences = alternative_class_hypotheses(keep, label_sets, alternative_class_probability)
    # the lines before the unions: each instance under its most likely class, then its class hypotheses
    line_rows = np.concatenate([np.arange(len(keep)), rows]).astype(np.int64)
    line_classes = np.concatenate([[i.class_index for i in keep], classes]).astype(np.int64)
    line_confidences = np.concatenate([[i.confidence for i in keep], confidences]).astype(np.float64)
    line_masks = masks[line_rows]
    pairs = np.zeros((0, 2), np.int64)
    union_confidences = np.zeros(0)
    if faces is not None and union_confidence_factor > 0:
        primary = np.arange(len(line_rows)) < len(keep)
        pairs, union_confidences = union_hypotheses(
            line_masks, line_classes, line_confidences, faces, union_confidence_factor, primary
        )
    return InstancePredictions(
        masks=np.concatenate([line_masks, line_masks[pairs[:, 0]] | line_masks[pairs[:, 1]]]),
        nyu40_ids=label_sets.nyu40_ids[np.concatenate([line_classes, line_classes[pairs[:, 0]]])],
        confidences=np.concatenate([line_confidences, union_confidences]),
        alternative=np.arange(len(line_rows) + len(pairs)) >= len(keep),
    )


def union_hypotheses(
    masks: np.ndarray,
    class_ids: np.ndarray,
    confidences: np.ndarray,
    faces: np.ndarray,
    factor: float,
    primary: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """`(pairs (U, 2), confidences (U,))`: the hypotheses (rows of `masks (P, V)`, of classes `class_ids (P,)` and
    confidences `(P,)`) two by two, `a < b`, where both are of one class and an edge of the mesh (`faces (F, 3)`)
    joins a vertex of one to a vertex of the other; the confidence is `factor` times the lower of the two.
    `primary (P,)` bool: only pairs with at least one primary row (an instance under its most likely class; the
    others are its alternative class hypotheses); None: every row is one.

    Why: the map splits an object whose masks cut it in two in most frames (an L-shaped sofa seen one arm at a
    time), and two pieces side by side never pass the merge's overlap test. Neither piece passes IoU 0.5 with the
    object; their union, submitted beside them and below both, does. Where the two are distinct objects (two
    cabinets in a row), the union is a false positive ranked under both. A piece whose labels lean to another class
    (the sofa's arm fused as a chair, sofa its second class) joins under the class of its alternative hypothesis."""
    masks = np.asarray(masks, bool)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    pairs: list[tuple[int, int]] = []
    if len(masks) < 2 or len(faces) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    ends = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    for c in np.unique(class_ids):
        rows = np.flatnonzero(class_ids == c)
        if len(rows) < 2:
            continue
        held = masks[rows]  # (R, V)
        # the edges with both ends on this class's lines: the only ones that can join two of them
        on_class = np.asarray(held.any(axis=0))
        near = ends[on_class[ends[:, 0]] & on_class[ends[:, 1]]]
        start, end = held[:, near[:, 0]], held[:, near[:, 1]]  # (R, E')
        for a in range(len(rows)):
            for b in range(a + 1, len(rows)):
                if primary is not None and not (primary[rows[a]] or primary[rows[b]]):
                    continue  # two alternatives: neither piece is its instance's most likely class
                if np.any((start[a] & end[b]) | (start[b] & end[a])):
                    pairs.append((int(rows[a]), int(rows[b])))
    if not pairs:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    pairs.sort()
    out = np.array(pairs, np.int64)
    return out, factor * np.minimum(confidences[out[:, 0]], confidences[out[:, 1]])


def alternative_class_hypotheses(
    instances: list[MapInstance], label_sets: LabelSets, min_probability: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(rows (A,), classes (A,), confidences (A,))`: for each instance (row of `instances`), each class other than
    its most likely one, not wall or floor, of probability at least `min_probability` in its distribution; the
    confidence is that probability times the instance's existence (as `MapInstance.confidence` is for the most
    likely class). In instance order, then by falling probability.

    Why: the benchmark ranks every (mask, class) hypothesis per class. An instance whose fused distribution is
    split between two classes (a cabinet or a counter, a desk or a table) is the object of one of them; submitted
    under both, it counts for the right one at a confidence below the sure instances of that class."""
    structure = {label_sets.class_index(name) for name in STRUCTURE_CLASSES if name in label_sets.class_names}
    rows, classes, confidences = [], [], []
    for row, inst in enumerate(instances):
        top = inst.class_index
        for c in np.argsort(-inst.distribution, kind="stable"):
            p = float(inst.distribution[c])
            if p < min_probability or p <= 0.0:
                break
            if c != top and c not in structure:
                rows.append(row)
                classes.append(int(c))
                confidences.append(p * float(inst.existence))
    return np.array(rows, np.int64), np.array(classes, np.int64), np.array(confidences, np.float64)


# ---------------------------------------------------------------------------------------------------
# overview.png: a top-down picture of the map by class, beside the ground truth when there is one.
