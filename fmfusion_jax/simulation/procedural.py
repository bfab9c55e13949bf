"""Procedural indoor scenes with exact ground truth: a room and furniture made of oriented boxes.

A `ProceduralScene` is a rectangular room (walls, floor, ceiling, at least one door and one window) holding
objects of the ScanNet benchmark classes, each object an instance made of one or more boxes that rotate about
the vertical axis only. Everything is deterministic per seed. The world frame has its origin at a floor corner
of the room, z up, the room spanning `[0, W] x [0, D] x [0, H]`.

- `generate_scene(seed, room_size, num_objects, kinds, stacked)`: the room and its objects, placed without
  overlap (furniture on the floor or against a wall, doors/windows/pictures/curtains on walls, and `stacked`
  small things on top of tables, desks, counters and cabinets); `ProceduralScene.relations` says which object
  rests on which and which are near each other, for testing a scene graph.
- `camera_trajectory(scene, num_frames)`: a smooth hand-held-like loop around the room, `T_world_camera`.
- `build_mesh(scene)`: the visible box surfaces as a triangle mesh with ~3 cm vertex spacing (like ScanNet's
  `_vh_clean_2.ply`), per-vertex instance and over-segmentation ids.

Rendering is in `raycast`, writing the ScanNet layout in `scannet_writer`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence

import numpy as np

from fmfusion_jax.simulation import raycast

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

#: Default room for up to `_BASE_OBJECTS` objects; more objects grow its floor area proportionally.
DEFAULT_ROOM = (5.0, 4.0, 2.6)
_BASE_OBJECTS = 12

WALL_THICKNESS = 0.1
#: Gap between furniture set against a wall and the wall (small: the hidden back faces are culled from the mesh).
_WALL_GAP = 0.003
#: Camera path: margin from the walls and lowest camera height; objects taller than `_TALL` keep off the path.
_PATH_MARGIN = 1.2
_CAMERA_MIN_HEIGHT = 1.3
_TALL = 1.05
_PATH_CLEARANCE = 0.35


@dataclasses.dataclass(frozen=True)
class Box:
    """One oriented box of the scene.

    Attributes:
      center: `(3,)` float64 world centre, metres.
      half_extents: `(3,)` float64 half sizes along the box's local x, y, z.
      yaw: rotation about world +z, radians (local z stays vertical).
      instance_id: the instance it belongs to (>= 1).
      color: `(3,)` float albedo in [0, 1], RGB.
      material: a `raycast.MATERIALS` name (procedural texture).
      part: what the box is (``"seat"``, ``"leg"``...), for debugging.
    """

    center: np.ndarray
    half_extents: np.ndarray
    yaw: float
    instance_id: int
    color: np.ndarray
    material: str = "plain"
    part: str = ""

    @property
    def rotation(self) -> np.ndarray:
        """`(3, 3)` box-to-world rotation."""
        return raycast.yaw_rotation(self.yaw)

    def contains(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """`(N,)` bool: points `(N, 3)` inside the box grown by `margin` on every side."""
        local = (np.asarray(points, np.float64) - self.center) @ self.rotation
        return np.all(np.abs(local) <= self.half_extents + margin, axis=1)


def box_distance(a: tuple[np.ndarray, np.ndarray, float], b: tuple[np.ndarray, np.ndarray, float], samples: int = 11) -> float:
    """Metres between two oriented boxes `(center (3,), extent (3,), yaw)` (0 when they touch or overlap): the
    least distance from a grid of points over each box (faces included) to the other, exact to ~extent/samples."""
    t = np.linspace(-0.5, 0.5, samples)
    grid = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)
    distance = math.inf
    for one, other in ((a, b), (b, a)):
        points = one[0] + (grid * one[1]) @ raycast.yaw_rotation(one[2]).T
        local = (points - other[0]) @ raycast.yaw_rotation(other[2])
        outside = np.maximum(np.abs(local) - np.asarray(other[1]) / 2, 0.0)
        distance = min(distance, float(np.linalg.norm(outside, axis=1).min()))
    return distance


@dataclasses.dataclass(frozen=True)
class InstanceInfo:
    """What an instance is.

    Attributes:
      instance_id: >= 1 (0 means "no instance" in images).
      kind: the generator's name for it (``"wall"``, ``"chair"``...).
      class_name: one of the 20 closed classes (`labels.load_label_sets().class_names`), or ``"ceiling"``.
      nyu40_id: its NYU40 class id.
      raw_label: the ScanNet raw label (``"office chair"``), the `category` of the labels tsv.
    """

    instance_id: int
    kind: str
    class_name: str
    nyu40_id: int
    raw_label: str


@dataclasses.dataclass(frozen=True, eq=False)
class ProceduralScene:
    """A room of boxes with its instances (see the module docstring for the frame).

    Attributes:
      seed: the generator's seed.
      room_size: `(W, D, H)` interior size, metres.
      boxes: every box; walls, floor and ceiling first.
      instances: instance id -> `InstanceInfo` (walls, floor, ceiling and objects).
      light_position: `(3,)` the point light used for shading.
      enclosure_boxes: `(6,)` indices in `boxes` of the x-, x+, y-, y+ walls, the floor and the ceiling.
      resting_on: object instance id -> the instance it stands on: the floor's id for objects whose lowest
        box touches the floor, the supporting object's for stacked ones (objects hung on walls: absent).
    """

    seed: int
    room_size: tuple[float, float, float]
    boxes: tuple[Box, ...]
    instances: dict[int, InstanceInfo]
    light_position: np.ndarray
    enclosure_boxes: tuple[int, ...]
    resting_on: dict[int, int] = dataclasses.field(default_factory=dict)

    @functools.cached_property
    def _box_arrays(self) -> raycast.BoxArrays:
        return raycast.BoxArrays(
            centers=np.array([b.center for b in self.boxes], np.float64).reshape(-1, 3),
            half_extents=np.array([b.half_extents for b in self.boxes], np.float64).reshape(-1, 3),
            rotations=np.array([b.rotation for b in self.boxes], np.float64).reshape(-1, 3, 3),
            colors=np.array([b.color for b in self.boxes], np.float32).reshape(-1, 3),
            materials=np.array([raycast.material_code(b.material) for b in self.boxes], np.int32),
            instance_ids=np.array([b.instance_id for b in self.boxes], np.int32),
        )

    def box_arrays(self) -> raycast.BoxArrays:
        """The boxes as arrays for the renderer (cached)."""
        return self._box_arrays

    def enclosure(self) -> raycast.Enclosure:
        """The room interior with its wall/floor/ceiling boxes, for `raycast.raycast_boxes`."""
        return raycast.Enclosure(np.zeros(3), np.asarray(self.room_size, np.float64), np.asarray(self.enclosure_boxes, np.int64))

    @property
    def object_ids(self) -> list[int]:
        """Instance ids of the objects (everything but walls, floor and ceiling)."""
        return [i for i, info in self.instances.items() if info.kind not in ("wall", "floor", "ceiling")]

    def instance_boxes(self, instance_id: int) -> list[Box]:
        return [b for b in self.boxes if b.instance_id == instance_id]

    def contains(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """`(N,)` int: the instance id of a box holding each point (grown by `margin`), 0 where none."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        result = np.zeros(points.shape[0], np.int64)
        for box in self.boxes:
            inside = box.contains(points, margin) & (result == 0)
            result[inside] = box.instance_id
        return result

    def instance_box(self, instance_id: int) -> tuple[np.ndarray, np.ndarray, float]:
        """`(center (3,), extent (3,), yaw)`: the oriented box around an instance's boxes (they share a yaw)."""
        boxes = self.instance_boxes(instance_id)
        yaw = boxes[0].yaw
        rotation = raycast.yaw_rotation(yaw)
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
        corners = np.concatenate([(b.center - boxes[0].center) @ rotation + signs * b.half_extents for b in boxes])
        lower, upper = corners.min(axis=0), corners.max(axis=0)
        return boxes[0].center + rotation @ ((lower + upper) / 2), upper - lower, float(yaw)

    def relations(self, near_distance: float = 0.3) -> dict[str, set[tuple[int, int]]]:
        """The relations the generator made: `{"on": {(object, support)}, "near": {(a, b)}}` with instance ids
        (`on` the floor: the floor's id), `near` pairs sorted, between objects that do not rest on one another
        and whose oriented boxes (`instance_box`) are less than `near_distance` metres apart."""
        on = set(self.resting_on.items())
        objects = self.object_ids
        boxes = {i: self.instance_box(i) for i in objects}
        near = set()
        for k, a in enumerate(objects):
            for b in objects[k + 1 :]:
                if (a, b) in on or (b, a) in on:
                    continue
                if box_distance(boxes[a], boxes[b]) < near_distance:
                    near.add((min(a, b), max(a, b)))
        return {"on": on, "near": near}

    def trajectory(self, num_frames: int, seed: int | None = None) -> np.ndarray:
        """`camera_trajectory(self, num_frames, seed)`."""
        return camera_trajectory(self, num_frames, seed)

    def summary(self) -> str:
        """One line: room size and the count of objects of each class."""
        counts: dict[str, int] = {}
        for i in self.object_ids:
            counts[self.instances[i].class_name] = counts.get(self.instances[i].class_name, 0) + 1
        objects = ", ".join(f"{n} {name}" for name, n in sorted(counts.items()))
        w, d, h = self.room_size
        return f"room {w:.2f} x {d:.2f} x {h:.2f} m, {len(self.object_ids)} objects ({objects}), {len(self.boxes)} boxes"


