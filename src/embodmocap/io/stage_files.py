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

The sequence frame rate lives in Stage II's ``cameras.npz`` (key ``fps``); :func:`sequence_fps`
reads it, and falls back to Stage II's manifest figure for files written before the key existed.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path
from typing import Iterator, Literal

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.atomic import write_json, write_npz
from embodmocap.io.layout import SequenceLayout
from embodmocap.io.npz_file import check_finite, check_shapes, load_npz
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


class _FileRecord:
    """``np.load``-like access to a dataclass whose field names are a file's keys."""

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


def _take(cls, data: dict) -> dict:
    """The dataclass's fields from a file's arrays (None for the keys the file lacks)."""
    return {f.name: data.get(f.name) for f in fields(cls)}


# ------------------------------------------------------------------------------------------------
# Cameras: Stage II (VIO world), Stage III (scene world), Stage IV (after the contact alignment)


@dataclass(frozen=True, eq=False)
class CameraFile(_FileRecord):
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
    return CameraFile(**_take(CameraFile, d))


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
class Keypoints2DFile(_FileRecord):
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
    return Keypoints2DFile(**_take(Keypoints2DFile, d))


def write_keypoints2d(path: str | Path, kp: Keypoints2DFile) -> Path:
    write_npz(path, **kp.arrays())
    return Path(path)


# ------------------------------------------------------------------------------------------------
# Registration (Stage III)


@dataclass(frozen=True, eq=False)
class RegistrationFile(_FileRecord):
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
    return RegistrationFile(**_take(RegistrationFile, d))


def write_registration(path: str | Path, reg: RegistrationFile) -> Path:
    write_npz(path, **reg.arrays())
    return Path(path)


# ------------------------------------------------------------------------------------------------
# 3D keypoints and world joints (Stage IV)


@dataclass(frozen=True, eq=False)
class Keypoints3DFile(_FileRecord):
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
    return Keypoints3DFile(**_take(Keypoints3DFile, d))


def write_keypoints3d(path: str | Path, k3: Keypoints3DFile) -> Path:
    write_npz(path, **k3.arrays())
    return Path(path)


@dataclass(frozen=True, eq=False)
class WorldJointsFile(_FileRecord):
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
    return WorldJointsFile(**_take(WorldJointsFile, d))


def write_world_joints(path: str | Path, wj: WorldJointsFile) -> Path:
    write_npz(path, **wj.arrays())
    return Path(path)



# ------------------------------------------------------------------------------------------------
# JSON hand-over files: key frames (Stage I), sync and frame maps (Stage II), calibration and the
# final sync (Stage III), and the stage manifests' records. Each is written by one stage only.

#: Largest hand-over JSON read (a frame map of a 10-minute 60 fps sequence is a few MB).
MAX_STAGE_JSON_BYTES = 256 << 20
#: Version Stage II writes in ``sync.json`` and Stage III in ``final_sync.json``; version-1 files
#: (before the geometric sync) still read.
SYNC_RECORD_VERSION = 2
SYNC_VERSIONS = (1, SYNC_RECORD_VERSION)
#: Versions of ``calibration.json``, ``keyframes.json`` and ``frame_map.json`` this reader knows.
CALIBRATION_VERSIONS = (1,)
KEYFRAMES_VERSIONS = (1,)
FRAME_MAP_VERSION = 1


def _read_doc(path: str | Path, what: str, fix: str, versions: tuple = ()) -> dict:
    """A hand-over JSON object (bounded read), its ``version`` one of ``versions`` when given."""
    from embodmocap.io.jsonfile import read_json

    doc = read_json(path, max_bytes=MAX_STAGE_JSON_BYTES, what=what, fix=fix)
    if not isinstance(doc, dict):
        raise InputError(path, f"{what} is not a JSON object", fix)
    if versions and doc.get("version") not in versions:
        raise InputError(path, f"{what} is version {doc.get('version')!r}; this package reads version "
                         f"{' or '.join(map(str, versions))}", fix)
    return doc


def _seq_fix(path: Path, command: str) -> str:
    return f"run `embodmocap {command} SESSION --seq {Path(path).parent.name or 'NAME'}` to write it again"


@dataclass(frozen=True, eq=False)
class SyncFile:
    """A sync record: Stage II's ``sync.json`` (laser and manual sources, the slicing) or Stage III's
    ``final_sync.json`` (the same plus the geometric source, the agreement and the final ``chosen``;
    ``docs/formats.md``).

    Attributes:
        version: 1 or 2.
        views: view -> its slicing event (``frame``, ``confidence``, ``method``, ...).
        record: the whole JSON object as written.
    """

    version: int
    views: dict
    record: dict

    @property
    def chosen(self) -> dict:
        return self.record.get("chosen") or {}

    @property
    def final(self) -> bool:
        """Stage III made the final choice (``final_sync.json``, or an older session's ``sync.json``)."""
        return bool(self.chosen.get("final"))

    @property
    def residual_s(self) -> float:
        """The offset Stage IV applies to the second view on top of the slicing, seconds (0 for
        version-1 records and where none was chosen)."""
        if self.version != SYNC_RECORD_VERSION:
            return 0.0
        r = self.chosen.get("residual_s", 0.0)
        return float(r) if r is not None and np.isfinite(float(r)) else 0.0


