"""Simulated detections: the clean preset reproduces the ground truth, each failure mode does what its
parameter says, frames are reproducible from the seed, and the files round-trip through the reader."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import load_label_sets, load_likelihood
from fmfusion_jax.simulation.noise import NoiseModel, cut_mask, mask_box, perturb_border
from fmfusion_jax.simulation.simulate import adjacent_pairs, simulate_frame

LABELS = load_label_sets()
LIKELIHOOD = load_likelihood("statistical")
COLUMNS = LIKELIHOOD / LIKELIHOOD.sum(axis=0, keepdims=True)
C = LABELS.class_index


def best_label(class_name: str) -> str:
    return LABELS.open_labels[int(COLUMNS[:, C(class_name)].argmax())]


def room() -> tuple[np.ndarray, dict[int, int]]:
    """120x160 instance image: wall, floor, a table with a chair touching it, a picture, a lamp (no class)."""
    image = np.zeros((120, 160), np.int32)
    image[:70, :] = 1  # wall
    image[70:, :] = 2  # floor
    image[50:95, 20:80] = 3  # table
    image[55:100, 80:110] = 4  # chair, touching the table
    image[10:35, 30:70] = 5  # picture on the wall
    image[20:60, 120:140] = 9  # lamp: not a target class
    classes = {1: C("wall"), 2: C("floor"), 3: C("table"), 4: C("chair"), 5: C("picture")}
    return image, classes


def one_object(class_name: str = "chair", size: int = 40) -> tuple[np.ndarray, dict[int, int]]:
    image = np.zeros((64, 64), np.int32)
    image[10 : 10 + size // 2, 5 : 5 + size] = 7
    return image, {7: C(class_name)}


def simulate(image, classes, noise, frame_index=0, recent=()):
    return simulate_frame(image, classes, f"frame-{frame_index:06d}", frame_index, noise, LABELS, LIKELIHOOD, recent)


def check_invariants(detections, noise: NoiseModel) -> None:
    """What every simulated frame must satisfy, whatever the noise."""
    n = detections.num_detections
    assert detections.masks.dtype == bool
    if n:
        assert detections.masks.sum(axis=0).max() <= 1, "masks must be disjoint"
        assert (detections.masks.sum(axis=(1, 2)) >= noise.min_mask_pixels).all()
    prompt = set(detections.prompt)
    assert set(detections.tags) <= prompt
    assert set(detections.tags) <= set(detections.raw_tags)
    assert set(detections.tags) <= set(LABELS.open_labels)
    for k in range(n):
        labels = detections.labels[k]
        assert 1 <= len(labels) <= noise.max_labels
        assert set(labels) <= prompt, "the detector only outputs prompt labels"
        assert max(labels.values()) >= noise.box_threshold
        assert min(labels.values()) >= noise.text_threshold
        np.testing.assert_array_equal(detections.boxes[k], mask_box(detections.masks[k]))


# --- noise model --------------------------------------------------------------------------------------


def test_presets_and_validation():
    assert NoiseModel.preset("default") == NoiseModel()
    clean = NoiseModel.preset("clean")
    assert clean.missed_tag_prob == clean.split_prob == clean.false_positive_rate == 0
    assert NoiseModel.preset("hard").missed_tag_prob > NoiseModel().missed_tag_prob
    assert NoiseModel.preset("default", seed=3, merge_prob=0.5).merge_prob == 0.5
    with pytest.raises(UserError, match="unknown noise preset"):
        NoiseModel.preset("noisy")
    with pytest.raises(UserError, match="unknown noise parameter"):
        NoiseModel().replace(split_probability=0.1)
    with pytest.raises(UserError, match="probability"):
        NoiseModel(miss_prob=1.5)
    with pytest.raises(UserError, match="must be a float"):
        NoiseModel().replace(miss_prob="abc")
    with pytest.raises(UserError, match="must be a bool"):
        NoiseModel().replace(prompt_augmentation=1)
    assert NoiseModel().replace(miss_prob=0).miss_prob == 0  # an int is a fine float
    with pytest.raises(UserError, match="text_threshold"):
        NoiseModel(text_threshold=0.5, box_threshold=0.35)


def test_cut_mask_partitions_the_mask():
    mask = np.zeros((80, 100), bool)
    mask[10:70, 20:90] = True
    rng = np.random.default_rng(0)
    for fraction in (0.3, 0.5, 0.8):
        first, second = cut_mask(mask, rng, fraction)
        assert not (first & second).any()
        np.testing.assert_array_equal(first | second, mask)
        assert abs(first.sum() / mask.sum() - fraction) < 0.02


def test_perturb_border_identity_and_smoothness():
    mask = np.zeros((100, 100), bool)
    mask[20:80, 30:70] = True
    rng = np.random.default_rng(1)
    np.testing.assert_array_equal(perturb_border(mask, rng, 0.0, 0.0), mask)
    noisy = perturb_border(mask, rng, 2.0, 3.0)
    iou = (noisy & mask).sum() / (noisy | mask).sum()
    assert 0.7 < iou < 1.0
    # The change stays near the border: nothing far inside is lost, nothing far outside is gained.
    assert noisy[35:65, 45:55].all() and not noisy[:5].any()


def test_adjacent_pairs():
    image, _ = room()
    pairs = adjacent_pairs(image)
    assert (3, 4) in pairs and (1, 5) in pairs
    assert (4, 5) not in pairs


# --- clean preset -------------------------------------------------------------------------------------


def test_clean_preset_reproduces_ground_truth():
    image, classes = room()
    noise = NoiseModel.preset("clean")
    detections = simulate(image, classes, noise)
    check_invariants(detections, noise)
    assert detections.num_detections == len(classes)  # every target instance, the lamp is not one
    seen = set()
    for mask, labels in zip(detections.masks, detections.labels):
        (instance,) = np.unique(image[mask])
        seen.add(int(instance))
        np.testing.assert_array_equal(mask, image == instance)
        class_name = LABELS.class_names[classes[int(instance)]]
        assert labels == {best_label(class_name): pytest.approx(noise.score_mean)}
    assert seen == set(classes)
    assert detections.tags == detections.prompt == detections.raw_tags == sorted(detections.tags)


# --- determinism --------------------------------------------------------------------------------------


def test_frames_are_reproducible_from_the_seed():
    image, classes = room()
    noise = NoiseModel.preset("hard", seed=5)
    a = simulate(image, classes, noise, frame_index=12)
    simulate(image, classes, noise, frame_index=11)  # other frames in between change nothing
    b = simulate(image, classes, noise, frame_index=12)
    np.testing.assert_array_equal(a.masks, b.masks)
    assert a.labels == b.labels and a.prompt == b.prompt and a.raw_tags == b.raw_tags
    others = [simulate(image, classes, noise.replace(seed=6), frame_index=12), simulate(image, classes, noise, frame_index=13)]
    for other in others:
        assert other.labels != a.labels or other.masks.shape != a.masks.shape or (other.masks != a.masks).any()


def test_invariants_hold_under_heavy_noise():
    image, classes = room()
    noise = NoiseModel.preset("hard", false_positive_rate=2.0, min_mask_pixels=50)
    for frame in range(40):
        check_invariants(simulate(image, classes, noise, frame, recent={"table", "floor"}), noise)


# --- failure modes ------------------------------------------------------------------------------------


def label_only(**changes) -> NoiseModel:
    """Clean masks and tags; only the given parameters noisy."""
    return NoiseModel.preset("clean", min_mask_pixels=20).replace(**changes)


@pytest.mark.parametrize("class_name", ["chair", "door", "table"])
def test_main_label_frequencies_follow_the_likelihood_column(class_name):
    image, classes = one_object(class_name)
    noise = label_only(label_confusion=1.0)
    draws = 1500
    counts = np.zeros(LABELS.num_open)
    for frame in range(draws):
        (labels,) = simulate(image, classes, noise, frame).labels
        counts[LABELS.open_labels.index(next(iter(labels)))] += 1
    np.testing.assert_allclose(counts / draws, COLUMNS[:, C(class_name)], atol=0.04)


def test_label_persistence_repeats_an_instance_label_across_frames():
    image, classes = one_object("door")
    noise = label_only(label_confusion=1.0, label_persistence=1.0, seed=4)
    mains = {next(iter(simulate(image, classes, noise, f).labels[0])) for f in range(30)}
    assert len(mains) == 1


def test_extra_labels_and_scores():
    image, classes = one_object("desk")
    noise = label_only(label_confusion=1.0, extra_label_prob=1.0, score_std=0.07)
    sizes, scores = [], []
    for frame in range(200):
        (labels,) = simulate(image, classes, noise, frame).labels
        sizes.append(len(labels))
        main, *rest = labels.values()
        assert all(score < main for score in rest)
        # Second and third labels are labels the class is really detected as (p >= 0.03).
        assert all(COLUMNS[LABELS.open_labels.index(name), C("desk")] >= 0.03 for name in list(labels)[1:])
        scores.append(main)
    assert max(sizes) == 3 and np.mean(sizes) > 2.2  # secondary scores under the text threshold drop out
    assert 0.42 < np.mean(scores) < 0.52 and min(scores) >= 0.35


def test_missed_tags_without_augmentation_lose_detections():
    image, classes = one_object("bed")  # the bed column is almost only "bed"
    noise = label_only(missed_tag_prob=0.3, prompt_augmentation=False)
    frames = 600
    results = [simulate(image, classes, noise, f) for f in range(frames)]
    missed = sum("bed" not in r.tags for r in results)
    assert abs(missed / frames - 0.3) < 0.05
    for r in results:
        assert r.prompt == r.tags
        assert r.num_detections == ("bed" in r.tags)


def test_prompt_augmentation_restores_recent_labels_except_the_excluded():
    noise = label_only(missed_tag_prob=1.0, prompt_augmentation=True)
    image, classes = one_object("bed")
    r = simulate(image, classes, noise, 0, recent={"bed", "floor", "door", "not a label"})
    assert r.tags == [] and r.prompt == ["bed"]
    assert r.labels == [{"bed": pytest.approx(noise.score_mean)}]
    # Excluded labels are never added back: a missed "floor" tag stays missed.
    image, classes = one_object("floor")
    r = simulate(image, classes, noise, 0, recent={"floor", "carpet"})
    assert r.prompt == [] and r.num_detections == 0
    # Ablation B: the same history, augmentation off.
    image, classes = one_object("bed")
    r = simulate(image, classes, noise.replace(prompt_augmentation=False), 0, recent={"bed"})
    assert r.prompt == [] and r.num_detections == 0


def test_relabel_gives_a_related_prompt_label():
    image, classes = one_object("table")
    noise = label_only(missed_tag_prob=1.0, relabel_prob=1.0, prompt_augmentation=True)
    r = simulate(image, classes, noise, 0, recent={"computer desk", "toilet bowl"})
    # "table" is missed from the prompt; the table is detected as the related prompt label.
    assert r.labels and set(r.labels[0]) == {"computer desk"}
    assert noise.box_threshold <= r.labels[0]["computer desk"] <= noise.box_threshold + 0.1


def test_split_gives_two_detections_inside_the_object():
    image, classes = one_object("table", size=50)
    noise = label_only(split_prob=1.0)
    for frame in range(10):
        r = simulate(image, classes, noise, frame)
        assert r.num_detections == 2
        union = r.masks[0] | r.masks[1]
        np.testing.assert_array_equal(union, image == 7)  # no border noise: the parts tile the object
        assert all(0.2 < m.sum() / union.sum() < 0.8 for m in r.masks)


def test_partial_mask_keeps_part_of_the_object():
    image, classes = one_object("table", size=50)
    noise = label_only(partial_prob=1.0)
    for frame in range(10):
        (mask,) = simulate(image, classes, noise, frame).masks
        obj = image == 7
        assert not (mask & ~obj).any()
        assert 0.3 < mask.sum() / obj.sum() < 0.9


def test_merge_joins_adjacent_objects_but_not_wall_or_floor():
    image, classes = room()
    r = simulate(image, classes, label_only(merge_prob=1.0), 0)
    table_or_chair = (image == 3) | (image == 4)
    merged = [m for m in r.masks if (m & table_or_chair).any()]
    assert len(merged) == 1 and (merged[0] == table_or_chair).all()
    assert r.num_detections == len(classes) - 1  # wall, floor, picture, table+chair


def test_border_noise_changes_borders_only():
    image, classes = room()
    r = simulate(image, classes, label_only(border_offset_px=2.0, border_jitter_px=2.0), 3)
    changed = 0
    for mask in r.masks:
        (instance, count) = np.unique(image[mask], return_counts=True)
        main = instance[np.argmax(count)]
        truth = image == main
        iou = (mask & truth).sum() / (mask | truth).sum()
        assert iou > 0.6
        changed += iou < 1.0
    assert changed >= 3


def test_missed_and_small_detections():
    image, classes = room()
    assert simulate(image, classes, label_only(miss_prob=1.0), 0).num_detections == 0
    rates = []
    for frame in range(300):
        r = simulate(image, classes, label_only(miss_prob=0.2), frame)
        rates.append(r.num_detections / len(classes))
    assert abs(1 - np.mean(rates) - 0.2) < 0.04
    # Small objects: the picture (1000 px) is missed more than the floor (>5000 px).
    noise = label_only(small_object_miss_prob=0.8, small_object_pixels=4000)
    found = {"picture": 0, "floor": 0}
    for frame in range(200):
        for labels in simulate(image, classes, noise, frame).labels:
            for name in found:
                found[name] += best_label(name) in labels
    assert found["floor"] == 200 and found["picture"] < 120
    # min_mask_pixels drops the picture outright.
    r = simulate(image, classes, label_only(min_mask_pixels=1001), 0)
    assert all(best_label("picture") not in labels for labels in r.labels)


def test_false_detections():
    image, classes = room()
    noise = label_only(false_positive_rate=3.0)
    extra, on_lamp = [], 0
    for frame in range(100):
        r = simulate(image, classes, noise, frame)
        check_invariants(r, noise)
        extra.append(r.num_detections - len(classes))
        low = [k for k, labels in enumerate(r.labels) if max(labels.values()) < noise.box_threshold + 0.08 and len(labels) == 1]
        on_lamp += any((r.masks[k] & (image == 9)).sum() > 0.5 * (image == 9).sum() for k in low)
    # Poisson(3) false detections, less those hidden below a smaller mask or too small.
    assert 1.5 < np.mean(extra) <= 3.2
    assert on_lamp > 20


def test_image_filling_masks_are_dropped():
    image = np.full((60, 80), 1, np.int32)
    noise = NoiseModel.preset("clean")
    assert simulate(image, {1: C("wall")}, noise).num_detections == 1
    assert simulate(image, {1: C("wall")}, noise.replace(max_box_fraction=0.95)).num_detections == 0


# --- files and scenes -----------------------------------------------------------------------------------


@pytest.mark.parametrize("mask_format", ["png", "npy"])
def test_round_trip_through_the_detection_files(tmp_path, mask_format):
    detections_io = pytest.importorskip("fmfusion_jax.io.detections")
    image, classes = room()
    r = simulate(image, classes, NoiseModel.preset("hard", seed=2), 4, recent={"bed", "chair"})
    assert r.num_detections > 0
    detections_io.write_frame_detections(tmp_path, r, mask_format=mask_format)
    back = detections_io.read_frame_detections(tmp_path, r.frame_name, image.shape)
    np.testing.assert_array_equal(back.masks, r.masks)
    np.testing.assert_allclose(back.boxes, r.boxes)
    assert back.labels == r.labels
    assert back.tags == r.tags and back.prompt == r.prompt and back.raw_tags == r.raw_tags


class PlaneScene:
    """A camera at the origin looking at a wall 2 m away: left half instance 1 (chair), right half 2 (table)."""

    name = "plane"

    def __init__(self, frames: int = 4):
        from fmfusion_jax.types import CameraIntrinsics

        self.intrinsics = CameraIntrinsics(100.0, 100.0, 80.0, 60.0, 160, 120)
        self.count = frames

    def __len__(self):
        return self.count

    def frames(self):
        from fmfusion_jax.types import RGBDFrame

        for i in range(self.count):
            yield RGBDFrame(
                i,
                f"frame-{i:06d}",
                np.zeros((120, 160, 3), np.uint8),
                np.full((120, 160), 2.0, np.float32),
                np.eye(4),
                self.intrinsics,
            )

    @staticmethod
    def ground_truth():
        x, y = np.meshgrid(np.arange(-1.8, 1.8, 0.03), np.arange(-1.4, 1.4, 0.03))
        vertices = np.stack([x.ravel(), y.ravel(), np.full(x.size, 2.0)], axis=1)
        instance_ids = np.where(vertices[:, 0] < 0, 1, 2).astype(np.int32)
        nyu40 = np.where(instance_ids == 1, 5, 7).astype(np.int32)
        return argparse.Namespace(
            vertices=vertices,
            faces=np.zeros((0, 3), np.int64),
            instance_ids=instance_ids,
            nyu40_ids=nyu40,
            instance_labels={1: "chair", 2: "table"},
        )


def test_rendering_and_simulate_scene_on_a_synthetic_plane(tmp_path):
    from fmfusion_jax.io.detections import list_detection_frames, read_frame_detections
    from fmfusion_jax.simulation.render import GroundTruthRenderer, instance_classes
    from fmfusion_jax.simulation.simulate import simulate_scene

    scene, gt = PlaneScene(), PlaneScene.ground_truth()
    assert instance_classes(gt) == {1: C("chair"), 2: C("table")}
    frame = next(scene.frames())
    rendered = GroundTruthRenderer.from_ground_truth(gt).render(frame.depth, frame.T_world_camera, frame.intrinsics)
    expected = np.where(np.arange(160) < 80, 1, 2)[None, :].repeat(120, axis=0)
    assert (rendered == expected).mean() > 0.98
    summary = simulate_scene(scene, gt, tmp_path / "sim", NoiseModel.preset("clean"), every=2, progress=False)
    assert summary.frame_names == ["frame-000000", "frame-000002"] == list_detection_frames(tmp_path / "sim")
    assert summary.detections_per_frame == [2, 2]
    detections = read_frame_detections(tmp_path / "sim", "frame-000002", (120, 160))
    assert detections.labels == [{best_label("chair"): 0.47}, {best_label("table"): 0.47}]
    np.testing.assert_array_equal(detections.masks[0], rendered == 1)


@pytest.mark.scannet
def test_ground_truth_rendering_on_the_real_scene(scannet_scene):
    from scipy.spatial import cKDTree

    from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
    from fmfusion_jax.io.scene import open_scene
    from fmfusion_jax.simulation.render import GroundTruthRenderer, instance_classes

    scene = open_scene(scannet_scene)
    gt = load_scannet_ground_truth(scannet_scene)
    classes = instance_classes(gt)
    assert classes[55] == C("door") and classes[38] == C("bed") and 12 not in classes  # 12: a scale
    renderer = GroundTruthRenderer.from_ground_truth(gt)
    tree = cKDTree(gt.vertices)
    poses = scene.poses()
    for i in (0, 150, 299):
        depth = scene.read_depth(i)
        rendered = renderer.render(depth, poses[i], scene.intrinsics)
        assert rendered.shape == depth.shape
        valid = depth > 0
        assert (rendered[valid] > 0).mean() > 0.7
        # Pixels whose surface point is within 3 cm of an instance vertex carry that vertex's instance.
        v, u = np.nonzero(valid)
        pick = np.random.default_rng(i).choice(v.size, 3000, replace=False)
        v, u = v[pick], u[pick]
        intr = scene.intrinsics
        z = depth[v, u].astype(np.float64)
        cam = np.stack([(u - intr.cx) * z / intr.fx, (v - intr.cy) * z / intr.fy, z], axis=1)
        world = cam @ poses[i][:3, :3].T + poses[i][:3, 3]
        distance, nearest = tree.query(world)
        near = (distance < 0.03) & (gt.instance_ids[nearest] > 0)
        agree = rendered[v[near], u[near]] == gt.instance_ids[nearest[near]]
        assert agree.mean() > 0.85


@pytest.mark.scannet
def test_simulate_scene_and_cli_on_the_real_scene(scannet_scene, tmp_path, capsys):
    from fmfusion_jax.cli import simulate as cli_simulate
    from fmfusion_jax.io.detections import list_detection_frames, read_frame_detections

    parser = argparse.ArgumentParser(prog="fmfusion")
    cli_simulate.register(parser.add_subparsers(dest="command"))
    out = tmp_path / "sim"
    args = parser.parse_args(
        [
            "simulate",
            str(scannet_scene),
            "--out",
            str(out),
            "--seed",
            "3",
            "--every",
            "50",
            "--max-frames",
            "3",
            "--set",
            "missed_tag_prob=0.5",
            "--no-prompt-augmentation",
        ]
    )
    assert args.func(args) == 0
    assert "simulated 3 frames" in capsys.readouterr().out
    assert list_detection_frames(out) == ["frame-000000", "frame-000050", "frame-000100"]
    record = json.loads((out / "simulation.json").read_text())
    assert record["seed"] == 3 and record["noise"]["missed_tag_prob"] == 0.5
    assert record["noise"]["prompt_augmentation"] is False and record["every"] == 50
    first = read_frame_detections(out, "frame-000050", (480, 640))
    assert first.num_detections == record["detections_per_frame"][1] > 0
    assert first.prompt == first.tags  # no augmentation
    # Running again into the same folder replaces the simulation; a foreign folder is refused.
    args = parser.parse_args(["simulate", str(scannet_scene), "--out", str(out), "--max-frames", "1", "--quiet"])
    assert args.func(args) == 0
    assert list_detection_frames(out) == ["frame-000000"]
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    args = parser.parse_args(["simulate", str(scannet_scene), "--out", str(foreign), "--quiet"])
    with pytest.raises(UserError, match="not empty"):
        args.func(args)
