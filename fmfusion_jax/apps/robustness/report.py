"""The robustness report: each method's scores per zoo entry summarized per family (mean, worst entry), the
precision counts, the verdict of the new map against the previous one, and the tables and chart of
robustness.md and robustness.png."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import cv2
import numpy as np

from fmfusion_jax.comparison.methods import (
    Method,
)
from fmfusion_jax.comparison.tables import markdown_table, scene_kind
from fmfusion_jax.evaluation.explain import explain_scene
from fmfusion_jax.simulation.noise import NoiseModel
from fmfusion_jax.simulation.zoo import FAMILIES, MIXED, ZooEntry

if TYPE_CHECKING:
    pass

log = logging.getLogger(__name__)


#: Benchmark scores summarized, as (name in the tables, `BenchmarkResult` attribute).
METRICS = (("AP", "mAP"), ("AP50", "mAP50"), ("AP25", "mAP25"))


#: The precision summary of a (method, entry), pooled over the scenes: (name in the table, key, whether
#: higher is worse). The no-object share is the share of the evaluated predictions of kind "no_object"
#: (`evaluation.explain`: overlapping no counted object); instances per object are evaluated predictions
#: per counted ground-truth object (1 for a perfect map; more: false positives and fragments).
PRECISION = (("no-object %", "no_object_share", True), ("inst/obj", "instances_per_object", True), ("AP50", "AP50", False))


def family_order(entries: Sequence[ZooEntry]) -> list[str]:
    """The families present, in report order (`FAMILIES`, then `MIXED`, then any other)."""
    present = list(dict.fromkeys(e.family for e in entries))
    known = [*FAMILIES, MIXED]
    return sorted(present, key=lambda f: known.index(f) if f in known else len(known))


def _finite(values) -> list[float]:
    return [float(v) for v in values if v is not None and not math.isnan(v)]


def _mean(values) -> float | None:
    values = _finite(values)
    return sum(values) / len(values) if values else None


def _worst(named: dict[str, float | None]) -> dict:
    """`{"value", "entry"}` of the least score (None when none is a number)."""
    finite = {k: float(v) for k, v in named.items() if v is not None and not math.isnan(v)}
    if not finite:
        return {"value": None, "entry": None}
    entry = min(finite, key=finite.__getitem__)
    return {"value": finite[entry], "entry": entry}


def summarize(entries: Sequence[ZooEntry], scores: dict, methods: Sequence[str]) -> dict:
    """Per method: per family the mean and worst over its entries (one entry: its score), and over the
    whole zoo the mean and the worst entry, of each metric.

    Args:
      entries: the zoo, in order.
      scores: entry name -> method name -> metric name ("AP", "AP50", "AP25") -> fraction (None: no score).
      methods: method names.

    Returns:
      method -> {"families": family -> {"entries", "mean": metric -> v, "worst": metric -> {"value",
      "entry"}}, "mean": metric -> v, "worst": metric -> {"value", "entry"}}.
    """
    metrics = [name for name, _ in METRICS]
    out = {}
    for method in methods:
        families = {}
        for family in family_order(entries):
            names = [e.name for e in entries if e.family == family]
            families[family] = {
                "entries": names,
                "mean": {m: _mean(scores[n][method][m] for n in names) for m in metrics},
                "worst": {m: _worst({n: scores[n][method][m] for n in names}) for m in metrics},
            }
        out[method] = {
            "families": families,
            "mean": {m: _mean(scores[e.name][method][m] for e in entries) for m in metrics},
            "worst": {m: _worst({e.name: scores[e.name][method][m] for e in entries}) for m in metrics},
        }
    return out


def best_methods(values: dict[str, float | None]) -> list[str]:
    """The methods with the highest score (all of them on a tie; none when no score is a number)."""
    finite = {k: v for k, v in values.items() if v is not None and not math.isnan(v)}
    if not finite:
        return []
    top = max(finite.values())
    return [k for k, v in finite.items() if v == top]


def family_rows(summary: dict, methods: Sequence[str], metric: str = "AP50") -> list[tuple[str, dict]]:
    """Rows of the per-family table: (title, method -> value) per family (a family of several entries,
    such as `mixed`, gives its mean and its worst), then the zoo's mean and worst."""
    first = summary[methods[0]]["families"]
    rows = []
    for family, info in first.items():
        if len(info["entries"]) > 1:
            rows.append(
                (
                    f"{family} (mean of {len(info['entries'])})",
                    {m: summary[m]["families"][family]["mean"][metric] for m in methods},
                )
            )
            rows.append((f"{family} (worst)", {m: summary[m]["families"][family]["worst"][metric]["value"] for m in methods}))
        else:
            rows.append((family, {m: summary[m]["families"][family]["mean"][metric] for m in methods}))
    rows.append(("mean", {m: summary[m]["mean"][metric] for m in methods}))
    rows.append(("worst", {m: summary[m]["worst"][metric]["value"] for m in methods}))
    return rows


