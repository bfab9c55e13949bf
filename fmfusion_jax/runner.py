"""A whole run: scene + detection source -> fused map -> output files (and a score when GT exists).

Shared by `fmfusion run`, `fmfusion demo` and the experiments; the loop itself is `pipeline.py`.
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import dataclasses
import functools
import json
import logging
import os
import shutil
import socket
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from fmfusion_jax import scene_graph
from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io import map_outputs
from fmfusion_jax.io.atomic import write_atomic
from fmfusion_jax.io.scene import DepthSample, Scene
from fmfusion_jax.labels import load_label_sets
from fmfusion_jax.map_file import MAP_STATE_FILE, save_map
from fmfusion_jax.pipeline import DetectionSchedule, DetectionSource, FusionResult, camera_motion, extract_map_instances
from fmfusion_jax.viz import overview

if TYPE_CHECKING:
    from fmfusion_jax.mapper import PreparedFrame
    from fmfusion_jax.types import FrameDetections

log = logging.getLogger(__name__)

T = TypeVar("T")


#: What a bad frame (unreadable image, malformed detection file) does: `skip` it with a warning naming the file,
#: or `stop` the run with that error.
ON_ERROR_POLICIES = ("skip", "stop")
#: Under `skip`, this many bad frames before the first good one mean the input is wrong as a whole: stop.
_MAX_LEADING_BAD_FRAMES = 10


class Checkpoint:
    """A resumable run's state in `folder`: `checkpoint.npz` (the map, `Mapper.save`) and `checkpoint.json`
    (the scene position reached, the frames skipped and the config, to refuse a resume that differs)."""

    MAP_FILE = "checkpoint.npz"
    INFO_FILE = "checkpoint.json"

    def __init__(self, folder: Path, every: int = 0):
        """`every`: write one every this many frames (0: only when the run is interrupted)."""
        self.folder = Path(folder)
        self.every = int(every)

    def exists(self) -> bool:
        return (self.folder / self.INFO_FILE).is_file() and (self.folder / self.MAP_FILE).is_file()

    def info(self) -> dict[str, Any]:
        try:
            return json.loads((self.folder / self.INFO_FILE).read_text())
        except (OSError, json.JSONDecodeError) as error:
            raise UserError(f"{self.folder / self.INFO_FILE}: unreadable checkpoint ({error})") from None

    def save(self, mapper, scene: Scene, position: int, skipped: list[tuple[str, str]]) -> None:
        """Writes the map, then the info that names it (each atomically: a crash leaves the previous pair)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        mapper.save(self.folder / self.MAP_FILE)
        info = {
            "scene": str(scene.path),
            "frames": len(scene),
            "position": position,
            "frames_integrated": mapper.frames_integrated,
            "skipped": [list(item) for item in skipped],
            "config": mapper.config.to_dict(),
        }
        write_atomic(self.folder / self.INFO_FILE, json.dumps(info, indent=1))

    def remove(self) -> None:
        for name in (self.MAP_FILE, self.INFO_FILE):
            (self.folder / name).unlink(missing_ok=True)


