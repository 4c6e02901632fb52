"""World joint positions as CSV, one row per frame (for spreadsheets and quick plots).

Format (version 1): a header line ``frame,time_s,<joint>_x,<joint>_y,<joint>_z,...`` for the 24
SMPL joints in SMPL order (names from :data:`SMPL_JOINT_NAMES`), then one row per frame: the
sequence frame (integer), its time ``frame / fps`` in seconds, and the joint coordinates in the
scene world (Z up), metres, 6 decimals (micrometres). Comma separated, no quoting, ``\\n`` line ends.
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


def joints_csv_header(names: tuple[str, ...] = SMPL_JOINT_NAMES) -> list[str]:
    """Column names: ``frame``, ``time_s``, then ``<joint>_x``, ``_y``, ``_z`` per joint."""
    return ["frame", "time_s"] + [f"{n}_{axis}" for n in names for axis in "xyz"]


def joints_csv_text(joints: NDArray, fps: float, frames: NDArray | None = None) -> str:
    """CSV text for ``joints`` (T, 24, 3) in metres; ``frames`` (T,) default ``0..T-1``."""
    joints = np.asarray(joints, dtype=np.float64)
    T = len(joints)
    if joints.shape != (T, len(SMPL_JOINT_NAMES), 3):
        raise ValueError(f"joints must be (T, {len(SMPL_JOINT_NAMES)}, 3), got {joints.shape}")
    frames = np.arange(T) if frames is None else np.asarray(frames, dtype=np.int64)
    buf = io.StringIO()
    buf.write(",".join(joints_csv_header()) + "\n")
    if T:
        # The frame column is formatted as an integer, the rest with 6 decimals.
        table = np.concatenate([frames[:, None], (frames / float(fps))[:, None], joints.reshape(T, -1)], axis=1)
        np.savetxt(buf, table, fmt=["%d"] + ["%.6f"] * (table.shape[1] - 1), delimiter=",")
    return buf.getvalue()


def write_joints_csv(path: str | Path, joints: NDArray, fps: float, frames: NDArray | None = None) -> Path:
    """Write :func:`joints_csv_text` to ``path`` atomically; returns the path."""
    write_text(path, joints_csv_text(joints, fps, frames))
    log.info("wrote joint CSV %s (%d frames)", path, len(joints))
    return Path(path)
