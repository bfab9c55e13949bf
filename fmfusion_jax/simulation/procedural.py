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
from collections.abc import Sequence

import numpy as np

from fmfusion_jax.labels import load_label_sets
from fmfusion_jax.simulation import raycast
from fmfusion_jax.simulation.furniture import CEILING_CLASS, CEILING_NYU40, OBJECT_KINDS, _fabric, _jitter, _wood
from fmfusion_jax.simulation.layout import _draw_kinds, _NoRoom, _path_axes, _place_objects, _place_on_tops, _Placed

#: Default room for up to `_BASE_OBJECTS` objects; more objects grow its floor area proportionally.
DEFAULT_ROOM = (5.0, 4.0, 2.6)
_BASE_OBJECTS = 12

WALL_THICKNESS = 0.1


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


# --------------------------------------------------------------------------------------------- placement


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


# ------------------------------------------------------------------------------------------------- mesh


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
