"""`overview.png`: a top-down picture of a map's instances by class beside the ground truth (a small
z-buffered rasterizer of points and coarse triangles, in NumPy and OpenCV).

It takes plain arrays and `MapInstance`s; the error-analysis picture (`evaluation.explain_picture`) reuses
its view, scale bar and text helpers.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from fmfusion_jax.instances import MapInstance
from fmfusion_jax.labels import LabelSets

#: Share of a wall's or the floor's class colour kept in the overview (the rest is the grey of the mesh):
#: they cover most of the picture and are not benchmark classes, so they stay in the background.
STRUCTURE_COLOR_SHARE = 0.45
#: Added to the height of instance points in the z-buffer, so that they cover mesh vertices at their place.
INSTANCE_Z_BIAS = 0.05
_BACKGROUND = 255
_PANEL_BACKGROUND = 238
_FONT = cv2.FONT_HERSHEY_SIMPLEX


@dataclasses.dataclass
class OverviewLayer:
    """Points drawn in one panel of the overview: world positions, RGB colours and their spacing (m)."""

    points: np.ndarray  # (N, 3) world metres, z up
    colors: np.ndarray  # (N, 3) uint8 RGB
    spacing: float  # typical distance between neighbouring points (sets the splat size)
    z_bias: float = 0.0  # added to z for the z-buffer only
    faces: np.ndarray | None = None  # (F, 3) triangles over `points`: filled in where they are coarse


@dataclasses.dataclass
class OverviewPanel:
    caption: str
    layers: list[OverviewLayer]
    class_counts: dict[int, int]  # closed-class index -> instances of that class in the panel


def grey_from_colors(colors: np.ndarray | None, count: int) -> np.ndarray:
    """`(N, 3)` uint8 greys: the colours' luminance compressed into a light band (flat grey without colours)."""
    if colors is None or len(colors) != count:
        return np.full((count, 3), 175, np.uint8)
    c = np.asarray(colors, np.float32)[:, :3]
    luminance = 0.299 * c[:, 0] + 0.587 * c[:, 1] + 0.114 * c[:, 2]
    return np.repeat((110 + 0.42 * luminance).astype(np.uint8)[:, None], 3, axis=1)


def overview_class_colors(label_sets: LabelSets) -> np.ndarray:
    """`(C, 3)` uint8 RGB colour of each class in the overview: NYU40 colours, walls and floor muted."""
    colors = label_sets.class_colors.astype(np.float32).copy()
    for name in ("wall", "floor"):
        k = label_sets.class_index(name)
        colors[k] = STRUCTURE_COLOR_SHARE * colors[k] + (1 - STRUCTURE_COLOR_SHARE) * 180
    return colors.astype(np.uint8)


