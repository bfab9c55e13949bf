"""Record3D exports (`io.record3d`, the `record3d` extra): a generated room in the ScanNet layout written as a ``.r3d``
(colour at twice the depth size as JPEG, LZFSE float32 depth with NaN holes, confidence maps, ARKit poses) reads
back as the ScanNet scene does and builds the same map; ARKit's camera and world conventions; the confidence
threshold; the extraction cache; the bad exports' errors, from Python and from the CLI."""

from __future__ import annotations

import builtins
import json
import logging
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from test_recordings import HEIGHT, NUM_FRAMES, WIDTH, Frames, bed_and_table_room, frames_of, tiny_frames

import fmfusion_jax.cli as cli
from fmfusion_jax.errors import DataError, UserError
from fmfusion_jax.io.record3d import camera_poses, depth_camera, infer_depth_size, parse_metadata
from fmfusion_jax.io.scene import detect_layout, open_scene

liblzfse = pytest.importorskip(
    "liblzfse", reason='pyliblzfse is not installed (the record3d extra: pip install -e ".[record3d]")'
)

#: Our +z-up world -> ARKit's +y-up world (written here independently of the reader's constants).
ARKIT_FROM_OURS = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
#: OpenCV camera axes <-> OpenGL's (its own inverse).
FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])


pytestmark = pytest.mark.usefixtures("cache_home")  # the recording cache in a temporary folder


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    return bed_and_table_room(tmp_path_factory.mktemp("record3d"), "synth0005_00")


@pytest.fixture(scope="module")
def frames(room) -> Frames:
    return frames_of(room)


