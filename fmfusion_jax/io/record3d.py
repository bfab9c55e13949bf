"""Record3D exports: iPhone / iPad LiDAR recordings of the Record3D app ("Export as .r3d"), a ``.r3d`` file or
the folder it unzips to. The depth is LZFSE-compressed, read through the pyliblzfse package (the ``record3d`` extra:
``pip install -e ".[record3d]"``; imported only when an export is extracted).

The format has no published specification. This reader follows how Record3D's own playback demo
(github.com/marek-simonik/record3d_offline_unity_demo, Record3DVideo.cs: K[0], K[4], K[6], K[7] are fx, fy, cx, cy)
and the loaders of viser (src/viser/extras/_record3d.py), nerfstudio (nerfstudio/process_data/record3d_utils.py) and
USA-Net (usa/tasks/datasets/r3d.py) read it::

    REC.r3d                     a ZIP archive holding
      metadata                  JSON: "w", "h" the colour size; "K" the colour camera's 3x3 intrinsics as 9 numbers,
                                column-major; "dw", "dh" the depth size (absent in old exports: then inferred from
                                the first depth image's size and the colour's aspect); "poses": per frame
                                [qx, qy, qz, qw, tx, ty, tz], camera-to-world in ARKit's conventions;
                                "frameTimestamps" (s, optional); "fps", "initPose", "cameraType" (not used)
      rgbd/0.jpg, 1.jpg, ...    colour, w x h
      rgbd/0.depth, ...         LZFSE-compressed float32 metres, dh rows of dw (0 or NaN: no depth)
      rgbd/0.conf, ...          (optional) LZFSE-compressed uint8 ARKit confidence: 0 low, 1 medium, 2 high
      icon, sound.m4a, ...      (not used)

How it is read:

- Poses: ARKit's camera looks along -z with +y up (OpenGL's camera axes), ours along +z with +y down (OpenCV's,
  as ScanNet's poses): T_cv = T_gl @ diag(1, -1, -1, 1) (`GL_TO_CV`). ARKit's world is gravity-aligned with +y up;
  it is turned about x so that +z is up (`Y_UP_TO_Z_UP`), as ScanNet's, so that the floor filter's default
  (``detections.floor_up_axis: +z``) holds.
- Camera: the depth camera is the colour camera scaled to the depth size, s = dw / w (= dh / h), with pixel centres
  at integer coordinates as the back-projection has them: f' = f s, c' = (c + 0.5) s - 0.5.
- Depth: pixels whose confidence is below `min_confidence` (``dataset.min_depth_confidence``, default 1: ARKit's
  low-confidence pixels, mostly flying pixels at depth edges, are dropped) read as no depth; stored as millimetre
  PNGs (depth scale 1000).
- Colour is larger than depth (e.g. 1920x1440 or 720x960 against 256x192): `Scene` resizes it to the depth size,
  as ScanNet's 1296x968 colour to its 640x480 depth.
- Frame i (rgbd/i.jpg) is named ``frame-00000i`` (six digits), as a ROS bag's frames.

The export is read once and its frames extracted into the cache (`io.recording_cache`; the key: the file's, or the
folder's files', path, size and mtime, and `min_confidence`): colour JPEGs byte for byte, depth as PNG.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import re
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeGuard

import cv2
import numpy as np

from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io.recording_cache import (
    EXTRACTED_DEPTH_SCALE,
    MANIFEST,
    cache_folder,
    extract_once,
    file_stats,
    is_extracted,
    millimetres,
)
from fmfusion_jax.io.recordings import Recording, quaternion_to_matrix
from fmfusion_jax.types import CameraIntrinsics

logger = logging.getLogger(__name__)

#: Bump when the cache folder's content changes: older folders are then not reused.
CACHE_FORMAT = 1
#: ARKit's (OpenGL's) camera axes -> OpenCV's: x stays, y and z flip (applied on the right of a camera-to-world).
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
#: ARKit's world (+y up) -> a +z-up world (applied on the left): x stays, y -> z, z -> -y; a rotation about x.
Y_UP_TO_Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])
#: ARKit's depth confidence levels (low, medium, high); depth pixels below `dataset.min_depth_confidence` are dropped.
CONFIDENCE_LEVELS = (0, 1, 2)
DEFAULT_MIN_CONFIDENCE = 1
_FRAME_FILE = re.compile(r"^rgbd/(\d+)\.(jpg|depth|conf)$")
_KINDS = {"jpg": "colour image", "depth": "depth image", "conf": "confidence map"}


@dataclasses.dataclass(frozen=True)
class Record3DMetadata:
    """What an export's metadata says.

    Attributes:
      color_size: `(w, h)` of the colour images.
      depth_size: `(dw, dh)` of the depth images, or None (old exports).
      K: `(3, 3)` the colour camera's intrinsics.
      poses: `(N, 7)` per frame `qx qy qz qw tx ty tz`, camera-to-world, ARKit's conventions.
      stamps: `(N,)` seconds, or None.
    """

    color_size: tuple[int, int]
    depth_size: tuple[int, int] | None
    K: np.ndarray
    poses: np.ndarray
    stamps: np.ndarray | None


def is_record3d(path: Path) -> bool:
    """A ``.r3d`` file, or a folder holding a ``metadata`` file and an ``rgbd/`` folder (an unzipped export)."""
    if path.is_file():
        return path.suffix.lower() == ".r3d"
    return path.is_dir() and (path / "metadata").is_file() and (path / "rgbd").is_dir()


def read_record3d(path: Path, min_confidence: int = DEFAULT_MIN_CONFIDENCE) -> Recording:
    """The frames of the Record3D export `path` (a `Recording` of layout ``record3d`` whose files lie in the cache
    folder); `UserError` without pyliblzfse, `DataError` naming the export and what is wrong for a bad one."""
    if min_confidence not in CONFIDENCE_LEVELS:
        raise UserError(f"dataset.min_depth_confidence must be one of {CONFIDENCE_LEVELS}, got {min_confidence!r}")
    folder = _extracted(path, min_confidence)
    manifest = json.loads((folder / MANIFEST).read_text())
    poses = np.load(folder / "poses.npy")
    names = [_frame_name(i) for i in range(len(poses))]
    stamps = np.load(folder / "stamps.npy") if (folder / "stamps.npy").is_file() else None
    camera = CameraIntrinsics(**manifest["camera"])
    return Recording(
        "record3d",
        names,
        [folder / "color" / f"{name}.jpg" for name in names],
        [folder / "depth" / f"{name}.png" for name in names],
        lambda i: (poses[i], f"{path.name} metadata pose {i}"),
        lambda: camera,
        EXTRACTED_DEPTH_SCALE,
        stamps,
    )


def parse_metadata(data: bytes, where: str) -> Record3DMetadata:
    """An export's ``metadata`` (JSON bytes); `DataError` naming `where` for a missing or malformed entry."""
    try:
        meta = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DataError(f"{where}: not JSON ({error})") from None
    if not isinstance(meta, dict):
        raise DataError(f"{where}: expected a JSON object, found {type(meta).__name__}")
    missing = [key for key in ("w", "h", "K", "poses") if key not in meta]
    if missing:
        raise DataError(f"{where}: no {', '.join(repr(k) for k in missing)} (its keys: {sorted(meta)})")
    color_size = _size(meta, "w", "h", where)
    depth_size = _size(meta, "dw", "dh", where) if "dw" in meta or "dh" in meta else None
    K = _array(meta["K"], where, "K", "9 numbers (a 3x3 matrix, column-major)")
    if K.shape != (9,):
        raise DataError(f'{where}: "K" must hold 9 numbers (a 3x3 matrix, column-major), found shape {K.shape}')
    poses = _array(meta["poses"], where, "poses", "a list of [qx, qy, qz, qw, tx, ty, tz]")
    if poses.ndim != 2 or poses.shape[1] != 7 or len(poses) == 0:
        raise DataError(f'{where}: "poses" must be a non-empty list of [qx, qy, qz, qw, tx, ty, tz], found shape {poses.shape}')
    stamps = meta.get("frameTimestamps")
    if isinstance(stamps, list) and len(stamps) == len(poses):
        stamps = _array(stamps, where, "frameTimestamps", "a number per frame")
        if stamps.ndim != 1:
            raise DataError(f'{where}: "frameTimestamps" must be a number per frame, found shape {stamps.shape}')
    else:
        stamps = None
    return Record3DMetadata(color_size, depth_size, K.reshape(3, 3).T, poses, stamps)


