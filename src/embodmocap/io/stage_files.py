"""Typed readers and writers of the files one stage hands to the next.

Every file a stage writes for a later one has a frozen dataclass here, a ``write_*`` function and
a ``read_*`` function that checks the format version, the keys and the shapes, and raises one
:class:`~embodmocap.errors.InputError` naming the file and the command that writes it:

==================================== ==================== =========================================
file (``sequences/<seq>/``)          dataclass            written by
==================================== ==================== =========================================
``<view>/cameras.npz``               :class:`CameraFile`  Stage II (form ``cameras``, VIO world)
``<view>/keypoints2d.npz``           :class:`Keypoints2DFile` Stage II
``<view>/registration.npz``          :class:`RegistrationFile` Stage III
``<view>/cameras_world.npz``         :class:`CameraFile`  Stage III (form ``cameras_world``)
``keypoints3d.npz``                  :class:`Keypoints3DFile` Stage IV ``triangulate``
``smpl_fit.npz``, ``smpl_world.npz`` ``SmplParams``       Stage IV (:mod:`embodmocap.io.smpl_file`)
``joints_world.npz``                 :class:`WorldJointsFile` Stage IV ``align``
``<view>/cameras_final.npz``         :class:`CameraFile`  Stage IV (form ``cameras_final``)
==================================== ==================== =========================================

Attribute names are the files' key names, and every dataclass also answers ``obj["key"]``,
``"key" in obj`` and ``obj.files`` like the ``NpzFile`` that ``np.load`` returns (optional keys
absent from the file are None and not "in" it), so code written against ``np.load`` switches to a
checked reader by changing only its load line.

The JSON hand-over files (``sync.json``, ``frame_map.json``, ``calibration.json``, ``keyframes.json``,
the stage manifests' records, ``skills.json``) have their readers and writers in
:mod:`embodmocap.io.stage_json`, imported from here as well.

The sequence frame rate lives in Stage II's ``cameras.npz`` (key ``fps``); :func:`sequence_fps`
reads it, and falls back to Stage II's manifest figure for files written before the key existed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from embodmocap.errors import InputError
from embodmocap.io.atomic import write_npz
from embodmocap.io.layout import SequenceLayout
from embodmocap.io.npz_file import NpzRecord, check_finite, check_shapes, load_npz, record_fields
# The JSON hand-over files (sync, frame maps, calibration, key frames, manifests' records, skills):
# their own module, re-exported here so that every hand-over file reads from one place.
from embodmocap.io.stage_json import (CALIBRATION_VERSIONS, EVALUATION_VERSIONS, FRAME_MAP_VERSION,  # noqa: F401
                                      KEYFRAMES_VERSIONS, MAX_STAGE_JSON_BYTES, SKILLS, SKILLS_FORMAT,
                                      SYNC_RECORD_VERSION, SYNC_VERSIONS, CalibrationFile, FrameMap, KeyframesFile,
                                      SkillClip, SkillObject, SkillsFile, SkillTarget, StageManifestRecord, SyncFile,
                                      read_calibration, read_evaluation, read_final_sync, read_frame_map,
                                      read_keyframes, read_report_json, read_skills, read_stage_record, read_sync,
                                      skills_to_json, write_calibration, write_frame_map, write_keyframes, write_skills,
                                      write_sync)
from embodmocap.io.smpl_file import read_smpl_npz, read_smpl_valid, write_smpl_npz  # noqa: F401 (SMPL motion)

CameraForm = Literal["cameras", "cameras_world", "cameras_final"]
#: Stage that writes each camera form, and the command that does it.
_WRITER = {"cameras": "sequence", "cameras_world": "calibrate", "cameras_final": "motion",
           "keypoints2d": "sequence", "registration": "calibrate", "keypoints3d": "motion", "joints_world": "motion"}
#: Versions of the registration file this reader knows (2 added ``accepted`` and ``run``; 3 added
#: ``off_chain`` and the optional ``T_world_vio_performer``).
REGISTRATION_VERSIONS = (1, 2, 3)


def _fix(path: Path, kind: str) -> str:
    """What to do about a bad stage file: run the stage that writes it (sequence folder from the path)."""
    p = Path(path)
    seq = p.parent.parent.name if kind in ("cameras", "cameras_world", "cameras_final", "keypoints2d", "registration") \
        else p.parent.name
    return f"run `embodmocap {_WRITER[kind]} SESSION --seq {seq or 'NAME'}` to write it again"


# ------------------------------------------------------------------------------------------------
# Cameras: Stage II (VIO world), Stage III (scene world), Stage IV (after the contact alignment)


@dataclass(frozen=True, eq=False)
class CameraFile(NpzRecord):
    """One view's per-frame cameras, in one of three forms (``docs/formats.md``).

    Attributes:
        version: format version (1).
        K: (3, 3) RGB intrinsics, pixels.
        width, height: () RGB size, pixels.
        T_world_cam: (N, 4, 4) camera-to-world, OpenCV axes (the VIO world for ``cameras``, the
            scene's world for the other forms).
        raw_frames: (N,) raw capture frame of each sequence frame.
        K_depth, depth_width, depth_height: depth intrinsics and size (``cameras`` only).
        timestamps_s: (N,) sequence times (``cameras`` only).
        frame_times_s: (N,) each raw frame's own time after the view's slicing event (``cameras``;
            absent in files older than sub-frame sync).
        untracked: (N,) bool, no pose of its own (``cameras`` only).
        fps: () the sequence frame rate (``cameras``; absent in older files: :func:`sequence_fps`).
        time_offset_s: () sub-frame sync Stage IV applies to the view (``cameras_world`` only).
    """

    version: np.ndarray
    K: np.ndarray
    width: np.ndarray
    height: np.ndarray
    T_world_cam: np.ndarray
    raw_frames: np.ndarray
    K_depth: np.ndarray | None = None
    depth_width: np.ndarray | None = None
    depth_height: np.ndarray | None = None
    timestamps_s: np.ndarray | None = None
    frame_times_s: np.ndarray | None = None
    untracked: np.ndarray | None = None
    fps: np.ndarray | None = None
    time_offset_s: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        return len(self.T_world_cam)


_CAMERA_KEYS = ("K", "width", "height", "T_world_cam", "raw_frames")
_CAMERA_FORM_KEYS: dict[str, tuple[str, ...]] = {
    "cameras": _CAMERA_KEYS + ("K_depth", "depth_width", "depth_height", "timestamps_s", "untracked"),
    "cameras_world": _CAMERA_KEYS,
    "cameras_final": _CAMERA_KEYS,
}
_CAMERA_SHAPES = {"K": (3, 3), "width": (), "height": (), "T_world_cam": ("N", 4, 4), "raw_frames": ("N",),
                  "K_depth": (3, 3), "depth_width": (), "depth_height": (), "timestamps_s": ("N",),
                  "frame_times_s": ("N",), "untracked": ("N",), "fps": (), "time_offset_s": ()}


def camera_form(path: str | Path) -> CameraForm:
    """The form of a camera file from its name (``cameras.npz`` -> ``cameras``)."""
    stem = Path(path).stem
    if stem not in _CAMERA_FORM_KEYS:
        raise ValueError(f"{path}: not a camera file name (cameras, cameras_world, cameras_final .npz)")
    return stem  # type: ignore[return-value]


def read_cameras(path: str | Path, form: CameraForm | None = None) -> CameraFile:
    """Read and check a view's camera file; ``form`` defaults to the one the file name says."""
    path = Path(path)
    form = form or camera_form(path)
    fix = _fix(path, form)
    d = load_npz(path, what=f"{form}.npz", fix=fix, required=_CAMERA_FORM_KEYS[form])
    check_shapes(path, d, _CAMERA_SHAPES, fix)
    check_finite(path, d, ("K", "T_world_cam"), fix)
    return CameraFile(**record_fields(CameraFile, d))


def write_cameras(path: str | Path, cams: CameraFile) -> Path:
    """Write a camera file atomically (the keys that are not None)."""
    write_npz(path, **cams.arrays())
    return Path(path)


def sequence_fps(seq_root_or_cameras) -> float:
    """The sequence frame rate: Stage II's ``<v1>/cameras.npz`` ``fps`` key, or, for a file
    written before that key existed, Stage II's manifest figure ``fps``.

    Args:
        seq_root_or_cameras: the sequence folder (``sequences/<seq>``, or a ``SequenceLayout``'s
            ``root``), or a ``cameras.npz`` path.
    """
    x = seq_root_or_cameras
    p = Path(x) if isinstance(x, (str, Path)) else Path(x.root)  # a SequenceLayout
    cams_path = p if p.suffix == ".npz" else SequenceLayout(p).view("v1").cameras
    seq_root = cams_path.parent.parent
    cams = read_cameras(cams_path, "cameras")
    if cams.fps is not None:
        return float(cams.fps)
    try:
        return float(read_stage_record(SequenceLayout(seq_root).manifest).figures["fps"])
    except (InputError, KeyError, ValueError, TypeError) as err:
        raise InputError(cams_path, "no frame rate: no `fps` key here and none in the Stage II manifest",
                         _fix(cams_path, "cameras")) from err


# ------------------------------------------------------------------------------------------------
# 2D keypoints (Stage II)


@dataclass(frozen=True, eq=False)
class Keypoints2DFile(NpzRecord):
    """The performer's 2D keypoints of one view.

    Attributes:
        version: 1.
        keypoints: (T, 17, 3) COCO-17 pixels x, y and confidence (0 = not seen).
        boxes: (T, 4) x1, y1, x2, y2 pixels (NaN where not seen).
        raw_frames: (T,) raw capture frame of each sequence frame.
        seen: (T,) bool, the performer was seen.
        track_id: () the performer's track (-1 = none).
        layout: () str, the detector's keypoint layout (``COCO17`` when the file has none).
    """

    version: np.ndarray
    keypoints: np.ndarray
    boxes: np.ndarray
    raw_frames: np.ndarray
    seen: np.ndarray
    track_id: np.ndarray
    layout: np.ndarray


def read_keypoints2d(path: str | Path) -> Keypoints2DFile:
    """Read and check a view's ``keypoints2d.npz`` (a file without ``layout`` reads as COCO17)."""
    path = Path(path)
    fix = _fix(path, "keypoints2d")
    d = load_npz(path, what="keypoints2d.npz", fix=fix, required=("keypoints", "boxes", "raw_frames", "seen"))
    d.setdefault("track_id", np.int64(-1))
    d.setdefault("layout", np.array("COCO17"))
    check_shapes(path, d, {"keypoints": ("T", 17, 3), "boxes": ("T", 4), "raw_frames": ("T",), "seen": ("T",),
                           "track_id": (), "layout": ()}, fix)
    return Keypoints2DFile(**record_fields(Keypoints2DFile, d))


def write_keypoints2d(path: str | Path, kp: Keypoints2DFile) -> Path:
    write_npz(path, **kp.arrays())
    return Path(path)


# ------------------------------------------------------------------------------------------------
# Registration (Stage III)


@dataclass(frozen=True, eq=False)
class RegistrationFile(NpzRecord):
    """Registration of a view's sampled frames into the scene model (``docs/formats.md``).

    Attributes:
        version: 1 or 2 (files of version 1 read with every frame ``accepted``, ``run`` 0).
        attempted, attempted_inliers: (A,) frames tried and their inliers (0 = not registered).
        t: (R,) registered sequence frames.
        T_world_cam: (R, 4, 4) registered camera-to-world poses.
        inliers, reproj_error_px: (R,) per registered frame.
        match_frames, match_xy, match_xyz: (M,), (M, 2), (M, 3) the inlier 2D-3D matches.
        accepted: (R,) bool, consistent with the VIO (and on the whole chain's offset); run: (R,) run label.
        off_chain: (R,) bool, kept by the run check but off the whole chain's offset (version 3;
            all False when read from older files).
        T_world_vio_performer: (4, 4) or None: the view's offset when it was placed through the
            performer (its own registrations disagreed with its VIO; version 3, optional).
    """

    version: np.ndarray
    attempted: np.ndarray
    attempted_inliers: np.ndarray
    t: np.ndarray
    T_world_cam: np.ndarray
    inliers: np.ndarray
    reproj_error_px: np.ndarray
    match_frames: np.ndarray
    match_xy: np.ndarray
    match_xyz: np.ndarray
    accepted: np.ndarray
    run: np.ndarray
    off_chain: np.ndarray | None = None
    T_world_vio_performer: np.ndarray | None = None


def read_registration(path: str | Path) -> RegistrationFile:
    """Read and check a view's ``registration.npz`` (versions 1 to 3)."""
    path = Path(path)
    fix = _fix(path, "registration")
    keys = ("attempted", "attempted_inliers", "t", "T_world_cam", "inliers", "reproj_error_px",
            "match_frames", "match_xy", "match_xyz")
    d = load_npz(path, what="registration.npz", fix=fix, required=keys, versions=REGISTRATION_VERSIONS)
    if "accepted" not in d:  # written before the VIO check: every frame counts
        d["accepted"] = np.ones(len(d["t"]), dtype=bool)
        d["run"] = np.zeros(len(d["t"]), dtype=np.int64)
    if "off_chain" not in d:  # written before the whole-chain check (version 2)
        d["off_chain"] = np.zeros(len(d["t"]), dtype=bool)
    if "T_world_vio_performer" in d:
        check_shapes(path, d, {"T_world_vio_performer": (4, 4)}, fix)
    check_shapes(path, d, {"attempted": ("A",), "attempted_inliers": ("A",), "t": ("R",), "T_world_cam": ("R", 4, 4),
                           "inliers": ("R",), "reproj_error_px": ("R",), "match_frames": ("M",),
                           "match_xy": ("M", 2), "match_xyz": ("M", 3), "accepted": ("R",), "run": ("R",),
                           "off_chain": ("R",)}, fix)
    return RegistrationFile(**record_fields(RegistrationFile, d))


def write_registration(path: str | Path, reg: RegistrationFile) -> Path:
    write_npz(path, **reg.arrays())
    return Path(path)


# ------------------------------------------------------------------------------------------------
# 3D keypoints and world joints (Stage IV)


@dataclass(frozen=True, eq=False)
class Keypoints3DFile(NpzRecord):
    """Triangulated COCO-17 keypoints (``docs/formats.md``, ``keypoints3d.npz``).

    Attributes:
        version: 1.
        points: (T, 17, 3) world metres, NaN where not triangulated.
        conf: (T, 17) confidence in [0, 1].
        reproj_err_px: (T, 17, V) per view; filled: (T, 17) bool; views: (V,) str.
        keypoints2d: (T, V, 17, 3) the 2D keypoints as triangulated (swaps undone).
        swapped: (T, V, G) bool; swap_groups: (G,) str.
        one_view: () bool, True when the points were lifted from one view with its depth (a
            one-phone sequence, V = 1) instead of triangulated.
    Only ``points`` and ``conf`` are required; older files may lack the rest (then None).
    """

    version: np.ndarray
    points: np.ndarray
    conf: np.ndarray
    reproj_err_px: np.ndarray | None = None
    filled: np.ndarray | None = None
    views: np.ndarray | None = None
    keypoints2d: np.ndarray | None = None
    swapped: np.ndarray | None = None
    swap_groups: np.ndarray | None = None
    one_view: np.ndarray | None = None


def read_keypoints3d(path: str | Path) -> Keypoints3DFile:
    """Read and check ``keypoints3d.npz``."""
    path = Path(path)
    fix = _fix(path, "keypoints3d")
    d = load_npz(path, what="keypoints3d.npz", fix=fix, required=("points", "conf"))
    check_shapes(path, d, {"points": ("T", 17, 3), "conf": ("T", 17), "reproj_err_px": ("T", 17, "V"),
                           "filled": ("T", 17), "views": ("V",), "keypoints2d": ("T", "V", 17, 3),
                           "swapped": ("T", "V", "G"), "swap_groups": ("G",)}, fix)
    return Keypoints3DFile(**record_fields(Keypoints3DFile, d))


def write_keypoints3d(path: str | Path, k3: Keypoints3DFile) -> Path:
    write_npz(path, **k3.arrays())
    return Path(path)


@dataclass(frozen=True, eq=False)
class WorldJointsFile(NpzRecord):
    """Joints of the final body (``joints_world.npz``).

    Attributes:
        version: 1.
        joints: (T, 24, 3) SMPL joints, world metres.
        coco17: (T, 17, 3) COCO-17 keypoints of the body, world metres.
        frames: (T,) sequence frames (``0..T-1`` for files written without it).
    """

    version: np.ndarray
    joints: np.ndarray
    coco17: np.ndarray
    frames: np.ndarray


def read_world_joints(path: str | Path) -> WorldJointsFile:
    """Read and check ``joints_world.npz``."""
    path = Path(path)
    fix = _fix(path, "joints_world")
    d = load_npz(path, what="joints_world.npz", fix=fix, required=("joints", "coco17"))
    d.setdefault("frames", np.arange(len(d["joints"]), dtype=np.int64))
    check_shapes(path, d, {"joints": ("T", 24, 3), "coco17": ("T", 17, 3), "frames": ("T",)}, fix)
    return WorldJointsFile(**record_fields(WorldJointsFile, d))


def write_world_joints(path: str | Path, wj: WorldJointsFile) -> Path:
    write_npz(path, **wj.arrays())
    return Path(path)
