"""Open3D peers of the fusion loop for `fmfusion bench`: what a CPU design with one volume per instance costs.

Two peers, both on Open3D (open3d-cpu==0.19.0, the optional `bench` extra), fed the same frames and
detections as the JAX engine:

- `Open3DInstancePipeline`: the design of the authors' Python pipeline, written here from its description.
  One global legacy `ScalableTSDFVolume` integrates every frame; every instance owns its own
  `ScalableTSDFVolume`, fed only the depth under its detections. Per detection frame (the `STAGES`):

    tsdf          the frame into the global volume (every frame, detections or not).
    projection    each instance's surface points (extracted from its volumes, cached until a volume changes)
                  are projected into the frame and kept where the frame's depth agrees (visible); the hit
                  pixels, closed over the gaps between neighbouring points, are its projected mask.
    association   the detections filtered as our loop does (`pack_detections`: min mask pixels, no scored
                  label, the `max_detections` best scores; then each mask's depth kept between its 10th/90th
                  percentiles), scored against the instances in view (`|m ∩ r| / |r|` or IoU), matched
                  greedily by score, one detection per instance; in-view instances left unmatched are missed.
    label_fusion  the engine's update on the NumPy side (`engine.label_fusion`): additive `evidence += s @ L`
                  (or bayes); unmatched detections open new instances.
    integration   each detection's masked depth (0 outside its filtered mask) into its instance's volume.
    merge         (refinement, every `merge_every` detection frames) pairs with `p_a . p_b > merge_similarity`
                  and more than `merge_overlap` of the smaller one's voxels inside the larger one inflated 2x
                  are merged; instances missed `remove_missed` times while smaller than `remove_min_voxels`
                  voxels are removed. It starts by re-extracting the points of the instances this frame
                  integrated (most of its time; the next projection reuses them, and with refinement off that
                  cost moves to projection).

  Differences from the authors' pipeline, chosen to keep the cost representative and the code simple:
  inflation is a 2x coarser voxel grid (the engine's rule: a voxel is inside when its 2x2x2 cell holds one of
  the larger instance's voxels); Open3D volumes cannot be merged cheaply, so a merged instance keeps the list
  of its members' volumes (later detections go into the first; its points are the union), and projection and
  extraction keep paying for every volume, as a re-integration would; no geometry fusion, no export. Unlike
  our engine it works on every pixel (no `association.pixel_stride`) and leaves overlapping masks overlapping.

  A peer for speed, but a working pipeline: on a clean sequence it finds each object once, on the object,
  with its class (tests/test_open3d_peer.py).

- `VoxelBlockGridTSDF`: Open3D's tensor `VoxelBlockGrid` integration alone (depth and colour), the fastest
  CPU TSDF we know: the floor under any CPU fusion loop.

Open3D is imported lazily, so this module imports without it; `open3d_unavailable_reason` says why the peers
cannot run and how to fix it. Open3D's kernels run on OpenMP threads (`OMP_NUM_THREADS`, read when open3d is
first imported); on an oversubscribed machine they stall for up to seconds, so fix the count for timings.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import cv2
import numpy as np

from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.engine.detections import pack_detections
from fmfusion_jax.engine.label_fusion import DEFAULT_BAYES_EPS
from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import LabelSets, load_label_sets
from fmfusion_jax.types import CameraIntrinsics, FrameDetections, RGBDFrame

#: Keys of `Open3DInstancePipeline.add_frame`'s timings, in the order the stages run.
STAGES = ("tsdf", "projection", "association", "label_fusion", "integration", "merge")

INSTALL_HINT = (
    'pip install -e ".[bench]" (open3d-cpu==0.19.0); on Debian/Ubuntu its library also needs apt-get install libusb-1.0-0'
)

#: A projected instance point is visible when the frame's depth at its pixel is within this of its own depth (m).
VISIBILITY_TOLERANCE = 0.05


def class_distribution(evidence: np.ndarray, mode: str, prior_weight: float = 1.0) -> np.ndarray:
    """`(N, C)` class distributions of label evidence `(N, C)`, in NumPy: softmax of the log-evidence for
    `bayes`, the evidence plus a uniform prior of `prior_weight`, normalized, for `additive` (the engine's
    `label_fusion` rules, so that the peer fuses labels as the paper does). The peer's own NumPy label fusion,
    part of its algorithm (merge similarity and export); the tests check the engine against their own oracle
    (`tests/oracles`), never against this."""
    e = np.asarray(evidence, np.float64)
    c = e.shape[1]
    if mode == "bayes":
        x = np.exp(e - e.max(1, keepdims=True))
        return x / x.sum(1, keepdims=True)
    num = e + prior_weight / c
    total = num.sum(1, keepdims=True)
    return np.where(total > 0, num / np.where(total > 0, total, 1), 1.0 / c)


def open3d_unavailable_reason() -> str | None:
    """None when open3d 0.19 imports; otherwise one line saying why not and how to fix it."""
    try:
        import open3d
    except Exception as error:  # ImportError, or OSError from a missing shared library (libusb)
        detail = " ".join(str(error).split()) or type(error).__name__
        return f"open3d is not importable ({detail}): {INSTALL_HINT}"
    version = str(getattr(open3d, "__version__", "unknown"))
    if not version.startswith("0.19."):
        return f"open3d {version} is installed, the Open3D peer needs 0.19.0: {INSTALL_HINT}"
    return None


def _open3d() -> Any:
    """The open3d module, quiet (errors only); a `UserError` naming the fix when it cannot be used."""
    reason = open3d_unavailable_reason()
    if reason is not None:
        raise UserError(reason)
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


def _elapsed_ms(start: float) -> float:
    return (time.perf_counter() - start) * 1e3


# ----------------------------------------------------------------------------------------------- VoxelBlockGrid


class VoxelBlockGridTSDF:
    """Open3D's tensor `VoxelBlockGrid` TSDF (tsdf, weight, colour per voxel; 8^3-voxel blocks), integration only.

    Frames go in as uint16 millimetres with uint8 colour: the sensor's own format (ScanNet's depth PNGs) and
    the pair Open3D's CPU kernel takes without converting colour to float; the conversion from our float
    metres happens before the timed call, as the JAX loop's host-to-device copy does.
    """

    def __init__(
        self,
        voxel_size: float,
        sdf_trunc: float,
        depth_max: float,
        intrinsics: CameraIntrinsics,
        block_count: int = 50000,
        device: str = "CPU:0",
    ):
        o3d = _open3d()
        self._o3d = o3d
        self._device = o3d.core.Device(device)
        self.voxel_size = float(voxel_size)
        self.depth_max = float(depth_max)
        self.trunc_voxel_multiplier = float(sdf_trunc) / float(voxel_size)
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"),
            attr_dtypes=(o3d.core.float32, o3d.core.float32, o3d.core.float32),
            attr_channels=((1), (1), (3)),
            voxel_size=self.voxel_size,
            block_resolution=8,
            block_count=int(block_count),
            device=self._device,
        )
        self._intrinsic = o3d.core.Tensor(intrinsics.matrix, o3d.core.float64)

    def integrate(self, frame: RGBDFrame) -> float:
        """Integrates a frame's depth and colour; returns the wall ms of block selection + integration."""
        o3d = self._o3d
        depth_mm = np.round(np.clip(frame.depth, 0.0, 65.535) * 1000.0).astype(np.uint16)
        depth = o3d.t.geometry.Image(o3d.core.Tensor.from_numpy(depth_mm)).to(self._device)
        color = o3d.t.geometry.Image(o3d.core.Tensor.from_numpy(np.ascontiguousarray(frame.color, np.uint8)))
        color = color.to(self._device)
        T_camera_world = o3d.core.Tensor(np.linalg.inv(frame.T_world_camera), o3d.core.float64)
        start = time.perf_counter()
        blocks = self.grid.compute_unique_block_coordinates(
            depth, self._intrinsic, T_camera_world, 1000.0, self.depth_max, self.trunc_voxel_multiplier
        )
        self.grid.integrate(
            blocks,
            depth,
            color,
            self._intrinsic,
            self._intrinsic,
            T_camera_world,
            1000.0,
            self.depth_max,
            self.trunc_voxel_multiplier,
        )
        return _elapsed_ms(start)

    def extract_points(self, weight_threshold: float = 0.0) -> np.ndarray:
        """`(P, 3)` float32 zero-crossing points of voxels with weight above `weight_threshold`."""
        cloud = self.grid.extract_point_cloud(weight_threshold)
        return cloud.point.positions.cpu().numpy().astype(np.float32).reshape(-1, 3)

    def extract_point_count(self, weight_threshold: float = 0.0) -> int:
        """Number of surface points (a sanity check that integration did something)."""
        return len(self.extract_points(weight_threshold))