class SceneFusion:
    """Fuses a scene frame by frame through a `Mapper` under a run's policies: a bad frame skipped (named in
    a warning and in `skipped`) or fatal (`on_error`), checkpoints, and a stop request honoured between
    frames. `run()` returns whether every frame was read; `finalize()` gives the map.

    A new map's block index covers the scene's bounds (estimated from its poses and depth, after a check
    that the depth is in the units the config says); detections are read only for the frames the schedule
    fuses.
    """

    def __init__(
        self,
        scene: Scene,
        detection_source: DetectionSource,
        config: PipelineConfig,
        *,
        on_error: str = "skip",
        checkpoint: Checkpoint | None = None,
        resume: bool = False,
        time_stages: bool = False,
        observer: Callable[..., None] | None = None,
    ):
        """`observer(position, frame, detections or None, mapper)` is called after each frame is fused (e.g. a
        `viz.live.RerunView`)."""
        from fmfusion_jax.mapper import Mapper

        if on_error not in ON_ERROR_POLICIES:
            raise UserError(f"on_error {on_error!r}: expected one of {ON_ERROR_POLICIES}")
        self.scene, self.detection_source, self.config = scene, detection_source, config
        # a source of files is read with its frame in the reader threads; others on due frames, in order
        self._source_reads_ahead = bool(getattr(detection_source, "reads_ahead", False))
        # a source of models runs in a detection thread of its own, in frame order, on the frames a copy of the
        # detection schedule says are due, while the main thread fuses the frames before
        self._source_detects_ahead = bool(getattr(detection_source, "detects_ahead", False))
        self.on_error, self.checkpoint, self.observer = on_error, checkpoint, observer
        #: `(frame name, reason)` of the frames left out: bad poses (found when the scene was opened) and
        #: frames whose files failed to read
        self.skipped: list[tuple[str, str]] = list(scene.skipped)
        #: the next frame of the scene to read
        self.position = 0
        #: wall time of each frame fused in this process, as run (waiting for its read included)
        self.frame_seconds: list[float] = []
        self._last_checkpoint, self._checkpoint_seconds = time.perf_counter(), 0.0
        if resume:
            if checkpoint is None or not checkpoint.exists():
                raise UserError(f"nothing to resume: no checkpoint in {checkpoint.folder if checkpoint else '-'}")
            info = checkpoint.info()
            if info.get("config") != config.to_dict():
                raise UserError(
                    f"{checkpoint.folder / checkpoint.INFO_FILE}: the checkpoint was made with another "
                    "config; resume with the same --config and --set values"
                )
            if info.get("frames") != len(scene) or Path(info.get("scene", "")).name != scene.name:
                raise UserError(
                    f"{checkpoint.folder / checkpoint.INFO_FILE}: the checkpoint is of "
                    f"{info.get('scene')} ({info.get('frames')} frames), not of {scene.path} "
                    f"({len(scene)} frames)"
                )
            self.mapper = Mapper.load(checkpoint.folder / checkpoint.MAP_FILE, time_stages=time_stages)
            self.position = int(info["position"])
            self.skipped = [(str(name), str(reason)) for name, reason in info.get("skipped", [])]
            log.info("%s: resuming at frame %d of %d", scene.name, self.position, len(scene))
        else:
            sample = scene.sample_depth(max_frames=60)
            check_depth_units(scene, sample)
            warn_static_trajectory(scene)
            self.mapper = mapper_for_scene(scene, config, sample, time_stages=time_stages)

    #: Frames read, decoded and prepared (`Mapper.prepare`) ahead per reader thread, while the current one is fused.
    READ_AHEAD = 2
    #: Reader threads: one on a small machine (its cores run the device's work), up to four where cores are many (a
    #: GPU's host: reading a ScanNet frame and its detection files takes ~10 ms of one core, the fusion ~5 ms).
    READ_WORKERS = max(1, min(4, (os.cpu_count() or 1) // 4))

    def run(self, progress: Callable[[int], None] | None = None, should_stop: Callable[[], bool] | None = None) -> bool:
        """Fuses the frames from `position` on; True when the scene is done, False when `should_stop()` said
        stop (checked between frames; a checkpoint is written then, when the run has one). The next frames'
        images are read, decoded and prepared in a background thread meanwhile."""
        if progress and self.position:
            progress(self.position)
        workers = self.READ_WORKERS
        with (
            concurrent.futures.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="fmfusion-read") as reader,
            concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="fmfusion-detect") as detector,
        ):
            frames: Iterator[Any] = read_ahead(
                self._read_frame, range(self.position, len(self.scene)), reader, self.READ_AHEAD * workers
            )
            if self._source_detects_ahead:
                lookahead = Lookahead(self.mapper.schedule_copy(), self.mapper.frames_integrated)
                frames = read_ahead(functools.partial(self._detect_ahead, lookahead), frames, detector, 1)
            while self.position < len(self.scene):
                if should_stop and should_stop():
                    if self.checkpoint is not None:
                        self.checkpoint.save(self.mapper, self.scene, self.position, self.skipped)
                    return False
                started = time.perf_counter()
                self._fuse_frame(self.position, next(frames))
                self.frame_seconds.append(time.perf_counter() - started)
                self.position += 1
                if progress:
                    progress(1)
                if self.checkpoint is not None and self.position < len(self.scene) and self._checkpoint_due():
                    saving = time.perf_counter()
                    self.checkpoint.save(self.mapper, self.scene, self.position, self.skipped)
                    self._last_checkpoint = time.perf_counter()
                    self._checkpoint_seconds = self._last_checkpoint - saving
        return True

    #: Without `--checkpoint-every`, a checkpoint once the run has gone this long since the last one (s) ...
    AUTO_CHECKPOINT_AFTER_S = 120.0
    #: ... and long enough that checkpoints cost at most this share of the run (a ScanNet room's takes ~2 s)
    AUTO_CHECKPOINT_SHARE = 0.03

    def _checkpoint_due(self) -> bool:
        """`--checkpoint-every N`: every N frames; otherwise by time, so that a killed run (SIGKILL, a power cut)
        loses at most a few minutes while the checkpoints cost under 3 % of the run."""
        assert self.checkpoint is not None
        if self.checkpoint.every:
            return self.position % self.checkpoint.every == 0
        since = time.perf_counter() - self._last_checkpoint
        return since >= max(self.AUTO_CHECKPOINT_AFTER_S, self._checkpoint_seconds / self.AUTO_CHECKPOINT_SHARE)

    def _read_frame(self, i: int) -> tuple[PreparedFrame, DataError | None, FrameDetections | None] | DataError:
        """Frame `i` prepared (`Mapper.prepare`) with its detections when the source reads ahead (and the error
        reading them gave, reported if the frame turns out due), or the error reading the frame gave. The third
        item is the detections made ahead by the detection thread (`_detect_ahead`), None until then."""
        try:
            frame = self.scene.read_frame(i)
        except DataError as error:
            return error
        detections, detection_error = None, None
        if self._source_reads_ahead:
            try:
                detections = self.detection_source(frame)
            except DataError as failure:
                detection_error = failure
        return self.mapper.prepare(frame, detections), detection_error, None

    def _detect_ahead(self, lookahead: Lookahead, read: Any) -> Any:
        """In the detection thread, in frame order: a read frame with the detections of the models when the
        schedule's copy says it is due (the main thread's schedule decides again; the two agree, as every due
        frame gets detections)."""
        if isinstance(read, DataError):
            return read
        prepared, detection_error, detections = read
        frame = prepared.frame
        schedule = lookahead.schedule
        if schedule.due(lookahead.position, frame.T_world_camera):
            try:
                detections = self.detection_source(frame)
            except DataError as failure:
                detection_error = failure
            if detections is not None:
                schedule.fused(frame.T_world_camera)
        schedule.advance(frame.T_world_camera)
        lookahead.position += 1
        return prepared, detection_error, detections

    def finalize(self) -> FusionResult:
        """The finalized map of the frames fused so far (no frame can be added afterwards)."""
        if self.mapper.frames_integrated == 0:
            raise UserError(
                f"{self.scene.path}: no frame could be fused ({len(self.skipped)} skipped; first: "
                f"{self.skipped[0][0] if self.skipped else '-'})"
            )
        return self.mapper.finalize()

    def _fuse_frame(self, i: int, read: tuple[PreparedFrame, DataError | None, FrameDetections | None] | DataError) -> None:
        name = self.scene.frame_names[i]
        if isinstance(read, DataError):
            self._bad_input(name, str(read), "skipping frame")
            if self.mapper.frames_integrated == 0 and len(self.skipped) - len(self.scene.skipped) >= _MAX_LEADING_BAD_FRAMES:
                raise UserError(
                    f"the first {_MAX_LEADING_BAD_FRAMES} frames all failed; first: {self.skipped[len(self.scene.skipped)][1]}"
                ) from None
            return
        prepared, detection_error, detections = read
        frame = prepared.frame
        if self.mapper.detection_due(frame.T_world_camera):
            # a source read with the frame, or run ahead in the detection thread, was asked there already
            ahead = self._source_reads_ahead or self._source_detects_ahead
            if not ahead and detections is None and detection_error is None:
                try:
                    detections = self.detection_source(frame)
                except DataError as failure:
                    detection_error = failure
            if detection_error is not None:  # the frame's geometry is still fused
                self._bad_input(name, f"detections skipped: {detection_error}", "frame")
        fused = self.mapper.integrate(prepared, detections)
        if self.observer is not None:
            fused_detections = detections if detections is not None else prepared.detections
            self.observer(i, frame, fused_detections if fused else None, self.mapper)

    def _bad_input(self, name: str, reason: str, action: str) -> None:
        if self.on_error == "stop":
            raise UserError(f"{reason} (frame {name}; --on-error skip would skip it)")
        log.warning("%s %s: %s", action, name, reason)
        self.skipped.append((name, reason))


