"""Writes a `ProceduralScene` as a ScanNet scan folder (frames, mesh and instance ground truth).

Layout of `OUT_DIR` (its name is the scene name, e.g. ``synth0000_00``), as `fmfusion_jax.io.scene` and
`fmfusion_jax.io.ground_truth` read real ScanNet scenes::

    color/frame-000000.jpg           640x480 JPEG (BGR on disk, as cv2 writes it)
    depth/frame-000000.png           uint16 millimetres, 0 = invalid
    pose/frame-000000.txt            4x4 T_world_camera
    gt_instances/frame-000000.png    uint16 instance id per pixel (0 = none or invalid depth)   [extra]
    gt_instances/instances.json      instance id -> objectId, raw label, class, nyu40 id           [extra]
    intrinsic/intrinsic_depth.txt, intrinsic_color.txt (4x4, the same camera), sensor_shapes.txt
    <scene>_vh_clean_2.ply                    binary PLY, vertex colours (+alpha) and triangles
    <scene>_vh_clean_2.0.010000.segs.json     {"segIndices": [...]} one over-segment id per vertex
    <scene>.aggregation.json                  {"segGroups": [{"id", "objectId", "label", "segments"}]}
    <scene>.txt                               ScanNet-style sensor metadata
    scannetv2-labels.combined.tsv             raw label -> nyu40 (columns id, raw_category, category, count,
                                              nyu40id, nyu40class)
    synthesis.json                            generator parameters                                  [extra]

Instance id `i` of the images is the aggregation's `objectId + 1` (the convention of
`io.ground_truth.load_scannet_ground_truth`).
"""

from __future__ import annotations

import concurrent.futures
import json
import logging
import time
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import load_label_sets
from fmfusion_jax.simulation import raycast
from fmfusion_jax.simulation.furniture import CEILING_CLASS, CEILING_NYU40, RAW_LABELS
from fmfusion_jax.simulation.procedural import ProceduralScene
from fmfusion_jax.simulation.scene_mesh import build_mesh
from fmfusion_jax.simulation.scene_views import RenderedFrame, render_frame

logger = logging.getLogger(__name__)

#: NYU40 class names as the ScanNet tsv spells them ("refridgerator" included).
NYU40_CLASS_NAMES = {
    1: "wall",
    2: "floor",
    3: "cabinet",
    4: "bed",
    5: "chair",
    6: "sofa",
    7: "table",
    8: "door",
    9: "window",
    10: "bookshelf",
    11: "picture",
    12: "counter",
    14: "desk",
    16: "curtain",
    22: "ceiling",
    24: "refridgerator",
    28: "shower curtain",
    33: "toilet",
    34: "sink",
    36: "bathtub",
    39: "otherfurniture",
}

LABELS_TSV = "scannetv2-labels.combined.tsv"
_FRAME_DIRS = {"color": ".jpg", "depth": ".png", "pose": ".txt", "gt_instances": ".png"}


def scene_intrinsics(width: int = 640, height: int = 480):
    """ScanNet's depth camera scaled to `width x height` (`raycast.SCANNET_INTRINSICS` at 640x480)."""
    return raycast.SCANNET_INTRINSICS.scaled(width, height)