# ----------------------------------------------------------------------------------------------- instances


@dataclasses.dataclass
class _Instance:
    """One instance: its volumes, label evidence and counters, and its surface points (cached).

    Attributes:
      volumes: the `ScalableTSDFVolume`s holding its geometry; more than one after merges (the first takes
        new detections).
      evidence: `(C,)` float64 label evidence (`engine.label_fusion` meaning; zeros = prior).
      observations: detections fused into it.
      missed: detection frames it was in view but matched no detection.
      points: `(P, 3)` float64 world points of all its volumes, or None when a volume changed since.
      voxels: sorted unique int64 keys of the voxels holding `points` (`_voxel_keys`).
      cells: sorted unique int64 keys of the 2x coarser cells holding them (its inflated volume).
    """

    volumes: list
    evidence: np.ndarray
    observations: int = 0
    missed: int = 0
    points: np.ndarray | None = None
    voxels: np.ndarray | None = None
    cells: np.ndarray | None = None

    @property
    def voxel_count(self) -> int:
        return 0 if self.voxels is None else len(self.voxels)


@dataclasses.dataclass
class _Projection:
    """An instance's projected mask in one frame, as a crop of the image.

    Attributes:
      rows, cols: the crop's slices of the image.
      mask: `(h, w)` bool projected pixels inside the crop.
      pixels: number of projected pixels.
    """

    rows: slice
    cols: slice
    mask: np.ndarray
    pixels: int