# ----------------------------------------------------------------------------------------------- objects


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


# --------------------------------------------------------------------------------------------- placement


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


# ------------------------------------------------------------------------------------------------ scene


def default_room_size(num_objects: int) -> tuple[float, float, float]:
    """The room `generate_scene` uses for `num_objects` when none is given: 5 x 4 x 2.6 m up to 12 objects,
    then a floor area growing in proportion (60 objects: 11.2 x 8.9 x 2.8 m)."""
    w, d, h = DEFAULT_ROOM
    if num_objects <= _BASE_OBJECTS:
        return (w, d, h)
    scale = math.sqrt(num_objects / _BASE_OBJECTS)
    return (round(w * scale, 2), round(d * scale, 2), 2.8 if num_objects > 30 else h)


def generate_scene(
    seed: int,
    room_size: Sequence[float] | None = None,
    num_objects: int = 12,
    kinds: Sequence[str] | None = None,
    stacked: int = 0,
) -> ProceduralScene:
    """A random room with `num_objects` objects, deterministic per `seed`.

    Args:
      seed: any integer.
      room_size: `(W, D, H)` interior metres; None: `default_room_size(num_objects)`, grown further (by 12 %
        steps) when the objects do not fit.
      num_objects: objects besides walls, floor and ceiling (>= 1). Without `kinds` the first two are a door
        and a window, then every other kind once in random order, then kinds drawn by frequency (chairs most).
      kinds: the object kinds to draw from (`OBJECT_KINDS`), each placed once before any repeats.
      stacked: small objects (lamps, boxes, baskets: class otherfurniture) to stand on the tops of the tables,
        desks, counters and low cabinets, besides `num_objects` (fewer when there is no such top or no room on
        them). 0 draws nothing more: the room is the same as without the argument.

    Raises:
      ValueError: bad arguments, or (with an explicit `room_size`) the objects do not fit in the room.
    """
    if int(num_objects) != num_objects or num_objects < 1:
        raise ValueError(f"num_objects must be a positive integer, got {num_objects!r}")
    num_objects = int(num_objects)
    if num_objects > 900:
        raise ValueError(f"num_objects {num_objects} is too many (at most 900: ScanNet object ids stay below 999)")
    if kinds is not None:
        kinds = list(kinds)
        unknown = sorted(set(kinds) - set(OBJECT_KINDS))
        if unknown or not kinds:
            raise ValueError(f"unknown object kinds {unknown or kinds}; expected some of {list(OBJECT_KINDS)}")
    auto = room_size is None
    size = default_room_size(num_objects) if room_size is None else tuple(float(x) for x in room_size)
    if len(size) != 3 or min(size[:2]) < 2.0 or size[2] < 2.2 or max(size) > 100:
        raise ValueError(f"room_size {size}: expected (W, D, H) metres with W, D >= 2 and H >= 2.2 (and <= 100)")
    for attempt in range(8):
        rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, attempt])
        drawn = _draw_kinds(rng, num_objects, kinds)
        try:
            placed = _place_objects(size, drawn, rng, kinds)
            break
        except _NoRoom as error:
            if not auto:
                w, d, h = size
                raise ValueError(
                    f"could place only {error.placed} of {num_objects} objects in a {w:g} x {d:g} m room; "
                    "use a bigger room or fewer objects"
                ) from None
            size = (round(size[0] * 1.12, 2), round(size[1] * 1.12, 2), size[2])
    else:  # pragma: no cover - the room grows by 2.5x in area over the attempts
        raise ValueError(f"could not place {num_objects} objects")
    if stacked:
        placed = placed + _place_on_tops(placed, int(stacked), rng)
    return _assemble(int(seed), size, placed, rng)


