"""The files of an error analysis (`explain.SceneExplanation`): `explain.md`, `explain.json` and the
picture `explain.png` (`explain_picture`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from fmfusion_jax.evaluation.explain import GT_STATUSES, PREDICTION_KINDS, SceneExplanation
from fmfusion_jax.evaluation.explain_picture import write_explanation_picture
from fmfusion_jax.evaluation.scannet_benchmark import MIN_REGION_SIZE
from fmfusion_jax.io.benchmark_format import InstancePredictions


def explanation_markdown(explanation: SceneExplanation) -> str:
    """`explain.md`: summary counts, per-class counts, the objects, the predictions sorted by kind."""
    e = explanation
    ap50 = e.ap50_counts()
    lines = [
        f"# Error analysis: {e.scene_name}",
        "",
        f"{len(e.ground_truth)} ground-truth objects (18 benchmark classes, at least {MIN_REGION_SIZE} "
        f"vertices); {len(e.predictions)} evaluated predictions of {e.num_input_predictions} "
        f"({e.num_skipped_predictions} not evaluated: under {MIN_REGION_SIZE} vertices or of another class). "
        f"At AP50 the benchmark counts {ap50['true_positive']} true positives, "
        f"{ap50['false_positive']} false positives and ignores {ap50['ignored']} predictions.",
        "",
        "Rules: docs/error-analysis.md (and `fmfusion_jax/evaluation/explain.py`). "
        "IoU passes 0.5 / 0.25 when strictly greater, as in the benchmark.",
        "",
        "## Summary",
        "",
        "| objects by status | count |",
        "|---|---:|",
        *(f"| {k} | {v} |" for k, v in e.status_counts().items()),
        "",
        "| predictions by kind | count |",
        "|---|---:|",
        *(f"| {k} | {v} |" for k, v in e.kind_counts().items()),
        "",
        "## Per class",
        "",
    ]
    per_class = e.class_counts()
    for total, key, names in (("objects", "status", GT_STATUSES), ("predictions", "kind", PREDICTION_KINDS)):
        lines += [f"| class | {total} | " + " | ".join(names) + " |", "|---|" + "---:|" * (1 + len(names))]
        lines += [
            f"| {name} | {row[total]} | " + " | ".join(str(n) for n in row[key].values()) + " |"
            for name, row in per_class.items()
            if row[total]
        ]
        lines.append("")
    lines += [
        "## Ground-truth objects",
        "",
        "Best prediction: the highest IoU, any class. Fragments: predictions with more than half of "
        "their vertices inside the object that do not pass 0.5 with it.",
        "",
        "| gt id | class | vertices | status | best pred | its class | conf | IoU | same-class IoU | "
        "AP50 match | fragments | centroid |",
        "|---:|---|---:|---|---:|---|---:|---:|---:|---:|---:|---|",
    ]
    order = {s: k for k, s in enumerate(GT_STATUSES)}
    for g in sorted(e.ground_truth, key=lambda g: (order[g.status], g.gt_id)):
        lines.append(
            f"| {g.gt_id} | {g.class_name} | {g.size} | {g.status} | {_cell(g.best_prediction)} | "
            f"{_cell(g.best_class)} | {_num(g.best_confidence)} | {g.best_iou:.3f} | "
            f"{g.best_same_class_iou:.3f} | {_cell(g.match)} | {g.num_fragments} | {_xyz(g.centroid)} |"
        )
    lines += [
        "",
        "## Predictions by kind",
        "",
        "Pred: row in the prediction file (mask `<scene>_<pred>.txt`). Shares of its vertices against its "
        "reference object: on it, on other objects, on small objects, wall, floor, void.",
        "",
        "| pred | class | conf | vertices | kind | AP50 | best gt | its class | IoU | reference gt | "
        "object | other obj. | small obj. | wall | floor | void | centroid |",
        "|---:|---|---:|---:|---|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    order = {k: n for n, k in enumerate(PREDICTION_KINDS)}
    for p in sorted(e.predictions, key=lambda p: (order[p.kind], -p.confidence, p.index)):
        shares = " | ".join(f"{s:.2f}" for s in p.shares)
        lines.append(
            f"| {p.index} | {p.class_name} | {p.confidence:.3f} | {p.size} | {p.kind} | {p.ap50} | "
            f"{_cell(p.best_gt)} | {_cell(p.best_gt_class)} | {p.best_iou:.3f} | {_cell(p.reference_gt)} | "
            f"{shares} | {_xyz(p.centroid)} |"
        )
    return "\n".join(lines) + "\n"


def write_explanation(
    out_dir: str | Path,
    explanation: SceneExplanation,
    gt_ids: np.ndarray | None = None,
    preds: InstancePredictions | None = None,
    vertices: np.ndarray | None = None,
    faces: np.ndarray | None = None,
    title: str | None = None,
) -> list[Path]:
    """Writes `explain.md`, `explain.json` and, given the vertices (and the ids and predictions the
    explanation was made from), `explain.png` into `out_dir` (created).

    Args:
      gt_ids: `(V,)`, preds: `(P, V)`, vertices: `(V, 3)`, faces: `(F, 3)` optional (sizes the splats).

    Returns:
      the paths written.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [out_dir / "explain.md", out_dir / "explain.json"]
    written[0].write_text(explanation_markdown(explanation))
    written[1].write_text(json.dumps(explanation.to_json_dict(), indent=1) + "\n")
    if vertices is not None and gt_ids is not None and preds is not None:
        written.append(write_explanation_picture(out_dir / "explain.png", explanation, gt_ids, preds, vertices, faces, title))
    return written


def _cell(value) -> str:
    return "-" if value is None else str(value)


def _num(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def _xyz(point) -> str:
    return "-" if point is None else "(" + ", ".join(f"{v:.2f}" for v in point) + ")"
