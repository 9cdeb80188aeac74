"""The C heap of a process that moves messages: grown and kept in steps, not page by page.

Every message's payload (tens of kB) is a ``bytes`` object from glibc's main
heap. In a process whose heap is small (one that has not loaded numba's LLVM,
like the recorder), glibc grows the heap's top for such a payload and trims it
when it is freed, so every message pays a ``brk`` and the page faults of fresh,
zeroed pages. Measured (``mntes-stream bench recording``, the recorder's
per-message path, 2-core VM): 0.042-0.044 CPU s per M samples that way,
0.025-0.026 with the top padded (``M_TOP_PAD``) by 4-16 MiB. The converter,
whose heap numba has already grown, is unchanged. Pages of the pad are
touched only when used. A ``MALLOC_TOP_PAD_`` in the environment wins.
"""

from __future__ import annotations

import ctypes
import gc
import os
import sys

__all__ = ["TOP_PAD_BYTES", "freeze_setup", "own_process", "pad_heap", "trim_heap"]

TOP_PAD_BYTES = 16 << 20
_M_TOP_PAD = -2  # glibc's mallopt parameter (malloc.h)
_padded = False
_own_process = False


def pad_heap(top_pad_bytes: int = TOP_PAD_BYTES) -> bool:
    """Ask glibc to grow and keep the heap's top ``top_pad_bytes`` at a time; False where it cannot (no change).

    Idempotent; a no-op off Linux/glibc and when ``MALLOC_TOP_PAD_`` is set.
    """
    global _padded
    if _padded:
        return True
    if not sys.platform.startswith("linux") or "MALLOC_TOP_PAD_" in os.environ:
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the process's own C library (musl has no mallopt)
    except (OSError, AttributeError):
        return False
    _padded = bool(mallopt(_M_TOP_PAD, int(top_pad_bytes)))
    return _padded


def trim_heap() -> bool:
    """Give the C heap's free pages back to the system (glibc ``malloc_trim(0)``); False where it cannot.

    After a burst (a flood of big messages queued, then freed), glibc keeps the freed memory in its heaps
    and arenas: resident, though free. A service calls this when idle, not per message: it walks every
    arena, and gives back the top pad too (:func:`pad_heap`; the next messages grow it again). Measured
    (2-core VM): 300 MB freed in 100 kB pieces between live ones, 46 ms to give back (RSS 298 -> 12 MB);
    0.3 ms when there is nothing to give back.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        malloc_trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return False
    return bool(malloc_trim(0))


def own_process() -> None:
    """Say that this process runs one service or command (the ``mntes-stream`` executable, a spawned service),
    so :func:`freeze_setup` may act; a process embedding services (a test, a notebook) never calls it."""
    global _own_process
    _own_process = True


def freeze_setup() -> bool:
    """After a service's setup, in a process of its own: what exists now leaves the cyclic collector's sight.

    Parameters, tables, compiled kernels and imported modules live as long as the service; left in
    the collector's generations, every full collection in the hot loop walks them all (a converter
    did one every few thousand chunks over about 200,000 objects). Garbage is collected first, so
    none is kept for good; what the service drops later of what existed now is freed by reference
    counting, and only a reference cycle among it would stay. False (nothing done) in a process
    that did not call :func:`own_process`: there the frozen objects would be the embedder's.
    """
    if not _own_process:
        return False
    gc.collect()
    gc.freeze()
    return True
