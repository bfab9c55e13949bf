"""`fmfusion bench`: prepares the scenes, runs every pipeline on them in its own process, writes the report.

scenes (real + generated, cached) ──► a worker process per (pipeline, scene) ──► report ──► bench.md/.json
                                  ├──► the per-object sweep on the main scene (`bench.sweep`): a
                                  │    process per pipeline, running every cap
                                  └──► `fmfusion run` on the main scene, cold and warm (`bench.whole_run`)
"""

from __future__ import annotations

import dataclasses
import json
import shlex
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fmfusion_jax.apps.bench import report
from fmfusion_jax.apps.bench.scenes import DEFAULT_SCENE, BenchScene, prepare_generated_scene, prepare_real_scene
from fmfusion_jax.apps.bench.whole_run import measure_whole_run
from fmfusion_jax.errors import UserError
from fmfusion_jax.run.folder import prepare_output_dir

DEFAULT_OUT = Path("outputs/bench")
#: The sizes of `--quick`: a smoke test in well under a minute.
QUICK_SIZES = {
    "frames": 6,
    "objects": (2, 8),
    "generated_frames": 6,
    "width": 160,
    "height": 120,
    "peer_frames": 6,
    "sweep": (1, 4),
    "sweep_frames": 4,
}


@dataclasses.dataclass(frozen=True)
class BenchOptions:
    """What to run (the `fmfusion bench` options; see `cli/bench.py` for their meaning)."""

    out: Path = DEFAULT_OUT
    cache: Path | None = None  # scenes and detections made once; default OUT/cache
    scene: Path | None = None  # the real scene, or None
    frames: int | None = None  # frames of the real scene (None: all)
    objects: tuple[int, ...] = (4, 8, 16, 32)  # generated rooms' object counts
    generated_frames: int = 40
    width: int = 640  # generated frames
    height: int = 480
    peer: bool = True
    peer_frames: int | None = None  # the Open3D per-instance pipeline runs on this prefix (None: all)
    sweep: tuple[int, ...] = (1, 2, 4, 8, 16)  # detection caps of the per-object sweep (empty: no sweep)
    sweep_frames: int | None = 30  # the sweep runs on this prefix of the main scene (None: all)
    seed: int = 0
    overrides: tuple[str, ...] = ()  # KEY=VALUE config overrides for every scene (`--set`)
    progress: bool = True
    profile_frames: int = 0  # the last N frames of our as-run pass on the main scene traced (`--profile`; 0: none)
    whole_run: bool = True  # `fmfusion run` end to end on the main scene, cold and warm compile cache


