"""The engine's main jitted steps, callable through saved executables.

Before JAX's compile cache can find a step, the step is traced and lowered: ~0.7 s of Python for the fusion and
merge steps of a room, in every process, warm cache or not. A `SavedStep` asks the process's executable store
(`compile_cache.executable_store()`, on wherever the compile cache is) for the executable of its arguments' types
instead: loaded whole from a file when an earlier process saved it, else compiled and saved. Without a store, and
inside another trace (its arguments are tracers: `fuse_and_refine`, the vmapped batch), it is the jitted function.
The engine does no I/O: the store reads and writes the files.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

import jax

from fmfusion_jax import compile_cache


def _signature(leaf: Any) -> tuple:
    """What a compiled step depends on of one argument leaf: shape, dtype, weak type (a host value and a device
    array of one type share the executable, which takes both). Read from the array's attributes: every call of a
    step makes one per leaf (~0.3 us each, against ~2 us through its `aval`)."""
    if isinstance(leaf, jax.Array):
        return (leaf.shape, leaf.dtype, leaf.weak_type)
    aval = jax.typeof(leaf)
    return (aval.shape, aval.dtype, aval.weak_type)


class SavedStep:
    """A jitted function (`jax.jit(..., static_argnames=...)`) called through compiled executables that the process's
    store saves and loads; the jitted function's attributes pass through (`lower`, `_cache_size`, ...).

    Each executable is kept per key (the static arguments, the tree and the types of the others), as `jax.jit` keeps
    its own: a new key is looked up in the store once, then called directly."""

    def __init__(self, jitted: Any, fn: Callable[..., Any], static_argnames: tuple[str, ...]):
        self._jitted = jitted
        self._name = f"{fn.__module__}.{fn.__qualname__}"
        self._source = inspect.getsourcefile(fn)  # in the key: a step defined outside the package's digested source
        self._static_names = frozenset(static_argnames)
        parameters = list(inspect.signature(fn).parameters)
        self._static_positions = frozenset(i for i, name in enumerate(parameters) if name in self._static_names)
        self._executables: dict[Any, Any] = {}
        self.__wrapped__ = fn  # as `jax.jit` has it: the Python function
        self.__doc__ = fn.__doc__
        self.__name__ = fn.__name__

    def __getattr__(self, name: str) -> Any:
        return getattr(self._jitted, name)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        store = compile_cache.executable_store()
        if store is None:
            return self._jitted(*args, **kwargs)
        dynamic_args = tuple(a for i, a in enumerate(args) if i not in self._static_positions)
        dynamic_kwargs = {k: v for k, v in kwargs.items() if k not in self._static_names}
        leaves, tree = jax.tree.flatten((dynamic_args, dynamic_kwargs))
        if any(isinstance(leaf, jax.core.Tracer) for leaf in leaves):
            return self._jitted(*args, **kwargs)  # traced into a caller's step
        statics = (
            tuple((i, a) for i, a in enumerate(args) if i in self._static_positions),
            tuple(sorted((k, v) for k, v in kwargs.items() if k in self._static_names)),
        )
        key = (statics, tree, tuple(_signature(leaf) for leaf in leaves))
        executable = self._executables.get(key)
        if executable is None:
            described = repr((statics, str(tree), key[2]))
            executable = store.load_or_compile(
                self._name, described, lambda: self._jitted.lower(*args, **kwargs).compile(), source=self._source
            )
            self._executables[key] = executable
        return executable(*dynamic_args, **dynamic_kwargs)

    def clear(self) -> None:
        """Drops the executables this step holds (`clear_executables` drops every step's, and JAX's)."""
        self._executables.clear()

    def _cache_size(self) -> int:
        """Executables held: the jitted function's and this step's (a test of "no recompilation" counts both)."""
        return self._jitted._cache_size() + len(self._executables)  # type: ignore[attr-defined]


#: Every `SavedStep` made, so that `clear_executables` reaches them all.
_STEPS: list[SavedStep] = []


def saved_step(*, static_argnames: tuple[str, ...] = (), donate_argnames: tuple[str, ...] = ()) -> Callable[..., SavedStep]:
    """Decorator: `jax.jit(fn, static_argnames=..., donate_argnames=...)` as a `SavedStep`."""

    def wrap(fn: Callable[..., Any]) -> SavedStep:
        step = SavedStep(jax.jit(fn, static_argnames=static_argnames, donate_argnames=donate_argnames), fn, static_argnames)
        _STEPS.append(step)
        return step

    return wrap


def clear_executables() -> None:
    """Drops all compiled code this process holds: JAX's caches (`jax.clear_caches()`), every saved step's
    executables and the steps loaded ahead."""
    jax.clear_caches()
    for step in _STEPS:
        step.clear()
    store = compile_cache.executable_store()
    if store is not None:
        store.forget_prefetched()
