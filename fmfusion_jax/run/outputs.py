"""The output files of a run, as a registry of small writers (`OUTPUT_WRITERS`, in the order they are written).

Each `OutputWriter` names the files it writes and says in one line what they hold; `write_files` runs them (all,
or a chosen subset) on one `OutputContext`. `OUTPUT_NAMES`, the end-of-run summary's outputs line,
`fmfusion run --help` and the README's outputs table are made from the registry: a new output format is one
writer added here (and its README row, `readme_table`).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import importlib
import json
import logging
import statistics
import sys
import threading
import time
from collections.abc import Callable, Collection, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fmfusion_jax import host_memory
from fmfusion_jax.config import PipelineConfig
from fmfusion_jax.errors import UserError
from fmfusion_jax.evaluation.explain import explain_scene
from fmfusion_jax.evaluation.scannet_benchmark import BenchmarkResult, evaluate_scenes
from fmfusion_jax.instances import MapInstance
from fmfusion_jax.io.benchmark_format import InstancePredictions, write_benchmark_predictions
from fmfusion_jax.io.scene import Scene
from fmfusion_jax.labels import LabelSets

if TYPE_CHECKING:
    from fmfusion_jax.io.ground_truth import SceneGroundTruth
    from fmfusion_jax.io.map_outputs import InstancePoints
    from fmfusion_jax.mapping.builder import FusionResult

log = logging.getLogger(__name__)


@dataclasses.dataclass
class OutputContext:
    """What the writers need, built once per run; the derived values (instances, points, score, ...) are computed on
    first use, so a subset of writers computes only what it needs.

    Attributes:
      scene: the scene mapped.
      out_dir: the output folder.
      config: the run's config.
      label_sets: the label sets of the map.
      instances: the map's instances (None: extracted from `result` when first read, `map_instances`).
      result: the fused map (None: instances without a map, as a baseline's; then only the writers of
        config.yaml, instances.json, the clouds, the scene graph and the benchmark files apply).
      ground_truth: the scene's ground truth (None: none, or `ground_truth_error`).
      ground_truth_error: why the ground truth could not be read (run.json's benchmark error).
      floor: the map's floor `(up, height)` (`FusionResult.floor()`), whose mesh vertices no object claims.
      skipped: the frames skipped for bad input, `(frame, reason)` (run.json).
      detection_ms: the models' mean ms per detected frame, when a run detected online (run.json).
      frame_seconds: each frame's wall time as run, summarized in run.json.
      timings: seconds per writing step (run.json's `export_seconds`), filled by `write_files`.
      benchmark: run.json's `benchmark` entry, filled by the benchmark and explain writers.
      summary: the run summary, once the run.json writer has run.
      outputs_wall_s: seconds from the instances' extraction to run.json (the writers run side by side, so their
        `timings` add up to more), once `write_files` has run them.
    """

    scene: Scene
    out_dir: Path
    config: PipelineConfig
    label_sets: LabelSets
    instances: list[MapInstance] | None = None
    result: FusionResult | None = None
    ground_truth: SceneGroundTruth | None = None
    ground_truth_error: str | None = None
    floor: tuple[tuple[float, float, float], float] | None = None
    skipped: Sequence[tuple[str, str]] = ()
    detection_ms: dict[str, float] | None = None
    frame_seconds: Sequence[float] = ()
    timings: dict[str, float] = dataclasses.field(default_factory=dict)
    benchmark: dict[str, Any] = dataclasses.field(default_factory=dict)
    summary: dict[str, Any] | None = None
    outputs_wall_s: float | None = None

    @property
    def fused_map(self) -> FusionResult:
        if self.result is None:
            raise ValueError(f"{self.out_dir}: this output needs the fused map, and the context has none")
        return self.result

    @functools.cached_property
    def map_instances(self) -> list[MapInstance]:
        """The instances given, or those of the fused map (`mapping.export.extract_map_instances`)."""
        if self.instances is not None:
            return self.instances
        from fmfusion_jax.mapping.export import extract_map_instances  # lazy: JAX (`fmfusion --help` reads the registry)

        return extract_map_instances(self.fused_map, self.label_sets)

    @functools.cached_property
    def records(self) -> list[dict]:
        """The records of instances.json."""
        from fmfusion_jax.io import map_outputs  # lazy: `fmfusion --help` reads the registry

        return map_outputs.instances_json(self.map_instances, self.label_sets)

    @functools.cached_property
    def points(self) -> InstancePoints:
        from fmfusion_jax.io import map_outputs  # lazy: `fmfusion --help` reads the registry

        return map_outputs.instance_points(self.map_instances, self.label_sets)

    @functools.cached_property
    def graph(self) -> dict[str, Any]:
        from fmfusion_jax import scene_graph  # lazy: `fmfusion --help` reads the registry

        return scene_graph.build_scene_graph(self.records)

    @functools.cached_property
    def overview_panels(self) -> tuple[list[Any], Any]:
        """`(panels, drawn)` of overview.png: the map's surface voxels under its instances, beside the ground truth
        when there is one, drawn (`viz.overview.rasterize_panels`); the title, with the score, comes last."""
        from fmfusion_jax.engine import extraction  # lazy: `fmfusion --help` reads the registry
        from fmfusion_jax.viz import overview

        result, gt, label_sets = self.fused_map, self.ground_truth, self.label_sets
        points, colors = extraction.extract_surface_voxels(result.state, result.map_config)
        panels = [overview.map_overview_panel(self.map_instances, label_sets, points, colors, None, result.map_config.voxel_size)]
        if gt is not None:
            panels.append(
                overview.ground_truth_overview_panel(
                    gt.vertices, gt.faces, gt.vertex_colors, gt.nyu40_ids, gt.instance_ids, label_sets
                )
            )
        return panels, overview.rasterize_panels(panels)

    @functools.cached_property
    def scored(self) -> tuple[Any, InstancePredictions, BenchmarkResult]:
        """`(gt_ids, predictions, score)`: the benchmark predictions over the ground truth's mesh vertices and
        their score on this scene alone."""
        if self.ground_truth is None:
            raise ValueError(f"{self.out_dir}: the benchmark outputs need the scene's ground truth")
        gt_ids = self.ground_truth.benchmark_ids()
        predictions, score = score_instances(
            self.map_instances, self.ground_truth, self.scene.name, self.config, self.label_sets, gt_ids, self.floor
        )
        return gt_ids, predictions, score


@dataclasses.dataclass(frozen=True)
class OutputWriter:
    """One output of a run.

    Attributes:
      name: what `write_files(names=...)` calls it.
      files: the files (and folders, ending in `/`) it writes into the output folder.
      description: one line for `fmfusion run --help` and the README's outputs table.
      write: writes them from the `OutputContext`.
      lap: the run.json `export_seconds` entry its time adds to (None: its time counts toward the next writer's).
      listed: its place in the end-of-run summary's "outputs in ..." line (None: not named there).
      needs_ground_truth: written only when the scene has ground truth.
      uses: the `OutputContext` values it reads that other writers read too (made once, before the writers run).
    """

    name: str
    files: tuple[str, ...]
    description: str
    write: Callable[[OutputContext], None]
    lap: str | None = None
    listed: int | None = None
    needs_ground_truth: bool = False
    uses: tuple[str, ...] = ()


def score_instances(instances, gt, scene_name: str, config: PipelineConfig, label_sets, gt_ids=None, floor=None):
    """`(predictions, BenchmarkResult)`: the ScanNet benchmark predictions of `instances` over the scene's
    mesh vertices (transfer radius `config.export.transfer_radius`), and their score on this scene alone.

    Args:
      gt: the scene's `SceneGroundTruth`.
      gt_ids: `gt.benchmark_ids()` when the caller already has it (computed here otherwise).
      floor: the map's floor (`FusionResult.floor()`: `(up, height)`), whose mesh vertices no object claims.
    """
    from fmfusion_jax.io import map_outputs  # lazy: `fmfusion --help` reads the registry
    from fmfusion_jax.io.vertex_transfer import floor_vertices  # lazy: `fmfusion --help` reads the registry

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
        config.export.alternative_class_probability,
        gt.faces,
        config.export.union_confidence_factor,
    )
    gt_ids = gt.benchmark_ids() if gt_ids is None else gt_ids
    return predictions, evaluate_scenes([(gt_ids, predictions)], scene_names=[scene_name])


def capacity_used(result: FusionResult) -> dict[str, int]:
    """How full the fixed capacities got (to size tsdf.block_capacity and instances.capacity)."""
    blocks, table = result.state.blocks, result.state.instances
    return {
        "blocks": int(blocks.num_blocks),
        "block_capacity": result.map_config.block_capacity,
        "dropped_blocks": int(blocks.dropped_blocks),
        "touched_overflow": int(blocks.touched_overflow),
        "instances_live": int(np.count_nonzero(np.asarray(table.valid))),  # on the host: no reduction compiled for it
        "instance_capacity": result.map_config.instance_capacity,
        "table_overflow": int(table.overflow),
    }


def _peak_rss_mib() -> float:
    """This process's peak resident memory so far, MiB (Linux reports KiB, macOS bytes)."""
    import resource  # POSIX only

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024


def _as_run_summary(frame_seconds: Sequence[float]) -> dict[str, float]:
    """Median, mean and max ms of the frames as run (the steps not timed one by one: `-v` times them)."""
    ms = [1000.0 * s for s in frame_seconds]
    return {
        "frames": len(ms),
        "median": round(float(statistics.median(ms)), 3),
        "mean": round(sum(ms) / len(ms), 3),
        "max": round(max(ms), 3),
    }


def run_summary(context: OutputContext) -> dict[str, Any]:
    """The run summary (run.json): counts, timings, capacities, skipped frames, the score."""
    result = context.fused_map
    summary: dict[str, Any] = {
        "scene": context.scene.name,
        "frames": result.frames_integrated,
        "detection_frames": result.detection_frames,
        "instances": len(context.map_instances),
        "counters": result.counters,
        "timings_ms": result.timings.summary(),
        **({"frame_ms_as_run": _as_run_summary(context.frame_seconds)} if context.frame_seconds else {}),
        **({"detection_ms_per_frame": context.detection_ms} if context.detection_ms else {}),
        "map": result.map_config.describe(),
        "capacity_used": capacity_used(result),
        "skipped_frames": [{"frame": name, "reason": reason} for name, reason in context.skipped],
    }
    if context.ground_truth_error is not None:
        summary["benchmark"] = {"error": context.ground_truth_error}
    elif context.benchmark:
        summary["benchmark"] = context.benchmark
    summary["export_seconds"] = context.timings
    if context.outputs_wall_s is not None:
        summary["export_wall_seconds"] = round(context.outputs_wall_s, 3)
    summary["peak_rss_mib"] = round(_peak_rss_mib(), 1)
    return summary


# ------------------------------------------------------------------------------------------------ writers


def _write_config(context: OutputContext) -> None:
    (context.out_dir / "config.yaml").write_text(context.config.to_yaml())


def _write_instances_json(context: OutputContext) -> None:
    from fmfusion_jax.io import map_outputs  # lazy: `fmfusion --help` reads the registry

    map_outputs.write_instances_json(context.out_dir / "instances.json", context.records)


def _write_semantic_cloud(context: OutputContext) -> None:
    from fmfusion_jax.io import map_outputs  # lazy: `fmfusion --help` reads the registry

    p = context.points
    map_outputs.write_point_cloud(context.out_dir / "semantic.ply", p.points, p.class_colors, p.label, p.instance)


def _write_instance_cloud(context: OutputContext) -> None:
    from fmfusion_jax.io import map_outputs  # lazy: `fmfusion --help` reads the registry

    p = context.points
    map_outputs.write_point_cloud(context.out_dir / "instances.ply", p.points, p.instance_colors, p.label, p.instance)


def _write_instance_folder(context: OutputContext) -> None:
    from fmfusion_jax.io import map_outputs  # lazy: `fmfusion --help` reads the registry

    map_outputs.write_instance_folder(context.out_dir / "instances", context.map_instances, context.label_sets)


def _write_labelled_points(context: OutputContext) -> None:
    from fmfusion_jax.io import map_outputs  # lazy: `fmfusion --help` reads the registry

    p = context.points
    map_outputs.write_labelled_points(context.out_dir, p.points, p.class_colors, p.label, p.instance)


def _write_scene_graph_json(context: OutputContext) -> None:
    (context.out_dir / "scene_graph.json").write_text(json.dumps(context.graph, indent=1))


def _write_scene_graph_graphml(context: OutputContext) -> None:
    from fmfusion_jax import scene_graph  # lazy: `fmfusion --help` reads the registry

    scene_graph.write_graphml(context.out_dir / "scene_graph.graphml", context.graph)


def _write_mesh(context: OutputContext) -> None:
    """The global TSDF's surface, made here and not kept: no other output reads it (~110 MiB for a room)."""
    from fmfusion_jax.engine import extraction  # lazy: `fmfusion --help` reads the registry
    from fmfusion_jax.io import map_outputs

    result = context.fused_map
    vertices, faces, colors = extraction.extract_mesh(result.state, result.map_config)
    map_outputs.write_mesh(context.out_dir / "mesh.ply", vertices, faces, colors)
    if len(faces) == 0:
        log.warning("%s: the global surface is empty (no depth fused?): mesh.ply has no face", context.scene.name)


def _write_map_state(context: OutputContext) -> None:
    from fmfusion_jax.mapping.map_file import save_map  # lazy: `fmfusion --help` reads the registry

    save_map(context.out_dir / MAP_STATE_FILE, context.fused_map)


def _write_benchmark(context: OutputContext) -> None:
    _, predictions, score = context.scored
    txt = write_benchmark_predictions(context.out_dir / "benchmark", context.scene.name, predictions)
    context.benchmark.update(
        predictions=str(txt.relative_to(context.out_dir)),  # the folder is renamed when the run completes
        mAP=score.mAP,
        mAP50=score.mAP50,
        mAP25=score.mAP25,
        table=score.to_table(),
    )


def _write_report(context: OutputContext) -> None:
    (context.out_dir / "report.json").write_text(json.dumps(context.scored[2].to_json_dict(), indent=1))


def _write_explain(context: OutputContext) -> None:
    """The error analysis beside report.json; its counts go into run.json. It reads the predictions already
    scored; it does not run the benchmark again."""
    from fmfusion_jax.evaluation.explain_report import write_explanation  # lazy: `fmfusion --help` reads the registry

    assert context.ground_truth is not None
    gt = context.ground_truth
    gt_ids, predictions, _ = context.scored
    start = time.perf_counter()
    explanation = explain_scene(gt_ids, predictions, gt.vertices, scene_name=context.scene.name)
    write_explanation(context.out_dir, explanation, gt_ids, predictions, gt.vertices, gt.faces)
    context.benchmark["explain"] = {
        "objects": explanation.status_counts(),
        "predictions": explanation.kind_counts(),
        "seconds": round(time.perf_counter() - start, 3),
    }


def _write_overview(context: OutputContext) -> None:
    """overview.png: the panels drawn already (`OutputContext.overview_panels`, beside the benchmark's scoring),
    titled with the score."""
    from fmfusion_jax.viz import overview  # lazy: `fmfusion --help` reads the registry

    result, gt = context.fused_map, context.ground_truth
    panels, drawn = context.overview_panels
    title = f"{context.scene.name}: {result.frames_integrated} frames"
    if gt is not None:
        score = context.scored[2]
        title += f"  |  AP {score.mAP:.3f}   AP50 {score.mAP50:.3f}   AP25 {score.mAP25:.3f}"
    try:
        overview.write_overview(context.out_dir / "overview.png", panels, context.label_sets, title, drawn=drawn)
    except OSError as error:
        log.warning("no overview: %s", error)


def _write_run_json(context: OutputContext) -> None:
    context.summary = run_summary(context)
    (context.out_dir / RUN_RECORD).write_text(json.dumps(context.summary, indent=1, default=float))


#: File name of the saved map in a run's output folder.
MAP_STATE_FILE = "map_state.npz"
#: The run's record (counts, timings, capacities): written last, and by every run whatever outputs it chose.
RUN_RECORD = "run.json"

#: Every output of a run (run.json last: it holds every other writer's time).
OUTPUT_WRITERS: tuple[OutputWriter, ...] = (
    OutputWriter("config.yaml", ("config.yaml",), "the config used", _write_config),
    OutputWriter(
        "instances.json",
        ("instances.json",),
        "per instance: class, confidence, fused distribution, observations, open-set label histogram, voxel count, "
        "oriented box; metres, world frame (schema: docs/instances.schema.json)",
        _write_instances_json,
        uses=("records",),
        lap="write_instances",
        listed=2,
    ),
    OutputWriter(
        "semantic.ply",
        ("semantic.ply",),
        "the instance points (binary PLY, metres, world frame) coloured by class (NYU40 palette), with `label` "
        "(NYU40 id, as ScanNet's `*_vh_clean_2.labels.ply`) and `instance` (the `id` of instances.json) vertex properties",
        _write_semantic_cloud,
        uses=("points",),
        lap="write_instances",
        listed=3,
    ),
    OutputWriter(
        "instances.ply",
        ("instances.ply",),
        "the same points coloured by instance, with the same `label` and `instance` vertex properties",
        _write_instance_cloud,
        uses=("points",),
        lap="write_instances",
        listed=4,
    ),
    OutputWriter(
        "instances",
        ("instances/",),
        "one PLY per instance, `NNNN_<class>.ply`, in its instance colour",
        _write_instance_folder,
        uses=("map_instances",),
        lap="write_instances",
    ),
    OutputWriter(
        "labelled_points",
        ("labelled_points.npz", "labelled_points.pcd"),
        "the instance points with their labels for robotics tools (ROS, PCL, NumPy): `points` (metres, world frame), "
        "`colors`, `label` (NYU40 id), `instance` (id of instances.json); the PCD has fields x y z rgb label instance",
        _write_labelled_points,
        uses=("points",),
        lap="write_instances",
    ),
    OutputWriter(
        "scene_graph.json",
        ("scene_graph.json",),
        "the scene graph: nodes = the instances (class, confidence, top open-set labels, centroid, oriented box, "
        "points) and the floor as root; edges `on`, `inside`, `near` computed from the boxes, each with a score",
        _write_scene_graph_json,
        uses=("records", "graph"),
        lap="scene_graph",
        listed=8,
    ),
    OutputWriter(
        "scene_graph.graphml",
        ("scene_graph.graphml",),
        "the scene graph as GraphML (for networkx, Gephi, yEd)",
        _write_scene_graph_graphml,
        uses=("records", "graph"),
        lap="scene_graph",
    ),
    OutputWriter(
        "mesh.ply",
        ("mesh.ply",),
        "the global TSDF surface (marching cubes) with colour",
        _write_mesh,
        lap="mesh",
        listed=5,
    ),
    OutputWriter(
        "map_state.npz",
        (MAP_STATE_FILE,),
        "the map state, loadable with `fmfusion_jax.Mapper.load` to inspect or continue",
        _write_map_state,
        lap="map_state",
        listed=6,
    ),
    OutputWriter(
        "benchmark",
        ("benchmark/",),
        "ScanNet benchmark prediction files (`<scene>.txt`, `pred_mask/`) over the scene's `_vh_clean_2.ply` vertices, "
        "when the scene has ground truth: each instance under its most likely class, then under each other class of "
        "at least 10 % (`export.alternative_class_probability`), then two touching instances of one class (or class "
        "hypothesis) as one (`export.union_confidence_factor`); a mask file per line, as the official script needs",
        _write_benchmark,
        uses=("scored",),
        lap="benchmark",
        needs_ground_truth=True,
    ),
    OutputWriter(
        "report.json",
        ("report.json",),
        "the evaluation, when the scene has ground truth",
        _write_report,
        uses=("scored",),
        lap="benchmark",
        listed=9,
        needs_ground_truth=True,
    ),
    OutputWriter(
        "explain",
        ("explain.md", "explain.json", "explain.png"),
        "the error analysis beside report.json: why each object was (not) found and what each prediction is, "
        "with a top-down picture (docs/error-analysis.md)",
        _write_explain,
        uses=("scored",),
        lap="benchmark",
        listed=10,
        needs_ground_truth=True,
    ),
    OutputWriter(
        "overview.png",
        ("overview.png",),
        "top-down picture of the instances by class, beside the ground truth when there is one",
        _write_overview,
        uses=("overview_panels", "scored"),
        lap="overview",
        listed=1,
    ),
    OutputWriter(RUN_RECORD, (RUN_RECORD,), "counts, timings per stage, capacities used", _write_run_json, listed=7),
)

#: Every file and folder the writers may write: removed before a run writes into a folder again.
OUTPUT_NAMES: tuple[str, ...] = tuple(file.rstrip("/") for writer in OUTPUT_WRITERS for file in writer.files)


#: The modules the writers and their shared values import when they first run (lazily, so that `fmfusion --help` and
#: the commands that write no map stay fast): ~0.3 s of imports that `preload_writer_modules` moves off the outputs'
#: critical path. `tests/test_run_policies.py` checks that writing a run's outputs after it imports nothing more.
WRITER_MODULES: tuple[str, ...] = (
    "scipy.ndimage",  # `instances.drop_far_specks`
    "skimage.measure._marching_cubes_lewiner",  # `engine.extraction.extract_mesh`
    "fmfusion_jax.mapping.export",
    "fmfusion_jax.mapping.map_file",
    "fmfusion_jax.io.map_outputs",
    "fmfusion_jax.io.vertex_transfer",
    "fmfusion_jax.scene_graph",
    "fmfusion_jax.viz.overview",
    "fmfusion_jax.evaluation.explain_report",
)


def preload_writer_modules() -> threading.Thread:
    """Imports `WRITER_MODULES` in a daemon thread, started while a map is fused (the imports overlap the compile and
    the frames' reading, which release the GIL) so that the writers find them loaded; returns the thread. A module
    that fails to import is left to its writer, which reports the error where it matters."""

    def load() -> None:
        for name in WRITER_MODULES:
            try:
                importlib.import_module(name)
            except Exception as error:  # the writer that needs it raises it again, with context
                log.debug("preloading %s failed: %s", name, error)

    thread = threading.Thread(target=load, name="fmfusion-preload", daemon=True)
    thread.start()
    return thread


def select_writers(names: Collection[str] | None = None) -> list[OutputWriter]:
    """The writers named (in registry order), all with `names=None`; an unknown name is a ValueError."""
    if names is None:
        return list(OUTPUT_WRITERS)
    unknown = set(names) - {writer.name for writer in OUTPUT_WRITERS}
    if unknown:
        known = ", ".join(writer.name for writer in OUTPUT_WRITERS)
        raise ValueError(f"unknown outputs {', '.join(sorted(unknown))} (known: {known})")
    return [writer for writer in OUTPUT_WRITERS if writer.name in names]


def chosen_outputs(names: Sequence[str] | None) -> tuple[str, ...] | None:
    """`fmfusion run --outputs NAME...` as writer names (run.json always: it is the run's record), or None for
    all; an unknown name is a UserError listing the known ones."""
    if names is None:
        return None
    try:
        select_writers(names)
    except ValueError as error:
        raise UserError(f"--outputs: {error}") from None
    return tuple(dict.fromkeys([*names, RUN_RECORD]))


#: The `OutputContext` values several writers read, each made once.
SHARED_VALUES = ("map_instances", "records", "points", "scored", "graph", "overview_panels")
#: What a shared value is made from (`write_files` starts it once these are made).
_VALUE_INPUTS = {
    "records": ("map_instances",),
    "points": ("map_instances",),
    "scored": ("map_instances",),
    "graph": ("records",),
    "overview_panels": ("map_instances",),
}
#: Steps started first when they are ready: the mesh (the longest step, written and let go at once) beside the
#: instances, then the overview's panels and the benchmark score (each waits for the instances only), then the map file.
_FIRST = ("mesh.ply", "map_instances", "overview_panels", "scored", "overview.png", "map_state.npz")

#: Threads the writers run in: zlib and PNG encoding release the GIL, and so does much of NumPy.
WRITER_THREADS = 2


def write_files(context: OutputContext, names: Collection[str] | None = None) -> None:
    """Runs the writers named in `names` (all by default) into `context.out_dir`, side by side in threads, each as
    soon as the values it reads (`OutputWriter.uses`) are made, then run.json, which records each step's seconds
    (`context.timings`, under the writer's `lap`). The benchmark writers are skipped without ground truth. The
    files do not depend on the order the threads finish in."""
    start = time.perf_counter()
    writers = [w for w in select_writers(names) if not (w.needs_ground_truth and context.ground_truth is None)]
    record = [w for w in writers if w.name == RUN_RECORD]
    others = [w for w in writers if w.name != RUN_RECORD]
    if context.instances is None:  # extracted here, beside the values that do not need them (the mesh, the map file)
        context.timings.setdefault("extract_instances", 0.0)
    for writer in others:  # run.json lists the steps in registry order
        if writer.lap is not None:
            context.timings.setdefault(writer.lap, 0.0)
    steps: dict[str, tuple[Callable[[], Any], tuple[str, ...], str | None]] = {}
    for name in SHARED_VALUES:
        readers = [w for w in others if name in w.uses or any(name in _VALUE_INPUTS.get(u, ()) for u in w.uses)]
        if name == "scored" and context.ground_truth is None:
            readers = [w for w in readers if w.needs_ground_truth]  # the overview reads the score only with ground truth
        if name == "map_instances" and context.instances is not None:
            continue  # given
        if readers:  # a shared value's time counts to the first writer that reads it
            lap = "extract_instances" if name == "map_instances" else readers[0].lap
            inputs = tuple(i for i in _VALUE_INPUTS.get(name, ()) if i in steps)
            steps[name] = (functools.partial(getattr, context, name), inputs, lap)
    for writer in others:
        inputs = tuple(name for name in writer.uses if name in steps)
        steps[writer.name] = (functools.partial(writer.write, context), inputs, writer.lap)
    order = sorted(steps, key=lambda name: _FIRST.index(name) if name in _FIRST else len(_FIRST))
    seconds = _run_steps({name: steps[name][:2] for name in order}, WRITER_THREADS)
    for name in steps:  # registry order: the sums do not depend on which thread finished first
        lap = steps[name][2]
        if lap is not None:
            context.timings[lap] = round(context.timings.get(lap, 0.0) + seconds[name], 3)
    context.outputs_wall_s = context.timings.get("extract_instances", 0.0) if context.instances is not None else 0.0
    context.outputs_wall_s += time.perf_counter() - start
    for writer in record:
        writer.write(context)


def _run_steps(steps: dict[str, tuple[Callable[[], Any], tuple[str, ...]]], threads: int) -> dict[str, float]:
    """Runs each step `name: (fn, inputs)` in a pool of `threads` once the steps named in its inputs are done: a
    thread that comes free takes the first ready step in the order given. Returns each step's seconds. A step's
    exception is raised here once the steps already running have finished."""
    seconds: dict[str, float] = {}
    waiting = dict(steps)
    with concurrent.futures.ThreadPoolExecutor(threads, thread_name_prefix="outputs") as pool:
        running: dict[concurrent.futures.Future, str] = {}
        while waiting or running:
            for name, (fn, inputs) in list(waiting.items()):  # a free thread takes the first ready step
                if len(running) < threads and all(i in seconds for i in inputs):
                    running[pool.submit(_timed, fn)] = name
                    del waiting[name]
            if not running:  # a step waits for one that is not there: a bug in the steps' inputs
                raise RuntimeError(f"output steps {sorted(waiting)} wait for steps that never run")
            done, _ = concurrent.futures.wait(running, return_when=concurrent.futures.FIRST_COMPLETED)
            for future in done:
                seconds[running.pop(future)] = future.result()
    return seconds


#: A writer step that took this long (s) is followed by a trim of the C heap (which itself takes 10-100 ms).
TRIM_AFTER_STEP_S = 0.3


def _timed(fn: Callable[..., Any], *args: Any) -> float:
    """Seconds `fn(*args)` took. After a long step the C heap is trimmed: its temporaries' memory goes back to the
    system before the next step's (each writer thread keeps an arena of its own)."""
    start = time.perf_counter()
    fn(*args)
    seconds = time.perf_counter() - start
    if seconds > TRIM_AFTER_STEP_S:
        host_memory.trim_heap()
    return seconds


def listed_outputs(out_dir: Path) -> list[str]:
    """The files of `out_dir` that the end-of-run summary names, in its order."""
    listed = sorted((writer for writer in OUTPUT_WRITERS if writer.listed is not None), key=lambda w: w.listed or 0)
    return [file for writer in listed for file in writer.files if (out_dir / file).is_file()]


def output_names() -> list[str]:
    """The writers' names, in registry order (what `--outputs` takes)."""
    return [writer.name for writer in OUTPUT_WRITERS]


def outputs_help() -> str:
    """The outputs paragraph of `fmfusion run --help`."""
    return "Outputs: " + "; ".join(f"{', '.join(writer.files)}: {writer.description}" for writer in OUTPUT_WRITERS) + "."


def readme_table() -> str:
    """The README's outputs table (a test keeps the README equal to it)."""
    rows = [f"| {', '.join(f'`{file}`' for file in writer.files)} | {writer.description} |" for writer in OUTPUT_WRITERS]
    return "\n".join(["| file | content |", "|---|---|", *rows])
