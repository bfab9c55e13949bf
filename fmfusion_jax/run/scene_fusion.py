"""A scene fused frame by frame as `fmfusion run` does it: bad frames skipped or fatal (`ON_ERROR_POLICIES`), frames
read ahead in threads, detections ahead in a thread of their own, checkpoints, a stop between frames; and the
checks of a scene before its first frame (depth units, a static trajectory).
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import dataclasses
import functools
import logging
import os
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, TypeVar

from fmfusion_jax import host_memory
from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io.scene import DepthSample, Scene
from fmfusion_jax.mapping.builder import FusionResult
from fmfusion_jax.mapping.inputs import DetectionSource, PreparedFrame
from fmfusion_jax.mapping.mapper import Mapper
from fmfusion_jax.mapping.schedule import DetectionSchedule, camera_motion
from fmfusion_jax.run.checkpoint import Checkpoint
from fmfusion_jax.run.outputs import capacity_used as capacity_used  # re-exported: experiments, likelihood, examples
from fmfusion_jax.run.outputs import score_instances as score_instances
from fmfusion_jax.types import FrameDetections

log = logging.getLogger(__name__)


T = TypeVar("T")


#: What a bad frame (unreadable image, malformed detection file) does: `skip` it with a warning naming the file,
#: or `stop` the run with that error.
ON_ERROR_POLICIES = ("skip", "stop")


#: Under `skip`, this many bad frames before the first good one mean the input is wrong as a whole: stop.
_MAX_LEADING_BAD_FRAMES = 10


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
            self.mapper = Mapper.for_scene(scene, config, sample=sample, time_stages=time_stages)

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
            compiled = host_memory.compilations()
            while self.position < len(self.scene):
                if should_stop and should_stop():
                    if self.checkpoint is not None:
                        self.checkpoint.save(self.mapper, self.scene, self.position, self.skipped)
                    return False
                started = time.perf_counter()
                self._fuse_frame(self.position, next(frames))
                self.frame_seconds.append(time.perf_counter() - started)
                if host_memory.compilations() != compiled:  # a step was compiled: the compiler's memory goes back
                    compiled = host_memory.compilations()
                    host_memory.trim_heap()
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
    from tqdm import tqdm  # only when a bar is shown
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
    where = f"{scene.depth_path(0).parent} ({len(sample.frame_names)} frames sampled)"
    if share < _MIN_VALID_DEPTH_SHARE:
        raise UserError(f"{where}: only {100 * share:.2f}% of the pixels have depth within {scene.depth_max:g} m; {hint}")
    if p99 < _NEAR_DEPTH_LIMIT:
        raise UserError(f"{where}: 99% of the depth is closer than {p99:.3g} m, which no room-scale scene is; {hint}")
