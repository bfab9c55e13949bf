"""A scene graph of a map, and text queries over its instances (NumPy; reads `instances.json` records).

Nodes are the instances (class, confidence, top open-set labels, the gravity-aligned oriented box) plus
the room's floor as the root. Edges are spatial relations computed from the boxes, each with a score in
(0, 1]:

- `on` (a on b): a's bottom lies within `support_gap` of b's top and most of a's footprint is over b's
  (score: the footprint share); an object on no other object is `on` the floor when its bottom is within
  `floor_gap` of the floor;
- `inside` (a inside b): most of a's box volume lies in b's box (score: that share);
- `near` (a near b, both ways): the gap between the boxes is below `near_distance` and neither is on or
  inside the other (score: 1 - gap / near_distance).

Footprints and volumes are compared on a grid of sample points in each box, so oriented boxes need no
polygon clipping. Structure classes (wall, floor) take no part in `near`.
"""

from __future__ import annotations

import dataclasses
import difflib
import re
from collections.abc import Sequence
from typing import Any

import networkx as nx
import numpy as np

from fmfusion_jax.instances import STRUCTURE_CLASSES

FLOOR_NODE = "floor"
RELATIONS = ("on", "inside", "near")


@dataclasses.dataclass(frozen=True)
class GraphSettings:
    support_gap: float = 0.10  # m between a's bottom and b's top for `on`
    min_support_share: float = 0.5  # share of a's footprint over b's
    floor_gap: float = 0.15  # m between an object's bottom and the floor for `on` the floor
    min_inside_share: float = 0.8  # share of a's volume inside b for `inside`
    near_distance: float = 0.3  # m between the boxes for `near`


def _box(record: dict) -> tuple[np.ndarray, np.ndarray, float]:
    box = record["oriented_box"]
    return np.asarray(box["center"], float), np.maximum(np.asarray(box["extent"], float), 1e-3), float(box["yaw"])


def _to_local(points: np.ndarray, center: np.ndarray, yaw: float) -> np.ndarray:
    """World points `(M, 3)` in a box's frame (its centre at the origin, its axes along x, y, z)."""
    c, s = np.cos(yaw), np.sin(yaw)
    rel = points - center
    return np.stack([rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c, rel[:, 2]], axis=1)


def _samples(center: np.ndarray, extent: np.ndarray, yaw: float, n: int = 6, closed: bool = False) -> np.ndarray:
    """`(n^3, 3)` world points spread over a box: cell centres, or with `closed` a grid reaching its faces."""
    t = np.linspace(-0.5, 0.5, n) if closed else (np.arange(n) + 0.5) / n - 0.5
    grid = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3) * extent
    c, s = np.cos(yaw), np.sin(yaw)
    world = np.stack([grid[:, 0] * c - grid[:, 1] * s, grid[:, 0] * s + grid[:, 1] * c, grid[:, 2]], axis=1)
    return world + center


def _inside_share(points: np.ndarray, center: np.ndarray, extent: np.ndarray, yaw: float, dims: int = 3) -> float:
    local = _to_local(points, center, yaw)
    return float(np.mean(np.all(np.abs(local[:, :dims]) <= extent[:dims] / 2 + 1e-9, axis=1)))


Box = tuple[np.ndarray, np.ndarray, float]


def _face_samples(box: Box) -> np.ndarray:
    """`_gap`'s sample points of a box: a 7^3 grid reaching its faces."""
    return _samples(*box, n=7, closed=True)


def _gap(a: Box, b: Box, samples_a: np.ndarray, samples_b: np.ndarray) -> float:
    """Distance between two boxes, approximated from sample points reaching their faces (0 when they overlap);
    `samples_*`: their `_face_samples` (made once per box)."""
    gaps = []
    for samples, other in ((samples_a, b), (samples_b, a)):
        local = _to_local(samples, other[0], other[2])
        gaps.append(float(np.min(np.linalg.norm(np.maximum(np.abs(local) - other[1] / 2, 0.0), axis=1))))
    return min(gaps)


