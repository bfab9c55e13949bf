import numpy as np

from fmfusion_jax.config import ExportConfig
from fmfusion_jax.instances import MapInstance, postprocess_instances
from fmfusion_jax.labels import load_label_sets

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
