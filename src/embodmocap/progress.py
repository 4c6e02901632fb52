"""Progress on long steps: one helper for the whole package.

Where a person watches (stderr is a terminal) each long step shows a tqdm bar; where nobody does (a
log file, CI, a pipe, a batch worker) it is one INFO line per step on the ``embodmocap.progress``
logger instead of hundreds of bar redraws; with ``-q`` (:func:`set_quiet`) there is neither (the
line still reaches a ``--log-file``, which keeps INFO). Two forms:

- :func:`progress` wraps an iterable whose items take a while (frames, views, windows, chunks);
- :func:`step` wraps one long call that reports nothing on its own (a COLMAP match, a solver),
  showing its elapsed time.
"""

from __future__ import annotations

import logging
import sys
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import TypeVar

log = logging.getLogger("embodmocap.progress")

T = TypeVar("T")

_quiet = False


def set_quiet(quiet: bool) -> bool:
    """Silence (True) or allow (False) progress output; returns the previous setting. The command
    line sets it from ``-q``."""
    global _quiet
    old, _quiet = _quiet, bool(quiet)
    return old


def is_quiet() -> bool:
    """Whether progress (and a command's routine output) is silenced (``-q``)."""
    return _quiet


def _bars() -> bool:
    try:
        return not _quiet and sys.stderr.isatty()
    except (AttributeError, ValueError):  # a replaced or closed stderr
        return False


def progress(items: Iterable[T], desc: str, total: int | None = None, unit: str = "item",
             disable: bool = False) -> Iterable[T]:
    """``items`` unchanged, with a bar on a terminal or one ``desc: N units`` line otherwise.

    Args:
        items: what the step iterates over.
        desc: the step, e.g. ``"seq0 view1: keypoints"``.
        total: number of items (default ``len(items)`` when it has one).
        unit: the item's name for the bar and the line (``"frame"``, ``"window"``).
        disable: no output for this call (a caller's own ``progress=False`` setting).
    """
    if total is None:
        try:
            total = len(items)  # type: ignore[arg-type]
        except TypeError:
            total = None
    if disable or _quiet:
        return items
    if _bars():
        from tqdm import tqdm

        return tqdm(items, total=total, desc=desc, unit=unit, dynamic_ncols=True, file=sys.stderr)
    if total is None:
        log.info("%s", desc)
    else:
        log.info("%s: %d %s%s", desc, total, unit, "" if total == 1 else "s")
    return items


@contextmanager
def step(desc: str) -> Iterator[None]:
    """Around one long call: on a terminal a line with the running elapsed time, else one INFO
    line when it starts; nothing when quiet."""
    if _quiet:
        yield
        return
    if not _bars():
        log.info("%s", desc)
        yield
        return
    from tqdm import tqdm

    bar = tqdm(total=None, desc=desc, bar_format="{desc}: {elapsed}", file=sys.stderr)
    done = threading.Event()

    def tick() -> None:
        while not done.wait(0.5):
            bar.refresh()

    ticker = threading.Thread(target=tick, daemon=True)
    ticker.start()
    try:
        yield
    finally:
        done.set()
        ticker.join()
        bar.close()
