"""Errors a user can act on.

Every failure caused by input (a missing file, a malformed row, a wrong shape) is raised as an
:class:`InputError` whose message is one line: *what* is wrong, *where* (the file), and *what to
do*. The CLI prints that line alone (the traceback only with ``--debug``).
"""

from __future__ import annotations

from pathlib import Path


class EmbodMocapError(Exception):
    """Base class of all errors the package raises on purpose."""


class InputError(EmbodMocapError):
    """Bad or missing input. ``str(err)`` is the single line shown to the user."""

    def __init__(self, path: str | Path | None, problem: str, fix: str = "") -> None:
        self.path = Path(path) if path is not None else None
        self.problem = problem
        self.fix = fix
        where = f"{self.path}: " if self.path is not None else ""
        tail = f" ({fix})" if fix else ""
        super().__init__(f"{where}{problem}{tail}")


class MissingExtraError(EmbodMocapError):
    """An optional dependency is not installed; the message names the extra to install."""

    def __init__(self, module: str, extra: str) -> None:
        super().__init__(
            f"optional dependency '{module}' is not installed: pip install 'embodmocap[{extra}]'"
        )


def require(module: str, extra: str):
    """Import an optional module lazily, or raise :class:`MissingExtraError` naming the extra."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise MissingExtraError(module, extra) from err
