"""`fmfusion bench`: the stages jitted apart make the fused step's map, the report's figures, the sweep's
detection cap, and a `--quick` run end to end, sweep included (with the Open3D peer when it can run here,
and without it).

The bench runs spawn worker processes; they share a persistent JAX compilation cache (a temporary
folder) so that the second run does not compile again.
"""

from __future__ import annotations

import gzip
import json
import math
from pathlib import Path

import jax
import numpy as np
import pytest
from oracles.reference import BoxRoom, orbit_poses, scannet_like_intrinsics

from fmfusion_jax.apps.bench import figures, report, targets
from fmfusion_jax.apps.bench.harness import peer_unavailable_reason
from fmfusion_jax.apps.bench.stages import FUSION_STAGES, FrameTimer, staged_fuse_detections
from fmfusion_jax.apps.bench.sweep import cap_detections, groups_that_fit
from fmfusion_jax.cli import main
from fmfusion_jax.config import load_config
from fmfusion_jax.engine import step
from fmfusion_jax.engine.detections import pack_detections
from fmfusion_jax.engine.state import init_map_state
from fmfusion_jax.labels import load_label_sets, load_likelihood
from fmfusion_jax.mapping.engine_configs import build_fusion_config, build_map_config
from fmfusion_jax.mapping.inputs import frame_inputs
from fmfusion_jax.types import CameraIntrinsics, FrameDetections, RGBDFrame

H, W = 60, 80
LABELS = load_label_sets()
SURFACE_LABELS = {0: "floor", 2: "wall", 6: "bed", 7: "cabinet", 8: "bin"}


def box_room_frames(n: int):
    """`n` frames of the analytic box room with one clean detection per visible surface."""
    room = BoxRoom()
    k = scannet_like_intrinsics(W, H)
    intrinsics = CameraIntrinsics(float(k[0]), float(k[1]), float(k[2]), float(k[3]), W, H)
    frames = []
    for i, pose in enumerate(orbit_poses(room, n)):
        depth, color, labels = room.render(pose, k, H, W)
        frame = RGBDFrame(i, f"frame-{i:06d}", color, depth.astype(np.float32), pose, intrinsics)
        masks = [labels == s for s in SURFACE_LABELS if (labels == s).sum() >= 40]
        names = [{SURFACE_LABELS[s]: 0.6} for s in SURFACE_LABELS if (labels == s).sum() >= 40]
        detections = FrameDetections(
            frame.name, np.array(masks, bool).reshape(-1, H, W), names, np.zeros((len(masks), 4), np.float32)
        )
        frames.append((frame, detections))
    return room, frames


def test_stages_composed_make_the_fused_steps_map_bit_for_bit():
    room, frames = box_room_frames(3)
    config = load_config(
        "scannet",
        [
            "tsdf.block_capacity=3000",
            "tsdf.max_touched_blocks=1024",
            "instances.capacity=16",
            "detections.max_detections=6",
            "association.min_projected_pixels=50",
        ],
    )
    map_config = build_map_config(config, room.lo, room.hi, H, W)
    fusion = build_fusion_config(config)
    likelihood = jax.numpy.asarray(load_likelihood("statistical"), jax.numpy.float32)
    timer = FrameTimer()
    staged = staged_fuse_detections(timer)
    fused_state, staged_state = init_map_state(map_config), init_map_state(map_config)
    for frame, detections in frames:
        inputs = frame_inputs(frame, map_config)
        batch = pack_detections(detections, LABELS.open_labels, 6, 40)
        fused_state, fused_stats = step.fuse_detections(fused_state, inputs, batch, likelihood, map_config, fusion)
        timer.start_frame()
        staged_state, staged_stats = staged(staged_state, inputs, batch, likelihood, map_config, fusion)
        assert tuple(map(int, staged_stats)) == tuple(map(int, fused_stats))
    assert int(fused_state.instances.valid.sum()) >= 3
    for got, expected in zip(jax.tree.leaves(staged_state), jax.tree.leaves(fused_state)):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(expected))
    # every stage was timed once per frame, the first call kept apart as the compiling one
    assert set(timer.compiled[0]) == set(FUSION_STAGES) and set(timer.frames[1]) == set(FUSION_STAGES)


