"""A live 3D view of a fusion in Rerun (`rerun-sdk`, the `viewer` extra): `fmfusion run --viewer rerun` opens a
viewer, `--viewer-save FILE.rrd` records one (headless; open it later with `rerun FILE.rrd`).

Logged per frame: the camera (pose and pinhole) with its colour and depth images and the frame's detections
(a segmentation image and labelled 2D boxes); every `map_every` frames and at the end: the global TSDF's mesh
and the instances' oriented boxes, labelled by class. Entities: `world/camera`, `world/camera/image/{rgb,
depth,detections,boxes}`, `world/mesh`, `world/instances`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fmfusion_jax.errors import UserError
from fmfusion_jax.types import FrameDetections, RGBDFrame


class RerunView:
    """Logs a fusion to a Rerun recording (an observer of `run.scene_fusion.SceneFusion`)."""

    def __init__(self, save: str | Path | None = None, spawn: bool = False, map_every: int = 30, image_stride: int = 2):
        try:
            import rerun as rr
        except ImportError:
            raise UserError("the live view needs rerun-sdk: pip install -e '.[viewer]'") from None
        if not (save or spawn):
            raise UserError("RerunView: give save=FILE.rrd or spawn=True")
        self.rr = rr
        self.map_every = max(1, int(map_every))
        self.image_stride = max(1, int(image_stride))
        self.recording = rr.RecordingStream("fmfusion")
        if save:
            self.recording.save(str(save))
        else:
            self.recording.spawn()
        self.recording.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    def __call__(self, position: int, frame: RGBDFrame, detections: FrameDetections | None, mapper: Any) -> None:
        rr, rec, s = self.rr, self.recording, self.image_stride
        rec.set_time("frame", sequence=position)
        T = np.asarray(frame.T_world_camera, np.float64)
        rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        k = frame.intrinsics
        rec.log(
            "world/camera/image",
            rr.Pinhole(
                focal_length=[k.fx / s, k.fy / s],
                principal_point=[k.cx / s, k.cy / s],
                resolution=[k.width // s + (k.width % s > 0), k.height // s + (k.height % s > 0)],
            ),
        )
        rec.log("world/camera/image/rgb", rr.Image(np.ascontiguousarray(frame.color[::s, ::s])))
        rec.log("world/camera/image/depth", rr.DepthImage(np.ascontiguousarray(frame.depth[::s, ::s]), meter=1.0))
        if detections is not None and detections.num_detections:
            masks = np.asarray(detections.masks, bool)[:, ::s, ::s]
            order = np.argsort(-masks.reshape(len(masks), -1).sum(axis=1))  # large first, small ones on top
            segmentation = np.zeros(masks.shape[1:], np.uint16)
            for k_det in order:
                segmentation[masks[k_det]] = k_det + 1
            labels = [max(scores, key=lambda label: scores[label]) if scores else "?" for scores in detections.labels]
            rec.log("world/camera/image/detections", rr.SegmentationImage(segmentation))
            rec.log(
                "world/camera/image/boxes",
                rr.Boxes2D(array=np.asarray(detections.boxes, np.float32) / s, array_format=rr.Box2DFormat.XYXY, labels=labels),
            )
        if position % self.map_every == 0:
            self.log_map(mapper)

    def log_map(self, mapper: Any) -> None:
        """The map as it stands: the mesh and the instances' boxes."""

        rr, rec = self.rr, self.recording
        mesh = mapper.extract_mesh()
        if len(mesh.faces):
            colors = np.asarray(mesh.visual.vertex_colors)[:, :3] if hasattr(mesh.visual, "vertex_colors") else None
            rec.log(
                "world/mesh",
                rr.Mesh3D(
                    vertex_positions=np.asarray(mesh.vertices, np.float32),
                    triangle_indices=np.asarray(mesh.faces, np.uint32),
                    vertex_colors=colors,
                ),
            )
        instances = mapper.instances()
        if instances:
            from fmfusion_jax.io.map_outputs import oriented_box  # lazy: scipy's KD-tree, only with a viewer

            boxes = [oriented_box(inst.points) for inst in instances]
            names = mapper.label_sets.class_names
            rec.log(
                "world/instances",
                rr.Boxes3D(
                    centers=[b["center"] for b in boxes],
                    half_sizes=[np.asarray(b["extent"]) / 2 for b in boxes],
                    rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1], radians=b["yaw"]) for b in boxes],
                    labels=[f"{names[inst.class_index]} {inst.instance_id}" for inst in instances],
                ),
            )

    def close(self, mapper: Any | None = None) -> None:
        """Logs the final map (when given) and flushes the recording."""
        if mapper is not None:
            self.log_map(mapper)
        self.recording.flush()
