"""The command line's log output: one line per record, repeated lines folded.

A message logged several times in a row by the same logger at the same level (a warning raised
per window, per view or per retry) is printed once, followed by one ``(the line above repeated N
more times)`` line when something else is logged or the run ends.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TextIO

FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class FoldingHandler(logging.StreamHandler):
    """A stream handler that folds runs of identical records (same logger, level and message)."""

    def __init__(self, stream: TextIO | None = None) -> None:
        super().__init__(stream if stream is not None else sys.stderr)
        self._last: tuple[str, int, str] | None = None
        self._repeats = 0

    def emit(self, record: logging.LogRecord) -> None:
        try:
            key = (record.name, record.levelno, record.getMessage())
        except Exception:  # noqa: BLE001 - a bad format string: let the base class report it
            super().emit(record)
            return
        if key == self._last:
            self._repeats += 1
            return
        self.flush_repeats()
        self._last = key
        super().emit(record)

    def flush_repeats(self) -> None:
        """Write the pending ``repeated N more times`` line, if any."""
        if self._repeats:
            self.stream.write(f"(the line above repeated {self._repeats} more times)\n")
            self.stream.flush()
        self._repeats = 0

    def close(self) -> None:
        self.flush_repeats()
        super().close()


def setup(logger: logging.Logger, debug: bool, stream: TextIO | None = None, *,
          level: int | None = None) -> FoldingHandler:
    """Attach one folding handler to ``logger`` (the package logger): INFO, or DEBUG with ``debug``;
    ``level`` overrides both (``-q``: WARNING, ``-v``: DEBUG)."""
    level = level if level is not None else (logging.DEBUG if debug else logging.INFO)
    handler = FoldingHandler(stream)
    handler.setFormatter(logging.Formatter(FORMAT, "%H:%M:%S"))
    handler.setLevel(level)
    logger.addHandler(handler)
    logger.setLevel(level)
    return handler


def add_file(logger: logging.Logger, path: Path, level: int) -> logging.FileHandler:
    """Also write ``logger``'s records at ``level`` and above to ``path`` (appended, full dates), so
    a ``-q`` run still keeps its INFO lines in the file; the logger's own level is lowered to match."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setFormatter(logging.Formatter(FORMAT, "%Y-%m-%d %H:%M:%S"))
    handler.setLevel(level)
    logger.addHandler(handler)
    logger.setLevel(min(logger.level, level))
    return handler


@contextmanager
def command_logging(logger: logging.Logger, level: int, log_file: Path | None = None) -> Iterator[None]:
    """The command line's handlers for one command: the folding handler on stderr at ``level`` and,
    with ``log_file``, the file at ``level`` or INFO, whichever shows more. Removed on exit."""
    handler = setup(logger, level <= logging.DEBUG, level=level)
    file_handler = None
    try:
        if log_file is not None:
            file_handler = add_file(logger, log_file, min(level, logging.INFO))
        yield
    finally:
        handler.flush_repeats()  # a run of repeated lines at the very end is still counted
        logger.removeHandler(handler)
        if file_handler is not None:
            logger.removeHandler(file_handler)
            file_handler.close()


def say_error(logger: logging.Logger, line: str) -> None:
    """A command's one-line failure: on stderr, and as an ERROR record in ``logger``'s log files
    (not through the stderr handler, which would print it twice)."""
    print(line, file=sys.stderr)
    for h in logger.handlers:
        if isinstance(h, logging.FileHandler):
            h.emit(logger.makeRecord(logger.name, logging.ERROR, __file__, 0, line, (), None))


@contextmanager
def quiet_colmap(pycolmap, log: logging.Logger) -> Iterator[None]:
    """Keep COLMAP's own logging (glog, straight to stderr) to errors unless ``log`` is at DEBUG:
    its INFO line per image and its routine "many threads" warning would drown the package's log."""
    old = pycolmap.logging.minloglevel
    if not log.isEnabledFor(logging.DEBUG):
        pycolmap.logging.minloglevel = max(old, 2)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old
