import dataclasses

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from fmfusion_jax.config import ExportConfig
from fmfusion_jax.instances import (
    MapInstance,
    detector_hit_rate,
    drop_far_specks,
    existence_probability,
    expected_structure_share,
    postprocess_instances,
    score_existence,
    structure_label_votes,
    thickness,
)
from fmfusion_jax.labels import load_label_sets, load_likelihood

LABELS = load_label_sets()


def make_instance(instance_id, class_name, centre, n_points=300):
    distribution = np.full(LABELS.num_classes, 0.01)
    distribution[LABELS.class_index(class_name)] = 1.0
    points = np.asarray(centre, np.float32) + np.random.default_rng(instance_id).normal(0, 0.05, (n_points, 3))
    return MapInstance(instance_id, distribution / distribution.sum(), points.astype(np.float32), 3, np.zeros(LABELS.num_open))


def test_postprocessing_rules():
    instances = [
        make_instance(0, "toilet", [0, 0, 0]),
        make_instance(1, "curtain", [1, 0, 0]),  # near the toilet: becomes a shower curtain
        make_instance(2, "curtain", [5, 0, 0]),  # far: stays a curtain
        make_instance(3, "floor", [0, 0, -1]),
        make_instance(4, "floor", [3, 0, -1], n_points=500),
        make_instance(5, "chair", [2, 2, 0], n_points=50),  # too small
        make_instance(6, "shower curtain", [0, 1, 0]),  # near the toilet: stays
        make_instance(7, "shower curtain", [0, 6, 0]),  # far: a curtain (by context)
    ]
    export = ExportConfig(min_points=200, shower_curtain_radius=2.0)
    out = postprocess_instances(instances, LABELS, export)
    classes = {inst.instance_id: LABELS.class_names[inst.class_index] for inst in out}
    assert classes == {0: "toilet", 1: "shower curtain", 2: "curtain", 4: "floor", 6: "shower curtain", 7: "curtain"}
    reference = postprocess_instances(instances, LABELS, export.model_copy(update={"curtain_by_context": False}))
    assert {inst.instance_id: LABELS.class_names[inst.class_index] for inst in reference}[7] == "shower curtain"
    floor = next(inst for inst in out if inst.instance_id == 4)
    assert len(floor.points) == 800
    for inst in out:
        assert np.isclose(inst.distribution.sum(), 1.0)


def test_a_room_without_toilet_or_bathtub_has_no_shower_curtain():
    instances = [make_instance(0, "shower curtain", [0, 0, 0]), make_instance(1, "curtain", [3, 0, 0])]
    out = postprocess_instances(instances, LABELS, ExportConfig(min_points=200))
    assert [LABELS.class_names[inst.class_index] for inst in out] == ["curtain", "curtain"]


def test_floor_claims_its_vertices_in_the_benchmark_transfer():
    """Floor vertices around a table's lowest points go to the floor (then dropped) when the structure takes
    part in the transfer; without it the table takes them."""
    from fmfusion_jax.io.map_outputs import benchmark_predictions

    label_sets = load_label_sets()
    grid = np.stack(np.meshgrid(np.arange(0, 1, 0.02), np.arange(0, 1, 0.02), [0.0]), -1).reshape(-1, 3)
    table_points = grid[(grid[:, 0] > 0.4) & (grid[:, 0] < 0.6)] + [0, 0, 0.05]
    floor = MapInstance(0, np.eye(20)[label_sets.class_index("floor")], grid, 5, np.zeros(38))
    table = MapInstance(1, np.eye(20)[label_sets.class_index("table")], table_points, 5, np.zeros(38))
    vertices = grid  # the floor of the mesh
    plain = benchmark_predictions([floor, table], label_sets, vertices, 0.08)
    claimed = benchmark_predictions([floor, table], label_sets, vertices, 0.08, structure_claims_vertices=True)
    assert plain.num_instances == claimed.num_instances == 1
    assert plain.masks[0].sum() >= 0.25 * len(vertices)
    assert claimed.masks[0].sum() == 0


# ---------------------------------------------------------------------------------------------------
# The existence model.


