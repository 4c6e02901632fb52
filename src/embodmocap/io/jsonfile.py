"""Bounded JSON reading: a user's JSON file is refused by its size and its nesting depth, with one
line naming the file, before the parser can exhaust memory or recursion.

``json.loads`` on a 200 MB file first holds the whole text in memory, and a few thousand nested
brackets raise ``RecursionError`` from the C parser. :func:`read_json` checks the size with
``stat`` before reading (and never reads more than the limit), then measures the nesting depth with
one vectorised pass over the bytes (string contents ignored), then parses.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from embodmocap.errors import InputError

#: Deepest nesting accepted. Every format we read needs fewer than 10 levels.
MAX_JSON_DEPTH = 64

#: A JSON string (escapes included); possessive so that a huge string cannot backtrack.
_STRING = re.compile(rb'"(?:[^"\\]++|\\.)*+"', re.DOTALL)


def json_depth(data: bytes) -> int:
    """Deepest nesting of ``[`` / ``{`` in JSON text, brackets inside strings ignored."""
    stripped = _STRING.sub(b'""', data)
    a = np.frombuffer(stripped, dtype=np.uint8)
    if a.size == 0:
        return 0
    step = np.isin(a, (ord("["), ord("{"))).astype(np.int32) - np.isin(a, (ord("]"), ord("}"))).astype(np.int32)
    return int(max(np.cumsum(step).max(), 0))


def _mib(n: int) -> str:
    return f"{n / 2**20:.1f} MiB" if n >= 2**20 else f"{n} bytes"


def read_json(path: str | Path, *, max_bytes: int, what: str = "JSON file", fix: str = "check the file",
              max_depth: int = MAX_JSON_DEPTH) -> Any:
    """Parse a JSON file no larger than ``max_bytes`` and nested no deeper than ``max_depth``.

    Raises:
        InputError: missing, unreadable, too large (with its size), too deep, or not JSON; the
            message names the file, ``what`` it is and ``fix``.
    """
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > max_bytes:
            raise InputError(p, f"{what} is {_mib(size)}, over the {_mib(max_bytes)} limit", fix)
        with open(p, "rb") as f:
            data = f.read(max_bytes + 1)  # bounded even for files that report no size (pipes)
    except FileNotFoundError:
        raise InputError(p, f"{what} not found", fix) from None
    except IsADirectoryError:
        raise InputError(p, f"{what} is a folder, not a file", fix) from None
    except PermissionError:
        raise InputError(p, f"{what} cannot be read (permission denied)", "make it readable (chmod u+r)") from None
    if len(data) > max_bytes:
        raise InputError(p, f"{what} is over the {_mib(max_bytes)} limit", fix)
    if not data.strip():
        raise InputError(p, f"{what} is empty (0 bytes of JSON)" if not data else f"{what} holds only whitespace", fix)
    # Nesting is at most the number of opening brackets: a file with few (a per-frame keypoint file
    # has ~10) needs no measuring.
    depth = json_depth(data) if data.count(b"[") + data.count(b"{") > max_depth else 0
    if depth > max_depth:
        raise InputError(p, f"{what} is nested {depth} levels deep (at most {max_depth} accepted)", fix)
    try:
        return json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as err:
        raise InputError(p, f"{what} is not valid JSON ({str(err).splitlines()[0]})", fix) from None