def _assemble(seed: int, size, placed: list[_Placed], rng) -> ProceduralScene:
    from fmfusion_jax.labels import load_label_sets

    label_sets = load_label_sets()
    nyu40 = label_sets.class_to_nyu40()
    w, d, h = size
    t = WALL_THICKNESS
    boxes: list[Box] = []
    instances: dict[int, InstanceInfo] = {}

    def add_instance(kind, class_name, raw_label, nyu) -> int:
        instance_id = len(instances) + 1
        instances[instance_id] = InstanceInfo(instance_id, kind, class_name, nyu, raw_label)
        return instance_id

    wall_color = _jitter(rng, rng.choice([(0.88, 0.86, 0.8), (0.85, 0.87, 0.88), (0.9, 0.88, 0.84), (0.8, 0.84, 0.78)]), 0.02)
    # x-, x+, y-, y+ walls (inner faces on the room's faces), floor, ceiling.
    structure = [
        ((-t / 2, d / 2, h / 2), (t, d, h)),
        ((w + t / 2, d / 2, h / 2), (t, d, h)),
        ((w / 2, -t / 2, h / 2), (w, t, h)),
        ((w / 2, d + t / 2, h / 2), (w, t, h)),
    ]
    for center, full in structure:
        instance_id = add_instance("wall", "wall", "wall", nyu40["wall"])
        boxes.append(
            Box(np.array(center), np.array(full) / 2, 0.0, instance_id, _jitter(rng, wall_color, 0.015), "paint", "wall")
        )
    floor_material = str(rng.choice(["wood", "tiles", "carpet"]))
    floor_color = {"wood": _wood(rng), "tiles": _jitter(rng, (0.75, 0.73, 0.7)), "carpet": _fabric(rng) * 0.8}[floor_material]
    instance_id = add_instance("floor", "floor", "floor", nyu40["floor"])
    boxes.append(
        Box(np.array([w / 2, d / 2, -t / 2]), np.array([w, d, t]) / 2, 0.0, instance_id, floor_color, floor_material, "floor")
    )
    instance_id = add_instance("ceiling", CEILING_CLASS, "ceiling", CEILING_NYU40)
    boxes.append(
        Box(
            np.array([w / 2, d / 2, h + t / 2]),
            np.array([w, d, t]) / 2,
            0.0,
            instance_id,
            _jitter(rng, (0.93, 0.93, 0.92), 0.01),
            "paint",
            "ceiling",
        )
    )

    floor_id = next(i for i, info in instances.items() if info.kind == "floor")
    instance_of: list[int] = []
    resting_on: dict[int, int] = {}
    for p in placed:
        spec = p.spec
        assert spec is not None  # placed objects have their spec (only keep-clear zones have none)
        instance_id = add_instance(spec.kind, spec.kind, spec.raw_label, nyu40[spec.kind])
        instance_of.append(instance_id)
        if p.support >= 0:
            resting_on[instance_id] = instance_of[p.support]
        elif spec.bounds[0][2] <= 0.01:
            resting_on[instance_id] = floor_id
        R = raycast.yaw_rotation(p.yaw)
        origin = np.array([p.center[0], p.center[1], 0.0])
        for part in spec.parts:
            center = origin + R @ np.asarray(part.center, np.float64)
            boxes.append(
                Box(
                    center,
                    np.asarray(part.size, np.float64) / 2,
                    float(p.yaw),
                    instance_id,
                    np.asarray(part.color, np.float64),
                    part.material,
                    part.name,
                )
            )
    light = np.array([w / 2, d / 2, h - 0.35])
    return ProceduralScene(
        seed, (float(w), float(d), float(h)), tuple(boxes), instances, light, (0, 1, 2, 3, 4, 5), resting_on=resting_on
    )


