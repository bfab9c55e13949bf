"""Union hypotheses in the benchmark files (`export.union_confidence_factor`).

Two instances of one class whose vertex masks touch on the mesh (an edge joins them) are also submitted as one,
at the factor times the lower of their confidences. Checked: which pairs are made (a property against a direct
oracle), the files (read back as hypotheses, not instances), and what it does to the benchmark: an object the map
holds in two pieces is found, and the pieces' own ranking is untouched.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fmfusion_jax.evaluation.scannet_benchmark import evaluate_scenes
from fmfusion_jax.instances import MapInstance
from fmfusion_jax.io.benchmark_format import InstancePredictions, read_benchmark_predictions, write_benchmark_predictions
from fmfusion_jax.io.map_outputs import benchmark_predictions, union_hypotheses
from fmfusion_jax.labels import load_label_sets

LABELS = load_label_sets()


def grid_mesh(nx: int, ny: int, step: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """`(vertices (nx*ny, 3), faces (2*(nx-1)*(ny-1), 3))`: a flat triangulated grid, vertex `i*ny + j` at (i, j)."""
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    vertices = np.stack([i * step, j * step, np.zeros_like(i, float)], -1).reshape(-1, 3)
    at = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = at[:-1, :-1].ravel(), at[1:, :-1].ravel(), at[:-1, 1:].ravel(), at[1:, 1:].ravel()
    return vertices, np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])


def pairs_oracle(masks, class_ids, faces):
    """Every pair (a < b) of one class that some face's edge joins, by looping over the edges."""
    out = set()
    for face in faces:
        for u, v in ((face[0], face[1]), (face[1], face[2]), (face[2], face[0])):
            for a in np.flatnonzero(masks[:, u]):
                for b in np.flatnonzero(masks[:, v]):
                    if a != b and class_ids[a] == class_ids[b]:
                        out.add((min(a, b), max(a, b)))
    return out


@given(st.integers(0, 2**31 - 1), st.integers(1, 6), st.integers(1, 3), st.floats(0.05, 1.0))
@settings(max_examples=60, deadline=None)
def test_pairs_are_the_touching_instances_of_one_class(seed, num_instances, num_classes, factor):
    rng = np.random.default_rng(seed)
    _, faces = grid_mesh(6, 5)
    owner = rng.integers(-1, num_instances, 30)  # disjoint masks, as the vertex transfer makes them; -1: no one's
    masks = np.stack([owner == k for k in range(num_instances)])
    class_ids = rng.integers(0, num_classes, num_instances)
    confidences = rng.uniform(0.01, 1.0, num_instances)
    pairs, union_confidences = union_hypotheses(masks, class_ids, confidences, faces, factor)
    assert {tuple(map(int, p)) for p in pairs} == pairs_oracle(masks, class_ids, faces)
    assert len({tuple(p) for p in pairs.tolist()}) == len(pairs)  # each pair once
    assert pairs.tolist() == sorted(pairs.tolist())
    for (a, b), c in zip(pairs, union_confidences):
        assert c == pytest.approx(factor * min(confidences[a], confidences[b]))
        assert c <= min(confidences[a], confidences[b]) + 1e-12  # below both pieces


@given(st.integers(0, 2**31 - 1), st.integers(2, 7))
@settings(max_examples=40, deadline=None)
def test_pairs_hold_at_least_one_primary_line(seed, num_lines):
    """With `primary`, the pairs are the oracle's less those of two alternative class hypotheses."""
    rng = np.random.default_rng(seed)
    _, faces = grid_mesh(6, 5)
    owner = rng.integers(-1, num_lines, 30)
    masks = np.stack([owner == k for k in range(num_lines)])
    class_ids = rng.integers(0, 2, num_lines)
    primary = rng.random(num_lines) < 0.5
    pairs, _ = union_hypotheses(masks, class_ids, rng.uniform(0.1, 1, num_lines), faces, 0.25, primary)
    expected = {(a, b) for a, b in pairs_oracle(masks, class_ids, faces) if primary[a] or primary[b]}
    assert {tuple(map(int, p)) for p in pairs} == expected


def test_no_pairs_without_faces_or_with_one_instance():
    _, faces = grid_mesh(3, 3)
    masks = np.ones((1, 9), bool)
    assert len(union_hypotheses(masks, np.array([0]), np.array([0.5]), faces, 0.5)[0]) == 0
    two = np.zeros((2, 9), bool)
    two[0, :4], two[1, 4:] = True, True
    assert len(union_hypotheses(two, np.array([0, 0]), np.array([0.5, 0.5]), np.zeros((0, 3), int), 0.5)[0]) == 0


def sofa_scene():
    """A 20 x 30 grid: the sofa is columns 0-13 (an L seen as two pieces), a chair columns 16-19 (120 vertices: a
    counted object), the rest void."""
    vertices, faces = grid_mesh(20, 30)
    sofa, chair = LABELS.nyu40_ids[LABELS.class_index("sofa")], LABELS.nyu40_ids[LABELS.class_index("chair")]
    column = np.arange(len(vertices)) // 30
    ids = np.zeros(len(vertices), np.int64)
    ids[column <= 13] = sofa * 1000 + 1
    ids[column >= 16] = chair * 1000 + 2
    return vertices, faces, column, ids