def camera_poses(rows: np.ndarray, where: str) -> np.ndarray:
    """`(N, 7)` Record3D poses (`qx qy qz qw tx ty tz`, ARKit: camera-to-world, OpenGL camera axes, +y up) ->
    `(N, 4, 4)` camera-to-world with OpenCV camera axes in a +z-up world. A non-finite row gives a non-finite pose
    (the frame is skipped); a zero quaternion is a `DataError` naming `where` and the frame."""
    poses = np.full((len(rows), 4, 4), np.nan)
    for i, row in enumerate(np.asarray(rows, np.float64)):
        if not np.all(np.isfinite(row)):
            continue
        norm = np.linalg.norm(row[:4])
        if norm < 1e-6:
            raise DataError(f"{where}: pose {i}: the quaternion (qx qy qz qw) is zero")
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = quaternion_to_matrix(row[:4] / norm), row[4:]
        poses[i] = Y_UP_TO_Z_UP @ T @ GL_TO_CV
    return poses


def depth_camera(K: np.ndarray, color_size: tuple[int, int], depth_size: tuple[int, int], where: str) -> CameraIntrinsics:
    """The depth camera: the colour camera `K` `(3, 3)` of `color_size` `(w, h)` scaled to `depth_size` `(dw, dh)`
    (pixel centres at integer coordinates: f' = f s, c' = (c + 0.5) s - 0.5); `DataError` naming `where` when the
    two sizes differ in aspect or K is no pinhole camera of the colour images."""
    (w, h), (dw, dh) = color_size, depth_size
    sx, sy = dw / w, dh / h
    if abs(sx / sy - 1) > 0.01:
        raise DataError(
            f"{where}: the depth size {dw}x{dh} (dw, dh) is not the colour size {w}x{h} (w, h) scaled: their aspects "
            "differ (depth and colour of a Record3D export share one field of view)"
        )
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (np.all(np.isfinite(K)) and fx > 0 and fy > 0 and 0 < cx < w and 0 < cy < h):
        raise DataError(
            f'{where}: "K" is no pinhole camera of the {w}x{h} colour images (fx {fx:g}, fy {fy:g}, cx {cx:g}, cy {cy:g}; '
            "9 numbers, column-major: fx 0 0 0 fy 0 cx cy 1)"
        )
    return CameraIntrinsics(float(fx * sx), float(fy * sy), float((cx + 0.5) * sx - 0.5), float((cy + 0.5) * sy - 0.5), dw, dh)