def empty_room(room_size: Sequence[float] = DEFAULT_ROOM, seed: int = 0) -> ProceduralScene:
    """A room with walls, floor and ceiling only (instance ids 1-4 walls, 5 floor, 6 ceiling), for hand-made
    test worlds: add objects with `add_object`."""
    size = tuple(float(x) for x in room_size)
    if len(size) != 3 or min(size) <= 0:
        raise ValueError(f"room_size {size}: expected (W, D, H) positive metres")
    return _assemble(int(seed), size, [], np.random.default_rng([int(seed) & 0xFFFFFFFF, 99]))


def add_object(
    scene: ProceduralScene,
    kind: str,
    boxes: Sequence[tuple],
    raw_label: str | None = None,
    color: Sequence[float] = (0.6, 0.4, 0.3),
    material: str = "plain",
) -> ProceduralScene:
    """A copy of `scene` with one more instance made of `boxes`, each `(center (3,), size (3,), yaw)` in world
    metres/radians. `kind` is one of the closed classes (`OBJECT_KINDS`, or ``"wall"``/``"floor"``); the new
    instance id is one more than the largest. Overlaps are not checked."""
    from fmfusion_jax.labels import load_label_sets

    label_sets = load_label_sets()
    nyu40 = label_sets.class_to_nyu40()
    if kind not in nyu40:
        raise ValueError(f"kind {kind!r}: expected one of the closed classes {list(nyu40)}")
    instance_id = max(scene.instances) + 1
    raw_label = raw_label or kind
    instances = dict(scene.instances)
    instances[instance_id] = InstanceInfo(instance_id, kind, kind, nyu40[kind], raw_label)
    new_boxes = [
        Box(
            np.asarray(center, np.float64),
            np.asarray(size, np.float64) / 2,
            float(yaw),
            instance_id,
            np.asarray(color, np.float64),
            material,
            kind,
        )
        for center, size, yaw in boxes
    ]
    return dataclasses.replace(scene, boxes=scene.boxes + tuple(new_boxes), instances=instances)