def weighted_median_oracle(rates, weights):
    """The smallest rate at which at least half of the weight lies at or below it."""
    pairs = sorted(zip(rates, weights))
    total, running = sum(weights), 0.0
    for rate, weight in pairs:
        running += weight
        if running >= total / 2:
            return rate
    raise AssertionError


@given(st.lists(st.tuples(st.integers(0, 60), st.integers(0, 60)), min_size=1, max_size=30))
@settings(max_examples=60, deadline=None)
def test_detector_hit_rate_is_the_observation_weighted_median_of_the_sure_instances(counts):
    obs = np.array([c[0] for c in counts])
    missed = np.array([c[1] for c in counts])
    rate = detector_hit_rate(obs, missed, min_observations=5)
    sure = [(o / (o + m), o) for o, m in counts if o >= 5]
    if not sure:
        assert rate is None
    else:
        assert rate == weighted_median_oracle(*zip(*sure))


@given(st.integers(0, 80), st.integers(0, 80), st.floats(0.05, 1.0), st.floats(0.5, 10.0))
@example(1, 0, 0.9999999999999999, 4.25)  # the rate a hair under 1 (CI, 2026-12-06): equal to rounding only
@settings(max_examples=80, deadline=None)
def test_existence_falls_with_missed_frames_and_rises_with_detections(obs, missed, rate, prior):
    e = existence_probability(obs, missed, rate, 3.0, prior)
    assert 0.0 <= e <= 1.0
    assert existence_probability(obs, missed + 1, rate, 3.0, prior) <= e  # seen, not detected: less evidence
    assert existence_probability(obs + 1, missed, rate, 3.0, prior) >= e
    # at or above the detector's own rate only the repeated support counts (to rounding: at a rate of 1 - 1e-16 the
    # posterior over the rate may come out a hair under 1)
    assert existence_probability(obs, 0, rate, 3.0, prior) == pytest.approx(1.0 - np.exp(-obs / 3.0), rel=1e-12, abs=0.0)


def test_a_patch_seen_often_but_rarely_detected_loses_to_an_object_of_the_same_detector():
    # a poor detector (finds objects in a third of the frames that show them): its objects are not penalized
    obs = np.array([10, 12, 9, 3])
    missed = np.array([20, 25, 17, 40])
    rate = detector_hit_rate(obs, missed)
    assert 0.3 < rate < 0.4
    objects = [existence_probability(o, m, rate, 3.0, 4.0) for o, m in zip(obs[:3], missed[:3])]
    phantom = existence_probability(obs[3], missed[3], rate, 3.0, 4.0)
    assert min(objects) > 0.9 and phantom < 0.3


def test_thickness_of_a_plane_and_of_a_box():
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(0, 1, (500, 2)), np.zeros(500)] @ np.linalg.qr(rng.normal(size=(3, 3)))[0]
    box = rng.uniform(0, [1.0, 0.6, 0.4], (500, 3))
    assert thickness(plane) < 1e-6
    assert abs(thickness(box) - 0.4 / np.sqrt(12)) < 0.02  # uniform: std = width / sqrt(12)
    assert thickness(box[:2]) == 0.0


def test_sheets_of_volumetric_classes_have_no_existence_and_are_not_exported():
    rng = np.random.default_rng(1)
    sheet = np.c_[rng.uniform(0, 1, (400, 2)), np.full(400, 2.0)].astype(np.float32)  # one voxel layer
    solid = rng.uniform(0, 0.5, (400, 3)).astype(np.float32)

    def instance(k, name, points):
        return dataclasses.replace(make_instance(k, name, [0, 0, 0], 400), points=points, observations=20, missed=2)

    instances = [
        instance(0, "cabinet", sheet),
        instance(1, "door", sheet),
        instance(2, "cabinet", solid),
        instance(3, "wall", sheet),
    ]
    export = ExportConfig(min_points=200)
    scored = {i.instance_id: i.existence for i in score_existence(instances, LABELS, export, voxel_size=0.02)}
    assert scored[1] > 0.9 and scored[2] > 0.9 and scored[0] == 0.5 * scored[2]  # a sheet's evidence is halved
    weak = [dataclasses.replace(i, missed=60) if i.instance_id == 0 else i for i in instances]
    kept = {i.instance_id for i in postprocess_instances(score_existence(weak, LABELS, export, 0.02), LABELS, export)}
    assert kept == {1, 2, 3}  # a weak sheet is not exported; the wall stays: structure is never ranked or dropped
    veto = export.model_copy(update={"sheet_factor": 0.0})
    assert {i.instance_id: i.existence for i in score_existence(instances, LABELS, veto, 0.02)}[0] == 0.0
    off = export.model_copy(update={"planar_thickness": 0.0, "min_existence": 0.0})
    assert len(postprocess_instances(score_existence(instances, LABELS, off, 0.02), LABELS, off)) == 4


