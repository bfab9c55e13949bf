"""The registry of output writers (`run/outputs.py`) is what the README, `fmfusion run --help`, the output
names cleared before a run and the end-of-run summary say."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from fmfusion_jax.run.outputs import OUTPUT_NAMES, OUTPUT_WRITERS, listed_outputs, outputs_help, select_writers

README = Path(__file__).resolve().parents[1] / "README.md"


def readme_rows() -> list[tuple[list[str], str]]:
    """The rows of the README's outputs table: (the files of the first cell, the content cell)."""
    text = README.read_text()
    section = text[text.index("## Outputs of `fmfusion run`") :]
    table = section[section.index("| file | content |") :].split("\n\n", 1)[0].splitlines()[2:]
    rows = []
    for line in table:
        files, content = line.strip("|").split("|", 1)
        rows.append((re.findall(r"`([^`]+)`", files), content.strip(" |")))
    return rows


def test_the_readme_table_has_one_row_per_writer_in_registry_order():
    rows = readme_rows()
    assert [files for files, _ in rows] == [list(writer.files) for writer in OUTPUT_WRITERS], (
        "README's outputs table differs from run/outputs.py's OUTPUT_WRITERS: one row per writer, in order "
        "(`python -c 'from fmfusion_jax.run.outputs import readme_table; print(readme_table())'` prints it)"
    )
    assert [content for _, content in rows] == [writer.description for writer in OUTPUT_WRITERS]


def test_names_help_and_cleared_files_come_from_the_registry():
    names = [writer.name for writer in OUTPUT_WRITERS]
    assert len(set(names)) == len(names)
    files = [file.rstrip("/") for writer in OUTPUT_WRITERS for file in writer.files]
    assert len(set(files)) == len(files) and tuple(files) == OUTPUT_NAMES
    assert all(file in outputs_help() for writer in OUTPUT_WRITERS for file in writer.files)
    assert OUTPUT_WRITERS[-1].name == "run.json"  # it holds every other writer's time
    ranks = [writer.listed for writer in OUTPUT_WRITERS if writer.listed is not None]
    assert sorted(ranks) == list(range(1, len(ranks) + 1))


def test_a_subset_is_chosen_by_name_in_registry_order():
    assert [w.name for w in select_writers(["run.json", "config.yaml"])] == ["config.yaml", "run.json"]
    with pytest.raises(ValueError, match="unknown outputs nope"):
        select_writers(["nope"])


def test_the_summary_names_the_listed_files_present_in_its_order(tmp_path):
    for name in ("run.json", "mesh.ply", "overview.png", "config.yaml", "explain.md"):
        (tmp_path / name).write_text("")
    assert listed_outputs(tmp_path) == ["overview.png", "mesh.ply", "run.json", "explain.md"]


def test_steps_run_after_their_inputs_and_a_missing_input_is_an_error():
    """`_run_steps`: a step starts only once its inputs are done, whatever the threads; a step waiting for one that
    is not there fails at once (it never spins)."""
    import threading
    import time

    from fmfusion_jax.run.outputs import _run_steps

    finished: list[str] = []
    lock = threading.Lock()

    def step(name: str, seconds: float):
        def run():
            time.sleep(seconds)
            with lock:
                finished.append(name)

        return run

    steps = {
        "slow": (step("slow", 0.05), ()),
        "after_slow": (step("after_slow", 0.0), ("slow",)),
        "fast": (step("fast", 0.0), ()),
        "after_both": (step("after_both", 0.0), ("after_slow", "fast")),
    }
    seconds = _run_steps(steps, threads=2)
    assert set(seconds) == set(steps)
    assert finished.index("slow") < finished.index("after_slow") < finished.index("after_both")
    assert finished.index("fast") < finished.index("after_both")
    with pytest.raises(RuntimeError, match="never run"):
        _run_steps({"orphan": (step("orphan", 0.0), ("absent",))}, threads=2)


def test_given_instances_are_written_without_a_fused_map(tmp_path):
    """A context with instances given (a baseline's: no fused map) writes the writers that need no map."""
    import types

    from fmfusion_jax.labels import load_label_sets
    from fmfusion_jax.run.outputs import OutputContext, write_files

    context = OutputContext(types.SimpleNamespace(name="given"), tmp_path, None, load_label_sets(), [])
    write_files(context, names=("instances.json", "semantic.ply", "scene_graph.json"))
    assert {"instances.json", "semantic.ply", "scene_graph.json"} <= {p.name for p in tmp_path.iterdir()}
