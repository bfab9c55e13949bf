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

JAX's cache still traces and lowers each step before it can look it up (~0.7 s of Python for the fusion and merge
steps of a room). The engine's main steps (`engine.saved_steps`) are also saved whole in the same folder
(`fmfusion-*.step`, beside JAX's `*-cache` entries) when they are compiled: a later process loads them without
tracing. Their key is the step, its static arguments, its arguments' shapes and types, the source of the engine and
of the package's top-level modules (an edit there invalidates them), the JAX and jaxlib versions, the device, the
CPU's features, `XLA_FLAGS` and JAX's settings.
"""

from __future__ import annotations

import concurrent.futures
import functools
import hashlib
import json
import logging
import os
import pickle
import platform
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

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
    global _STORE
    _STORE = ExecutableStore(folder)
    return folder


def use_compile_cache() -> None:
    """The Python API's default (`Mapper`, `MapperBatch`): the cache the `fmfusion` commands fill, unless this
    process chose a cache folder of its own; `FMFUSION_COMPILE_CACHE=off` turns it off. Without it every new process
    compiles each step again (seconds each on a CPU)."""
    import jax  # lazy: JAX (`fmfusion --help` imports this module); the Python API has imported it already

    if not getattr(jax.config, "jax_compilation_cache_dir", None):
        enable_compile_cache()
    if _STORE is not None:
        _STORE.prefetch()  # the steps the last process used, loaded while this one opens and sizes its scene


class ExecutableStore:
    """Compiled steps saved whole (`jax.experimental.serialize_executable`), one file per step and key, in `folder`.

    `load_or_compile` returns a step's executable for a key: loaded from its file when there is one, else
    compiled (JAX's cache may load it, after tracing and lowering) and saved. A file that cannot be read or
    written costs only the time: the step is compiled as usual (logged)."""

    #: Bumped when what a file holds changes.
    FORMAT = 1
    #: The steps the last process loaded or saved, in the order it first used them (`prefetch` loads them ahead).
    MANIFEST = "fmfusion-steps-used.json"

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self._used: list[str] = []
        self._prefetched: dict[str, concurrent.futures.Future] = {}
        self._lock = threading.Lock()

    def prefetch(self) -> None:
        """Starts loading, in a background thread, the steps the last process used (its manifest, when it ran the
        same code): a run's first frame then finds them loaded, while the scene is opened and sized. A step loaded
        ahead that this process does not ask for costs only that thread's time. Once per store, and never while a
        loading thread of this process is still at work (a run that failed early, then the next run in the same
        process, with a store of its own: `enable_compile_cache` makes one per command)."""
        global _LOADER
        with self._lock, _LOADER_LOCK:
            if self._prefetched or self._used or (_LOADER is not None and _LOADER.is_alive()):
                return
            try:
                manifest = json.loads((self.folder / self.MANIFEST).read_text())
            except (OSError, ValueError):
                return
            if not isinstance(manifest, dict) or manifest.get("code") != _code_digest():
                return
            names = [name for name in manifest.get("steps", []) if isinstance(name, str) and (self.folder / name).is_file()]
            self._prefetched = {name: concurrent.futures.Future() for name in names}
            ahead = list(self._prefetched.items())
            if ahead:
                _LOADER = threading.Thread(target=self._load_ahead, args=(ahead,), name="fmfusion-steps", daemon=True)
                _LOADER.start()

    def _load_ahead(self, ahead: list[tuple[str, concurrent.futures.Future]]) -> None:
        # the futures themselves, not the dict's entries: a step asked for before its turn has been taken out of the
        # dict by `load_or_compile`, which waits on its future
        for name, future in ahead:
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(_load_step(self.folder / name))
            except Exception as error:  # noqa: BLE001 - reported where the step is asked for (compiled instead)
                future.set_exception(error)

    def forget_prefetched(self) -> None:
        """Drops the steps loaded ahead that nothing asked for (`engine.saved_steps.clear_executables`)."""
        with self._lock:
            for future in self._prefetched.values():
                future.cancel()
            self._prefetched = {}

    def _note_used(self, path: Path) -> None:
        """Adds the step to this process's manifest (written at once: a process may end any time)."""
        with self._lock:
            if path.name in self._used:
                return
            self._used.append(path.name)
            text = json.dumps({"code": _code_digest(), "steps": self._used})
        try:
            partial = self.folder / f"{self.MANIFEST}.{os.getpid()}.partial"
            partial.write_text(text)
            os.replace(partial, self.folder / self.MANIFEST)
        except OSError as error:
            log.info("steps used not noted (%s)", error)

    def path(self, name: str, key: str, source: str | None = None) -> Path:
        """The file of step `name` under `key` (the step's static arguments and its arguments' types), defined in the
        file `source` (its content is in the key too: a step may be defined outside the package)."""
        text = f"{self.FORMAT}|{name}|{key}|{_code_digest()}|{_file_digest(source)}|{_environment()}"
        digest = hashlib.sha256(text.encode()).hexdigest()
        return self.folder / f"fmfusion-{name.rsplit('.', 1)[-1]}-{digest[:40]}.step"

    def load_or_compile(self, name: str, key: str, compile_step: Callable[[], Any], source: str | None = None) -> Any:
        """The executable of step `name` (defined in the file `source`) under `key`: loaded, or `compile_step()` (a
        `jax.stages.Compiled`) saved."""
        from jax.experimental import serialize_executable  # lazy: JAX

        path = self.path(name, key, source)
        with self._lock:
            ahead = self._prefetched.pop(path.name, None)
        if ahead is not None and not ahead.cancelled():
            try:
                compiled = ahead.result()
                self._note_used(path)
                return compiled
            except Exception:  # noqa: BLE001 - read again below, where a damaged file is handled
                pass
        if path.is_file():
            try:
                compiled = _load_step(path)
                self._note_used(path)
                return compiled
            except Exception as error:  # noqa: BLE001 - a damaged file: compile instead
                log.info("saved step %s unreadable (%s): removed, compiling the step", path, error)
                path.unlink(missing_ok=True)  # ours (named by this store): saved again when next compiled anew
        with XLA_TURNS:
            misses = _compiled_here()
            compiled = compile_step()
            compiled_here = _compiled_here() != misses
        if not compiled_here:
            # Not compiled here but found (in JAX's cache, or as the same program compiled before in this process):
            # such an executable saved again does not run (XLA's CPU executables lose kernels: "Function ... not
            # found"). It is saved by a process that compiles it.
            return compiled
        try:
            with XLA_TURNS:
                data = pickle.dumps(serialize_executable.serialize(compiled))
            partial = path.with_name(f"{path.name}.{os.getpid()}.partial")
            partial.write_bytes(data)
            os.replace(partial, path)  # whole or not at all: processes side by side may write the same step
            self._note_used(path)
        except Exception as error:  # noqa: BLE001 - a backend that cannot serialize, a full disk: not saved
            log.info("step %s not saved (%s)", name, error)
        return compiled


def _load_step(path: Path) -> Any:
    """The executable saved in `path` (a `jax.stages.Compiled`)."""
    from jax.experimental import serialize_executable  # lazy: JAX

    payload, in_tree, out_tree = pickle.loads(path.read_bytes())
    with XLA_TURNS:
        return serialize_executable.deserialize_and_load(payload, in_tree, out_tree)


#: Taken while a saved step is deserialized, compiled or serialized: XLA's CPU client aborted the process ("Fatal
#: Python error: Aborted", in CI) with two threads deserializing steps while a third compiled one (a run that failed
#: early left its loading thread at work, and the next run in the same process started another). They take turns.
XLA_TURNS = threading.Lock()


_STORE: ExecutableStore | None = None
#: The thread loading steps ahead (`ExecutableStore.prefetch`), one per process at a time.
_LOADER: threading.Thread | None = None
_LOADER_LOCK = threading.Lock()


def executable_store() -> ExecutableStore | None:
    """Where this process saves and loads compiled steps: the compile cache's folder once `enable_compile_cache`
    ran, else None (every step is traced and compiled, or found in a cache the process chose itself)."""
    return _STORE


#: JAX's monitoring event of a program compiled, or loaded from JAX's cache (`host_memory.compilations` counts it too).
BACKEND_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
_CACHE_HIT_EVENT = "/jax/compilation_cache/cache_hits"
_events: dict[tuple[int, str], int] | None = None


def _compiled_here() -> int:
    """Programs this thread compiled so far, not loaded from JAX's cache (JAX monitoring listeners, called in the
    compiling thread): its compilations less its cache hits. The same program compiled before in this process is
    neither (JAX keeps it)."""
    global _events
    if _events is None:
        import jax.monitoring  # lazy: JAX

        _events = {}
        jax.monitoring.register_event_listener(_count_event)
        jax.monitoring.register_event_duration_secs_listener(_count_duration_event)
    thread = threading.get_ident()
    return _events.get((thread, BACKEND_COMPILE_EVENT), 0) - _events.get((thread, _CACHE_HIT_EVENT), 0)


def _count_event(event: str, **kwargs: Any) -> None:
    if event == _CACHE_HIT_EVENT and _events is not None:
        key = (threading.get_ident(), event)
        _events[key] = _events.get(key, 0) + 1


def _count_duration_event(event: str, duration_secs: float, **kwargs: Any) -> None:
    if event == BACKEND_COMPILE_EVENT and _events is not None:
        key = (threading.get_ident(), event)
        _events[key] = _events.get(key, 0) + 1


@functools.cache
def _code_digest() -> str:
    """SHA-256 of the source of the engine and of the package's top-level modules (what the engine may import: the
    import contracts keep the layers above out of it): a saved step is never used by other code."""
    digest = hashlib.sha256()
    root = Path(__file__).parent
    for path in sorted([*root.glob("*.py"), *(root / "engine").rglob("*.py")]):
        digest.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


@functools.cache
def _file_digest(path: str | None) -> str:
    """SHA-256 of a file's content (empty without a file)."""
    if path is None:
        return ""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return ""


@functools.cache
def _environment() -> str:
    """What else a compiled step depends on: JAX, jaxlib, the devices, the CPU's features, XLA's flags and JAX's
    settings (all but the logging and caching ones)."""
    import jax  # lazy: JAX
    import jax.extend
    import jaxlib

    cpu_flags = ""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            cpu_flags = next((line for line in cpuinfo if line.startswith(("flags", "Features"))), "")
    except OSError:
        pass
    backend = jax.extend.backend.get_backend()
    settings = sorted(
        (name, repr(value))
        for name, value in jax.config.values.items()
        if not any(word in name for word in ("cache", "log", "explain", "traceback"))
    )
    return repr(
        (
            jax.__version__,
            jaxlib.__version__,
            backend.platform,
            backend.platform_version,
            [device.device_kind for device in jax.devices()],
            platform.machine(),
            cpu_flags,
            os.environ.get("XLA_FLAGS", ""),
            settings,
        )
    )


__all__ = [
    "ENV",
    "ExecutableStore",
    "compile_cache_dir",
    "enable_compile_cache",
    "executable_store",
    "use_compile_cache",
    "user_cache_dir",
]