def verdict(summary: dict, methods: Sequence[str], metric: str = "AP50", new: str = "full", old: str = "previous") -> dict:
    """Who wins on the mean, on the worst entry and on each family (`metric`), and whether `new` beats
    `old` (strictly) on every family; `where_not` lists the families where it does not."""

    def winners(get):
        return best_methods({m: get(m) for m in methods})

    record = {
        "metric": metric,
        "mean": winners(lambda m: summary[m]["mean"][metric]),
        "worst": winners(lambda m: summary[m]["worst"][metric]["value"]),
        "families": {
            f: winners(lambda m, f=f: summary[m]["families"][f]["mean"][metric]) for f in summary[methods[0]]["families"]
        },
    }
    if new in methods and old in methods:
        where_not = []
        for family in summary[new]["families"]:
            a = summary[new]["families"][family]["mean"][metric]
            b = summary[old]["families"][family]["mean"][metric]
            if a is None or b is None or not a > b:
                where_not.append({"family": family, new: a, old: b})
        record["beats"] = {"new": new, "old": old, "every_family": not where_not, "where_not": where_not}
    return record


def precision_counts(gt_ids: np.ndarray, predictions) -> dict[str, int]:
    """`{"objects", "predictions", "no_object"}` of one run: the counted ground-truth objects, the evaluated
    predictions and those of kind "no_object" (`explain.explain_scene` on the benchmark predictions).

    Args:
      gt_ids: `(V,)` benchmark ids of the scene's mesh vertices.
      predictions: the run's `InstancePredictions` over the same vertices.
    """

    explanation = explain_scene(gt_ids, predictions)
    return {
        "objects": len(explanation.ground_truth),
        "predictions": len(explanation.predictions),
        "no_object": explanation.kind_counts()["no_object"],
    }


def pooled_precision(counts: Sequence[Mapping[str, int]], ap50: float | None) -> dict:
    """The precision summary of one (method, entry) from its runs' `precision_counts` (pooled: counts summed
    over the scenes, then divided) and its pooled AP50; None where the divisor is 0."""
    objects = sum(c["objects"] for c in counts)
    predictions = sum(c["predictions"] for c in counts)
    no_object = sum(c["no_object"] for c in counts)
    return {
        "no_object_share": no_object / predictions if predictions else None,
        "instances_per_object": predictions / objects if objects else None,
        "AP50": ap50,
        "objects": objects,
        "predictions": predictions,
        "no_object": no_object,
    }


def _worst_of(named: dict[str, float | None], higher_is_worse: bool) -> dict:
    if not higher_is_worse:
        return _worst(named)
    flipped = _worst({k: None if v is None else -v for k, v in named.items()})
    return {"value": None if flipped["value"] is None else -flipped["value"], "entry": flipped["entry"]}


def summarize_precision(entries: Sequence[ZooEntry], precision: dict, methods: Sequence[str]) -> dict:
    """Per method, over the zoo: the mean of each `PRECISION` number and its worst entry (the highest
    no-object share and instances per object, the lowest AP50).

    Args:
      precision: entry name -> method name -> `pooled_precision` record.

    Returns:
      method -> {"mean": key -> v, "worst": key -> {"value", "entry"}}.
    """
    return {
        m: {
            "mean": {key: _mean(precision[e.name][m][key] for e in entries) for _, key, _ in PRECISION},
            "worst": {key: _worst_of({e.name: precision[e.name][m][key] for e in entries}, up) for _, key, up in PRECISION},
        }
        for m in methods
    }


def _pct(value: float | None) -> str:
    return "-" if value is None or math.isnan(value) else f"{100 * value:.1f}"


def entries_table(entries: Sequence[ZooEntry], scores: dict, summary: dict, methods: Sequence[Method]) -> str:
    """Rows: the zoo entries grouped by family, then the mean and the worst (with its entry); columns:
    each method's AP, AP50 and AP25 (%)."""
    header = ["Family", "Entry"] + [f"{m.name} {metric}" for m in methods for metric, _ in METRICS]
    rows = []
    for family in family_order(entries):
        for i, entry in enumerate(e for e in entries if e.family == family):
            rows.append(
                [family if i == 0 else "", entry.name]
                + [_pct(scores[entry.name][m.name][metric]) for m in methods for metric, _ in METRICS]
            )
    rows.append(["**mean**", ""] + [_pct(summary[m.name]["mean"][metric]) for m in methods for metric, _ in METRICS])
    worst = [summary[m.name]["worst"][metric] for m in methods for metric, _ in METRICS]
    rows.append(["**worst**", ""] + [f"{_pct(w['value'])} ({w['entry']})" if w["entry"] else "-" for w in worst])
    return markdown_table(header, rows)


