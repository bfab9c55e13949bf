"""`fmfusion batch`: many scenes, one command; each scene a `fmfusion run` of its own, one pooled benchmark.

Each scene runs in a process of its own (`python -m fmfusion_jax.cli run ...`, after `simulate` with
`--simulate`), so a scene that fails, crashes or runs past `--scene-timeout` is recorded with its error and
the batch goes on. The executors give the same per-scene results: local worker processes (`--workers N`), or
one Ray task per scene (`--ray ADDRESS`; needs the `cluster` extra and a file system the workers share).

Outputs in OUT: `<scene>/` (the outputs of `fmfusion run`), `batch.json` (written atomically as scenes
finish: the state of every scene, so `--resume` skips the complete ones), and at the end `batch.md` and
`batch.csv` (per-scene table) with the pooled benchmark over all scored scenes (the ScanNet evaluation pools
the matches of all scenes; it is not a mean of per-scene APs).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import csv
import dataclasses
import io
import json
import logging
import os
import re
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax

from fmfusion_jax.config import load_config
from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.evaluation.scannet_benchmark import evaluate_scenes
from fmfusion_jax.io.atomic import write_atomic
from fmfusion_jax.io.benchmark_format import read_benchmark_predictions
from fmfusion_jax.io.detections import DetectionFolder
from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
from fmfusion_jax.io.scene import detect_layout, open_dataset_scene
from fmfusion_jax.mapping.batch import MapperBatch
from fmfusion_jax.run.command import write_outputs

log = logging.getLogger(__name__)

BATCH_FILE = "batch.json"
#: The detections of `--simulate` and `--models`, per scene, under OUT.
SIMULATED_DIR = "_detections"


@dataclasses.dataclass(frozen=True)
class SceneTask:
    """One scene's job: the commands to run and where its outputs go."""

    name: str
    scene: str
    out: str
    detections: str
    simulate: bool
    run_options: tuple[str, ...]
    timeout_s: float | None
    memory_mib: float | None = None
    models: str | None = None  # detections made by `fmfusion detect --models` into `detections` first

    def detection_command(self, command: list[str]) -> list[str] | None:
        """The child command that makes the scene's detections (`simulate` or `detect`), or None (given)."""
        if self.simulate:
            return command + ["simulate", self.scene, "--out", self.detections, "--no-progress"]
        if self.models is not None:
            config_options = [option for option in self.run_options if option != "--restart"]
            detect = ["detect", self.scene, "--models", self.models, "--out", self.detections, "--no-progress"]
            return command + detect + config_options
        return None


def list_scenes(source: Path, root: Path | None = None) -> list[Path]:
    """The scenes of a dataset: the entries of `source` that are scenes (folders of any layout `detect_layout`
    knows, and recording files: ROS 1 / RealSense bags, Record3D exports), or the scene ids of a split file (one
    per line, `#` comments) resolved under `root` (default: the split file's folder). A listed scene that does
    not exist is a `UserError`."""
    if source.is_dir():
        scenes = []
        for child in sorted(source.iterdir()):
            try:
                detect_layout(child)
            except (UserError, DataError, OSError):  # not a scene (a README, a trajectory beside a bag, ...)
                continue
            scenes.append(child)
        if not scenes:
            raise UserError(
                f"{source}: no scene inside (a ScanNet or SceneNN folder, a TUM, Replica or Redwood recording, a ROS "
                "bag, a Record3D export or a RealSense recording)"
            )
        return scenes
    if not source.is_file():
        raise UserError(f"{source}: neither a folder of scenes nor a split file")
    base = root or source.parent
    ids = [line.split("#")[0].strip() for line in source.read_text().splitlines()]
    scenes = [base / scene_id for scene_id in ids if scene_id]
    missing = [str(path) for path in scenes if not path.exists()]
    if missing:
        raise UserError(f"{source}: {len(missing)} listed scenes not found under {base} (first: {missing[0]})")
    if not scenes:
        raise UserError(f"{source}: the split file lists no scene")
    return scenes


def detections_for(pattern: str, scene: Path) -> str:
    """`--detections` pattern for one scene: `{scene}` is the scene's name, `{root}` its parent folder."""
    return pattern.format(scene=scene.name, root=scene.parent)


#: Seconds between two progress lines of a running scene.
PROGRESS_EVERY_S = 15.0


#: JAX's GPU memory preallocation (75 % of the device per process by default), turned off for the scene processes
#: that share a device: with it, the third or fourth process on one GPU cannot start ("no supported devices").
PREALLOCATE_ENV = "XLA_PYTHON_CLIENT_PREALLOCATE"