def test_line_fit_recovers_base_and_slope():
    x = np.array([3.0, 6.0, 12.0, 24.0])
    base, slope = report.fit_line(x, 20.0 + 0.4 * x + np.array([0.01, -0.02, 0.02, -0.01]))
    assert base == pytest.approx(20.0, abs=0.05) and slope == pytest.approx(0.4, abs=0.005)
    assert all(math.isnan(v) for v in report.fit_line([5.0, 5.0], [1.0, 2.0]))  # one distinct load: no line


def test_the_targets_judge_the_whole_frame_as_run_when_that_pass_ran():
    timed = [{"fusion": 20.0, "host": 3.0}] * 4
    ours = {"frames": timed, "compiled": [{}] * 4, "stage_frames": [], "stage_compiled": []}
    calls = [{}, {"call": 19.0}, {"call": 21.0}, {"call": 20.0}]  # the first call left out (a chunk's first)
    as_run = {**ours, "run_frames": calls, "run_compiled": [{"call": 9.0}, {}, {}, {}]}
    peer = {"frames": [{"tsdf": 100.0, "merge": 300.0}] * 4}
    for result, whole_ms in ((ours, 23.0), (as_run, 20.0)):
        table = report.stage_table(result, peer)
        row = figures.whole_frame_row(table)
        assert row is not None and row["ours_all"] == whole_ms and row["ratio"] == pytest.approx(400.0 / whole_ms)
    assert figures.whole_frame_row(report.stage_table(as_run, peer))["label"] == figures.AS_RUN_LABEL
    assert figures.whole_frame_row(None) is None


def test_frame_sums_leave_out_warm_up_and_compiling_frames():
    frames = [{"fusion": 900.0}, {"fusion": 10.0, "refine": 5.0}, {"fusion": 12.0}, {"fusion": 11.0, "refine": 7.0}]
    compiled = [{"fusion": 3000.0}, {}, {"refine": 2000.0}, {}]
    assert figures.frame_sums(frames, compiled, ("fusion",)) == [10.0, 12.0, 11.0]  # frame 2 compiled refine only
    assert figures.frame_sums(frames, compiled, None) == [15.0, 18.0]
    assert figures.frame_sums(frames, None, ("refine",), stop=3) == [5.0]


def test_compile_cache_state_says_whether_the_steps_were_compiled_in_the_measured_process():
    """Peak memory depends on it: a process that compiles its steps peaks higher than one that loads them."""
    state = lambda **cache: targets.compile_cache_state({"compile_cache": cache})  # noqa: E731
    assert state(dir=None).startswith("compile cache off")
    assert state(dir="c", entries_before=0, entries_after=12).startswith("compile cache cold")
    assert state(dir="c", entries_before=248, entries_after=248).startswith("compile cache warm (248 entries")
    assert "12 new ones" in state(dir="c", entries_before=248, entries_after=260)
    assert state(dir="c", entries_before=248).startswith("compile cache warm")  # results of older runs


