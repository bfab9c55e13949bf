"""The XLA options `fmfusion` sets before JAX starts a backend (`fmfusion_jax.xla_options`)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from fmfusion_jax import xla_options
from fmfusion_jax.apps.bench.report import _flags_worth_naming
from fmfusion_jax.xla_options import GPU_COMMAND_BUFFER_FLAG, enable_gpu_command_buffers


@pytest.fixture
def no_backend(monkeypatch):
    """A process with a JAX GPU plugin installed whose backend has not started yet."""
    monkeypatch.setattr(xla_options, "_backend_started", lambda: False)
    monkeypatch.setattr(xla_options, "_gpu_plugin_installed", lambda: True)


def test_the_gpu_loops_option_is_added_beside_the_users_flags(monkeypatch, no_backend):
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/tmp/nowhere")
    assert enable_gpu_command_buffers(jaxlib_version=(0, 11)) == GPU_COMMAND_BUFFER_FLAG
    assert os.environ["XLA_FLAGS"] == f"--xla_dump_to=/tmp/nowhere {GPU_COMMAND_BUFFER_FLAG}"
    monkeypatch.delenv("XLA_FLAGS")
    assert enable_gpu_command_buffers(jaxlib_version=(0, 10)) == GPU_COMMAND_BUFFER_FLAG
    assert os.environ["XLA_FLAGS"] == GPU_COMMAND_BUFFER_FLAG


@pytest.mark.parametrize(
    ("flags", "version"),
    [
        ("--xla_gpu_enable_command_buffer=", (0, 11)),  # the user's own choice (here: no command buffers) stays
        ("--xla_gpu_enable_command_buffer=FUSION --xla_dump_to=/tmp/x", (0, 11)),
        ("", (0, 4)),  # an older XLA might not know WHILE or CONDITIONAL and would stop the process
        ("", (0, 12)),  # a newer one might have dropped or renamed the option
        ("", None),  # jaxlib's version unknown
    ],
)
def test_the_option_is_left_out_where_it_could_override_or_break(monkeypatch, no_backend, flags, version):
    monkeypatch.setenv("XLA_FLAGS", flags)
    monkeypatch.setattr(xla_options, "_jaxlib_version", lambda: None)
    assert enable_gpu_command_buffers(jaxlib_version=version) is None
    assert os.environ["XLA_FLAGS"] == flags


def test_the_option_is_left_out_without_a_gpu_plugin(monkeypatch, no_backend):
    monkeypatch.setattr(xla_options, "_gpu_plugin_installed", lambda: False)  # a CPU-only install: never touched
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/tmp/x")
    assert enable_gpu_command_buffers(jaxlib_version=(0, 11)) is None
    assert os.environ["XLA_FLAGS"] == "--xla_dump_to=/tmp/x"


def test_the_option_is_left_out_once_a_backend_has_started(monkeypatch):
    import jax.numpy as jnp

    jnp.zeros(1).block_until_ready()  # a backend runs in this process now: the option would not take effect
    monkeypatch.setenv("XLA_FLAGS", "")
    assert enable_gpu_command_buffers(jaxlib_version=(0, 11)) is None
    assert os.environ["XLA_FLAGS"] == ""


def test_the_installed_xla_accepts_the_option_when_it_would_be_added():
    """XLA stops the process at startup on a flag value it does not know: check the installed one takes it."""
    version, (first, after_last) = xla_options._jaxlib_version(), xla_options.CHECKED_JAXLIB
    if version is None or not first <= version < after_last:
        pytest.skip(f"jaxlib {version} is outside the releases checked with the option: fmfusion does not add it")
    code = "import jax, jax.numpy as jnp; print(float(jax.jit(lambda x: x + 1)(jnp.ones(()))))"
    env = {**os.environ, "XLA_FLAGS": GPU_COMMAND_BUFFER_FLAG, "JAX_PLATFORMS": "cpu"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "2.0"


def test_bench_names_the_flags_that_matter_on_the_device_it_ran_on():
    assert _flags_worth_naming({"platform": "gpu", "xla_flags": GPU_COMMAND_BUFFER_FLAG})
    assert not _flags_worth_naming({"platform": "cpu", "xla_flags": GPU_COMMAND_BUFFER_FLAG})  # the CPU ignores it
    assert _flags_worth_naming({"platform": "cpu", "xla_flags": f"--xla_cpu_use_thunk_runtime=false {GPU_COMMAND_BUFFER_FLAG}"})
    assert not _flags_worth_naming({"platform": "gpu", "xla_flags": ""})


def test_a_gpu_plugin_is_found_in_jaxs_plugin_namespace(tmp_path, monkeypatch):
    (tmp_path / "jax_plugins" / "xla_cuda12").mkdir(parents=True)
    (tmp_path / "jax_plugins" / "xla_cuda12" / "__init__.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert xla_options._gpu_plugin_installed()
