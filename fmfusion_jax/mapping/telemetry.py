"""What a run reports without waiting for the device more than it must: stage timings (`StageTimer`) and
small device-to-host copies of statistics.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time

import jax
import jax.numpy as jnp
import numpy as np

log = logging.getLogger(__name__)


def small_tree_to_host(tree):
    """A tree of small device arrays as numpy arrays: on the CPU each leaf read in place (`np.asarray`, no copy:
    `jax.device_get` took 0.28 ms per frame for the step's eight statistics there, this 0.08); elsewhere the
    leaves joined on the device into one array per dtype and those copied (a GPU profile: each leaf's copy
    cost ~0.09 ms of host time, one per frame's ten statistics)."""
    if jax.default_backend() == "cpu":
        return jax.tree.map(np.asarray, tree)
    return joined_tree_to_host(tree)


def joined_tree_to_host(tree):
    """`tree`'s device arrays as numpy arrays, joined on the device first (one copy per dtype)."""
    leaves, treedef = jax.tree.flatten(tree)
    if not leaves:
        return tree
    dtypes = sorted({leaf.dtype.name for leaf in leaves})
    joined = jax.device_get(_join_by_dtype(leaves, tuple(dtypes)))
    offsets = dict.fromkeys(dtypes, 0)
    host = []
    for leaf in leaves:
        start = offsets[leaf.dtype.name]
        offsets[leaf.dtype.name] = start + leaf.size
        host.append(joined[dtypes.index(leaf.dtype.name)][start : start + leaf.size].reshape(leaf.shape))
    return jax.tree.unflatten(treedef, host)


@functools.partial(jax.jit, static_argnames=("dtypes",))
def _join_by_dtype(leaves: list[jax.Array], dtypes: tuple[str, ...]) -> tuple[jax.Array, ...]:
    """The leaves raveled and joined, one 1-d array per dtype of `dtypes` (in its order; leaves in theirs)."""
    return tuple(jnp.concatenate([leaf.ravel() for leaf in leaves if leaf.dtype.name == name]) for name in dtypes)


@dataclasses.dataclass
class StageTimer:
    """Wall time per named stage (milliseconds per call), with the calls that compiled kept apart.

    Timing a stage waits for its result, so the host cannot work ahead of the device; `enabled=False`
    runs the stages without waiting and records nothing. The first call of a stage compiles; after
    `new_layout()` (a map that grew: the steps recompile for its shapes) the next call of each stage does
    again. `first_ms` keeps each stage's first call, `samples_ms` the calls that did not compile.
    """

    first_ms: dict[str, float] = dataclasses.field(default_factory=dict)
    samples_ms: dict[str, list[float]] = dataclasses.field(default_factory=dict)
    enabled: bool = True
    #: the stages called since the last layout change (their next call does not compile)
    warm: set[str] = dataclasses.field(default_factory=set)
    #: milliseconds of every call recorded so far, compiling ones too (`host_since` leaves out the stages inside)
    recorded_ms: float = 0.0

    def run(self, name: str, fn, *args):
        if not self.enabled:
            return fn(*args)
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        self.record(name, (time.perf_counter() - start) * 1e3, compiled=name not in self.warm)
        return out

    def host_since(self, name: str, start: float, recorded_before: float) -> None:
        """Keeps as a call of stage `name` the host's own time since `start` (`time.perf_counter()`): the wall time
        less the stages recorded since, when `recorded_ms` was `recorded_before` (nothing when not enabled)."""
        if self.enabled:
            inside = self.recorded_ms - recorded_before
            self.record(name, (time.perf_counter() - start) * 1e3 - inside, compiled=name not in self.warm)

    def record(self, name: str, elapsed_ms: float, compiled: bool) -> None:
        """Keeps one call's time: apart when it compiled (the first one in `first_ms`), else as a sample."""
        self.recorded_ms += elapsed_ms
        self.warm.add(name)
        if compiled:
            self.first_ms.setdefault(name, elapsed_ms)
        else:
            self.samples_ms.setdefault(name, []).append(elapsed_ms)

    def new_layout(self) -> None:
        """The map's shapes changed: the next call of every stage compiles (it is not a sample)."""
        self.warm.clear()

    def median_ms(self, name: str) -> float:
        samples = self.samples_ms.get(name) or [self.first_ms.get(name, float("nan"))]
        return float(np.median(samples))

    def summary(self) -> dict[str, dict[str, float]]:
        return {
            name: {"median_ms": self.median_ms(name), "first_call_ms": first, "calls": 1 + len(self.samples_ms.get(name, []))}
            for name, first in self.first_ms.items()
        }