def build_scene_graph(records: Sequence[dict], settings: GraphSettings = GraphSettings()) -> dict[str, Any]:
    """The scene graph of `instances.json` records: `{"nodes": [...], "edges": [...], "floor_z": z}`.

    Each edge is `{"source": id, "relation": "on" | "inside" | "near", "target": id or "floor", "score": s}`.
    """
    objects = [r for r in records if r["class"] not in STRUCTURE_CLASSES]
    boxes = {r["id"]: _box(r) for r in records}
    floors = [r for r in records if r["class"] == "floor"]
    bottoms = {i: b[0][2] - b[1][2] / 2 for i, b in boxes.items()}
    tops = {i: b[0][2] + b[1][2] / 2 for i, b in boxes.items()}
    if floors:
        floor_z = float(np.median([tops[r["id"]] for r in floors]))
    elif objects:
        floor_z = float(min(bottoms[r["id"]] for r in objects))
    else:
        floor_z = 0.0

    nodes = [{"id": FLOOR_NODE, "class": "floor", "root": True, "z": round(floor_z, 4)}]
    for r in records:
        center, extent, yaw = boxes[r["id"]]
        labels = sorted(r.get("open_label_histogram", {}).items(), key=lambda kv: -kv[1])[:3]
        nodes.append(
            {
                "id": r["id"],
                "class": r["class"],
                "confidence": r.get("confidence"),
                "top_labels": [label for label, _ in labels],
                "centroid": center.round(4).tolist(),
                "extent": extent.round(4).tolist(),
                "yaw": round(yaw, 4),
                "points": r.get("voxel_count"),
            }
        )

    edges: list[dict[str, Any]] = []
    supported: set = set()
    contained: set[tuple] = set()
    for a in objects:
        ia, box_a = a["id"], boxes[a["id"]]
        footprint = _samples(*box_a, n=6)  # a's volume samples; their x, y are its footprint
        best = None
        for b in objects:
            ib, box_b = b["id"], boxes[b["id"]]
            if ib == ia:
                continue
            share = _inside_share(footprint, *box_b)
            if share >= settings.min_inside_share and np.prod(box_a[1]) < np.prod(box_b[1]):
                edges.append({"source": ia, "relation": "inside", "target": ib, "score": round(share, 3)})
                contained.add((ia, ib))
                continue
            if abs(bottoms[ia] - tops[ib]) <= settings.support_gap and tops[ia] > tops[ib]:
                over = _inside_share(footprint, *box_b, dims=2)
                if over >= settings.min_support_share and (best is None or over > best[1]):
                    best = (ib, over)
        if best is not None:
            edges.append({"source": ia, "relation": "on", "target": best[0], "score": round(best[1], 3)})
            supported.add((ia, best[0]))
        elif bottoms[ia] - floor_z <= settings.floor_gap and not any(pair[0] == ia for pair in contained):
            score = 1.0 - max(0.0, bottoms[ia] - floor_z) / settings.floor_gap
            edges.append({"source": ia, "relation": "on", "target": FLOOR_NODE, "score": round(max(score, 0.01), 3)})

    face_samples = {r["id"]: _face_samples(boxes[r["id"]]) for r in objects}  # once per box, not per pair
    for i, a in enumerate(objects):
        for b in objects[i + 1 :]:
            ia, ib = a["id"], b["id"]
            if {(ia, ib), (ib, ia)} & (supported | contained):
                continue
            gap = _gap(boxes[ia], boxes[ib], face_samples[ia], face_samples[ib])
            if gap < settings.near_distance:
                score = round(1.0 - gap / settings.near_distance, 3)
                edges.append({"source": ia, "relation": "near", "target": ib, "score": score})
                edges.append({"source": ib, "relation": "near", "target": ia, "score": score})
    return {"floor_z": floor_z, "nodes": nodes, "edges": edges}


def write_graphml(path, graph: dict[str, Any]) -> None:
    """The scene graph as GraphML (networkx), for graph tools (Gephi, yEd, networkx itself)."""

    g = nx.MultiDiGraph()
    for node in graph["nodes"]:
        g.add_node(
            str(node["id"]), **{k: (str(v) if isinstance(v, list) else v) for k, v in node.items() if k != "id" and v is not None}
        )
    for edge in graph["edges"]:
        g.add_edge(str(edge["source"]), str(edge["target"]), relation=edge["relation"], score=edge["score"])
    nx.write_graphml(g, str(path))


# ------------------------------------------------------------------------------------------------
# Queries

