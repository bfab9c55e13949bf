"""The noise zoo: each failure mode beyond the paper's does what its parameter claims on a small drawn
room, `clean`/`default` frames are those of the original simulator, and the zoo is deterministic."""

from __future__ import annotations

import dataclasses
import hashlib
import json

import numpy as np
import pytest

from fmfusion_jax.apps.simulate import parse_overrides
from fmfusion_jax.cli import simulate as cli_simulate
from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import load_label_sets, load_likelihood
from fmfusion_jax.simulation import noise as noise_module
from fmfusion_jax.simulation.noise import FAMILIES, FAMILY_DOSES, NoiseModel, bleed_kernel, family_noise, mask_box
from fmfusion_jax.simulation.sim_false_positives import BLOB_LABELS
from fmfusion_jax.simulation.sim_labels import (
    CONFUSER_CLASSES,
    EXTRA_CONFUSIONS,
    _LabelModel,
    consistent_mislabels,
    perturb_likelihood,
    wrong_labels,
)
from fmfusion_jax.simulation.simulate import simulate_frame
from fmfusion_jax.simulation.zoo import MIXED, noise_zoo

LABELS = load_label_sets()
LIKELIHOOD = load_likelihood("statistical")
COLUMNS = LIKELIHOOD / LIKELIHOOD.sum(axis=0, keepdims=True)
C = LABELS.class_index
ROW_CLASS = COLUMNS.argmax(axis=1)  # the class the published matrix ascribes each open label to

#: The parameters this module is about: zero (off) in `clean` and `default`.
NEW_PARAMS = (
    "likelihood_perturbation",
    "extra_confusion_prob",
    "consistent_mislabel_prob",
    "score_miscalibration",
    "partial_large_prob",
    "partial_straight_share",
    "partial_occluder_share",
    "merge_neighbor_prob",
    "bleed_prob",
    "bleed_px",
    "erode_prob",
    "erode_px",
    "confuser_prob",
    "blob_rate",
    "persistent_phantoms",
    "persistent_radius_m",
    "persistent_detect_prob",
    "background_rate",
    "background_strip_share",
    "texture_prob",
)

WALL, FLOOR, TABLE, CHAIR, PICTURE, BOX, LAMP = 1, 2, 3, 4, 5, 8, 9


def room() -> tuple[np.ndarray, dict[int, int]]:
    """120x160: wall over floor, a large table with a chair beside it and a box (no class) below it, a
    picture and a lamp (no class) on the wall."""
    image = np.zeros((120, 160), np.int32)
    image[:60, :] = WALL
    image[60:, :] = FLOOR
    image[45:95, 20:90] = TABLE  # 3500 px
    image[55:100, 90:115] = CHAIR  # 1125 px, touching the table
    image[10:30, 30:60] = PICTURE  # 600 px
    image[95:110, 30:70] = BOX  # 600 px, touching the table from below
    image[15:55, 120:140] = LAMP  # 800 px
    classes = {WALL: C("wall"), FLOOR: C("floor"), TABLE: C("table"), CHAIR: C("chair"), PICTURE: C("picture")}
    return image, classes


def quiet(**changes) -> NoiseModel:
    """`clean` (ground-truth masks, every label tagged) with some failure modes switched on."""
    return NoiseModel.preset("clean", **changes)


def simulate(image, classes, noise, frame_index=0, recent=()):
    return simulate_frame(image, classes, f"frame-{frame_index:06d}", frame_index, noise, LABELS, LIKELIHOOD, recent)


def check_thresholds(detections, noise: NoiseModel) -> None:
    """What every simulated frame must satisfy: the detector's thresholds, prompt labels, disjoint masks."""
    if detections.num_detections:
        assert detections.masks.sum(axis=0).max() <= 1
        assert (detections.masks.sum(axis=(1, 2)) >= noise.min_mask_pixels).all()
    for k, labels in enumerate(detections.labels):
        assert 1 <= len(labels) <= noise.max_labels
        assert set(labels) <= set(detections.prompt)
        assert max(labels.values()) >= noise.box_threshold
        assert min(labels.values()) >= noise.text_threshold
        np.testing.assert_array_equal(detections.boxes[k], mask_box(detections.masks[k]))