def specks_oracle(points, voxel_size, max_distance):
    """Brute force: pieces by flood fill over 26-neighbouring two-voxel cells; keep the largest piece and the
    pieces with a point within max_distance of it."""
    cells = [tuple(c) for c in np.floor((points - points.min(axis=0)) / (2 * voxel_size)).astype(int)]
    occupied, piece_of = set(cells), {}
    for start in occupied:
        if start in piece_of:
            continue
        piece_of[start], stack = start, [start]
        while stack:
            c = stack.pop()
            for d in np.ndindex(3, 3, 3):
                n = (c[0] + d[0] - 1, c[1] + d[1] - 1, c[2] + d[2] - 1)
                if n in occupied and n not in piece_of:
                    piece_of[n] = start
                    stack.append(n)
    piece = np.array([hash(piece_of[c]) for c in cells])
    names, counts = np.unique(piece, return_counts=True)
    if len(counts) > 1 and np.sort(counts)[-2] == counts.max():
        return None  # two largest pieces: either may be the body
    if counts.max() < 0.3 * len(points):
        return points  # no body
    body = piece == names[np.argmax(counts)]
    keep = body.copy()
    for name in names:
        member = piece == name
        gaps = np.linalg.norm(points[member][:, None] - points[body][None], axis=-1)
        keep |= member & (gaps.min() <= max_distance)
    return points[keep]


def test_far_specks_are_dropped_and_near_parts_kept():
    voxel = 0.02
    grid = np.stack(np.meshgrid(*(np.arange(10),) * 3, indexing="ij"), -1).reshape(-1, 3)
    body = (grid + 0.5) * voxel  # a 20 cm cube
    near = body[:50] + [0.3, 0, 0]  # 10 cm beyond the cube's face: a leg seen apart from the seat
    far = body[:30] + [1.0, 1.0, 0]  # a speck a metre away
    points = np.concatenate([body, near, far]).astype(np.float32)
    kept = drop_far_specks(points, voxel, 0.2)
    assert len(kept) == len(body) + len(near)
    assert np.array_equal(drop_far_specks(points, voxel, 0.0), points)
    # no body: five pieces of one voxel each, a metre apart, are kept whole
    scattered = (np.arange(5)[:, None] * [1.0, 0, 0] + 0.5 * voxel).astype(np.float32)
    assert len(drop_far_specks(scattered, voxel, 0.2)) == 5


@given(st.integers(0, 2**31 - 1), st.floats(0.05, 0.5))
@settings(max_examples=25, deadline=None)
def test_far_specks_match_the_flood_fill_oracle(seed, max_distance):
    rng = np.random.default_rng(seed)
    voxel = 0.02
    clusters = [
        rng.integers(0, 60, 3) + rng.integers(0, 4, (int(rng.integers(1, 40)), 3)) for _ in range(int(rng.integers(1, 5)))
    ]
    g = np.unique(np.concatenate(clusters), axis=0)
    points = ((g + 0.5) * voxel).astype(np.float64)
    kept = drop_far_specks(points, voxel, max_distance)
    expected = specks_oracle(points, voxel, max_distance)
    assume(expected is not None)
    assert sorted(map(tuple, kept)) == sorted(map(tuple, expected))


