"""The furniture of procedural rooms: the object kinds, their raw labels and frequencies, and one generator
per kind building an object from boxes in its local frame (`procedural.generate_scene` places them)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

#: Class of the ceiling: in the mesh and the instance images, but not one of the 20 classes.
CEILING_CLASS, CEILING_NYU40 = "ceiling", 22

#: Object kinds `generate_scene` knows (each is also the name of its closed class).
OBJECT_KINDS = (
    "door",
    "window",
    "bed",
    "chair",
    "sofa",
    "table",
    "desk",
    "cabinet",
    "bookshelf",
    "counter",
    "refrigerator",
    "toilet",
    "sink",
    "bathtub",
    "curtain",
    "picture",
    "otherfurniture",
)


#: Every raw label the generator uses -> its class (the labels tsv lists them all).
RAW_LABELS = {
    "wall": "wall",
    "floor": "floor",
    "ceiling": CEILING_CLASS,
    "door": "door",
    "window": "window",
    "bed": "bed",
    "chair": "chair",
    "office chair": "chair",
    "armchair": "chair",
    "couch": "sofa",
    "table": "table",
    "dining table": "table",
    "kitchen table": "table",
    "side table": "table",
    "end table": "table",
    "desk": "desk",
    "cabinet": "cabinet",
    "kitchen cabinet": "cabinet",
    "file cabinet": "cabinet",
    "bookshelf": "bookshelf",
    "counter": "counter",
    "kitchen counter": "counter",
    "refrigerator": "refrigerator",
    "mini fridge": "refrigerator",
    "toilet": "toilet",
    "sink": "sink",
    "bathroom sink": "sink",
    "bathtub": "bathtub",
    "curtain": "curtain",
    "picture": "picture",
    "trash can": "otherfurniture",
    "ottoman": "otherfurniture",
    "bench": "otherfurniture",
    # small things that `generate_scene(stacked=...)` puts on tables, desks, counters and cabinets (the
    # generator's own class for them: ScanNet's 20 classes have no lamp or box)
    "lamp": "otherfurniture",
    "storage box": "otherfurniture",
    "basket": "otherfurniture",
}


#: Relative frequency of a kind once every allowed kind has been placed once.
_KIND_WEIGHTS = {
    "chair": 6.0,
    "table": 2.0,
    "desk": 1.5,
    "cabinet": 2.0,
    "bookshelf": 1.2,
    "sofa": 1.0,
    "bed": 0.6,
    "counter": 0.6,
    "refrigerator": 0.4,
    "toilet": 0.4,
    "sink": 0.5,
    "bathtub": 0.3,
    "curtain": 1.0,
    "picture": 2.0,
    "otherfurniture": 1.5,
    "window": 0.8,
    "door": 0.3,
}


#: Placement order (big and anchoring things first; chairs after tables; curtains after windows).
_PLACEMENT_ORDER = (
    "door",
    "window",
    "bed",
    "bathtub",
    "counter",
    "sofa",
    "bookshelf",
    "refrigerator",
    "cabinet",
    "desk",
    "table",
    "toilet",
    "sink",
    "chair",
    "otherfurniture",
    "curtain",
    "picture",
)


#: Gap between furniture set against a wall and the wall (small: the hidden back faces are culled from the mesh).
_WALL_GAP = 0.003


@dataclasses.dataclass
class _Part:
    center: tuple[float, float, float]  # local frame: x across, y depth (+y = back), z up from the floor
    size: tuple[float, float, float]  # full sizes
    color: np.ndarray
    material: str
    name: str


@dataclasses.dataclass
class _Spec:
    """An object in its local frame before placement."""

    kind: str
    raw_label: str
    parts: list[_Part]
    placement: str  # "wall" (back against a wall, on the floor), "free" (anywhere on the floor), "mounted", "on" (a top)
    wall_gap: float = _WALL_GAP  # distance of the local back plane (y = +depth/2) in front of the wall

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        centers = np.array([p.center for p in self.parts])
        halves = np.array([p.size for p in self.parts]) / 2
        return (centers - halves).min(axis=0), (centers + halves).max(axis=0)

    def recentred(self) -> "_Spec":
        """The same object with its footprint centred on the local origin (x, y)."""
        lower, upper = self.bounds
        shift = np.array([(lower[0] + upper[0]) / 2, (lower[1] + upper[1]) / 2, 0.0])
        for part in self.parts:
            part.center = tuple(np.asarray(part.center) - shift)
        return self


def _jitter(rng: np.random.Generator, color, amount: float = 0.04) -> np.ndarray:
    return np.clip(np.asarray(color, np.float64) + rng.uniform(-amount, amount, 3), 0.02, 0.98)


_WOODS = [(0.55, 0.38, 0.22), (0.67, 0.50, 0.33), (0.42, 0.28, 0.17), (0.78, 0.64, 0.46), (0.36, 0.24, 0.15)]


_WHITE = (0.90, 0.90, 0.88)


def _wood(rng):
    return _jitter(rng, _WOODS[rng.integers(len(_WOODS))])


def _fabric(rng):
    hue = rng.uniform(0, 1)
    sat = rng.uniform(0.15, 0.6)
    val = rng.uniform(0.35, 0.8)
    return _hsv(hue, sat, val)


def _paint(rng):
    return _hsv(rng.uniform(0, 1), rng.uniform(0.0, 0.35), rng.uniform(0.6, 0.92))


def _hsv(h, s, v) -> np.ndarray:
    i = int(h * 6) % 6
    f = h * 6 - math.floor(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return np.array([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i])


def _legs(width, depth, height, leg, color, material, inset=0.0) -> list[_Part]:
    x = width / 2 - leg / 2 - inset
    y = depth / 2 - leg / 2 - inset
    return [_Part((sx * x, sy * y, height / 2), (leg, leg, height), color, material, "leg") for sx in (-1, 1) for sy in (-1, 1)]


def _chair(rng, label=None) -> _Spec:
    label = label or rng.choice(["chair", "chair", "office chair", "armchair"])
    w, d = rng.uniform(0.42, 0.5), rng.uniform(0.42, 0.5)
    seat_h, seat_t = rng.uniform(0.42, 0.48), 0.05
    back_h = rng.uniform(0.35, 0.5)
    frame = _wood(rng) if rng.random() < 0.6 else _jitter(rng, (0.2, 0.2, 0.22))
    seat = _fabric(rng) if rng.random() < 0.5 else frame
    parts = [
        _Part((0, 0, seat_h - seat_t / 2), (w, d, seat_t), seat, "fabric", "seat"),
        _Part((0, d / 2 - 0.02, seat_h + back_h / 2), (w, 0.04, back_h), seat, "fabric", "back"),
    ]
    if label == "office chair":
        metal = _jitter(rng, (0.25, 0.25, 0.27))
        parts += [
            _Part((0, 0, (seat_h - seat_t) / 2 + 0.05), (0.06, 0.06, seat_h - seat_t - 0.1), metal, "metal", "column"),
            _Part((0, 0, 0.025), (0.55, 0.06, 0.05), metal, "metal", "base"),
            _Part((0, 0, 0.025), (0.06, 0.55, 0.05), metal, "metal", "base"),
        ]
    elif label == "armchair":
        w += 0.2
        parts[0].size = (w - 0.2, d, seat_t + 0.1)
        parts[0].center = (0, 0, seat_h - (seat_t + 0.1) / 2)
        parts[1].size = (w, 0.08, back_h)
        parts[1].center = (0, d / 2 - 0.04, seat_h + back_h / 2)
        parts += [
            _Part((sx * (w / 2 - 0.05), 0, (seat_h + 0.2) / 2), (0.1, d, seat_h + 0.2), seat, "fabric", "arm") for sx in (-1, 1)
        ]
        parts += [_Part((0, 0, (seat_h - seat_t - 0.1) / 2), (w - 0.2, d, seat_h - seat_t - 0.1), seat, "fabric", "base")]
    else:
        parts += _legs(w, d, seat_h - seat_t, 0.04, frame, "wood")
    return _Spec("chair", label, parts, "free").recentred()


def _table(rng) -> _Spec:
    label = rng.choice(["table", "table", "dining table", "kitchen table", "side table", "end table"])
    if label in ("side table", "end table"):
        w, d, h = rng.uniform(0.4, 0.6), rng.uniform(0.4, 0.6), rng.uniform(0.5, 0.6)
    else:
        w, d, h = rng.uniform(0.9, 1.7), rng.uniform(0.65, 1.0), rng.uniform(0.72, 0.77)
    top_t = rng.uniform(0.03, 0.05)
    color = _wood(rng) if rng.random() < 0.75 else _jitter(rng, _WHITE)
    parts = [_Part((0, 0, h - top_t / 2), (w, d, top_t), color, "wood", "top")]
    parts += _legs(w, d, h - top_t, 0.05, color, "wood", inset=0.04)
    return _Spec("table", label, parts, "free")


def _desk(rng) -> _Spec:
    w, d, h = rng.uniform(1.1, 1.6), rng.uniform(0.6, 0.75), rng.uniform(0.73, 0.76)
    color = _wood(rng) if rng.random() < 0.6 else _jitter(rng, (0.85, 0.85, 0.83))
    top_t, side_t = 0.03, 0.025
    parts = [
        _Part((0, 0, h - top_t / 2), (w, d, top_t), color, "wood", "top"),
        _Part((-(w / 2 - side_t / 2), 0, (h - top_t) / 2), (side_t, d, h - top_t), color, "wood", "side"),
        _Part((0, d / 2 - 0.01, h - top_t - 0.2), (w - 2 * side_t, 0.02, 0.4), color, "wood", "modesty"),
    ]
    if rng.random() < 0.6:  # a drawer unit on the right
        dw = 0.4
        parts.append(_Part((w / 2 - dw / 2, 0.0, (h - top_t) / 2), (dw, d, h - top_t), color, "wood", "drawers"))
        parts += [
            _Part((w / 2 - dw / 2, -d / 2 - 0.01, z), (0.12, 0.02, 0.02), _jitter(rng, (0.3, 0.3, 0.3)), "metal", "handle")
            for z in (0.2, 0.45, 0.65)
        ]
    else:
        parts.append(_Part((w / 2 - side_t / 2, 0, (h - top_t) / 2), (side_t, d, h - top_t), color, "wood", "side"))
    return _Spec("desk", "desk", parts, "wall").recentred()


def _bed(rng) -> _Spec:
    w, length = rng.choice([rng.uniform(0.95, 1.1), rng.uniform(1.4, 1.8)]), rng.uniform(1.95, 2.1)
    frame = _wood(rng)
    sheet = _jitter(rng, _WHITE) if rng.random() < 0.5 else _fabric(rng)
    base_h, mat_h = rng.uniform(0.25, 0.32), rng.uniform(0.18, 0.24)
    head_h = rng.uniform(0.9, 1.05)
    parts = [
        _Part((0, 0, base_h / 2), (w, length, base_h), frame, "wood", "frame"),
        _Part((0, -0.02, base_h + mat_h / 2), (w - 0.06, length - 0.12, mat_h), sheet, "fabric", "mattress"),
        _Part((0, length / 2 + 0.03, head_h / 2), (w + 0.04, 0.06, head_h), frame, "wood", "headboard"),
    ]
    pillows = 1 if w < 1.2 else 2
    for k in range(pillows):
        x = 0 if pillows == 1 else (k - 0.5) * w / 2
        parts.append(
            _Part(
                (x, length / 2 - 0.3, base_h + mat_h + 0.06),
                (min(0.6, w / pillows - 0.1), 0.38, 0.12),
                _jitter(rng, _WHITE),
                "fabric",
                "pillow",
            )
        )
    return _Spec("bed", "bed", parts, "wall").recentred()


def _sofa(rng) -> _Spec:
    w, d = rng.uniform(1.6, 2.2), rng.uniform(0.85, 0.95)
    color = _fabric(rng)
    seat_h, back_h, arm_w, arm_h, back_t = 0.42, rng.uniform(0.78, 0.88), 0.16, 0.6, 0.2
    parts = [
        _Part((0, -back_t / 2, seat_h / 2), (w - 2 * arm_w, d - back_t, seat_h), color, "fabric", "seat"),
        _Part((0, d / 2 - back_t / 2, back_h / 2), (w, back_t, back_h), color, "fabric", "back"),
        _Part((-(w / 2 - arm_w / 2), -back_t / 2, arm_h / 2), (arm_w, d - back_t, arm_h), color, "fabric", "arm"),
        _Part((w / 2 - arm_w / 2, -back_t / 2, arm_h / 2), (arm_w, d - back_t, arm_h), color, "fabric", "arm"),
    ]
    return _Spec("sofa", "couch", parts, "wall")


def _cabinet(rng) -> _Spec:
    label = rng.choice(["cabinet", "kitchen cabinet", "file cabinet"])
    if label == "file cabinet":
        w, d, h = rng.uniform(0.4, 0.5), rng.uniform(0.55, 0.65), rng.uniform(0.7, 1.3)
    elif label == "kitchen cabinet":
        w, d, h = rng.uniform(0.8, 1.6), rng.uniform(0.55, 0.62), rng.uniform(0.85, 0.9)
    else:
        w, d, h = rng.uniform(0.6, 1.1), rng.uniform(0.42, 0.6), rng.choice([rng.uniform(0.8, 1.0), rng.uniform(1.7, 2.0)])
    body = _wood(rng) if rng.random() < 0.5 else _paint(rng)
    handle = _jitter(rng, (0.7, 0.7, 0.72))
    parts = [_Part((0, 0.008, h / 2), (w, d - 0.016, h), body, "wood", "body")]
    if label == "file cabinet":
        n = max(2, int(round(h / 0.33)))
        dh = h / n
        for k in range(n):
            z = (k + 0.5) * dh
            parts.append(_Part((0, -d / 2 + 0.008, z), (w - 0.03, 0.016, dh - 0.02), body, "wood", "drawer"))
            parts.append(_Part((0, -d / 2 - 0.01, z + dh * 0.25), (0.12, 0.02, 0.02), handle, "metal", "handle"))
    else:
        n = 1 if w < 0.55 else 2
        dw = w / n
        for k in range(n):
            x = -w / 2 + (k + 0.5) * dw
            parts.append(_Part((x, -d / 2 + 0.008, h / 2), (dw - 0.02, 0.016, h - 0.04), body, "wood", "door"))
            hx = x + (dw / 2 - 0.06) * (1 if k == 0 and n == 2 else -1 if n == 2 else 1)
            parts.append(
                _Part((hx, -d / 2 - 0.01, h * 0.55 if h > 1.2 else h * 0.75), (0.02, 0.02, 0.14), handle, "metal", "handle")
            )
    return _Spec("cabinet", label, parts, "wall").recentred()


def _bookshelf(rng) -> _Spec:
    w, d, h = rng.uniform(0.6, 1.2), rng.uniform(0.28, 0.4), rng.uniform(1.4, 2.0)
    color = _wood(rng) if rng.random() < 0.7 else _jitter(rng, _WHITE)
    t = 0.02
    parts = [
        _Part((-(w / 2 - t / 2), 0, h / 2), (t, d, h), color, "wood", "side"),
        _Part((w / 2 - t / 2, 0, h / 2), (t, d, h), color, "wood", "side"),
        _Part((0, d / 2 - 0.005, h / 2), (w - 2 * t, 0.01, h), color, "wood", "back"),
        _Part((0, 0, h - t / 2), (w - 2 * t, d - 0.01, t), color, "wood", "top"),
        _Part((0, 0, 0.04), (w - 2 * t, d - 0.01, 0.08), color, "wood", "bottom"),
    ]
    shelves = int(rng.integers(3, 6))
    gap = (h - 0.08 - t) / shelves
    for k in range(1, shelves):
        parts.append(_Part((0, -0.005, 0.08 + k * gap), (w - 2 * t, d - 0.02, t), color, "wood", "shelf"))
    for k in range(shelves):  # rows of books
        if rng.random() < 0.25:
            continue
        z0 = 0.08 + k * gap + (t / 2 if k else 0)
        bw = rng.uniform(0.25, 0.8) * (w - 2 * t)
        bh = min(gap - 0.04, rng.uniform(0.16, 0.3))
        x = -w / 2 + t + bw / 2 + rng.uniform(0, w - 2 * t - bw)
        parts.append(_Part((x, 0.0, z0 + bh / 2), (bw, d * 0.7, bh), _fabric(rng), "plain", "books"))
    return _Spec("bookshelf", "bookshelf", parts, "wall")


def _counter(rng) -> _Spec:
    label = rng.choice(["counter", "kitchen counter"])
    w, d, h = rng.uniform(1.2, 2.4), rng.uniform(0.58, 0.65), rng.uniform(0.88, 0.93)
    body, top = _paint(rng), _jitter(rng, rng.choice([(0.3, 0.3, 0.32), (0.85, 0.84, 0.8), (0.5, 0.45, 0.4)]))
    parts = [
        _Part((0, 0.02, (h - 0.04) / 2), (w, d - 0.04, h - 0.04), body, "paint", "body"),
        _Part((0, 0, h - 0.02), (w + 0.02, d, 0.04), top, "plain", "top"),
        _Part((0, -d / 2 + 0.035, 0.05), (w, 0.03, 0.1), _jitter(rng, (0.2, 0.2, 0.2)), "plain", "kick"),
    ]
    return _Spec("counter", label, parts, "wall").recentred()


def _refrigerator(rng) -> _Spec:
    label = "mini fridge" if rng.random() < 0.2 else "refrigerator"
    if label == "mini fridge":
        w, d, h = rng.uniform(0.45, 0.55), rng.uniform(0.5, 0.6), rng.uniform(0.8, 0.9)
    else:
        w, d, h = rng.uniform(0.6, 0.8), rng.uniform(0.65, 0.75), rng.uniform(1.65, 1.9)
    color = _jitter(rng, rng.choice([_WHITE, (0.75, 0.76, 0.78), (0.2, 0.2, 0.22)]), 0.02)
    parts = [_Part((0, 0.02, h / 2), (w, d - 0.04, h), color, "metal", "body")]
    split = h * 0.65 if h > 1.2 else h
    parts.append(_Part((0, -d / 2 + 0.02, split / 2), (w - 0.01, 0.04, split - 0.01), color, "metal", "door"))
    if split < h:
        parts.append(_Part((0, -d / 2 + 0.02, (split + h) / 2), (w - 0.01, 0.04, h - split - 0.01), color, "metal", "door"))
    handle = _jitter(rng, (0.6, 0.6, 0.62))
    parts.append(
        _Part((w / 2 - 0.06, -d / 2 - 0.02, split * 0.7), (0.025, 0.04, min(0.4, split * 0.5)), handle, "metal", "handle")
    )
    return _Spec("refrigerator", label, parts, "wall").recentred()


def _toilet(rng) -> _Spec:
    white = _jitter(rng, (0.94, 0.94, 0.93), 0.02)
    parts = [
        _Part((0, -0.05, 0.16), (0.24, 0.36, 0.32), white, "plain", "pedestal"),
        _Part((0, -0.1, 0.355), (0.38, 0.5, 0.07), white, "plain", "bowl"),
        _Part((0, -0.1, 0.4), (0.4, 0.46, 0.02), white, "plain", "seat"),
        _Part((0, 0.19, 0.6), (0.44, 0.18, 0.4), white, "plain", "tank"),
        _Part((0, 0.19, 0.81), (0.46, 0.2, 0.02), white, "plain", "lid"),
    ]
    return _Spec("toilet", "toilet", parts, "wall").recentred()


def _hollow(cx, cy, z0, w, d, h, t, color, material, name) -> list[_Part]:
    """An open-top box: bottom and four sides of thickness `t`."""
    return [
        _Part((cx, cy, z0 + t / 2), (w, d, t), color, material, name + " bottom"),
        _Part((cx - w / 2 + t / 2, cy, z0 + h / 2), (t, d, h), color, material, name + " side"),
        _Part((cx + w / 2 - t / 2, cy, z0 + h / 2), (t, d, h), color, material, name + " side"),
        _Part((cx, cy - d / 2 + t / 2, z0 + h / 2), (w - 2 * t, t, h), color, material, name + " side"),
        _Part((cx, cy + d / 2 - t / 2, z0 + h / 2), (w - 2 * t, t, h), color, material, name + " side"),
    ]


def _sink(rng) -> _Spec:
    label = rng.choice(["sink", "bathroom sink"])
    white = _jitter(rng, (0.93, 0.93, 0.92), 0.02)
    w, d, top = rng.uniform(0.5, 0.65), rng.uniform(0.4, 0.5), rng.uniform(0.82, 0.88)
    basin_h = 0.16
    parts = [_Part((0, 0.05, (top - basin_h) / 2), (0.18, 0.16, top - basin_h), white, "plain", "pedestal")]
    parts += _hollow(0, 0, top - basin_h, w, d, basin_h, 0.035, white, "plain", "basin")
    parts.append(_Part((0, d / 2 - 0.05, top + 0.08), (0.04, 0.04, 0.16), _jitter(rng, (0.7, 0.7, 0.72)), "metal", "faucet"))
    return _Spec("sink", label, parts, "wall").recentred()


def _bathtub(rng) -> _Spec:
    w, d, h = rng.uniform(1.5, 1.7), rng.uniform(0.7, 0.8), rng.uniform(0.5, 0.58)
    white = _jitter(rng, (0.95, 0.95, 0.94), 0.02)
    return _Spec("bathtub", "bathtub", _hollow(0, 0, 0, w, d, h, 0.07, white, "plain", "tub"), "wall")


def _otherfurniture(rng) -> _Spec:
    label = rng.choice(["trash can", "ottoman", "bench"])
    if label == "trash can":
        w = rng.uniform(0.25, 0.35)
        color = _jitter(rng, rng.choice([(0.3, 0.3, 0.32), (0.2, 0.4, 0.7), (0.8, 0.8, 0.8)]))
        return _Spec(
            "otherfurniture", label, _hollow(0, 0, 0, w, w, rng.uniform(0.35, 0.5), 0.012, color, "plain", "bin"), "free"
        )
    if label == "ottoman":
        w = rng.uniform(0.45, 0.6)
        return _Spec("otherfurniture", label, [_Part((0, 0, 0.21), (w, w, 0.42), _fabric(rng), "fabric", "body")], "free")
    w, d, h = rng.uniform(1.0, 1.5), rng.uniform(0.35, 0.45), rng.uniform(0.42, 0.47)
    color = _wood(rng)
    parts = [
        _Part((0, 0, h - 0.02), (w, d, 0.04), color, "wood", "seat"),
        _Part((-(w / 2 - 0.04), 0, (h - 0.04) / 2), (0.04, d, h - 0.04), color, "wood", "leg"),
        _Part((w / 2 - 0.04, 0, (h - 0.04) / 2), (0.04, d, h - 0.04), color, "wood", "leg"),
    ]
    return _Spec("otherfurniture", label, parts, "free")


def _small_object(rng) -> _Spec:
    """A lamp, a storage box or a basket, to stand on a table, desk, counter or cabinet (local z = 0 at its base)."""
    label = rng.choice(["lamp", "storage box", "basket"])
    if label == "lamp":
        base, h, shade = rng.uniform(0.14, 0.2), rng.uniform(0.38, 0.5), rng.uniform(0.24, 0.32)
        metal = _jitter(rng, rng.choice([(0.3, 0.3, 0.32), (0.75, 0.72, 0.6), (0.85, 0.85, 0.85)]))
        cloth = _jitter(rng, rng.choice([(0.92, 0.88, 0.78), (0.85, 0.85, 0.8), (0.6, 0.2, 0.15)]))
        stem = 0.6 * h
        parts = [
            _Part((0, 0, 0.015), (base, base, 0.03), metal, "metal", "base"),
            _Part((0, 0, 0.03 + (stem - 0.03) / 2), (0.03, 0.03, stem - 0.03), metal, "metal", "stem"),
            _Part((0, 0, stem + (h - stem) / 2), (shade, shade, h - stem), cloth, "fabric", "shade"),
        ]
    elif label == "storage box":
        w, d, h = rng.uniform(0.22, 0.4), rng.uniform(0.18, 0.3), rng.uniform(0.14, 0.3)
        parts = [_Part((0, 0, h / 2), (w, d, h), _jitter(rng, rng.choice([(0.7, 0.55, 0.35), (0.2, 0.4, 0.7)])), "plain", "box")]
    else:
        w, h = rng.uniform(0.24, 0.36), rng.uniform(0.16, 0.26)
        parts = _hollow(0, 0, 0, w, w * rng.uniform(0.7, 1.0), h, 0.012, _jitter(rng, (0.62, 0.48, 0.3)), "fabric", "basket")
    return _Spec("otherfurniture", str(label), parts, "on")


def _curtain(rng, height) -> _Spec:
    w = rng.uniform(0.6, 1.4)
    top = height - rng.uniform(0.15, 0.3)
    bottom = rng.choice([rng.uniform(0.02, 0.05), rng.uniform(0.8, 1.0)])
    color = _fabric(rng)
    pleats = max(3, int(round(w / 0.18)))
    pw = w / pleats
    parts = [
        _Part((-w / 2 + (k + 0.5) * pw, 0.015 * (k % 2), (top + bottom) / 2), (pw, 0.03, top - bottom), color, "fabric", "pleat")
        for k in range(pleats)
    ]
    return _Spec("curtain", "curtain", parts, "mounted", wall_gap=rng.uniform(0.07, 0.1)).recentred()


def _picture(rng, height) -> _Spec:
    w, h = rng.uniform(0.3, 1.0), rng.uniform(0.3, 0.8)
    zc = min(rng.uniform(1.3, 1.75), height - 0.2 - h / 2)
    frame = _jitter(rng, rng.choice([(0.1, 0.1, 0.1), (0.85, 0.85, 0.82), _WOODS[1]]))
    b, t = 0.04, 0.03
    parts = [
        _Part((0, 0, zc + h / 2 - b / 2), (w, t, b), frame, "wood", "frame"),
        _Part((0, 0, zc - h / 2 + b / 2), (w, t, b), frame, "wood", "frame"),
        _Part((-w / 2 + b / 2, 0, zc), (b, t, h - 2 * b), frame, "wood", "frame"),
        _Part((w / 2 - b / 2, 0, zc), (b, t, h - 2 * b), frame, "wood", "frame"),
        _Part(
            (0, 0.005, zc),
            (w - 2 * b, t - 0.01, h - 2 * b),
            _hsv(rng.uniform(), rng.uniform(0.3, 0.8), rng.uniform(0.4, 0.9)),
            "fabric",
            "canvas",
        ),
    ]
    return _Spec("picture", "picture", parts, "mounted", wall_gap=0.0)


def _door(rng, height) -> _Spec:
    w, h = rng.uniform(0.8, 0.95), min(rng.uniform(2.0, 2.1), height - 0.2)
    leaf = _wood(rng) if rng.random() < 0.6 else _jitter(rng, _WHITE)
    frame = _jitter(rng, _WHITE) if rng.random() < 0.6 else leaf
    # The leaf's back is 3.5 cm inside the wall, its front 1.5 cm in front of it; the trim stands out 2.5 cm.
    parts = [
        _Part((0, 0.005, h / 2), (w, 0.05, h), leaf, "wood", "leaf"),
        _Part((-(w / 2 + 0.035), -0.005, (h + 0.07) / 2), (0.07, 0.05, h + 0.07), frame, "paint", "trim"),
        _Part((w / 2 + 0.035, -0.005, (h + 0.07) / 2), (0.07, 0.05, h + 0.07), frame, "paint", "trim"),
        _Part((0, -0.005, h + 0.035), (w + 0.14, 0.05, 0.07), frame, "paint", "trim"),
        _Part((w / 2 - 0.08, -0.045, h * 0.48), (0.12, 0.05, 0.025), _jitter(rng, (0.7, 0.7, 0.7)), "metal", "handle"),
    ]
    return _Spec("door", "door", parts, "mounted", wall_gap=-0.03 - 0.005)


def _window(rng, height) -> _Spec:
    w = rng.uniform(0.8, 1.6)
    sill = rng.uniform(0.8, 1.0)
    top = min(sill + rng.uniform(0.9, 1.4), height - 0.25)
    h = top - sill
    frame = _jitter(rng, _WHITE, 0.02)
    glass = _jitter(rng, (0.62, 0.74, 0.85), 0.05)
    b = 0.06
    parts = [
        _Part((0, -0.01, (sill + top) / 2), (w - 2 * b, 0.04, h - 2 * b), glass, "glass", "pane"),
        _Part((0, -0.01, sill + b / 2), (w + 0.06, 0.06, b), frame, "paint", "frame"),
        _Part((0, -0.01, top - b / 2), (w, 0.06, b), frame, "paint", "frame"),
        _Part((-(w / 2 - b / 2), -0.01, (sill + top) / 2), (b, 0.06, h - 2 * b), frame, "paint", "frame"),
        _Part((w / 2 - b / 2, -0.01, (sill + top) / 2), (b, 0.06, h - 2 * b), frame, "paint", "frame"),
    ]
    if w > 1.1:
        parts.append(_Part((0, -0.01, (sill + top) / 2), (0.04, 0.06, h - 2 * b), frame, "paint", "mullion"))
    # Back of the frame 4 cm inside the wall, its front 2 cm in front of it, the glass 1 cm.
    return _Spec("window", "window", parts, "mounted", wall_gap=-0.04)


_GENERATORS: dict[str, Callable] = {
    "chair": _chair,
    "table": _table,
    "desk": _desk,
    "bed": _bed,
    "sofa": _sofa,
    "cabinet": _cabinet,
    "bookshelf": _bookshelf,
    "counter": _counter,
    "refrigerator": _refrigerator,
    "toilet": _toilet,
    "sink": _sink,
    "bathtub": _bathtub,
    "otherfurniture": _otherfurniture,
}


_WALL_GENERATORS: dict[str, Callable] = {"curtain": _curtain, "picture": _picture, "door": _door, "window": _window}