@dataclasses.dataclass
class Lookahead:
    """The detection thread's copy of the detection schedule and the frames it has integrated (its position)."""

    schedule: DetectionSchedule
    position: int


def warn_static_trajectory(scene: Scene, metres: float = 0.01, degrees: float = 1.0) -> bool:
    """Warns (and says True) when every pose of a sequence of several frames lies within `metres` and `degrees` of
    the first: identity or copied poses fuse every frame at one place, which is rarely what the user has."""
    poses = scene.poses()
    if len(poses) < 2:
        return False
    motions = [camera_motion(poses[0], pose) for pose in poses[1:]]
    if max(m for m, _ in motions) < metres and max(d for _, d in motions) < degrees:
        log.warning(
            "%s: the camera does not move: all %d poses lie within %.0f cm and %.0f degree of the first (identity or "
            "copied poses?); every frame is fused at that one place",
            scene.name,
            len(poses),
            100 * metres,
            degrees,
        )
        return True
    return False


def read_ahead(read: Callable[[Any], T], items: Iterable[Any], reader: concurrent.futures.Executor, window: int) -> Iterator[T]:
    """`read(item)` of each item, in order, run in `reader` up to `window` items ahead of the one taken: the next
    frames are read while the current one is fused, never the whole sequence at once."""
    pending: collections.deque[concurrent.futures.Future[T]] = collections.deque()
    for item in items:
        pending.append(reader.submit(read, item))
        if len(pending) > window:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()


