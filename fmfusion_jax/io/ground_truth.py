"""ScanNet instance ground truth on the `<scene>_vh_clean_2.ply` mesh, per vertex.

A vertex's instance is the aggregation group (`segGroups[i]`) whose `segments` hold the vertex's
over-segmentation id (`segIndices`); its class is the nyu40 id of the group's raw label through the
ScanNet labels tsv. The benchmark encodes both in one integer per vertex: `nyu40 * 1000 + objectId + 1`.
"""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np

from fmfusion_jax.errors import DataError

#: File names of the labels tsv, searched in the scene folder and then its parent (ScanNet v2 name first).
LABELS_TSV_NAMES = ("scannetv2-labels.combined.tsv", "scannet-labels.combined.tsv")

# Object ids are encoded as `nyu40 * 1000 + objectId + 1`, so an objectId must stay below 999.
_MAX_OBJECT_ID = 998


@dataclasses.dataclass(frozen=True, eq=False)
class SceneGroundTruth:
    """Per-vertex instance ground truth of one scene.

    Attributes:
      scene_name: e.g. ``"scene0000_00"``.
      vertices: `(V, 3)` float64 mesh vertices (metres, ScanNet world frame).
      faces: `(F, 3)` int64 vertex indices of the mesh triangles.
      vertex_colors: `(V, 3)` uint8 RGB, or None when the mesh has no colours.
      instance_ids: `(V,)` int32, 0 = no instance, else `objectId + 1`.
      nyu40_ids: `(V,)` int32 nyu40 class of the vertex's instance, 0 = unlabelled (or no instance).
      instance_labels: instance id (`objectId + 1`) -> raw ScanNet label of the instance.
    """

    scene_name: str
    vertices: np.ndarray
    faces: np.ndarray
    vertex_colors: np.ndarray | None
    instance_ids: np.ndarray
    nyu40_ids: np.ndarray
    instance_labels: dict[int, str]

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    def benchmark_ids(self) -> np.ndarray:
        """`(V,)` int64 official benchmark encoding: `nyu40 * 1000 + instance_id` on labelled instance
        vertices, 0 elsewhere (no instance, or an instance whose label has no nyu40 class)."""
        labelled = (self.instance_ids > 0) & (self.nyu40_ids > 0)
        encoded = self.nyu40_ids.astype(np.int64) * 1000 + self.instance_ids.astype(np.int64)
        return np.where(labelled, encoded, 0)


def load_scannet_ground_truth(scene_dir: str | Path, labels_tsv: str | Path | None = None) -> SceneGroundTruth:
    """Reads the mesh, over-segmentation, aggregation and labels tsv of a ScanNet scene folder.

    Args:
      scene_dir: folder named after the scene holding `<scene>_vh_clean_2.ply`,
        `<scene>_vh_clean_2.0.010000.segs.json` and `<scene>.aggregation.json`.
      labels_tsv: the raw label -> nyu40 tsv; default: `LABELS_TSV_NAMES` in `scene_dir`, then its parent.

    Raises:
      DataError: a file is missing or malformed (the message names it).
    """
    scene_dir = Path(scene_dir)
    if not scene_dir.is_dir():
        raise DataError(f"{scene_dir}: not a ScanNet scene folder (it does not exist or is not a folder)")
    name = scene_dir.name
    tsv_path = Path(labels_tsv) if labels_tsv is not None else find_labels_tsv(scene_dir)
    label_to_nyu40 = read_nyu40_mapping(tsv_path)

    vertices, faces, colors = read_ply_mesh(scene_dir / f"{name}_vh_clean_2.ply")
    segment_ids = read_segment_ids(scene_dir / f"{name}_vh_clean_2.0.010000.segs.json")
    if segment_ids.shape[0] != vertices.shape[0]:
        raise DataError(
            f"{scene_dir / f'{name}_vh_clean_2.0.010000.segs.json'}: {segment_ids.shape[0]} segIndices "
            f"but the mesh has {vertices.shape[0]} vertices"
        )
    groups = read_aggregation(scene_dir / f"{name}.aggregation.json")

    instance_ids = vertex_instance_ids(segment_ids, groups)
    instance_labels = {object_id + 1: label for object_id, label, _ in groups}
    instance_nyu40 = {inst: label_to_nyu40.get(label, 0) for inst, label in instance_labels.items()}
    nyu40_lookup = np.zeros(max(instance_labels, default=0) + 1, np.int32)
    for inst, nyu40 in instance_nyu40.items():
        nyu40_lookup[inst] = nyu40
    return SceneGroundTruth(
        scene_name=name,
        vertices=vertices,
        faces=faces,
        vertex_colors=colors,
        instance_ids=instance_ids,
        nyu40_ids=nyu40_lookup[instance_ids],
        instance_labels=instance_labels,
    )


