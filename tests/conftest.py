"""Shared fixtures. The real ScanNet scene is read from ../shared beside the repository, never copied."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

import pytest

# The `fmfusion` commands the tests run, in this process and as subprocesses, share one persistent compile
# cache in a temporary folder (never the user's): each step compiles once per suite, not once per command.
if "FMFUSION_COMPILE_CACHE" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="fmfusion-test-xla-")
    os.environ["FMFUSION_COMPILE_CACHE"] = _cache
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_SCANNET = Path(os.environ.get("FMFUSION_SCANNET_DIR", REPO_ROOT.parent / "shared" / "data" / "scannet"))


@pytest.fixture
def cache_home(tmp_path, monkeypatch) -> Path:
    """The user cache (`XDG_CACHE_HOME`: extracted recordings) in the test's temporary folder, never the user's."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache"


@pytest.fixture(scope="session")
def scannet_root() -> Path:
    """`../shared/data/scannet` (or $FMFUSION_SCANNET_DIR); skips the test when it is absent."""
    if not (SHARED_SCANNET / "scene0000_00").is_dir():
        pytest.skip(
            f"ScanNet sample not found at {SHARED_SCANNET} (it is never part of the repo; "
            "set FMFUSION_SCANNET_DIR to a folder holding scene0000_00)"
        )
    return SHARED_SCANNET


@pytest.fixture(scope="session")
def scannet_scene(scannet_root: Path) -> Path:
    """The real scene `scene0000_00` (skips when absent)."""
    return scannet_root / "scene0000_00"