def covering(detections, image, instance):
    """Index of the detection holding most of `instance`'s pixels, or None."""
    overlap = detections.masks[:, image == instance].sum(axis=1) if detections.num_detections else np.zeros(0)
    return int(overlap.argmax()) if overlap.size and overlap.max() > 0 else None


def main_label(labels: dict[str, float]) -> str:
    return max(labels, key=labels.get)


# --- presets, validation, zoo -------------------------------------------------------------------------


def test_new_parameters_are_off_in_clean_and_default():
    for preset in ("clean", "default"):
        noise = NoiseModel.preset(preset)
        assert all(getattr(noise, name) == 0 for name in NEW_PARAMS), preset
    assert NoiseModel().large_object_pixels > 0


def test_clean_and_default_frames_are_the_original_simulators():
    # sha256 of these frames made by the simulator before the new failure modes (commit acf7b8e), with
    # this numpy and OpenCV; explicit zeros for every new parameter give the same frames.
    pinned = {
        "clean": "3db9cd08c57c226c6c4d1230e986e693805e4f7038991acfe142775f219d0627",
        "default": "56862b53d4caef55c0d306b4175c385fac091388e6f38dfae4742a4fd80a521d",
    }
    image, classes = room()
    for preset, expected in pinned.items():
        for noise in (NoiseModel.preset(preset), NoiseModel.preset(preset, **{name: 0.0 for name in NEW_PARAMS})):
            digest = hashlib.sha256()
            for seed in (0, 1):
                for f in range(6):
                    d = simulate(image, classes, noise.replace(seed=seed), f, ("table",))
                    digest.update(np.packbits(d.masks).tobytes())
                    digest.update(json.dumps([d.labels, d.tags, d.prompt]).encode())
            assert digest.hexdigest() == expected, preset


def test_validation_of_the_new_parameters():
    with pytest.raises(UserError, match="must be a probability"):
        NoiseModel(confuser_prob=1.5)
    with pytest.raises(UserError, match="must be >= 0"):
        NoiseModel(blob_rate=-1.0)
    with pytest.raises(UserError, match="needs bleed_px"):
        NoiseModel(bleed_prob=0.5)
    with pytest.raises(UserError, match="must be <= 1"):
        NoiseModel(partial_straight_share=0.7, partial_occluder_share=0.5)
    with pytest.raises(UserError, match="must be <= 1"):
        NoiseModel(bleed_prob=0.8, bleed_px=3.0, erode_prob=0.3, erode_px=2.0)
    with pytest.raises(UserError, match="must be a int"):
        NoiseModel(large_object_pixels=1.5)


def test_family_presets_and_cli_choices():
    assert cli_simulate.PRESETS == noise_module.PRESETS
    assert FAMILIES == ("default", *noise_module.FAMILY_PRESETS)
    for family in noise_module.FAMILY_PRESETS:
        assert NoiseModel.preset(family) == family_noise(family)
        assert NoiseModel.preset(family, seed=4).seed == 4
    border = NoiseModel.preset("border", seed=2, bleed_px=4.0)
    assert (border.bleed_px, border.bleed_prob, border.seed) == (4.0, FAMILY_DOSES["border"]["bleed_prob"], 2)
    with pytest.raises(UserError, match="unknown noise preset"):
        NoiseModel.preset("noisy")


def test_cli_accepts_family_presets_and_their_parameters():
    from fmfusion_jax.cli import build_parser

    args = build_parser().parse_args(
        ["simulate", "scene", "--out", "sim", "--noise-preset", "border", "--set", "bleed_px=8", "--set", "erode_prob=0.1"]
    )
    noise = NoiseModel.preset(args.noise_preset, **parse_overrides(args.set))
    assert (noise.bleed_px, noise.erode_prob, noise.bleed_prob) == (8, 0.1, FAMILY_DOSES["border"]["bleed_prob"])


