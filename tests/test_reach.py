"""The detector's reach (`likelihood.reach`): what the detections ever saw of each ground-truth object."""

from __future__ import annotations

import numpy as np
import pytest

from fmfusion_jax.io.detections import DetectionFolder, write_frame_detections
from fmfusion_jax.likelihood.reach import detector_reach
from fmfusion_jax.simulation.noise import NoiseModel
from fmfusion_jax.simulation.scene_sets import GeneratedSceneSpec, generated_scene, simulated_detections
from fmfusion_jax.types import FrameDetections

SPEC = GeneratedSceneSpec(seed=3, num_objects=5, num_frames=12, width=320, height=240)


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    root = tmp_path_factory.mktemp("reach")
    scene_dir = generated_scene(SPEC, root)
    clean = NoiseModel.preset("clean").replace(min_mask_pixels=50, small_object_pixels=50)
    return scene_dir, simulated_detections(scene_dir, root / "clean", clean), root


def test_clean_detections_see_the_objects_as_their_class(room):
    scene_dir, detections, _ = room
    reach = detector_reach(scene_dir, detections)
    assert reach.objects and reach.detection_frames == SPEC.num_frames
    seen = [o for o in reach.objects if o.seen_as_class]
    assert len(seen) >= 0.6 * len(reach.objects)
    assert all(o.seen and o.best_iou >= 0.5 for o in seen)
    per_class = reach.per_class()
    assert sum(r["objects"] for r in per_class.values()) == len(reach.objects)
    ceiling, strict = reach.ceiling_map50(), reach.ceiling_map50(as_class=True)
    assert strict == pytest.approx(np.mean([r["seen_as_class"] / r["objects"] for r in per_class.values()]))
    assert ceiling == pytest.approx(np.mean([r["seen"] / r["objects"] for r in per_class.values()]))
    assert 0 < strict <= ceiling <= 1
    text = reach.markdown({o.gt_id: True for o in reach.objects})
    assert "Detector reach" in text and f"| **all** | {len(reach.objects)} |" in text


def test_no_detection_sees_nothing(room):
    scene_dir, detections, root = room
    empty = root / "empty"
    for name in DetectionFolder(detections).frame_names:
        write_frame_detections(empty, FrameDetections(name, np.zeros((0, SPEC.height, SPEC.width), bool), [], np.zeros((0, 4))))
    reach = detector_reach(scene_dir, empty)
    assert not any(o.seen for o in reach.objects) and reach.ceiling_map50() == 0.0
    assert any(o.frames_visible > 0 for o in reach.objects)  # in view, never detected


@pytest.mark.parametrize("no_progress", [False, True])
def test_eval_with_detections_prints_the_reach_with_a_bar_unless_told_not_to(room, capsys, no_progress):
    from fmfusion_jax.cli import main

    scene_dir, detections, root = room
    as_predictions = root / f"gt-as-predictions-{no_progress}"
    assert main(["eval", "--gt", str(scene_dir), "--export-gt", str(as_predictions)]) == 0
    capsys.readouterr()
    argv = ["eval", str(as_predictions), "--gt", str(scene_dir), "--detections", str(detections)]
    assert main(argv + (["--no-progress"] if no_progress else [])) == 0
    out, err = capsys.readouterr()
    assert "Detector reach" in out
    assert ("detector reach" in err) is not no_progress