def test_cap_keeps_the_k_highest_scoring_usable_detections_in_order():
    masks = np.zeros((6, 40, 50), bool)
    for i, rows in enumerate((30, 30, 30, 1, 30, 30)):  # detection 3: too small a mask (50 < 100 pixels)
        masks[i, :rows] = True
    labels = [
        {"chair": 0.5},
        {"bed": 0.9},
        {"tag not in the label set": 0.99},
        {"wall": 0.95},
        {"floor": 0.7},
        {"sofa": 0.3, "table": 0.7},
    ]  # usable: 0, 1, 4, 5; best scores 0.5, 0.9, 0.7, 0.7
    detections = FrameDetections("frame-000000", masks, labels, np.zeros((6, 4), np.float32))
    open_labels, min_pixels = LABELS.open_labels, 100

    capped = cap_detections(detections, 2, open_labels, min_pixels)
    assert capped.labels == [labels[1], labels[4]]  # 0.9, then 0.7 of detection 4 (the tie goes to the earlier)
    np.testing.assert_array_equal(capped.masks, masks[[1, 4]])
    assert capped.frame_name == detections.frame_name and capped.boxes.shape == (2, 4)
    assert cap_detections(detections, 1, open_labels, min_pixels).labels == [labels[1]]
    assert cap_detections(detections, 3, open_labels, min_pixels).labels == [labels[1], labels[4], labels[5]]
    for k in (4, 5, 16):  # 4 usable detections or fewer than k: the frame as it is
        assert cap_detections(detections, k, open_labels, min_pixels) is detections
    # capping at k fuses what packing with capacity k keeps, while the padded shape stays the config's
    with pytest.warns(RuntimeWarning, match="keeping the 3 highest-scoring"):
        packed_k = pack_detections(detections, open_labels, 3, min_pixels)
    packed = pack_detections(cap_detections(detections, 3, open_labels, min_pixels), open_labels, 8, min_pixels)
    assert packed.masks.shape[0] == 8 and int(packed.valid.sum()) == 3
    np.testing.assert_array_equal(packed.masks[:3], packed_k.masks)
    np.testing.assert_array_equal(packed.label_scores[:3], packed_k.label_scores)
    with pytest.raises(ValueError):
        cap_detections(detections, 0, open_labels, min_pixels)


def test_sweep_holds_as_many_maps_as_fit_in_half_the_free_memory():
    assert groups_that_fit([1, 2, 4, 8, 16], 1.0, 100.0) == [[1, 2, 4, 8, 16]]
    assert groups_that_fit([1, 2, 4, 8, 16], 1.0, 4.0) == [[1, 2], [4, 8], [16]]
    assert groups_that_fit([1, 2, 4], 10.0, 1.0) == [[1], [2], [4]]


def test_sweep_fit_over_the_caps():
    def run(k: int, detections: float, ms: float) -> dict:
        return {
            "k": k,
            "frames": [{"fusion": 1e3, "refine": 1.0}] + [{"fusion": ms, "refine": 1.0}] * 3,
            "compiled": [{}] * 4,
            "detections_in": [9] * 4,
            "detections_fused": [detections] * 4,
            "live_instances": [5] * 4,
        }

    sweep = {
        "scene": {"name": "room", "kind": "generated"},
        "sweep": [1, 2, 4],
        "ours": {"runs": [run(1, 1, 10.5), run(2, 2, 11.0), run(4, 3.5, 11.75)], "groups": [[1, 2, 4]]},
        "peer": {"unavailable": "--no-peer"},
    }
    costs = report.sweep_costs(sweep)
    assert costs["fits"]["ours_fusion"]["per_object_ms"] == pytest.approx(0.5)
    assert costs["fits"]["ours_whole"]["base_ms"] == pytest.approx(11.0)
    assert math.isnan(costs["fits"]["peer_whole"]["per_object_ms"]) and costs["peer_note"] == "--no-peer"
    target = targets._per_object_target(costs)
    assert target["met"] is True and "+0.50 ms per detection" in target["figure"]
    assert targets._per_object_target(None)["met"] is None


@pytest.fixture(scope="module")
def bench_dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    return {"cache": root / "cache", "jax_cache": root / "jax-cache", "root": root}


