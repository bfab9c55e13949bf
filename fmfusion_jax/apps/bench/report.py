"""The benchmark's figures out of the workers' per-frame times, and the Markdown report (like the paper's
Table IV: time per stage, then base + per-object cost: from the controlled sweep, `bench.sweep`, with the
generated rooms as context).

Conventions: every figure is a median over frames of milliseconds per frame (per call for the stages
that do not run every frame), over frames 1.. (frame 0 warms up), leaving out the calls that compiled.
Ours and the Open3D peer are compared on the same frames: the peer's prefix (`--peer-frames`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from fmfusion_jax.apps.bench.figures import (
    AS_RUN_LABEL,
    READER_LABEL,
    TIMED_WHOLE_LABEL,
    _pass,
    _usable,
    frame_sums,
    median,
    why_missing,
)
from fmfusion_jax.apps.bench.profile import profile_lines
from fmfusion_jax.apps.bench.stages import FUSION_STAGES
from fmfusion_jax.apps.bench.targets import _ms, _ratio, compile_cache_state, targets, whole_run_targets
from fmfusion_jax.xla_options import GPU_COMMAND_BUFFER_FLAG

#: Frames the worker's pass without timers reads ahead at a time (`worker._as_run_pass`; the first call of each
#: chunk finds the device idle and is left out). Defined here, where the report's text needs it too.
AS_RUN_CHUNK = 32

#: The peer's stages of a detection frame (keys of `Open3DInstancePipeline.add_frame`'s result).
PEER_FUSION_STAGES = ("tsdf", "projection", "association", "label_fusion", "integration")


#: Rows of the stage table: (label, our pass ("staged", "fused" or "as_run"), our keys, the peer's keys);
#: keys None = every stage of the frame. Several keys: their sum per frame.
STAGE_ROWS = (
    ("global TSDF", "staged", ("tsdf",), ("tsdf",)),
    ("detection image + depth filter", "staged", ("detections",), ()),
    ("projection", "staged", ("projection",), ("projection",)),
    ("association", "staged", ("association",), ("association",)),
    ("label fusion", "staged", ("label_fusion",), ("label_fusion",)),
    ("instance integration", "staged", ("integration",), ("integration",)),
    ("merge (removal + online merge)", "fused", ("refine",), ("merge",)),
    ("geometry fusion (per call)", "fused", ("geometry_fusion",), ("geometry_fusion",)),
    (READER_LABEL, "fused", ("prepare",), ()),
    ("host: frame sent, steps dispatched, statistics read", "fused", ("host",), ()),
    ("host: the Mapper's frame checks, schedule and growth check", "fused", ("mapper",), ()),
    ("sum of the stages above, jitted apart", "staged", FUSION_STAGES, PEER_FUSION_STAGES),
    ("**fusion step** (`fuse_detections`, one jit)", "fused", ("fusion",), PEER_FUSION_STAGES),
    (TIMED_WHOLE_LABEL, "fused", None, None),
    (AS_RUN_LABEL, "as_run", None, None),
)

#: Our timed functions, by timer name (`compile_ms` keys of the ours worker).
COMPILED_NAMES = {
    "fusion": "fuse_detections",
    "tsdf": "integrate_frame (non-detection frames)",
    "refine": "refine (_merge_step)",
    "geometry_fusion": "fuse_geometry",
    "stage:tsdf": "integrate_frame",
    "stage:detections": "detection_image",
    "stage:projection": "project_instances",
    "stage:association": "associate",
    "stage:label_fusion": "fuse_table",
    "stage:integration": "integrate_instance_votes",
}


def fit_line(x: ArrayLike, y: ArrayLike) -> tuple[float, float]:
    """Least-squares `y = base + slope * x`: `(base, slope)`; NaNs with fewer than two distinct x."""
    xs, ys = np.asarray(x, np.float64), np.asarray(y, np.float64)
    keep = np.isfinite(xs) & np.isfinite(ys)
    xs, ys = xs[keep], ys[keep]
    if len(np.unique(xs)) < 2:
        return math.nan, math.nan
    design = np.stack([np.ones_like(xs), xs], axis=1)
    (base, slope), *_ = np.linalg.lstsq(design, ys, rcond=None)
    return float(base), float(slope)


def stage_table(ours: dict, peer: dict | None) -> dict:
    """Rows `{label, ours_all, ours, peer, ratio}` (ms; ratio = peer / ours on the peer's frames) and the
    frame windows they cover."""
    n = len(ours.get("frames", []))
    p = len(peer["frames"]) if _usable(peer) else 0
    rows = []
    for label, pass_name, keys, peer_keys in STAGE_ROWS:
        frames, compiled = _pass(ours, pass_name)
        row: dict[str, Any] = {
            "label": label,
            "ours_all": median(frame_sums(frames, compiled, keys)),
            "ours": math.nan,
            "peer": math.nan,
            "ratio": math.nan,
        }
        if p:
            assert peer is not None  # p > 0: the peer is usable
            row["ours"] = median(frame_sums(frames, compiled, keys, stop=p))
            if peer_keys is None or peer_keys:
                row["peer"] = median(frame_sums(peer["frames"], None, peer_keys, stop=p))
            row["ratio"] = row["peer"] / row["ours"] if row["ours"] > 0 else math.nan
        rows.append(row)
    return {"rows": rows, "frames": n, "peer_frames": p}


def whole_frame_means(ours: dict, peer: dict | None) -> str:
    """A sentence with the mean whole frame of each pass (the medians leave out the periodic geometry fusion's frames;
    the means spread it), or "" when ours ran no pass without timers."""
    if not ours.get("run_frames"):
        return ""
    run = _mean(frame_sums(ours["run_frames"], ours.get("run_compiled"), None))
    timed = _mean(frame_sums(ours.get("frames", []), ours.get("compiled"), None))
    text = (
        "Means per frame (the periodic geometry fusion spread over the frames): "
        f"ours {_ms(run)} ms as run, {_ms(timed)} ms with stages timed"
    )
    if _usable(peer):
        text += f"; the Open3D peer {_ms(_mean(frame_sums(peer['frames'], None, None)))} ms"
    return text + "."


def whole_frame_ms(result: dict, stop: int | None = None) -> float:
    """Median ms per frame of everything the pipeline did in a frame (ours: the fused pass)."""
    return median(frame_sums(result["frames"], result.get("compiled"), None, stop=stop))


def per_object_costs(generated: Sequence[dict]) -> dict:
    """Per generated scene the load (detections per frame, live instances) and the whole-frame ms, and the
    least-squares lines `ms = base + per_object * load` for us and the peer."""
    points = []
    for entry in generated:
        scene, ours, peer = entry["scene"], entry.get("ours"), entry.get("peer")
        if not _usable(ours):
            continue
        point = {
            "scene": scene["name"],
            "objects": scene.get("objects"),
            "room_size": scene.get("room_size"),
            "frames": len(ours["frames"]),
            "detections": float(np.mean(ours["detections_in"][1:] or [math.nan])),
            "live_instances": float(np.mean(ours["live_instances"][1:] or [math.nan])),
            "fusion_ms": median(frame_sums(ours["frames"], ours["compiled"], ("fusion",))),
            "whole_ms": whole_frame_ms(ours),
        }
        if _usable(peer):
            point.update(
                peer_frames=len(peer["frames"]),
                peer_whole_ms=whole_frame_ms(peer),
                peer_detections=float(np.mean(peer["detections_in"][1:] or [math.nan])),
                peer_live_instances=float(np.mean(peer["live_instances"][1:] or [math.nan])),
            )
        points.append(point)

    def fit(load: str, ms: str) -> dict:
        have = [q for q in points if ms in q]
        base, slope = fit_line([q[load] for q in have], [q[ms] for q in have])
        return {"base_ms": base, "per_object_ms": slope, "points": len(have)}

    fits = {
        "ours_vs_detections": fit("detections", "whole_ms"),
        "ours_vs_instances": fit("live_instances", "whole_ms"),
        "ours_fusion_vs_detections": fit("detections", "fusion_ms"),
        "peer_vs_detections": fit("peer_detections", "peer_whole_ms"),
        "peer_vs_instances": fit("peer_live_instances", "peer_whole_ms"),
    }
    return {"points": points, "fits": fits}


def _mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if len(values) else math.nan


def sweep_costs(sweep: dict | None) -> dict | None:
    """The controlled sweep's figures: per cap `k` the mean detections fused per frame and live
    instances, our fusion step and whole frame ms and the peer's (medians over frames 1..); and the lines
    `ms = base + per_object * detections fused per frame`. None when no sweep ran."""
    if not sweep:
        return None
    ours, peer = sweep.get("ours"), sweep.get("peer")
    have_ours = bool(ours and "runs" in ours and not ours.get("error"))
    have_peer = bool(peer and "runs" in peer and not peer.get("error") and not peer.get("unavailable"))
    by_k: dict[int, dict] = {}
    for name, result, fusion_keys in (("ours", ours, ("fusion",)), ("peer", peer, PEER_FUSION_STAGES)):
        if not (have_ours if name == "ours" else have_peer):
            continue
        assert result is not None  # have_ours / have_peer hold only for a result
        for run in result["runs"]:
            point = by_k.setdefault(run["k"], {"k": run["k"]})
            point.update(
                {
                    f"{name}_frames": len(run["frames"]),
                    f"{name}_detections": _mean(run["detections_fused"][1:]),
                    f"{name}_detections_in": _mean(run["detections_in"][1:]),
                    f"{name}_live_instances": _mean(run["live_instances"][1:]),
                    f"{name}_fusion_ms": median(frame_sums(run["frames"], run["compiled"], fusion_keys)),
                    f"{name}_whole_ms": median(frame_sums(run["frames"], run["compiled"], None)),
                }
            )
    points = [by_k[k] for k in sorted(by_k)]

    def fit(name: str, ms: str) -> dict:
        have = [q for q in points if f"{name}_{ms}" in q]
        base, slope = fit_line([q[f"{name}_detections"] for q in have], [q[f"{name}_{ms}"] for q in have])
        return {"base_ms": base, "per_object_ms": slope, "points": len(have)}

    fits = {
        "ours_whole": fit("ours", "whole_ms"),
        "ours_fusion": fit("ours", "fusion_ms"),
        "peer_whole": fit("peer", "whole_ms"),
        "peer_fusion": fit("peer", "fusion_ms"),
    }
    return {
        "scene": sweep["scene"]["name"],
        "kind": sweep["scene"]["kind"],
        "caps": list(sweep.get("sweep", [])),
        "points": points,
        "fits": fits,
        "groups": (ours or {}).get("groups"),
        "ours_note": "" if have_ours else why_missing(ours),
        "peer_note": "" if have_peer else why_missing(peer),
    }


def summarize(runs: Sequence[dict], primary: str, sweep: dict | None = None, whole_run: dict | None = None) -> dict:
    """The report's figures out of the runs (`{"scene": BenchScene json, "ours", "peer", "vbg"}` each), the
    per-object sweep (`{"scene", "sweep", "frames", "ours", "peer"}`, or None) and `fmfusion run` end to end on the
    main scene (`whole_run.measure_whole_run`, or None)."""
    by_name = {run["scene"]["name"]: run for run in runs}
    main = by_name[primary]
    ours, peer, vbg = main.get("ours"), main.get("peer"), main.get("vbg")
    summary: dict = {"primary": primary, "device": (ours or {}).get("device")}
    if _usable(ours):
        summary["stages"] = stage_table(ours, peer)
        summary["compile_ms"] = {COMPILED_NAMES.get(k, k): v for k, v in ours.get("compile_ms", {}).items()}
        tsdf = median(frame_sums(ours["stage_frames"], ours["stage_compiled"], ("tsdf",)))
        summary["vbg"] = {"ours_ms": tsdf, "vbg_ms": math.nan, "ratio": math.nan, "note": why_missing(vbg)}
        if _usable(vbg):
            vbg_ms = median(frame_sums(vbg["frames"], None, ("tsdf",)))
            summary["vbg"].update(vbg_ms=vbg_ms, ratio=tsdf / vbg_ms if vbg_ms > 0 else math.nan, note="")
    summary["memory"] = {
        name: {
            k: result.get(k)
            for k in ("peak_rss_mb", "baseline_rss_mb", "device_memory_mb", "map_state_mb")
            if result.get(k) is not None
        }
        for name, result in (("ours", ours), ("peer", peer), ("vbg", vbg))
        if _usable(result)
    }
    summary["per_object"] = per_object_costs([run for run in runs if run["scene"]["kind"] == "generated"])
    summary["sweep"] = sweep_costs(sweep)
    summary["whole_run"] = whole_run
    summary["targets"] = targets(summary, main) + whole_run_targets(whole_run, main)
    return summary


def _flags_worth_naming(device: dict) -> bool:
    """Whether bench.md names the run's XLA_FLAGS: always on an accelerator, on the CPU unless they are only the
    GPU options that `fmfusion` sets itself (which the CPU ignores)."""
    flags = device.get("xla_flags") or ""
    return bool(flags.strip()) and (device.get("platform") != "cpu" or bool(flags.replace(GPU_COMMAND_BUFFER_FLAG, "").strip()))


def render_markdown(summary: dict, runs: Sequence[dict], command: str) -> str:
    """bench.md: device, the stage table, compile times, memory, VoxelBlockGrid, per-object cost, targets."""
    device = summary.get("device") or {}
    by_name = {run["scene"]["name"]: run for run in runs}
    main = by_name[summary["primary"]]
    scene = main["scene"]
    lines = [
        "# fmfusion bench",
        "",
        f"Command: `{command}`  ",
        f"Device: {device.get('device_kind', '?')} ({device.get('platform', '?')}), "
        f"{device.get('cpus', '?')} CPUs, "
        f"jax {device.get('jax', '?')}; Open3D {_peer_version(runs) or 'not run'}.  ",
        *([f"XLA_FLAGS: `{device['xla_flags']}`  "] if _flags_worth_naming(device) else []),
        "Figures: median ms per frame over frames 1.. (frame 0 warms up; calls that compiled left out).",
        "",
    ]
    stages = summary.get("stages")
    lines += [f"## Time per stage: {scene['name']} ({scene['kind']}, {scene['frames']} frames)", ""]
    if stages is None:
        lines += [f"Our pipeline did not run: {why_missing(main.get('ours'))}", ""]
    else:
        p = stages["peer_frames"]
        peer_note = (
            f"compared on frames 1-{p - 1} (the frames the peer ran)" if p else f"not run: {why_missing(main.get('peer'))}"
        )
        lines += [
            f"Ours vs the Open3D per-instance reference pipeline (global ScalableTSDFVolume + one volume per "
            f"instance), {peer_note}. Stage rows time each stage jitted apart; the fusion step is the same "
            "stages in one jit. Timing a stage waits for its result, so in the timed rows the host's work and the "
            "device's add up; the last row is a pass without timers, as `fmfusion run` fuses (each step dispatched "
            "without waiting while reader threads prepare the next frames, and waits only to read the frame "
            f"before's statistics; the first call after each {AS_RUN_CHUNK} frames read ahead left out). "
            "The targets judge that row; the peer runs synchronously, so its whole frame is the same in both.",
            "",
            f"| stage | ours, ms ({f'frames 1-{p - 1}' if p else 'the peer frames'}) | Open3D peer, ms | "
            "peer / ours | "
            f"ours, ms (all {stages['frames']} frames) |",
            "|---|---:|---:|---:|---:|",
        ]
        for row in stages["rows"]:
            lines.append(
                f"| {row['label']} | {_ms(row['ours'])} | {_ms(row['peer'])} | {_ratio(row['ratio'])} | {_ms(row['ours_all'])} |"
            )
        ours = main["ours"]
        means = whole_frame_means(ours, main.get("peer"))
        if means:
            lines += ["", means]
        lines += [
            "",
            f"Geometry fusion runs every {ours.get('geometry_fusion_every')} frames. Map (as `fmfusion run` sizes and "
            f"grows it; {ours.get('growths', 0)} growth(s), their recompiling calls left out): {ours.get('map')}; "
            f"{ours.get('blocks_used')} of {ours.get('block_capacity')} blocks used; counters "
            f"{ours.get('counters')}.",
            "",
        ]
        for mismatch in ("staged_mismatch", "as_run_mismatch"):
            if ours.get(mismatch):
                lines += [f"**Warning**: {ours[mismatch]}.", ""]
        lines += ["Compile time (first call minus the median call):", "", "| jitted function | compile, s |", "|---|---:|"]
        lines += [f"| {name} | {ms / 1e3:.2f} |" for name, ms in summary["compile_ms"].items()]
        lines.append("")
        vbg = summary["vbg"]
        lines += [
            "## Global TSDF vs Open3D VoxelBlockGrid",
            "",
            f"Same frames: our `integrate_frame` {_ms(vbg['ours_ms'])} ms, VoxelBlockGrid "
            f"{_ms(vbg['vbg_ms'])} ms: ours / VBG = {_ratio(vbg['ratio'])}"
            + (f" ({vbg['note']})" if vbg.get("note") else "")
            + ".",
            "",
        ]
    lines += [
        "## Peak memory",
        "",
        "| pipeline | peak RSS, MiB | RSS before fusing, MiB | map state, MiB | device peak, MiB |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, memory in summary["memory"].items():
        lines.append(
            f"| {name} | {_mb(memory.get('peak_rss_mb'))} | {_mb(memory.get('baseline_rss_mb'))} | "
            f"{_mb(memory.get('map_state_mb'))} | {_mb(memory.get('device_memory_mb'))} |"
        )
    lines += ["", "Each pipeline runs in a process of its own; ours is measured after its fused pass."]
    if _usable(main.get("ours")):
        lines += [f"Ours: {compile_cache_state(main['ours'])}."]
    lines.append("")
    lines += _whole_run_lines(summary.get("whole_run"), scene)
    lines += _sweep_lines(summary.get("sweep"))
    lines += _per_object_lines(summary["per_object"])
    lines += profile_lines((main.get("ours") or {}).get("profile"))
    lines += ["## Targets", "", "| target | figure | met |", "|---|---|---|"]
    lines += [
        f"| {t['target']} | {t['figure']} | {'—' if t['met'] is None else 'yes' if t['met'] else '**no**'} |"
        for t in summary["targets"]
    ]
    return "\n".join(lines) + "\n"


def _whole_run_lines(whole_run: dict | None, scene: dict) -> list[str]:
    """The section on `fmfusion run` end to end: each pass's wall time and its split, the outputs one by one."""
    lines = ["## The whole command: `fmfusion run`", ""]
    if whole_run is None:
        return lines + ["Not run (`--no-whole-run`).", ""]
    if "error" in whole_run:
        return lines + [f"Failed: {whole_run['error']}", ""]
    lines += [
        f"`fmfusion run` on {scene['frames']} frames of {scene['name']} with all outputs, in a fresh process: first with "
        "an empty compile cache (cold: every step compiled), then with the cache it filled (warm). Frames: the frames "
        "as run (reading, detections, fusion; the first calls compile or load the steps); outputs: their wall time, "
        "from the instances' extraction to run.json (`export_wall_seconds`); other: start-up, imports, opening the "
        "scene and its ground truth, the final merge.",
        "",
        "| compile cache | wall, s | frames, s | outputs, s | other, s | peak RSS, MiB |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, split in whole_run.items():
        lines.append(
            f"| {name} | {split['wall_s']:.1f} | {split['frames_s']:.1f} | {split['outputs_s']:.1f} | "
            f"{split['other_s']:.1f} | {_mb(split['peak_rss_mib'])} |"
        )
    warm = whole_run.get("warm") or next(iter(whole_run.values()))
    parts = ", ".join(f"{name} {seconds:.2f}" for name, seconds in warm["outputs"].items())
    lines += [
        "",
        f"Outputs of the warm run, s (each writer's own time; they run two at a time): {parts}.",
        "",
    ]
    return lines


def _per_object_lines(per_object: dict) -> list[str]:
    points = per_object["points"]
    lines = ["## Cost per object (generated rooms)", ""]
    if not points:
        return lines + ["No generated scene was run.", ""]
    lines += [
        "Context only: the rooms differ in size and in much else besides their detections per frame, which "
        "vary little, so these lines do not isolate an object's cost (the controlled sweep above does).",
        "",
    ]
    lines += [
        "| scene | objects | room, m | frames | detections / frame | live instances | ours fusion step, ms | "
        "ours whole frame, ms | peer frames | peer whole frame, ms | peer live instances |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for q in points:
        room = "x".join(f"{x:.1f}" for x in q["room_size"]) if q.get("room_size") else "?"
        lines.append(
            f"| {q['scene']} | {q['objects']} | {room} | {q['frames']} | {q['detections']:.1f} | "
            f"{q['live_instances']:.1f} | {_ms(q['fusion_ms'])} | {_ms(q['whole_ms'])} | "
            f"{q.get('peer_frames', '—')} | {_ms(q.get('peer_whole_ms', math.nan))} | "
            f"{q.get('peer_live_instances', math.nan):.1f} |"
        )
    names = {
        "ours_vs_detections": "ours, whole frame vs detections per frame",
        "ours_fusion_vs_detections": "ours, fusion step vs detections per frame",
        "ours_vs_instances": "ours, whole frame vs live instances",
        "peer_vs_detections": "Open3D peer, whole frame vs detections per frame",
        "peer_vs_instances": "Open3D peer, whole frame vs live instances",
    }
    lines += [
        "",
        "Least-squares lines ms per frame = base + per object x load (Table IV's base + per object):",
        "",
        "| fit | base, ms | per object, ms | scenes |",
        "|---|---:|---:|---:|",
    ]
    for key, fit in per_object["fits"].items():
        lines.append(f"| {names[key]} | {_ms(fit['base_ms'])} | {_signed(fit['per_object_ms'])} | {fit['points']} |")
    return lines + [""]


def _sweep_lines(sweep: dict | None) -> list[str]:
    lines = ["## Cost per object (controlled sweep)", ""]
    if sweep is None:
        return lines + ["Not run (`--sweep` with no caps).", ""]
    points = sweep["points"]
    frames = max([q.get("ours_frames", 0) for q in points] + [q.get("peer_frames", 0) for q in points] + [0])
    groups = sweep.get("groups")
    lines += [
        f"The first {frames} frames of {sweep['scene']} ({sweep['kind']}), fused once per cap k: each frame's "
        "detections capped on the host to its k highest-scoring usable ones (the packer's rule; frames with k "
        "or fewer left alone), so the map, the frames and the padded shapes stay the same (nothing "
        "recompiles) and only the objects fused per frame vary. The runs of the caps advance together, a "
        "frame each in turn"
        + (f" (ours in groups {groups}, as many maps as fit in memory)" if groups and len(groups) > 1 else "")
        + "; ours compiled in an untimed uncapped pass first. Medians over frames 1..; detections and "
        "instances are means per frame. Fewer detections also make fewer instances, so the slope is the cost "
        "of one more object fused per frame, its instance's share of projection, merge and geometry fusion "
        "included.",
        "",
    ]
    notes = [f"{name}: {note}" for name, note in (("ours", sweep["ours_note"]), ("Open3D peer", sweep["peer_note"])) if note]
    if notes:
        lines += ["Not measured: " + "; ".join(notes) + ".", ""]
    if points:
        lines += [
            "| cap k | detections fused / frame | ours live instances | ours fusion step, ms | "
            "ours whole frame, ms | peer live instances | peer fusion step, ms | peer whole frame, ms |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for q in points:
            detections = q.get("ours_detections", q.get("peer_detections", math.nan))
            lines.append(
                f"| {q['k']} | {detections:.2f} | {q.get('ours_live_instances', math.nan):.1f} | "
                f"{_ms(q.get('ours_fusion_ms', math.nan))} | {_ms(q.get('ours_whole_ms', math.nan))} | "
                f"{q.get('peer_live_instances', math.nan):.1f} | {_ms(q.get('peer_fusion_ms', math.nan))} | "
                f"{_ms(q.get('peer_whole_ms', math.nan))} |"
            )
    names = {
        "ours_whole": "ours, whole frame",
        "ours_fusion": "ours, fusion step",
        "peer_whole": "Open3D peer, whole frame",
        "peer_fusion": "Open3D peer, fusion step",
    }
    lines += [
        "",
        "Least-squares lines ms per frame = base + per object x detections fused per frame:",
        "",
        "| fit | base, ms | per object, ms | caps |",
        "|---|---:|---:|---:|",
    ]
    for key, fit in sweep["fits"].items():
        lines.append(f"| {names[key]} | {_ms(fit['base_ms'])} | {_signed(fit['per_object_ms'])} | {fit['points']} |")
    return lines + [""]


def _signed(value: float) -> str:
    return "—" if not math.isfinite(value) else f"{value:+.3f}"


def _mb(value) -> str:
    return "—" if value is None or not math.isfinite(value) else f"{value:.0f}"


def _peer_version(runs: Sequence[dict]) -> str | None:
    for run in runs:
        for name in ("peer", "vbg"):
            if (run.get(name) or {}).get("open3d"):
                return run[name]["open3d"]
    return None