def test_the_curtain_context_leaves_no_twin_class_to_offer_as_an_alternative():
    """The likelihood weighs the label 'curtain' alike under curtain and shower curtain; once the context decides,
    the other keeps no mass, whichever of the two the instance had: else the benchmark files would offer every
    curtain as a shower curtain of the same weight (and the reverse by a toilet)."""
    from fmfusion_jax.io.map_outputs import alternative_class_hypotheses

    curtain, shower = LABELS.class_index("curtain"), LABELS.class_index("shower curtain")

    def twin(instance_id, top, other, centre):
        inst = make_instance(instance_id, "curtain", centre)
        distribution = np.full(LABELS.num_classes, 0.01)
        distribution[top], distribution[other] = 0.41, 0.39
        return dataclasses.replace(inst, distribution=distribution / distribution.sum())

    instances = [make_instance(0, "toilet", [0, 0, 0]), twin(1, shower, curtain, [1, 0, 0]), twin(2, curtain, shower, [6, 0, 0])]
    out = {inst.instance_id: inst for inst in postprocess_instances(instances, LABELS, ExportConfig(min_points=200))}
    assert out[1].class_index == shower and out[1].distribution[curtain] == 0.0
    assert out[2].class_index == curtain and out[2].distribution[shower] == 0.0
    rows, classes, _ = alternative_class_hypotheses([out[1], out[2]], LABELS, 0.1)
    assert not set(classes.tolist()) & {curtain, shower}
    # the reference's rule (one way) leaves them as they were
    reference = postprocess_instances(instances, LABELS, ExportConfig(min_points=200, curtain_by_context=False))
    assert {inst.instance_id: inst for inst in reference}[2].distribution[shower] > 0.3


def structure_label_share(hist, likelihood, structure):
    """The votes of `structure_label_votes`, checked to be non-negative shares, summed."""
    votes = structure_label_votes(hist, likelihood, structure)
    assert votes.shape == (len(structure),) and (votes >= 0).all()
    return float(votes.sum())


def test_structure_label_votes_split_each_label_by_its_likelihood_row():
    likelihood = load_likelihood()
    structure = [LABELS.class_index("wall"), LABELS.class_index("floor")]
    hist = np.zeros(LABELS.num_open)
    hist[LABELS.open_labels.index("wall")] = 8 * 0.5
    hist[LABELS.open_labels.index("closet")] = 2 * 0.5

    def structure_part(name):  # the oracle: the label's row, normalized, summed over wall and floor
        row = likelihood[LABELS.open_labels.index(name)]
        return row[structure].sum() / row.sum()

    expected = (4.0 * structure_part("wall") + 1.0 * structure_part("closet")) / 5.0
    assert abs(structure_label_share(hist, likelihood, structure) - expected) < 1e-9
    assert expected > 0.6  # a patch of wall that "closet" labels now and then would fuse as a door
    door = np.zeros(LABELS.num_open)
    door[LABELS.open_labels.index("door")] = 3.0
    assert structure_label_share(door, likelihood, structure) < 0.15
    assert structure_label_share(np.zeros(LABELS.num_open), likelihood, structure) == 0.0


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(0, 5, allow_subnormal=False), min_size=38, max_size=38), st.floats(0.01, 10))
def test_structure_label_votes_are_shares_and_ignore_the_histogram_scale(values, scale):
    likelihood, structure = load_likelihood(), [0, 1]
    hist = np.asarray(values)
    share = structure_label_share(hist, likelihood, structure)
    assert 0.0 <= share <= 1.0
    assert abs(structure_label_share(scale * hist, likelihood, structure) - share) < 1e-9


