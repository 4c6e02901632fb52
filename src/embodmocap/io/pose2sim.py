"""Readers for Pose2Sim files: camera calibration TOML and TRC marker trajectories.

Used to check our triangulation against Pose2Sim's on its real demo (4 static cameras, OpenPose
BODY_25B keypoints). Formats (see docs/formats.md):

- ``Calib_*.toml``: one table per camera with ``name``, ``size`` [w, h] px, ``matrix`` (K, 3x3),
  ``distortions`` [k1, k2, p1, p2] (OpenCV model), ``rotation`` (Rodrigues vector, world ->
  camera), ``translation`` (metres, world -> camera), ``fisheye`` (bool); other tables (e.g.
  ``[metadata]``) have no ``matrix`` and are skipped.
- ``*.trc``: tab-separated text. Line 1 ``PathFileType ...``; line 2 header keys and line 3 their
  values (``DataRate``, ``NumFrames``, ``NumMarkers``, ``Units`` ...); line 4 ``Frame#``, ``Time``
  and the marker names (each followed by two empty cells); line 5 ``X1 Y1 Z1 ...``; then one row
  per frame: frame number, time (s), x y z per marker (empty cell = missing).
"""

from __future__ import annotations

import logging
import tomllib
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from embodmocap.errors import InputError
from embodmocap.geometry.transforms import invert_T, make_T

log = logging.getLogger(__name__)

#: BODY_25B keypoint index -> Pose2Sim marker name (Pose2Sim's BODY_25B skeleton; the ears, eyes
#: and the rest have no marker in its TRC files).
BODY_25B_MARKERS: dict[int, str] = {
    0: "Nose", 5: "LShoulder", 6: "RShoulder", 7: "LElbow", 8: "RElbow", 9: "LWrist",
    10: "RWrist", 11: "LHip", 12: "RHip", 13: "LKnee", 14: "RKnee", 15: "LAnkle", 16: "RAnkle",
    17: "Neck", 18: "Head", 19: "LBigToe", 20: "LSmallToe", 21: "LHeel", 22: "RBigToe",
    23: "RSmallToe", 24: "RHeel",
}

#: Rotation taking a Pose2Sim TRC's Y-up axes to its calibration's world axes:
#: (X, Y, Z)_world = (z, x, y)_trc.
R_CALIB_TRC: NDArray[np.float64] = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])

_UNIT_SCALE = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}


class Pose2SimCamera(NamedTuple):
    """One calibrated camera (a tuple: ``K, dist, T_world_cam, size = cam`` works)."""

    K: NDArray[np.float64]
    """(3, 3) intrinsics, pixels."""
    dist: NDArray[np.float64]
    """(4,) OpenCV distortion k1, k2, p1, p2."""
    T_world_cam: NDArray[np.float64]
    """(4, 4) camera-to-world (OpenCV camera axes), metres, in the calibration's world frame."""
    size: tuple[int, int]
    """Image (width, height), pixels."""


def read_pose2sim_calibration(path: str | Path) -> dict[str, Pose2SimCamera]:
    """Read a Pose2Sim calibration TOML: camera name -> :class:`Pose2SimCamera`.

    The name is the table's ``name`` value (the table key when absent), in file order.

    Raises:
        InputError: unreadable or invalid TOML, no camera table, a missing or mis-shaped field,
            or a fisheye camera (its distortion model is not OpenCV's pinhole one).
    """
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        raise InputError(path, "calibration file not found", "check the path") from err
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
        raise InputError(path, f"not a valid TOML file ({err})", "re-export the calibration from Pose2Sim") from err
    cams: dict[str, Pose2SimCamera] = {}
    for key, table in doc.items():
        if not isinstance(table, dict) or "matrix" not in table:
            continue
        name = str(table.get("name", key))
        if table.get("fisheye", False):
            raise InputError(path, f"[{key}] is a fisheye camera, which is not supported",
                             "calibrate with the pinhole model")
        K = _array(path, key, table, "matrix", (3, 3))
        dist = _array(path, key, table, "distortions", (4,))
        rvec = _array(path, key, table, "rotation", (3,))
        tvec = _array(path, key, table, "translation", (3,))
        size = _array(path, key, table, "size", (2,))
        T_cam_world = make_T(Rotation.from_rotvec(rvec).as_matrix(), tvec)
        cams[name] = Pose2SimCamera(K, dist, invert_T(T_cam_world), (int(size[0]), int(size[1])))
    if not cams:
        raise InputError(path, "no camera table (with a 'matrix') found", "pass a Pose2Sim Calib_*.toml file")
    log.debug("%s: %d cameras", path, len(cams))
    return cams


