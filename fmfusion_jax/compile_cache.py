"""JAX's persistent compilation cache, in one folder for every `fmfusion` process.

The engine's steps take seconds each to compile on a CPU, and compiling costs memory (LLVM's working set
stays in the process's resident memory). With the cache on, a process whose steps were compiled before,
by any earlier process with the same map layout, JAX and device, loads them instead: `fmfusion run` again
on a scene, or on another scene of the same layout, starts at once. The layout is `MapConfig.compiled_layout()`:
image size, capacities and the block index's shape (rounded up to buckets), not where the index lies (the
state holds that, docs/compile-sharing.md), so rooms of similar size share their steps. Entries are keyed
by the program, the compile options, the JAX version and the device, so a stale entry is never used.

The `fmfusion` commands turn it on (`enable_compile_cache()`), and so does the Python API (`Mapper`, `MapperBatch`)
unless the process chose a cache folder of its own.
`FMFUSION_COMPILE_CACHE=off` turns it off, `FMFUSION_COMPILE_CACHE=DIR` moves it (default:
`$XDG_CACHE_HOME/fmfusion-jax/xla`, i.e. `~/.cache/fmfusion-jax/xla`).
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

log = logging.getLogger(__name__)

#: The environment variable naming the cache folder (`off`, `0`, `no` or `false`: no cache).
ENV = "FMFUSION_COMPILE_CACHE"
_OFF = ("off", "0", "no", "false")


def compile_cache_dir() -> Path | None:
    """The folder `enable_compile_cache` uses by default (None when `FMFUSION_COMPILE_CACHE` turns it off)."""
    setting = os.environ.get(ENV, "").strip()
    if setting.lower() in _OFF:
        return None
    if setting:
        return Path(setting).expanduser()
    return user_cache_dir() / "xla"


def user_cache_dir() -> Path:
    """The project's cache folder of this user: `$XDG_CACHE_HOME/fmfusion-jax` (default `~/.cache/fmfusion-jax`)."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "fmfusion-jax"


def enable_compile_cache(path: str | Path | None = None) -> Path | None:
    """Turns JAX's persistent compilation cache on in `path` (default: `compile_cache_dir()`) for this process
    and the processes it starts; returns the folder, or None when it is turned off or the folder cannot be
    made (logged; compiling goes on as usual). Does not import JAX when it is not imported yet (JAX reads
    the setting from the environment when it is)."""
    folder = Path(path).expanduser() if path is not None else compile_cache_dir()
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        log.warning("compile cache off: cannot make %s (%s)", folder, error.strerror or error)
        return None
    settings = {"jax_compilation_cache_dir": str(folder), "jax_persistent_cache_min_compile_time_secs": "0"}
    for name, value in settings.items():
        os.environ[name.upper()] = value
    if "jax" in sys.modules:
        import jax  # lazy: JAX (`fmfusion --help` imports this module)

        jax.config.update("jax_compilation_cache_dir", str(folder))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # every step: entries are small
    return folder


def use_compile_cache() -> None:
    """The Python API's default (`Mapper`, `MapperBatch`): the cache the `fmfusion` commands fill, unless this
    process chose a cache folder of its own; `FMFUSION_COMPILE_CACHE=off` turns it off. Without it every new process
    compiles each step again (seconds each on a CPU)."""
    import jax  # lazy: JAX (`fmfusion --help` imports this module); the Python API has imported it already

    if not getattr(jax.config, "jax_compilation_cache_dir", None):
        enable_compile_cache()


__all__ = ["ENV", "compile_cache_dir", "enable_compile_cache", "use_compile_cache", "user_cache_dir"]