_KEY_OFFSET = 1 << 20  # voxel coordinates within +-2^20 (16 km at 1.5 cm) pack into 21 bits each


def _voxel_keys(points: np.ndarray, size: float) -> np.ndarray:
    """Sorted unique int64 keys of the `size`-cells holding `(P, 3)` points."""
    g = np.floor(points / size).astype(np.int64) + _KEY_OFFSET
    return np.unique((g[:, 0] << 42) | (g[:, 1] << 21) | g[:, 2])


def _coarse_keys(keys: np.ndarray) -> np.ndarray:
    """Keys of the 2x coarser cells holding the voxels of `keys` (same packing, unsorted, repeated)."""
    low = (1 << 21) - 1
    cells = [((g - _KEY_OFFSET) >> 1) + _KEY_OFFSET for g in (keys >> 42, (keys >> 21) & low, keys & low)]
    return (cells[0] << 42) | (cells[1] << 21) | cells[2]


def _filter_mask_depth(masks: np.ndarray, depth: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """`(N, H, W)` masks keeping only pixels with depth, between each mask's `lo`/`hi` depth quantiles."""
    out = masks & (depth > 0)[None]
    for mask in out:
        rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
        if not rows.size:
            continue
        box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))  # work on the mask's bounding box
        crop, d = mask[box], depth[box]
        q_lo, q_hi = np.quantile(d[crop], (lo, hi))
        crop &= (d >= q_lo) & (d <= q_hi)
    return out


def _greedy_match(scores: np.ndarray, threshold: float) -> np.ndarray:
    """`(N,)` column matched to each row of `(N, K)` scores, or -1: best pairs above `threshold` first,
    each row and column used once (ties: lower row, then lower column)."""
    n, k = scores.shape
    match = np.full(n, -1, np.int64)
    if n == 0 or k == 0:
        return match
    taken = np.zeros(k, bool)
    flat = np.argsort(-scores, axis=None, kind="stable")
    for i, j in zip(*np.unravel_index(flat, scores.shape)):
        if scores[i, j] <= threshold:
            break
        if match[i] < 0 and not taken[j]:
            match[i], taken[j] = j, True
    return match


def _union_groups(pairs: list[tuple[int, int]]) -> list[list[int]]:
    """Connected components (size >= 2) of the graph with these edges."""
    parent: dict[int, int] = {}

    def find(x: int) -> int:
        parent.setdefault(x, x)
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for a, b in pairs:
        parent[find(a)] = find(b)
    groups: dict[int, list[int]] = {}
    for x in parent:
        groups.setdefault(find(x), []).append(x)
    return [g for g in groups.values() if len(g) > 1]