def read_trc(path: str | Path) -> tuple[list[str], NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
    """Read a TRC marker file.

    Returns:
        ``(marker_names, times, frames, xyz)``: M names; (T,) times, seconds; (T,) frame numbers
        as written (Pose2Sim numbers from 1); (T, M, 3) positions in metres (converted from the
        header's ``Units`` when mm or cm) in the file's own axes (Pose2Sim: Y up; see
        :data:`R_CALIB_TRC`), NaN where a cell is empty.

    Raises:
        InputError: missing file, a header that is not TRC, names that disagree with
            ``NumMarkers``, unknown units, non-numeric cells or rows of the wrong length.
    """
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError as err:
        raise InputError(path, "TRC file not found", "check the path") from err
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(path, f"cannot read the file ({err})", "check the file") from err
    if len(lines) < 5 or not lines[0].startswith("PathFileType") or not lines[3].startswith("Frame#"):
        raise InputError(path, "not a TRC file (expected 'PathFileType' and 'Frame#' header lines)", "pass a .trc file")
    header = dict(zip(lines[1].split("\t"), lines[2].split("\t")))
    names = [n.strip() for n in lines[3].split("\t")[2:] if n.strip()]
    try:
        n_markers = int(header["NumMarkers"])
        scale = _UNIT_SCALE[header.get("Units", "m").strip()]
    except KeyError as err:
        raise InputError(path, f"header lacks NumMarkers or has unknown Units ({err})", "use m, cm or mm") from err
    except ValueError as err:
        raise InputError(path, f"NumMarkers is not a number ({err})", "fix the header") from err
    if len(names) != n_markers:
        raise InputError(path, f"{len(names)} marker names but NumMarkers = {n_markers}", "fix the header")

    rows = [ln.split("\t") for ln in lines[5:] if ln.strip()]
    width = 2 + 3 * n_markers
    table = np.full((len(rows), width), np.nan)
    for i, cells in enumerate(rows):
        cells = [c.strip() for c in cells]
        if len(cells) > width and any(cells[width:]):
            raise InputError(path, f"data row {i + 1} has {len(cells)} cells, expected {width}", "fix the file")
        try:
            values = [float(c) if c else np.nan for c in cells[:width]]
        except ValueError as err:
            raise InputError(path, f"data row {i + 1}: non-numeric cell ({err})", "fix the file") from err
        table[i, : len(values)] = values
    if np.isnan(table[:, :2]).any():
        raise InputError(path, "a data row lacks its frame number or time", "fix the file")
    if "NumFrames" in header and header["NumFrames"].strip().isdigit() and int(header["NumFrames"]) != len(rows):
        log.warning("%s: header says %s frames, file has %d rows", path, header["NumFrames"], len(rows))
    xyz = table[:, 2:].reshape(len(rows), n_markers, 3) * scale
    return names, table[:, 1], table[:, 0].astype(np.int64), xyz


def _array(path: Path, key: str, table: dict, field: str, shape: tuple[int, ...]) -> NDArray[np.float64]:
    """One numeric field of a camera table as an array of ``shape``, or InputError."""
    if field not in table:
        raise InputError(path, f"[{key}] has no '{field}'", "re-export the calibration from Pose2Sim")
    try:
        arr = np.asarray(table[field], dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise InputError(path, f"[{key}] '{field}' is not numeric", "re-export the calibration") from err
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise InputError(path, f"[{key}] '{field}' must be {shape} finite numbers, got shape {arr.shape}",
                         "re-export the calibration")
    return arr