def _precision_cell(key: str, value: float | None) -> str:
    if value is None or math.isnan(value):
        return "-"
    return f"{value:.2f}" if key == "instances_per_object" else _pct(value)


def precision_table(entries: Sequence[ZooEntry], precision: dict, summary: dict, methods: Sequence[Method]) -> str:
    """Rows: the zoo entries grouped by family, then the mean and the worst (with its entry); columns: each
    method's no-object share (%), instances per object and AP50 (%)."""
    header = ["Family", "Entry"] + [f"{m.name} {title}" for m in methods for title, _, _ in PRECISION]
    rows = []
    for family in family_order(entries):
        for i, entry in enumerate(e for e in entries if e.family == family):
            rows.append(
                [family if i == 0 else "", entry.name]
                + [_precision_cell(key, precision[entry.name][m.name][key]) for m in methods for _, key, _ in PRECISION]
            )
    rows.append(
        ["**mean**", ""] + [_precision_cell(key, summary[m.name]["mean"][key]) for m in methods for _, key, _ in PRECISION]
    )
    worst = [(key, summary[m.name]["worst"][key]) for m in methods for _, key, _ in PRECISION]
    rows.append(
        ["**worst**", ""] + [f"{_precision_cell(key, w['value'])} ({w['entry']})" if w["entry"] else "-" for key, w in worst]
    )
    return markdown_table(header, rows)


def family_table(summary: dict, methods: Sequence[Method], metric: str = "AP50") -> str:
    """AP50 (%) per family (rows, then mean and worst) and method (columns); the best of each row in bold."""
    names = [m.name for m in methods]
    rows = []
    for title, values in family_rows(summary, names, metric):
        best = best_methods(values)
        rows.append([title] + [f"**{_pct(values[n])}**" if n in best else _pct(values[n]) for n in names])
    return markdown_table(["Family", *names], rows)


def verdict_lines(record: dict) -> list[str]:
    """The verdict as sentences."""
    metric = record["metric"]
    join = lambda names: " = ".join(names) if names else "-"  # noqa: E731 - ties are shown as equals
    lines = [
        f"- Best {metric} on the mean over the zoo: {join(record['mean'])}; on the worst entry: {join(record['worst'])}.",
        "- Best per family: " + ", ".join(f"{f}: {join(w)}" for f, w in record["families"].items()) + ".",
    ]
    beats = record.get("beats")
    if beats:
        new, old = beats["new"], beats["old"]
        line = f"- {new} beats {old} on every family ({metric}): {'yes' if beats['every_family'] else 'no'}"
        if beats["where_not"]:
            line += ", where not: " + ", ".join(f"{w['family']} ({_pct(w[new])} vs {_pct(w[old])})" for w in beats["where_not"])
        lines.append(line + ".")
    return lines


def noise_table(entries: Sequence[ZooEntry]) -> str:
    """The parameters of each entry that differ from the `default` preset (generated scenes' pixel counts
    are scaled to their images: see each scene's record in robustness.json)."""

    # Every parameter, the later ones too (`to_dict` leaves those out at their defaults).
    default = dataclasses.asdict(NoiseModel.preset("default", seed=entries[0].noise.seed)) if entries else {}
    values = [dataclasses.asdict(e.noise) for e in entries]
    changed = [k for k in default if any(v[k] != default[k] for v in values)]
    header = ["Parameter", "default preset", *(e.name for e in entries)]
    show = lambda v: f"{v:.3g}" if isinstance(v, float) else str(v)  # noqa: E731
    rows = [[k, show(default[k]), *(show(v[k]) for v in values)] for k in changed]
    return markdown_table(header, rows) if rows else "(every entry is the default preset)"


