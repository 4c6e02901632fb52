"""``skills.json``: the skill clips of one sequence (typed reader and writer; docs/formats.md).

The contract between the clip finder (writer) and the skill tasks (reader): world = the session's
Z-up metric world of ``smpl_world.npz``; frame ranges ``[start, end)`` index its rows.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from embodmocap.errors import InputError
from embodmocap.io.atomic import write_json
from embodmocap.skills.boxes import CORNER_SIGNS, Box

FORMAT = "embodmocap.skills/1"
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
    def of_box(cls, box: Box, name: str | None = None) -> "SkillObject":
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
    format: str = FORMAT

    def of_skill(self, skill: str) -> list[SkillClip]:
        return [c for c in self.clips if c.skill == skill]


def _floats(a) -> list[float]:
    return [round(float(x), 6) for x in np.asarray(a, dtype=np.float64).ravel()]


def to_json(sf: SkillsFile) -> dict[str, Any]:
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
    write_json(path, to_json(sf))
    return Path(path)


def read_skills(path: str | Path) -> SkillsFile:
    """Read and check ``skills.json``.

    Raises:
        InputError: missing or unreadable file, wrong format tag, a clip with an unknown skill, a
            frame range outside ``[0, n_frames]``, or an object whose corners do not match its box.
    """
    path = Path(path)
    fix = "run `embodmocap skills SESSION --seq NAME --force` to write it again"
    if not path.is_file():
        raise InputError(path, "skills file not found", "run `embodmocap skills SESSION --seq NAME` first")
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(path, f"unreadable skills file ({e})", fix) from None
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise InputError(path, f"format is {d.get('format') if isinstance(d, dict) else None!r}, expected {FORMAT!r}", fix)
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