def instance(instance_id, class_name, points, existence=1.0, second=None):
    """An instance sure of `class_name`; with `second`, 0.35 of it goes to that class instead."""
    distribution = np.full(LABELS.num_classes, 0.01)
    distribution[LABELS.class_index(class_name)] = 1.0
    if second is not None:
        distribution[LABELS.class_index(second)] = 0.6
    return MapInstance(
        instance_id,
        distribution / distribution.sum(),
        np.asarray(points, np.float32),
        5,
        np.zeros(LABELS.num_open),
        existence=existence,
    )


def test_an_object_in_two_pieces_is_found_and_read_back_as_a_hypothesis(tmp_path):
    vertices, faces, column, ids = sofa_scene()
    left, right = vertices[column <= 6], vertices[(column >= 7) & (column <= 13)]
    instances = [
        instance(0, "sofa", left, 0.9),
        instance(1, "sofa", right, 0.6),
        instance(2, "chair", vertices[column >= 16], 0.8),
        instance(3, "sofa", vertices[column >= 17], 0.2),  # touches the chair, of another class: no union with it
    ]
    kwargs = dict(label_sets=LABELS, vertices=vertices, radius=0.03, faces=faces)
    without = benchmark_predictions(instances, union_confidence_factor=0.0, **kwargs)
    with_union = benchmark_predictions(instances, union_confidence_factor=0.5, **kwargs)
    assert without.num_predictions == 4
    assert with_union.num_instances == 4 and with_union.num_predictions == 5  # sofa pieces 0 and 1; 3 is apart
    assert np.array_equal(with_union.masks[4], with_union.masks[0] | with_union.masks[1])
    assert with_union.confidences[4] == pytest.approx(0.5 * instances[1].confidence)
    assert with_union.alternative.tolist() == [False] * 4 + [True]

    before, after = evaluate_scenes([(ids, without)]), evaluate_scenes([(ids, with_union)])
    # each piece has half the sofa (IoU 0.5 does not pass 0.5); their union is the sofa
    assert before.ap50["sofa"] == 0.0 and after.ap50["sofa"] > 0.0
    assert after.ap50["chair"] == before.ap50["chair"] == 1.0

    back = read_benchmark_predictions(write_benchmark_predictions(tmp_path, "s", with_union), len(vertices))
    assert back.alternative.tolist() == with_union.alternative.tolist()
    assert back.num_instances == 4 and back.primary().num_predictions == 4


def test_a_piece_fused_as_another_class_joins_under_its_class_hypothesis(tmp_path):
    """The sofa's right arm fused as a chair (sofa its second class, at 0.35): its sofa line and the left piece make
    the sofa; two alternative lines are not joined."""
    vertices, faces, column, ids = sofa_scene()
    left, right = vertices[column <= 6], vertices[(column >= 7) & (column <= 13)]
    instances = [
        instance(0, "sofa", left, 0.9),
        instance(1, "chair", right, 0.7, second="sofa"),
        instance(2, "chair", vertices[column >= 16], 0.8),
    ]
    kwargs = dict(label_sets=LABELS, vertices=vertices, radius=0.03, faces=faces, alternative_class_probability=0.1)
    preds = benchmark_predictions(instances, union_confidence_factor=0.25, **kwargs)
    sofa = LABELS.nyu40_ids[LABELS.class_index("sofa")]
    assert preds.num_instances == 3 and preds.num_predictions == 5  # 3 instances, 1's sofa line, their sofa union
    assert preds.nyu40_ids[3] == preds.nyu40_ids[4] == sofa
    assert np.array_equal(preds.masks[4], preds.masks[0] | preds.masks[1])
    assert preds.confidences[4] == pytest.approx(0.25 * min(preds.confidences[0], preds.confidences[3]))
    without = benchmark_predictions(instances, union_confidence_factor=0.0, **kwargs)
    assert evaluate_scenes([(ids, without)]).ap50["sofa"] == 0.0
    assert evaluate_scenes([(ids, preds)]).ap50["sofa"] > 0.0
    back = read_benchmark_predictions(write_benchmark_predictions(tmp_path, "s", preds), len(vertices))
    assert back.alternative.tolist() == preds.alternative.tolist() == [False] * 3 + [True, True]


def test_only_a_union_of_two_earlier_instances_of_its_class_reads_back_as_a_hypothesis(tmp_path):
    masks = np.zeros((6, 12), bool)
    masks[0, :3] = masks[1, 3:6] = masks[2, 6:9] = True  # instances: classes 3, 3, 4
    masks[3, :6] = True  # the union of 0 and 1, class 3: a hypothesis
    masks[4, 3:9] = True  # the union of 1 (class 3) and 2 (class 4) under class 4: an instance
    masks[5, :3] = True  # 0's mask again under its own class: another instance
    preds = InstancePredictions(masks, [3, 3, 4, 3, 4, 3], [0.9, 0.8, 0.7, 0.4, 0.3, 0.2])
    back = read_benchmark_predictions(write_benchmark_predictions(tmp_path, "s", preds))
    assert back.alternative.tolist() == [False, False, False, True, False, False]
    # with 1 also under class 4 (its class hypothesis) before it, the same line is the union of 1 and 2 under 4
    masks = np.concatenate([masks[:3], masks[1:2], masks[4:5]])
    preds = InstancePredictions(masks, [3, 3, 4, 4, 4], [0.9, 0.8, 0.7, 0.3, 0.1])
    back = read_benchmark_predictions(write_benchmark_predictions(tmp_path / "b", "s", preds))
    assert back.alternative.tolist() == [False, False, False, True, True]