def read_sync(path: str | Path) -> SyncFile:
    """Read and check a sync record (``sync.json`` or ``final_sync.json``)."""
    path = Path(path)
    final = path.name == "final_sync.json"
    fix = _seq_fix(path, "calibrate" if final else "sequence")
    doc = _read_doc(path, path.name, fix, SYNC_VERSIONS)
    if not isinstance(doc.get("views"), dict):
        raise InputError(path, f"{path.name} has no `views` object", fix)
    return SyncFile(int(doc["version"]), doc["views"], doc)


def read_final_sync(seq) -> SyncFile:
    """The sequence's final sync: Stage III's ``final_sync.json``, or, in sessions written before
    that file existed, ``sync.json`` (which Stage III then completed in place).

    Args:
        seq: the sequence's :class:`~embodmocap.io.layout.SequenceLayout`.
    """
    return read_sync(seq.final_sync if seq.final_sync.is_file() else seq.sync)


def write_sync(path: str | Path, record: dict) -> Path:
    """Write a sync record atomically (Stage II: ``sync.json``; Stage III: ``final_sync.json``)."""
    write_json(path, record)
    return Path(path)


@dataclass(frozen=True)
class FrameMap:
    """Map from sequence frames to the raw frames of one view (``frame_map.json``).

    Attributes:
        seq_times_s: (T,) float64 time of each sequence frame, seconds after the sync event.
        raw_frames: (T,) int64 raw frame index of this view nearest to each sequence time.
        dt_s: (T,) float64 ``|raw frame time - sequence time|``, seconds.
        dropped: (T,) bool, the nearest raw frame is more than half a frame period away (the
            frame that belonged there was dropped); the raw frame is still the nearest one.
        event_frame: raw frame index of the view's sync event (sequence time 0).
        event_time_s: the view's own timestamp of the event frame, seconds (its raw clock).
        fps: frame rate of the sequence timeline.
    """

    seq_times_s: NDArray[np.float64]
    raw_frames: NDArray[np.int64]
    dt_s: NDArray[np.float64]
    dropped: NDArray[np.bool_]
    event_frame: int = 0
    event_time_s: float = 0.0
    fps: float = 30.0

    def __post_init__(self) -> None:
        for name, dtype in (("seq_times_s", np.float64), ("raw_frames", np.int64), ("dt_s", np.float64), ("dropped", np.bool_)):
            a = np.array(getattr(self, name), dtype=dtype, copy=True)
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        n = len(self.seq_times_s)
        if any(getattr(self, k).shape != (n,) for k in ("raw_frames", "dt_s", "dropped")):
            raise ValueError("frame map arrays must all be (T,)")

    def __len__(self) -> int:
        return len(self.seq_times_s)

    @property
    def num_dropped(self) -> int:
        return int(self.dropped.sum())


def write_frame_map(path: str | Path, fm: FrameMap) -> Path:
    """Write a view's ``frame_map.json`` atomically."""
    write_json(path, {
        "version": FRAME_MAP_VERSION, "fps": fm.fps, "event_frame": fm.event_frame, "event_time_s": fm.event_time_s,
        "num_frames": len(fm), "seq_times_s": fm.seq_times_s.tolist(), "raw_frames": fm.raw_frames.tolist(),
        "dt_s": fm.dt_s.tolist(), "dropped": fm.dropped.tolist(),
    })
    return Path(path)


def read_frame_map(path: str | Path) -> FrameMap:
    """Read and check a view's ``frame_map.json``."""
    path = Path(path)
    fix = "delete the file to redo the slicing"
    obj = _read_doc(path, "frame_map.json", fix, (FRAME_MAP_VERSION,))
    try:
        fm = FrameMap(np.asarray(obj["seq_times_s"], float), np.asarray(obj["raw_frames"], np.int64),
                      np.asarray(obj["dt_s"], float), np.asarray(obj["dropped"], bool),
                      int(obj["event_frame"]), float(obj["event_time_s"]), float(obj["fps"]))
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(path, f"malformed frame map: {err}", fix) from err
    if len(fm) != obj.get("num_frames", len(fm)):
        raise InputError(path, f"frame map holds {len(fm)} frames but says num_frames = {obj['num_frames']}", fix)
    return fm