def test_zoo_is_deterministic_and_each_family_changes_its_parameters():
    zoo = noise_zoo(mixed=3, seed=5)
    assert zoo == noise_zoo(mixed=3, seed=5)
    assert zoo != noise_zoo(mixed=3, seed=6)
    assert [e.name for e in zoo] == [*FAMILIES, f"{MIXED}-1", f"{MIXED}-2", f"{MIXED}-3"]
    default = dataclasses.asdict(NoiseModel(seed=5))
    for entry in zoo[: len(FAMILIES)]:
        changed = {k for k, v in dataclasses.asdict(entry.noise).items() if v != default[k]}
        assert changed == set(FAMILY_DOSES[entry.family]), entry.family
        assert all(entry.noise.to_dict()[k] == pytest.approx(v) for k, v in FAMILY_DOSES[entry.family].items())
    covered = {name for dose in FAMILY_DOSES.values() for name in dose}
    assert set(NEW_PARAMS) - {"large_object_pixels"} <= covered
    for entry in zoo[len(FAMILIES) :]:
        assert entry.family == MIXED and entry.noise.to_dict() != default
    # Severity scales the dose from default (0) through the dose (1); probabilities stay valid beyond.
    assert family_noise("border", 0.0) == NoiseModel()
    assert family_noise("merged", 0.5).merge_neighbor_prob == pytest.approx(0.15)
    strong = family_noise("partial", 4.0)
    assert strong.partial_large_prob == 1.0 and strong.partial_prob + strong.split_prob <= 1.0


def test_every_zoo_entry_respects_the_detector_thresholds():
    image, classes = room()
    for entry in noise_zoo(mixed=2, seed=1):
        recent = ()
        for f in range(6):
            d = simulate(image, classes, entry.noise, f, recent)
            check_thresholds(d, entry.noise)
            recent = [name for labels in d.labels for name in labels]


# --- labels ---------------------------------------------------------------------------------------------


def test_likelihood_perturbation_makes_one_detector_per_seed():
    perturbed = perturb_likelihood(COLUMNS, 0.7, seed=3)
    np.testing.assert_allclose(perturbed.sum(axis=0), 1.0)
    np.testing.assert_array_equal(perturbed, perturb_likelihood(COLUMNS, 0.7, seed=3))
    assert not np.allclose(perturbed, perturb_likelihood(COLUMNS, 0.7, seed=4))
    assert ((COLUMNS == 0) & (perturbed > 0)).sum(axis=0).min() >= 1, "each column gains labels it lacked"
    # Main labels follow the detector's (perturbed) column, far from the published one (chi-square).
    chair, n = C("chair"), 4000

    def chi2(counts, column):
        expected = n * column
        return float((((counts - expected)[expected > 0]) ** 2 / expected[expected > 0]).sum())

    for sigma in (0.0, 0.7):
        noise = NoiseModel(likelihood_perturbation=sigma, label_persistence=0.0, seed=3)
        model = _LabelModel(noise, LABELS, LIKELIHOOD)
        rng = np.random.default_rng(0)
        counts = np.zeros(len(LABELS.open_labels))
        for _ in range(n):
            counts[LABELS.open_labels.index(next(iter(model.draw(rng, chair, 1))))] += 1
        assert chi2(counts, model.columns[:, chair]) < 60  # 37 degrees of freedom at most
        assert (chi2(counts, COLUMNS[:, chair]) > 200) == (sigma > 0)


def test_extra_confusion_gives_the_partner_label_at_its_rate():
    index = {name: i for i, name in enumerate(LABELS.open_labels)}
    for class_name, partners in EXTRA_CONFUSIONS.items():
        for name in partners:
            assert COLUMNS[index[name], C(class_name)] < 0.03, (class_name, name)  # the matrix lacks them
    image = np.zeros((40, 60), np.int32)
    image[5:35, 5:55] = 7
    noise = quiet(extra_confusion_prob=0.25)
    mains = [main_label(simulate(image, {7: C("table")}, noise, f).labels[0]) for f in range(400)]
    share = np.mean([m in EXTRA_CONFUSIONS["table"] for m in mains])
    assert abs(share - 0.25) < 0.06
    assert set(mains) <= {*EXTRA_CONFUSIONS["table"], LABELS.open_labels[int(COLUMNS[:, C("table")].argmax())]}