def scene_extent(scene: Scene, config: PipelineConfig, sample: DepthSample | None = None):
    """`(bounds, expected_blocks)` of `scene` as `fmfusion run` sizes its map: the bounds of the sampled frames'
    poses and depth (`sample`: a `Scene.sample_depth`, default 60 frames) and the blocks those frames allocate."""
    from fmfusion_jax.mapper import sample_block_count
    from fmfusion_jax.pipeline import build_map_config

    sample = sample or scene.sample_depth(max_frames=60)
    bounds = scene.bounds(sample=sample)
    layout = build_map_config(config, *bounds, scene.intrinsics.height, scene.intrinsics.width)
    return bounds, sample_block_count(sample.points_world, sample.ray_origins, layout)


def mapper_for_scene(
    scene: Scene, config: PipelineConfig, sample: DepthSample | None = None, time_stages: bool = False, **hooks: Any
):
    """The `Mapper` `fmfusion run` fuses `scene` into: its block index over the scene's bounds, its pool
    starting at the blocks the sampled frames allocate (`scene_extent`) and doubling if the others show more.
    `hooks`: the Mapper's `timer` and `fuse_detections` (the benchmark's)."""
    from fmfusion_jax.mapper import Mapper

    bounds, expected = scene_extent(scene, config, sample)
    return Mapper(config, bounds=bounds, expected_blocks=expected, time_stages=time_stages, **hooks)


def fuse_scene(
    scene: Scene,
    detection_source: DetectionSource,
    config: PipelineConfig,
    progress: bool = True,
    on_error: str = "skip",
    time_stages: bool = False,
) -> FusionResult:
    """Fuses every frame of `scene` (`SceneFusion`, bad frames skipped with a warning) and finalizes the map;
    `time_stages`: the result's `timings` hold each engine step's median (the host then waits for each)."""
    fusion = SceneFusion(scene, detection_source, config, on_error=on_error, time_stages=time_stages)
    with progress_bar(len(scene), f"fusing {scene.name}", progress) as update:
        fusion.run(update)
    return fusion.finalize()


@contextlib.contextmanager
def progress_bar(total: int, description: str, enabled: bool = True) -> Iterator[Callable[[int], None] | None]:
    """A frame progress bar on stderr (log lines go above it), as its `update` function; None when disabled."""
    if not enabled:
        yield None
        return
    from tqdm import tqdm
    from tqdm.contrib.logging import logging_redirect_tqdm

    with logging_redirect_tqdm(), tqdm(total=total, desc=description, unit="frame", dynamic_ncols=True) as bar:
        yield bar.update


#: Depth a room-scale RGB-D scene cannot have: nearly all of it (99%) closer than this, in metres ...
_NEAR_DEPTH_LIMIT = 0.5
#: ... or valid (within dataset.depth_max) on fewer than this share of the sampled pixels.
_MIN_VALID_DEPTH_SHARE = 0.01


def check_depth_units(scene: Scene, sample: DepthSample) -> None:
    """A `UserError` when the sampled depth cannot be in the units `dataset.depth_scale` says (depth in metres
    or centimetres read as millimetres is 'all within 4 mm' or 'within 40 cm'; depth in finer units than
    said lies mostly beyond `depth_max`), before minutes of fusion build an empty or wrong map."""
    share, p99 = sample.valid_fraction, float(sample.depth_percentiles[-1])
    hint = (
        f"check dataset.depth_scale (now {scene.depth_scale:g} raw units per metre; millimetres: 1000, "
        f"TUM: 5000) and dataset.depth_max ({scene.depth_max:g} m)"
    )
    where = f"{scene.path / 'depth'} ({len(sample.frame_names)} frames sampled)"
    if share < _MIN_VALID_DEPTH_SHARE:
        raise UserError(f"{where}: only {100 * share:.2f}% of the pixels have depth within {scene.depth_max:g} m; {hint}")
    if p99 < _NEAR_DEPTH_LIMIT:
        raise UserError(f"{where}: 99% of the depth is closer than {p99:.3g} m, which no room-scale scene is; {hint}")


def ground_truth_mesh_path(scene: Scene) -> Path | None:
    path = scene.path / f"{scene.name}_vh_clean_2.ply"
    return path if path.is_file() else None


#: Everything `write_outputs` may write (files and folders): removed before a run writes into a folder again,
#: so no file of an earlier run (an instance that no longer exists, a report without ground truth) stays.
OUTPUT_NAMES = (
    "config.yaml",
    "instances.json",
    "semantic.ply",
    "instances.ply",
    "labelled_points.npz",
    "labelled_points.pcd",
    "instances",
    "mesh.ply",
    MAP_STATE_FILE,
    "overview.png",
    "run.json",
    "benchmark",
    "scene_graph.json",
    "scene_graph.graphml",
    "report.json",
    "explain.md",
    "explain.json",
    "explain.png",
)


def clear_outputs(out_dir: Path) -> None:
    """Removes the outputs of an earlier run from `out_dir` (only the names in `OUTPUT_NAMES`)."""
    for name in OUTPUT_NAMES:
        path = out_dir / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()