def child_environment(concurrent_scenes: int) -> dict[str, str]:
    """The environment of a scene's child processes: this one's, unbuffered, and without JAX's GPU memory
    preallocation when several scenes run at once (each takes what it uses; a user's own setting is kept). On a
    CPU the setting changes nothing."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if concurrent_scenes > 1:
        env.setdefault(PREALLOCATE_ENV, "false")
    return env


def run_scene(
    task: SceneTask, progress: Callable[[str, str], None] | None = None, env: dict[str, str] | None = None
) -> dict[str, Any]:
    """Runs one scene's commands in child processes (environment `env`, default `child_environment(1)`); returns
    its record (status ok / failed / timeout / memory). `progress(scene, text)` hears how far the fusion got every
    `PROGRESS_EVERY_S` seconds."""
    start = time.perf_counter()
    record: dict[str, Any] = {"scene": task.name, "path": task.scene, "out": task.out}
    command = [sys.executable, "-m", "fmfusion_jax.cli"]
    steps = []
    making = task.detection_command(command)
    if making is not None:
        steps.append(making)
    steps.append(command + ["run", task.scene, "--detections", task.detections, "--out", task.out, *task.run_options])
    for argv in steps:
        left = None if task.timeout_s is None else max(1.0, task.timeout_s - (time.perf_counter() - start))
        report = None if progress is None else (lambda text: progress(task.name, text))  # noqa: E731
        outcome = _run_child(argv, left, task.memory_mib, report, env)
        if outcome["status"] != "ok":
            record.update(status=outcome["status"], error=outcome["error"])
            break
    else:
        record["status"] = "ok"
        record.update(_summary_fields(json.loads((Path(task.out) / "run.json").read_text())))
    record["seconds"] = round(time.perf_counter() - start, 2)
    return record


def _summary_fields(summary: dict[str, Any]) -> dict[str, Any]:
    """A scene's record fields from its run summary (`run.json`)."""
    benchmark = summary.get("benchmark", {})
    fields = {
        "frames": summary["frames"],
        "detection_frames": summary["detection_frames"],
        "instances": summary["instances"],
        "mAP50": benchmark.get("mAP50"),
        "skipped_frames": len(summary.get("skipped_frames", [])),
        "peak_rss_mib": summary.get("peak_rss_mib"),
    }
    if "error" in benchmark:
        fields["not_scored"] = benchmark["error"]
    return fields


def _run_child(
    argv: list[str],
    timeout_s: float | None,
    memory_mib: float | None = None,
    progress: Callable[[str], None] | None = None,
    env: dict[str, str] | None = None,
) -> dict[str, Any]:
    """One child process: its status (ok, failed, timeout, memory) and its error line. The child is stopped
    past `timeout_s` seconds or `memory_mib` MiB of resident memory (polled twice a second); `progress` hears
    the last frame count of its progress bar every `PROGRESS_EVERY_S` seconds."""

    with tempfile.TemporaryFile("w+") as stderr_file:
        process = subprocess.Popen(
            argv, stdout=subprocess.DEVNULL, stderr=stderr_file, text=True, env=env or child_environment(1)
        )
        start = last_report = time.perf_counter()
        stopped = None
        while process.poll() is None:
            if progress is not None and time.perf_counter() - last_report > PROGRESS_EVERY_S:
                last_report = time.perf_counter()
                stderr_file.seek(0)
                counts = re.findall(r"(\d+)/(\d+) \[", stderr_file.read())
                if counts:
                    progress(f"{counts[-1][0]}/{counts[-1][1]} frames")
            if timeout_s is not None and time.perf_counter() - start > timeout_s:
                stopped = {"status": "timeout", "error": f"stopped: past the scene timeout ({timeout_s:.0f} s were left)"}
            elif memory_mib is not None and _resident_mib(process.pid) > memory_mib:
                stopped = {"status": "memory", "error": f"stopped: over the scene memory limit ({memory_mib:.0f} MiB)"}
            if stopped:
                process.kill()
                process.wait()
                return stopped
            with contextlib.suppress(subprocess.TimeoutExpired):  # returns as soon as the child ends
                process.wait(timeout=0.5)
        stderr_file.seek(0)
        stderr = stderr_file.read()
    lines = [line for line in stderr.splitlines() if line.strip() and not line.startswith("WARNING")]
    if process.returncode != 0:
        error = next((line for line in reversed(lines) if "error" in line.lower()), lines[-1] if lines else "")
        return {"status": "failed", "error": f"exit {process.returncode}: {error}"}
    return {"status": "ok", "error": None}


