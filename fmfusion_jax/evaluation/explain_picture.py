"""`explain.png`: a top-down picture of an error analysis (`explain.SceneExplanation`).

Two panels over the same view of the ground-truth mesh vertices (ceiling cut away, as in overview.png):
left, the objects coloured by status; right, the evaluated predictions coloured by kind over the
mesh, with the objects outlined. Numbers are the objects' benchmark ids (left) and the
predictions' rows (right), as in the tables of explain.md. cv2 and NumPy only.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from fmfusion_jax.evaluation.explain import GT_STATUSES, PREDICTION_KINDS, SceneExplanation, vertex_categories
from fmfusion_jax.io.benchmark_format import InstancePredictions
from fmfusion_jax.viz.overview import height_cut, mesh_spacing, point_spacing, put_fitted, scale_bar, view_rotation

#: RGB colours of the object statuses and prediction kinds.
STATUS_COLORS = {
    "found": (50, 170, 60),
    "wrong_class": (150, 70, 200),
    "low_iou": (245, 150, 30),
    "fragmented": (235, 210, 30),
    "missed": (220, 35, 35),
}
KIND_COLORS = {
    "true_positive": (50, 170, 60),
    "duplicate": (40, 120, 230),
    "wrong_class": (150, 70, 200),
    "smear": (230, 40, 130),
    "fragment": (235, 210, 30),
    "no_object": (120, 70, 30),
}
#: Which kind shows where predictions overlap: errors over true positives, smears and no_object on top.
KIND_DRAW_ORDER = ("true_positive", "fragment", "duplicate", "wrong_class", "no_object", "smear")
#: Greys of the mesh where no status / kind colour is drawn: wall, floor, void, instances (small ones too).
_GREY = {"wall": 205, "floor": 225, "void": 190, "object": 160}
_OUTLINE = (60, 60, 60)
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def render_explanation(
    explanation: SceneExplanation,
    gt_ids: np.ndarray,
    preds: InstancePredictions,
    vertices: np.ndarray,
    faces: np.ndarray | None = None,
    title: str | None = None,
    panel_width: int = 800,
) -> np.ndarray:
    """The picture, `(H, W, 3)` uint8 BGR.

    Args:
      explanation: made from `gt_ids` and `preds`.
      gt_ids: `(V,)` benchmark ids; preds: `(P, V)` masks (their instances, as `explain_scene` reads them);
        vertices: `(V, 3)` metres, z up.
      faces: `(F, 3)` mesh triangles, only to size the splats (nearest-neighbour spacing without them).
    """
    preds = preds.primary()
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    instance_ids, category = vertex_categories(gt_ids)
    n = len(instance_ids)
    object_of = {g.gt_id: g for g in explanation.ground_truth}
    # Per vertex: the object index (-1: none) and base grey.
    vertex_object = np.where(category < n, category, -1)
    counted = np.array([int(i) in object_of for i in instance_ids] + [False], bool)
    vertex_object[~counted[vertex_object]] = -1
    grey = np.select(
        [category == n, category == n + 1, category < n], [_GREY["wall"], _GREY["floor"], _GREY["object"]], _GREY["void"]
    )
    base = np.repeat(grey.astype(np.uint8)[:, None], 3, axis=1)

    left = base.copy()
    status_rgb = np.array(
        [STATUS_COLORS[object_of[int(i)].status] if int(i) in object_of else (0, 0, 0) for i in instance_ids] + [(0, 0, 0)],
        np.uint8,
    ).reshape(-1, 3)
    left[vertex_object >= 0] = status_rgb[vertex_object[vertex_object >= 0]]

    right = base.copy()
    drawn = np.full(len(vertices), -1, np.int64)  # rank in KIND_DRAW_ORDER of the kind shown per vertex
    for p in explanation.predictions:
        rank = KIND_DRAW_ORDER.index(p.kind)
        mask = preds.masks[p.index] & (drawn < rank)
        drawn[mask] = rank
    kind_rgb = np.array([KIND_COLORS[k] for k in KIND_DRAW_ORDER], np.uint8)
    right[drawn >= 0] = kind_rgb[drawn[drawn >= 0]]

    # One view for both panels; the ceiling is cut away.
    cut = height_cut(vertices[:, 2])
    visible = vertices[:, 2] <= cut
    rotation = view_rotation(vertices[visible, :2])
    xy = vertices[:, :2] @ rotation.T
    pad = 24
    if visible.any():
        lo, hi = np.percentile(xy[visible], 0.05, axis=0), np.percentile(xy[visible], 99.95, axis=0)
    else:
        lo, hi = np.zeros(2), np.ones(2)
    extent = np.maximum(hi - lo, 0.5)
    scale = (panel_width - 2 * pad) / extent[0]
    height = min(int(np.ceil(extent[1] * scale)) + 2 * pad, 2 * panel_width)
    u = np.round((xy[:, 0] - lo[0]) * scale + pad).astype(np.int64)
    v = np.round((hi[1] - xy[:, 1]) * scale + pad).astype(np.int64)
    spacing = mesh_spacing(vertices, faces) if faces is not None else point_spacing(vertices, 0.01)
    radius = int(max(2, min(6, round(0.8 * spacing * scale))))  # no holes between the vertices

    shape = (height, panel_width)
    idx = np.flatnonzero(visible)
    # Left: the top surface wins. Right: predicted vertices win over the mesh (drawn over the left's
    # winners), so that what lies under a table top, a smear on the floor, still shows.
    left_winner = _winners(shape, u[idx], v[idx], vertices[idx, 2], radius, idx)
    idx = np.flatnonzero(visible & (drawn >= 0))
    predicted = _winners(shape, u[idx], v[idx], vertices[idx, 2], radius, idx)
    right_winner = np.where(predicted >= 0, predicted, left_winner)

    outline = _outlines(np.where(left_winner >= 0, vertex_object[np.maximum(left_winner, 0)], -1))
    panels = []
    for colors, winner, labels in (
        (left, left_winner, _object_labels(explanation, instance_ids, vertex_object, u, v)),
        (right, right_winner, _prediction_labels(explanation, preds, u, v, visible)),
    ):
        image = np.full((height, panel_width, 3), 238, np.uint8)
        image[winner >= 0] = colors[winner[winner >= 0]]
        image[outline] = _OUTLINE
        image = np.ascontiguousarray(image[..., ::-1])
        for text, (x, y), rgb in labels:
            _label(image, text, x, y, rgb)
        panels.append(image)

    status_counts, kind_counts = explanation.status_counts(), explanation.kind_counts()
    legends = [
        [(f"{s} {status_counts[s]}", STATUS_COLORS[s]) for s in GT_STATUSES],
        [(f"{k} {kind_counts[k]}", KIND_COLORS[k]) for k in PREDICTION_KINDS],
    ]
    captions = [
        f"objects by status ({len(explanation.ground_truth)})",
        f"predictions by kind ({len(explanation.predictions)}), objects outlined",
    ]
    return _compose(panels, captions, legends, title or f"{explanation.scene_name}: error analysis", scale)


def write_explanation_picture(
    path: str | Path,
    explanation: SceneExplanation,
    gt_ids: np.ndarray,
    preds: InstancePredictions,
    vertices: np.ndarray,
    faces: np.ndarray | None = None,
    title: str | None = None,
) -> Path:
    """Renders (`render_explanation`) and writes the PNG; returns its path."""
    path = Path(path)
    if not cv2.imwrite(str(path), render_explanation(explanation, gt_ids, preds, vertices, faces, title)):
        raise OSError(f"cannot write {path}")
    return path


def _winners(shape: tuple[int, int], u: np.ndarray, v: np.ndarray, z: np.ndarray, radius: int, index: np.ndarray) -> np.ndarray:
    """`(H, W)` int64 `index` of the point drawn at each pixel, -1 where none: points are discs of
    `radius` pixels, the highest (largest `z`) wins.

    Args:
      u, v: `(N,)` int pixel column and row; z: `(N,)` heights; index: `(N,)` what to report per point.
    """
    height, width = shape
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u, v, z, index = u[inside], v[inside], z[inside], index[inside]
    # The highest point of each pixel (the later one on equal heights) ...
    pixel = v * width + u
    order = np.lexsort((z, pixel))
    top = order[np.append(pixel[order][1:] != pixel[order][:-1], True)] if len(order) else order
    # ... ranked by height (1 = lowest), so that a max filter (cv2.dilate with a disc) spreads each over
    # its disc with the highest winning; the rank then names the point.
    by_height = top[np.argsort(z[top], kind="stable")]
    ranks = np.zeros(height * width, np.float32)  # exact integers up to 2**24 points
    ranks[pixel[by_height]] = np.arange(1, len(by_height) + 1)
    dy, dx = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    disc = (dx * dx + dy * dy <= radius * radius + radius).astype(np.uint8)
    spread = cv2.dilate(ranks.reshape(shape), disc).astype(np.int64)
    return np.concatenate([[-1], index[by_height]])[spread]


def _outlines(labels: np.ndarray) -> np.ndarray:
    """`(H, W)` bool: pixels of a labelled region (label >= 0 in the `(H, W)` labels) next to another label."""
    border = np.zeros(labels.shape, bool)
    rows = labels[1:] != labels[:-1]
    border[1:] |= rows & (labels[1:] >= 0)
    border[:-1] |= rows & (labels[:-1] >= 0)
    columns = labels[:, 1:] != labels[:, :-1]
    border[:, 1:] |= columns & (labels[:, 1:] >= 0)
    border[:, :-1] |= columns & (labels[:, :-1] >= 0)
    return border


def _object_labels(
    explanation: SceneExplanation, instance_ids: np.ndarray, vertex_object: np.ndarray, u: np.ndarray, v: np.ndarray
) -> list[tuple[str, tuple[int, int], tuple[int, int, int]]]:
    """Each object's id at the pixel mean of its vertices."""
    position = {int(i): k for k, i in enumerate(instance_ids)}
    labels = []
    for g in explanation.ground_truth:
        on = vertex_object == position[g.gt_id]
        if on.any():
            labels.append((str(g.gt_id), (int(u[on].mean()), int(v[on].mean())), STATUS_COLORS[g.status]))
    return labels