def write_outputs(
    result: FusionResult,
    scene: Scene,
    out_dir: Path,
    save_state: bool = True,
    skipped: list[tuple[str, str]] | None = None,
    detection_ms: dict[str, float] | None = None,
    frame_seconds: Sequence[float] = (),
) -> dict:
    """Writes every output of a run into `out_dir`; returns the run summary (also saved as run.json).

    Outputs: config.yaml, instances.json, semantic.ply, instances.ply, instances/*.ply, mesh.ply,
    map_state.npz (the map, for `load_map`; unless `save_state` is False), overview.png, run.json, and
    with ground truth the benchmark prediction files, report.json and the error analysis explain.md,
    explain.json, explain.png. `detection_ms`: the models' mean ms per detected frame, when a run detected online;
    `frame_seconds`: each frame's wall time as run (`SceneFusion.frame_seconds`), summarized in run.json.
    """
    from fmfusion_jax.engine import extraction

    label_sets = load_label_sets()
    out_dir.mkdir(parents=True, exist_ok=True)
    clear_outputs(out_dir)
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name] = round(now - clock, 3)
        clock = now

    (out_dir / "config.yaml").write_text(result.config.to_yaml())
    instances = extract_map_instances(result, label_sets)
    lap("extract_instances")
    records = map_outputs.instances_json(instances, label_sets)
    map_outputs.write_instances_json(out_dir / "instances.json", records)
    map_outputs.write_instance_clouds(out_dir, instances, label_sets)
    lap("write_instances")
    graph = scene_graph.build_scene_graph(records)
    (out_dir / "scene_graph.json").write_text(json.dumps(graph, indent=1))
    scene_graph.write_graphml(out_dir / "scene_graph.graphml", graph)
    lap("scene_graph")
    vertices, faces, colors = extraction.extract_mesh(result.state, result.map_config)
    map_outputs.write_mesh(out_dir / "mesh.ply", vertices, faces, colors)
    if len(faces) == 0:
        log.warning("%s: the global surface is empty (no depth fused?): mesh.ply has no face", scene.name)
    if not instances:
        log.warning(
            "%s: the map has no instance: instances.json lists none, semantic.ply and instances.ply are empty", scene.name
        )
    lap("mesh")
    if save_state:
        save_map(out_dir / MAP_STATE_FILE, result)
        lap("map_state")

    summary: dict[str, Any] = {
        "scene": scene.name,
        "frames": result.frames_integrated,
        "detection_frames": result.detection_frames,
        "instances": len(instances),
        "counters": result.counters,
        "timings_ms": result.timings.summary(),
        **({"frame_ms_as_run": _as_run_summary(frame_seconds)} if frame_seconds else {}),
        **({"detection_ms_per_frame": detection_ms} if detection_ms else {}),
        "map": result.map_config.describe(),
        "capacity_used": capacity_used(result),
        "skipped_frames": [{"frame": name, "reason": reason} for name, reason in (scene.skipped if skipped is None else skipped)],
    }
    gt = load_ground_truth(scene)
    if isinstance(gt, str):
        summary["benchmark"] = {"error": gt}
        gt = None
    elif gt is not None:
        summary["benchmark"] = _export_and_score(instances, gt, scene, result, out_dir, label_sets)
        lap("benchmark")
    _write_overview(
        out_dir / "overview.png",
        scene.name,
        instances,
        (vertices, faces, colors),
        gt,
        result,
        summary.get("benchmark", {}),
        label_sets,
    )
    lap("overview")
    summary["export_seconds"] = timings
    summary["peak_rss_mib"] = round(_peak_rss_mib(), 1)
    (out_dir / "run.json").write_text(json.dumps(summary, indent=1, default=float))
    log.info("outputs of %s written into %s (seconds: %s)", scene.name, out_dir, timings)
    return summary


def _peak_rss_mib() -> float:
    """This process's peak resident memory so far, MiB (Linux reports KiB, macOS bytes)."""
    import resource

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024


def capacity_used(result: FusionResult) -> dict[str, int]:
    """How full the fixed capacities got (to size tsdf.block_capacity and instances.capacity)."""
    blocks, table = result.state.blocks, result.state.instances
    return {
        "blocks": int(blocks.num_blocks),
        "block_capacity": result.map_config.block_capacity,
        "dropped_blocks": int(blocks.dropped_blocks),
        "touched_overflow": int(blocks.touched_overflow),
        "instances_live": int(table.valid.sum()),
        "instance_capacity": result.map_config.instance_capacity,
        "table_overflow": int(table.overflow),
    }


def load_ground_truth(scene: Scene):
    """The scene's ground truth; None without a GT mesh; the error text when GT files are incomplete."""
    from fmfusion_jax.errors import DataError
    from fmfusion_jax.io.ground_truth import load_scannet_ground_truth

    if ground_truth_mesh_path(scene) is None:
        return None
    try:
        return load_scannet_ground_truth(scene.path)
    except DataError as error:
        log.warning("no benchmark export: %s", error)
        return str(error)