def run_bench(
    options: BenchOptions,
    command: str = "fmfusion bench",
    say: Callable[[str], None] = lambda text: print(text, file=sys.stderr, flush=True),
) -> dict:
    """Runs the benchmark; writes `bench.md` and `bench.json` into `options.out`; returns the summary."""
    from fmfusion_jax.apps.bench.worker import peer_unavailable_reason

    out = prepare_output_dir(options.out)
    cache = options.cache or out / "cache"
    work = out / "runs"
    work.mkdir(parents=True, exist_ok=True)
    peer_reason = "--no-peer" if not options.peer else peer_unavailable_reason()
    if peer_reason and options.peer:
        say(f"Open3D peer unavailable: {peer_reason}; measuring ours only")

    scenes = _prepare_scenes(options, cache, say)
    if not scenes:
        raise UserError("nothing to benchmark: no real scene and no generated object count")
    primary = scenes[0] if scenes[0].kind == "real" else max(scenes, key=lambda s: s.objects or 0)
    runs = []
    for scene in scenes:
        run: dict = {"scene": scene.to_json()}
        traced = None
        if scene is primary and options.profile_frames:
            traced = {"frames": options.profile_frames, "trace": str(out / f"profile-{scene.name}.json.gz")}
        run["ours"] = _child("ours", scene, None, options, work, say, profile=traced)
        if peer_reason:
            run["peer"] = {"unavailable": peer_reason}
        else:
            run["peer"] = _child("peer", scene, options.peer_frames, options, work, say)
            if scene is primary:
                run["vbg"] = _child("vbg", scene, None, options, work, say)
        if scene is primary and "vbg" not in run:
            run["vbg"] = {"unavailable": peer_reason}
        runs.append(run)

    sweep = None
    if options.sweep:
        sweep = {"scene": primary.to_json(), "sweep": list(options.sweep), "frames": options.sweep_frames}
        sweep["ours"] = _child("ours-sweep", primary, options.sweep_frames, options, work, say, sweep=list(options.sweep))
        sweep["peer"] = (
            {"unavailable": peer_reason}
            if peer_reason
            else _child("peer-sweep", primary, options.sweep_frames, options, work, say, sweep=list(options.sweep))
        )

    whole_run = measure_whole_run(primary, work, say) if options.whole_run else None
    summary = report.summarize(runs, primary.name, sweep, whole_run)
    summary["command"] = command
    (out / "bench.json").write_text(
        json.dumps(
            {
                "summary": summary,
                "runs": runs,
                "sweep": sweep,
                "whole_run": whole_run,
                "options": _jsonable(dataclasses.asdict(options)),
            },
            default=float,
        )
        + "\n"
    )
    markdown = report.render_markdown(summary, runs, command)
    (out / "bench.md").write_text(markdown)
    summary["markdown"] = markdown
    return summary


def _prepare_scenes(options: BenchOptions, cache: Path, say) -> list[BenchScene]:
    scenes = []
    if options.scene is not None:
        say(f"preparing {options.scene} ({options.frames or 'all'} frames; detections simulated once into {cache})")
        scenes.append(prepare_real_scene(options.scene, cache, options.frames, options.seed, options.progress, options.overrides))
    for objects in options.objects:
        say(f"preparing a generated room with {objects} objects (made once into {cache})")
        scenes.append(
            prepare_generated_scene(
                cache,
                objects,
                options.generated_frames,
                options.width,
                options.height,
                options.seed,
                options.progress,
                options.overrides,
            )
        )
    return scenes


def _child(
    pipeline: str,
    scene: BenchScene,
    frames: int | None,
    options: BenchOptions,
    work: Path,
    say,
    sweep: list[int] | None = None,
    profile: dict | None = None,
) -> dict:
    """Runs one pipeline on one scene in a fresh Python process (`bench.worker`); its result, or
    `{"error": ...}` when it failed (its messages went to stderr). `sweep`: the caps of a sweep pipeline;
    `profile`: `{"frames", "trace"}` of `--profile`."""
    stem = f"{pipeline}-{scene.name}"
    spec_path, result_path = work / f"{stem}.spec.json", work / f"{stem}.result.json"
    spec: dict[str, Any] = {"pipeline": pipeline, "scene": scene.to_json(), "frames": frames, "progress": options.progress}
    if sweep is not None:
        spec["sweep"] = sweep
    if profile is not None:
        spec["profile"] = profile
    spec_path.write_text(json.dumps(spec))
    result_path.unlink(missing_ok=True)
    names = {
        "ours": "ours",
        "peer": "Open3D per-instance peer",
        "vbg": "Open3D VoxelBlockGrid",
        "ours-sweep": "the per-object sweep of ours",
        "peer-sweep": "the per-object sweep of the Open3D peer",
    }
    caps = f", detections capped to {' '.join(map(str, sweep))}" if sweep else ""
    say(f"running {names[pipeline]} on {scene.name} ({min(frames or scene.frames, scene.frames)} frames{caps})")
    start = time.perf_counter()
    completed = subprocess.run(
        [sys.executable, "-m", "fmfusion_jax.apps.bench.worker", str(spec_path), str(result_path)], check=False
    )
    seconds = time.perf_counter() - start
    if completed.returncode != 0 or not result_path.is_file():
        say(f"  {names[pipeline]} failed (exit {completed.returncode}) after {seconds:.0f} s")
        return {"error": f"worker exited with {completed.returncode} (command: {shlex.join(completed.args)})"}
    result = json.loads(result_path.read_text())
    result["wall_s"] = seconds
    if result.get("unavailable"):
        say(f"  {names[pipeline]} unavailable: {result['unavailable']}")
    else:
        say(f"  done in {seconds:.0f} s")
    return result


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return str(value) if isinstance(value, Path) else value