def r3d_members(frames: Frames, color_scale: int = 2, confidence: np.ndarray | None = None) -> dict[str, bytes]:
    """The members of a Record3D export of `frames`: colour `color_scale` times the depth size (JPEG), depth as
    LZFSE float32 metres (NaN where the millimetres are 0), `confidence` `(N, H, W)` uint8 (None: no .conf files),
    poses in ARKit's conventions, K of the colour camera (column-major)."""
    K, s = frames.intrinsics, color_scale
    height, width = frames.depths_mm.shape[1:]
    members: dict[str, bytes] = {}
    poses = []
    for i in range(len(frames.poses)):
        big = np.repeat(np.repeat(frames.colors[i], s, axis=0), s, axis=1)
        ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(big, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
        members[f"rgbd/{i}.jpg"] = jpeg.tobytes()
        metres = frames.depths_mm[i].astype(np.float32) / np.float32(1000.0)
        metres[frames.depths_mm[i] == 0] = np.nan
        members[f"rgbd/{i}.depth"] = liblzfse.compress(metres.tobytes())
        if confidence is not None:
            members[f"rgbd/{i}.conf"] = liblzfse.compress(np.ascontiguousarray(confidence[i], np.uint8).tobytes())
        T = ARKIT_FROM_OURS @ frames.poses[i] @ FLIP_YZ
        poses.append([*Rotation.from_matrix(T[:3, :3]).as_quat(), *T[:3, 3]])
    # the colour camera: the depth camera scaled up (pixel centres at integers: c = (c' + 0.5) s - 0.5)
    fx, fy, cx, cy = K.fx * s, K.fy * s, (K.cx + 0.5) * s - 0.5, (K.cy + 0.5) * s - 0.5
    metadata = {
        "w": width * s,
        "h": height * s,
        "K": [fx, 0.0, 0.0, 0.0, fy, 0.0, cx, cy, 1.0],
        "fps": 30,
        "dw": width,
        "dh": height,
        "poses": [[float(x) for x in pose] for pose in poses],
        "initPose": [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        "frameTimestamps": [i / 30 for i in range(len(poses))],
        "cameraType": 1,
    }
    members["metadata"] = json.dumps(metadata).encode()
    members["icon"] = b"\x89PNG not read"
    return members


def write_r3d(members: dict[str, bytes], path: Path) -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return path


def write_unzipped(members: dict[str, bytes], folder: Path) -> Path:
    for name, data in members.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(data)
    return folder


def _metadata(members: dict[str, bytes], **changes) -> dict[str, bytes]:
    """`members` with the metadata's keys changed (a value None removes the key)."""
    metadata = json.loads(members["metadata"])
    metadata.update(changes)
    members["metadata"] = json.dumps({k: v for k, v in metadata.items() if v is not None}).encode()
    return members


# --------------------------------------------------------------------------------------------------
# An export reads back as the ScanNet layout of the same room, and maps the same.


def test_an_export_reads_back_as_the_scannet_scene(room, frames, tmp_path, cache_home, caplog):
    confidence = np.full(frames.depths_mm.shape, 2, np.uint8)
    confidence[:, :4] = 0  # the top rows low: dropped by default
    confidence[:, 4:8] = 1  # the next ones medium: kept by default
    export = write_r3d(r3d_members(frames, confidence=confidence), tmp_path / "room.r3d")
    assert detect_layout(export) == "record3d"
    with caplog.at_level(logging.INFO, logger="fmfusion_jax.io.record3d"):
        scene = open_scene(export, depth_max=10.0)
    reference = open_scene(room, depth_max=10.0)
    assert scene.layout == "record3d" and len(scene) == NUM_FRAMES and not scene.skipped and scene.depth_scale == 1000.0
    assert scene.frame_names == reference.frame_names  # frame-000000, ...: the ScanNet copy's detections apply
    np.testing.assert_allclose(_camera(scene), _camera(reference), atol=1e-9)
    assert (scene.intrinsics.width, scene.intrinsics.height) == (WIDTH, HEIGHT)
    np.testing.assert_allclose(scene.poses(), reference.poses(), atol=1e-6)
    for i in (0, 5, NUM_FRAMES - 1):
        ours, theirs = scene.read_frame(i), reference.read_frame(i)
        assert not ours.depth[:4].any()
        np.testing.assert_allclose(ours.depth[4:], theirs.depth[4:], atol=1e-6, rtol=0)
        assert ours.color.shape == theirs.color.shape  # the 320x240 JPEG resized to the depth size
        assert np.abs(ours.color.astype(int) - theirs.color).mean() < 3
    assert "extracting 12 frames (160x120 depth)" in caplog.text
    # extracted once into the cache, never beside the export; the next open reads the cache
    assert len(list((cache_home / "fmfusion-jax" / "recordings").iterdir())) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache", export.name]
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="fmfusion_jax.io.record3d"):
        again = open_scene(export, stride=3)
    assert "from the cache" in caplog.text and "extracting" not in caplog.text
    np.testing.assert_allclose(again.poses(), reference.poses()[::3], atol=1e-6)
    # the confidence threshold: 0 keeps every pixel, 2 only the high ones (each its own extraction)
    everything, high = open_scene(export, depth_max=10.0, min_depth_confidence=0), open_scene(export, min_depth_confidence=2)
    np.testing.assert_allclose(everything.read_depth(5), reference.read_depth(5), atol=1e-6, rtol=0)
    assert not high.read_depth(5)[:8].any() and high.read_depth(5)[8:].any()
    assert len(list((cache_home / "fmfusion-jax" / "recordings").iterdir())) == 3


def _camera(scene) -> list[float]:
    K = scene.intrinsics
    return [K.fx, K.fy, K.cx, K.cy]


def test_an_unzipped_export_and_an_old_one_without_depth_size(frames, tmp_path):
    members = r3d_members(Frames(frames.colors[:3], frames.depths_mm[:3], frames.poses[:3], frames.intrinsics))
    folder = write_unzipped(members, tmp_path / "unzipped")
    assert detect_layout(folder) == "record3d"
    scene = open_scene(folder)
    np.testing.assert_allclose(scene.poses(), frames.poses[:3], atol=1e-6)
    assert scene.frame_names == ["frame-000000", "frame-000001", "frame-000002"]
    old = open_scene(write_r3d(_metadata(members, dw=None, dh=None, frameTimestamps=None), tmp_path / "old.r3d"))
    assert old.intrinsics == scene.intrinsics
    assert infer_depth_size(256 * 192, (1920, 1440)) == (256, 192) and infer_depth_size(192 * 256, (720, 960)) == (192, 256)
    assert infer_depth_size(1000, (1920, 1440)) is None


def test_the_same_map_as_the_scannet_layout(room, frames, tmp_path):
    """The Mapper over the export's frames builds the map it builds from the ScanNet layout (the detections are
    keyed by the same frame names)."""
    from fmfusion_jax.io.detections import DetectionFolder
    from fmfusion_jax.mapping.mapper import Mapper
    from fmfusion_jax.simulation.demo_setup import demo_config

    confidence = np.full(frames.depths_mm.shape, 2, np.uint8)
    export = write_r3d(r3d_members(frames, confidence=confidence), tmp_path / "room.r3d")
    folder = DetectionFolder(room.parent / "detections", image_shape=(HEIGHT, WIDTH))
    results = []
    for path in (room, export):
        scene = open_scene(path)
        mapper = Mapper(demo_config(NUM_FRAMES, WIDTH, HEIGHT), bounds=scene.bounds())
        for frame in scene.frames():
            mapper.integrate(frame, folder.get(frame.name))
        mapper.finalize()
        results.append((len(mapper.instances()), mapper.extract_point_cloud()[0]))
    (count, points), (r3d_count, r3d_points) = results
    assert count >= 2 and r3d_count == count
    assert r3d_points.shape == points.shape
    distances, _ = cKDTree(points).query(r3d_points)
    assert distances.max() < 1e-4  # the TUM copy's tolerance (test_recordings); measured: 1e-5 m at most, median 0


# --------------------------------------------------------------------------------------------------
# ARKit's conventions.


def test_arkit_poses_become_opencv_cameras_in_a_z_up_world():
    """A level ARKit camera at (1, 2, 3) looking along ARKit's -z (identity rotation): our camera's x is the world's
    x, its y (down) the world's -z, its z (forward) the world's +y; ARKit's height y becomes our z."""
    pose = camera_poses(np.array([[0.0, 0.0, 0.0, 1.0, 1.0, 2.0, 3.0]]), "test")[0]
    np.testing.assert_allclose(pose[:3, :3], [[1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-12)
    np.testing.assert_allclose(pose[:3, 3], [1.0, -3.0, 2.0])
    # a camera turned 90 degrees to its left about ARKit's up axis (+y) looks along ARKit's -x: our world's -x
    turned = Rotation.from_euler("y", 90, degrees=True).as_quat()
    pose = camera_poses(np.array([[*turned, 0.0, 0.0, 0.0]]), "test")[0]
    np.testing.assert_allclose(pose[:3, 2], [-1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(pose[:3, 1], [0.0, 0.0, -1.0], atol=1e-12)
    lost = camera_poses(np.array([[np.nan] * 7]), "test")
    assert np.isnan(lost).all()  # a non-finite pose: the frame is skipped


# --------------------------------------------------------------------------------------------------
# Bad and partial exports.


def _drop(name: str):
    def drop(members: dict[str, bytes]) -> dict[str, bytes]:
        del members[name]
        return members

    return drop


def _replace(name: str, data: bytes):
    def replace(members: dict[str, bytes]) -> dict[str, bytes]:
        members[name] = data
        return members

    return replace


def _wrong_depth_size(members):
    members["rgbd/2.depth"] = liblzfse.compress(np.zeros((10, 10), np.float32).tobytes())
    return members


@pytest.mark.parametrize(
    "break_it, message",
    [
        (_drop("metadata"), r"no metadata file"),
        (_replace("metadata", b"{"), r"metadata: not JSON"),
        (lambda m: _metadata(m, K=None), r"metadata: no 'K'"),
        (lambda m: _metadata(m, K=[1, 2, 3]), r'"K" must hold 9 numbers'),
        (lambda m: _metadata(m, poses=json.loads(m["metadata"])["poses"][:3]), r"metadata holds 3 poses for 4 frames"),
        (lambda m: _metadata(m, poses=[[0, 0, 0, 0, 0, 0, 0]] * 4), r"pose 0: the quaternion \(qx qy qz qw\) is zero"),
        (lambda m: _metadata(m, poses=[[0, 0, 1]] * 4), r'"poses" must be a non-empty list of \[qx, qy, qz, qw, tx, ty, tz\]'),
        (_drop("rgbd/2.depth"), r"rgbd/2.depth missing \(1 of 4 frames lack their depth image\)"),
        (_drop("rgbd/1.jpg"), r"rgbd/1.jpg missing \(1 of 4 frames lack their colour image\)"),
        (_wrong_depth_size, r"rgbd/2.depth: 400 bytes decompressed, expected a 32x24 float32 image"),
        (_replace("rgbd/1.depth", b"not lzfse"), r"rgbd/1.depth: not LZFSE-compressed"),
        (_replace("rgbd/3.jpg", b"\xff\xd8 cut short"), r"rgbd/3.jpg: not a complete JPEG"),
        (lambda m: _metadata(m, w=128, h=96), r"rgbd/0.jpg is 64x48, but the metadata's \"w\", \"h\" say 128x96"),
        (lambda m: _metadata(m, dw=24, dh=32), r"the depth size 24x32 .* aspects differ"),
        (lambda m: _metadata(m, w="64"), r'"w" and "h" must be positive integers'),
    ],
)
def test_a_bad_export_is_a_named_error_and_leaves_no_cache(tmp_path, cache_home, break_it, message):
    members = break_it(r3d_members(tiny_frames(4)))
    export = write_r3d(members, tmp_path / "bad.r3d")
    with pytest.raises(DataError, match=message) as raised:
        open_scene(export)
    assert str(raised.value).startswith(f"{export}: ")
    recordings = cache_home / "fmfusion-jax" / "recordings"
    assert not recordings.exists() or not any(recordings.iterdir())


_json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-5, 300), st.floats(), st.text(max_size=8)),
    lambda children: st.one_of(st.lists(children, max_size=9), st.dictionaries(st.text(max_size=4), children, max_size=3)),
    max_leaves=30,
)


@settings(max_examples=150, deadline=None)
@given(changes=st.dictionaries(st.sampled_from(["w", "h", "K", "poses", "dw", "dh", "frameTimestamps"]), _json_values))
def test_fuzzed_metadata_reads_or_is_a_named_error(changes):
    """Whatever the metadata's values, its reading (and the camera and poses made of it) returns or raises the
    project's `DataError` naming the file; never another exception."""
    members = _metadata(r3d_members(tiny_frames(2)), **{key: value for key, value in changes.items() if value is not None})
    try:
        meta = parse_metadata(members["metadata"], "REC.r3d: metadata")
        depth_camera(meta.K, meta.color_size, meta.depth_size or meta.color_size, "REC.r3d: metadata")
        camera_poses(meta.poses, "REC.r3d: metadata")
    except DataError as error:
        assert str(error).startswith("REC.r3d: metadata: "), error


def test_a_file_that_is_no_zip_and_a_forced_layout(tmp_path):
    export = tmp_path / "broken.r3d"
    export.write_bytes(b"PK not really")
    with pytest.raises(DataError, match=r"broken.r3d: not a ZIP archive"):
        open_scene(export)
    with pytest.raises(UserError, match=r"a Record3D export, but the layout asked for is 'tum'"):
        open_scene(export, layout="tum")


def test_without_pyliblzfse_the_error_says_how_to_install(tmp_path, monkeypatch):
    export = write_r3d(r3d_members(tiny_frames(2)), tmp_path / "room.r3d")
    real_import = builtins.__import__

    def no_lzfse(name, *args, **kwargs):
        if name == "liblzfse":
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_lzfse)
    with pytest.raises(UserError, match=r'pyliblzfse package: pip install -e "\.\[record3d\]"'):
        open_scene(export)


# --------------------------------------------------------------------------------------------------
# The commands.


def test_fmfusion_info_and_run_on_an_export(room, frames, tmp_path, capsys):
    export = write_r3d(r3d_members(frames), tmp_path / "room.r3d")
    assert cli.main(["info", str(export)]) == 0
    printed = capsys.readouterr().out
    assert "layout        record3d" in printed and f"{NUM_FRAMES} usable" in printed
    config = tmp_path / "demo.yaml"
    from fmfusion_jax.simulation.demo_setup import demo_config

    demo = demo_config(NUM_FRAMES, WIDTH, HEIGHT).to_dict()
    demo["dataset"]["layout"] = "auto"  # the demo's is scannet
    config.write_text(yaml.safe_dump(demo))
    out = tmp_path / "out"
    detections = room.parent / "detections"
    argv = ["run", str(export), "--detections", str(detections), "--out", str(out), "--config", str(config), "--no-progress"]
    assert cli.main(argv) == 0, capsys.readouterr().err
    summary = json.loads((out / "run.json").read_text())
    assert summary["frames"] == NUM_FRAMES and summary["instances"] >= 2
    assert (out / "mesh.ply").is_file() and (out / "instances.json").is_file()


def test_a_bad_export_is_one_line_from_the_cli(tmp_path, capsys):
    members = r3d_members(tiny_frames(3))
    del members["rgbd/1.depth"]
    export = write_r3d(members, tmp_path / "partial.r3d")
    assert cli.main(["info", str(export)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1 and "rgbd/1.depth missing" in err
    assert cli.main(["run", str(export), "--out", str(tmp_path / "out"), "--set", "dataset.layout=scannet"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "a Record3D export, but the layout asked for is 'scannet'" in err
