"""The procedural scene generator (`fmfusion synth`): scenes, trajectory, renderer, mesh and ScanNet writer.

Everything here runs on tiny images (160x120) and a few frames, in a few seconds in all.
"""

from __future__ import annotations

import csv
import json
import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import fmfusion_jax.cli as cli
from fmfusion_jax.labels import load_label_sets
from fmfusion_jax.simulation import raycast
from fmfusion_jax.simulation.furniture import CEILING_NYU40, OBJECT_KINDS, RAW_LABELS
from fmfusion_jax.simulation.procedural import (
    add_object,
    camera_trajectory,
    default_room_size,
    empty_room,
    generate_scene,
    look_pose,
)
from fmfusion_jax.simulation.scannet_writer import scene_intrinsics, write_scannet_scene
from fmfusion_jax.simulation.scene_mesh import build_mesh
from fmfusion_jax.simulation.scene_views import render_frame

SMALL = raycast.SCANNET_INTRINSICS.scaled(160, 120)


def box_overlap(a, b, tolerance: float = 1e-6) -> bool:
    """Whether the interiors of two yaw-rotated boxes intersect (by more than `tolerance`)."""
    if abs(a.center[2] - b.center[2]) >= a.half_extents[2] + b.half_extents[2] - tolerance:
        return False
    axes = [(math.cos(y), math.sin(y)) for y in (a.yaw, b.yaw)]
    axes += [(-s, c) for c, s in axes]
    for ax in axes:
        ax = np.array(ax)

        def radius(box):
            c, s = math.cos(box.yaw), math.sin(box.yaw)
            return abs(ax @ [c, s]) * box.half_extents[0] + abs(ax @ [-s, c]) * box.half_extents[1]

        if abs(ax @ (a.center[:2] - b.center[:2])) >= radius(a) + radius(b) - tolerance:
            return False
    return True


# ------------------------------------------------------------------------------------------------ scenes


def test_generation_is_deterministic_per_seed():
    a, b, c = generate_scene(3, num_objects=10), generate_scene(3, num_objects=10), generate_scene(4, num_objects=10)
    assert len(a.boxes) == len(b.boxes)
    for x, y in zip(a.boxes, b.boxes):
        np.testing.assert_array_equal(x.center, y.center)
        np.testing.assert_array_equal(x.half_extents, y.half_extents)
        assert (x.yaw, x.instance_id) == (y.yaw, y.instance_id)
    assert a.instances == b.instances
    np.testing.assert_array_equal(a.trajectory(20), b.trajectory(20))
    assert [x.center.tolist() for x in a.boxes] != [x.center.tolist() for x in c.boxes]


@pytest.mark.parametrize("num_objects", [1, 5, 15, 60])
def test_object_count_classes_and_labels(num_objects):
    scene = generate_scene(num_objects, num_objects=num_objects)
    assert len(scene.object_ids) == num_objects
    label_sets = load_label_sets()
    nyu40 = dict(zip(label_sets.class_names, label_sets.nyu40_ids.tolist()))
    kinds = [info.kind for info in scene.instances.values()]
    assert kinds[:6] == ["wall"] * 4 + ["floor", "ceiling"]
    for info in scene.instances.values():
        assert RAW_LABELS[info.raw_label] == info.class_name
        assert info.nyu40_id == (CEILING_NYU40 if info.class_name == "ceiling" else nyu40[info.class_name])
        assert scene.instance_boxes(info.instance_id), info
    if num_objects >= 2:
        assert {"door", "window"} <= set(kinds)
    if num_objects >= 17:  # every kind once before repeats
        assert set(OBJECT_KINDS) <= set(kinds)
    w, d, _ = scene.room_size
    assert w >= default_room_size(num_objects)[0] and d >= default_room_size(num_objects)[1]


def test_kinds_restrict_the_objects():
    scene = generate_scene(1, num_objects=6, kinds=["chair", "table"])
    assert sorted({scene.instances[i].kind for i in scene.object_ids}) == ["chair", "table"]
    with pytest.raises(ValueError, match="unknown object kinds"):
        generate_scene(1, kinds=["spaceship"])
    with pytest.raises(ValueError, match="could place only"):
        generate_scene(1, room_size=(2.0, 2.0, 2.4), num_objects=30)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), num_objects=st.integers(5, 40))