__all__ = ["BenchOptions", "run_bench", "DEFAULT_OUT"]


def run_bench_command(
    *,
    objects: list[int] | None,
    generated_frames: int | None,
    sweep: list[int] | None,
    sweep_frames: int | None,
    profile: int,
    quick: bool,
    frames: int | None,
    peer_frames: int | None,
    size: list[int] | None,
    no_scene: bool,
    scene: Path | None,
    out: Path,
    cache: Path | None,
    no_peer: bool,
    seed: int,
    overrides: list[str],
    no_progress: bool,
    command: str,
    no_whole_run: bool = False,
) -> int:
    for name, value in (
        ("frames", frames),
        ("generated_frames", generated_frames),
        ("peer_frames", peer_frames),
        ("sweep_frames", sweep_frames),
    ):
        if value is not None and value < 0:
            raise UserError(f"--{name.replace('_', '-')} must be >= 0, got {value}")
    if objects is not None and any(n < 1 for n in objects):
        raise UserError(f"--objects must be positive, got {objects}")
    if generated_frames == 0 or generated_frames == 1:
        raise UserError("--generated-frames must be >= 2")
    if sweep is not None and any(k < 1 for k in sweep):
        raise UserError(f"--sweep caps must be >= 1, got {sweep}")
    if sweep_frames == 1:
        raise UserError("--sweep-frames must be >= 2 (frame 0 warms up)")
    if profile < 0:
        raise UserError(f"--profile must be >= 0, got {profile}")

    defaults = dict(QUICK_SIZES) if quick else {}
    given: dict[str, Any] = {
        "frames": frames,
        "objects": None if objects is None else tuple(objects),
        "generated_frames": generated_frames,
        "peer_frames": peer_frames,
        "sweep": None if sweep is None else tuple(dict.fromkeys(sweep)),
        "sweep_frames": sweep_frames,
    }
    if size is not None:
        given["width"], given["height"] = size
    options = {**defaults, **{k: v for k, v in given.items() if v is not None}}
    for name in ("frames", "peer_frames", "sweep_frames"):  # 0 = all
        if options.get(name) == 0:
            options[name] = None
    real_scene = None if no_scene else _real_scene(scene, quick=quick)
    bench = BenchOptions(
        out=out,
        cache=cache,
        scene=real_scene,
        peer=not no_peer,
        seed=seed,
        overrides=tuple(overrides),
        progress=not no_progress,
        profile_frames=profile,
        whole_run=not no_whole_run,
        **options,
    )
    summary = run_bench(bench, command=command)
    print(summary["markdown"])
    print(f"written: {out / 'bench.md'}, {out / 'bench.json'}")
    return 0


def _real_scene(given: Path | None, quick: bool) -> Path | None:
    """The real scene to run: the one given (must exist), else the shared sample when present (not with
    --quick); None, saying so, when there is none."""
    if given is not None:
        if not given.is_dir():
            raise UserError(f"scene folder {given} does not exist")
        return given
    if quick:
        print("fmfusion bench: --quick runs generated rooms only (give --scene to add the real scene)", file=sys.stderr)
        return None
    if DEFAULT_SCENE.is_dir():
        return DEFAULT_SCENE
    print(f"fmfusion bench: no real scene at {DEFAULT_SCENE} (give one with --scene); generated rooms only", file=sys.stderr)
    return None
