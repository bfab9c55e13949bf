"""Placement of the objects of a procedural room without overlap: on the floor, against a wall, on walls and
on top of tables, desks, counters and cabinets, away from the camera path (`procedural.generate_scene`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from fmfusion_jax.simulation.furniture import (
    _GENERATORS,
    _KIND_WEIGHTS,
    _PLACEMENT_ORDER,
    _WALL_GENERATORS,
    OBJECT_KINDS,
    _small_object,
    _Spec,
)

#: Camera path: margin from the walls and lowest camera height; objects taller than `_TALL` keep off the path.
_PATH_MARGIN = 1.2


_CAMERA_MIN_HEIGHT = 1.3


_TALL = 1.05


_PATH_CLEARANCE = 0.35


@dataclasses.dataclass
class _Placed:
    kind: str
    center: np.ndarray  # (2,) footprint centre
    yaw: float
    half: np.ndarray  # (2,) footprint half sizes (local x, y)
    z: tuple[float, float]
    wall: int  # -1 for free objects
    along: float  # position along the wall
    spec: _Spec | None
    reserved: bool = False  # a keep-clear zone, not an object
    support: int = -1  # index in the placed list of the object it stands on (-1: the floor or a wall)


def _rect_corners(center, yaw, half) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    axes = np.array([[c, s], [-s, c]])
    signs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64)
    return center + (signs * half) @ axes


def _rects_overlap(a: _Placed, b: _Placed, gap: float) -> bool:
    """Separating-axis test of two oriented rectangles grown by `gap / 2` each."""
    ca = _rect_corners(a.center, a.yaw, a.half + gap / 2)
    cb = _rect_corners(b.center, b.yaw, b.half + gap / 2)
    for yaw in (a.yaw, b.yaw):
        for axis in (np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])):
            pa, pb = ca @ axis, cb @ axis
            if pa.max() <= pb.min() or pb.max() <= pa.min():
                return False
    return True


def _path_points(room_size, count: int = 256) -> np.ndarray:
    w, d, _ = room_size
    a, b = _path_axes(room_size)
    theta = np.linspace(0, 2 * np.pi, count, endpoint=False)
    return np.stack([w / 2 + a * np.cos(theta), d / 2 + b * np.sin(theta)], axis=1)


def _path_axes(room_size) -> tuple[float, float]:
    w, d, _ = room_size
    margin = min(_PATH_MARGIN, 0.3 * min(w, d))
    return max(0.25, w / 2 - margin), max(0.25, d / 2 - margin)


def _rect_distance(points: np.ndarray, placed: _Placed) -> np.ndarray:
    c, s = math.cos(placed.yaw), math.sin(placed.yaw)
    rel = points - placed.center
    local = np.stack([rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c], axis=1)
    return np.linalg.norm(np.maximum(np.abs(local) - placed.half, 0.0), axis=1)


class _Layout:
    """Free-space bookkeeping of one placement attempt."""

    def __init__(self, room_size, rng) -> None:
        self.room_size = room_size
        self.rng = rng
        self.placed: list[_Placed] = []
        self.path = _path_points(room_size)

    def wall_length(self, wall: int) -> float:
        w, d, _ = self.room_size
        return d if wall < 2 else w

    def wall_pose(self, wall: int, along: float, offset: float) -> tuple[np.ndarray, float]:
        """Footprint centre and yaw of an object whose local +y points into `wall`, its centre `offset` from it."""
        w, d, _ = self.room_size
        if wall == 0:
            return np.array([offset, along]), math.pi / 2
        if wall == 1:
            return np.array([w - offset, along]), -math.pi / 2
        if wall == 2:
            return np.array([along, offset]), math.pi
        return np.array([along, d - offset]), 0.0

    def fits(self, cand: _Placed) -> bool:
        w, d, h = self.room_size
        corners = _rect_corners(cand.center, cand.yaw, cand.half)
        slack = 0.0 if cand.wall < 0 else 0.08  # wall-mounted things reach into their wall
        if (corners.min(axis=0) < -slack).any() or corners[:, 0].max() > w + slack or corners[:, 1].max() > d + slack:
            return False
        if cand.z[1] > h + 1e-6:
            return False
        if cand.wall >= 0:  # stay clear of the corners along the wall
            if cand.along - cand.half[0] < 0.05 or cand.along + cand.half[0] > self.wall_length(cand.wall) - 0.05:
                return False
        if cand.z[1] > _TALL and _rect_distance(self.path, cand).min() < _PATH_CLEARANCE:
            return False
        for other in self.placed:
            if cand.z[0] >= other.z[1] or other.z[0] >= cand.z[1]:
                continue
            mounted = cand.wall >= 0 and cand.spec is not None and cand.spec.placement == "mounted"
            gap = 0.02 if mounted or other.reserved else 0.05
            if _rects_overlap(cand, other, gap):
                return False
        return True

    def candidate(self, spec: _Spec, anchor: _Placed | None = None) -> _Placed:
        lower, upper = spec.bounds
        half = np.array([max(abs(lower[0]), abs(upper[0])), max(abs(lower[1]), abs(upper[1]))])
        z = (float(lower[2]), float(upper[2]))
        rng = self.rng
        if spec.placement == "free":
            if anchor is not None:  # a chair at a table or a desk, facing it
                sides = [(0, -1)] if anchor.kind == "desk" else [(0, -1), (0, 1), (-1, 0), (1, 0)]
                sx, sy = sides[rng.integers(len(sides))]
                c, s = math.cos(anchor.yaw), math.sin(anchor.yaw)
                normal = np.array([c * sx - s * sy, s * sx + c * sy])
                tangent = np.array([-normal[1], normal[0]])
                reach = anchor.half[0] if sx else anchor.half[1]
                side_half = anchor.half[1] if sx else anchor.half[0]
                slide = rng.uniform(-1, 1) * max(0.0, side_half - half[0])
                center = anchor.center + normal * (reach + 0.06 + half[1]) + tangent * slide
                yaw = math.atan2(-normal[0], normal[1]) + rng.normal(0, 0.12)
                return _Placed(spec.kind, center, yaw, half, z, -1, 0.0, spec)
            w, d, _ = self.room_size
            margin = 0.15 + half.max()
            center = np.array(
                [rng.uniform(min(margin, w / 2), max(w - margin, w / 2)), rng.uniform(min(margin, d / 2), max(d - margin, d / 2))]
            )
            if spec.kind == "chair":
                yaw = rng.uniform(-math.pi, math.pi)
            else:
                yaw = rng.integers(4) * math.pi / 2 + rng.normal(0, 0.15)
            return _Placed(spec.kind, center, yaw, half, z, -1, 0.0, spec)
        if anchor is not None:  # a curtain beside a window
            wall = anchor.wall
            along = anchor.along + rng.choice([-1, 1]) * (anchor.half[0] - 0.05)
        else:
            wall = int(rng.integers(4))
            length = self.wall_length(wall)
            along = rng.uniform(half[0] + 0.05, max(half[0] + 0.05, length - half[0] - 0.05))
        # Local y of the spec: the back plane is at upper[1]; it must sit `wall_gap` in front of the wall.
        offset = spec.wall_gap + upper[1]
        center, yaw = self.wall_pose(wall, along, offset)
        return _Placed(spec.kind, center, yaw, half, z, wall, along, spec)

    def add(self, placed: _Placed) -> None:
        self.placed.append(placed)
        if placed.kind == "door":  # keep the way through the door clear
            zone_half = np.array([placed.half[0] + 0.1, 0.45])
            center, yaw = self.wall_pose(placed.wall, placed.along, 0.45)
            self.placed.append(
                _Placed("door zone", center, yaw, zone_half, (0.0, self.room_size[2]), -1, placed.along, None, reserved=True)
            )


def _draw_kinds(rng, num_objects: int, kinds: Sequence[str] | None) -> list[str]:
    if kinds is None:
        forced = ["door", "window"][:num_objects]
        pool = [k for k in OBJECT_KINDS if k not in forced]
    else:
        forced = []
        pool = list(dict.fromkeys(kinds))
    rest = num_objects - len(forced)
    first = list(rng.permutation(pool))[:rest]
    weights = np.array([_KIND_WEIGHTS[k] for k in pool], np.float64)
    extra = list(rng.choice(pool, size=max(0, rest - len(first)), p=weights / weights.sum())) if pool else []
    return forced + [str(k) for k in first + extra]


def _make_spec(kind: str, rng, height: float) -> _Spec:
    if kind in _WALL_GENERATORS:
        return _WALL_GENERATORS[kind](rng, height)
    return _GENERATORS[kind](rng)


def _place_objects(room_size, kinds: list[str], rng, allowed: Sequence[str] | None = None, max_tries: int = 60) -> list[_Placed]:
    layout = _Layout(room_size, rng)
    # First one of each kind (so that every kind gets its chance), then the repeats; in placement order.
    occurrence = [kinds[:i].count(kind) for i, kind in enumerate(kinds)]
    order = sorted(range(len(kinds)), key=lambda i: (min(occurrence[i], 1), _PLACEMENT_ORDER.index(kinds[i]), i))
    queue = [kinds[i] for i in order]
    failures = 0
    result: list[_Placed] = []
    while queue:
        kind = queue.pop(0)
        placed = None
        for attempt in range(max_tries):
            spec = _make_spec(kind, rng, room_size[2])
            anchor = None
            if kind == "chair" and attempt < max_tries // 2 and rng.random() < 0.75:
                tables = [p for p in result if p.kind in ("table", "desk")]
                anchor = tables[rng.integers(len(tables))] if tables else None
            elif kind == "curtain" and attempt < max_tries // 2:
                windows = [p for p in result if p.kind == "window"]
                anchor = windows[rng.integers(len(windows))] if windows else None
            cand = layout.candidate(spec, anchor)
            if layout.fits(cand):
                placed = cand
                break
        if placed is None:
            failures += 1
            if failures > 2 * len(kinds) + 5:
                raise _NoRoom(len(result))
            # Something else that may fit better: a small kind.
            small = [k for k in ("chair", "picture", "otherfurniture", "table") if allowed is None or k in allowed]
            queue.append(str(rng.choice(small or list(allowed or ()))))  # small holds them all when allowed is None
            continue
        layout.add(placed)
        result.append(placed)
    return result


#: Kinds whose flat top `generate_scene(stacked=...)` puts small objects on, and the highest top it uses (the
#: camera, at 1.3 m or more, must see onto it).
_SUPPORT_KINDS = ("table", "desk", "counter", "cabinet")


_MAX_SUPPORT_TOP = 1.0


def _top_rect(spec: _Spec) -> tuple[np.ndarray, np.ndarray, float]:
    """`(centre (2,), half size (2,), z)` of the highest part's top face, in the spec's local frame."""
    part = max(spec.parts, key=lambda q: q.center[2] + q.size[2] / 2)
    return np.asarray(part.center[:2], np.float64), np.asarray(part.size[:2], np.float64) / 2, part.center[2] + part.size[2] / 2


def _place_on_tops(placed: list[_Placed], count: int, rng, max_tries: int = 30) -> list[_Placed]:
    """Up to `count` small objects standing on the tops of the placed supports (round robin over them in a
    random order), each wholly on its support's top and clear of the others and of wall-mounted things."""
    supports = [
        i
        for i, q in enumerate(placed)
        if q.spec is not None and q.kind in _SUPPORT_KINDS and _top_rect(q.spec)[2] <= _MAX_SUPPORT_TOP
    ]
    result: list[_Placed] = []
    if not supports:
        return result
    order = [supports[k] for k in rng.permutation(len(supports))]
    for n in range(count):
        index = order[n % len(order)]
        support = placed[index]
        assert support.spec is not None
        center, half, top = _top_rect(support.spec)
        for _ in range(max_tries):
            spec = _small_object(rng)
            lower, upper = spec.bounds
            small_half = np.maximum(np.abs(lower[:2]), np.abs(upper[:2]))
            room = half - small_half - 0.03
            if (room < 0).any():
                continue
            local = center + rng.uniform(-room, room)
            c, s = math.cos(support.yaw), math.sin(support.yaw)
            world = support.center + np.array([c * local[0] - s * local[1], s * local[0] + c * local[1]])
            for part in spec.parts:  # on the top: shift up by its height
                part.center = (part.center[0], part.center[1], part.center[2] + top)
            cand = _Placed(spec.kind, world, support.yaw, small_half, (top, top + float(upper[2])), -1, 0.0, spec, support=index)
            clash = any(
                _rects_overlap(cand, other, 0.03) and cand.z[0] < other.z[1] and other.z[0] < cand.z[1]
                for other in placed + result
                if other is not support
            )
            if not clash:
                result.append(cand)
                break
    return result


class _NoRoom(Exception):
    def __init__(self, placed: int):
        super().__init__(placed)
        self.placed = placed