#: Words for what an object is for, mapped to the classes that serve it.
SYNONYMS: dict[str, tuple[str, ...]] = {
    "something to sit on": ("chair", "sofa", "bed", "toilet"),
    "seat": ("chair", "sofa", "toilet"),
    "couch": ("sofa",),
    "armchair": ("chair", "sofa"),
    "fridge": ("refrigerator",),
    "shelf": ("bookshelf",),
    "bookcase": ("bookshelf",),
    "closet": ("cabinet",),
    "wardrobe": ("cabinet",),
    "drawer": ("cabinet",),
    "tub": ("bathtub",),
    "washbasin": ("sink",),
    "nightstand": ("cabinet", "otherfurniture"),
    "worktop": ("counter",),
    "screen": ("otherfurniture",),
}
#: An instance is found by an open-set label only when that label holds this share of all it was seen as.
MIN_LABEL_SHARE = 0.2
_RELATION_WORDS = {
    "on": "on",
    "on top of": "on",
    "in": "inside",
    "inside": "inside",
    "near": "near",
    "next to": "near",
    "beside": "near",
    "by": "near",
}


@dataclasses.dataclass(frozen=True)
class QueryMatch:
    instance_id: int
    score: float
    why: str


def _clean(text: str) -> str:
    return re.sub(r"\s+", " ", re.sub(r"\b(the|a|an|some)\b", " ", text.lower())).strip()


def match_phrase(records: Sequence[dict], phrase: str) -> list[QueryMatch]:
    """Instances a noun phrase names, best first: the closed class or a synonym (score 1 + confidence), an
    open-set label that is at least `MIN_LABEL_SHARE` of what the instance was seen as (half that share),
    then close spellings of either (0.25 x confidence)."""
    phrase = _clean(phrase)
    singular = phrase[:-1] if phrase.endswith("s") and not phrase.endswith("ss") else phrase
    classes = set(SYNONYMS.get(phrase, ()) + SYNONYMS.get(singular, ()))
    matches = []
    for r in records:
        name = r["class"]
        histogram = r.get("open_label_histogram", {})
        total = sum(histogram.values()) or 1.0
        confidence = float(r.get("confidence") or 0.0)
        if name in (phrase, singular) or name in classes:
            matches.append(QueryMatch(r["id"], 1.0 + confidence, f"class {name}"))
        elif (share := histogram.get(phrase, histogram.get(singular, 0.0)) / total) >= MIN_LABEL_SHARE:
            matches.append(QueryMatch(r["id"], 0.5 * share, f"seen as '{phrase}' ({100 * share:.0f}% of its labels)"))
        else:
            close = difflib.get_close_matches(singular, [name, *histogram], n=1, cutoff=0.85)
            if close:
                matches.append(QueryMatch(r["id"], 0.25 * max(confidence, 0.1), f"close to '{close[0]}'"))
    return sorted(matches, key=lambda m: -m.score)


def query(records: Sequence[dict], text: str, graph: dict[str, Any] | None = None) -> list[QueryMatch]:
    """Instances matching `text`: a noun phrase (`"chair"`, `"something to sit on"`), or a phrase, a relation
    and another phrase (`"sofa near the window"`, `"lamp on the table"`); ranked best first."""
    graph = graph or build_scene_graph(records)
    cleaned = " " + _clean(text) + " "
    for words in sorted(_RELATION_WORDS, key=len, reverse=True):
        marker = f" {words} "
        if marker in cleaned and not cleaned.strip().startswith("something to sit on"):
            target_text, anchor_text = cleaned.split(marker, 1)
            if not target_text.strip() or not anchor_text.strip():
                continue
            relation = _RELATION_WORDS[words]
            anchors = {m.instance_id: m.score for m in match_phrase(records, anchor_text)}
            if anchor_text.strip() == "floor":
                anchors[FLOOR_NODE] = 1.0  # type: ignore[index]
            related: dict[Any, tuple[float, str]] = {}
            for edge in graph["edges"]:
                if edge["relation"] == relation and edge["target"] in anchors:
                    score = edge["score"] * anchors[edge["target"]]
                    if score > related.get(edge["source"], (0.0, ""))[0]:
                        related[edge["source"]] = (score, f"{relation} {edge['target']}")
            results = []
            for m in match_phrase(records, target_text):
                if m.instance_id in related:
                    score, why = related[m.instance_id]
                    results.append(QueryMatch(m.instance_id, m.score * score, f"{m.why}, {why}"))
            return sorted(results, key=lambda m: -m.score)
    return match_phrase(records, text)