def run_quick_bench(bench_dirs, monkeypatch, name: str, *extra: str) -> dict:
    """A --quick bench on one tiny generated room; returns bench.json."""
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(bench_dirs["jax_cache"]))
    monkeypatch.setenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    # Open3D's OpenMP threads stall for seconds a call on a busy machine; one thread keeps the peer quick
    # (its timings are not what this test checks)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    out = bench_dirs["root"] / name
    code = main(
        [
            "bench",
            "--quick",
            "--no-scene",
            "--objects",
            "3",
            "--generated-frames",
            "4",
            "--peer-frames",
            "2",
            "--cache",
            str(bench_dirs["cache"]),
            "--out",
            str(out),
            "--no-progress",
            *extra,
        ]
    )
    assert code == 0
    markdown = (out / "bench.md").read_text()
    for label, *_ in report.STAGE_ROWS:
        assert f"| {label} |" in markdown
    assert "Means per frame (the periodic geometry fusion spread over the frames): ours " in markdown
    data = json.loads((out / "bench.json").read_text())
    ours = data["runs"][0]["ours"]
    assert "error" not in ours and not ours.get("staged_mismatch") and not ours.get("as_run_mismatch")
    assert len(ours["run_frames"]) == len(ours["frames"])  # the pass without timers made the timed pass's map
    rows = data["summary"]["stages"]["rows"]
    assert len(rows) == len(report.STAGE_ROWS)
    for row in rows:
        assert math.isfinite(row["ours_all"]) and row["ours_all"] > 0, row
    assert data["summary"]["device"]["cpus"] >= 1
    assert data["summary"]["memory"]["ours"]["peak_rss_mb"] > 0
    # the sweep, --quick's caps: 1 and 4
    assert "## Cost per object (controlled sweep)" in markdown
    sweep = data["summary"]["sweep"]
    assert [q["k"] for q in sweep["points"]] == [1, 4] and not sweep["ours_note"]
    for q in sweep["points"]:
        assert q["ours_frames"] == 4 and 0 < q["ours_detections"] <= q["k"]
        assert all(math.isfinite(q[key]) and q[key] > 0 for key in ("ours_fusion_ms", "ours_whole_ms")), q
    assert sweep["points"][0]["ours_detections"] == 1  # every frame of the room has a detection or more
    assert math.isfinite(sweep["fits"]["ours_whole"]["per_object_ms"])
    target = next(t for t in data["summary"]["targets"] if t["target"].startswith("marginal cost"))
    assert "controlled sweep" in target["figure"] and target["met"] is not None
    return data


def test_quick_bench_with_the_open3d_peer(bench_dirs, monkeypatch):
    reason = peer_unavailable_reason()
    if reason:
        pytest.skip(f"Open3D peer unavailable: {reason}")
    data = run_quick_bench(bench_dirs, monkeypatch, "with-peer")
    whole = data["summary"]["stages"]["rows"][-1]
    assert math.isfinite(whole["peer"]) and math.isfinite(whole["ratio"])
    assert math.isfinite(data["summary"]["vbg"]["ratio"])
    for q in data["summary"]["sweep"]["points"]:  # the peer fuses the same capped detections
        assert q["peer_detections"] == q["ours_detections"] and math.isfinite(q["peer_whole_ms"])
    assert math.isfinite(data["summary"]["sweep"]["fits"]["peer_whole"]["per_object_ms"])


def test_quick_bench_without_the_peer(bench_dirs, monkeypatch):
    data = run_quick_bench(bench_dirs, monkeypatch, "no-peer", "--no-peer", "--profile", "2")
    # --profile: the main scene's last 2 frames as run traced, left out of the figures, summarized per thread
    primary = next(run for run in data["runs"] if run["scene"]["name"] == data["summary"]["primary"])
    ours, markdown = primary["ours"], (bench_dirs["root"] / "no-peer" / "bench.md").read_text()
    assert ours["run_frames"][-2:] == [{}, {}] and ours["run_frames"][-3] != {}
    profile = ours["profile"]
    assert profile["frames"] == 2 and not profile.get("error") and Path(profile["trace"]).is_file()
    python = next(row for row in profile["threads"] if "python" in row["thread"])
    assert python["busy_ms"] > 0 and any("integrate" in event["name"] for event in python["top"])
    assert "## Profile: the last 2 frames as run (`--profile`)" in markdown and profile["trace"] in markdown
    assert all("profile" not in run["ours"] for run in data["runs"] if run is not primary)
    assert data["runs"][0]["peer"] == {"unavailable": "--no-peer"}
    assert data["summary"]["sweep"]["peer_note"] == "--no-peer"
    assert "Not measured: Open3D peer: --no-peer." in (bench_dirs["root"] / "no-peer" / "bench.md").read_text()
    whole = data["summary"]["stages"]["rows"][-1]
    assert math.isnan(whole["ratio"])
    assert "n/a (--no-peer)" in (bench_dirs["root"] / "no-peer" / "bench.md").read_text()


