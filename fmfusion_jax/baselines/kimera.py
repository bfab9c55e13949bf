"""Kimera-style baseline: closed-set labels fused per voxel, instances formed afterwards by Cluster-All.

The paper's main comparison (Sec. V, Table I, "G-SAM & Kimera"): the same open-set detections fed to a
traditional semantic mapper. Each detection becomes one closed-set label by the hard association of its
highest-scoring open-set label (Appendix A: every open label belongs to one NYUv2 class, the 0.9 entry of
its row of `configs/labels/likelihood_manual.csv`), and that label is fused into the voxels its pixels
observe, with no notion of instances. Instances are formed only at the end, by clustering adjacent voxels
of the same label ("Cluster-All", Douillard et al. 2011, as the paper does).

**Semantic update** (the one of Kimera-Semantics, Rosinol et al. 2020): every voxel holds a distribution
over the C classes, uniform at first. A measurement z of a voxel whose true class is c has likelihood

    p(z | c) = 0.9 if z == c else 0.1 / (C - 1)

and updates the voxel's log-probabilities by Bayes' rule: log p(c) += log p(z | c), then renormalise.
The detector's score is ignored, as in Kimera (the paper's probabilistic label fusion is what improves on
this). Because the model is fixed, the posterior depends only on how often each class was measured,
log p(c) = sum_z n_z log p(z | c) + const, so the mapper keeps sparse per-voxel measurement counts on the
host and evaluates the posterior once at the end (`log_posterior_from_counts`; the tests check it against
the sequential update `bayes_update`).

**Which voxels a pixel updates**: Kimera-Semantics updates the voxels its ray crosses near the surface
(the TSDF truncation band); only voxels near the surface are exported, so here a pixel updates the voxels
at -1, 0 and +1 voxel along its ray from its depth point. In the spirit of Kimera's merged integrator
(which bundles the points falling into one voxel into a single ray), a voxel gets at most one measurement
per class and frame, so its evidence does not grow with the number of pixels it covers (i.e. with its
closeness to the camera).

**Same inputs as FM-Fusion**: the global TSDF is the engine's (`step.integrate_frame` on every frame, via
`MapBuilder` without detections); detections are read on the same frames, with the same minimum mask
size, the same rule for overlapping masks (the smallest wins a pixel), the same per-mask depth-percentile
filter (`engine.detections`) and the same pixel stride.

**Export**: the voxels on the global surface (TSDF weight >= `export.min_weight`, |sdf| <= one voxel)
that received a measurement, labelled by their posterior's argmax; Cluster-All joins 26-adjacent voxels
of one label into an instance (distribution: its voxels' mean posterior, so its confidence is their mean
max probability); then FM-Fusion's export rules (`instances.postprocess_instances`: fewer than
`export.min_points` voxels dropped, the shower-curtain rule, floors merged). The result is a list of
`MapInstance`, so the exporters and the benchmark scoring are those of FM-Fusion's map.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import time
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from tqdm import tqdm

from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.detections import batch_pixel_image, filter_detection_depth
from fmfusion_jax.engine.state import voxel_offsets
from fmfusion_jax.instances import MapInstance, postprocess_instances
from fmfusion_jax.labels import LabelSets, load_label_sets, load_likelihood
from fmfusion_jax.mapping.builder import MapBuilder
from fmfusion_jax.mapping.engine_configs import build_map_config
from fmfusion_jax.mapping.schedule import scheduled_detections
from fmfusion_jax.types import FrameDetections, RGBDFrame

if TYPE_CHECKING:
    from fmfusion_jax.mapping.builder import FusionResult

log = logging.getLogger(__name__)

#: Kimera's probability that a measured label is the voxel's true class.
CORRECT_MEASUREMENT_PROBABILITY = 0.9
#: Voxels (offsets along each pixel's ray from its depth point, in voxels) that a pixel's label updates.
RAY_OFFSETS_VOXELS = (-1.0, 0.0, 1.0)
#: One of each pair of opposite offsets of the 26-neighbourhood (13), so each adjacent pair is linked once.
HALF_NEIGHBOURHOOD = np.array([d for d in itertools.product((-1, 0, 1), repeat=3) if d > (0, 0, 0)], np.int64)
#: Pending per-frame measurements are merged into the running counts beyond this many entries (bounds memory).
_CONSOLIDATE_ENTRIES = 4_000_000


# --------------------------------------------------------------------------------------------------
# Labels and the semantic update.


def hard_association(manual_likelihood: np.ndarray) -> np.ndarray:
    """int64[O]: the closed-set class of each open-set label: the argmax of its row of the manual
    likelihood `(O, C)`, which holds 0.9 at the hard-associated class and 0.1 elsewhere."""
    return np.argmax(np.asarray(manual_likelihood), axis=1).astype(np.int64)


def detection_classes(label_scores: np.ndarray, valid: np.ndarray, hard_class: np.ndarray) -> np.ndarray:
    """int64[N]: the closed-set class of each detection, -1 for invalid rows.

    Args:
      label_scores: `(N, O)` score of each open-set label (0 = not measured).
      valid: `(N,)` bool.
      hard_class: `(O,)` `hard_association`.

    A detection takes the class of its highest-scoring open label (ties: the earlier label).
    """
    best = np.argmax(np.asarray(label_scores), axis=1)
    return np.where(np.asarray(valid, bool), np.asarray(hard_class)[best], -1).astype(np.int64)


def measurement_log_likelihood(num_classes: int, p_correct: float = CORRECT_MEASUREMENT_PROBABILITY) -> np.ndarray:
    """float64[C, C]: log p(z | c), rows the measured class z, columns the true class c: log `p_correct` on
    the diagonal, log `(1 - p_correct) / (C - 1)` elsewhere (each column sums to 1 in probability)."""
    off = (1.0 - p_correct) / (num_classes - 1)
    matrix = np.full((num_classes, num_classes), off)
    np.fill_diagonal(matrix, p_correct)
    return np.log(matrix)


def _normalize_log(logits: np.ndarray) -> np.ndarray:
    top = logits.max(axis=1, keepdims=True)
    return logits - (top + np.log(np.exp(logits - top).sum(axis=1, keepdims=True)))


def bayes_update(log_probs: np.ndarray, measured: np.ndarray, log_likelihood: np.ndarray) -> np.ndarray:
    """One Bayesian update per voxel: `(N, C)` normalized log-probabilities, `(N,)` measured classes, the
    `(C, C)` `measurement_log_likelihood` -> `(N, C)` normalized log posterior."""
    return _normalize_log(np.asarray(log_probs, np.float64) + log_likelihood[np.asarray(measured)])


def log_posterior_from_counts(counts: np.ndarray, log_likelihood: np.ndarray, log_prior: np.ndarray | None = None) -> np.ndarray:
    """The normalized log posterior `(V, C)` after `counts[v, z]` measurements of class z in voxel v, in any
    order (uniform prior unless `log_prior (C,)` is given): log prior + sum_z n_z log p(z | c)."""
    logits = np.asarray(counts, np.float64) @ log_likelihood
    if log_prior is not None:
        logits = logits + log_prior
    return _normalize_log(logits)


# --------------------------------------------------------------------------------------------------
# Voxel keys: a global voxel (x, y, z) of the map's lattice as one int64.


def grid_dims(map_config: MapConfig) -> np.ndarray:
    """int64[3]: voxels per axis of the map's block index (`grid_shape * block_size`)."""
    return np.asarray(map_config.grid_shape, np.int64) * map_config.block_size


