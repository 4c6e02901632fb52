"""Giving memory that a finished stage freed back to the operating system.

Why: glibc's malloc keeps freed memory in its heaps for the next allocation instead of returning it,
unless the free block is at a heap's top. After Stage I (a TSDF volume, a 5-million-face mesh and
their temporaries, many of them between the 128 KiB mmap threshold and glibc's raised one) about
2.4 GB stayed resident in one ``embodmocap run`` process although nothing referenced it, and the
later stages allocated next to it (Stage IV's threads in heaps of their own, which cannot reuse it):
the whole run peaked ~1 GB above its largest stage. ``malloc_trim`` releases the free pages of every
heap; resident memory then falls to what is still alive (~0.4 GB after Stage I).
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
                if hasattr(lib, "malloc_trim"):
                    lib.malloc_trim.argtypes = [ctypes.c_size_t]
                    lib.malloc_trim.restype = ctypes.c_int
                    _libc = lib
            except OSError:
                pass
    return _libc or None


def release_freed_memory() -> bool:
    """Collect unreachable Python objects, then return every heap's free pages to the system
    (glibc's ``malloc_trim(0)``). Call between stages, never inside a hot loop: it walks all heaps
    (milliseconds for gigabytes). Returns False where the C library has no ``malloc_trim``: nothing
    is released there beyond what the garbage collector frees, and nothing else changes."""
    gc.collect()
    libc = _glibc()
    if libc is None:
        return False
    libc.malloc_trim(0)
    return True