def _write_overview(path: Path, scene_name: str, instances, mesh, gt, result: FusionResult, benchmark: dict, label_sets) -> None:
    vertices, faces, colors = mesh
    panels = [overview.map_overview_panel(instances, label_sets, vertices, colors, faces, result.map_config.voxel_size)]
    if gt is not None:
        panels.append(
            overview.ground_truth_overview_panel(
                gt.vertices, gt.faces, gt.vertex_colors, gt.nyu40_ids, gt.instance_ids, label_sets
            )
        )
    title = f"{scene_name}: {result.frames_integrated} frames"
    if "mAP" in benchmark:
        title += f"  |  AP {benchmark['mAP']:.3f}   AP50 {benchmark['mAP50']:.3f}   AP25 {benchmark['mAP25']:.3f}"
    try:
        overview.write_overview(path, panels, label_sets, title)
    except OSError as error:
        log.warning("no overview: %s", error)


def score_instances(instances, gt, scene_name: str, config: PipelineConfig, label_sets, gt_ids=None, floor=None):
    """`(predictions, BenchmarkResult)`: the ScanNet benchmark predictions of `instances` over the scene's
    mesh vertices (transfer radius `config.export.transfer_radius`), and their score on this scene alone.

    Args:
      gt: the scene's `SceneGroundTruth`.
      gt_ids: `gt.benchmark_ids()` when the caller already has it (computed here otherwise).
      floor: the map's floor (`FusionResult.floor()`: `(up, height)`), whose mesh vertices no object claims.
    """
    from fmfusion_jax.evaluation.scannet_benchmark import evaluate_scenes
    from fmfusion_jax.io.vertex_transfer import floor_vertices

    on_floor = None
    if floor is not None:
        up, height = floor
        on_floor = floor_vertices(gt.vertices, gt.faces, up, height, config.detections.floor_band)
    predictions = map_outputs.benchmark_predictions(
        instances,
        label_sets,
        gt.vertices,
        config.export.transfer_radius,
        config.export.structure_claims_vertices,
        config.export.transfer_neighbours,
        on_floor,
    )
    gt_ids = gt.benchmark_ids() if gt_ids is None else gt_ids
    return predictions, evaluate_scenes([(gt_ids, predictions)], scene_names=[scene_name])


def _export_and_score(instances, gt, scene: Scene, result: FusionResult, out_dir: Path, label_sets) -> dict:
    """Benchmark prediction files over the scene's mesh vertices, and the score against its GT."""
    from fmfusion_jax.io.benchmark_format import write_benchmark_predictions

    gt_ids = gt.benchmark_ids()
    predictions, score = score_instances(
        instances, gt, scene.name, result.config, label_sets, gt_ids=gt_ids, floor=result.floor()
    )
    txt = write_benchmark_predictions(out_dir / "benchmark", scene.name, predictions)
    report = score.to_json_dict()
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    return {
        "predictions": str(txt.relative_to(out_dir)),  # the folder is renamed when the run completes
        "mAP": score.mAP,
        "mAP50": score.mAP50,
        "mAP25": score.mAP25,
        "table": score.to_table(),
        "explain": _explain(gt, gt_ids, predictions, scene.name, out_dir),
    }


def _explain(gt, gt_ids, predictions, scene_name: str, out_dir: Path) -> dict:
    """The error analysis beside report.json (explain.md, explain.json, explain.png); its counts for run.json.

    It reads the predictions already scored; it does not run the benchmark again.
    """
    from fmfusion_jax.evaluation.explain import explain_scene
    from fmfusion_jax.evaluation.explain_report import write_explanation

    start = time.perf_counter()
    explanation = explain_scene(gt_ids, predictions, gt.vertices, scene_name=scene_name)
    write_explanation(out_dir, explanation, gt_ids, predictions, gt.vertices, gt.faces)
    return {
        "objects": explanation.status_counts(),
        "predictions": explanation.kind_counts(),
        "seconds": round(time.perf_counter() - start, 3),
    }


