"""OpenSim marker file (``.trc``) of the world joints: the input of OpenSim's scaling and inverse
kinematics, as Pose2Sim writes it.

Layout (tab separated, ``\\n`` line ends), header lines exactly as the ``.trc`` files Pose2Sim
writes and OpenSim reads::

    PathFileType  4  (X/Y/Z)  <file name>
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  OrigNumFrames
    <fps>     <fps>       <T>        24          m      <fps>         <first frame>       <T>
    Frame#  Time  pelvis  (2 empty)  left_hip  (2 empty) ...
    (2 empty)     X1  Y1  Z1  X2  Y2  Z2 ...
    1  <time>  x y z of every marker ...

- **Markers** are the 24 SMPL joints (:data:`~embodmocap.body.joints.SMPL_JOINT_NAMES`, SMPL
  order), not skin markers: use them with an OpenSim model whose markers sit on the joint centres
  (Pose2Sim's joint-centre models do), or as virtual markers.
- **Y up**, as OpenSim expects: a world point is turned from our Z-up world with
  ``(x, y, z) -> (x, z, -y)`` (a -90 degree rotation about X; right-handed, the same change as the
  BVH and glTF exports), so the height is the Y column and the floor is y = 0.
- ``Frame#`` counts rows from 1; ``Time`` is the sequence frame divided by the frame rate (the
  ``time_s`` of the CSV export), so a sequence with dropped frames keeps true times.
- Units ``m``, 6 decimals (micrometres). Frames the fit flags not ``valid`` (the body was filled in
  from neighbouring frames) or ``suspect`` (a view contradicts a limb) are written like the others
  (the format has no column for them); the export warns with their counts.
"""

from __future__ import annotations

import io
import logging
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.body.joints import SMPL_JOINT_NAMES
from embodmocap.export.bvh import R_YUP_ZUP
from embodmocap.io.atomic import write_text

log = logging.getLogger(__name__)

#: The header keys of line 2, in the order every .trc file lists them.
TRC_HEADER_KEYS = ("DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate",
                   "OrigDataStartFrame", "OrigNumFrames")


def trc_text(joints: NDArray, fps: float, frames: NDArray | None = None, *, name: str = "motion.trc",
             names: tuple[str, ...] = SMPL_JOINT_NAMES) -> str:
    """The ``.trc`` text of ``joints`` (T, J, 3), metres in our Z-up world; ``frames`` (T,) are the
    sequence frames (default ``0..T-1``), ``name`` the file name written on line 1."""
    joints = np.asarray(joints, dtype=np.float64)
    T = len(joints)
    if joints.shape != (T, len(names), 3):
        raise ValueError(f"joints must be (T, {len(names)}, 3), got {joints.shape}")
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    frames = np.arange(T, dtype=np.int64) if frames is None else np.asarray(frames, dtype=np.int64)
    if frames.shape != (T,):
        raise ValueError(f"frames must be ({T},), got {frames.shape}")
    y_up = joints @ R_YUP_ZUP.T
    J = len(names)
    buf = io.StringIO()
    buf.write(f"PathFileType\t4\t(X/Y/Z)\t{name}\n")
    buf.write("\t".join(TRC_HEADER_KEYS) + "\n")
    start = int(frames[0]) if T else 0
    buf.write(f"{fps:g}\t{fps:g}\t{T}\t{J}\tm\t{fps:g}\t{start}\t{T}\n")
    # Each marker name heads its three columns: the name, then two empty fields.
    buf.write("Frame#\tTime\t" + "".join(f"{n}\t\t\t" for n in names)[:-1] + "\n")
    buf.write("\t\t" + "\t".join(f"{a}{j + 1}" for j in range(J) for a in "XYZ") + "\n")
    if T:
        table = np.concatenate([np.arange(1, T + 1)[:, None], (frames / float(fps))[:, None], y_up.reshape(T, -1)], 1)
        np.savetxt(buf, table, fmt=["%d"] + ["%.6f"] * (table.shape[1] - 1), delimiter="\t")
    return buf.getvalue()


def write_trc(path: str | Path, joints: NDArray, fps: float, frames: NDArray | None = None,
              valid: NDArray | None = None, suspect: NDArray | None = None) -> Path:
    """Write :func:`trc_text` to ``path`` atomically; ``valid``, ``suspect`` (T,) bool only feed the warnings."""
    path = Path(path)
    write_text(path, trc_text(joints, fps, frames, name=path.name))
    if valid is not None and not np.all(valid):
        log.warning("%s: %d of %d frames are not valid in the fit (filled from neighbours); they are "
                    "written like the others", path, int(np.sum(~np.asarray(valid, bool))), len(joints))
    if suspect is not None and np.any(suspect):
        log.warning("%s: %d of %d frames are suspect in the fit (a view contradicts a limb: smpl_world.npz's "
                    "`suspect`); they are written like the others", path, int(np.sum(suspect)), len(joints))
    log.info("wrote OpenSim marker file %s (%d frames, %d markers, Y up)", path, len(joints), np.shape(joints)[1])
    return path