def test_consistent_mislabel_is_one_wrong_label_in_every_view_and_instance():
    image = np.zeros((60, 120), np.int32)
    image[10:50, 5:50] = 4
    image[10:50, 60:110] = 6  # a second chair
    classes = {4: C("chair"), 6: C("chair")}
    # Tag misses off: a missed tag makes the detector relabel (another failure mode).
    noise = NoiseModel(
        consistent_mislabel_prob=1.0,
        seed=2,
        missed_tag_prob=0.0,
        miss_prob=0.0,
        small_object_miss_prob=0.0,
        partial_prob=0.0,
        split_prob=0.0,
        merge_prob=0.0,
        false_positive_rate=0.0,
    )
    mains = {main_label(labels) for f in range(10) for labels in simulate(image, classes, noise, f).labels}
    assert len(mains) == 1
    assert ROW_CLASS[LABELS.open_labels.index(mains.pop())] != C("chair")
    # Per seed and class with the stated probability, and always a label the matrix ascribes elsewhere.
    wrong = wrong_labels(COLUMNS)
    hits = 0
    for seed in range(40):
        chosen = consistent_mislabels(COLUMNS, 0.3, seed, {})
        assert all(wrong[label, c] for c, label in chosen.items())
        hits += len(chosen)
    assert abs(hits / (40 * LABELS.num_classes) - 0.3) < 0.06


def test_score_miscalibration_decorrelates_scores_from_correctness():
    image, classes = room()

    def score_gap(miscalibration: float) -> float:
        # Wrong labels here come from relabels and false detections only, which score low when calibrated.
        noise = NoiseModel(
            score_miscalibration=miscalibration,
            label_confusion=0.0,
            missed_tag_prob=0.5,
            relabel_prob=1.0,
            false_positive_rate=2.0,
            seed=1,
        )
        right, wrong = [], []
        for f in range(150):
            d = simulate(image, classes, noise, f)
            for mask, labels in zip(d.masks, d.labels):
                ids, counts = np.unique(image[mask], return_counts=True)
                instance = int(ids[counts.argmax()])
                label = main_label(labels)
                correct = instance in classes and ROW_CLASS[LABELS.open_labels.index(label)] == classes[instance]
                (right if correct else wrong).append(labels[label])
        return float(np.mean(right) - np.mean(wrong))

    calibrated, miscalibrated = score_gap(0.0), score_gap(1.0)
    assert calibrated > 0.045
    assert abs(miscalibrated) < 0.25 * calibrated


# --- masks ----------------------------------------------------------------------------------------------


def test_bleed_kernel_spreads_mostly_downwards():
    kernel, (ax, ay) = bleed_kernel(4.0)
    rows = np.flatnonzero(kernel.any(axis=1))
    below, above = ay - rows.min(), rows.max() - ay  # kernel rows above the anchor spread downwards
    assert below == 8 and above == 2 and kernel.shape[1] == 2 * 4 + 1


def test_bleed_adds_only_background_pixels_mostly_below():
    image, classes = room()
    noise = quiet(bleed_prob=1.0, bleed_px=5.0)
    background = np.isin(image, [0, WALL, FLOOR, BOX, LAMP])
    below = above = 0
    for f in range(5):
        d = simulate(image, classes, noise, f)
        for instance in (TABLE, CHAIR, PICTURE):
            mask = d.masks[covering(d, image, instance)]
            added = mask & (image != instance)
            assert added.any() and background[added].all(), "bleeds onto wall, floor and clutter only"
            rows = np.flatnonzero((image == instance).any(axis=1))
            below += added[rows.max() + 1 :].sum()
            above += added[: rows.min()].sum()
        for surface in (WALL, FLOOR):
            assert not (d.masks[covering(d, image, surface)] & (image != surface)).any(), "walls do not bleed"
    assert below > 2 * above


def test_erode_shrinks_masks():
    image, classes = room()
    d = simulate(image, classes, quiet(erode_prob=1.0, erode_px=3.0), 0)
    for instance in (TABLE, CHAIR, PICTURE):
        mask = d.masks[covering(d, image, instance)]
        gt = image == instance
        assert not (mask & ~gt).any() and 0.4 * gt.sum() < mask.sum() < 0.9 * gt.sum()


