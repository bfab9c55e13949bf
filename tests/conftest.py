"""Shared fixtures. The real ScanNet scene is read from ../shared beside the repository, never copied."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_SCANNET = Path(os.environ.get("FMFUSION_SCANNET_DIR", REPO_ROOT.parent / "shared" / "data" / "scannet"))


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
