"""Writers of a fused map's outputs: PLY point clouds and meshes, instances.json, benchmark files.

They take plain arrays and `MapInstance`s; nothing here knows the engine.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh

from fmfusion_jax.instances import MapInstance
from fmfusion_jax.io.benchmark_format import InstancePredictions
from fmfusion_jax.labels import LabelSets


def instance_colors(num: int, seed: int = 7) -> np.ndarray:
    """`(num, 3)` uint8 well-separated random colours (golden-ratio hues), stable for a given seed."""
    hues = (np.arange(num) * 0.618033988749895 + seed * 0.1) % 1.0
    rgb = np.stack([np.abs(hues * 6 - 3) - 1, 2 - np.abs(hues * 6 - 2), 2 - np.abs(hues * 6 - 4)], axis=1)
    return (np.clip(rgb, 0, 1) * 200 + 40).astype(np.uint8)


def write_point_cloud(path: Path, points: np.ndarray, colors: np.ndarray) -> None:
    """A PLY point cloud with RGB colours (opens in MeshLab, CloudCompare, Open3D, trimesh)."""
    rgba = np.concatenate([colors.astype(np.uint8), np.full((len(colors), 1), 255, np.uint8)], axis=1)
    trimesh.PointCloud(np.asarray(points, np.float64), colors=rgba).export(str(path))


def write_mesh(path: Path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None) -> None:
    mesh = trimesh.Trimesh(vertices=np.asarray(vertices, np.float64), faces=np.asarray(faces), process=False)
    if colors is not None:
        mesh.visual.vertex_colors = np.concatenate(
            [colors.astype(np.uint8), np.full((len(colors), 1), 255, np.uint8)], axis=1)
    mesh.export(str(path))


def write_instance_clouds(out_dir: Path, instances: list[MapInstance], label_sets: LabelSets) -> None:
    """`semantic.ply` (coloured by class), `instances.ply` (per instance) and one PLY per instance."""
    if not instances:
        return
    points = np.concatenate([inst.points for inst in instances])
    class_colors = np.concatenate([np.repeat(label_sets.class_colors[inst.class_index][None], len(inst.points), 0)
                                   for inst in instances])
    palette = instance_colors(len(instances))
    per_instance = np.concatenate([np.repeat(palette[i][None], len(inst.points), 0)
                                   for i, inst in enumerate(instances)])
    write_point_cloud(out_dir / "semantic.ply", points, class_colors)
    write_point_cloud(out_dir / "instances.ply", points, per_instance)
    folder = out_dir / "instances"
    folder.mkdir(exist_ok=True)
    for i, inst in enumerate(instances):
        name = label_sets.class_names[inst.class_index].replace(" ", "_")
        write_point_cloud(folder / f"{inst.instance_id:04d}_{name}.ply", inst.points,
                          np.repeat(palette[i][None], len(inst.points), 0))


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
    return {"center": [float(centre_xy[0]), float(centre_xy[1]), float(centre_local[2])],
            "extent": (hi - lo).astype(float).tolist(), "yaw": yaw}


def instances_json(instances: list[MapInstance], label_sets: LabelSets) -> list[dict]:
    """One record per instance: class, confidence, distribution, label histogram, size, box."""
    records = []
    for inst in instances:
        histogram = {label_sets.open_labels[i]: round(float(v), 4)
                     for i, v in enumerate(inst.open_label_histogram) if v > 0}
        records.append({
            "id": inst.instance_id,
            "class": label_sets.class_names[inst.class_index],
            "nyu40_id": int(label_sets.nyu40_ids[inst.class_index]),
            "confidence": round(inst.confidence, 6),
            "distribution": {name: round(float(p), 6) for name, p in zip(label_sets.class_names, inst.distribution)},
            "observations": inst.observations,
            "open_label_histogram": dict(sorted(histogram.items(), key=lambda kv: -kv[1])),
            "points": int(len(inst.points)),
            "oriented_box": oriented_box(inst.points),
        })
    return records


def write_instances_json(path: Path, instances: list[MapInstance], label_sets: LabelSets) -> None:
    path.write_text(json.dumps({"instances": instances_json(instances, label_sets)}, indent=1))


def benchmark_predictions(instances: list[MapInstance], label_sets: LabelSets, vertices: np.ndarray,
                          radius: float) -> InstancePredictions:
    """Instances transferred to mesh vertices by radius search, with nyu40 ids and confidences.

    Wall and floor are not benchmark classes and are left out.
    """
    from fmfusion_jax.evaluation.vertex_transfer import points_to_vertex_masks

    keep = [inst for inst in instances if label_sets.class_names[inst.class_index] not in ("wall", "floor")]
    if not keep:
        return InstancePredictions.empty(len(vertices))
    masks = points_to_vertex_masks(vertices, [inst.points for inst in keep], radius=radius)
    return InstancePredictions(masks=masks,
                               nyu40_ids=np.array([label_sets.nyu40_ids[i.class_index] for i in keep], np.int32),
                               confidences=np.array([i.confidence for i in keep], np.float64))

