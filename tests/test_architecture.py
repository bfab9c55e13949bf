"""The layers of the code (`.importlinter`): apps <- runner <- io / evaluation / simulation / baselines /
detectors <- mapper <- pipeline <- instances <- engine <- base; io never imports the engine."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_import_contracts_hold():
    lint_imports = shutil.which("lint-imports") or str(Path(sys.executable).parent / "lint-imports")
    if not Path(lint_imports).exists():
        pytest.fail("lint-imports is missing: install the test extras (pip install -e '.[test]')")
    done = subprocess.run([lint_imports, "--no-cache"], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    assert "0 broken" in done.stdout


def test_oracles_are_not_shipped():
    """NumPy oracles and test scenes live in tests/, not in the package."""
    assert not list((ROOT / "fmfusion_jax").rglob("reference*.py"))
