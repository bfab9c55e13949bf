"""The persistent compilation cache the `fmfusion` commands turn on: where it goes, how to turn it off, and
what happens when its folder cannot be made."""

from __future__ import annotations

import logging
import subprocess
import sys

import jax
import pytest

from fmfusion_jax import compile_cache


@pytest.fixture
def restore_jax_cache(monkeypatch):
    """Puts JAX's cache setting (and the environment) back as they were after the test."""
    before = jax.config.jax_compilation_cache_dir
    for name in ("JAX_COMPILATION_CACHE_DIR", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"):
        monkeypatch.delenv(name, raising=False)
    yield
    jax.config.update("jax_compilation_cache_dir", before)


def test_the_folder_comes_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(compile_cache.ENV, str(tmp_path / "xla"))
    assert compile_cache.compile_cache_dir() == tmp_path / "xla"
    for off in ("off", "0", "NO", "false"):
        monkeypatch.setenv(compile_cache.ENV, off)
        assert compile_cache.compile_cache_dir() is None
    monkeypatch.delenv(compile_cache.ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    assert compile_cache.compile_cache_dir() == tmp_path / "cache" / "fmfusion-jax" / "xla"


def test_enabling_sets_jax_and_the_environment_of_child_processes(restore_jax_cache, tmp_path, monkeypatch):
    monkeypatch.setenv(compile_cache.ENV, "off")
    assert compile_cache.enable_compile_cache() is None
    folder = compile_cache.enable_compile_cache(tmp_path / "xla")
    assert folder == tmp_path / "xla" and folder.is_dir()
    assert jax.config.jax_compilation_cache_dir == str(folder)
    child = subprocess.run(
        [sys.executable, "-c", "import jax; print(jax.config.jax_compilation_cache_dir)"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert child.stdout.strip() == str(folder)  # a process it starts (fmfusion batch's scenes) shares it


def test_a_folder_that_cannot_be_made_turns_it_off_with_a_warning(restore_jax_cache, tmp_path, caplog):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    with caplog.at_level(logging.WARNING, logger="fmfusion_jax.compile_cache"):
        assert compile_cache.enable_compile_cache(blocker / "xla") is None
    assert "compile cache off" in caplog.text and str(blocker / "xla") in caplog.text


def test_the_python_api_uses_the_cache_unless_the_process_chose_its_own(restore_jax_cache, tmp_path, monkeypatch):
    """A `Mapper` in a notebook loads the steps the commands compiled (same folder, same rule to turn it off),
    but a process that set a cache folder of its own keeps it."""
    from fmfusion_jax import Mapper

    monkeypatch.setenv(compile_cache.ENV, str(tmp_path / "ours"))
    jax.config.update("jax_compilation_cache_dir", None)
    Mapper("demo")
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "ours")
    jax.config.update("jax_compilation_cache_dir", str(tmp_path / "theirs"))
    Mapper("demo")
    assert jax.config.jax_compilation_cache_dir == str(tmp_path / "theirs")
    jax.config.update("jax_compilation_cache_dir", None)
    monkeypatch.setenv(compile_cache.ENV, "off")
    Mapper("demo")
    assert jax.config.jax_compilation_cache_dir is None