def assert_straight_axis_aligned_cut(kept: np.ndarray, whole: np.ndarray) -> None:
    """The kept pixels next to the removed ones lie on a line within 1 px, within 35 degrees of an axis."""
    removed = whole & ~kept
    edge = kept & (np.roll(removed, 1, 0) | np.roll(removed, -1, 0) | np.roll(removed, 1, 1) | np.roll(removed, -1, 1))
    points = np.argwhere(edge).astype(float)
    points -= points.mean(axis=0)
    _, spread, axes = np.linalg.svd(points, full_matrices=False)
    assert spread[1] / np.sqrt(len(points)) < 1.0, "straight"
    assert min(abs(axes[0][0]), abs(axes[0][1])) < np.sin(np.radians(35)), "near horizontal or vertical"


@pytest.mark.parametrize("style", ["wavy", "straight", "occluder"])
def test_partial_large_cuts_only_large_objects(style):
    image, classes = room()
    shares = {"wavy": {}, "straight": {"partial_straight_share": 1.0}, "occluder": {"partial_occluder_share": 1.0}}[style]
    noise = quiet(partial_large_prob=1.0, large_object_pixels=3000, **shares)
    for f in range(8):
        d = simulate(image, classes, noise, f)
        table = d.masks[covering(d, image, TABLE)]
        kept = table.sum() / (image == TABLE).sum()
        assert not (table & (image != TABLE)).any() and 0.29 <= kept <= 0.81, kept
        if style == "straight":
            assert_straight_axis_aligned_cut(table, image == TABLE)
        for small in (CHAIR, PICTURE):
            np.testing.assert_array_equal(d.masks[covering(d, image, small)], image == small)


def test_merge_neighbor_absorbs_any_touching_neighbour_but_wall_and_floor():
    image, classes = room()
    noise = quiet(merge_neighbor_prob=1.0)
    pairs = set()
    for f in range(12):
        d = simulate(image, classes, noise, f)
        for mask, labels in zip(d.masks, d.labels):
            ids = {int(i) for i in np.unique(image[mask])}
            if ids in ({WALL}, {FLOOR}):
                continue
            assert not ids & {WALL, FLOOR}, "never a wall or floor in an object's mask"
            if len(ids) == 2:
                pairs.add(tuple(sorted(ids)))
                # The absorbing table keeps its label; the absorbed neighbour is whole.
                assert TABLE in ids and main_label(labels) == LABELS.open_labels[int(COLUMNS[:, C("table")].argmax())]
                assert all((mask[image == i]).all() for i in ids)
    assert pairs == {(TABLE, CHAIR), (TABLE, BOX)}, "a target and a non-target neighbour both occur"


# --- detections -----------------------------------------------------------------------------------------


def test_confusers_are_detected_with_a_fixed_label_and_a_normal_score():
    image, classes = room()
    noise = quiet(confuser_prob=1.0, score_std=0.07)
    allowed = {LABELS.open_labels[i] for c in CONFUSER_CLASSES for i in np.flatnonzero(COLUMNS[:, C(c)] > 0)}
    seen: dict[int, set[str]] = {BOX: set(), LAMP: set()}
    scores = []
    for f in range(10):
        d = simulate(image, classes, noise, f)
        check_thresholds(d, noise)
        for instance in seen:
            k = covering(d, image, instance)
            assert k is not None and not (d.masks[k] & (image != instance)).any()
            seen[instance].add(main_label(d.labels[k]))
            scores.append(max(d.labels[k].values()))
    assert all(len(labels) == 1 and labels <= allowed for labels in seen.values())
    assert np.mean(scores) > 0.44 and min(scores) >= noise.box_threshold
    assert simulate(image, classes, quiet(), 0).num_detections == 5  # off: targets only


def test_blobs_lie_on_walls_and_floors_with_surface_labels():
    image, classes = room()
    noise = quiet(blob_rate=3.0, score_std=0.07)
    blobs = 0
    for f in range(20):
        d = simulate(image, classes, noise, f)
        check_thresholds(d, noise)
        for mask, labels in zip(d.masks, d.labels):
            ids = set(np.unique(image[mask]).tolist())
            label = main_label(labels)
            if len(ids) == 1 and ids <= {WALL, FLOOR} and label in BLOB_LABELS["wall"] + BLOB_LABELS["floor"]:
                surface = "wall" if ids == {WALL} else "floor"
                assert label in BLOB_LABELS[surface]
                blobs += 1
            else:
                assert len(ids) == 1, "targets keep their ground-truth masks"
    assert 30 < blobs < 80
