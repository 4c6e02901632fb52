"""World joint positions as CSV, one row per frame (for spreadsheets and quick plots).

Format (version 1): a header line ``frame,time_s,<joint>_x,<joint>_y,<joint>_z,...`` for the 24
SMPL joints in SMPL order (names from :data:`SMPL_JOINT_NAMES`), then one row per frame: the
sequence frame (integer), its time ``frame / fps`` in seconds, and the joint coordinates in the
scene world (Z up), metres, 6 decimals (micrometres). Comma separated, no quoting, ``\\n`` line ends.
With the motion's frame flags (``embodmocap export`` passes them), two last columns ``valid`` and
``suspect`` (0 / 1, ``smpl_world.npz``'s keys): a frame the body could not be placed in, or whose
fit a view contradicts, says so in every row.
"""

from __future__ import annotations

import io
import logging
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.body.joints import SMPL_JOINT_NAMES
from embodmocap.io.atomic import write_text

log = logging.getLogger(__name__)


#: The flag columns written last when the frame flags are given.
FLAG_COLUMNS: tuple[str, ...] = ("valid", "suspect")


def joints_csv_header(names: tuple[str, ...] = SMPL_JOINT_NAMES, flags: bool = False) -> list[str]:
    """Column names: ``frame``, ``time_s``, then ``<joint>_x``, ``_y``, ``_z`` per joint (then
    ``valid``, ``suspect`` with ``flags``)."""
    return ["frame", "time_s"] + [f"{n}_{axis}" for n in names for axis in "xyz"] + (list(FLAG_COLUMNS) if flags else [])


def joints_csv_text(joints: NDArray, fps: float, frames: NDArray | None = None,
                    flags: tuple[NDArray, NDArray] | None = None) -> str:
    """CSV text for ``joints`` (T, 24, 3) in metres; ``frames`` (T,) default ``0..T-1``;
    ``flags``: (valid, suspect) (T,) bool each, written as the last two columns (None: no columns)."""
    joints = np.asarray(joints, dtype=np.float64)
    T = len(joints)
    if joints.shape != (T, len(SMPL_JOINT_NAMES), 3):
        raise ValueError(f"joints must be (T, {len(SMPL_JOINT_NAMES)}, 3), got {joints.shape}")
    frames = np.arange(T) if frames is None else np.asarray(frames, dtype=np.int64)
    cols = [frames[:, None], (frames / float(fps))[:, None], joints.reshape(T, -1)]
    if flags is not None:
        f = np.stack([np.asarray(x, dtype=bool) for x in flags], axis=1)
        if f.shape != (T, len(FLAG_COLUMNS)):
            raise ValueError(f"flags must be {len(FLAG_COLUMNS)} arrays of ({T},), got {f.shape}")
        cols.append(f.astype(np.float64))
    buf = io.StringIO()
    buf.write(",".join(joints_csv_header(flags=flags is not None)) + "\n")
    if T:
        # The frame (and flag) columns are formatted as integers, the rest with 6 decimals.
        table = np.concatenate(cols, axis=1)
        fmt = ["%d"] + ["%.6f"] * (1 + joints[0].size) + ["%d"] * (table.shape[1] - 2 - joints[0].size)
        np.savetxt(buf, table, fmt=fmt, delimiter=",")
    return buf.getvalue()


def write_joints_csv(path: str | Path, joints: NDArray, fps: float, frames: NDArray | None = None,
                     flags: tuple[NDArray, NDArray] | None = None) -> Path:
    """Write :func:`joints_csv_text` to ``path`` atomically; returns the path."""
    write_text(path, joints_csv_text(joints, fps, frames, flags))
    log.info("wrote joint CSV %s (%d frames)", path, len(joints))
    return Path(path)