def vertex_instance_ids(segment_ids: np.ndarray, groups: list[tuple[int, str, list[int]]]) -> np.ndarray:
    """`(V,)` int32 instance id (`objectId + 1`, 0 = none) of each vertex from its segment id.

    Args:
      segment_ids: `(V,)` int64 over-segmentation id per vertex.
      groups: `(objectId, label, segments)` per aggregation group; a segment listed by two groups goes to
        the later one (as the ScanNet export does).
    """
    largest = max([int(segment_ids.max(initial=0))] + [max(s, default=0) for _, _, s in groups])
    segment_to_instance = np.zeros(largest + 1, np.int32)
    for object_id, _, segments in groups:
        segment_to_instance[np.asarray(segments, np.int64)] = object_id + 1
    return segment_to_instance[segment_ids]


def load_benchmark_gt_txt(path: str | Path) -> np.ndarray:
    """Reads a benchmark ground-truth file: one int per line (`nyu40 * 1000 + instance`, 0 = none).

    Returns:
      `(V,)` int64.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise DataError(f"{path}: cannot read the ground-truth ids ({error})") from error
    ids = _parse_int_lines(text, path, "a ground-truth id")
    if ids.size == 0:
        raise DataError(f"{path}: no ground-truth ids (expected one integer per mesh vertex)")
    if ids.min() < 0:
        line = int(np.argmax(ids < 0)) + 1
        raise DataError(f"{path}:{line}: negative ground-truth id {ids[line - 1]}")
    return ids


def find_labels_tsv(scene_dir: Path) -> Path:
    """The labels tsv of a scene: first of `LABELS_TSV_NAMES` in `scene_dir`, then in its parent."""
    for folder in (scene_dir, scene_dir.parent):
        for name in LABELS_TSV_NAMES:
            if (folder / name).is_file():
                return folder / name
    raise DataError(
        f"{scene_dir}: no labels tsv ({' or '.join(LABELS_TSV_NAMES)}) in the scene folder or its "
        "parent; pass its path explicitly"
    )


def read_nyu40_mapping(path: str | Path) -> dict[str, int]:
    """Raw ScanNet label -> nyu40 id from a labels tsv.

    The raw label is the `raw_category` column when present (ScanNet v2 tsv), else `category` (the older
    tsv). Rows with an empty nyu40id map to 0 (unlabelled); the first row of a repeated label wins.
    """
    path = Path(path)
    try:
        with path.open(newline="") as file:
            reader = csv.DictReader(file, delimiter="\t")
            fields = reader.fieldnames or []
            label_column = "raw_category" if "raw_category" in fields else "category"
            if label_column not in fields or "nyu40id" not in fields:
                raise DataError(
                    f"{path}: a labels tsv needs columns 'category' (or 'raw_category') and 'nyu40id'; found {fields}"
                )
            mapping: dict[str, int] = {}
            for row in reader:
                label, nyu40 = (row[label_column] or "").strip(), (row["nyu40id"] or "").strip()
                if not label or label in mapping:
                    continue
                try:
                    mapping[label] = int(nyu40) if nyu40 else 0
                except ValueError:
                    raise DataError(f"{path}:{reader.line_num}: nyu40id {nyu40!r} of {label!r} is not an integer") from None
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise DataError(f"{path}: cannot read the labels tsv ({error})") from error
    return mapping


def read_segment_ids(path: Path) -> np.ndarray:
    """`(V,)` int64 `segIndices` of a ScanNet over-segmentation json."""
    data = _read_json(path)
    segment_ids = data.get("segIndices") if isinstance(data, dict) else None
    if not isinstance(segment_ids, list):
        raise DataError(f"{path}: no 'segIndices' list")
    try:
        array = np.asarray(segment_ids, np.int64)
    except (TypeError, ValueError, OverflowError):
        raise DataError(f"{path}: 'segIndices' must be a list of integers") from None
    if array.ndim != 1 or (array.size and array.min() < 0):
        raise DataError(f"{path}: 'segIndices' must be a flat list of non-negative integers")
    return array


def read_aggregation(path: Path) -> list[tuple[int, str, list[int]]]:
    """`(objectId, label, segments)` of each `segGroups` entry of a ScanNet aggregation json, in file order."""
    data = _read_json(path)
    groups = data.get("segGroups") if isinstance(data, dict) else None
    if not isinstance(groups, list):
        raise DataError(f"{path}: no 'segGroups' list")
    parsed, seen = [], set()
    for i, group in enumerate(groups):
        try:
            object_id, label, segments = group["objectId"], group["label"], group["segments"]
        except (KeyError, TypeError):
            raise DataError(f"{path}: segGroups[{i}] lacks 'objectId', 'label' or 'segments'") from None
        if not isinstance(object_id, int) or not 0 <= object_id <= _MAX_OBJECT_ID:
            raise DataError(f"{path}: segGroups[{i}].objectId {object_id!r} is not an integer in [0, {_MAX_OBJECT_ID}]")
        if object_id in seen:
            raise DataError(f"{path}: segGroups[{i}].objectId {object_id} is used by two groups")
        if not isinstance(segments, list) or not all(isinstance(s, int) and s >= 0 for s in segments):
            raise DataError(f"{path}: segGroups[{i}].segments must be a list of non-negative integers")
        seen.add(object_id)
        parsed.append((object_id, str(label).strip(), segments))
    return parsed


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DataError(f"{path}: cannot read it as JSON ({error})") from error


def _parse_int_lines(text: str, path: Path, what: str) -> np.ndarray:
    """`(N,)` int64 from one integer per line; the error names the first bad line."""
    lines = text.split("\n")
    if lines and lines[-1].strip() == "":
        lines.pop()
    try:
        return np.array([int(line) for line in lines], np.int64)
    except ValueError:
        for number, line in enumerate(lines, 1):
            try:
                int(line)
            except ValueError:
                raise DataError(f"{path}:{number}: {line.strip()!r} is not {what} (one integer per line)") from None
        raise


# ---------------------------------------------------------------------------------------------------------
# A small PLY reader: vertices (+ colours) and triangles, ascii or binary. Enough for ScanNet meshes.

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


@dataclasses.dataclass
class _PlyElement:
    name: str
    count: int
    scalars: list[tuple[str, str]]  # (property name, numpy type code)
    lists: list[tuple[str, str, str]]  # (property name, count type, item type)
    order: list[str] = dataclasses.field(default_factory=list)  # property names in file order


def read_ply_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Reads a triangle mesh PLY.

    Returns:
      vertices `(V, 3)` float64, faces `(F, 3)` int64, colours `(V, 3)` uint8 or None.
    """
    path = Path(path)
    arrays = _read_ply_elements(path, "mesh file")
    vertex = arrays["vertex"]
    if not all(k in vertex for k in "xyz"):
        raise DataError(f"{path}: vertices lack x, y or z")
    vertices = np.stack([vertex[k] for k in "xyz"], axis=1).astype(np.float64)
    colors = None
    if all(k in vertex for k in ("red", "green", "blue")):
        colors = np.stack([vertex[k] for k in ("red", "green", "blue")], axis=1).astype(np.uint8)
    faces = arrays.get("face", {}).get("__triangles__", np.zeros((0, 3), np.int64)).astype(np.int64)
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise DataError(f"{path}: a face refers to a vertex outside 0..{len(vertices) - 1}")
    return vertices, faces, colors


