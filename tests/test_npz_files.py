"""`.npz` files deflated by ISA-L are ordinary zip archives: NumPy and zipfile read them back exactly."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from fmfusion_jax import npz_files
from fmfusion_jax.npz_files import isal_level, write_npz

ARRAYS = st.lists(
    hnp.arrays(
        st.sampled_from([np.float32, np.float16, np.int16, np.uint8, np.bool_]),
        hnp.array_shapes(min_dims=0, max_dims=3, max_side=40),
    ),
    min_size=1,
    max_size=4,
)


@settings(max_examples=25, deadline=None)
@given(arrays=ARRAYS, level=st.sampled_from([0, 1, 5, 9]))
def test_written_arrays_read_back_exactly(tmp_path_factory, arrays, level):
    path = tmp_path_factory.mktemp("npz") / "a.npz"
    write_npz(path, [(f"a{i}", a) for i, a in enumerate(arrays)], compresslevel=level)
    with zipfile.ZipFile(path) as archive:
        assert archive.testzip() is None  # every entry's CRC checks out
    with np.load(path, allow_pickle=False) as data:
        assert data.files == [f"a{i}" for i in range(len(arrays))]
        for i, a in enumerate(arrays):
            np.testing.assert_array_equal(data[f"a{i}"], a)
            assert data[f"a{i}"].dtype == a.dtype


def test_isal_deflates_a_map_sized_array_as_well_as_zlib(tmp_path):
    """The swapped compressor really runs (a stored entry would be as large as the data) and keeps zlib's ratio."""
    pytest.importorskip("isal", reason="isal not installed: the files are deflated by zlib")
    rng = np.random.default_rng(0)
    tsdf = np.where(rng.random((4000, 512)) < 0.5, 1.0, rng.normal(0, 0.3, (4000, 512))).astype(np.float32)
    path = write_npz(tmp_path / "isal.npz", [("tsdf", tsdf)])
    np.savez_compressed(tmp_path / "zlib.npz", tsdf=tsdf)
    with zipfile.ZipFile(path) as archive:
        entry = archive.getinfo("tsdf.npy")
    assert entry.compress_type == zipfile.ZIP_DEFLATED
    assert entry.compress_size < 0.8 * entry.file_size
    assert entry.compress_size < 1.1 * zipfile.ZipFile(tmp_path / "zlib.npz").getinfo("tsdf.npy").compress_size
    with np.load(path) as data:
        np.testing.assert_array_equal(data["tsdf"], tsdf)


def test_without_isal_zlib_writes_the_same_arrays(tmp_path, monkeypatch):
    monkeypatch.setattr(npz_files, "isal_zlib", None)
    assert isal_level(1) is None
    values = np.arange(1000, dtype=np.float32)
    write_npz(tmp_path / "z.npz", [("v", values)])
    with np.load(tmp_path / "z.npz") as data:
        np.testing.assert_array_equal(data["v"], values)


def test_isal_levels_follow_zlib_levels():
    pytest.importorskip("isal", reason="isal not installed")
    assert [isal_level(level) for level in range(10)] == [None, 1, 1, 1, 2, 2, 2, 3, 3, 3]


def test_object_arrays_are_refused(tmp_path):
    with pytest.raises(ValueError, match="no pickle"):
        write_npz(tmp_path / "o.npz", [("o", np.array([{}, 1], dtype=object))])