def mesh_spacing(vertices: np.ndarray, faces: np.ndarray | None, default: float = 0.02) -> float:
    """Median edge length of a triangle mesh (a sample of faces); `default` without faces."""
    if faces is None or len(faces) == 0 or len(vertices) == 0:
        return default
    faces = np.asarray(faces)[:: max(1, len(faces) // 20000)]
    edges = np.linalg.norm(vertices[faces[:, 0]] - vertices[faces[:, 1]], axis=1)
    return float(np.median(edges)) if len(edges) else default


def point_spacing(points: np.ndarray, default: float, max_tree_points: int = 200_000) -> float:
    """Median distance from a point to its nearest neighbour (on a sample; at least `default`, e.g. the
    voxel size): instance points taken from few pixels are sparse and are drawn with bigger splats."""

    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) < 2:
        return default
    step = max(1, -(-len(points) // max_tree_points))
    tree_points = points[::step]
    if len(tree_points) < 2:
        return default
    queries = tree_points[:: max(1, len(tree_points) // 5000)]
    # distances alone are read: exact whatever the tree's shape, so the quicker unbalanced tree
    distances, _ = cKDTree(tree_points, balanced_tree=False, compact_nodes=False).query(queries, k=2)
    # a surface sampled every `step`-th point is sqrt(step) times sparser
    return max(default, float(np.median(distances[:, 1])) / np.sqrt(step))


def map_overview_panel(
    instances: list[MapInstance],
    label_sets: LabelSets,
    surface_points: np.ndarray,
    surface_colors: np.ndarray | None,
    surface_faces: np.ndarray | None,
    voxel_size: float,
    caption: str = "fused map",
) -> OverviewPanel:
    """The fused map's panel: the global surface in grey under the instance points coloured by class.

    The surface is the global mesh (`surface_faces` its triangles) or its voxels (`surface_faces` None:
    `engine.extraction.extract_surface_voxels`, drawn as splats one voxel wide)."""
    palette = overview_class_colors(label_sets)
    surface_points = np.asarray(surface_points, np.float32).reshape(-1, 3)
    layers = [
        OverviewLayer(
            surface_points,
            grey_from_colors(surface_colors, len(surface_points)),
            mesh_spacing(surface_points, surface_faces, voxel_size),
            faces=surface_faces,
        )
    ]
    counts: dict[int, int] = {}
    structure = {label_sets.class_index("wall"), label_sets.class_index("floor")}
    # Walls and floor first, objects after them: a voxel held by two instances shows the object.
    for group in ([i for i in instances if i.class_index in structure], [i for i in instances if i.class_index not in structure]):
        if group:
            points = np.concatenate([inst.points for inst in group]).astype(np.float32)
            colors = np.concatenate([np.repeat(palette[inst.class_index][None], len(inst.points), 0) for inst in group])
            layers.append(OverviewLayer(points, colors, point_spacing(points, voxel_size), INSTANCE_Z_BIAS))
    for inst in instances:
        counts[inst.class_index] = counts.get(inst.class_index, 0) + 1
    return OverviewPanel(caption, layers, counts)


def ground_truth_overview_panel(
    vertices: np.ndarray,
    faces: np.ndarray | None,
    vertex_colors: np.ndarray | None,
    nyu40_ids: np.ndarray,
    instance_ids: np.ndarray,
    label_sets: LabelSets,
    caption: str = "ground truth",
) -> OverviewPanel:
    """The ground-truth mesh with its vertices coloured by the class of their instance (others grey).

    Ceiling vertices (nyu40 22) are left out so that the room can be seen from above.
    """
    vertices = np.asarray(vertices, np.float32).reshape(-1, 3)
    nyu40_ids = np.asarray(nyu40_ids)
    instance_ids = np.asarray(instance_ids)
    to_class = label_sets.nyu40_to_class_index()
    lookup = np.full(max(int(nyu40_ids.max(initial=0)), max(to_class)) + 1, -1, np.int64)
    for nyu40, k in to_class.items():
        lookup[nyu40] = k
    classes = np.where((instance_ids > 0) & (nyu40_ids >= 0), lookup[np.clip(nyu40_ids, 0, None)], -1)
    colors = grey_from_colors(vertex_colors, len(vertices))
    labelled = classes >= 0
    colors[labelled] = overview_class_colors(label_sets)[classes[labelled]]
    keep = nyu40_ids != 22
    spacing = mesh_spacing(vertices, faces)
    counts: dict[int, int] = {}
    for k in np.unique(classes[labelled]):
        counts[int(k)] = int(len(np.unique(instance_ids[classes == k])))
    vertices, colors, faces = _subset_mesh(vertices, colors, faces, keep)
    return OverviewPanel(caption, [OverviewLayer(vertices, colors, spacing, faces=faces)], counts)


def _subset_mesh(vertices: np.ndarray, colors: np.ndarray, faces: np.ndarray | None, keep: np.ndarray):
    """The vertices in `keep`, and the faces whose three corners are kept (renumbered)."""
    if faces is not None and len(faces):
        faces = np.asarray(faces, np.int64)
        faces = faces[keep[faces].all(axis=1)]
        renumber = np.cumsum(keep) - 1
        faces = renumber[faces]
    return vertices[keep], colors[keep], faces


def view_rotation(points_xy: np.ndarray) -> np.ndarray:
    """2x2 rotation that puts the walls of the room along the image axes, the long side horizontal."""
    if len(points_xy) < 3:
        return np.eye(2)
    sample = points_xy[:: max(1, len(points_xy) // 50000)].astype(np.float32)
    angle = cv2.minAreaRect(sample)[2]
    theta = -np.radians(angle)

    def rotation(a: float) -> np.ndarray:
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])

    extent = np.ptp(sample @ rotation(theta).T, axis=0)
    if extent[1] > extent[0]:
        theta += np.pi / 2
    # Snap to the world axes when the room is (almost) aligned with them already.
    quarter = round(theta / (np.pi / 2))
    if abs(theta - quarter * np.pi / 2) < np.radians(2):
        return np.round(rotation(quarter * np.pi / 2))
    return rotation(theta)


def view_columns(points: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The view's two float64 coordinates of `points (N, >=2)` (x, y used) under the 2x2 `rotation`: the product
    `points[:, :2] @ rotation.T` written out per column (a strided `(N, 2)` product is ~3x slower in NumPy)."""
    x, y = points[:, 0].astype(np.float64), points[:, 1].astype(np.float64)
    return x * rotation[0, 0] + y * rotation[0, 1], x * rotation[1, 0] + y * rotation[1, 1]


def height_cut(z: np.ndarray) -> float:
    """Height above which points are dropped (the ceiling, so that the room is seen from above)."""
    if len(z) == 0:
        return np.inf
    floor, top = np.percentile(z, [2, 99.9])
    return float(floor + np.clip(top - floor - 0.25, 2.0, 2.3))


def _top_points(idx: np.ndarray, z: np.ndarray, z0: float | None = None) -> np.ndarray:
    """Indices of the highest entry (largest `z`, to the millimetre above `z0`, default `z.min()`; the later of
    equals) for each distinct non-negative `idx`, in increasing `idx` order."""
    n = len(z)
    if n == 0:
        return np.zeros(0, np.int64)
    millimetres = np.subtract(z, z.min() if z0 is None else z0, dtype=np.float64)  # in place from here: a room's
    millimetres *= 1000  # splats are millions, and each temporary of them tens of MiB at the outputs' peak
    zq = np.round(millimetres, out=millimetres).astype(np.int64)
    del millimetres
    bits = [max(1, int(x).bit_length()) for x in (zq.max(), n)]
    span = int(idx.max()) + 1
    if sum(bits) <= 63 and span <= 16 * n + (1 << 20):
        # One scatter-max of unique keys (height, position) per index: ~6x faster than sorting the points.
        best = np.full(span, -1, np.int64)
        zq <<= bits[1]
        zq |= np.arange(n, dtype=np.int64)
        np.maximum.at(best, idx, zq)
        return best[best >= 0] & ((1 << bits[1]) - 1)
    by_height = np.lexsort((np.arange(n), zq))
    order = by_height[np.argsort(idx[by_height], kind="stable")]
    last = np.ones(n, bool)
    last[:-1] = idx[order][1:] != idx[order][:-1]
    return order[last]


def disc_offsets(radius: int) -> np.ndarray:
    """`(K, 2)` int64 pixel offsets `(dx, dy)` of a splat of `radius` pixels (dx^2 + dy^2 <= r^2 + r: a 3x3 square
    at radius 1, a rounder disc above)."""
    r = radius
    return np.array([(dx, dy) for dx in range(-r, r + 1) for dy in range(-r, r + 1) if dx * dx + dy * dy <= r * r + r], np.int64)


def _rasterize(
    shape: tuple[int, int], u: np.ndarray, v: np.ndarray, z: np.ndarray, colors: np.ndarray, radii: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Splats points as discs of their radius (pixels, `disc_offsets`) with a z-buffer: the highest point wins a
    pixel (to the millimetre; of equals, the later point of the largest radius).

    Returns the `(H, W, 3)` uint8 image and the `(H, W)` bool coverage.
    """
    height, width = shape
    image = np.zeros((height * width, 3), np.uint8)
    covered = np.zeros(height * width, bool)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    if not inside.all():
        u, v, z, colors, radii = u[inside], v[inside], z[inside], colors[inside], radii[inside]
    del inside
    if len(u):
        # Only the highest point of each pixel can win anywhere its disc reaches (same radius per pixel); taken per
        # radius (pixel keys: an H*W scatter each, not 8*H*W), smallest radius first.
        if np.all(radii == radii[0]):  # one radius (the usual panel): no copies of the splats by group
            top = _top_points(v * width + u, z)
        else:
            low = z.min()
            groups = _radius_groups(radii)
            top = np.concatenate([group[_top_points(v[group] * width + u[group], z[group], low)] for group in groups])
        u, v, z, colors, radii = u[top], v[top], z[top], colors[top], radii[top]
        # Each kept point's key, (height in mm, its place in that order), is unique, and the z-buffer is the largest
        # key over the discs that cover a pixel: a grey dilation of the key image by the disc, per radius. The keys
        # are exact in float64 (OpenCV dilates float64 images) while they fit in 53 bits.
        mm = np.round((z - z.min()) * 1000).astype(np.int64)
        source_bits = max(1, (len(z) - 1).bit_length())
        if int(mm.max()).bit_length() + source_bits > 53:
            raise ValueError(f"overview: heights spread over {float(np.ptp(z)):.0f} m cannot be drawn")  # ~1000 km
        key = (mm << source_bits) | np.arange(len(z), dtype=np.int64)
        best = np.full((height, width), -1.0)
        for group in _radius_groups(radii):
            keys = np.full(height * width, -1.0)
            keys[v[group] * width + u[group]] = key[group]
            r = int(radii[group[0]])
            kernel = np.zeros((2 * r + 1, 2 * r + 1), np.uint8)
            offsets = disc_offsets(r)
            kernel[offsets[:, 1] + r, offsets[:, 0] + r] = 1
            reach = cv2.dilate(keys.reshape(height, width), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=-1.0)
            np.maximum(best, reach, out=best)
        best_key = best.reshape(-1).astype(np.int64)
        won = np.flatnonzero(best_key >= 0)
        image[won] = colors[best_key[won] & ((1 << source_bits) - 1)]
        covered[won] = True
    return image.reshape(height, width, 3), covered.reshape(height, width)


def _radius_groups(radii: np.ndarray) -> list[np.ndarray]:
    """Indices of the splats of each radius, smallest radius first, each in index order."""
    return [np.flatnonzero(radii == r) for r in np.unique(radii)]


def _densify(
    points: np.ndarray, colors: np.ndarray, faces: np.ndarray | None, pixel: float, max_points: int = 3_000_000
) -> tuple[np.ndarray, np.ndarray]:
    """Adds points inside the triangles whose top-down edges are longer than 2 pixels (`pixel` metres), about 2
    pixels apart, so that a coarse mesh draws as a surface: the discs splatted there (radius 1, 3x3 pixels) still
    meet after rounding, and a ScanNet room's ground truth takes 1.7 M points (2.7 M at 1.5 pixels: ~60 MiB more
    at the outputs' peak); each new point takes its nearest corner's colour."""
    if faces is None or len(faces) == 0:
        return points, colors
    faces = np.asarray(faces, np.int64)
    corners = points[faces]  # (F, 3, 3)
    # the longest top-down edge: squared lengths compared, one square root per face
    squared = [np.sum(np.square(corners[:, b, :2] - corners[:, a, :2]), axis=1) for a, b in ((0, 1), (1, 2), (2, 0))]
    edge = np.sqrt(np.maximum(np.maximum(squared[0], squared[1]), squared[2]))
    step = 2.0 * pixel
    for _ in range(8):  # coarser steps until the new points fit the budget
        steps = np.minimum(np.ceil(edge / step), 32).astype(np.int64)
        added = np.where(steps >= 2, (steps + 1) * (steps + 2) // 2 - 3, 0)
        if added.sum() <= max_points:
            break
        step *= 1.5
    big = np.flatnonzero(steps >= 2)
    if not len(big):
        return points, colors
    new_points, new_colors = [points], [colors]
    for n in np.unique(steps[big]):
        tris = big[steps[big] == n]
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        inner = (i + j <= n) & ~(((i == 0) | (i == n)) & ((j == 0) | (j == n)))  # all but the corners
        a, b = i[inner] / n, j[inner] / n
        weights = np.stack([1 - a - b, a, b], axis=1).astype(np.float32)  # (S, 3) barycentric
        new_points.append(np.einsum("sk,tkd->tsd", weights, corners[tris]).reshape(-1, 3))
        nearest = faces[tris][:, np.argmax(weights, axis=1)]  # (T, S) nearest corner of each new point
        new_colors.append(colors[nearest.reshape(-1)])
    return np.concatenate(new_points).astype(np.float32), np.concatenate(new_colors)


#: The overview's layout in pixels: outer margin, gap between panels, title and caption heights, pad in a panel.
_MARGIN, _GAP, _TITLE_H, _CAPTION_H, _PANEL_PAD = 12, 16, 44, 30, 10


@dataclasses.dataclass
class PanelImages:
    """The panels drawn (`rasterize_panels`): their BGR images, `(height, width, 3)` uint8 each, and the view's scale
    in pixels per metre (the scale bar's)."""

    images: list[np.ndarray]
    scale: float
    height: int
    width: int


def render_overview(panels: list[OverviewPanel], label_sets: LabelSets, title: str, panel_width: int = 800) -> np.ndarray:
    """The overview picture (`(H, W, 3)` uint8 BGR): title, panels side by side, legend of the classes.

    Every panel uses the same top-down orthographic view (rotated so that the room's walls are along the
    image axes), so the map and the ground truth can be compared place by place.
    """
    return compose_overview(panels, rasterize_panels(panels, panel_width), label_sets, title)


def rasterize_panels(panels: list[OverviewPanel], panel_width: int = 800) -> PanelImages:
    """Draws the panels in one top-down view (the long part of `render_overview`; the title is not needed yet)."""
    pad = _PANEL_PAD
    everything = [layer.points for panel in panels for layer in panel.layers if len(layer.points)]
    # the heights, then the kept points' two top-down columns, joined (not every point's three): the same values
    cut = height_cut(np.concatenate([p[:, 2] for p in everything]) if everything else np.zeros(0, np.float32))
    xy_all = np.concatenate([p[:, :2][p[:, 2] <= cut] for p in everything]) if everything else np.zeros((0, 2), np.float32)
    rotation = view_rotation(xy_all)
    if len(xy_all):
        columns = view_columns(xy_all, rotation)
        lo = np.array([np.percentile(c, 0.05) for c in columns])
        hi = np.array([np.percentile(c, 99.95) for c in columns])
        del columns
    else:
        lo, hi = np.zeros(2), np.ones(2)
    del everything, xy_all  # the view is fixed: these copies of every point go before the splats
    extent = np.maximum(hi - lo, 0.5)
    scale = (panel_width - 2 * pad) / extent[0]
    panel_height = min(int(np.ceil(extent[1] * scale)) + 2 * pad, 2 * panel_width)

    images = []
    for panel in panels:
        us, vs, zs, cs, rs = [], [], [], [], []
        for layer in panel.layers:
            pts, colors, spacing = layer.points, layer.colors, layer.spacing
            if layer.faces is not None and len(layer.faces):
                pts, colors = _densify(pts, colors, layer.faces, 1.0 / scale)
                spacing = min(spacing, 1.0 / scale)
            visible = pts[:, 2] <= cut
            pts, colors = pts[visible], colors[visible]
            if not len(pts):
                continue
            x, y = view_columns(pts, rotation)
            # int32 pixels and int8 radii (a panel is at most 1600 x 1600 pixels): the same picture in less memory
            us.append(np.round((x - lo[0]) * scale + pad).astype(np.int32))
            vs.append(np.round((hi[1] - y) * scale + pad).astype(np.int32))
            zs.append(pts[:, 2].astype(np.float64) + layer.z_bias)
            cs.append(colors)
            radius = int(max(1, min(6, round(0.6 * spacing * scale))))
            rs.append(np.full(len(pts), radius, np.int8))
            del pts, colors, x, y, visible
        drawn = bool(us)
        if drawn:
            splats = [np.concatenate(parts) for parts in (us, vs, zs, cs, rs)]
            us, vs, zs, cs, rs = [], [], [], [], []  # the layers' arrays go before the z-buffer's own
            image, covered = _rasterize((panel_height, panel_width), *splats)
            del splats
        else:
            image = np.zeros((panel_height, panel_width, 3), np.uint8)
            covered = np.zeros((panel_height, panel_width), bool)
        image[~covered] = _PANEL_BACKGROUND
        image = np.ascontiguousarray(image[..., ::-1])  # RGB -> BGR
        if not drawn:
            cv2.putText(image, "empty", (panel_width // 2 - 30, panel_height // 2), _FONT, 0.8, (90, 90, 90), 2, cv2.LINE_AA)
        images.append(image)
    return PanelImages(images, scale, panel_height, panel_width)


def compose_overview(panels: list[OverviewPanel], drawn: PanelImages, label_sets: LabelSets, title: str) -> np.ndarray:
    """The overview picture from the panels drawn by `rasterize_panels`: title, captions, scale bars, legend."""
    margin, gap, title_h, caption_h = _MARGIN, _GAP, _TITLE_H, _CAPTION_H
    images, scale, panel_height, panel_width = drawn.images, drawn.scale, drawn.height, drawn.width
    # Legend: every class in any panel, with its count per panel.
    present = sorted({k for panel in panels for k in panel.class_counts})
    palette = overview_class_colors(label_sets)
    column_w = 250
    columns = max(1, (len(panels) * (panel_width + gap) - gap) // column_w)
    rows = -(-len(present) // columns) if present else 1
    legend_h = 34 + rows * 24
    width = 2 * margin + len(panels) * panel_width + (len(panels) - 1) * gap
    height = title_h + caption_h + panel_height + legend_h + margin
    canvas = np.full((height, width, 3), _BACKGROUND, np.uint8)
    put_fitted(canvas, title, (margin, 30), width - 2 * margin, 0.75, 2)
    for i, (panel, image) in enumerate(zip(panels, images)):
        x = margin + i * (panel_width + gap)
        caption = f"{panel.caption}: {sum(panel.class_counts.values())} instances"
        put_fitted(canvas, caption, (x, title_h + 20), panel_width - 220, 0.6, 1)
        scale_bar(canvas, x + panel_width - 2, title_h + 20, scale)
        canvas[title_h + caption_h : title_h + caption_h + panel_height, x : x + panel_width] = image
        cv2.rectangle(
            canvas, (x, title_h + caption_h), (x + panel_width - 1, title_h + caption_h + panel_height - 1), (160, 160, 160), 1
        )
    y0 = title_h + caption_h + panel_height + 12
    heading = "classes (instances per panel: " + " / ".join(p.caption for p in panels) + ")"
    if not present:
        heading = "no instances"
    put_fitted(canvas, heading, (margin, y0 + 14), width - 2 * margin, 0.5, 1)
    for j, k in enumerate(present):
        row, col = divmod(j, columns)
        x, y = margin + col * column_w, y0 + 28 + row * 24
        color = tuple(int(c) for c in palette[k][::-1])
        cv2.rectangle(canvas, (x, y), (x + 16, y + 16), color, -1)
        cv2.rectangle(canvas, (x, y), (x + 16, y + 16), (80, 80, 80), 1)
        counts = " / ".join(str(p.class_counts.get(k, 0)) for p in panels)
        put_fitted(canvas, f"{label_sets.class_names[k]}  {counts}", (x + 24, y + 13), column_w - 30, 0.5, 1)
    return canvas


def put_fitted(image: np.ndarray, text: str, origin: tuple[int, int], max_width: int, scale: float, thickness: int) -> None:
    """`cv2.putText`, shrinking the font (down to half) or cutting the text so it fits `max_width`."""
    text = text.encode("ascii", "replace").decode("ascii")
    for _ in range(6):
        (w, _), _ = cv2.getTextSize(text, _FONT, scale, thickness)
        if w <= max_width:
            break
        scale *= 0.9
    while text and cv2.getTextSize(text, _FONT, scale, thickness)[0][0] > max_width:
        text = text[:-1]
    cv2.putText(image, text, origin, _FONT, scale, (30, 30, 30), thickness, cv2.LINE_AA)


def scale_bar(image: np.ndarray, right: int, baseline: int, scale: float) -> None:
    """A 1 m bar (0.5 m on small rooms' large scales) ending at x = `right`, on the caption's baseline."""
    metres = 1.0 if scale <= 250 else 0.5
    length = int(round(metres * scale))
    label = f"{metres:g} m"
    (text_w, _), _ = cv2.getTextSize(label, _FONT, 0.5, 1)
    x1 = right
    x0 = x1 - length
    cv2.line(image, (x0, baseline - 4), (x1, baseline - 4), (40, 40, 40), 2)
    for x in (x0, x1):
        cv2.line(image, (x, baseline - 9), (x, baseline + 1), (40, 40, 40), 2)
    cv2.putText(image, label, (x0 - text_w - 8, baseline), _FONT, 0.5, (40, 40, 40), 1, cv2.LINE_AA)


def write_overview(
    path: Path,
    panels: list[OverviewPanel],
    label_sets: LabelSets,
    title: str,
    panel_width: int = 800,
    drawn: PanelImages | None = None,
) -> np.ndarray:
    """Renders the overview (see `render_overview`; from `drawn`, the panels' `rasterize_panels`, when given) and
    writes it as PNG; returns the BGR image."""
    drawn = rasterize_panels(panels, panel_width) if drawn is None else drawn
    image = compose_overview(panels, drawn, label_sets, title)
    if not cv2.imwrite(str(path), image):
        raise OSError(f"cannot write {path}")
    return image