def prepare_output_dir(out_dir: str | Path, create: bool = True) -> Path:
    """Checks (and creates, or with `create=False` its parent) the output folder up front, before minutes of
    fusion; a path that cannot be one is a UserError."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"--out {out_dir} is a file, not a folder")
    where = out_dir if create else out_dir.parent
    try:
        where.mkdir(parents=True, exist_ok=True)
        # the outputs are staged beside --out (OUT.partial): a read-only place fails now, not after the fusion
        os.rmdir(tempfile.mkdtemp(prefix=".fmfusion-write-check-", dir=where))
    except OSError as error:
        raise UserError(f"cannot write the output folder {out_dir} ({where}: {error.strerror or error})") from None
    return out_dir


def _as_run_summary(frame_seconds: Sequence[float]) -> dict[str, float]:
    """Median, mean and max ms of the frames as run (the steps not timed one by one: `-v` times them)."""
    ms = [1000.0 * s for s in frame_seconds]
    return {
        "frames": len(ms),
        "median": round(float(statistics.median(ms)), 3),
        "mean": round(sum(ms) / len(ms), 3),
        "max": round(max(ms), 3),
    }


def check_output_folder(out_dir: Path, inputs: Iterable[Path | None] = (), overwrite: bool = False) -> None:
    """Refuses, before any work, an `--out` that `fmfusion run` must not replace: a folder holding one of the
    run's `inputs` (the scene, the detections, the models: replacing it would delete them), or an existing
    folder with files that is not a previous run's output (no run.json of one) unless `overwrite`."""
    target = out_dir.resolve()
    for path in inputs:
        if path is None:
            continue
        source = Path(path).resolve()
        if source == target or target in source.parents:
            raise UserError(f"--out {out_dir} holds the run's input {path}: the outputs would replace it; choose another folder")
    if not out_dir.is_dir() or overwrite or not any(out_dir.iterdir()):
        return
    try:
        previous = json.loads((out_dir / "run.json").read_text())
        if isinstance(previous, dict) and {"scene", "frames"} <= previous.keys():
            return
    except (OSError, ValueError):
        pass
    raise UserError(
        f"--out {out_dir} is a folder with files that is not an earlier `fmfusion run`'s output (no run.json): its "
        "contents would be replaced; choose a new folder, or pass --overwrite to replace it"
    )


class OutputLock:
    """One writer per output folder: `OUT.lock` beside `--out` holds the owner's pid and host while a run writes.

    A second run on the same `--out` is a UserError naming the owner; a lock whose process is gone (same host, dead
    pid: a run killed outright) is taken over with a warning. Created with O_EXCL, so two runs starting together
    cannot both take it."""

    def __init__(self, out_dir: Path):
        self.path = out_dir.with_name(out_dir.name + ".lock")
        self.owner = {"pid": os.getpid(), "host": socket.gethostname()}

    def __enter__(self) -> "OutputLock":
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                holder = self._holder()
                if holder is None:  # being written this instant, or left half written: look again once
                    time.sleep(0.2)
                    holder = self._holder()
                if holder is not None and not self._stale(holder):
                    raise UserError(
                        f"--out {self.path.with_suffix('')} is being written by another run (pid {holder.get('pid')} on "
                        f"{holder.get('host')}, {self.path}): wait for it, or choose another folder"
                    ) from None
                log.warning("taking over %s, left by a run that is gone (%s)", self.path, holder)
                self.path.unlink(missing_ok=True)
                continue
            with os.fdopen(fd, "w") as file:
                json.dump(self.owner, file)
            return self
        raise UserError(f"cannot take the lock {self.path}: another run keeps taking it")

    def __exit__(self, *exc_info) -> None:
        if self._holder() == self.owner:
            self.path.unlink(missing_ok=True)

    def _holder(self) -> dict | None:
        try:
            holder = json.loads(self.path.read_text())
        except (OSError, ValueError):
            return None  # half written or gone: treated as stale
        return holder if isinstance(holder, dict) else None

    def _stale(self, holder: dict) -> bool:
        if holder.get("host") != self.owner["host"]:
            return False  # another machine's run (a shared file system): never taken over
        try:
            os.kill(int(holder.get("pid", -1)), 0)
        except ProcessLookupError:
            return True
        except (PermissionError, ValueError, TypeError, OverflowError):
            return False
        return False


def partial_dir(out_dir: Path) -> Path:
    """Where `run_and_export` builds a run's outputs and keeps its checkpoint: `OUT.partial` beside `OUT`."""
    return out_dir.with_name(out_dir.name + ".partial")


@dataclasses.dataclass
class RunOutcome:
    """What `run_and_export` did: `summary` (the lines to print), `complete` (False: interrupted, the map so far
    and a checkpoint are in `folder`), `folder` (where the outputs are)."""

    summary: str
    complete: bool
    folder: Path