# ------------------------------------------------------------------------------------------- trajectory


def camera_trajectory(scene: ProceduralScene, num_frames: int, seed: int | None = None) -> np.ndarray:
    """A closed loop of `num_frames` camera poses `(N, 4, 4)` float64 `T_world_camera` (OpenCV axes).

    The camera walks once around an ellipse 1.2 m in from the walls (less in small rooms) at 1.33-1.57 m
    height, sweeping its heading +-95 degrees around the walking direction (so it looks at the walls and
    into the room in turn), pitched 25-40 degrees down (so the optical axis meets the floor or something
    nearer within 3.5 m), with a little roll. Every camera centre is checked to be outside all boxes.
    """
    if int(num_frames) != num_frames or num_frames < 1:
        raise ValueError(f"num_frames must be a positive integer, got {num_frames!r}")
    rng = np.random.default_rng([int(scene.seed if seed is None else seed) & 0xFFFFFFFF, 7919])
    w, d, _ = scene.room_size
    a, b = _path_axes(scene.room_size)
    phase = rng.uniform(0, 2 * np.pi, 5)
    direction = rng.choice([-1.0, 1.0])
    s = np.arange(num_frames) / num_frames
    theta = phase[0] + direction * 2 * np.pi * s
    position = np.stack(
        [w / 2 + a * np.cos(theta), d / 2 + b * np.sin(theta), 1.45 + 0.12 * np.sin(2 * np.pi * 3 * s + phase[1])], axis=1
    )
    tangent = np.stack([-a * np.sin(theta), b * np.cos(theta)], axis=1) * direction
    heading = np.arctan2(tangent[:, 1], tangent[:, 0])
    yaw = heading + np.radians(95) * np.sin(2 * np.pi * 5 * s + phase[2])
    pitch = -np.radians(32.5 + 7.5 * np.sin(2 * np.pi * 7 * s + phase[3]))
    roll = np.radians(2.5) * np.sin(2 * np.pi * 4 * s + phase[4])
    poses = np.stack([look_pose(p, y, pt, r) for p, y, pt, r in zip(position, yaw, pitch, roll)])
    inside = scene.contains(position, margin=0.1)
    if inside.any():  # pragma: no cover - tall objects keep off the path by construction
        k = int(np.argmax(inside > 0))
        raise RuntimeError(f"camera {k} at {position[k]} is inside instance {inside[k]}")
    return poses