def infer_depth_size(pixels: int, color_size: tuple[int, int]) -> tuple[int, int] | None:
    """`(dw, dh)` of a depth image of `pixels` pixels with the colour's aspect (old exports lack ``dw``, ``dh``), or
    None when no such size exists."""
    w, h = color_size
    dw = round(math.sqrt(pixels * w / h))
    if dw > 0 and pixels % dw == 0 and abs(dw / (pixels // dw) - w / h) < 0.01 * w / h:
        return dw, pixels // dw
    return None


def _frame_name(i: int) -> str:
    return f"frame-{i:06d}"


def _size(meta: dict[str, Any], width_key: str, height_key: str, where: str) -> tuple[int, int]:
    width, height = meta.get(width_key), meta.get(height_key)
    if not (_positive_int(width) and _positive_int(height)):
        raise DataError(f'{where}: "{width_key}" and "{height_key}" must be positive integers, found {width!r}, {height!r}')
    return width, height


def _positive_int(value: Any) -> TypeGuard[int]:
    return isinstance(value, int) and not isinstance(value, bool) and value > 0


def _array(value: Any, where: str, key: str, expected: str) -> np.ndarray:
    try:
        return np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise DataError(f'{where}: "{key}" must be {expected}') from None


# --------------------------------------------------------------------------------------------------
# Extracting the frames (once per export and confidence threshold).


def _lzfse() -> Any:
    try:
        import liblzfse
    except ImportError:
        raise UserError('reading Record3D exports needs the pyliblzfse package: pip install -e ".[record3d]"') from None
    return liblzfse


def _extracted(path: Path, min_confidence: int) -> Path:
    """The cache folder of the export's frames (made now unless an earlier open made it)."""
    files = [path] if path.is_file() else [path / "metadata", *sorted((path / "rgbd").iterdir())]
    folder = cache_folder(["record3d", CACHE_FORMAT, file_stats(files), min_confidence])
    if is_extracted(folder):
        logger.info("%s: frames read from the cache %s", path.name, folder)
        return folder
    lzfse = _lzfse()
    with _opened(path) as (names, read):
        extract_once(folder, lambda staging: _extract_into(path, names, read, lzfse, min_confidence, staging))
    logger.info("%s: frames extracted into %s", path.name, folder)
    return folder


@contextlib.contextmanager
def _opened(path: Path) -> Iterator[tuple[set[str], Callable[[str], bytes]]]:
    """The export's member names (``metadata``, ``rgbd/0.jpg``, ...) and a function reading one."""
    if path.is_dir():
        yield (
            {"metadata", *(f"rgbd/{entry.name}" for entry in (path / "rgbd").iterdir())},
            lambda name: (path / name).read_bytes(),
        )
        return
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as error:
        raise DataError(f"{path}: not a ZIP archive, which a Record3D .r3d export is ({error})") from None
    with archive:
        yield set(archive.namelist()), archive.read


def _extract_into(path: Path, names: set[str], read: Callable[[str], bytes], lzfse: Any, min_confidence: int, out: Path) -> None:
    """`_extract`, its failures named by the export: a member the archive cannot inflate, a file it cannot read."""
    try:
        _extract(path, names, read, lzfse, min_confidence, out)
    except (DataError, UserError):
        raise
    except Exception as error:  # noqa: BLE001 - any reading failure of a user's export is a DataError naming it
        raise DataError(f"{path}: reading the export failed ({type(error).__name__}: {error})") from None


def _extract(path: Path, names: set[str], read: Callable[[str], bytes], lzfse: Any, min_confidence: int, out: Path) -> None:
    if "metadata" not in names:
        raise DataError(f"{path}: no metadata file (a Record3D export holds metadata, rgbd/0.jpg, rgbd/0.depth, ...)")
    meta = parse_metadata(read("metadata"), f"{path}: metadata")
    count = len(meta.poses)
    has_confidence = _check_frame_files(path, names, count)
    poses = camera_poses(meta.poses, f"{path}: metadata")
    first = _decompress(lzfse, read("rgbd/0.depth"), f"{path}: rgbd/0.depth")
    depth_size = meta.depth_size or infer_depth_size(len(first) // 4, meta.color_size)
    if depth_size is None:
        raise DataError(
            f'{path}: metadata has no "dw", "dh" and rgbd/0.depth ({len(first)} bytes) is no float32 image of the '
            f"colour's aspect {meta.color_size[0]}x{meta.color_size[1]}"
        )
    camera = depth_camera(meta.K, meta.color_size, depth_size, f"{path}: metadata")
    _check_first_color(path, read("rgbd/0.jpg"), meta.color_size)
    if not has_confidence and min_confidence > 0:
        logger.info("%s: no confidence maps (rgbd/*.conf): every depth pixel is kept", path.name)
    logger.info("%s: extracting %d frames (%dx%d depth) into the cache", path.name, count, *depth_size)
    (out / "color").mkdir()
    (out / "depth").mkdir()
    for i in range(count):
        jpeg = read(f"rgbd/{i}.jpg")
        if jpeg[:2] != b"\xff\xd8" or jpeg.rstrip(b"\0")[-2:] != b"\xff\xd9":
            raise DataError(f"{path}: rgbd/{i}.jpg: not a complete JPEG (no start or end marker)")
        (out / "color" / f"{_frame_name(i)}.jpg").write_bytes(jpeg)
        raw = first if i == 0 else _decompress(lzfse, read(f"rgbd/{i}.depth"), f"{path}: rgbd/{i}.depth")
        depth = _image(raw, np.float32, depth_size, f"{path}: rgbd/{i}.depth").copy()
        if has_confidence:
            where = f"{path}: rgbd/{i}.conf"
            confidence = _image(_decompress(lzfse, read(f"rgbd/{i}.conf"), where), np.uint8, depth_size, where)
            depth[confidence < min_confidence] = 0.0
        cv2.imwrite(str(out / "depth" / f"{_frame_name(i)}.png"), millimetres(depth))
    np.save(out / "poses.npy", poses)
    if meta.stamps is not None:
        np.save(out / "stamps.npy", meta.stamps)
    manifest = {"export": str(path), "frames": count, "min_confidence": min_confidence, "confidence": has_confidence}
    manifest["camera"] = dataclasses.asdict(camera)
    (out / MANIFEST).write_text(json.dumps(manifest))  # last: its presence marks a complete folder


def _check_frame_files(path: Path, names: set[str], count: int) -> bool:
    """`DataError` unless rgbd/ holds a colour and a depth image for each of the `count` poses (and a confidence map
    for each, if for any); returns whether it holds confidence maps."""
    found: dict[str, set[int]] = {kind: set() for kind in _KINDS}
    for name in names:
        match = _FRAME_FILE.match(name)
        if match:
            found[match.group(2)].add(int(match.group(1)))
    frames = max(found["jpg"] | found["depth"], default=-1) + 1
    if frames == 0:
        raise DataError(f"{path}: no frame (rgbd/0.jpg, rgbd/0.depth, ...)")
    if frames != count:
        raise DataError(
            f"{path}: metadata holds {count} poses for {frames} frames (rgbd/0.jpg .. rgbd/{frames - 1}.jpg); "
            "one pose per frame is needed"
        )
    for kind in _KINDS if found["conf"] else ("jpg", "depth"):
        missing = sorted(set(range(count)) - found[kind])
        if missing:
            raise DataError(
                f"{path}: rgbd/{missing[0]}.{kind} missing ({len(missing)} of {count} frames lack their {_KINDS[kind]})"
            )
    return bool(found["conf"])


def _check_first_color(path: Path, jpeg: bytes, color_size: tuple[int, int]) -> None:
    """`DataError` unless rgbd/0.jpg decodes to the metadata's colour size (the others are resized when read)."""
    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR) if jpeg else None
    if image is None:
        raise DataError(f"{path}: rgbd/0.jpg: not a decodable image")
    if image.shape[:2] != color_size[::-1]:
        raise DataError(
            f'{path}: rgbd/0.jpg is {image.shape[1]}x{image.shape[0]}, but the metadata\'s "w", "h" say '
            f"{color_size[0]}x{color_size[1]} (the camera K is for that size)"
        )


def _decompress(lzfse: Any, data: bytes, where: str) -> bytes:
    try:
        return lzfse.decompress(data)
    except lzfse.error:
        raise DataError(f"{where}: not LZFSE-compressed data, or cut short") from None


def _image(raw: bytes, dtype: Any, size: tuple[int, int], where: str) -> np.ndarray:
    """Decompressed bytes as a `(dh, dw)` image of `dtype`; `DataError` naming `where` when their size differs."""
    (width, height), itemsize = size, np.dtype(dtype).itemsize
    if len(raw) != width * height * itemsize:
        raise DataError(
            f"{where}: {len(raw)} bytes decompressed, expected a {width}x{height} {np.dtype(dtype).name} image "
            f'({width * height * itemsize} bytes; the metadata\'s "dw", "dh")'
        )
    return np.frombuffer(raw, dtype).reshape(height, width)