def test_sweep_options(monkeypatch, tmp_path):
    import fmfusion_jax.apps.bench.run as bench_run

    given = []
    monkeypatch.setattr(bench_run, "run_bench", lambda options, command: given.append((options, command)) or {"markdown": ""})
    for argv, sweep, frames in (
        (["--quick"], (1, 4), 4),
        ([], (1, 2, 4, 8, 16), 30),
        (["--sweep", "2", "1", "2", "--sweep-frames", "0"], (2, 1), None),
        (["--quick", "--sweep"], (), 4),
    ):
        assert main(["bench", "--no-scene", "--out", str(tmp_path / "out"), *argv]) == 0
        options, command = given.pop()
        assert (options.sweep, options.sweep_frames) == (sweep, frames), argv
        assert ("--sweep" in command) == ("--sweep" in argv)
    assert "Not run (`--sweep` with no caps)." in report._sweep_lines(None)


def test_bad_arguments_fail_in_one_line_before_any_work(tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for argv, fragment in (
        (["--frames", "-1"], "--frames must be >= 0"),
        (["--objects", "0"], "--objects must be"),
        (["--sweep", "2", "0"], "--sweep caps must be >= 1"),
        (["--sweep-frames", "1"], "--sweep-frames must be >= 2"),
        (["--scene", str(tmp_path / "missing")], "does not exist"),
        (["--no-scene", "--out", str(a_file)], "is a file"),
    ):
        assert main(["bench", *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("fmfusion bench: error: ") and fragment in err[0], err


def test_the_memory_target_is_judged_on_the_cpu_and_reported_with_the_device_peak_on_a_gpu():
    """A GPU process holds the CUDA libraries in its resident memory and the map on the device: its peak RSS
    says nothing of the map's budget, so the row gives the figures without a verdict there."""
    ours = {
        "frames": [{"fusion": 2.0}] * 4,
        "compiled": [{}] * 4,
        "peak_rss_mb": 3200.0,
        "baseline_rss_mb": 270.0,
        "map_state_mb": 430.0,
        "blocks_used": 19375,
        "block_capacity": 32768,
        "device_memory_mb": 656.0,
    }
    main = {"scene": {"kind": "real", "frames": 300, "name": "scene0000_00"}, "ours": ours, "peer": None}
    memory_row = lambda platform: next(  # noqa: E731
        row for row in targets.targets({"device": {"platform": platform}}, main) if row["target"].startswith("peak RSS")
    )
    on_cpu, on_gpu = memory_row("cpu"), memory_row("gpu")
    assert on_cpu["met"] is False and "3.12x the target" in on_cpu["figure"]
    assert on_gpu["met"] is None and on_gpu["figure"].startswith("n/a on a GPU") and "device peak 656 MiB" in on_gpu["figure"]
    assert "x the target" not in on_gpu["figure"]
    ours["dropped_blocks"] = 7  # a pool too small is a failure on any device
    assert memory_row("gpu")["met"] is False


def test_the_gpu_target_says_by_how_much_it_is_missed_and_what_bounds_the_frame():
    frames = [{"prepare": 1.3, "fusion": 2.0, "refine": 1.5, "host": 1.0, "mapper": 0.8}] * 6
    ours = {"frames": frames, "compiled": [{}] * 6, "geometry_fusion_every": 11}
    main = {"scene": {"kind": "generated", "frames": 6, "name": "room"}, "ours": ours, "peer": None}
    summary = {"stages": report.stage_table(ours, None), "device": {"platform": "gpu", "device_kind": "H100"}}
    row = targets.targets(summary, main)[-1]
    assert row["target"].startswith("GPU") and row["met"] is False
    whole = figures.whole_frame_row(summary["stages"])["ours_all"]
    assert f"{whole / 3:.2f}x the target" in row["figure"]
    assert "bound by: fusion step 2.00 ms, merge 1.50 ms" in row["figure"] and "the host's work 1.80 ms" in row["figure"]
    assert "the reader thread's 1.30 ms beside them" in row["figure"]  # `fmfusion run` prepares frames in another thread
    summary["device"]["platform"] = "cpu"
    assert targets.targets(summary, main)[-1] == {"target": row["target"], "figure": "n/a (no GPU in this run)", "met": None}


def test_the_profile_summary_counts_each_threads_busy_time_once_per_frame(tmp_path):
    """Nested events (a call and the calls it makes) add to the busy time once, a thread's waits on locks and
    queues not at all (an idle reader thread); time and calls per frame."""
    from fmfusion_jax.apps.bench.profile import profile_lines, summarize_trace

    meta = [
        {"ph": "M", "name": "process_name", "pid": 1, "args": {"name": "/host:CPU"}},
        {"ph": "M", "name": "thread_name", "pid": 1, "tid": 7, "args": {"name": "python"}},
        {"ph": "M", "name": "thread_name", "pid": 1, "tid": 8, "args": {"name": "worker|1"}},
        {"ph": "M", "name": "thread_name", "pid": 1, "tid": 9, "args": {"name": "reader"}},
        {"ph": "M", "name": "thread_name", "pid": 1, "tid": 10, "args": {"name": "python"}},  # another, named alike
    ]
    spans = [  # µs: python busy 0-1000 and 3000-3500 (a nested call inside the first), the worker 500-700
        {"ph": "X", "pid": 1, "tid": 7, "ts": 0, "dur": 1000, "name": "integrate"},
        {"ph": "X", "pid": 1, "tid": 7, "ts": 100, "dur": 400, "name": "pack"},
        {"ph": "X", "pid": 1, "tid": 7, "ts": 3000, "dur": 500, "name": "integrate"},
        {"ph": "X", "pid": 1, "tid": 8, "ts": 500, "dur": 200, "name": "fusion"},
        # the reader: its worker loop spans the trace, idle in the queue's get but for one frame prepared
        {"ph": "X", "pid": 1, "tid": 9, "ts": 0, "dur": 4000, "name": "$thread.py:69 _worker"},
        {"ph": "X", "pid": 1, "tid": 9, "ts": 0, "dur": 2000, "name": "$<unknown> get"},
        {"ph": "X", "pid": 1, "tid": 9, "ts": 2000, "dur": 600, "name": "$mapper.py:412 prepare"},
        {"ph": "X", "pid": 1, "tid": 9, "ts": 2600, "dur": 1400, "name": "$<unknown> get"},
        {"ph": "X", "pid": 1, "tid": 9, "ts": 2100, "dur": 50, "name": "$threading.py:355 wait"},
        {"ph": "X", "pid": 1, "tid": 10, "ts": 0, "dur": 20, "name": "log"},
    ]
    path = tmp_path / "trace.json.gz"
    with gzip.open(path, "wt") as stream:
        json.dump({"traceEvents": meta + spans}, stream)
    python, reader, worker, other = summarize_trace(path, frames=2)
    assert reader["thread"] == "/host:CPU / reader" and reader["busy_ms"] == pytest.approx(0.275)  # 600 - 50 µs
    assert other["thread"] == "/host:CPU / python #10" and other["busy_ms"] == pytest.approx(0.01)
    assert python["thread"] == "/host:CPU / python #7" and python["busy_ms"] == pytest.approx(0.75) and python["events"] == 1.5
    assert python["top"][0] == {"name": "integrate", "ms": pytest.approx(0.75), "calls": 1.0}
    assert python["top"][1]["name"] == "pack" and python["top"][1]["ms"] == pytest.approx(0.2)
    assert worker["busy_ms"] == pytest.approx(0.1)
    lines = profile_lines({"frames": 2, "trace": str(path), "threads": [python, worker]})
    assert lines[0] == "## Profile: the last 2 frames as run (`--profile`)"
    assert "| /host:CPU / worker\\|1 | 0.10 | 0.5 | `fusion` 0.10 (0.5) |" in lines
    assert profile_lines(None) == [] and "No profile: why" in profile_lines({"frames": 2, "error": "why"})[2]


def test_the_as_run_passes_alone_report_each_pass(tmp_path, capsys):
    """`python -m fmfusion_jax.apps.bench.as_run`: the bench's as-run pass, repeated, one line per pass; bad input is a
    message and exit status 2, not a traceback."""
    from fmfusion_jax.apps.bench import as_run
    from fmfusion_jax.apps.bench.scenes import prepare_generated_scene

    scene = prepare_generated_scene(tmp_path / "cache", 2, 6, 160, 120, 0, False, ())
    rows = as_run.as_run_passes(scene, passes=2)
    assert [row["pass"] for row in rows] == [0, 1]
    assert all(row["frames"] > 0 and 0 < row["median_ms"] <= row["p90_ms"] for row in rows)
    assert [json.loads(line)["pass"] for line in capsys.readouterr().out.splitlines()] == [0, 1]
    assert as_run.main(["--scene", str(tmp_path / "missing"), "--cache", str(tmp_path / "c2"), "--passes", "1"]) == 2
    assert "scene folder not found" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        as_run.main(["--scene", str(tmp_path), "--passes", "0"])


def test_the_whole_run_is_split_by_its_record_and_judged_on_a_real_scene():
    """`fmfusion run` end to end: its wall time split into the frames as run, the outputs' wall time and the rest;
    the targets judge a real scene only, on the warm and the cold pass."""
    from fmfusion_jax.apps.bench.whole_run import split_of_run

    record = {
        "frame_ms_as_run": {"frames": 300, "mean": 20.0, "median": 10.0},
        "export_seconds": {"mesh": 2.0, "map_state": 1.5},  # writers side by side: more than their wall time
        "export_wall_seconds": 2.5,
        "peak_rss_mib": 900.0,
    }
    split = split_of_run(record, 12.0)
    assert (split["frames_s"], split["outputs_s"], split["other_s"]) == (6.0, 2.5, 3.5)
    warm, cold = split, split_of_run({**record, "peak_rss_mib": 1100.0}, 20.0)
    real = {"scene": {"kind": "real", "name": "s", "frames": 300}}
    rows = targets.whole_run_targets({"cold": cold, "warm": warm}, real)
    assert [row["met"] for row in rows] == [False, False, False, False]  # 12 > 10 s, 20 > 18 s, 2.5 > 2 s, 1.07 > 1 GiB
    fast = split_of_run({**record, "export_wall_seconds": 1.0}, 9.0)
    rows = targets.whole_run_targets({"cold": fast, "warm": fast}, real)
    assert [row["met"] for row in rows] == [True, True, True, True]
    generated = {"scene": {"kind": "generated", "name": "g", "frames": 6}}
    assert all(row["met"] is None for row in targets.whole_run_targets({"cold": fast, "warm": fast}, generated))
    assert all("n/a (not run)" in row["figure"] for row in targets.whole_run_targets(None, real))
