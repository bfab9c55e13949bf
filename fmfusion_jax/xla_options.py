"""XLA options the `fmfusion` commands set for the process before JAX starts a backend.

On a GPU the engine's steps hold `while` loops whose trip counts depend on the frame (the TSDF's touched
blocks, the census' changed cells, the merge's renamed cells). By default XLA runs such a loop from the
host: each iteration reads its condition back from the device, so the host waits for the GPU once per
iteration (~30 times a frame) and cannot queue the next kernels meanwhile. With `WHILE` and `CONDITIONAL`
among XLA's command-buffer types, the loops run as CUDA graphs with conditional nodes, on the device. On
an H100 the as-run whole frame of `scene0000_00` went from 7.26 to 6.27 ms median (mean 8.74 to 6.79 ms;
one run of each on the same machine, docs/benchmark.md). The CPU ignores these options.

`enable_gpu_command_buffers()` adds the option to `XLA_FLAGS` (this process and those it starts) where JAX
has a GPU plugin installed, unless the user's `XLA_FLAGS` already set `--xla_gpu_enable_command_buffer`, the
installed jaxlib is outside the versions it was checked with (an XLA that does not know the option or one of
its values stops the process at startup), or a backend has already started (then it would not take effect).
The Python API leaves `XLA_FLAGS` to the caller: call `enable_gpu_command_buffers()` (or set the option) before
the first JAX computation.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import pkgutil
import sys
from importlib import metadata

log = logging.getLogger(__name__)

#: XLA's command-buffer types: fusions, cuBLAS, cuDNN and custom calls (as XLA records them by default), plus the
#: loops and conditionals.
GPU_COMMAND_BUFFER_TYPES = "FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL"
GPU_COMMAND_BUFFER_FLAG = f"--xla_gpu_enable_command_buffer={GPU_COMMAND_BUFFER_TYPES}"
#: The jaxlib releases (major, minor) whose XLA was seen to accept the flag, from the first to the one after the last
#: (0.10.2 parses it, 0.11.2 ran it on an H100).
CHECKED_JAXLIB = ((0, 10), (0, 12))


def _jaxlib_version() -> tuple[int, ...] | None:
    try:
        release = metadata.version("jaxlib").split("+")[0]
        return tuple(int(part) for part in release.split(".")[:2])
    except (metadata.PackageNotFoundError, ValueError):
        return None


def _gpu_plugin_installed() -> bool:
    """Whether a JAX GPU plugin is installed (`jax_plugins.xla_cuda12`, `xla_cuda13`, `xla_rocm...`: the namespace
    JAX finds its plugins in): CPU-only installs never see the option. Looks at one folder, not at every installed
    distribution (which took 30-60 ms at each command's start)."""
    spec = importlib.util.find_spec("jax_plugins")
    if spec is None or not spec.submodule_search_locations:
        return False
    return any(name.startswith(("xla_cuda", "xla_rocm")) for _, name, _ in pkgutil.iter_modules(spec.submodule_search_locations))


def _backend_started() -> bool:
    if "jax" not in sys.modules:
        return False
    try:
        # private: JAX has no public way to ask this; lazy: JAX (`fmfusion --help` imports this module)
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):
        return False


def enable_gpu_command_buffers(jaxlib_version: tuple[int, ...] | None = None) -> str | None:
    """Adds `GPU_COMMAND_BUFFER_FLAG` to `XLA_FLAGS` where it can take effect safely; returns the flag added,
    or None (with the reason at debug level) when it leaves `XLA_FLAGS` as it is. `jaxlib_version` (major,
    minor) stands in for the installed jaxlib's (tests)."""
    current = os.environ.get("XLA_FLAGS", "")
    version = jaxlib_version if jaxlib_version is not None else _jaxlib_version()
    first, after_last = CHECKED_JAXLIB
    if "xla_gpu_enable_command_buffer" in current:
        reason = "XLA_FLAGS already sets --xla_gpu_enable_command_buffer"
    elif version is None or not first <= tuple(version[:2]) < after_last:
        reason = f"jaxlib {'.'.join(map(str, version)) if version else '(version unknown)'} is not known to accept it"
    elif not _gpu_plugin_installed():
        reason = "no JAX GPU plugin is installed"
    elif _backend_started():
        reason = "a JAX backend has already started"
    else:
        os.environ["XLA_FLAGS"] = f"{current} {GPU_COMMAND_BUFFER_FLAG}".strip()
        return GPU_COMMAND_BUFFER_FLAG
    log.debug("GPU command buffers for loops left as XLA has them: %s", reason)
    return None


__all__ = ["CHECKED_JAXLIB", "GPU_COMMAND_BUFFER_FLAG", "GPU_COMMAND_BUFFER_TYPES", "enable_gpu_command_buffers"]