def _resident_mib(pid: int) -> float:
    """A process's resident memory, MiB (Linux /proc; 0 where it cannot be read)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0.0


class Batch:
    """A batch over scenes: its tasks, its record file and its executors."""

    def __init__(
        self,
        scenes: Sequence[Path],
        out: Path,
        *,
        detections: str | None,
        simulate: bool,
        run_options: Sequence[str] = (),
        timeout_s: float | None = None,
        memory_mib: float | None = None,
        models: str | Path | None = None,
    ):
        if (detections is not None) + simulate + (models is not None) != 1:
            raise UserError("give one of --detections PATTERN, --simulate or --models DIR")
        names = [scene.name for scene in scenes]
        if len(set(names)) != len(names):
            raise UserError("two scenes share a folder name; their outputs would collide")
        self.out = out
        self.tasks = [
            SceneTask(
                scene.name,
                str(scene),
                str(out / scene.name),
                str(out / SIMULATED_DIR / scene.name) if detections is None else detections_for(detections, scene),
                simulate,
                tuple(run_options),
                timeout_s,
                memory_mib,
                None if models is None else str(Path(models).resolve()),
            )
            for scene in scenes
        ]
        self.records: dict[str, dict[str, Any]] = {}
        self._position = {task.name: i for i, task in enumerate(self.tasks)}  # the record file's order

    def load(self) -> None:
        """Reads the records of an earlier run of this batch (for `--resume`)."""
        path = self.out / BATCH_FILE
        if path.is_file():
            try:
                self.records = {r["scene"]: r for r in json.loads(path.read_text()).get("scenes", [])}
            except (json.JSONDecodeError, KeyError, TypeError) as error:
                raise UserError(f"{path}: unreadable batch record ({error}); remove it or drop --resume") from None

    def pending(self, resume: bool) -> list[SceneTask]:
        """The tasks to run: all, or with `resume` those not complete (record ok and run.json present)."""
        if not resume:
            return list(self.tasks)
        return [
            t
            for t in self.tasks
            if not (self.records.get(t.name, {}).get("status") == "ok" and (Path(t.out) / "run.json").is_file())
        ]

    def record(self, result: dict[str, Any]) -> None:
        self.records[result["scene"]] = result
        scenes = sorted(self.records.values(), key=lambda r: self._position.get(r["scene"], 0))
        write_atomic(self.out / BATCH_FILE, json.dumps({"scenes": scenes}, indent=1))

    def run_local(
        self,
        tasks: Sequence[SceneTask],
        workers: int,
        report: Callable[[dict], None],
        progress: Callable[[str, str], None] | None = None,
    ) -> None:
        """Runs `tasks` in up to `workers` concurrent scene processes (`progress`: see `run_scene`), which share the
        device (`child_environment`)."""
        env = child_environment(min(workers, len(tasks)))
        with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
            futures = [pool.submit(run_scene, task, progress, env) for task in tasks]
            for future in concurrent.futures.as_completed(futures):
                result = future.result()
                self.record(result)
                report(result)

    def run_ray(
        self,
        tasks: Sequence[SceneTask],
        address: str,
        report: Callable[[dict], None],
        cpus_per_scene: float = 1.0,
        gpus_per_scene: float = 0.0,
    ) -> None:
        """One Ray task per scene (`cpus_per_scene` CPUs and `gpus_per_scene` GPUs declared), gathered on the
        driver as they finish."""
        try:
            import ray
        except ImportError:
            raise UserError("--ray needs Ray: pip install -e '.[cluster]'") from None
        if not ray.is_initialized():
            ray.init(address=None if address == "local" else address, log_to_driver=False)
        remote = ray.remote(num_cpus=cpus_per_scene, num_gpus=gpus_per_scene)(run_scene)
        pending = {remote.remote(task): task for task in tasks}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                task = pending.pop(ref)
                try:
                    result = ray.get(ref)
                except Exception as error:  # noqa: BLE001 - a lost worker is one scene's failure
                    result = {
                        "scene": task.name,
                        "path": task.scene,
                        "out": task.out,
                        "status": "failed",
                        "error": f"ray: {error}",
                    }
                self.record(result)
                report(result)

    def run_vmapped(self, tasks: Sequence[SceneTask], size: int, config, report: Callable[[dict], None]) -> None:
        """Fuses `size` scenes at a time in this process, vmapped on one device (`MapperBatch`: one compiled
        step for the group, maps padded to a common block layout covering every scene's bounds); then writes
        each scene's outputs as `fmfusion run` does. Scenes of another image size than the group's first go
        into a later group. A group that fails records its error for each of its scenes."""
        queue = list(tasks)
        while queue:
            group = [queue.pop(0)]
            while queue and len(group) < size:
                group.append(queue.pop(0))
            for result in _fuse_group(group, config):
                self.record(result)
                report(result)


def warn_vmapped_on_cpu() -> None:
    """Warns when `--batch` would run on the CPU backend: the vmapped step is built for a GPU,
    where the maps' steps run side by side; on a CPU each of its selects and scatters walks every map's whole pool,
    so separate processes are faster (3 generated rooms of 12 frames at 160 x 120 on a 2-core VM, warm compile
    cache, with the pool sized to the rooms: `--batch 3` 26.5 s, `--workers 1` 17.9 s, `--workers 2` 13.2 s)."""
    if jax.default_backend() == "cpu":
        log.warning(
            "--batch fuses the scenes in one vmapped step, which is built for a GPU: on this CPU it is slower than "
            "one process per scene (--workers N, N up to the cores)"
        )


def _fuse_group(group: Sequence[SceneTask], config) -> list[dict[str, Any]]:

    start = time.perf_counter()
    records: list[dict[str, Any]] = [{"scene": t.name, "path": t.scene, "out": t.out} for t in group]
    try:
        for task in group:
            making = task.detection_command([sys.executable, "-m", "fmfusion_jax.cli"])
            if making is not None:
                outcome = _run_child(making, task.timeout_s)
                if outcome["status"] != "ok":
                    raise UserError(f"{task.name}: {making[3]}: {outcome['error']}")
        dataset = config.dataset
        scenes = [open_dataset_scene(t.scene, dataset) for t in group]
        batch = MapperBatch.for_scenes(scenes, config)  # sized from a sample of each scene's frames
        image_shape = (batch.map_config.image_height, batch.map_config.image_width)
        folders = [DetectionFolder(t.detections, image_shape=image_shape) for t in group]
        maps_mib = len(group) * batch.map_config.memory_bytes() / 2**20
        log.info(
            "fusing %s in one vmapped step: %s each, ~%.0f MiB of maps",
            ", ".join(t.name for t in group),
            batch.map_config.describe(),
            maps_mib,
        )
        for position in range(max(len(s) for s in scenes)):
            frames = [s.read_frame(position) if position < len(s) else None for s in scenes]
            detections = [f.get(fr.name) if fr is not None else None for f, fr in zip(folders, frames)]
            batch.integrate(frames, detections)
        results = batch.finalize()
        seconds = (time.perf_counter() - start) / len(group)
        for task, scene, result, record in zip(group, scenes, results, records):
            out = Path(task.out)
            out.mkdir(parents=True, exist_ok=True)
            summary = write_outputs(result, scene, out)  # it clears an earlier run's outputs first
            record.update(
                status="ok", **_summary_fields(summary), seconds=round(seconds, 2), batched_with=[t.name for t in group]
            )
    except (UserError, OSError) as error:
        for record in records:
            record.setdefault("status", "failed")
            if record["status"] != "ok":
                record["error"] = f"batch of {len(group)}: {error}"
    return records


def pooled_benchmark(records: Sequence[dict[str, Any]]):
    """`(result, scene names)`: the ScanNet benchmark pooled over the scenes that ran and have ground truth
    (result None when none has)."""

    pairs, names = [], []
    for record in records:
        txt = Path(record["out"]) / "benchmark" / f"{record['scene']}.txt"
        if record.get("status") != "ok" or not txt.is_file():
            continue
        gt_ids = load_scannet_ground_truth(Path(record["path"])).benchmark_ids()
        pairs.append((gt_ids, read_benchmark_predictions(txt, len(gt_ids))))
        names.append(record["scene"])
    return (evaluate_scenes(pairs, scene_names=names) if pairs else None), names


COLUMNS = ("scene", "status", "frames", "instances", "mAP50", "seconds", "peak_rss_mib", "skipped_frames", "error")


def write_reports(out: Path, records: Sequence[dict[str, Any]], pooled, scored: Sequence[str]) -> str:
    """batch.md and batch.csv (per-scene table, the pooled score, the failures); returns the Markdown."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, extrasaction="ignore")
    writer.writeheader()
    for record in records:
        writer.writerow({k: record.get(k, "") for k in COLUMNS})
    write_atomic(out / "batch.csv", buffer.getvalue())

    def cell(record: dict, key: str) -> str:
        value = record.get(key)
        if value is None:
            return "-"
        return f"{100 * value:.1f}" if key == "mAP50" else str(value)

    ok = [r for r in records if r.get("status") == "ok"]
    lines = ["# fmfusion batch", "", f"{len(records)} scenes: {len(ok)} ok, {len(records) - len(ok)} failed.", ""]
    if pooled is not None:
        lines += [
            f"Pooled ScanNet benchmark over the {len(scored)} scored scenes: mAP {100 * pooled.mAP:.1f}, "
            f"mAP50 {100 * pooled.mAP50:.1f}, mAP25 {100 * pooled.mAP25:.1f} (%).",
            "",
        ]
    header = ["scene", "status", "frames", "instances", "AP50 %", "seconds", "peak RSS MiB", "skipped frames"]
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in records:
        lines.append("| " + " | ".join(cell(r, k) for k in COLUMNS[:-1]) + " |")
    unscored = [r for r in records if r.get("not_scored")]
    if unscored:
        lines += ["", "## Not scored", ""] + [f"- `{r['scene']}`: {r['not_scored']}" for r in unscored]
    failed = [r for r in records if r.get("status") != "ok"]
    if failed:
        lines += ["", "## Failures", ""] + [f"- `{r['scene']}`: {r.get('status')}: {r.get('error')}" for r in failed]
    text = "\n".join(lines) + "\n"
    write_atomic(out / "batch.md", text)
    return text


def run_batch(
    *,
    workers: int,
    scene_timeout: float | None,
    scene_memory: float | None,
    config: str | None,
    overrides: list[str],
    dataset: Path,
    root: Path | None,
    out: Path,
    detections: str | None,
    simulate: bool,
    models: Path | None,
    resume: bool,
    no_progress: bool,
    batch_size: int | None,
    ray: str | None,
    ray_cpus: float,
    ray_gpus: float,
) -> int:

    if workers < 1:
        raise UserError(f"--workers must be >= 1, got {workers}")
    if scene_timeout is not None and scene_timeout <= 0:
        raise UserError(f"--scene-timeout must be > 0, got {scene_timeout}")
    if scene_memory is not None and scene_memory <= 0:
        raise UserError(f"--scene-memory must be > 0 GiB, got {scene_memory}")
    load_config(config or "scannet", overrides)  # a bad config fails now, not in every scene
    scenes = list_scenes(dataset, root)
    options = ["--config", str(Path(config).resolve()) if os.path.isfile(config) else config] if config else []
    for item in overrides:
        options += ["--set", item]
    options.append("--restart")  # an interrupted scene of an earlier batch starts over
    out.mkdir(parents=True, exist_ok=True)
    batch = Batch(
        scenes,
        out,
        detections=detections,
        simulate=simulate,
        models=models,
        run_options=options,
        timeout_s=scene_timeout,
        memory_mib=None if scene_memory is None else 1024 * scene_memory,
    )
    if resume:
        batch.load()
    tasks = batch.pending(resume)
    skipped = len(batch.tasks) - len(tasks)
    total = len(tasks)
    print(f"{len(batch.tasks)} scenes, {total} to run" + (f" ({skipped} done before)" if skipped else ""), file=sys.stderr)
    done = 0

    def report(record: dict) -> None:
        nonlocal done
        done += 1
        if not no_progress:
            score = f", AP50 {100 * record['mAP50']:.1f}" if record.get("mAP50") is not None else ""
            what = record["status"] if record["status"] == "ok" else f"{record['status']}: {record.get('error')}"
            print(f"[{done}/{total}] {record['scene']}: {what}{score} ({record.get('seconds', 0):.0f} s)", file=sys.stderr)

    if batch_size:
        if batch_size < 1 or ray:
            raise UserError("--batch K needs K >= 1 and no --ray")
        warn_vmapped_on_cpu()
        batch.run_vmapped(tasks, batch_size, load_config(config or "scannet", overrides), report)
    elif ray:
        batch.run_ray(tasks, ray, report, cpus_per_scene=ray_cpus, gpus_per_scene=ray_gpus)
    else:
        batch.run_local(
            tasks,
            workers,
            report,
            None if no_progress else lambda scene, text: print(f"  {scene}: {text}", file=sys.stderr),
        )
    records = [batch.records[t.name] for t in batch.tasks if t.name in batch.records]
    pooled, scored = pooled_benchmark(records)
    print(write_reports(out, records, pooled, scored))
    failed = sum(r.get("status") != "ok" for r in records)
    return 1 if failed else 0