def test_objects_do_not_overlap_and_stay_in_the_room(seed, num_objects):
    scene = generate_scene(seed, num_objects=num_objects)
    w, d, h = scene.room_size
    structure = set(range(1, 7))
    objects = [b for b in scene.boxes if b.instance_id not in structure]
    for i, a in enumerate(objects):
        for b in objects[i + 1 :]:
            if a.instance_id != b.instance_id:
                assert not box_overlap(a, b), (scene.instances[a.instance_id], scene.instances[b.instance_id])
        mounted = scene.instances[a.instance_id].kind in ("door", "window")
        corners = raycast.BoxArrays(
            a.center[None], a.half_extents[None], a.rotation[None], np.zeros((1, 3)), np.zeros(1, np.int32), np.zeros(1, np.int32)
        ).corners()[0]
        slack = 0.06 if mounted else 1e-6  # doors and windows are set into their wall
        assert corners.min(axis=0)[:2].min() >= -slack and corners[:, 0].max() <= w + slack
        assert corners[:, 1].max() <= d + slack and -1e-6 <= corners[:, 2].min() and corners[:, 2].max() <= h


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), stacked=st.integers(1, 6))
def test_stacked_objects_stand_on_their_support_and_overlap_nothing(seed, stacked):
    kinds = ("table", "desk", "counter", "cabinet", "chair")
    plain, scene = (
        generate_scene(seed, num_objects=6, kinds=kinds),
        generate_scene(seed, num_objects=6, kinds=kinds, stacked=stacked),
    )
    same = generate_scene(seed, num_objects=6, kinds=kinds, stacked=0)  # 0: the room without the option
    arrays = lambda room: [np.concatenate([b.center, b.half_extents, b.color, [b.yaw]]) for b in room.boxes]  # noqa: E731
    np.testing.assert_array_equal(arrays(same), arrays(plain))
    floor = next(i for i, info in scene.instances.items() if info.kind == "floor")
    on_objects = {a: b for a, b in scene.resting_on.items() if b != floor}
    assert 1 <= len(on_objects) <= stacked and len(scene.object_ids) == len(plain.object_ids) + len(on_objects)
    objects = [b for b in scene.boxes if b.instance_id in scene.object_ids]
    for i, a in enumerate(objects):
        for b in objects[i + 1 :]:
            if a.instance_id != b.instance_id:
                assert not box_overlap(a, b), (scene.instances[a.instance_id], scene.instances[b.instance_id])
    for thing, support in on_objects.items():
        assert scene.instances[thing].class_name == "otherfurniture" and scene.instances[support].kind in kinds
        center, extent, yaw = scene.instance_box(thing)
        s_center, s_extent, s_yaw = scene.instance_box(support)
        assert center[2] - extent[2] / 2 == pytest.approx(s_center[2] + s_extent[2] / 2, abs=1e-9)  # on its top
        corners = (
            center[:2]
            + np.array([[x, y] for x in (-0.5, 0.5) for y in (-0.5, 0.5)]) * extent[:2] @ raycast.yaw_rotation(yaw)[:2, :2].T
        )
        local = (corners - s_center[:2]) @ raycast.yaw_rotation(s_yaw)[:2, :2]
        assert (np.abs(local) <= s_extent[:2] / 2 + 1e-9).all()  # wholly over it
        assert (thing, support) in scene.relations()["on"]
    assert {a for a, b in scene.resting_on.items() if b == floor} == set(plain.resting_on)


# ------------------------------------------------------------------------------------------- trajectory


def test_trajectory_is_smooth_outside_furniture_and_looks_at_something_near():
    scene = generate_scene(7, num_objects=15)
    poses = camera_trajectory(scene, 120)
    assert poses.shape == (120, 4, 4)
    R = poses[:, :3, :3]
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    positions = poses[:, :3, 3]
    assert np.all((positions[:, 2] > 1.3) & (positions[:, 2] < 1.6))
    assert not scene.contains(positions, margin=0.1).any()
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    assert steps.max() < 0.2
    forward = poses[:, :3, 2]
    assert np.all(forward[:, 2] < -0.3)  # pitched down
    t, box = raycast.raycast_rays(scene.box_arrays(), positions, forward)
    assert np.all(box >= 0) and t.max() < 4.0


# ---------------------------------------------------------------------------------------------- renderer