def _prediction_labels(
    explanation: SceneExplanation, preds: InstancePredictions, u: np.ndarray, v: np.ndarray, visible: np.ndarray
) -> list[tuple[str, tuple[int, int], tuple[int, int, int]]]:
    """Each prediction's row at the pixel mean of its visible vertices (true positives not labelled: the
    left panel names their objects)."""
    labels = []
    for p in explanation.predictions:
        on = preds.masks[p.index] & visible
        if p.kind != "true_positive" and on.any():
            labels.append((str(p.index), (int(u[on].mean()), int(v[on].mean())), KIND_COLORS[p.kind]))
    return labels


def _label(image: np.ndarray, text: str, x: int, y: int, rgb: tuple[int, int, int]) -> None:
    """A small number centred at (x, y): dark text on a white box edged in the status / kind colour."""
    (w, h), _ = cv2.getTextSize(text, _FONT, 0.4, 1)
    x0, y0 = x - w // 2 - 2, y - h // 2 - 2
    cv2.rectangle(image, (x0, y0), (x0 + w + 3, y0 + h + 4), (255, 255, 255), -1)
    cv2.rectangle(image, (x0, y0), (x0 + w + 3, y0 + h + 4), tuple(int(c) for c in rgb[::-1]), 1)
    cv2.putText(image, text, (x0 + 2, y0 + h + 1), _FONT, 0.4, (20, 20, 20), 1, cv2.LINE_AA)


