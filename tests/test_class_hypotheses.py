"""Alternative class hypotheses in the benchmark files (`export.alternative_class_probability`).

An instance is submitted under its most likely class and under each other class it has at least the threshold's
probability of, at confidence probability x existence. Checked: which hypotheses are made (a property against a
direct oracle), the files (one mask per instance, listed again), that the error analysis counts instances, and
what it does to the benchmark: an instance whose fused distribution put the right class second is found.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fmfusion_jax.errors import DataError
from fmfusion_jax.evaluation.explain import explain_scene
from fmfusion_jax.evaluation.scannet_benchmark import evaluate_scenes
from fmfusion_jax.instances import MapInstance
from fmfusion_jax.io.benchmark_format import InstancePredictions, read_benchmark_predictions, write_benchmark_predictions
from fmfusion_jax.io.map_outputs import alternative_class_hypotheses, benchmark_predictions
from fmfusion_jax.labels import load_label_sets

LABELS = load_label_sets()
STRUCTURE = {LABELS.class_index("wall"), LABELS.class_index("floor")}


def instance(instance_id: int, distribution, points=None, existence: float = 1.0) -> MapInstance:
    distribution = np.asarray(distribution, np.float64)
    points = np.zeros((1, 3), np.float32) if points is None else np.asarray(points, np.float32)
    return MapInstance(instance_id, distribution / distribution.sum(), points, 5, np.zeros(LABELS.num_open), existence=existence)


def hypotheses_oracle(instances, threshold):
    """Every (row, class, confidence) the rule asks for, in no particular order."""
    out = set()
    for row, inst in enumerate(instances):
        for c, p in enumerate(inst.distribution):
            if c != int(np.argmax(inst.distribution)) and c not in STRUCTURE and p >= threshold and p > 0:
                out.add((row, c, round(float(p) * inst.existence, 12)))
    return out


@given(
    st.lists(st.tuples(st.lists(st.floats(0.0, 1.0), min_size=20, max_size=20), st.floats(0.0, 1.0)), min_size=0, max_size=6),
    st.sampled_from([0.0, 0.05, 0.1, 0.3, 1.0]),
)
@settings(max_examples=80, deadline=None)
def test_hypotheses_are_the_other_classes_above_the_threshold(rows, threshold):
    instances = [instance(i, np.asarray(d) + 1e-3, existence=e) for i, (d, e) in enumerate(rows)]
    got_rows, got_classes, got_confidences = alternative_class_hypotheses(instances, LABELS, threshold)
    got = {(int(r), int(c), round(float(x), 12)) for r, c, x in zip(got_rows, got_classes, got_confidences)}
    assert got == hypotheses_oracle(instances, threshold)
    assert len(got) == len(got_rows)  # no hypothesis twice
    for r, x in zip(got_rows, got_confidences):  # never above the instance's own confidence
        assert x <= instances[r].confidence + 1e-12
    assert np.all(np.diff(got_rows) >= 0)  # in instance order


def test_threshold_one_is_the_most_likely_class_only():
    split = np.full(20, 0.01)
    split[LABELS.class_index("cabinet")], split[LABELS.class_index("counter")] = 0.45, 0.45
    rows, classes, confidences = alternative_class_hypotheses([instance(0, split)], LABELS, 1.0)
    assert len(rows) == len(classes) == len(confidences) == 0


def test_files_give_each_line_its_own_mask_and_read_back_the_alternatives(tmp_path):
    vertices = np.stack(np.meshgrid(np.arange(0, 2, 0.05), np.arange(0, 1, 0.05), [0.0]), -1).reshape(-1, 3)
    split = np.full(20, 0.01)
    split[LABELS.class_index("cabinet")], split[LABELS.class_index("counter")] = 0.5, 0.3
    sure = np.full(20, 0.01)
    sure[LABELS.class_index("sofa")] = 0.9
    wall_second = np.full(20, 0.01)
    wall_second[LABELS.class_index("door")], wall_second[LABELS.class_index("wall")] = 0.5, 0.4
    left, right = vertices[vertices[:, 0] < 0.6], vertices[vertices[:, 0] > 1.4]
    middle = vertices[(vertices[:, 0] > 0.8) & (vertices[:, 0] < 1.2)]
    instances = [instance(0, split, left, 0.8), instance(1, sure, right), instance(2, wall_second, middle)]
    preds = benchmark_predictions(instances, LABELS, vertices, 0.03, alternative_class_probability=0.1)
    assert preds.num_instances == 3 and preds.num_predictions == 4  # the door's second class is the wall: none
    assert preds.nyu40_ids[3] == LABELS.nyu40_ids[LABELS.class_index("counter")]
    assert preds.confidences[3] == pytest.approx(instances[0].distribution[LABELS.class_index("counter")] * 0.8)
    assert np.array_equal(preds.masks[3], preds.masks[0]) and preds.alternative.tolist() == [False] * 3 + [True]

    txt = write_benchmark_predictions(tmp_path, "s", preds)
    lines = txt.read_text().splitlines()
    # a mask file per line: the official script keys the predictions by mask file (a file listed twice keeps its
    # last line only), so the counter has a copy of the cabinet's mask
    assert len(lines) == 4 and len({line.split()[0] for line in lines}) == 4
    assert (tmp_path / lines[3].split()[0]).read_bytes() == (tmp_path / lines[0].split()[0]).read_bytes()
    back = read_benchmark_predictions(txt, len(vertices))
    assert back.alternative.tolist() == preds.alternative.tolist()
    assert np.array_equal(back.masks, preds.masks) and np.array_equal(back.nyu40_ids, preds.nyu40_ids)
    assert back.primary().num_predictions == 3 and not back.primary().alternative.any()

    # A mask file listed twice is refused, named (the official script would keep its last line only).
    txt.write_text(txt.read_text() + lines[0].split()[0] + " 5 0.1\n")
    with pytest.raises(DataError, match="already listed on line 1"):
        read_benchmark_predictions(txt, len(vertices))


def test_equal_masks_read_back_as_alternatives_only_under_another_class(tmp_path):
    """Read back, a line is an alternative when an earlier line has the same vertices under another class; the
    same vertices under the same class are another instance, and an empty mask is never an alternative."""
    masks = np.zeros((5, 10), bool)
    masks[0, :4] = masks[1, :4] = masks[2, :4] = True
    preds = InstancePredictions(masks, [3, 3, 4, 5, 6], [0.9, 0.8, 0.3, 0.7, 0.6])
    back = read_benchmark_predictions(write_benchmark_predictions(tmp_path, "s", preds))
    assert back.alternative.tolist() == [False, False, True, False, False]
    assert back.num_instances == 4


def gt_scene(num_vertices: int = 400):
    """Benchmark ids of 400 vertices: a cabinet (0-99), a counter (100-199), the rest void."""
    cabinet, counter = LABELS.nyu40_ids[LABELS.class_index("cabinet")], LABELS.nyu40_ids[LABELS.class_index("counter")]
    ids = np.zeros(num_vertices, np.int64)
    ids[:100] = cabinet * 1000 + 1
    ids[100:200] = counter * 1000 + 2
    return ids


def test_a_right_second_class_is_found_and_the_explanation_counts_instances():
    ids = gt_scene()
    masks = np.zeros((2, 400), bool)
    masks[0, :100] = True  # the cabinet, called a counter first
    masks[1, 100:200] = True  # the counter, called a counter
    counter, cabinet = LABELS.nyu40_ids[LABELS.class_index("counter")], LABELS.nyu40_ids[LABELS.class_index("cabinet")]
    top_only = InstancePredictions(masks, [counter, counter], [0.5, 0.9])
    with_second = InstancePredictions(
        np.concatenate([masks, masks[:1]]), [counter, counter, cabinet], [0.5, 0.9, 0.4], [False, False, True]
    )
    before, after = evaluate_scenes([(ids, top_only)]), evaluate_scenes([(ids, with_second)])
    assert before.ap50["cabinet"] == 0.0 and after.ap50["cabinet"] == 1.0
    assert after.ap50["counter"] == before.ap50["counter"]  # the counter's ranking is untouched
    # The error analysis sees the map's two instances, not three predictions.
    explanation = explain_scene(ids, with_second.primary())
    assert len(explanation.predictions) == 2