def write_scannet_scene(
    scene: ProceduralScene,
    out_dir: str | Path,
    num_frames: int = 300,
    width: int = 640,
    height: int = 480,
    seed: int | None = None,
    depth_noise: bool = True,
    progress: bool = True,
    overwrite: bool = False,
    mesh_spacing: float = 0.03,
    max_vertices: int = 300_000,
    jpeg_quality: int = 90,
) -> Path:
    """Renders `num_frames` frames along `scene.trajectory` and writes them with the mesh ground truth.

    Args:
      scene: from `procedural.generate_scene`.
      out_dir: the scene folder to write (created; its name is the scene name).
      num_frames, width, height: the sequence and image size (intrinsics scaled from ScanNet's 640x480).
      seed: seed of the trajectory's phases and of the sensor noise (default: the scene's seed).
      depth_noise: Kinect-like depth noise, mm quantization, holes and grazing-angle dropouts (else exact depth).
      progress: show a tqdm progress bar.
      overwrite: allow a non-empty `out_dir` (frame files from an earlier run are deleted first).
      mesh_spacing, max_vertices: mesh resolution (see `scene_mesh.build_mesh`).
      jpeg_quality: of the colour images.

    Returns:
      The scene folder.

    Raises:
      UserError: bad sizes or counts, or a non-empty `out_dir` without `overwrite`.
    """
    out = Path(out_dir)
    if int(num_frames) != num_frames or num_frames < 1:
        raise UserError(f"num_frames must be a positive integer, got {num_frames!r}")
    if not (16 <= int(width) <= 4096 and 16 <= int(height) <= 4096):
        raise UserError(f"image size {width}x{height}: width and height must be within 16..4096 pixels")
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise UserError(f"{out}: folder is not empty (choose another folder or allow overwriting)")
        _clear_previous(out)
    name = out.resolve().name
    seed = scene.seed if seed is None else int(seed)
    intrinsics = scene_intrinsics(int(width), int(height))
    started = time.perf_counter()

    for sub in (*_FRAME_DIRS, "intrinsic"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    _write_intrinsics(out / "intrinsic", intrinsics)

    poses = scene.trajectory(int(num_frames), seed=seed)
    boxes = scene.box_arrays()
    bar = _progress(int(num_frames), progress, name)
    pending: list[concurrent.futures.Future] = []
    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as writer:
        for k, pose in enumerate(poses):
            frame = render_frame(
                scene,
                pose,
                intrinsics,
                rng=np.random.default_rng([seed & 0xFFFFFFFF, 1, k]),
                depth_noise=depth_noise,
                boxes=boxes,
            )
            pending.append(writer.submit(_write_frame, out, f"frame-{k:06d}", frame, pose, jpeg_quality))
            while len(pending) > 3:
                pending.pop(0).result()
            if bar is not None:
                bar.update(1)
        for future in pending:
            future.result()
    if bar is not None:
        bar.close()

    mesh = build_mesh(scene, spacing=mesh_spacing, max_vertices=max_vertices)
    write_ply(out / f"{name}_vh_clean_2.ply", mesh.vertices, mesh.faces, mesh.colors)
    segs = {
        "params": {"synthetic": "one segment per patch (<= 0.4 m) of a box face"},
        "sceneId": name,
        "segIndices": mesh.segment_ids.tolist(),
    }
    (out / f"{name}_vh_clean_2.0.010000.segs.json").write_text(json.dumps(segs))
    groups = []
    for instance_id, info in sorted(scene.instances.items()):
        segments = np.unique(mesh.segment_ids[mesh.instance_ids == instance_id])
        if segments.size == 0:
            continue
        groups.append(
            {"id": instance_id - 1, "objectId": instance_id - 1, "segments": segments.tolist(), "label": info.raw_label}
        )
    aggregation = {
        "sceneId": name,
        "appId": "fmfusion-jax.synth",
        "segGroups": groups,
        "segmentsFile": f"scannet.{name}_vh_clean_2.0.010000.segs.json",
    }
    (out / f"{name}.aggregation.json").write_text(json.dumps(aggregation, indent=1))
    write_labels_tsv(out / LABELS_TSV, scene)
    instances = [
        {
            "instance_id": i,
            "objectId": i - 1,
            "label": info.raw_label,
            "class": info.class_name,
            "nyu40_id": info.nyu40_id,
            "kind": info.kind,
        }
        for i, info in sorted(scene.instances.items())
    ]
    (out / "gt_instances" / "instances.json").write_text(json.dumps(instances, indent=1))
    _write_metadata(out / f"{name}.txt", intrinsics, int(num_frames))
    w, d, h = scene.room_size
    params = {
        "generator": "fmfusion_jax.simulation.procedural",
        "seed": scene.seed,
        "noise_seed": seed,
        "room_size": [w, d, h],
        "num_objects": len(scene.object_ids),
        "num_boxes": len(scene.boxes),
        "num_frames": int(num_frames),
        "image_size": [int(width), int(height)],
        "depth_noise": bool(depth_noise),
        "mesh_vertices": int(mesh.vertices.shape[0]),
        "mesh_spacing": mesh.spacing,
        "seconds": round(time.perf_counter() - started, 2),
    }
    (out / "synthesis.json").write_text(json.dumps(params, indent=1))
    return out


def _clear_previous(out: Path) -> None:
    """Deletes the frame files an earlier run wrote (only files of our names, in our sub-folders)."""
    for sub, suffix in _FRAME_DIRS.items():
        folder = out / sub
        if folder.is_dir():
            for file in folder.glob(f"frame-*{suffix}"):
                file.unlink()


def _progress(total: int, enabled: bool, name: str):
    if not enabled:
        return None
    return tqdm(total=total, desc=f"rendering {name}", unit="frame")


def _write_frame(out: Path, stem: str, frame: RenderedFrame, pose: np.ndarray, jpeg_quality: int) -> None:

    _imwrite(
        out / "color" / f"{stem}.jpg", cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)]
    )
    depth_mm = np.clip(np.round(frame.depth * 1000.0), 0, 65535).astype(np.uint16)
    _imwrite(out / "depth" / f"{stem}.png", depth_mm, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    _imwrite(out / "gt_instances" / f"{stem}.png", frame.instance.astype(np.uint16), [cv2.IMWRITE_PNG_COMPRESSION, 3])
    np.savetxt(out / "pose" / f"{stem}.txt", pose, fmt="%.8f")


def _imwrite(path: Path, image: np.ndarray, params) -> None:

    ok, data = cv2.imencode(path.suffix, image, params)
    if not ok:  # pragma: no cover
        raise OSError(f"{path}: cannot encode the image")
    path.write_bytes(data.tobytes())


def _write_intrinsics(folder: Path, intrinsics) -> None:
    matrix = np.eye(4)
    matrix[:3, :3] = intrinsics.matrix
    for name in ("intrinsic_depth.txt", "intrinsic_color.txt"):
        np.savetxt(folder / name, matrix, fmt="%f")
    w, h = intrinsics.width, intrinsics.height
    (folder / "sensor_shapes.txt").write_text(f"color_width:{w}\ncolor_height:{h}\ndepth_width:{w}\ndepth_height:{h}\n")


def _write_metadata(path: Path, intrinsics, num_frames: int) -> None:
    k = intrinsics
    lines = [
        f"colorHeight = {k.height}",
        f"colorWidth = {k.width}",
        f"depthHeight = {k.height}",
        f"depthWidth = {k.width}",
        f"fx_color = {k.fx:f}",
        f"fx_depth = {k.fx:f}",
        f"fy_color = {k.fy:f}",
        f"fy_depth = {k.fy:f}",
        f"mx_color = {k.cx:f}",
        f"mx_depth = {k.cx:f}",
        f"my_color = {k.cy:f}",
        f"my_depth = {k.cy:f}",
        f"numColorFrames = {num_frames}",
        f"numDepthFrames = {num_frames}",
        "axisAlignment = 1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1",
        "sceneType = Synthetic (fmfusion synth)",
    ]
    path.write_text("\n".join(lines) + "\n")


def write_labels_tsv(path: str | Path, scene: ProceduralScene | None = None) -> None:
    """Writes the raw label -> nyu40 tsv for every raw label the generator knows (`count`: instances in `scene`)."""

    label_sets = load_label_sets()
    nyu40 = label_sets.class_to_nyu40()
    nyu40[CEILING_CLASS] = CEILING_NYU40
    counts: dict[str, int] = {}
    if scene is not None:
        for info in scene.instances.values():
            counts[info.raw_label] = counts.get(info.raw_label, 0) + 1
    rows = ["\t".join(("id", "raw_category", "category", "count", "nyu40id", "nyu40class"))]
    for row_id, (raw, class_name) in enumerate(RAW_LABELS.items(), start=1):
        nyu = nyu40[class_name]
        rows.append("\t".join((str(row_id), raw, raw, str(counts.get(raw, 0)), str(nyu), NYU40_CLASS_NAMES[nyu])))
    Path(path).write_text("\n".join(rows) + "\n")


def write_ply(path: str | Path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> None:
    """Binary little-endian PLY like ScanNet's: float x y z, uchar red green blue alpha, uchar-int face lists."""
    vertices = np.asarray(vertices, np.float32).reshape(-1, 3)
    faces = np.asarray(faces, np.int32).reshape(-1, 3)
    colors = np.asarray(colors, np.uint8).reshape(-1, 3)
    header = (
        f"ply\nformat binary_little_endian 1.0\ncomment fmfusion-jax synth\nelement vertex {len(vertices)}\n"
        "property float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\n"
        f"property uchar blue\nproperty uchar alpha\nelement face {len(faces)}\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    vertex_type = np.dtype([("xyz", "<f4", 3), ("rgba", "u1", 4)])
    vertex_data = np.empty(len(vertices), vertex_type)
    vertex_data["xyz"] = vertices
    vertex_data["rgba"][:, :3] = colors
    vertex_data["rgba"][:, 3] = 255
    face_type = np.dtype([("n", "u1"), ("v", "<i4", 3)])
    face_data = np.empty(len(faces), face_type)
    face_data["n"] = 3
    face_data["v"] = faces
    with open(path, "wb") as file:
        file.write(header.encode("ascii"))
        file.write(vertex_data.tobytes())
        file.write(face_data.tobytes())