def test_depth_of_a_known_box_is_the_analytic_distance():
    room = empty_room((6.0, 6.0, 3.0))
    scene = add_object(room, "cabinet", [((3.0, 4.0, 1.0), (1.0, 0.5, 2.0), 0.0)])
    # Camera at (3, 1, 1) looking along +y (yaw 90 deg), level: the cabinet's front face is the plane y = 3.75.
    pose = look_pose((3.0, 1.0, 1.0), math.pi / 2, 0.0)
    frame = render_frame(scene, pose, SMALL, depth_noise=False, color_noise=False)
    cx, cy = int(round(SMALL.cx)), int(round(SMALL.cy))
    assert frame.depth_exact[cy, cx] == pytest.approx(2.75, abs=1e-5)
    cabinet = frame.instance == 7
    assert cabinet[cy, cx]
    np.testing.assert_allclose(frame.depth[cabinet], 2.75, atol=1e-5)  # a fronto-parallel face: constant z-depth
    # Its projected width: 1 m at 2.75 m.
    assert abs(cabinet[cy].sum() - SMALL.fx * 1.0 / 2.75) <= 1.5
    # The floor below: z-depth of the ray meeting the plane z = 0 at 1 m below the camera.
    v = SMALL.height - 1
    assert frame.instance[v, cx] == 5
    assert frame.depth[v, cx] == pytest.approx(SMALL.fy / (v - SMALL.cy) * 1.0, rel=1e-5)
    # A wall beside the cabinet: the far wall y = 6 at z-depth 5.
    assert frame.instance[cy, 2] == 4 and frame.depth[cy, 2] == pytest.approx(5.0, abs=1e-5)


@settings(max_examples=10, deadline=None)
@given(yaw=st.floats(-math.pi, math.pi), box_yaw=st.floats(-math.pi, math.pi), pitch=st.floats(-0.6, 0.3))
def test_rendered_depth_matches_independent_rays(yaw, box_yaw, pitch):
    scene = add_object(empty_room((6.0, 6.0, 3.0)), "table", [((3.0, 3.0, 0.5), (1.2, 0.7, 1.0), box_yaw)])
    pose = look_pose((1.0 + 4 * (math.cos(yaw) < 0), 1.0 + 4 * (math.sin(yaw) < 0), 1.4), yaw, pitch)
    intrinsics = raycast.SCANNET_INTRINSICS.scaled(32, 24)
    frame = render_frame(scene, pose, intrinsics, depth_noise=False, color_noise=False, max_range=100.0)
    xs, ys = raycast.camera_rays(intrinsics)
    directions = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], 1.0), -1).reshape(-1, 3) @ pose[:3, :3].T
    t, box = raycast.raycast_rays(scene.box_arrays(), np.broadcast_to(pose[:3, 3], directions.shape), directions)
    np.testing.assert_allclose(frame.depth_exact.ravel(), t, rtol=1e-4, atol=1e-4)
    ids = scene.box_arrays().instance_ids[box]
    agree = frame.instance.ravel() == ids
    assert agree.mean() > 0.97  # ties between touching faces (wall/floor edges) may go either way


def test_instance_image_is_consistent_with_depth():
    scene = generate_scene(2, num_objects=12)
    poses = scene.trajectory(6)
    for k, pose in enumerate(poses):
        noisy = render_frame(scene, pose, SMALL, rng=np.random.default_rng(k))
        assert np.all(noisy.depth[noisy.instance > 0] > 0)
        assert noisy.color.dtype == np.uint8 and noisy.color.shape == (120, 160, 3)
        valid = noisy.depth > 0
        assert 0.8 < valid.mean() < 1.0  # a few holes and grazing-angle dropouts
        # The noise is Kinect-like: a few mm to cm, growing with depth.
        error = np.abs(noisy.depth - noisy.depth_exact)[valid]
        assert 0.0005 < np.median(error) < 0.02
        exact = render_frame(scene, pose, SMALL, depth_noise=False)
        assert np.all(exact.instance > 0) and np.all(exact.depth > 0)  # a closed room, all within 6 m
        np.testing.assert_array_equal(exact.depth, exact.depth_exact)


# -------------------------------------------------------------------------------------------------- mesh


def test_mesh_is_fine_bounded_and_labelled():
    scene = generate_scene(5, num_objects=15)
    mesh = build_mesh(scene)
    assert mesh.spacing == 0.03
    edges = mesh.vertices[mesh.faces] - mesh.vertices[np.roll(mesh.faces, 1, axis=1)]
    assert np.linalg.norm(edges, axis=2).max() <= 0.03 * math.sqrt(2) + 1e-4
    assert set(np.unique(mesh.instance_ids)) == set(scene.instances)
    # A segment never spans two instances.
    for segment in np.unique(mesh.segment_ids)[::25]:
        assert np.unique(mesh.instance_ids[mesh.segment_ids == segment]).size == 1
    big = build_mesh(generate_scene(5, num_objects=60))
    assert big.vertices.shape[0] <= 300_000 and big.spacing > 0.03