def voxel_keys(coords: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """int64[N] row-major keys of global voxel coordinates `(N, 3)` inside `[0, dims)`."""
    coords = np.asarray(coords, np.int64)
    return (coords[:, 0] * dims[1] + coords[:, 1]) * dims[2] + coords[:, 2]


def key_coords(keys: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """int64[N, 3]: inverse of `voxel_keys`."""
    keys = np.asarray(keys, np.int64)
    return np.stack([keys // (dims[1] * dims[2]), (keys // dims[2]) % dims[1], keys % dims[2]], axis=1)


def voxel_centres(keys: np.ndarray, map_config: MapConfig) -> np.ndarray:
    """float32[N, 3] world coordinates of the voxels' centres."""
    g = key_coords(keys, grid_dims(map_config)).astype(np.float64)
    return (np.asarray(map_config.grid_origin) + (g + 0.5) * map_config.voxel_size).astype(np.float32)


def frame_measurements(
    pixel_class: np.ndarray,
    depth_s: np.ndarray,
    T_world_camera: np.ndarray,
    intrinsics: Sequence[float],
    map_config: MapConfig,
    num_classes: int,
    offsets: Sequence[float] = RAY_OFFSETS_VOXELS,
) -> np.ndarray:
    """The distinct (voxel, class) measurements of one frame, as int64 `key * C + class`, sorted.

    Args:
      pixel_class: `(Hs, Ws)` int closed-set class measured at each subsampled pixel (-1: none); pixel
        `(r, c)` is full-resolution pixel `(r * stride, c * stride)`, stride = `map_config.pixel_stride`.
      depth_s: `(Hs, Ws)` float depth in metres at the same pixels (0 = none).
      T_world_camera: `(4, 4)`.
      intrinsics: `(fx, fy, cx, cy)` of the full-resolution image.
      map_config: the map's lattice and depth range.
      num_classes: C.
      offsets: voxels along each pixel's ray (from its depth point) that its class is measured in.
    """
    stride, vs = map_config.pixel_stride, map_config.voxel_size
    depth_s = np.asarray(depth_s, np.float64)
    rows, cols = np.nonzero(
        (np.asarray(pixel_class) >= 0) & (depth_s >= map_config.depth_min) & (depth_s <= map_config.depth_max)
    )
    if rows.size == 0:
        return np.zeros(0, np.int64)
    fx, fy, cx, cy = (float(x) for x in intrinsics)
    xn, yn = (cols * stride - cx) / fx, (rows * stride - cy) / fy
    depth = depth_s[rows, cols]
    classes = np.asarray(pixel_class)[rows, cols].astype(np.int64)
    T = np.asarray(T_world_camera, np.float64)
    dims = grid_dims(map_config)
    origin = np.asarray(map_config.grid_origin)
    ray_norm = np.sqrt(xn * xn + yn * yn + 1.0)
    pairs = []
    for offset in offsets:
        d = depth + offset * vs / ray_norm  # a distance along the ray changes z by offset / |(xn, yn, 1)|
        camera = np.stack([xn * d, yn * d, d], axis=1)
        g = np.floor((camera @ T[:3, :3].T + T[:3, 3] - origin) / vs).astype(np.int64)
        inside = np.all((g >= 0) & (g < dims), axis=1)
        pairs.append(voxel_keys(g[inside], dims) * num_classes + classes[inside])
    return sorted_unique(np.concatenate(pairs))


def sorted_unique(values: np.ndarray) -> np.ndarray:
    """`np.unique` of a 1-D array by sorting (NumPy >= 2.3's hash-based `np.unique` was ~30x slower on the
    ~10^5 int64 keys of a frame)."""
    values = np.sort(np.asarray(values).reshape(-1))
    return values[_run_starts(values)]


def _run_starts(sorted_values: np.ndarray) -> np.ndarray:
    """bool[N]: where a run of equal values starts in a sorted array."""
    starts = np.ones(len(sorted_values), bool)
    starts[1:] = sorted_values[1:] != sorted_values[:-1]
    return starts


def _contains(sorted_keys: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """bool[N]: which of `keys` are in `sorted_keys`."""
    if len(sorted_keys) == 0:
        return np.zeros(len(keys), bool)
    at = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return sorted_keys[at] == keys


class LabelCounts:
    """Sparse per-voxel measurement counts, `(voxel key, class) -> n`, accumulated frame by frame."""

    def __init__(self, num_classes: int):
        self.num_classes = num_classes
        self._pairs = np.zeros(0, np.int64)
        self._counts = np.zeros(0, np.int64)
        self._pending: list[np.ndarray] = []
        self._pending_entries = 0

    def add(self, pairs: np.ndarray) -> None:
        """Adds one measurement per entry of `pairs` (int64 `key * C + class`)."""
        self._pending.append(np.asarray(pairs, np.int64))
        self._pending_entries += len(pairs)
        if self._pending_entries > _CONSOLIDATE_ENTRIES:
            self._consolidate()

    def _consolidate(self) -> None:
        if not self._pending:
            return
        pairs = np.concatenate([self._pairs, *self._pending])
        weights = np.concatenate([self._counts, np.ones(self._pending_entries, np.int64)])
        order = np.argsort(pairs, kind="stable")
        pairs, weights = pairs[order], weights[order]
        starts = np.flatnonzero(_run_starts(pairs))
        self._pairs = pairs[starts]
        self._counts = np.add.reduceat(weights, starts) if len(starts) else np.zeros(0, np.int64)
        self._pending, self._pending_entries = [], 0

    def pairs_and_counts(self) -> tuple[np.ndarray, np.ndarray]:
        """`(pairs int64[P] sorted distinct, counts int64[P])`."""
        self._consolidate()
        return self._pairs, self._counts

    def voxel_counts(self, keep_keys: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """`(keys int64[V] sorted, counts int32[V, C])` of the measured voxels (only those in `keep_keys`,
        sorted, when given)."""
        pairs, counts = self.pairs_and_counts()
        keys, classes = np.divmod(pairs, self.num_classes)
        if keep_keys is not None:
            keep = _contains(np.asarray(keep_keys, np.int64), keys)
            keys, classes, counts = keys[keep], classes[keep], counts[keep]
        new_voxel = _run_starts(keys)  # keys are sorted, as the pairs are
        voxels, row = keys[new_voxel], np.cumsum(new_voxel) - 1
        matrix = np.zeros((len(voxels), self.num_classes), np.int32)
        matrix[row, classes] = counts  # (key, class) pairs are distinct
        return voxels, matrix


# --------------------------------------------------------------------------------------------------
# Export: surface voxels, Cluster-All, instances.


def surface_voxel_keys(state, map_config: MapConfig, min_weight: float, band: float | None = None) -> np.ndarray:
    """int64[S] sorted keys of the voxels on the global TSDF surface: weight >= `min_weight` and
    `|sdf| <= band` metres (default one voxel). `state`: a `MapState` (its blocks are read on the host)."""

    blocks = state.blocks
    n = int(blocks.num_blocks)
    band = map_config.voxel_size if band is None else band
    tsdf, weight = np.asarray(blocks.tsdf[:n]), np.asarray(blocks.weight[:n])
    block, voxel = np.nonzero((weight >= min_weight) & (np.abs(tsdf) * map_config.sdf_trunc <= band))
    coords = np.asarray(blocks.block_coords[:n], np.int64)[block] * map_config.block_size
    coords = coords + voxel_offsets(map_config.block_size)[voxel]
    return np.sort(voxel_keys(coords, grid_dims(map_config)))


def cluster_all(keys: np.ndarray, labels: np.ndarray, dims: np.ndarray) -> tuple[np.ndarray, int]:
    """Cluster-All: connected components of 26-adjacent voxels with the same label.

    Args:
      keys: `(N,)` int64 sorted distinct voxel keys (`voxel_keys` with `dims`).
      labels: `(N,)` int label of each voxel.
      dims: `(3,)` voxels per axis of the lattice.

    Returns:
      `(component int64[N], count)`: components numbered 0.. in the order of their first voxel.
    """

    keys, labels = np.asarray(keys, np.int64), np.asarray(labels)
    n = len(keys)
    if n == 0:
        return np.zeros(0, np.int64), 0
    coords = key_coords(keys, dims)
    source_parts: list[np.ndarray] = []
    target_parts: list[np.ndarray] = []
    for offset in HALF_NEIGHBOURHOOD:
        neighbour = coords + offset
        inside = np.all((neighbour >= 0) & (neighbour < dims), axis=1)
        neighbour_keys = voxel_keys(neighbour, dims)
        at = np.minimum(np.searchsorted(keys, neighbour_keys), n - 1)
        linked = inside & (keys[at] == neighbour_keys) & (labels[at] == labels)
        source_parts.append(np.flatnonzero(linked))
        target_parts.append(at[linked])
    sources, targets = np.concatenate(source_parts), np.concatenate(target_parts)
    graph = coo_matrix((np.ones(len(sources), np.int8), (sources, targets)), shape=(n, n)).tocsr()
    count, component = connected_components(graph, directed=False)
    _, first = np.unique(component, return_index=True)  # renumber by first voxel: independent of scipy's order
    rank = np.empty(count, np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(count)
    return rank[component], int(count)


def component_instances(
    keys: np.ndarray,
    probabilities: np.ndarray,
    measurements: np.ndarray,
    component: np.ndarray,
    map_config: MapConfig,
    min_points: int,
    num_open_labels: int,
) -> list[MapInstance]:
    """One `MapInstance` per component of at least `min_points` voxels.

    Args:
      keys: `(N,)` voxel keys; probabilities: `(N, C)` posterior of each voxel; measurements: `(N,)`
        measurements each voxel received; component: `(N,)` `cluster_all`'s component of each voxel.
      map_config: the lattice (for the voxel centres).
      min_points: smaller components are dropped here already (they are noise, and many).
      num_open_labels: O, the length of the (empty) open-label histogram: Kimera never sees open labels.

    An instance's points are its voxel centres, its distribution the mean posterior of its voxels, its
    `observations` the most measurements one of its voxels received (about the frames that labelled it).
    """
    if len(keys) == 0:
        return []
    sizes = np.bincount(component)
    order = np.argsort(component, kind="stable")
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    instances = []
    for k in np.flatnonzero(sizes >= max(1, min_points)):
        members = order[starts[k] : starts[k] + sizes[k]]
        instances.append(
            MapInstance(
                instance_id=int(k),
                distribution=probabilities[members].mean(axis=0, dtype=np.float64),
                points=voxel_centres(keys[members], map_config),
                observations=int(measurements[members].max()),
                open_label_histogram=np.zeros(num_open_labels, np.float32),
            )
        )
    return instances


# --------------------------------------------------------------------------------------------------
# The mapper.


@dataclasses.dataclass
class KimeraResult:
    """A Kimera-style map: its instances, the geometry it was built on, counts and timings.

    Attributes:
      instances: the exported instances (post-processed like FM-Fusion's).
      geometry: the global TSDF map (a `FusionResult` without instances; its `state` gives the mesh).
      counters: detections, measurements, measured and surface voxels, components, instances.
      seconds: wall time of the labelling (per frame, summed) and of the export.
    """

    instances: list[MapInstance]
    geometry: FusionResult
    counters: dict[str, int]
    seconds: dict[str, float]

    @property
    def map_config(self) -> MapConfig:
        return self.geometry.map_config

    @property
    def frames_integrated(self) -> int:
        return self.geometry.frames_integrated

    @property
    def detection_frames(self) -> int:
        return self.geometry.detection_frames


class KimeraMapper:
    """Kimera-style mapping of one sequence: `add_frame` per frame, then `result()`.

    The global TSDF is FM-Fusion's (a `MapBuilder` fed no detections, refinement off since there are no
    instances); the labels are counted on the host (`LabelCounts`).
    """

    def __init__(self, config: PipelineConfig, map_config: MapConfig, label_sets: LabelSets | None = None):

        self.config = config
        self.map_config = map_config
        self.label_sets = label_sets or load_label_sets()
        geometry_only = config.model_copy(update={"refinement": config.refinement.model_copy(update={"enabled": False})})
        self.geometry = MapBuilder(geometry_only, map_config, self.label_sets)
        self.hard_class = hard_association(load_likelihood("manual"))
        self.counts = LabelCounts(self.label_sets.num_classes)
        self.counters = {"detections": 0, "measurements": 0}
        self.seconds = {"labels": 0.0}

    def add_frame(self, frame: RGBDFrame, detections: FrameDetections | None) -> None:
        """Integrates a frame into the TSDF; fuses its detections' labels when given."""
        self.geometry.add_frame(frame, None)
        if detections is not None:
            start = time.perf_counter()
            self._add_labels(frame, detections)
            self.geometry.progress.detection_frames += 1
            self.seconds["labels"] += time.perf_counter() - start

    def _add_labels(self, frame: RGBDFrame, detections: FrameDetections) -> None:

        config, map_config = self.config, self.map_config
        batch = self.geometry.adapter.detections(detections)
        stride = map_config.pixel_stride
        depth_s = np.asarray(frame.depth, np.float32)[::stride, ::stride]
        lo, hi = config.detections.depth_percentiles
        image_shape = (map_config.image_height, map_config.image_width)
        raw = batch_pixel_image(batch, image_shape, stride)
        det_image = np.asarray(filter_detection_depth(raw, depth_s, batch.valid.shape[0], lo, hi, depth_max=map_config.depth_max))
        classes = detection_classes(batch.label_scores, batch.valid, self.hard_class)
        pixel_class = np.where(det_image >= 0, classes[np.maximum(det_image, 0)], -1)
        k = frame.intrinsics
        pairs = frame_measurements(
            pixel_class, depth_s, frame.T_world_camera, (k.fx, k.fy, k.cx, k.cy), map_config, self.label_sets.num_classes
        )
        self.counts.add(pairs)
        self.counters["detections"] += int(batch.valid.sum())
        self.counters["measurements"] += len(pairs)

    def result(self) -> KimeraResult:
        """The TSDF map and the instances of its labelled surface (see the module docstring)."""
        geometry = self.geometry.result()
        start = time.perf_counter()
        export = self.config.export
        num_classes = self.label_sets.num_classes
        surface = surface_voxel_keys(geometry.state, self.map_config, export.min_weight)
        keys, counts = self.counts.voxel_counts(keep_keys=surface)
        log_posterior = log_posterior_from_counts(counts, measurement_log_likelihood(num_classes))
        probabilities = np.exp(log_posterior).astype(np.float32)
        labels = np.argmax(log_posterior, axis=1)
        component, num_components = cluster_all(keys, labels, grid_dims(self.map_config))
        instances = component_instances(
            keys, probabilities, counts.sum(axis=1), component, self.map_config, export.min_points, self.label_sets.num_open
        )
        instances = postprocess_instances(instances, self.label_sets, export)
        self.seconds["export"] = time.perf_counter() - start
        counters = dict(
            self.counters,
            surface_voxels=len(surface),
            labelled_surface_voxels=len(keys),
            components=num_components,
            instances=len(instances),
        )
        log.info(
            "kimera: %d labelled surface voxels of %d, %d components, %d instances",
            len(keys),
            len(surface),
            num_components,
            len(instances),
        )
        return KimeraResult(instances, geometry, counters, {k: round(v, 3) for k, v in self.seconds.items()})


def run_kimera(
    scene, detection_source, config: PipelineConfig, progress: bool = True, label_sets: LabelSets | None = None
) -> KimeraResult:
    """The Kimera-style baseline over every frame of an opened `scene` (`io.scene.Scene`), with detections
    from `detection_source(frame)` on the detection frames (`mapping.schedule.DetectionSchedule`, as FM-Fusion)."""

    bounds_min, bounds_max = scene.bounds()
    label_sets = label_sets or load_label_sets()
    map_config = build_map_config(config, bounds_min, bounds_max, scene.intrinsics.height, scene.intrinsics.width, label_sets)
    mapper = KimeraMapper(config, map_config, label_sets)
    frames: Iterable[RGBDFrame] = scene.frames()
    bar = None
    if progress:
        bar = tqdm(total=len(scene), desc=f"kimera {scene.name}", unit="frame", dynamic_ncols=True)
    try:
        for frame, detections in scheduled_detections(frames, detection_source, config):
            mapper.add_frame(frame, detections)
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return mapper.result()
