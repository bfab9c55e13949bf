"""The zoo's families of false positives seen on real detections (`persistent`, `background`, `texture`):
each makes the detections it claims on a small room, and adding them left every earlier entry's noise
record, cache name and detections as they were."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fmfusion_jax.errors import UserError
from fmfusion_jax.labels import load_label_sets, load_likelihood
from fmfusion_jax.simulation.noise import FAMILY_DOSES, LATER_PARAMS, NoiseModel, split_into_pieces
from fmfusion_jax.simulation.sim_false_positives import BACKGROUND_CLASSES, Phantom, phantom_mask, place_phantoms
from fmfusion_jax.simulation.simulate import simulate_frame, simulate_scene
from fmfusion_jax.simulation.zoo import LATER_FAMILIES, MIXED, noise_zoo
from fmfusion_jax.types import CameraIntrinsics

LABELS = load_label_sets()
LIKELIHOOD = load_likelihood("statistical")
C = LABELS.class_index
WALL, FLOOR, TABLE, CHAIR, BOX = 1, 2, 3, 4, 8


def room() -> tuple[np.ndarray, dict[int, int]]:
    """120x160: wall over floor, a table with a chair beside it, a box (no class) and a strip of no ground truth."""
    image = np.zeros((120, 160), np.int32)
    image[:60, :] = WALL
    image[60:, :] = FLOOR
    image[45:95, 20:90] = TABLE
    image[55:100, 90:115] = CHAIR
    image[95:110, 30:70] = BOX
    image[:, 150:] = 0
    return image, {WALL: C("wall"), FLOOR: C("floor"), TABLE: C("table"), CHAIR: C("chair")}


def quiet(**changes) -> NoiseModel:
    """`clean` (ground-truth masks, every label tagged) with some failure modes switched on."""
    return NoiseModel.preset("clean", min_mask_pixels=50, **changes)


def simulate(image, classes, noise, frame_index=0, phantoms=()):
    return simulate_frame(image, classes, f"frame-{frame_index:06d}", frame_index, noise, LABELS, LIKELIHOOD, phantoms=phantoms)


def extra_detections(image, classes, noise, frame_index=0, phantoms=()):
    """The detections of `noise` that the same frame without the new failure modes lacks: (mask, labels)."""
    base = noise.replace(**{k: getattr(NoiseModel(), k) for k in LATER_PARAMS})
    before = simulate(image, classes, base, frame_index)
    after = simulate(image, classes, noise, frame_index, phantoms)
    # A detection of before that the new masks cut into (smaller masks win) is still the same detection.
    return [
        (m, l)
        for m, l in zip(after.masks, after.labels)
        if not any(l == old_labels and not (m & ~old).any() for old, old_labels in zip(before.masks, before.labels))
    ]


# --- nothing earlier changed --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def generated_room(tmp_path_factory):
    """A procedural room of 4 objects, 8 frames at 160x120 (ScanNet layout, with ground truth)."""
    from fmfusion_jax.io.ground_truth import load_scannet_ground_truth
    from fmfusion_jax.io.scene import open_scene
    from fmfusion_jax.simulation.procedural import generate_scene
    from fmfusion_jax.simulation.scannet_writer import write_scannet_scene

    scene_dir = tmp_path_factory.mktemp("room") / "synth0007_00"
    write_scannet_scene(generate_scene(7, num_objects=4), scene_dir, num_frames=8, width=160, height=120, progress=False)
    return open_scene(scene_dir), load_scannet_ground_truth(scene_dir)


def _detections_digest(folder, frame_names) -> str:
    from fmfusion_jax.io.detections import read_frame_detections

    digest = hashlib.sha256()
    for name in frame_names:
        d = read_frame_detections(folder, name)
        assert d is not None
        digest.update(np.packbits(d.masks).tobytes())
        digest.update(json.dumps([d.labels, d.tags, d.prompt]).encode())
    return digest.hexdigest()


def test_earlier_families_simulate_the_same_detections_on_a_generated_room(generated_room, tmp_path):
    # sha256 of the detections the simulator made before the three families were added (commit 8709e87),
    # with this numpy and OpenCV.
    pinned = {
        "default": "c744e56ec89e086b14bc68c4d871de169a60b6498497ef4eba9b7a6ce2c7a45b",
        "confusers": "cef150e102a358c8a7450d7663963e7106b62786548b1c39c70c6d2584efc124",
        "border": "520f30198eaa2650c547fe47becf7233051e992796e4aa476b67237a8f771650",
    }
    scene, gt = generated_room
    for family, expected in pinned.items():
        noise = NoiseModel.preset(family, seed=2, min_mask_pixels=100, small_object_pixels=1000)
        summary = simulate_scene(scene, gt, tmp_path / family, noise, progress=False)
        record = json.loads((tmp_path / family / "simulation.json").read_text())
        assert not set(record["noise"]) & set(LATER_PARAMS) and "phantoms" not in record
        assert _detections_digest(tmp_path / family, summary.frame_names) == expected, family


def test_earlier_zoo_entries_keep_their_noise_records_and_mixtures_their_draws():
    zoo = {e.name: e for e in noise_zoo(mixed=4, seed=0)}
    for name, entry in zoo.items():
        if entry.family not in (*LATER_FAMILIES, MIXED):
            assert not set(entry.noise.to_dict()) & set(LATER_PARAMS), name
    # The mixtures' first-five-family parameters are those of the zoo before (pinned), whatever later
    # families they drew on top.
    pinned = {"mixed-1": "a036495984", "mixed-2": "4f50a9bce9", "mixed-3": "a9bbbaf7c8", "mixed-4": "49968aef40"}
    for name, expected in pinned.items():
        earlier = {k: v for k, v in zoo[name].noise.to_dict().items() if k not in LATER_PARAMS}
        assert hashlib.sha1(json.dumps(earlier, sort_keys=True).encode()).hexdigest()[:10] == expected, name
    drawn = [any(k in zoo[n].noise.to_dict() for k in LATER_PARAMS) for n in pinned]
    assert any(drawn)


def test_validation_and_doses():
    with pytest.raises(UserError, match="needs persistent_radius_m"):
        NoiseModel(persistent_phantoms=2.0, persistent_detect_prob=0.5)
    with pytest.raises(UserError, match="must be a probability"):
        NoiseModel(background_strip_share=1.5)
    with pytest.raises(UserError, match="must be >= 0"):
        NoiseModel(background_rate=-1.0)
    for family in LATER_FAMILIES:
        noise = NoiseModel.preset(family)
        assert set(noise.to_dict()) & set(LATER_PARAMS) == set(FAMILY_DOSES[family])


# --- persistent ------------------------------------------------------------------------------------------


def _backproject(mask, depth, T, intrinsics) -> np.ndarray:
    v, u = np.nonzero(mask & (depth > 0))
    z = depth[v, u].astype(np.float64)
    xyz = np.stack([(u - intrinsics.cx) * z / intrinsics.fx, (v - intrinsics.cy) * z / intrinsics.fy, z], axis=1)
    return xyz @ T[:3, :3].T + T[:3, 3]


def test_phantom_mask_is_the_seen_surface_inside_the_sphere_and_hidden_behind_occluders():
    intrinsics = CameraIntrinsics(100.0, 100.0, 80.0, 60.0, 160, 120)
    depth = np.full((120, 160), 2.0, np.float32)  # a wall 2 m in front of the camera
    T = np.eye(4)
    phantom = Phantom(np.array([0.2, 0.0, 2.0]), 0.25, C("cabinet"), "cabinet")
    mask = phantom_mask(phantom, depth, T, intrinsics)
    # the disc of radius 0.25 m at 2 m: radius 12.5 px around (90, 60)
    assert abs(mask.sum() - np.pi * 12.5**2) < 0.1 * np.pi * 12.5**2
    assert mask[60, 90] and not mask[60, 75]
    points = _backproject(mask, depth, T, intrinsics)
    assert np.linalg.norm(points - phantom.center, axis=1).max() < 0.25
    occluded = depth.copy()
    occluded[:, 85:] = 1.0  # something in front hides its right part
    hidden = phantom_mask(phantom, occluded, T, intrinsics)
    assert hidden.sum() < mask.sum() and not hidden[:, 85:].any()
    behind = Phantom(np.array([0.0, 0.0, -2.0]), 0.25, C("cabinet"), "cabinet")
    assert not phantom_mask(behind, depth, T, intrinsics).any()


def test_persistent_phantoms_land_at_the_same_world_place_in_every_view(generated_room, tmp_path):
    from fmfusion_jax.io.detections import read_frame_detections
    from fmfusion_jax.simulation.render import instance_classes

    scene, gt = generated_room
    noise = NoiseModel.preset(
        "clean", seed=1, min_mask_pixels=30, persistent_phantoms=3.0, persistent_radius_m=0.3, persistent_detect_prob=1.0
    )
    classes = instance_classes(gt, LABELS)
    phantoms = place_phantoms(gt.vertices, gt.faces, gt.instance_ids, classes, noise, LABELS, LIKELIHOOD)
    assert len(phantoms) == 3
    # per seed: the same places again, more phantoms only add to them
    more = place_phantoms(gt.vertices, gt.faces, gt.instance_ids, classes, noise.replace(persistent_phantoms=4.0))
    assert all(np.allclose(a.center, b.center) and a.label == b.label for a, b in zip(phantoms, more))
    summary = simulate_scene(scene, gt, tmp_path / "sim", noise, progress=False)
    record = json.loads((tmp_path / "sim" / "simulation.json").read_text())
    assert [p["label"] for p in record["phantoms"]] == [p.label for p in phantoms]
    poses = scene.poses()
    hits = 0
    for i, name in enumerate(summary.frame_names):
        d = read_frame_detections(tmp_path / "sim", name)
        depth = scene.read_depth(i)
        for phantom in phantoms:
            view = phantom_mask(phantom, depth, poses[i], scene.intrinsics)
            if view.sum() < 200:  # barely in view: the target objects' pixels may take it under the least size
                continue
            overlap = d.masks[:, view].sum(axis=1)
            k = int(overlap.argmax())
            assert phantom.label in d.labels[k], (name, phantom.label, d.labels[k])
            # the detection is the phantom's place in the world, nothing else
            points = _backproject(d.masks[k], depth, poses[i], scene.intrinsics)
            assert np.linalg.norm(points - phantom.center, axis=1).max() < phantom.radius + 1e-3
            hits += 1
    assert hits >= 3


# --- background ----------------------------------------------------------------------------------------


def test_background_regions_lie_on_wall_floor_or_nothing_with_furniture_labels():
    image, classes = room()
    background = (image == WALL) | (image == FLOOR) | (image == 0)
    noise = quiet(background_rate=2.0, background_strip_share=0.5)
    furniture = {label for c in BACKGROUND_CLASSES for label in np.asarray(LABELS.open_labels)[LIKELIHOOD[:, C(c)] > 0]}
    found, thin = 0, 0
    for f in range(20):
        for mask, labels in extra_detections(image, classes, noise, f):
            assert background[mask].all()
            assert set(labels) <= furniture
            assert max(labels.values()) >= noise.box_threshold
            rows, cols = np.nonzero(mask)
            thin += min(np.ptp(rows), np.ptp(cols)) + 1 <= 12
            found += 1
    assert found >= 20 and thin >= 3  # about two a frame, some of them strips


# --- texture ---------------------------------------------------------------------------------------------


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 30), st.integers(0, 2**31 - 1))
def test_split_into_pieces_partitions_the_mask(count, seed):
    mask = np.zeros((40, 60), bool)
    mask[5:35, 10:55] = True
    pieces = split_into_pieces(mask, count, np.random.default_rng(seed))
    assert len(pieces) == count
    total = np.sum(pieces, axis=0)
    assert (total == mask).all()  # disjoint, and together the mask


def test_texture_splits_large_regions_into_many_small_low_score_masks():
    image, classes = room()
    noise = quiet(texture_prob=1.0, texture_piece_share=0.02)  # pieces of ~384 px
    pieces = []
    for f in range(4):
        pieces += extra_detections(image, classes, noise, f)
    sizes = np.array([m.sum() for m, _ in pieces])
    assert len(pieces) >= 4 * 12  # many a frame
    assert np.median(sizes) < 2.5 * 0.02 * image.size and sizes.max() < 0.15 * image.size
    scores = [max(labels.values()) for _, labels in pieces]
    assert max(scores) <= noise.box_threshold + 0.08 + 1e-4
    # the pieces lie on the large regions only (wall, floor, table), never on the chair or box (too small)
    covered = np.any([m for m, _ in pieces], axis=0)
    assert not covered[(image == CHAIR) | (image == BOX)].any()
    off = quiet(texture_prob=0.0, texture_piece_share=0.02)
    assert simulate(image, classes, off).num_detections == simulate(image, classes, quiet()).num_detections