# --------------------------------------------------------------------------------------- written folder


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    scene = generate_scene(11, num_objects=8)
    out = write_scannet_scene(
        scene,
        tmp_path_factory.mktemp("synth") / "synth0011_00",
        num_frames=6,
        width=160,
        height=120,
        depth_noise=False,
        progress=False,
    )
    return scene, out


def read_vertex_ground_truth(out):
    """Per-vertex (instance id, nyu40 id) decoded from segs + aggregation + tsv, by hand."""
    name = out.name
    segments = np.asarray(json.loads((out / f"{name}_vh_clean_2.0.010000.segs.json").read_text())["segIndices"])
    groups = json.loads((out / f"{name}.aggregation.json").read_text())["segGroups"]
    with open(out / "scannetv2-labels.combined.tsv", newline="") as file:
        label_to_nyu40 = {row["category"]: int(row["nyu40id"]) for row in csv.DictReader(file, delimiter="\t")}
    instance = np.zeros(segments.size, np.int64)
    nyu40 = np.zeros(segments.size, np.int64)
    for group in groups:
        members = np.isin(segments, group["segments"])
        assert not instance[members].any(), "a segment in two groups"
        instance[members] = group["objectId"] + 1
        nyu40[members] = label_to_nyu40[group["label"]]
    return instance, nyu40


