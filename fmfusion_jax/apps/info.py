"""`fmfusion info`'s work (the parser is `cli/info.py`)."""

from __future__ import annotations

import collections
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from fmfusion_jax.errors import DataError
from fmfusion_jax.io.detections import list_detection_frames, read_frame_labels
from fmfusion_jax.io.scene import open_scene
from fmfusion_jax.labels import load_label_sets

#: Depth images read for the depth statistics and the bounds (the rest of the scene is never decoded).
SAMPLED_FRAMES = 30


def run_info(
    *,
    scene_dir: Path,
    layout: str,
    stride: int,
    depth_max: float,
    detections: Path | None,
) -> int:

    scene = open_scene(scene_dir, layout=layout, stride=stride, depth_max=depth_max)
    for key, value in describe_scene(scene):
        print(f"{key:<13} {value}")
    if detections is not None:
        for key, value in describe_detections(detections, scene.frame_names):
            print(f"{key:<13} {value}")
    return 0


def describe_scene(scene) -> list[tuple[str, str]]:
    """(heading, text) lines summarizing a `Scene`."""
    intrinsics = scene.intrinsics
    lines = [
        ("scene", f"{scene.name}  ({scene.path})"),
        ("layout", scene.layout),
        ("frames", f"{len(scene)} usable (stride {scene.stride}), {len(scene.skipped)} skipped"),
    ]
    for name, reason in scene.skipped[:10]:
        lines.append(("  skipped", f"{name}: {reason}"))
    if len(scene.skipped) > 10:
        lines.append(("  skipped", f"... and {len(scene.skipped) - 10} more"))
    lines += [
        ("image size", f"{intrinsics.width} x {intrinsics.height}"),
        (
            "intrinsics",
            f"fx {intrinsics.fx:.2f}  fy {intrinsics.fy:.2f}  cx {intrinsics.cx:.2f}  cy {intrinsics.cy:.2f}  "
            f"(depth camera; depth png {scene.depth_scale:g} units per metre)",
        ),
    ]
    if len(scene):
        sample = scene.sample_depth(max_frames=SAMPLED_FRAMES)
        p01, p25, p50, p75, p99 = sample.depth_percentiles
        lines.append(
            (
                "depth",
                f"{p01:.2f} / {p25:.2f} / {p50:.2f} / {p75:.2f} / {p99:.2f} m "
                f"(1/25/50/75/99th percentile), {100 * sample.valid_fraction:.1f}% of pixels valid, "
                f"truncated at {scene.depth_max:g} m; from {len(sample.frame_names)} frames",
            )
        )
        lower, upper = scene.bounds(sample=sample)
        size = upper - lower
        lines.append(
            ("bounds", f"min {_vector(lower)}  max {_vector(upper)}  size {_vector(size)} m (sampled depth + 0.25 m margin)")
        )
        frustum_lower, frustum_upper = scene.bounds(method="frustum")
        lines.append(
            (
                "  frusta",
                f"min {_vector(frustum_lower)}  max {_vector(frustum_upper)} m (every view frustum to {scene.depth_max:g} m)",
            )
        )
        positions = scene.poses()[:, :3, 3]
        lines.append(
            (
                "trajectory",
                f"{scene.trajectory_length():.2f} m over {len(scene)} poses; camera within "
                f"{_vector(positions.min(axis=0))} .. {_vector(positions.max(axis=0))}",
            )
        )
    for role, path in scene.ground_truth_files().items():
        lines.append(("ground truth", f"{role + ':':<15} {path.name if path else 'absent'}"))
    return lines


def describe_detections(folder: Path, scene_frames: Sequence[str]) -> list[tuple[str, str]]:
    """(heading, text) lines summarizing a detection folder (reads the JSON files, not the masks)."""

    detection_frames = list_detection_frames(folder)
    in_scene = set(scene_frames)
    matched = [name for name in detection_frames if name in in_scene]
    unmatched = [name for name in detection_frames if name not in in_scene]
    counts, errors = [], []
    top_labels: collections.Counter[str] = collections.Counter()
    for name in matched:
        try:
            parsed = read_frame_labels(folder, name)
        except DataError as error:
            errors.append(str(error))
            continue
        assert parsed is not None  # a listed frame has its _label.json
        counts.append(len(parsed["labels"]))
        top_labels.update(max(labels, key=labels.get) for labels in parsed["labels"] if labels)

    lines = [("detections", f"{folder}: {len(matched)} of {len(scene_frames)} scene frames have detection files")]
    if unmatched:
        lines.append(
            ("  unmatched", f"{len(unmatched)} files name no frame of the scene (or are cut by the stride), e.g. {unmatched[0]}")
        )
    if errors:
        lines.append(("  malformed", f"{len(errors)} files; first: {errors[0]}"))
    if counts:
        lines.append(("  per frame", f"median {np.median(counts):g}, max {max(counts)}, total {sum(counts)}"))
        open_labels = set(load_label_sets().open_labels)
        histogram = ", ".join(
            f"{label}{'' if label in open_labels else '*'} {count}" for label, count in top_labels.most_common(10)
        )
        lines.append(("  top labels", histogram + "  (best label per detection; * = not an open-set label)"))
    return lines


def _vector(values) -> str:
    return "[" + " ".join(f"{float(x):6.2f}" for x in values) + "]"
