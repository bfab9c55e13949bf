"""`fmfusion experiment --robustness` (`fmfusion_jax.apps.robustness`): the summaries on hand-made scores, the
reports, the detections' cache name, the command line, and one tiny end-to-end evaluation."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from fmfusion_jax.apps import robustness
from fmfusion_jax.apps.robustness import detections_tag, entry_noise, run_robustness, write_reports
from fmfusion_jax.apps.robustness.report import best_methods, family_rows, robustness_markdown, summarize, verdict, verdict_lines
from fmfusion_jax.comparison.methods import METHODS, PREVIOUS_MAP_OVERRIDES
from fmfusion_jax.comparison.scenes import SceneSource
from fmfusion_jax.simulation.demo_setup import scale_noise_to_image
from fmfusion_jax.simulation.noise import NoiseModel
from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec
from fmfusion_jax.simulation.zoo import ZooEntry, noise_zoo

METHOD_NAMES = ("kimera", "previous", "full")


def _entry(name: str, family: str, **changes) -> ZooEntry:
    return ZooEntry(name, family, NoiseModel.preset("default", **changes))


ENTRIES = [
    _entry("default", "default"),
    _entry("border", "border", border_offset_px=4.0),
    _entry("mixed-1", "mixed", merge_prob=0.3),
    _entry("mixed-2", "mixed", partial_prob=0.4),
]


def _scores(ap50: dict[str, tuple[float, float, float]]) -> dict:
    """entry -> method -> metrics, with AP = AP50 / 2 and AP25 = min(1, AP50 + 0.1)."""
    return {
        entry: {m: {"AP": v / 2, "AP50": v, "AP25": min(1.0, v + 0.1)} for m, v in zip(METHOD_NAMES, values)}
        for entry, values in ap50.items()
    }


SCORES = _scores(
    {"default": (0.40, 0.60, 0.70), "border": (0.30, 0.50, 0.40), "mixed-1": (0.20, 0.30, 0.35), "mixed-2": (0.10, 0.20, 0.25)}
)


def test_summaries_per_family_mean_and_worst():
    summary = summarize(ENTRIES, SCORES, METHOD_NAMES)
    full = summary["full"]
    assert list(full["families"]) == ["default", "border", "mixed"]
    assert full["families"]["border"]["entries"] == ["border"]
    assert full["families"]["border"]["mean"]["AP50"] == pytest.approx(0.40)  # one entry: its score
    assert full["families"]["mixed"]["mean"]["AP50"] == pytest.approx(0.30)  # mean of 0.35 and 0.25
    assert full["families"]["mixed"]["worst"]["AP50"] == {"value": pytest.approx(0.25), "entry": "mixed-2"}
    assert full["mean"]["AP50"] == pytest.approx((0.70 + 0.40 + 0.35 + 0.25) / 4)
    assert full["mean"]["AP"] == pytest.approx((0.70 + 0.40 + 0.35 + 0.25) / 8)
    assert full["worst"]["AP25"] == {"value": pytest.approx(0.35), "entry": "mixed-2"}
    assert summary["kimera"]["worst"]["AP50"]["entry"] == "mixed-2"
    # the per-family table: a family of several entries gives its mean and its worst
    titles = [title for title, _ in family_rows(summary, METHOD_NAMES)]
    assert titles == ["default", "border", "mixed (mean of 2)", "mixed (worst)", "mean", "worst"]


def test_missing_scores_are_left_out_not_counted_as_zero():
    scores = _scores({"default": (0.4, 0.6, 0.7), "border": (0.3, 0.5, 0.4)})
    scores["border"]["full"]["AP50"] = None  # e.g. no ground truth of any class
    summary = summarize(ENTRIES[:2], scores, METHOD_NAMES)
    assert summary["full"]["mean"]["AP50"] == pytest.approx(0.7)
    assert summary["full"]["worst"]["AP50"] == {"value": pytest.approx(0.7), "entry": "default"}
    assert summary["full"]["families"]["border"]["mean"]["AP50"] is None
    assert best_methods({"a": None, "b": float("nan")}) == [] and best_methods({"a": 0.2, "b": 0.2}) == ["a", "b"]


def test_verdict_names_the_winners_and_where_full_does_not_beat_previous():
    record = verdict(summarize(ENTRIES, SCORES, METHOD_NAMES), METHOD_NAMES)
    assert record["mean"] == ["full"] and record["worst"] == ["full"]
    assert record["families"] == {"default": ["full"], "border": ["previous"], "mixed": ["full"]}
    assert record["beats"]["every_family"] is False
    assert [w["family"] for w in record["beats"]["where_not"]] == ["border"]
    line = verdict_lines(record)[-1]
    assert line == "- full beats previous on every family (AP50): no, where not: border (40.0 vs 50.0)."

    better = _scores({e.name: (0.1, 0.2, 0.3) for e in ENTRIES})
    assert verdict(summarize(ENTRIES, better, METHOD_NAMES), METHOD_NAMES)["beats"]["every_family"] is True
    tied = _scores({e.name: (0.1, 0.2, 0.2) for e in ENTRIES})  # a tie is not a win
    tie = verdict(summarize(ENTRIES, tied, METHOD_NAMES), METHOD_NAMES)
    assert not tie["beats"]["every_family"] and tie["mean"] == ["previous", "full"]
    assert "beats" not in verdict(summarize(ENTRIES, SCORES, METHOD_NAMES), ["kimera", "full"])


def test_markdown_and_json_reports(tmp_path):
    methods = [METHODS[n] for n in METHOD_NAMES]
    summary = summarize(ENTRIES, SCORES, METHOD_NAMES)
    record = verdict(summary, METHOD_NAMES)
    scenes = [
        {
            "name": "synth0001_00",
            "kind": "generated",
            "frames": 20,
            "spec": {"seed": 1, "num_objects": 5, "width": 320, "height": 240},
            "config": "demo",
        }
    ]
    markdown = robustness_markdown(ENTRIES, SCORES, summary, record, methods, scenes, 0, 12.0, 12)
    lines = markdown.splitlines()
    header = next(line for line in lines if line.startswith("| Family | Entry |"))
    assert header.count("AP50") == 3 and "| full AP | full AP50 | full AP25 |" in header
    # rows grouped by family: the family is named on its first entry only
    assert "| mixed | mixed-1 | 10.0 | 20.0 | 30.0 |" in markdown and "|  | mixed-2 | 5.0 | 10.0 | 20.0 |" in markdown
    worst = next(line for line in lines if line.startswith("| **worst** |"))
    assert "25.0 (mixed-2)" in worst
    assert "| border | 30.0 | **50.0** | 40.0 |" in markdown  # AP50 per family, best in bold
    assert "| mixed (mean of 2) | 15.0 | 25.0 | **30.0** |" in markdown
    assert "full beats previous on every family (AP50): no, where not: border" in markdown
    assert "<details>" in markdown and "| merge_prob | 0.05 | 0.05 | 0.05 | 0.3 | 0.05 |" in markdown
    assert "`synth0001_00`: generated room, seed 1" in markdown

    chart = robustness.robustness_chart(ENTRIES, SCORES, summary, METHOD_NAMES)
    write_reports(tmp_path, markdown, {"scores": SCORES, "summary": summary, "verdict": record}, chart)
    assert (tmp_path / "robustness.md").read_text() == markdown
    assert json.loads((tmp_path / "robustness.json").read_text())["summary"]["full"]["mean"]["AP50"] == pytest.approx(
        summary["full"]["mean"]["AP50"]
    )
    image = cv2.imread(str(tmp_path / "robustness.png"))
    assert image is not None and image.shape == chart.shape and image.std() > 0


def test_cache_name_changes_with_any_noise_parameter():
    noise = NoiseModel.preset("default")
    assert detections_tag("border", noise) == detections_tag("border", NoiseModel.preset("default"))
    changed = {
        detections_tag("border", noise.replace(**{key: value}))
        for key, value in (
            ("border_offset_px", 4.0),
            ("seed", 1),
            ("merge_prob", 0.3),
            ("prompt_augmentation", False),
            ("min_mask_pixels", 100),
        )
    }
    assert len(changed) == 5 and detections_tag("border", noise) not in changed
    assert detections_tag("mixed-1", noise) != detections_tag("mixed-2", noise)


def test_generated_scenes_scale_pixel_counts_as_the_demo_does():
    from fmfusion_jax.simulation.demo_setup import demo_noise

    for width, height in ((640, 480), (320, 240), (160, 120)):
        assert scale_noise_to_image(NoiseModel.preset("default", seed=3), width, height) == demo_noise(3, width, height)
    entry = _entry("border", "border", border_offset_px=4.0, min_mask_pixels=800)
    small = SceneSource("synth0001_00", "generated", spec=GeneratedSceneSpec(1, 5, 30, 320, 240))
    noise = entry_noise(small, entry)
    assert noise.min_mask_pixels == 200 and noise.border_offset_px == 4.0
    assert entry_noise(SceneSource("scene0000_00", "real"), entry) == entry.noise
    assert entry_noise(small, entry, "noaug").prompt_augmentation is False


def test_cached_frames_are_the_frames_read_from_disk(tmp_path):
    from fmfusion_jax.io.scene import open_scene
    from fmfusion_jax.simulation.scene_sets import generated_scene

    scene_dir = generated_scene(GeneratedSceneSpec(2, 3, 4, 64, 48), tmp_path)
    cached, plain = open_scene(scene_dir), open_scene(scene_dir)
    assert robustness.cache_frames(cached)
    for a, b in zip(cached.frames(), plain.frames()):
        assert np.array_equal(a.depth, b.depth) and np.array_equal(a.color, b.color) and a.name == b.name
    with pytest.raises(ValueError):  # read-only: a caller writing into a frame would corrupt the next run
        cached.read_frame(0).depth[0, 0] = 1.0
    assert not robustness.cache_frames(open_scene(scene_dir), max_bytes=1000)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--methods", "kimmera"], "unknown method 'kimmera'"),
        (["--mixed", "-1"], "--mixed must be >= 0"),
        (["--noise-seed", "-2"], "--noise-seed must be >= 0"),
        (["--seed", "3"], "the zoo's seed is --noise-seed"),
        (["--generated-frames", "1"], "--generated-frames must be >= 2"),
        (["--scenes", "--generated", "0"], "no scenes"),
    ],
)
def test_cli_errors_are_one_line(tmp_path, capsys, argv, message):
    from fmfusion_jax.cli import main

    assert main(["experiment", "--robustness", "--out", str(tmp_path / "out"), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_zoo_flags_need_robustness(tmp_path, capsys):
    from fmfusion_jax.cli import main

    assert main(["experiment", "--mixed", "2", "--noise-seed", "1", "--out", str(tmp_path)]) == 2
    assert "--mixed and --noise-seed: only with --robustness" in capsys.readouterr().err


def test_cli_defaults_and_quick(monkeypatch, tmp_path):
    from fmfusion_jax.cli import main

    seen = {}

    class Result:
        text = "tables"

    def fake_run(out, **kwargs):
        seen.update(kwargs, out=out)
        return Result()

    monkeypatch.setattr(robustness, "run_robustness", fake_run)
    assert main(["experiment", "--robustness", "--quick", "--out", str(tmp_path)]) == 0
    assert seen["real_scenes"] == [] and seen["mixed"] == 1 and seen["noise_seed"] == 0
    assert [(s.num_frames, s.width, s.height, s.num_objects) for s in seen["generated"]] == [(30, 320, 240, 5)]
    assert main(["experiment", "--robustness", "--scenes", "--mixed", "3", "--noise-seed", "7"]) == 0
    assert seen["out"] == robustness.DEFAULT_OUT and seen["mixed"] == 3 and seen["noise_seed"] == 7
    assert [(s.seed, s.num_frames, s.width) for s in seen["generated"]] == [(1, 120, 640), (2, 120, 640)]
    assert seen["methods"] is None and seen["real_max_frames"] is None  # None: kimera, previous, full
    assert [m.name for m in robustness.resolve_methods(robustness.DEFAULT_METHODS)] == list(METHOD_NAMES)


def test_previous_is_a_method_but_not_a_default_of_the_plain_experiment():
    from fmfusion_jax.comparison.methods import DEFAULT_METHODS, PREVIOUS_MAP_OVERRIDES

    assert METHODS["previous"].overrides == PREVIOUS_MAP_OVERRIDES and "previous" not in DEFAULT_METHODS


@pytest.mark.slow
def test_tiny_evaluation_end_to_end(tmp_path):
    """One room of 20 frames at 320x240 crossed with three zoo entries (one mixture): every report is
    written, every score is an AP, identical configs share one map, and a second evaluation reads the
    cached detections."""
    entries = [e for e in noise_zoo(mixed=1, seed=0) if e.name in ("default", "border", "mixed-1")]
    spec = GeneratedSceneSpec(seed=3, num_objects=4, num_frames=20, width=320, height=240)
    cache, lines = tmp_path / "cache", []
    result = run_robustness(tmp_path / "out", generated=[spec], entries=entries, cache_dir=cache, report=lines.append)
    out = result.out_dir
    assert [line.split("]")[0] for line in lines if line.startswith("[")] == [f"[{i}/9" for i in range(1, 10)]
    assert "ETA" in lines[-1]
    record = json.loads((out / "robustness.json").read_text())
    assert [e["name"] for e in record["zoo"]] == ["default", "border", "mixed-1"]
    for entry in record["zoo"]:
        for method in METHOD_NAMES:
            for metric in ("AP", "AP50", "AP25"):
                value = record["scores"][entry["name"]][method][metric]
                assert value is not None and 0.0 <= value <= 1.0, (entry["name"], method, metric, value)
            assert (
                record["per_scene_ap50"][entry["name"]][spec.name][method] == record["scores"][entry["name"]][method]["AP50"]
            )  # one scene: pooling is the scene's score
            run = json.loads((out / "runs" / spec.name / entry["name"] / method / "run.json").read_text())
            assert run["method"] == method and run["frames"] == spec.num_frames
        full = json.loads((out / "runs" / spec.name / entry["name"] / "full" / "run.json").read_text())
        previous = json.loads((out / "runs" / spec.name / entry["name"] / "previous" / "run.json").read_text())
        # previous differs from full by PREVIOUS_MAP_OVERRIDES: two maps fused, neither copied
        assert previous["overrides"] == list(PREVIOUS_MAP_OVERRIDES) and full["overrides"] == []
        assert "same_run_as" not in full and "same_run_as" not in previous
    for method in METHOD_NAMES:
        summary = record["summary"][method]
        assert 0.0 <= summary["worst"]["AP50"]["value"] <= summary["mean"]["AP50"] <= 1.0
    assert not any(out.rglob("*.ply"))  # benchmark files only
    markdown = (out / "robustness.md").read_text()
    assert markdown == result.markdown and "| **mean** |" in markdown and "full beats previous" in markdown
    assert cv2.imread(str(out / "robustness.png")) is not None
    detections = sorted(p.name for p in (cache / "detections").iterdir())
    assert len(detections) == 3 and all(spec.name in d for d in detections)
    # detections are simulated on every frame, whatever the fusion's schedule
    frames = json.loads((cache / "detections" / detections[0] / "simulation.json").read_text())["frames"]
    assert len(frames) == spec.num_frames
    stamps = {p: p.stat().st_mtime_ns for p in (cache / "detections").rglob("simulation.json")}
    again = run_robustness(
        tmp_path / "out", generated=[spec], entries=entries[:1], methods=["kimera"], cache_dir=cache, progress=False
    )
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps  # cached: nothing simulated again
    assert math.isclose(again.scores["default"]["kimera"]["AP50"], result.scores["default"]["kimera"]["AP50"])


def test_precision_counts_pool_and_summarize_on_a_tiny_case():
    from fmfusion_jax.apps.robustness.report import pooled_precision, precision_counts, precision_table, summarize_precision
    from fmfusion_jax.io.benchmark_format import InstancePredictions

    chair, table = 5, 7  # nyu40
    gt = np.zeros(1000, np.int64)
    gt[0:200] = chair * 1000 + 1
    gt[200:400] = table * 1000 + 2  # vertices 400..999: wall, floor, void
    masks = np.zeros((4, 1000), bool)
    masks[0, 0:190] = True  # the chair, found
    masks[1, 200:390] = True  # the table, found
    masks[2, 500:700] = True  # a phantom on the wall: no object
    masks[3, 700:750] = True  # too small: not evaluated
    preds = InstancePredictions(masks, np.array([chair, table, chair, table]), np.array([0.9, 0.8, 0.7, 0.6]))
    counts = precision_counts(gt, preds)
    assert counts == {"objects": 2, "predictions": 3, "no_object": 1}
    empty = precision_counts(gt, InstancePredictions(np.zeros((0, 1000), bool), np.zeros(0), np.zeros(0)))
    assert empty == {"objects": 2, "predictions": 0, "no_object": 0}
    pooled = pooled_precision([counts, empty], 0.5)
    assert pooled["no_object_share"] == pytest.approx(1 / 3) and pooled["instances_per_object"] == pytest.approx(3 / 4)
    assert pooled["AP50"] == 0.5 and pooled_precision([empty], None)["no_object_share"] is None

    entries = ENTRIES[:2]
    precision = {
        "default": {m: pooled_precision([counts], 0.6) for m in METHOD_NAMES},
        "border": {m: pooled_precision([counts, counts, empty], 0.4) for m in METHOD_NAMES},
    }
    summary = summarize_precision(entries, precision, METHOD_NAMES)["full"]
    assert summary["mean"]["instances_per_object"] == pytest.approx((1.5 + 1.0) / 2)
    assert summary["worst"]["instances_per_object"] == {"value": pytest.approx(1.5), "entry": "default"}
    assert summary["worst"]["AP50"] == {"value": 0.4, "entry": "border"}  # AP50: the lowest is the worst
    assert summary["worst"]["no_object_share"]["value"] == pytest.approx(1 / 3)
    methods = [METHODS[n] for n in METHOD_NAMES]
    table_md = precision_table(entries, precision, summarize_precision(entries, precision, METHOD_NAMES), methods)
    assert "| full no-object % | full inst/obj | full AP50 |" in table_md
    assert "| default | default | 33.3 | 1.50 | 60.0 |" in table_md
    assert "1.50 (default)" in table_md and "40.0 (border)" in table_md
    markdown = robustness_markdown(
        entries,
        SCORES,
        summarize(entries, SCORES, METHOD_NAMES),
        verdict(summarize(entries, SCORES, METHOD_NAMES), METHOD_NAMES),
        methods,
        [],
        0,
        1.0,
        6,
        precision,
        summarize_precision(entries, precision, METHOD_NAMES),
    )
    assert "## Precision per zoo entry" in markdown and table_md in markdown
