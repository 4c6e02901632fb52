"""Atomic writes: a crash never leaves a half-written file that looks complete.

Each writer writes to a temporary name in the destination folder and renames it into place
(``os.replace`` is atomic on POSIX within one file system). Temporary names are hidden and carry
the writer's process id (``.<name>.part-<pid>-<random><suffix>``), so that a later run can remove
what a killed run left behind without touching the files of a run still in progress
(:func:`remove_stale_temps`).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np


#: Marks a temporary name written by this module (followed by the writer's pid).
TEMP_MARK = ".part-"

# Names of temporary files/folders of versions before the pid mark: ".<name>.<8 random chars>"
# (tempfile's alphabet), optionally with a suffix, and atomic_dir's ".<name>.old".
_LEGACY_TEMP = re.compile(r"^\.[^/]+\.(?:[a-z0-9_]{8}(?:\.[A-Za-z0-9]{1,5})?|old)$")


def temp_prefix(path: str | Path) -> str:
    """The hidden prefix of this process's temporary names for ``path``."""
    return f".{Path(path).name}{TEMP_MARK}{os.getpid()}-"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's live process
    return True


def is_stale_temp(name: str) -> bool:
    """True when ``name`` is a temporary name of a writer that is no longer running."""
    if not name.startswith("."):
        return False
    if TEMP_MARK in name:
        pid = name.split(TEMP_MARK, 1)[1].split("-", 1)[0]
        return pid.isdigit() and not _pid_alive(int(pid))
    return bool(_LEGACY_TEMP.match(name))


def remove_stale_temps(folder: str | Path, recursive: bool = True) -> list[Path]:
    """Remove the temporary files and folders that killed writers left in ``folder`` (and below).

    Only names this module writes are touched (see :func:`is_stale_temp`); those of a writer that
    is still running are kept. Returns what was removed.
    """
    removed: list[Path] = []
    folder = Path(folder)
    if not folder.is_dir():
        return removed
    for dirpath, dirnames, filenames in os.walk(folder):
        for name in list(dirnames) + filenames:
            if is_stale_temp(name):
                p = Path(dirpath) / name
                try:
                    if p.is_dir() and not p.is_symlink():
                        shutil.rmtree(p)
                    else:
                        p.unlink()
                except FileNotFoundError:
                    continue
                removed.append(p)
                if name in dirnames:
                    dirnames.remove(name)
        if not recursive:
            break
    return removed


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it is renamed to ``path``.

    ``suffix`` defaults to the destination's suffix so that libraries choosing a format by
    extension (OpenCV, Open3D, trimesh) still do so.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path), suffix=suffix if suffix is not None else path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # mkstemp creates 0600 files; give outputs the usual permissions (0666 minus the umask).
        if tmp_path.exists():
            os.chmod(tmp_path, default_file_mode())
        os.replace(tmp_path, path)
    except OSError as err:
        raise _naming(err, path, tmp_path) from err
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def default_file_mode() -> int:
    """The mode a plainly created file gets (0666 minus the umask); mkstemp files are 0600."""
    return 0o666 & ~_umask()


def write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | Path, text: str) -> None:
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | Path, obj: Any, indent: int | None = 2) -> None:
    """Write JSON atomically; numpy scalars and arrays are converted to plain lists/numbers."""
    write_text(path, json.dumps(obj, indent=indent, default=_json_default) + "\n")


def write_npz(path: str | Path, **arrays: Any) -> None:
    """Write an uncompressed-on-read, compressed-on-disk ``.npz`` atomically."""
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)


@contextlib.contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Yield a temporary folder next to ``path``; on success it replaces ``path`` whole."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=temp_prefix(path), dir=path.parent))
    # mkdtemp makes the folder 0700; give it the mode a plainly created folder gets.
    os.chmod(tmp, 0o777 & ~_umask())
    try:
        yield tmp
        if path.exists():
            old = path.with_name(f"{temp_prefix(path)}old")
            if old.exists():
                shutil.rmtree(old)
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old)
        else:
            os.replace(tmp, path)
    except OSError as err:
        raise _naming(err, path, tmp) from err
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


def _naming(err: OSError, path: Path, tmp: Path) -> OSError:
    """``err`` naming the destination: a failed ``write()`` (disk full) names no file, and the
    temporary name means nothing to a user."""
    name = None if err.filename is None else str(err.filename)
    if getattr(err, "filename2", None) is not None and str(err.filename2).startswith(str(tmp)):
        name = str(err.filename2)  # a copy into the temporary folder failed: name the copy
    if name is not None and not name.startswith(str(tmp)):
        return err
    where = str(path) if name is None or name == str(tmp) else str(path) + name[len(str(tmp)):]
    return type(err)(err.errno, err.strerror or str(err), where) if err.errno else OSError(None, str(err), where)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