def robustness_markdown(
    entries: Sequence[ZooEntry],
    scores: dict,
    summary: dict,
    verdict_record: dict,
    methods: Sequence[Method],
    scenes: Sequence[dict],
    noise_seed: int,
    seconds: float,
    runs: int,
    precision: dict | None = None,
    precision_summary: dict | None = None,
) -> str:
    """robustness.md (the precision table when `precision`, entry -> method -> `pooled_precision`, and its
    `summarize_precision` are given)."""
    precision_lines = []
    if precision is not None and precision_summary is not None:
        precision_lines = [
            "## Precision per zoo entry",
            "",
            "No-object %: share of the evaluated predictions that overlap no counted ground-truth object "
            "(`explain` kind no_object: mostly wall, floor or void); inst/obj: evaluated predictions per counted "
            "object; both pooled over the scenes. Worst: the highest no-object share and instances per object, "
            "the lowest AP50.",
            "",
            precision_table(entries, precision, precision_summary, methods),
            "",
        ]
    scene_lines = []
    for s in scenes:
        what = scene_kind(s)
        scene_lines.append(f"- `{s['name']}`: {what}, {s['frames']} frames, config {s['config']}")
    return "\n".join(
        [
            "# Robustness to detection noise",
            "",
            f"Methods: {', '.join(f'`{m.name}` ({m.title})' for m in methods)}. Zoo: {len(entries)} noise models "
            f"(`simulation.zoo.noise_zoo`, seed {noise_seed}), detections simulated on every frame of "
            f"{len(scenes)} scene{'' if len(scenes) == 1 else 's'}. Per entry the runs are pooled over the scenes by the "
            "ScanNet benchmark; "
            "AP in %.",
            "",
            "## Scores per zoo entry",
            "",
            entries_table(entries, scores, summary, methods),
            "",
            "## AP50 per family (best in bold)",
            "",
            family_table(summary, methods),
            "",
            *verdict_lines(verdict_record),
            "",
            *precision_lines,
            "## Scenes and noise models",
            "",
            *scene_lines,
            "",
            "<details><summary>Noise parameters of each zoo entry (those differing from the default preset)</summary>",
            "",
            noise_table(entries),
            "",
            "</details>",
            "",
            f"{runs} runs in {seconds:.0f} s ({seconds / max(runs, 1):.1f} s per run with simulation and scoring; "
            "timings per run in robustness.json).",
            "",
        ]
    )


# Colours (BGR) of the bars, one per method in order.
_PALETTE = ((180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148), (75, 86, 140))


def bar_chart(
    groups: Sequence[str],
    series: Mapping[str, Sequence[float | None]],
    title: str,
    height: int = 420,
    separator_before: int | None = None,
) -> np.ndarray:
    """`(H, W, 3)` uint8 BGR grouped bar chart: one group per name of `groups`, one bar per series (values
    fractions in [0, 1], shown in %; None: no bar), with a 0-100 % axis and a legend; a vertical line
    before group `separator_before` (the summaries)."""

    font, names = cv2.FONT_HERSHEY_SIMPLEX, list(series)
    bar_w, gap, left, right, top, bottom = 14, 16, 50, 20, 50, 80
    group_w = bar_w * len(names) + gap
    width = max(left + right + group_w * len(groups), 420)
    image = np.full((height, width, 3), 255, np.uint8)
    plot_h = height - top - bottom
    y_of = lambda v: int(round(top + plot_h * (1.0 - v)))  # noqa: E731
    for tick in range(0, 101, 20):
        y = y_of(tick / 100)
        cv2.line(image, (left, y), (width - right, y), (220, 220, 220), 1)
        cv2.putText(image, f"{tick}", (8, y + 4), font, 0.4, (60, 60, 60), 1, cv2.LINE_AA)
    for g, group in enumerate(groups):
        x0 = left + gap // 2 + g * group_w
        for s, name in enumerate(names):
            value = series[name][g]
            if value is None or math.isnan(value):
                continue
            x = x0 + s * bar_w
            cv2.rectangle(
                image, (x, y_of(min(max(value, 0.0), 1.0))), (x + bar_w - 2, y_of(0.0)), _PALETTE[s % len(_PALETTE)], -1
            )
        # group names written at a slant would need rotation; two lines of short text read well enough
        label, second = (group, "") if len(group) <= 10 else (group[:10], group[10:20])
        cv2.putText(image, label, (x0, height - bottom + 16), font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
        if second:
            cv2.putText(image, second, (x0, height - bottom + 30), font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    if separator_before is not None:
        x = left + separator_before * group_w
        cv2.line(image, (x, top), (x, y_of(0.0)), (150, 150, 150), 1)
    cv2.line(image, (left, y_of(0.0)), (width - right, y_of(0.0)), (0, 0, 0), 1)
    cv2.putText(image, title, (left, 22), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    x = left
    for s, name in enumerate(names):
        cv2.rectangle(image, (x, height - 28), (x + 12, height - 16), _PALETTE[s % len(_PALETTE)], -1)
        cv2.putText(image, name, (x + 16, height - 17), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        x += 24 + 10 * len(name)
    return image


def robustness_chart(entries: Sequence[ZooEntry], scores: dict, summary: dict, methods: Sequence[str]) -> np.ndarray:
    """AP50 per zoo entry and method, then the zoo's mean and worst."""
    groups = [e.name for e in entries] + ["mean", "worst"]
    series = {
        m: [scores[e.name][m]["AP50"] for e in entries] + [summary[m]["mean"]["AP50"], summary[m]["worst"]["AP50"]["value"]]
        for m in methods
    }
    return bar_chart(groups, series, "AP50 (%) per noise model of the zoo", separator_before=len(entries))