def test_written_folder_round_trips(written):
    scene, out = written
    name = out.name
    intrinsics = scene_intrinsics(160, 120)
    K = np.loadtxt(out / "intrinsic" / "intrinsic_depth.txt")
    np.testing.assert_allclose(K[:3, :3], intrinsics.matrix, atol=1e-5)
    np.testing.assert_allclose(np.loadtxt(out / "intrinsic" / "intrinsic_color.txt"), K)
    poses = scene.trajectory(6)
    for k in range(6):
        stem = f"frame-{k:06d}"
        pose = np.loadtxt(out / "pose" / f"{stem}.txt")
        np.testing.assert_allclose(pose, poses[k], atol=1e-7)
        depth_png = cv2.imread(str(out / "depth" / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        assert depth_png.dtype == np.uint16 and depth_png.shape == (120, 160)
        exact = render_frame(scene, poses[k], intrinsics, depth_noise=False, color_noise=False)
        np.testing.assert_allclose(depth_png / 1000.0, exact.depth_exact, atol=0.0005 + 1e-6)
        color = cv2.imread(str(out / "color" / f"{stem}.jpg"))
        assert color.shape == (120, 160, 3)
        # BGR on disk: the JPEG decodes close to the rendered RGB once swapped.
        assert np.abs(color[..., ::-1].astype(int) - exact.color).mean() < 12
        ids = cv2.imread(str(out / "gt_instances" / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(ids, exact.instance)
    # Mesh and ground truth.
    mesh = build_mesh(scene)
    ply = (out / f"{name}_vh_clean_2.ply").read_bytes()
    assert f"element vertex {mesh.vertices.shape[0]}\n".encode() in ply[:400]
    instance, nyu40 = read_vertex_ground_truth(out)
    np.testing.assert_array_equal(instance, mesh.instance_ids)
    expected_nyu40 = np.array([scene.instances[i].nyu40_id for i in mesh.instance_ids])
    np.testing.assert_array_equal(nyu40, expected_nyu40)
    listed = json.loads((out / "gt_instances" / "instances.json").read_text())
    assert [entry["instance_id"] for entry in listed] == sorted(scene.instances)


def test_written_mesh_reads_with_trimesh(written):
    trimesh = pytest.importorskip("trimesh")
    scene, out = written
    mesh = trimesh.load(out / f"{out.name}_vh_clean_2.ply", process=False)
    reference = build_mesh(scene)
    np.testing.assert_allclose(mesh.vertices, reference.vertices, atol=1e-6)
    np.testing.assert_array_equal(mesh.faces, reference.faces)
    np.testing.assert_array_equal(mesh.visual.vertex_colors[:, :3], reference.colors)


def test_depth_lands_on_the_ground_truth_mesh(written):
    from scipy.spatial import cKDTree

    scene, out = written
    mesh = build_mesh(scene)
    tree = cKDTree(mesh.vertices)
    intrinsics = scene_intrinsics(160, 120)
    for k, pose in enumerate(scene.trajectory(6)):
        depth = cv2.imread(str(out / "depth" / f"frame-{k:06d}.png"), cv2.IMREAD_UNCHANGED) / 1000.0
        ids = cv2.imread(str(out / "gt_instances" / f"frame-{k:06d}.png"), cv2.IMREAD_UNCHANGED)
        v, u = np.nonzero(depth > 0)
        z = depth[v, u]
        camera = np.stack([(u - intrinsics.cx) * z / intrinsics.fx, (v - intrinsics.cy) * z / intrinsics.fy, z], 1)
        distance, nearest = tree.query(camera @ pose[:3, :3].T + pose[:3, 3])
        assert np.median(distance) < 0.015 and distance.max() < 0.03  # vertex spacing 3 cm
        assert (mesh.instance_ids[nearest] == ids[v, u]).mean() > 0.97


def test_the_project_readers_read_the_written_scene(written):
    scene, out = written
    ground_truth = pytest.importorskip("fmfusion_jax.io.ground_truth")
    gt = ground_truth.load_scannet_ground_truth(out)
    mesh = build_mesh(scene)
    np.testing.assert_array_equal(gt.instance_ids, mesh.instance_ids)
    np.testing.assert_array_equal(gt.nyu40_ids, [scene.instances[i].nyu40_id for i in mesh.instance_ids])
    np.testing.assert_allclose(gt.vertices, mesh.vertices, atol=1e-6)
    assert gt.instance_labels == {i: info.raw_label for i, info in scene.instances.items()}

    scene_io = pytest.importorskip("fmfusion_jax.io.scene")
    opened = scene_io.open_scene(out, depth_max=10.0)
    assert len(opened) == 6 and opened.layout == "scannet"
    assert (opened.intrinsics.width, opened.intrinsics.height) == (160, 120)
    assert opened.intrinsics.fx == pytest.approx(scene_intrinsics(160, 120).fx, abs=1e-4)
    frame = opened.read_frame(2)
    np.testing.assert_allclose(frame.T_world_camera, scene.trajectory(6)[2], atol=1e-7)
    assert frame.depth.shape == (120, 160) and frame.color.shape == (120, 160, 3)
    assert all(opened.ground_truth_files()[role] is not None for role in ("mesh", "segments", "aggregation"))


def test_writer_refuses_a_non_empty_folder_unless_overwriting(written, tmp_path):
    from fmfusion_jax.errors import UserError

    scene, _ = written
    out = tmp_path / "synth_00"
    write_scannet_scene(scene, out, num_frames=3, width=32, height=24, progress=False)
    with pytest.raises(UserError, match="not empty"):
        write_scannet_scene(scene, out, num_frames=2, width=32, height=24, progress=False)
    write_scannet_scene(scene, out, num_frames=2, width=32, height=24, progress=False, overwrite=True)
    assert sorted(p.name for p in (out / "depth").iterdir()) == ["frame-000000.png", "frame-000001.png"]


# --------------------------------------------------------------------------------------------------- CLI


@pytest.fixture
def only_synth(monkeypatch):
    monkeypatch.setattr(cli, "SUBCOMMANDS", ("synth",))


def test_cli_synth(only_synth, tmp_path, capsys):
    out = tmp_path / "cli_00"
    code = cli.main(
        [
            "synth",
            str(out),
            "--seed",
            "3",
            "--objects",
            "5",
            "--frames",
            "4",
            "--size",
            "64x48",
            "--room",
            "4x4x2.5",
            "--no-noise",
            "--no-progress",
        ]
    )
    assert code == 0
    assert "5 objects" in capsys.readouterr().out
    params = json.loads((out / "synthesis.json").read_text())
    assert params["room_size"] == [4.0, 4.0, 2.5] and params["image_size"] == [64, 48]
    assert len(list((out / "color").glob("*.jpg"))) == 4
    assert cv2.imread(str(out / "color" / "frame-000000.jpg")).shape == (48, 64, 3)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--room", "4x4"], "--room '4x4'"),
        (["--size", "64"], "--size '64'"),
        (["--objects", "0"], "--objects 0"),
        (["--frames", "0"], "--frames 0"),
        (["--room", "2x2x2.4", "--objects", "30"], "could place only"),
    ],
)
def test_cli_synth_bad_arguments_are_one_line_errors(only_synth, tmp_path, capsys, args, message):
    code = cli.main(["synth", str(tmp_path / "bad_00"), "--quiet", *args])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1


def test_cli_synth_help(only_synth, capsys):
    with pytest.raises(SystemExit):
        cli.main(["synth", "--help"])
    out = capsys.readouterr().out
    for option in ("--seed", "--objects", "--frames", "--room", "--size", "--no-noise", "--overwrite"):
        assert option in out
