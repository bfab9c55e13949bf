"""`fmfusion query`'s work (the parser is `cli/query.py`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh

from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import load_label_sets
from fmfusion_jax.scene_graph import build_scene_graph, query
from fmfusion_jax.viz import overview


def run_query(
    *,
    map: Path,
    text: str,
    top: int,
    json_path: Path | None,
    picture: Path | None,
) -> int:

    path = map / "instances.json" if map.is_dir() else map
    try:
        records = json.loads(path.read_text())["instances"]
    except FileNotFoundError:
        raise UserError(f"{path}: not found (give the output folder of fmfusion run or demo)") from None
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as error:
        raise UserError(f"{path}: not an instances.json ({error})") from None
    graph_path = path.parent / "scene_graph.json"
    graph = json.loads(graph_path.read_text()) if graph_path.is_file() else build_scene_graph(records)
    by_id = {r["id"]: r for r in records}
    matches = query(records, text, graph)[: max(1, top)]
    rows = []
    for m in matches:
        record = by_id[m.instance_id]
        box = record["oriented_box"]
        rows.append(
            {
                "id": m.instance_id,
                "class": record["class"],
                "score": round(m.score, 3),
                "why": m.why,
                "center": [round(x, 3) for x in box["center"]],
                "extent": [round(x, 3) for x in box["extent"]],
                "yaw": round(box["yaw"], 3),
            }
        )
        print(f"{m.instance_id:5d}  {record['class']:<15} score {m.score:5.2f}  at {rows[-1]['center']}  ({m.why})")
    if not rows:
        print(f"no instance matches {text!r}")
    if json_path:
        json_path.write_text(json.dumps({"query": text, "matches": rows}, indent=1))
    if picture:
        draw_matches(picture, path.parent, text, [r["id"] for r in rows], records)
        print(f"picture: {picture}")
    return 0


#: RGB of the matched instances' points in the picture.
HIGHLIGHT = (220, 30, 30)


def draw_matches(picture: Path, out_dir: Path, text: str, matched: list[int], records: list[dict]) -> None:
    """A top-down picture of the map (mesh and instances in grey) with the matched instances in red."""

    cloud_path = out_dir / "labelled_points.npz"
    if not cloud_path.is_file():
        raise UserError(f"{cloud_path}: not found; --picture needs the labelled points written with the map")
    with np.load(cloud_path) as cloud:
        points, instance = cloud["points"], cloud["instance"]
    spacing = overview.point_spacing(points, 0.02) if len(points) else 0.02
    layers = []
    mesh_path = out_dir / "mesh.ply"
    if mesh_path.is_file():
        mesh = trimesh.load(mesh_path, process=False)
        if isinstance(mesh, trimesh.Trimesh) and len(mesh.faces):
            vertices = np.asarray(mesh.vertices, np.float32)
            vertex_colors = getattr(getattr(mesh, "visual", None), "vertex_colors", None)
            colors = None if vertex_colors is None else np.asarray(vertex_colors)[:, :3]
            layers.append(
                overview.OverviewLayer(
                    vertices,
                    overview.grey_from_colors(colors, len(vertices)),
                    overview.mesh_spacing(vertices, np.asarray(mesh.faces), spacing),
                    faces=np.asarray(mesh.faces),
                )
            )
    hit = np.isin(instance, matched)
    layers.append(
        overview.OverviewLayer(points[~hit], np.full(((~hit).sum(), 3), 150, np.uint8), spacing, overview.INSTANCE_Z_BIAS)
    )
    layers.append(
        overview.OverviewLayer(
            points[hit], np.tile(np.array(HIGHLIGHT, np.uint8), (int(hit.sum()), 1)), spacing, 2 * overview.INSTANCE_Z_BIAS
        )
    )
    label_sets = load_label_sets()
    by_id = {r["id"]: r for r in records}
    counts: dict[int, int] = {}
    for i in matched:
        index = label_sets.class_index(by_id[i]["class"])
        counts[index] = counts.get(index, 0) + 1
    panel = overview.OverviewPanel(f"matches in red ({len(matched)})", layers, counts)
    try:
        overview.write_overview(picture, [panel], label_sets, f"query: {text}")
    except OSError as error:
        raise UserError(f"cannot write {picture}: {error}") from None
