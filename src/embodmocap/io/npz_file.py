"""One checked reader for every ``.npz`` format the package reads.

:func:`load_npz` opens a file without pickles, reads every array, and checks the three things each
format needs (the file exists and is a readable npz; the required keys are there; its ``version``
is one this reader knows); :func:`check_shapes` checks the arrays' shapes against a symbolic
spec in which named dimensions must agree across keys. Every failure is one
:class:`~embodmocap.errors.InputError` that names the file, the problem and what to do.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from dataclasses import fields
from typing import Iterable, Iterator, Mapping, Sequence, Union

import numpy as np

from embodmocap.errors import InputError

#: One dimension of a shape spec: an int (exact), a name (same size wherever the name appears),
#: or None (any size).
Dim = Union[int, str, None]


class NpzData(dict):
    """A file's arrays by key (a ``dict``), with ``files`` as ``np.load``'s ``NpzFile`` has."""

    @property
    def files(self) -> list[str]:
        return list(self)


def load_npz(path: str | Path, *, what: str, fix: str, required: Iterable[str] = (),
             versions: Sequence[int] | None = (1,), default_version: int | None = 1) -> NpzData:
    """Every array of the npz file at ``path``, checked.

    Args:
        path: the file.
        what: what the file is, for the messages (``"Stage II cameras"``).
        fix: what a user does about a missing or bad file (``"run `embodmocap sequence` first"``).
        required: keys that must be present.
        versions: format versions this reader knows (the file's ``version`` key); None = any
            (formats without a version, e.g. the studio's ground truth).
        default_version: the version of a file without a ``version`` key; None = the key is required.

    Raises:
        InputError: missing or unreadable file, missing keys, unknown version.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, f"{what} not found", fix)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = NpzData({k: z[k] for k in z.files})
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as err:  # damaged zip / npy
        raise InputError(path, f"not a readable npz file ({err.__class__.__name__}: {err})", fix) from err
    missing = [k for k in required if k not in data]
    if "version" not in data and default_version is None:
        missing.insert(0, "version")
    if missing:
        raise InputError(path, f"keys {missing} missing (the {what} lacks them)", fix)
    if versions is None:
        return data
    version = int(np.asarray(data["version"]).reshape(-1)[0]) if "version" in data else default_version
    if version not in versions:
        known = ", ".join(str(v) for v in versions)
        raise InputError(path, f"{what} version {version}, this reader knows {known}",
                         f"update embodmocap, or {fix[0].lower() + fix[1:] if fix else 'write the file again'}")
    data["version"] = np.int64(version)
    return data


def check_shapes(path: str | Path, arrays: Mapping[str, np.ndarray], spec: Mapping[str, Sequence[Dim]],
                 fix: str) -> dict[str, int]:
    """Check ``arrays[key].shape`` against ``spec[key]`` for every key of ``spec`` present in ``arrays``.

    Named dimensions bind on first use, so ``{"points": ("T", 17, 3), "conf": ("T", 17)}`` needs both
    arrays to have the same ``T``. Returns the bound names (``{"T": 120}``).

    Raises:
        InputError: naming every key whose shape does not fit.
    """
    bound: dict[str, int] = {}
    bad = []
    for key, dims in spec.items():
        if key not in arrays or arrays[key] is None:
            continue
        shape = np.shape(arrays[key])
        ok = len(shape) == len(dims)
        for n, d in zip(shape, dims) if ok else ():
            if isinstance(d, str):
                ok &= bound.setdefault(d, n) == n
            elif d is not None:
                ok &= n == d
        if not ok:
            want = "(" + ", ".join("*" if d is None else str(d) for d in dims) + ("," if len(dims) == 1 else "") + ")"
            bad.append(f"{key} {shape} (expected {want})")
    if bad:
        sizes = f" with {', '.join(f'{k}={v}' for k, v in bound.items())}" if bound else ""
        raise InputError(path, f"wrong shapes: {'; '.join(bad)}{sizes}", fix)
    return bound


def check_finite(path: str | Path, arrays: Mapping[str, np.ndarray], keys: Iterable[str], fix: str) -> None:
    """InputError naming the keys among ``keys`` whose arrays hold NaN or infinite values."""
    bad = [k for k in keys if arrays.get(k) is not None and not np.isfinite(np.asarray(arrays[k], dtype=float)).all()]
    if bad:
        raise InputError(path, f"non-finite values in {', '.join(bad)}", fix)


class NpzRecord:
    """``np.load``-like access to a dataclass whose field names are a file's keys (the typed
    records of :mod:`embodmocap.io.stage_files` and :mod:`embodmocap.io.stage_json`)."""

    def __getitem__(self, key: str):
        value = getattr(self, key, None) if key in self._names() else None
        if value is None:
            raise KeyError(f"{key} is not a file in the archive")
        return value

    def __contains__(self, key: object) -> bool:
        return isinstance(key, str) and key in self._names() and getattr(self, key) is not None

    def __iter__(self) -> Iterator[str]:
        return iter(self.files)

    def keys(self) -> list[str]:
        return self.files

    def items(self) -> list[tuple[str, np.ndarray]]:
        return [(k, getattr(self, k)) for k in self.files]

    def get(self, key: str, default=None):
        return self[key] if key in self else default

    @property
    def files(self) -> list[str]:
        """The keys present (as ``NpzFile.files``)."""
        return [k for k in self._names() if getattr(self, k) is not None]

    def arrays(self) -> dict[str, np.ndarray]:
        """The keys present and their arrays (what the writer stores)."""
        return {k: getattr(self, k) for k in self.files}

    @classmethod
    def _names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))  # type: ignore[arg-type]


def record_fields(cls, data: dict) -> dict:
    """The dataclass's fields from a file's arrays (None for the keys the file lacks)."""
    return {f.name: data.get(f.name) for f in fields(cls)}