def read_ply_vertices(path: str | Path) -> dict[str, np.ndarray]:
    """The vertex properties of a PLY file by name (`x`, `y`, `z`, `red`, ..., `label`, `instance`)."""
    return dict(_read_ply_elements(Path(path), "PLY file")["vertex"])


def _read_ply_elements(path: Path, what: str) -> dict:
    """Every element of a PLY file (ascii or binary) as `{element: {property: array}}`; a vertex element
    is required. `what` names the file in the errors."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise DataError(f"{path}: {what} not found") from None
    except OSError as error:
        raise DataError(f"{path}: cannot read the {what} ({error})") from error
    fmt, elements, body = _parse_ply_header(data, path)
    arrays = (
        _read_ply_ascii(body, elements, path)
        if fmt == "ascii"
        else _read_ply_binary(body, elements, "<" if fmt == "binary_little_endian" else ">", path)
    )
    if "vertex" not in arrays:
        raise DataError(f"{path}: no 'vertex' element")
    return arrays


def _parse_ply_header(data: bytes, path: Path) -> tuple[str, list[_PlyElement], bytes]:
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise DataError(f"{path}: not a PLY file (no 'ply' magic or 'end_header')")
    body_start = data.find(b"\n", end) + 1
    fmt, elements = None, []
    for line in data[:end].decode("ascii", "replace").splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            elements.append(_PlyElement(words[1], int(words[2]), [], []))
        elif words[0] == "property" and elements and len(words) == 5 and words[1] == "list":
            if words[2] not in _PLY_TYPES or words[3] not in _PLY_TYPES:
                raise DataError(f"{path}: unknown PLY type in {line.strip()!r}")
            elements[-1].lists.append((words[4], _PLY_TYPES[words[2]], _PLY_TYPES[words[3]]))
            elements[-1].order.append(words[4])
        elif words[0] == "property" and elements and len(words) == 3:
            if words[1] not in _PLY_TYPES:
                raise DataError(f"{path}: unknown PLY type in {line.strip()!r}")
            elements[-1].scalars.append((words[2], _PLY_TYPES[words[1]]))
            elements[-1].order.append(words[2])
        else:
            raise DataError(f"{path}: unexpected PLY header line {line.strip()!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DataError(f"{path}: unsupported PLY format {fmt!r}")
    return fmt, elements, data[body_start:]


def _triangle_list(element: _PlyElement, path: Path) -> tuple[str, str, str]:
    if element.name != "face" or len(element.lists) != 1 or element.order[-1] != element.lists[0][0]:
        raise DataError(
            f"{path}: element {element.name!r} has list properties this reader does not support "
            "(only a face element ending with one vertex index list)"
        )
    return element.lists[0]


def _read_ply_binary(body: bytes, elements: list[_PlyElement], endian: str, path: Path) -> dict:
    arrays, offset = {}, 0
    for element in elements:
        fields: list[tuple[str, str] | tuple[str, str, tuple[int]]] = [(name, endian + code) for name, code in element.scalars]
        if element.lists:
            # Fast path: every face is a triangle, so each record has a fixed size.
            name, count_code, item_code = _triangle_list(element, path)
            fields += [("__count__", endian + count_code), ("__triangles__", endian + item_code, (3,))]
        dtype = np.dtype(fields)
        size = dtype.itemsize * element.count
        if offset + size > len(body):
            raise DataError(
                f"{path}: file ends inside the {element.name!r} element (truncated, or faces that are not all triangles)"
            )
        records = np.frombuffer(body, dtype, element.count, offset)
        offset += size
        if element.lists and np.any(records["__count__"] != 3):
            raise DataError(f"{path}: only triangle faces are supported")
        assert records.dtype.names is not None  # a structured dtype: it has field names
        arrays[element.name] = {name: records[name] for name in records.dtype.names}
    return arrays


def _read_ply_ascii(body: bytes, elements: list[_PlyElement], path: Path) -> dict:
    lines = body.decode("ascii", "replace").splitlines()
    arrays, start = {}, 0
    for element in elements:
        rows = lines[start : start + element.count]
        start += element.count
        width = len(element.scalars) + (4 if element.lists else 0)
        if element.lists:
            _triangle_list(element, path)
        try:
            table = np.array(" ".join(rows).split(), np.float64).reshape(element.count, width)
        except ValueError:
            raise DataError(
                f"{path}: element {element.name!r} is malformed (expected {element.count} rows of "
                f"{width} numbers{'; only triangle faces are supported' if element.lists else ''})"
            ) from None
        columns = {name: table[:, i].astype(code) for i, (name, code) in enumerate(element.scalars)}
        if element.lists:
            if np.any(table[:, -4] != 3):
                raise DataError(f"{path}: only triangle faces are supported")
            columns["__triangles__"] = table[:, -3:].astype(np.int64)
        arrays[element.name] = columns
    return arrays