def run_and_export(
    scene: Scene,
    detection_source: DetectionSource,
    config: PipelineConfig,
    out_dir: Path,
    progress: bool = True,
    *,
    on_error: str = "skip",
    checkpoint_every: int = 0,
    resume: bool = False,
    restart: bool = False,
    should_stop: Callable[[], bool] | None = None,
    time_stages: bool = False,
    observer: Callable[..., None] | None = None,
) -> RunOutcome:
    """`fmfusion run`: fuse, write, and summarize.

    The outputs are built in `OUT.partial` and renamed to `OUT` when complete, replacing an earlier run's
    folder as a whole (never mixing two runs). When `should_stop()` turns true, fusion stops between frames:
    a checkpoint and the outputs of what was fused are written into `OUT.partial`, and `resume=True` later
    continues from the checkpoint (the map equals an uninterrupted run's). `checkpoint_every` frames also
    writes one. An unfinished `OUT.partial` is continued (`resume`) or discarded (`restart`), never silently.
    """
    start = time.perf_counter()
    out_dir = prepare_output_dir(out_dir, create=False)
    with OutputLock(out_dir):
        staging = partial_dir(out_dir)
        checkpoint = Checkpoint(staging, checkpoint_every)
        if staging.exists() and not resume:
            if checkpoint.exists() and not restart:
                info = checkpoint.info()
                raise UserError(
                    f"{staging} holds an unfinished run (checkpoint at frame {info.get('position')} of "
                    f"{info.get('frames')}): add --resume to continue it, or --restart to discard it"
                )
            shutil.rmtree(staging)  # a run that failed before its first checkpoint: nothing to keep
        fusion = SceneFusion(
            scene,
            detection_source,
            config,
            on_error=on_error,
            checkpoint=checkpoint,
            resume=resume,
            time_stages=time_stages,
            observer=observer,
        )
        staging.mkdir(parents=True, exist_ok=True)
        with progress_bar(len(scene), f"fusing {scene.name}", progress) as update:
            complete = fusion.run(update, should_stop)
        if observer is not None and hasattr(observer, "close"):
            observer.close(fusion.mapper)
        if not complete:
            log.warning("interrupted at frame %d of %d: writing the map so far into %s", fusion.position, len(scene), staging)
        result = fusion.finalize()
        try:
            timings_ms = getattr(detection_source, "timings_ms", None)
            detection_ms = timings_ms() if callable(timings_ms) else None
            summary = write_outputs(
                result, scene, staging, skipped=fusion.skipped, detection_ms=detection_ms, frame_seconds=fusion.frame_seconds
            )
            if complete:
                checkpoint.remove()
                _replace_folder(staging, out_dir)
        except OSError as error:
            raise UserError(f"cannot write the outputs into {staging}: {error}") from None
        folder = out_dir if complete else staging
        text = summarize_run(summary, result, time.perf_counter() - start, folder)
        return RunOutcome(text, complete, folder)


def _replace_folder(new: Path, target: Path) -> None:
    """Renames `new` to `target`; an existing `target` is moved aside first and removed after."""
    if target.exists():
        aside = target.with_name(f".{target.name}.replaced")
        if aside.exists():
            shutil.rmtree(aside)
        target.rename(aside)
        new.rename(target)
        shutil.rmtree(aside, ignore_errors=True)
    else:
        new.rename(target)


def summarize_run(summary: dict, result: FusionResult, seconds: float, out_dir: Path) -> str:
    """The lines `fmfusion run` / `fmfusion demo` print at the end: AP table, counts, timings, outputs."""
    lines = [
        f"{summary['scene']}: {summary['frames']} frames, {summary['detection_frames']} with detections, "
        f"{summary['instances']} instances "
        f"(created {result.counters['created']}, merged {result.counters['merged']}, "
        f"removed {result.counters['removed']}) in {seconds:.1f} s"
    ]
    timings = result.timings.summary()
    stage = "fusion" if "fusion" in timings else "tsdf"
    frames_per_s = summary["frames"] / max(seconds, 1e-9)
    if stage in timings:
        lines.append(
            f"{'fusion' if stage == 'fusion' else 'integration'} step: median "
            f"{timings[stage]['median_ms']:.1f} ms/frame (first call incl. compile "
            f"{timings[stage]['first_call_ms'] / 1e3:.1f} s); {frames_per_s:.1f} frames/s overall"
        )
    else:
        lines.append(f"{frames_per_s:.1f} frames/s overall, reading and writing included (-v times each engine step)")
    models_ms = summary.get("detection_ms_per_frame")
    if models_ms:
        parts = ", ".join(f"{name} {ms:.0f}" for name, ms in models_ms.items() if name != "front_end")
        lines.append(f"models: {models_ms['front_end']:.0f} ms per detected frame ({parts})")
    skipped = summary.get("skipped_frames", [])
    if skipped:
        lines.append(
            f"warning: {len(skipped)} frames skipped or partly skipped for bad input (listed in run.json; "
            f"first: {skipped[0]['frame']}: {skipped[0]['reason']})"
        )
    if result.detection_frames == 0:
        lines.append("warning: no frame had detections, so the map has no instances: check the detections folder")
    benchmark = summary.get("benchmark", {})
    if "table" in benchmark:
        lines.insert(0, benchmark["table"])
    elif "error" in benchmark:
        lines.append(f"not scored: {benchmark['error']}")
    if summary["instances"] == 0 and result.detection_frames:
        lines.append("warning: the map has no instance although detections were fused")
    listed = [
        "overview.png",
        "instances.json",
        "semantic.ply",
        "instances.ply",
        "mesh.ply",
        MAP_STATE_FILE,
        "run.json",
        "scene_graph.json",
        "report.json",
        "explain.md",
        "explain.json",
        "explain.png",
    ]
    written = [name for name in listed if (out_dir / name).is_file() or name == "run.json"]
    lines.append(f"outputs in {out_dir}: {', '.join(written)}")
    return "\n".join(lines)
