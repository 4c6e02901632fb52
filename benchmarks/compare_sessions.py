"""Compare the Stage I-IV outputs of two runs of the same session, array by array, for equality.

Used to show that a change of structure changes no result: run the old and the new code on copies
of one synthesised session (``embodmocap run``), then

    python benchmarks/compare_sessions.py OLD_SESSION NEW_SESSION

Every ``.npz`` key under ``scenes/`` and ``sequences/`` must hold the same array (exact equality,
NaN equal to NaN), every ``.ply`` and other file the same bytes (an SQLite database without its header's change
counters), every ``.json`` the same content
except the bookkeeping keys in :data:`IGNORED` (timings, dates, output fingerprints, the package
version, the capture's absolute path), which differ between any two runs. Prints one line per
difference and a summary; exits 1 when anything differs or is missing.

Step fingerprints are compared too, unless ``--ignore-fingerprints``: Stage III's ``geosync``
fingerprint hashes ``calibration.json``, whose solver timings differ between any two runs, so it
differs even between two runs of the same code (every other fingerprint hashes content or config).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

#: JSON keys that differ between two runs of the same code (timings, dates, paths and what hashes them).
IGNORED = {"seconds", "finished", "ended", "started", "fit_seconds", "output_fingerprints", "inputs",
           "package_version", "fusion_fps", "capture"}
#: Output folders of Stages I-IV (the inputs, ground truth and perception files are the session's own).
STAGE_DIRS = ("scenes", "sequences")


def _strip(o, ignored: set[str]):
    """``o`` without the keys in ``ignored`` and those ending in ``_seconds``, at any depth."""
    if isinstance(o, dict):
        return {k: _strip(v, ignored) for k, v in o.items() if k not in ignored and not k.endswith("_seconds")}
    if isinstance(o, list):
        return [_strip(v, ignored) for v in o]
    return o


def _same_array(x: np.ndarray, y: np.ndarray) -> bool:
    if x.shape != y.shape or x.dtype != y.dtype:
        return False
    if x.dtype.kind in "fc":
        return bool(np.array_equal(x, y, equal_nan=True))
    return bool(np.array_equal(x, y))


def _content(path: Path) -> bytes:
    """A file's bytes; for an SQLite database (COLMAP's) without the header's change counters
    (bytes 24-27 and 92-95), which SQLite bumps on every write transaction."""
    data = path.read_bytes()
    if data.startswith(b"SQLite format 3\x00") and len(data) >= 100:
        data = data[:24] + bytes(4) + data[28:92] + bytes(4) + data[96:]
    return data


def compare(a: Path, b: Path, ignore_fingerprints: bool = False) -> tuple[int, list[str]]:
    """(number of equal files/keys, differences) between the stage outputs of sessions ``a`` and ``b``."""
    same, diffs = 0, []
    ignored = IGNORED | ({"fingerprint"} if ignore_fingerprints else set())
    files = sorted({p.relative_to(a) for d in STAGE_DIRS for p in (a / d).rglob("*") if p.is_file()}
                   | {p.relative_to(b) for d in STAGE_DIRS for p in (b / d).rglob("*") if p.is_file()})
    for rel in files:
        p, q = a / rel, b / rel
        if not p.is_file() or not q.is_file():
            diffs.append(f"{rel}: only in {'new' if q.is_file() else 'old'}")
            continue
        if rel.suffix == ".npz":
            with np.load(p, allow_pickle=False) as za, np.load(q, allow_pickle=False) as zb:
                for k in sorted(set(za.files) | set(zb.files)):
                    if k not in za.files or k not in zb.files:
                        diffs.append(f"{rel}:{k} only in {'new' if k in zb.files else 'old'}")
                    elif not _same_array(za[k], zb[k]):
                        x, y = za[k], zb[k]
                        extra = (f", max abs diff {np.nanmax(np.abs(x - y)):.3g}"
                                 if x.shape == y.shape and x.dtype.kind == "f" and x.size else "")
                        diffs.append(f"{rel}:{k} differs ({x.dtype}{x.shape} vs {y.dtype}{y.shape}{extra})")
                    else:
                        same += 1
        elif rel.suffix == ".json":
            if _strip(json.loads(p.read_text()), ignored) != _strip(json.loads(q.read_text()), ignored):
                diffs.append(f"{rel}: JSON content differs")
            else:
                same += 1
        elif _content(p) != _content(q):
            diffs.append(f"{rel}: bytes differ")
        else:
            same += 1
    return same, diffs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old", type=Path)
    ap.add_argument("new", type=Path)
    ap.add_argument("--ignore-fingerprints", action="store_true",
                    help="also ignore step fingerprints (they hash configs whose repr may change)")
    args = ap.parse_args(argv)
    same, diffs = compare(args.old, args.new, args.ignore_fingerprints)
    for d in diffs:
        print(d)
    print(f"equal: {same} files/keys; different or missing: {len(diffs)}")
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())
