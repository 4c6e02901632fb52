"""Typed readers and writers of the JSON files one stage hands to another (imported from
:mod:`embodmocap.io.stage_files` too, where the npz hand-over files are).

Each file has one writer: key frames (Stage I's ``keyframes.json``), sync and frame maps (Stage II's
``sync.json``, ``frame_map.json``), calibration and the final sync (Stage III's ``calibration.json``,
``final_sync.json``), the stage manifests' records (:class:`embodmocap.io.stage_manifest.StageManifest`),
the evaluation and the downstream reports, and ``skills.json`` (``embodmocap skills``). A reader
checks the version and the keys and raises one :class:`~embodmocap.errors.InputError` naming the
file and the command that writes it again.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.atomic import write_json
from embodmocap.io.npz_file import NpzRecord

#: Corner order of a box in ``skills.json`` (and of :class:`embodmocap.skills.boxes.Box`): signs
#: along the box axes, corner k = centre + R @ (sign_k * size / 2).
CORNER_SIGNS = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                         [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=np.float64)


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
class KeyframesFile(NpzRecord):
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


# ------------------------------------------------------------------------------------------------
# skills.json (`embodmocap skills`): the skill clips of one sequence. World = the session's Z-up
# metric world of smpl_world.npz; frame ranges [start, end) index its rows.

#: Format tag of ``skills.json`` (the version is its suffix).
SKILLS_FORMAT = "embodmocap.skills/1"
#: The skill labels a clip may carry.
SKILLS: tuple[str, ...] = ("follow", "sit", "climb", "lie", "prone", "support")


@dataclass(frozen=True)
class SkillObject:
    """The interacted object: the oriented bounding box of the scene surface around the contact."""

    name: str | None
    center: list[float]
    size: list[float]
    R_world_box: list[list[float]]
    top_z: float
    corners: list[list[float]]

    @classmethod
    def of_box(cls, box, name: str | None = None) -> "SkillObject":
        """From an :class:`embodmocap.skills.boxes.Box` (its centre, size, rotation, top and corners)."""
        return cls(name, _floats(box.center), _floats(box.size), [_floats(r) for r in box.R_world_box],
                   round(float(box.top_z), 6), [_floats(c) for c in box.corners()])


@dataclass(frozen=True)
class SkillTarget:
    """The skill's target: ``position`` (sit / climb / lie / prone root target, support surface
    centre), ``path`` (follow: 2D waypoints every ``path_dt_s``), ``facing`` (2D unit vector)."""

    position: list[float] | None = None
    path: list[list[float]] | None = None
    facing: list[float] | None = None


@dataclass(frozen=True)
class SkillClip:
    """One clip: label, frames ``[start, end)``, the hold ``[contact_start, contact_end)``, object, target."""

    id: str
    skill: str
    start: int
    end: int
    contact_start: int | None
    contact_end: int | None
    object: SkillObject | None
    target: SkillTarget
    parts: list[str] = field(default_factory=list)
    score: float = 1.0


@dataclass(frozen=True)
class SkillsFile:
    """The whole ``skills.json``."""

    session: str
    sequence: str
    fps: float
    n_frames: int
    clips: list[SkillClip]
    config: dict[str, Any] = field(default_factory=dict)
    format: str = SKILLS_FORMAT

    def of_skill(self, skill: str) -> list[SkillClip]:
        return [c for c in self.clips if c.skill == skill]


def _floats(a) -> list[float]:
    return [round(float(x), 6) for x in np.asarray(a, dtype=np.float64).ravel()]


def skills_to_json(sf: SkillsFile) -> dict[str, Any]:
    """The JSON object of ``sf`` (keys in the documented order)."""
    clips = []
    for c in sf.clips:
        o = None
        if c.object is not None:
            o = {"name": c.object.name, "center": c.object.center, "size": c.object.size,
                 "R_world_box": c.object.R_world_box, "top_z": c.object.top_z, "corners": c.object.corners}
        clips.append({"id": c.id, "skill": c.skill, "start": int(c.start), "end": int(c.end),
                      "contact_start": c.contact_start, "contact_end": c.contact_end, "object": o,
                      "target": {"position": c.target.position, "path": c.target.path, "facing": c.target.facing},
                      "parts": list(c.parts), "score": round(float(c.score), 4)})
    return {"format": sf.format, "session": sf.session, "sequence": sf.sequence, "fps": float(sf.fps),
            "n_frames": int(sf.n_frames), "clips": clips, "config": sf.config}


def write_skills(path: str | Path, sf: SkillsFile) -> Path:
    """Write ``skills.json`` atomically."""
    write_json(path, skills_to_json(sf))
    return Path(path)


def read_skills(path: str | Path) -> SkillsFile:
    """Read and check ``skills.json``.

    Raises:
        InputError: missing or unreadable file, wrong format tag, a clip with an unknown skill, a
            frame range outside ``[0, n_frames]``, or an object whose corners do not match its box.
    """
    import json

    path = Path(path)
    fix = "run `embodmocap skills SESSION --seq NAME --force` to write it again"
    if not path.is_file():
        raise InputError(path, "skills file not found", "run `embodmocap skills SESSION --seq NAME` first")
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(path, f"unreadable skills file ({e})", fix) from None
    if not isinstance(d, dict) or d.get("format") != SKILLS_FORMAT:
        raise InputError(path, f"format is {d.get('format') if isinstance(d, dict) else None!r}, expected {SKILLS_FORMAT!r}", fix)
    try:
        n = int(d["n_frames"])
        clips = []
        for c in d["clips"]:
            if c["skill"] not in SKILLS:
                raise InputError(path, f"clip {c.get('id')!r} has unknown skill {c['skill']!r}", f"use one of {', '.join(SKILLS)}")
            if not 0 <= int(c["start"]) < int(c["end"]) <= n:
                raise InputError(path, f"clip {c['id']!r} frames [{c['start']}, {c['end']}) outside [0, {n}]", fix)
            o = c.get("object")
            obj = None
            if o is not None:
                obj = SkillObject(o.get("name"), o["center"], o["size"], o["R_world_box"], float(o["top_z"]), o["corners"])
                want = np.asarray(obj.center) + (CORNER_SIGNS * np.asarray(obj.size) / 2) @ np.asarray(obj.R_world_box).T
                if np.abs(want - np.asarray(obj.corners)).max() > 1e-3:
                    raise InputError(path, f"clip {c['id']!r}: the object's corners do not match its box", fix)
            t = c.get("target") or {}
            clips.append(SkillClip(str(c["id"]), str(c["skill"]), int(c["start"]), int(c["end"]),
                                   None if c.get("contact_start") is None else int(c["contact_start"]),
                                   None if c.get("contact_end") is None else int(c["contact_end"]), obj,
                                   SkillTarget(t.get("position"), t.get("path"), t.get("facing")),
                                   list(c.get("parts", [])), float(c.get("score", 1.0))))
        return SkillsFile(str(d["session"]), str(d["sequence"]), float(d["fps"]), n, clips, dict(d.get("config", {})))
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(path, f"malformed skills file ({type(e).__name__}: {e})", fix) from None
