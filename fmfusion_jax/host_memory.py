"""Memory given back to the operating system on a CPU host, without changing any value.

The map's pool is allocated at its capacity, and `init_map_state` writes every row, so the whole pool is
resident from the first frame (a ScanNet room: 430 MiB, of which the frames fill 60 % by the end). The rows past
`num_blocks` hold their initial values, and for most pool arrays those are zero bytes: their pages can be handed
back (`madvise(MADV_DONTNEED)`), after which the kernel maps zero pages there again on the next touch. The values
the engine reads are the same; only the resident memory shrinks. This works on the CPU backend, where a
`jax.Array` is a host buffer that NumPy can view without a copy, on Linux; elsewhere every function here is a no-op.

`trim_heap` asks glibc to return the free memory its arenas keep (XLA's compiler and the outputs' temporaries
leave hundreds of MiB there); `compilations` tells a loop when a step was compiled, so that it trims then.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging
import mmap
import os
import sys
from typing import TYPE_CHECKING, Any

from fmfusion_jax.compile_cache import BACKEND_COMPILE_EVENT

if TYPE_CHECKING:
    import jax

log = logging.getLogger(__name__)

#: Pool arrays whose unallocated rows are zero bytes (`engine.state.init_voxel_blocks`); the others start at
#: -1 or 1 (ids, tsdf) and keep their pages.
ZERO_POOL_FIELDS = ("weight", "color", "instance_weight", "instance_bits", "geometry_stale")
_MADV_DONTNEED = 4  # Linux


@functools.cache
def _libc() -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
        libc.madvise.restype = ctypes.c_int
        libc.malloc_trim.argtypes = [ctypes.c_size_t]
        libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    except (OSError, AttributeError):  # not glibc (musl has madvise but no malloc_trim)
        return None
    return libc


def release_unallocated_rows(state: Any) -> int:
    """Hands back the pages of a `MapState`'s unallocated pool rows that hold zeros; returns the bytes given back.

    Rows `[num_blocks, capacity - 1)` of the `ZERO_POOL_FIELDS` arrays, page-aligned inwards, each range checked to
    be zeros first (an array where it is not keeps its pages). Waits for the steps dispatched on `state`. Only
    single maps on the CPU backend (a batch of maps, or device memory, is left alone: 0).
    """
    import jax  # lazy: the output registry and the command's entry import this module (`fmfusion --help` stays fast)
    import numpy as np

    libc = _libc()
    blocks = state.blocks
    if libc is None or np.ndim(blocks.num_blocks) != 0:
        return 0
    leaves = [getattr(blocks, name) for name in ZERO_POOL_FIELDS]
    if not all(isinstance(leaf, jax.Array) and _on_cpu(leaf) for leaf in leaves):
        return 0
    jax.block_until_ready(leaves)
    n = int(blocks.num_blocks)
    released = 0
    for leaf in leaves:
        host = np.asarray(leaf)
        if host.ctypes.data != leaf.unsafe_buffer_pointer():  # a copy: its pages are not the pool's
            continue
        row = host[0].nbytes
        base = host.ctypes.data
        start = -(-(base + n * row) // mmap.PAGESIZE) * mmap.PAGESIZE
        stop = (base + (len(host) - 1) * row) // mmap.PAGESIZE * mmap.PAGESIZE  # the last row is the scratch row
        if stop <= start or host[(start - base) // row : -(-(stop - base) // row)].any():
            continue
        if libc.madvise(start, stop - start, _MADV_DONTNEED) == 0:
            released += stop - start
    if released:
        log.debug("gave back %.0f MiB of unallocated pool rows (%d of %d allocated)", released / 2**20, n, len(host))
    return released


#: glibc malloc arenas the `fmfusion` command allows its threads (`limit_malloc_arenas`).
COMMAND_MALLOC_ARENAS = 2
_M_ARENA_MAX = -8  # glibc's mallopt parameter


def limit_malloc_arenas(arenas: int = COMMAND_MALLOC_ARENAS) -> bool:
    """Caps the C heap's arenas at `arenas` for the threads that first allocate after the call (glibc's
    `mallopt(M_ARENA_MAX)`), so that threads share their freed memory: each thread otherwise keeps an arena of its
    own, and the memory one writer thread freed is not reused by the other (scene0000_00's `fmfusion run`, peak RSS
    over 6 alternating runs: 1032-1064 MiB with glibc's default, 918-1004 MiB with 2, wall within 1 %; in a slower
    sitting both peaked alike, 881-924 MiB: the gain depends on how the writers' steps overlap). For a
    process of its own, called before JAX starts its threads: the `fmfusion` command, not the library (a process's
    allocator is its owner's choice). Returns whether the cap was set: not on other C libraries, nor when the
    environment sets `MALLOC_ARENA_MAX` (the user's choice stands)."""
    libc = _libc()
    if libc is None or "MALLOC_ARENA_MAX" in os.environ:
        return False
    return bool(libc.mallopt(_M_ARENA_MAX, arenas))


def trim_heap() -> None:
    """Returns the free memory of the C heap's arenas to the operating system (glibc's `malloc_trim`; a few to
    a hundred ms)."""
    libc = _libc()
    if libc is not None:
        libc.malloc_trim(0)


_compiled = 0
_listening = False


def compilations() -> int:
    """Executables compiled (or loaded from the compile cache) in this process since the first call: a loop that
    sees the count change after a frame knows that the frame compiled a step (a JAX monitoring listener)."""
    global _listening
    if not _listening:
        import jax.monitoring

        jax.monitoring.register_event_duration_secs_listener(_count_compilation)
        _listening = True
    return _compiled


def _count_compilation(event: str, duration_secs: float, **kwargs: str | int) -> None:
    global _compiled
    if event == BACKEND_COMPILE_EVENT:
        _compiled += 1


def _on_cpu(array: "jax.Array") -> bool:
    return all(device.platform == "cpu" for device in array.devices())