@dataclass(frozen=True, eq=False)
class CalibrationFile:
    """Stage III's ``calibration.json``: per-view offsets and the residual report (``docs/formats.md``).

    Attributes:
        version: 1.
        views: view -> its record (``T_world_vio`` (4, 4) as lists, ``refine_shift_m``, ``drift``, ...).
        warnings: the report's warnings.
        record: the whole JSON object as written.
    """

    version: int
    views: dict
    warnings: list
    record: dict

    def T_world_vio(self, view: str) -> NDArray[np.float64]:
        """(4, 4) the view's refined offset (its VIO world in the scene's world)."""
        return np.asarray(self.views[view]["T_world_vio"], dtype=np.float64)


def read_calibration(path: str | Path) -> CalibrationFile:
    """Read and check ``calibration.json`` (every view with a (4, 4) ``T_world_vio``)."""
    path = Path(path)
    fix = _seq_fix(path, "calibrate")
    doc = _read_doc(path, "calibration.json", fix, CALIBRATION_VERSIONS)
    views = doc.get("views")
    if not isinstance(views, dict):
        raise InputError(path, "calibration.json has no `views` object", fix)
    for v, rec in views.items():
        try:
            ok = np.asarray(rec["T_world_vio"], dtype=np.float64).shape == (4, 4)
        except (KeyError, TypeError, ValueError):
            ok = False
        if not ok:
            raise InputError(path, f"view {v} has no 4x4 `T_world_vio`", fix)
    return CalibrationFile(int(doc["version"]), views, list(doc.get("warnings", [])), doc)


def write_calibration(path: str | Path, report: dict) -> Path:
    """Write ``calibration.json`` atomically (Stage III's ``refine`` step)."""
    write_json(path, report)
    return Path(path)


@dataclass(frozen=True, eq=False)
class KeyframesFile(_FileRecord):
    """Stage I's ``keyframes.json``: the scene capture's key frames.

    Attributes:
        version: 1.
        frame_ids: (K,) capture frames chosen.
        T_world_cam: (K, 4, 4) their poses (VIO world).
        sharpness: (K,) their sharpness.
        record: the whole JSON object as written (``capture``, ``indoor``, ...).
    """

    version: int
    frame_ids: NDArray[np.int64]
    T_world_cam: NDArray[np.float64]
    sharpness: NDArray[np.float64]
    record: dict


def read_keyframes(path: str | Path) -> KeyframesFile:
    """Read and check ``keyframes.json``."""
    path = Path(path)
    fix = f"re-run `embodmocap scene SESSION --scene {path.parent.name or 'NAME'}`"
    data = _read_doc(path, "keyframes.json", fix, KEYFRAMES_VERSIONS)
    try:
        return KeyframesFile(int(data["version"]), np.asarray(data["frame_ids"], dtype=np.int64),
                             np.asarray(data["T_world_cam"], dtype=np.float64).reshape(-1, 4, 4),
                             np.asarray(data["sharpness"], dtype=np.float64), data)
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(path, f"malformed keyframes.json ({err})", fix) from err


def write_keyframes(path: str | Path, record: dict) -> Path:
    """Write ``keyframes.json`` atomically (Stage I's ``keyframes`` step)."""
    write_json(path, record)
    return Path(path)


@dataclass(frozen=True)
class StageManifestRecord:
    """What other modules read of a stage manifest (``manifest.json``, ``calibrate_manifest.json``,
    ``motion_manifest.json``, the downstream commands' ``manifest.json``): written by
    :class:`embodmocap.io.stage_manifest.StageManifest` only.

    Attributes:
        stage: the stage's name; status: ``ok``, ``failed``, ``running``, ``interrupted``.
        config: the resolved settings; figures: the quality figures; steps: one record per step.
    """

    stage: str
    status: str
    config: dict
    figures: dict
    steps: dict


def read_stage_record(path: str | Path) -> StageManifestRecord:
    """Read a stage manifest's record (any manifest version: missing parts are empty)."""
    doc = _read_doc(path, "stage manifest", "run the stage again to rewrite it")
    from_doc = {k: doc.get(k) if isinstance(doc.get(k), dict) else {} for k in ("config", "figures", "steps")}
    return StageManifestRecord(str(doc.get("stage", "")), str(doc.get("status", "")), **from_doc)


#: Versions of ``evaluation.json`` (``embodmocap evaluate``) this reader knows.
EVALUATION_VERSIONS = (1,)


def read_evaluation(path: str | Path) -> dict:
    """``evaluation.json``, checked for its version (``embodmocap evaluate`` writes it; keys:
    ``docs/formats.md``, "Evaluation keys")."""
    return _read_doc(path, "evaluation.json", "run `embodmocap evaluate SESSION` to write it again", EVALUATION_VERSIONS)


def read_report_json(path: str | Path, what: str, command: str) -> dict:
    """A downstream command's JSON report (``robot_report.json``, ``sim_check.json``), bounded;
    ``command`` is what writes it again."""
    return _read_doc(path, what, f"run `{command}` to write it again")
