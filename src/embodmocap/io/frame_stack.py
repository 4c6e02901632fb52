"""Per-frame masks and depth of a sliced sequence as memory-mapped ``.npy`` stacks.

One file per view and kind instead of one PNG per frame: writing is a memory copy (encoding a
noisy 16-bit PNG costs ~3.5 ms a frame, more than everything else Stage II does per frame), and
readers get random access to any frame without decoding, while memory stays flat because the file
is memory-mapped. Both are plain NumPy ``.npy`` files (``np.load(path, mmap_mode="r")``):

- masks: (T, H, ceil(W / 8)) uint8, each row bit-packed with ``np.packbits(mask, axis=-1)``
  (big-endian bit order); unpack with :func:`read_mask` or ``np.unpackbits(..., count=W)``.
- depth: (T, h, w) uint16 millimetres, 0 = invalid; :func:`read_depth_m` gives float32 metres.

The image width of the masks is stored in a sidecar-free way: the caller knows it from the view's
``cameras.npz`` (``width``), and :func:`read_mask` takes it.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Iterator

import numpy as np
from numpy.typing import NDArray

from embodmocap.io.atomic import atomic_path


@contextlib.contextmanager
def write_stack(path: str | Path, shape: tuple[int, ...], dtype) -> Iterator[np.memmap]:
    """A writable memory-mapped ``.npy`` of ``shape``; renamed into place only on success."""
    with atomic_path(path, suffix=".npy") as tmp:
        arr = np.lib.format.open_memmap(tmp, mode="w+", dtype=dtype, shape=shape)
        _reserve(tmp)
        try:
            yield arr
            arr.flush()
        finally:
            del arr


def _reserve(path: Path) -> None:
    """Allocate the file's blocks now: on a full disk, writing through the memory map would kill
    the process with SIGBUS (no message, no clean-up); allocating raises ENOSPC instead."""
    import errno
    import os

    with open(path, "r+b") as f:
        try:
            os.posix_fallocate(f.fileno(), 0, os.fstat(f.fileno()).st_size)
        except OSError as err:
            if err.errno not in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                raise


def pack_mask(mask: NDArray) -> NDArray[np.uint8]:
    """(H, W) bool -> (H, ceil(W/8)) uint8."""
    return np.packbits(np.asarray(mask, dtype=bool), axis=-1)


def read_mask(path: str | Path, t: int, width: int) -> NDArray[np.bool_]:
    """(H, W) bool mask of sequence frame ``t``."""
    stack = np.load(path, mmap_mode="r")
    return np.unpackbits(stack[t], axis=-1, count=width).astype(bool)


def depth_mm(depth_m: NDArray) -> NDArray[np.uint16]:
    """Metres (0 = invalid) -> uint16 millimetres, clipped to the uint16 range."""
    return np.clip(np.round(np.asarray(depth_m, dtype=np.float64) * 1000.0), 0, 65535).astype(np.uint16)


def read_depth_m(path: str | Path, t: int) -> NDArray[np.float32]:
    """(h, w) float32 depth in metres of sequence frame ``t`` (0 = invalid)."""
    return np.load(path, mmap_mode="r")[t].astype(np.float32) / 1000.0
