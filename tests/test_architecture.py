"""The layers of the code (`.importlinter`): apps <- runner <- io / evaluation / simulation / baselines /
detectors <- mapper <- pipeline <- instances <- engine <- base; io never imports the engine."""

from __future__ import annotations

import configparser
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


#: Modules allowed over `MAX_MODULE_LINES`, each with its reason.
OVER_LENGTH_ALLOWED: set[str] = set()
MAX_MODULE_LINES = 700


def _modules() -> list[Path]:
    return sorted([*(ROOT / "fmfusion_jax").rglob("*.py"), *(ROOT / "detectors").rglob("*.py")])


def test_no_import_cycles_between_files():
    """The file-level import graph (every import, also inside functions and under TYPE_CHECKING) has no cycle:
    a cycle means two files hold one concern between them, or a shared piece sits in the wrong one."""
    import grimp

    graph = grimp.build_graph("fmfusion_jax", "detectors")
    edges = {m: graph.find_modules_directly_imported_by(m) for m in graph.modules}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(module: str) -> None:  # Tarjan's strongly connected components
        index[module] = low[module] = len(index)
        stack.append(module)
        on_stack.add(module)
        for other in edges[module]:
            if other not in index:
                visit(other)
                low[module] = min(low[module], low[other])
            elif other in on_stack:
                low[module] = min(low[module], index[other])
        if low[module] == index[module]:
            component = []
            while True:
                other = stack.pop()
                on_stack.discard(other)
                component.append(other)
                if other == module:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for module in sorted(edges):
        if module not in index:
            visit(module)
    assert not cycles, f"import cycles between files: {cycles}"


def test_no_module_is_too_long():
    """A module over `MAX_MODULE_LINES` lines holds several concerns: split it (the allow-list says why not yet)."""
    long = {str(path.relative_to(ROOT)): n for path in _modules() if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES}
    assert set(long) <= OVER_LENGTH_ALLOWED, {k: v for k, v in long.items() if k not in OVER_LENGTH_ALLOWED}


def test_the_layers_cover_every_module():
    """Every top-level module and package of fmfusion_jax sits on a layer of the layers contract."""
    config = configparser.ConfigParser()
    config.read(ROOT / ".importlinter")
    layers = config["importlinter:contract:layers"]["layers"]
    named = {name.strip() for line in layers.splitlines() for name in line.split(":") if name.strip()}
    package = ROOT / "fmfusion_jax"
    top = {
        f"fmfusion_jax.{path.stem if path.is_file() else path.name}"
        for path in package.iterdir()
        if (path.suffix == ".py" and path.name != "__init__.py") or (path / "__init__.py").is_file()
    }
    assert top - named == set(), f"not on any layer of .importlinter: {sorted(top - named)}"


def test_the_apps_are_independent():
    """Every app (a module or package of fmfusion_jax/apps) is in the independence contract."""
    config = configparser.ConfigParser()
    config.read(ROOT / ".importlinter")
    listed = set(config["importlinter:contract:apps-independent"]["modules"].split())
    apps = ROOT / "fmfusion_jax" / "apps"
    found = {
        f"fmfusion_jax.apps.{path.stem if path.is_file() else path.name}"
        for path in apps.iterdir()
        if (path.suffix == ".py" and path.name != "__init__.py") or (path / "__init__.py").is_file()
    }
    assert found == listed