class Open3DInstancePipeline:
    """The authors' design on Open3D: a global TSDF volume plus one TSDF volume per instance (module docstring).

    `add_frame` per frame (the caller applies the detection schedule, as with `mapping.MapBuilder`);
    `instance_points` for sanity checks.
    """

    def __init__(
        self, config: PipelineConfig, intrinsics: CameraIntrinsics, likelihood: np.ndarray, label_sets: LabelSets | None = None
    ):
        o3d = _open3d()
        self._o3d = o3d
        self.config = config
        self.intrinsics = intrinsics
        self.label_sets = label_sets or load_label_sets()
        self.likelihood = np.asarray(likelihood, np.float64)
        self.mode = config.label_fusion.mode
        self._camera = o3d.camera.PinholeCameraIntrinsic(
            intrinsics.width, intrinsics.height, intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
        )
        self.global_volume = self._new_volume()
        self.instances: dict[int, _Instance] = {}
        self._next_id = 0
        self.detection_frames = 0
        self.counters = {"created": 0, "matched": 0, "merged": 0, "removed": 0, "detections": 0}

    # -------------------------------------------------------------------------------------------- public

    @property
    def num_instances(self) -> int:
        return len(self.instances)

    def add_frame(self, frame: RGBDFrame, detections: FrameDetections | None) -> dict[str, float]:
        """Integrates a frame and, when `detections` is given, fuses them; wall ms per stage that ran.

        The frame's conversion to Open3D images happens before the timers (the JAX loop's host-to-device
        copy is outside its timers too); everything else is inside one of `STAGES`.
        """
        o3d = self._o3d
        shape = (self.intrinsics.height, self.intrinsics.width)
        if frame.depth.shape != shape or frame.color.shape[:2] != shape:
            raise UserError(
                f"{frame.name}: depth {frame.depth.shape} / colour {frame.color.shape[:2]} differ from "
                f"the camera's image size {shape}"
            )
        if detections is not None and detections.image_shape != shape:
            raise UserError(f"{detections.frame_name}: detection masks are {detections.image_shape}, frames {shape}")
        depth = np.ascontiguousarray(frame.depth, np.float32)
        color = o3d.geometry.Image(np.ascontiguousarray(frame.color, np.uint8))
        T_camera_world = np.linalg.inv(np.asarray(frame.T_world_camera, np.float64))
        ms: dict[str, float] = {}

        start = time.perf_counter()
        self._integrate(self.global_volume, color, depth, T_camera_world)
        ms["tsdf"] = _elapsed_ms(start)
        if detections is None:
            return ms

        start = time.perf_counter()
        ids = [i for i, inst in self.instances.items() if inst.volumes]
        projections = {i: self._project(self.instances[i], depth, frame.T_world_camera) for i in ids}
        ms["projection"] = _elapsed_ms(start)

        start = time.perf_counter()
        masks, scores = self._filter_detections(detections, depth)
        visible = {
            i: projection
            for i, projection in projections.items()
            if projection is not None and projection.pixels > self.config.association.min_projected_pixels
        }  # in the order of ids
        in_view = list(visible)
        match = self._associate(masks, list(visible.values()))
        target = np.array([in_view[j] if j >= 0 else -1 for j in match], np.int64)
        matched = set(target[target >= 0].tolist())
        for i in in_view:
            if i not in matched:
                self.instances[i].missed += 1
        ms["association"] = _elapsed_ms(start)

        start = time.perf_counter()
        target = self._fuse_labels(scores, target)
        ms["label_fusion"] = _elapsed_ms(start)

        start = time.perf_counter()
        for mask, i in zip(masks, target):
            instance = self.instances[int(i)]
            if not instance.volumes:
                instance.volumes.append(self._new_volume())
            self._integrate(instance.volumes[0], color, np.where(mask, depth, 0.0).astype(np.float32), T_camera_world)
            instance.points = None  # re-extracted when next needed
        ms["integration"] = _elapsed_ms(start)

        self.detection_frames += 1
        self.counters["detections"] += len(masks)
        self.counters["matched"] += len(matched)
        refinement = self.config.refinement
        if refinement.enabled and self.detection_frames % refinement.merge_every == 0:
            start = time.perf_counter()
            self._refine()
            ms["merge"] = _elapsed_ms(start)
        return ms

    def instance_points(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per live instance: `(P, 3)` float32 world points and its `(C,)` float32 class distribution."""
        out = []
        for instance in self.instances.values():
            self._refresh(instance)
            assert instance.points is not None  # refreshed
            dist = class_distribution(instance.evidence[None], self.mode)[0]
            out.append((instance.points.astype(np.float32), dist.astype(np.float32)))
        return out

    def global_points(self) -> np.ndarray:
        """`(P, 3)` float32 surface points of the global volume."""
        return np.asarray(self.global_volume.extract_point_cloud().points, np.float32).reshape(-1, 3)

    # -------------------------------------------------------------------------------------------- volumes

    def _new_volume(self) -> Any:
        integration = self._o3d.pipelines.integration
        return integration.ScalableTSDFVolume(
            voxel_length=self.config.tsdf.voxel_size,
            sdf_trunc=self.config.tsdf.sdf_trunc,
            color_type=integration.TSDFVolumeColorType.RGB8,
        )

    def _integrate(self, volume: Any, color: Any, depth: np.ndarray, T_camera_world: np.ndarray) -> None:
        """`depth` `(H, W)` float32 metres (0: skip) with the frame's colour into `volume`."""
        o3d = self._o3d
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            color,
            o3d.geometry.Image(depth),
            depth_scale=1.0,
            depth_trunc=self.config.dataset.depth_max,
            convert_rgb_to_intensity=False,
        )
        volume.integrate(rgbd, self._camera, T_camera_world)

    def _refresh(self, instance: _Instance) -> None:
        """Re-extracts the instance's points (and voxel keys) if a volume changed since the last time."""
        if instance.points is not None:
            return
        clouds = [np.asarray(v.extract_point_cloud().points, np.float64).reshape(-1, 3) for v in instance.volumes]
        self._set_points(instance, np.concatenate(clouds) if clouds else np.zeros((0, 3)))

    def _set_points(self, instance: _Instance, points: np.ndarray) -> None:
        size = self.config.tsdf.voxel_size
        instance.points = points
        instance.voxels = _voxel_keys(points, size)
        instance.cells = np.unique(_coarse_keys(instance.voxels))

    # -------------------------------------------------------------------------------------------- stages

    def _project(self, instance: _Instance, depth: np.ndarray, T_world_camera: np.ndarray) -> _Projection | None:
        """The instance's visible projected mask in this frame (None when nothing of it is visible).

        Points project to single pixels, about `voxel_size * fx / z` apart; a morphological closing with a
        kernel of that spacing fills the gaps between them without growing the mask's outline.
        """
        self._refresh(instance)
        assert instance.points is not None  # refreshed
        k = self.intrinsics
        T = np.asarray(T_world_camera, np.float64)
        p = (instance.points - T[:3, 3]) @ T[:3, :3]  # x_camera = R^T (x_world - t)
        z = p[:, 2]
        front = z > 1e-6
        p, z = p[front], z[front]
        u = np.rint(k.fx * p[:, 0] / z + k.cx).astype(np.int64)
        v = np.rint(k.fy * p[:, 1] / z + k.cy).astype(np.int64)
        inside = (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
        u, v, z = u[inside], v[inside], z[inside]
        d = depth[v, u]
        visible = (d > 0) & (np.abs(d - z) < VISIBILITY_TOLERANCE)
        if not visible.any():
            return None
        u, v, z = u[visible], v[visible], z[visible]
        r = max(1, math.ceil(0.5 * self.config.tsdf.voxel_size * max(k.fx, k.fy) / float(np.median(z))))
        pad = 2 * r  # room for the closing's dilation to shrink back at the crop border
        v0, u0 = int(v.min()) - pad, int(u.min()) - pad
        crop: np.ndarray = np.zeros((int(v.max()) - v0 + 1 + pad, int(u.max()) - u0 + 1 + pad), np.uint8)
        crop[v - v0, u - u0] = 1
        crop = cv2.morphologyEx(crop, cv2.MORPH_CLOSE, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
        r0, c0 = max(v0, 0), max(u0, 0)
        r1, c1 = min(v0 + crop.shape[0], k.height), min(u0 + crop.shape[1], k.width)
        mask = crop[r0 - v0 : r1 - v0, c0 - u0 : c1 - u0].astype(bool)
        return _Projection(slice(r0, r1), slice(c0, c1), mask, int(np.count_nonzero(mask)))

    def _filter_detections(self, detections: FrameDetections, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`(N, H, W)` bool filtered masks and `(N, O)` float32 label scores of the kept detections."""
        cfg = self.config.detections
        batch = pack_detections(detections, self.label_sets.open_labels, cfg.max_detections, cfg.min_mask_pixels)
        assert batch.masks is not None  # packed as a mask stack (the default)
        n = int(np.count_nonzero(batch.valid))  # packed rows: the kept detections first
        lo, hi = cfg.depth_percentiles
        return _filter_mask_depth(batch.masks[:n], depth, lo, hi), batch.label_scores[:n]

    def _associate(self, masks: np.ndarray, projections: list[_Projection]) -> np.ndarray:
        """`(N,)` index into `projections` matched to each detection, or -1 (module docstring)."""
        scores = np.zeros((len(masks), len(projections)))
        mask_pixels = masks.reshape(len(masks), -1).sum(1)
        for j, proj in enumerate(projections):
            inter = np.count_nonzero(masks[:, proj.rows, proj.cols] & proj.mask[None], axis=(1, 2))
            if self.config.association.metric == "iou":
                union = mask_pixels + proj.pixels - inter
                scores[:, j] = inter / np.maximum(union, 1)
            else:  # projection_overlap
                scores[:, j] = inter / max(proj.pixels, 1)
        return _greedy_match(scores, self.config.association.threshold)

    def _fuse_labels(self, scores: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Adds each detection's measurement to its instance, opening instances for the unmatched (-1);
        returns the `(N,)` instance id of every detection."""
        if self.mode == "bayes":
            measurement = (scores > 0).astype(np.float64) @ np.log(np.maximum(self.likelihood, DEFAULT_BAYES_EPS))
        else:
            measurement = scores.astype(np.float64) @ self.likelihood
        target = target.copy()
        num_classes = self.likelihood.shape[1]
        for n in range(len(target)):
            if target[n] < 0:
                target[n] = self._next_id
                self.instances[self._next_id] = _Instance(volumes=[], evidence=np.zeros(num_classes))
                self._next_id += 1
                self.counters["created"] += 1
            instance = self.instances[int(target[n])]
            instance.evidence = instance.evidence + measurement[n]
            if self.mode == "bayes":
                instance.evidence -= instance.evidence.max()
            instance.observations += 1
        return target

    def _refine(self) -> None:
        """Online merge of overlapping, semantically similar instances, then removal of missed small ones."""
        refinement = self.config.refinement
        ids = list(self.instances)
        for i in ids:
            self._refresh(self.instances[i])
        ids = [i for i in ids if self.instances[i].voxel_count > 0]
        if len(ids) > 1:
            dist = class_distribution(np.stack([self.instances[i].evidence for i in ids]), self.mode)
            similarity = dist @ dist.T
            size = self.config.tsdf.voxel_size
            boxes = {}
            for i in ids:
                points = self.instances[i].points
                assert points is not None  # refreshed above
                boxes[i] = (points.min(0) - 2 * size, points.max(0) + 2 * size)
            pairs = []
            for a, b in np.argwhere(np.triu(similarity > refinement.merge_similarity, 1)):
                ia, ib = ids[a], ids[b]
                if np.any(boxes[ia][1] < boxes[ib][0]) or np.any(boxes[ib][1] < boxes[ia][0]):
                    continue  # bounding boxes apart: no voxel of one can be inside the other
                big = self._larger(ia, ib)
                small = ib if big == ia else ia
                small_voxels, big_cells = self.instances[small].voxels, self.instances[big].cells
                assert small_voxels is not None and big_cells is not None  # refreshed above
                ratio = np.count_nonzero(np.isin(_coarse_keys(small_voxels), big_cells)) / self.instances[small].voxel_count
                if ratio > refinement.merge_overlap:
                    pairs.append((ia, ib))
            for group in _union_groups(pairs):
                self._merge(group)
        for i in list(self.instances):
            instance = self.instances[i]
            if instance.missed >= refinement.remove_missed and instance.voxel_count < refinement.remove_min_voxels:
                del self.instances[i]
                self.counters["removed"] += 1

    def _larger(self, a: int, b: int) -> int:
        """The larger of two instances by voxel count (ties: the older)."""
        return a if (self.instances[a].voxel_count, -a) > (self.instances[b].voxel_count, -b) else b

    def _merge(self, group: list[int]) -> None:
        """Folds a group into its largest member: volumes, points, evidence and counters (module docstring)."""
        keep = group[0]
        for i in group[1:]:
            keep = self._larger(keep, i)
        target = self.instances[keep]
        for i in group:
            if i == keep:
                continue
            other = self.instances.pop(i)
            target.volumes.extend(other.volumes)
            target.evidence = target.evidence + other.evidence
            if self.mode == "bayes":
                target.evidence -= target.evidence.max()
            target.observations += other.observations
            target.missed = min(target.missed, other.missed)
            self._set_points(target, np.concatenate([target.points, other.points]))
            self.counters["merged"] += 1


__all__ = [
    "STAGES",
    "INSTALL_HINT",
    "VISIBILITY_TOLERANCE",
    "open3d_unavailable_reason",
    "Open3DInstancePipeline",
    "VoxelBlockGridTSDF",
]