def test_existence_falls_with_the_structure_share_of_the_labels():
    wall_labels = np.zeros(LABELS.num_open)
    wall_labels[LABELS.open_labels.index("tile wall")] = 5.0
    door_labels = np.zeros(LABELS.num_open)
    door_labels[LABELS.open_labels.index("door")] = 5.0
    rng = np.random.default_rng(2)
    sheet = np.c_[rng.uniform(0, 1, (400, 2)), np.full(400, 2.0)].astype(np.float32)  # one voxel layer: a surface
    solid = rng.uniform(0, 0.5, (400, 3)).astype(np.float32)
    instances = [
        dataclasses.replace(make_instance(k, "door", [0, 0, 0], 400), points=points, observations=20, open_label_histogram=h)
        for k, (h, points) in enumerate([(wall_labels, sheet), (door_labels, sheet), (wall_labels, solid)])
    ]
    on = ExportConfig(structure_label_factor=2.5)
    off = ExportConfig(structure_label_factor=0.0)
    likelihood = load_likelihood()
    scored_on = [i.existence for i in score_existence(instances, LABELS, on, 0.02, likelihood)]
    scored_off = [i.existence for i in score_existence(instances, LABELS, off, 0.02, likelihood)]
    assert scored_off[0] == scored_off[1] == scored_off[2] > 0.9
    assert scored_on[0] < 0.2 < 0.85 < scored_on[1]  # the wall's patch, not the door, loses its existence
    assert scored_on[2] == scored_off[2]  # an object with volume keeps it, whatever its labels say
    assert scored_on[1] == scored_off[1]  # a surface its labels leave an object keeps its rank (true doors carry wall labels)
    classes = [LABELS.class_names[i.class_index] for i in score_existence(instances, LABELS, on, 0.02, likelihood)]
    assert classes == ["wall", "door", "door"]  # the patch its labels took the existence of is a piece of the wall
    exported = postprocess_instances(score_existence(instances, LABELS, on, 0.02, likelihood), LABELS, on)
    assert [LABELS.class_names[i.class_index] for i in exported] == ["wall", "door", "door"]  # kept, as the wall
    weak = [dataclasses.replace(instances[0], missed=200), *instances[1:]]  # no evidence even without its labels
    assert [LABELS.class_names[i.class_index] for i in score_existence(weak, LABELS, on, 0.02, likelihood)][0] == "door"
    assert [i.existence for i in score_existence(instances, LABELS, on, 0.02)] == scored_off  # no likelihood: not used


def test_expected_structure_share_follows_the_likelihood_columns():
    """The oracle: each class's column normalized, times each label's structure part (its row normalized, wall and
    floor summed)."""
    likelihood = np.array([[0.9, 0.0, 0.1], [0.0, 0.5, 0.5], [0.3, 0.0, 0.3]])  # labels x (wall, door, shelf)
    expected = expected_structure_share(likelihood, [0])
    row_part = np.array([0.9, 0.0, 0.5])  # label 0: 0.9 of its row is wall, label 1: none, label 2: half
    columns = likelihood / likelihood.sum(axis=0)
    np.testing.assert_allclose(expected, columns.T @ row_part)
    assert expected[1] == 0.0  # a door labelled only by a label with no wall in its row
    published = expected_structure_share(load_likelihood(), [LABELS.class_index("wall"), LABELS.class_index("floor")])
    assert ((published >= 0) & (published <= 1)).all()
    assert published[LABELS.class_index("door")] > 2 * published[LABELS.class_index("curtain")]


def test_the_same_wall_labels_leave_a_door_and_take_a_curtain():
    """A door's own detections name the wall now and then: a share that a door shows keeps a door-class surface,
    and makes a curtain-class one a piece of the wall."""
    likelihood = load_likelihood()
    structure = [LABELS.class_index("wall"), LABELS.class_index("floor")]
    hist = np.zeros(LABELS.num_open)
    hist[LABELS.open_labels.index("door")] = 6.0
    hist[LABELS.open_labels.index("tile wall")] = 3.0
    share = structure_label_share(hist, likelihood, structure)
    expected = expected_structure_share(likelihood, structure)
    assert expected[LABELS.class_index("curtain")] + 0.3 < share < expected[LABELS.class_index("door")] + 0.3
    rng = np.random.default_rng(5)
    sheet = np.c_[rng.uniform(0, 1, (400, 2)), np.full(400, 2.0)].astype(np.float32)
    instances = [
        dataclasses.replace(make_instance(k, name, [0, 0, 0], 400), points=sheet, observations=20, open_label_histogram=hist)
        for k, name in enumerate(["door", "curtain"])
    ]
    scored = score_existence(instances, LABELS, ExportConfig(structure_label_factor=2.5), 0.02, likelihood)
    assert [LABELS.class_names[i.class_index] for i in scored] == ["door", "wall"]
