"""The merge step and the geometry fusion compiled on a thread of their own while the first frames are fused.

A run whose compile cache is cold compiles three large executables on the stepping thread while the run waits:
the detection step at the first detection frame, the merge step right after it (`refinement.merge_every` 1) and
the geometry fusion some frames later; XLA compiles a module on one core. A map's shapes are known once it
exists, so `CompileAhead` lowers and compiles the latter two on a second thread, beside the detection step's
compilation. JAX keeps what `jit(f).lower(shapes).compile()` made for the jitted function's own calls with
arguments of those shapes (and writes it to the persistent compile cache): the stepping thread waits for the
thread before their first call, which then runs the executable compiled here. With a warm cache the thread loads
them, as the first calls would have. The shapes name a device only where the state's arrays are committed to
one, as a jitted call sees them (otherwise the call would compile again).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

import jax

from fmfusion_jax.engine import step
from fmfusion_jax.engine.config import MapConfig
from fmfusion_jax.engine.state import MapState

log = logging.getLogger(__name__)

def _shape_of(x: jax.Array) -> jax.ShapeDtypeStruct:
    sharding = x.sharding if x.committed else None
    return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding, weak_type=x.weak_type)


class CompileAhead:
    """Compiles the merge step and the geometry fusion for a map's shapes on a background thread; `wait(name)` (the
    step's name as `engine.frame.fuse_frame` runs it: `refine`, `geometry_fusion`) before its first call."""

    def __init__(self, state: MapState, config: MapConfig, fusion: step.FusionConfig) -> None:
        shapes = jax.tree.map(_shape_of, state)  # taken now: the state's buffers are donated to the first step
        lowerings: dict[str, Callable[[], Any]] = {
            "refine": lambda: step.lower_refine(shapes, config, fusion),
            "geometry_fusion": lambda: step.lower_fuse_geometry(shapes, config, step.fusion_on_device(fusion)),
        }
        self._done = {name: threading.Event() for name in lowerings}
        # not a daemon: an interpreter that exits waits for it rather than tearing XLA down mid-compilation
        threading.Thread(target=self._compile, args=(lowerings,), name="compile-ahead").start()

    def _compile(self, lowerings: dict[str, Callable[[], Any]]) -> None:
        for name, lower in lowerings.items():
            try:
                lower().compile()
            except Exception as error:  # the step's first call compiles it instead, and reports any error
                log.debug("compiling %s ahead failed: %s", name, error)
            finally:
                self._done[name].set()

    def wait(self, name: str) -> None:
        """Returns once step `name` has been compiled ahead (at once if it is not compiled here)."""
        event = self._done.get(name)
        if event is not None:
            event.wait()

    def wait_all(self) -> None:
        """Returns once every step compiled here is compiled."""
        for event in self._done.values():
            event.wait()
