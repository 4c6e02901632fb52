"""A dataset: a folder of session folders, one session folder, or a list file naming session
folders. Which sessions it holds and where its own files go (catalog, batch logs); used by the
batch runner, the catalog and the data loaders."""

from __future__ import annotations

import os
from pathlib import Path

from embodmocap.errors import InputError
from embodmocap.io.manifest import MANIFEST_NAME


def session_folders(dataset: str | Path) -> list[Path]:
    """The session folders of a dataset (sorted by name for a folder, in file order for a list).

    Raises:
        InputError: no such path, a list naming a folder without ``session.toml``, no session at
            all, or two sessions with the same folder name (their catalog rows would collide).
    """
    p = Path(dataset)
    if p.is_file():
        out = []
        for i, line in enumerate(p.read_text().splitlines(), 1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            s = Path(line) if os.path.isabs(line) else p.parent / line
            if not (s / MANIFEST_NAME).is_file():
                raise InputError(p, f"line {i}: {s} holds no {MANIFEST_NAME}", "list session folders only")
            out.append(Path(os.path.abspath(s)))
    elif (p / MANIFEST_NAME).is_file():
        out = [Path(os.path.abspath(p))]
    elif p.is_dir():
        out = sorted(Path(os.path.abspath(c)) for c in p.iterdir() if (c / MANIFEST_NAME).is_file())
    else:
        raise InputError(p, "no such dataset folder or list file", "give a folder of session folders or a list file")
    if not out:
        raise InputError(p, f"no session folder (a folder holding {MANIFEST_NAME}) found",
                         "give a folder of session folders, one session folder, or a list file")
    names = [s.name for s in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(p, f"two sessions are named {dup[0]}", "rename one session folder")
    return out


def dataset_root(dataset: str | Path) -> Path:
    """Where the dataset's own files go (catalog, batch logs): the folder itself, or the folder
    holding the list file; for a single session folder, the session folder."""
    p = Path(os.path.abspath(dataset))
    return p.parent if p.is_file() else p