def look_pose(position, yaw: float, pitch: float, roll: float = 0.0) -> np.ndarray:
    """`(4, 4)` `T_world_camera` of a camera at `position` looking along heading `yaw` (radians from +x about
    +z), `pitch` (radians, negative = down) and `roll` about the optical axis; world z is up."""
    forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = math.cos(roll), math.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, position
    return pose


# ------------------------------------------------------------------------------------------------- mesh


@dataclasses.dataclass(frozen=True)
class SceneMesh:
    """The visible surfaces of a scene as a triangle mesh, with per-vertex ground truth.

    Attributes:
      vertices: `(V, 3)` float32 metres.
      faces: `(F, 3)` int32 vertex indices, counter-clockwise seen from outside.
      colors: `(V, 3)` uint8 RGB (albedo x texture x the renderer's lighting, no noise).
      instance_ids: `(V,)` int32 instance of each vertex (>= 1).
      segment_ids: `(V,)` int32 over-segmentation: one segment per patch (at most `patch_size` square) of a box
        face; a segment never spans two instances.
      spacing: the grid spacing used, metres.
    """

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    instance_ids: np.ndarray
    segment_ids: np.ndarray
    spacing: float


def build_mesh(
    scene: ProceduralScene,
    spacing: float = 0.03,
    max_vertices: int = 300_000,
    patch_size: float = 0.4,
    include_ceiling: bool = True,
) -> SceneMesh:
    """Meshes the visible surfaces of the boxes on a regular grid.

    Every box face is a grid of about `spacing` metres (coarser when the mesh would exceed `max_vertices`).
    Grid cells that cannot be seen are dropped, like the unscanned parts of a ScanNet mesh: cells outside the
    room, and cells in contact with another box (the point 5 mm in front of the cell's centre lies in another
    box: the floor under a leg, a wall behind a cabinet, a shelf's end inside the side panel).
    """
    if spacing <= 0 or max_vertices < 1000 or patch_size <= 0:
        raise ValueError("spacing and patch_size must be positive, max_vertices at least 1000")
    boxes = scene.box_arrays()
    use = np.ones(len(boxes), bool)
    if not include_ceiling:
        use[scene.enclosure_boxes[5]] = False
    # Choose the spacing from the visible area (walls, floor, objects; the outer faces are dropped anyway).
    room = np.asarray(scene.room_size)
    area = 0.0
    for i in np.nonzero(use)[0]:
        he = boxes.half_extents[i]
        area += 8 * (he[0] * he[1] + he[1] * he[2] + he[0] * he[2])
    # Structural boxes contribute one face each (their others are outside the room).
    for e in scene.enclosure_boxes:
        if use[e]:
            he = boxes.half_extents[e]
            area -= 8 * (he[0] * he[1] + he[1] * he[2] + he[0] * he[2])
            area += 4 * np.sort(he)[1] * np.sort(he)[2]
    spacing = max(spacing, math.sqrt(area / (0.9 * max_vertices)))

    vertex_parts: list[np.ndarray] = []
    face_parts: list[np.ndarray] = []
    owner_parts: list[np.ndarray] = []
    segment_parts: list[np.ndarray] = []
    normal_parts: list[np.ndarray] = []
    offset, segment_base = 0, 0
    for i in np.nonzero(use)[0]:
        R, c, he = boxes.rotations[i], boxes.centers[i], boxes.half_extents[i]
        for axis in range(3):
            for sign in (-1.0, 1.0):
                u_axis, v_axis = (axis + 1) % 3, (axis + 2) % 3
                if sign < 0:
                    u_axis, v_axis = v_axis, u_axis
                nu = max(1, int(math.ceil(2 * he[u_axis] / spacing)))
                nv = max(1, int(math.ceil(2 * he[v_axis] / spacing)))
                gu = np.linspace(-he[u_axis], he[u_axis], nu + 1)
                gv = np.linspace(-he[v_axis], he[v_axis], nv + 1)
                U, V = np.meshgrid(gu, gv, indexing="ij")
                local = np.zeros((nu + 1, nv + 1, 3))
                local[..., axis] = sign * he[axis]
                local[..., u_axis] = U
                local[..., v_axis] = V
                world = local.reshape(-1, 3) @ R.T + c
                # Cells: (iu, iv) -> 2 triangles, counter-clockwise around the outward normal (u x v = normal).
                iu, iv = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
                v00 = (iu * (nv + 1) + iv).ravel()
                v10, v01, v11 = v00 + (nv + 1), v00 + 1, v00 + nv + 2
                cell_faces = np.stack([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)], 1)  # (C, 2, 3)
                # Segments: patches of the face.
                pu = max(1, int(math.ceil(2 * he[u_axis] / patch_size)))
                pv = max(1, int(math.ceil(2 * he[v_axis] / patch_size)))
                su = np.minimum((np.arange(nu + 1) * pu) // (nu + 1), pu - 1)
                sv = np.minimum((np.arange(nv + 1) * pv) // (nv + 1), pv - 1)
                seg = (su[:, None] * pv + sv[None, :]).ravel() + segment_base
                segment_base += pu * pv
                vertex_parts.append(world)
                face_parts.append(cell_faces + offset)
                owner_parts.append(np.full(world.shape[0], i))
                segment_parts.append(seg)
                normal_parts.append(np.broadcast_to(R[:, axis] * sign, world.shape))
                offset += world.shape[0]
    vertices = np.concatenate(vertex_parts)
    faces = np.concatenate(face_parts)  # (C, 2, 3)
    owners = np.concatenate(owner_parts)
    segments = np.concatenate(segment_parts)
    normals = np.concatenate(normal_parts)

    # Visibility of each cell from its centre.
    cell_owner = owners[faces[:, 0, 0]]
    centre = vertices[faces[:, 0, [0, 2]]].mean(axis=1)
    probe = centre + 0.005 * normals[faces[:, 0, 0]]
    keep = np.all((centre >= -1e-3) & (centre <= room + 1e-3), axis=1)
    by_x = np.argsort(probe[:, 0], kind="stable")
    sorted_x = probe[by_x, 0]
    for j in range(len(boxes)):
        lower = boxes.centers[j] - np.abs(boxes.rotations[j]) @ boxes.half_extents[j]
        upper = boxes.centers[j] + np.abs(boxes.rotations[j]) @ boxes.half_extents[j]
        candidates = by_x[np.searchsorted(sorted_x, lower[0], "left") : np.searchsorted(sorted_x, upper[0], "right")]
        q = probe[candidates]
        near = keep[candidates] & np.all((q >= lower) & (q <= upper), axis=1) & (cell_owner[candidates] != j)
        if not near.any():
            continue
        idx = candidates[near]
        local = (probe[idx] - boxes.centers[j]) @ boxes.rotations[j]
        inside = np.all(np.abs(local) <= boxes.half_extents[j], axis=1)
        keep[idx[inside]] = False
    faces = faces[keep].reshape(-1, 3)
    used = np.zeros(vertices.shape[0], bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    faces = remap[faces].astype(np.int32)
    vertices, owners, segments, normals = vertices[used], owners[used], segments[used], normals[used]
    _, segments = np.unique(segments, return_inverse=True)

    # Colours: the renderer's albedo x texture x lighting, seen from the light (no view term).
    v32, n32 = vertices.astype(np.float32), normals.astype(np.float32)
    point = (v32[:, 0], v32[:, 1], v32[:, 2])
    shade = raycast.lambert((n32[:, 0], n32[:, 1], n32[:, 2]), point, scene.light_position)
    shade *= raycast.texture(boxes.materials[owners], owners, boxes, point)
    colors = np.clip(boxes.colors[owners] * (shade + 0.06)[:, None] * 255 + 0.5, 0, 255).astype(np.uint8)
    return SceneMesh(
        vertices=vertices.astype(np.float32),
        faces=faces,
        colors=colors,
        instance_ids=boxes.instance_ids[owners].astype(np.int32),
        segment_ids=segments.astype(np.int32),
        spacing=float(spacing),
    )