def _compose(
    panels: list[np.ndarray], captions: list[str], legends: list[list[tuple[str, tuple]]], title: str, scale: float
) -> np.ndarray:
    """Title, the panels side by side with their captions, and each panel's legend under it."""
    margin, gap, title_h, caption_h, legend_row = 12, 16, 44, 30, 24
    panel_h, panel_w = panels[0].shape[:2]
    per_row = max(1, panel_w // 200)
    legend_h = 12 + max(-(-len(items) // per_row) for items in legends) * legend_row
    width = 2 * margin + len(panels) * panel_w + (len(panels) - 1) * gap
    canvas = np.full((title_h + caption_h + panel_h + legend_h + margin, width, 3), 255, np.uint8)
    put_fitted(canvas, title, (margin, 30), width - 2 * margin, 0.75, 2)
    top = title_h + caption_h
    for k, (panel, caption, items) in enumerate(zip(panels, captions, legends)):
        x = margin + k * (panel_w + gap)
        put_fitted(canvas, caption, (x, title_h + 20), panel_w - 220, 0.6, 1)
        scale_bar(canvas, x + panel_w - 2, title_h + 20, scale)
        canvas[top : top + panel_h, x : x + panel_w] = panel
        cv2.rectangle(canvas, (x, top), (x + panel_w - 1, top + panel_h - 1), (160, 160, 160), 1)
        for j, (text, rgb) in enumerate(items):
            row, col = divmod(j, per_row)
            lx, ly = x + col * 200, top + panel_h + 12 + row * legend_row
            cv2.rectangle(canvas, (lx, ly), (lx + 16, ly + 16), tuple(int(c) for c in rgb[::-1]), -1)
            cv2.rectangle(canvas, (lx, ly), (lx + 16, ly + 16), (80, 80, 80), 1)
            put_fitted(canvas, text, (lx + 24, ly + 13), 170, 0.5, 1)
    return canvas
