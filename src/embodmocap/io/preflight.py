"""Checks a command runs on a session folder before it starts any work.

A command that writes (every stage, ``run``, ``evaluate``, ``report``, ``export``, ``render``)
first makes sure it can write where it will, so a read-only or foreign-owned session fails in one
line at once instead of after minutes of work; and it removes the temporary files that a killed
run left behind (:func:`embodmocap.io.atomic.remove_stale_temps`).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from embodmocap.errors import InputError
from embodmocap.io.atomic import TEMP_MARK, remove_stale_temps
from embodmocap.io.layout import SessionLayout


def _probe(folder: Path) -> OSError | None:
    """Try to create (and remove) a file in ``folder``: the only test that also holds for root,
    read-only mounts, ACLs and full disks' inode tables."""
    try:
        fd, name = tempfile.mkstemp(prefix=f".write-test{TEMP_MARK}{os.getpid()}-", dir=folder)
    except OSError as err:
        return err
    os.close(fd)
    os.unlink(name)
    return None


def output_folders(session: str | Path) -> list[Path]:
    """The session folder and the output folders in it that already exist (stages write in them)."""
    lay = SessionLayout(Path(session))
    found = [lay.root]
    for parent in (lay.scenes_dir, lay.sequences_dir):
        if parent.is_dir():
            found.append(parent)
            for sub in sorted(p for p in parent.iterdir() if p.is_dir() and not p.name.startswith(".")):
                found.append(sub)
                found += sorted(p for p in sub.iterdir() if p.is_dir() and not p.name.startswith("."))
    if lay.report_assets.is_dir():
        found.append(lay.report_assets)
    return found


def check_writable(folder: str | Path, what: str = "folder") -> None:
    """Raise :class:`InputError` when no file can be created in ``folder``."""
    folder = Path(folder)
    err = _probe(folder)
    if err is not None:
        reason = err.strerror or type(err).__name__
        raise InputError(folder, f"the {what} cannot be written ({reason})",
                         "make it writable (chmod u+w, or chown), or copy the session to a folder you own and run there")


def prepare_session(session: str | Path) -> None:
    """Before a writing command: every output folder writable, stale temporary files removed.

    A path that is not a folder is left to the command (it reports a missing session itself).
    """
    root = Path(session)
    if not root.is_dir():
        return
    for folder in output_folders(root):
        check_writable(folder, "session folder" if folder == root else "output folder")
    lay = SessionLayout(root)
    remove_stale_temps(root, recursive=False)
    for folder in (root / "scenes", root / "sequences", lay.report_assets):
        remove_stale_temps(folder)
