"""Giving memory that a finished stage freed back to the operating system.

Why: glibc's malloc keeps freed memory in its heaps for the next allocation instead of returning it,
unless the free block is at a heap's top. After Stage I (a TSDF volume, a 5-million-face mesh and
their temporaries, many of them between the 128 KiB mmap threshold and glibc's raised one) about
2.4 GB stayed resident in one ``embodmocap run`` process although nothing referenced it, and the
later stages allocated next to it (Stage IV's threads in heaps of their own, which cannot reuse it):
the whole run peaked ~1 GB above its largest stage. ``malloc_trim`` releases the free pages of every
heap; resident memory then falls to what is still alive (~0.6 GB after Stage I).

A trimmed heap still has holes: a later stage's mid-sized temporaries (a few MB, which glibc puts
in the heap once its mmap threshold has risen past them) scatter over them and Stage IV's peak
in the run stayed ~1 GB above Stage IV alone. :func:`map_large_blocks` fixes the threshold (4 MB):
larger blocks get their own mapping and go back to the system the moment they are freed.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
import sys

log = logging.getLogger(__name__)

_libc = None


def _glibc():
    """The C library when it is glibc (it has ``malloc_trim``), else None (macOS, musl, Windows)."""
    global _libc
    if _libc is None:
        _libc = False
        if sys.platform.startswith("linux"):
            try:
                lib = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
                if hasattr(lib, "malloc_trim") and hasattr(lib, "mallopt"):
                    lib.malloc_trim.argtypes = [ctypes.c_size_t]
                    lib.malloc_trim.restype = ctypes.c_int
                    _libc = lib
            except OSError:
                pass
    return _libc or None


#: glibc's ``mallopt`` parameter number of the mmap threshold (malloc.h ``M_MMAP_THRESHOLD``).
_M_MMAP_THRESHOLD = -3


def map_large_blocks(threshold_bytes: int = 4 << 20) -> bool:
    """From now on, allocations of ``threshold_bytes`` or more get their own memory mapping (returned
    to the system when freed) instead of glibc's heap, whose dynamic threshold otherwise rises to
    32 MB after the first large free. Process-wide: called by ``embodmocap run``, not by the stage
    functions a library user calls. Returns False where the C library is not glibc (no change)."""
    libc = _glibc()
    if libc is None:
        return False
    return bool(libc.mallopt(_M_MMAP_THRESHOLD, int(threshold_bytes)))


def trim_heaps() -> bool:
    """``malloc_trim(0)`` alone (no garbage collection: cheap enough after every step of a stage):
    the heaps' free pages back to the system. ``embodmocap run``'s workers call it as each step
    ends, so a stage's worker does not sit on a finished step's freed memory (Stage I's TSDF, ~2 GB
    on a 15 s scan) while its last steps run beside another worker's job. Returns False without
    glibc."""
    libc = _glibc()
    if libc is None:
        return False
    libc.malloc_trim(0)
    return True


def release_freed_memory() -> bool:
    """Collect unreachable Python objects, then return every heap's free pages to the system
    (glibc's ``malloc_trim(0)``). Call between stages, never inside a hot loop: it walks all heaps
    (milliseconds for gigabytes). Returns False where the C library has no ``malloc_trim``: nothing
    is released there beyond what the garbage collector frees, and nothing else changes."""
    gc.collect()
    return trim_heaps()
