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


def os_error_line(err: OSError) -> str:
    """One line for a failed file operation: the file, what happened, what to do."""
    import errno

    where = f"{err.filename}: " if err.filename else ""
    code = err.errno
    if code == errno.ENOSPC:
        what, fix = "no space left on the device", "free some disk space, then run the same command again to resume"
    elif code == getattr(errno, "EDQUOT", -1):
        what, fix = "disk quota exceeded", "free some space or raise the quota, then run the same command again to resume"
    elif code in (errno.EACCES, errno.EPERM):
        what, fix = "permission denied", "make it writable for you (chmod/chown), or copy the session to a folder you own"
    elif code == errno.EROFS:
        what, fix = "read-only file system", "copy the session to a writable disk and run there"
    elif code == errno.ENOENT:
        what, fix = "no such file or folder", "check the path"
    else:
        what, fix = err.strerror or str(err), "check the file, then run the same command again"
    return f"{where}{what} ({fix})"


def failure_message(err: BaseException) -> str:
    """How ``embodmocap run`` reports a stage's expected failure: an EmbodMocapError's own line, an
    OSError's file and cause, else the error's type and message."""
    return (str(err) if isinstance(err, EmbodMocapError) else os_error_line(err) if isinstance(err, OSError)
            else f"{type(err).__name__}: {err}")


# Ctrl-C. The default handler raises KeyboardInterrupt wherever Python is; inside the import of a
# compiled extension (torch, open3d, cv2 load on first use) that surfaces as "ImportError:
# initialization failed" instead. The CLI records that SIGINT arrived, so such an error still counts
# as an interruption (status 130, manifest "interrupted") and not as a bug.
_sigint_seen = [False]


def _on_sigint(signum, frame) -> None:
    _sigint_seen[0] = True
    import signal

    signal.default_int_handler(signum, frame)


def watch_interrupts():
    """Note SIGINT from now on (main thread only; a SIGINT that is ignored stays ignored).
    Returns the previous handler for :func:`stop_watching_interrupts`, or None when unchanged."""
    import signal
    import threading

    _sigint_seen[0] = False
    if threading.current_thread() is not threading.main_thread():
        return None
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return None
    return signal.signal(signal.SIGINT, _on_sigint)


def interrupt_once() -> None:
    """In a worker process (main thread): SIGINT watched as :func:`watch_interrupts` does, and only
    the first one interrupts: the terminal's Ctrl-C and the one the parent forwards must not cut
    the stage's own record of ``interrupted`` short."""
    import signal

    watch_interrupts()
    inner = signal.getsignal(signal.SIGINT)
    fired = [False]

    def once(signum, frame):
        if not fired[0]:
            fired[0] = True
            if callable(inner):
                inner(signum, frame)
            else:
                raise KeyboardInterrupt

    signal.signal(signal.SIGINT, once)


def stop_watching_interrupts(previous) -> None:
    """Put back the handler :func:`watch_interrupts` replaced."""
    import signal

    if previous is not None:
        signal.signal(signal.SIGINT, previous)


def interrupted(err: BaseException | None = None) -> bool:
    """True for a KeyboardInterrupt, or for any error raised after a watched SIGINT arrived."""
    return isinstance(err, KeyboardInterrupt) or _sigint_seen[0]
