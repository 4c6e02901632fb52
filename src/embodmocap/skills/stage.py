"""``embodmocap skills``: cut a fitted sequence into skill clips and write ``skills.json``.

Reads (through :class:`SessionLayout`): ``sequences/<seq>/smpl_world.npz``, the session's body
model and the sequence's scene mesh (the simplified one when Stage I wrote it). Writes
``sequences/<seq>/skills/skills.json`` (:func:`embodmocap.io.stage_files.write_skills`) and the stage manifest
``sequences/<seq>/skills/manifest.json``: the one step ``clips`` is skipped when the motion, the
mesh, the body model and the settings are unchanged (``--force`` redoes it); the file is written
atomically, so an interrupted run leaves the old file or none. ``run(config, session, seq, force=)``
has the stages' shape; the decisions are pure functions in :mod:`embodmocap.skills.solve`.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from embodmocap.errors import InputError
from embodmocap.io.layout import SessionLayout
from embodmocap.io.stage_manifest import StageManifest, tracked_stage
from embodmocap.skills.config import SkillsConfig
from embodmocap.skills.solve import clip_figures, clips_of_motion  # noqa: F401 (re-exported)
from embodmocap.skills.steps import STEPS

log = logging.getLogger(__name__)


def skills_dir(layout: SessionLayout, seq: str) -> Path:
    """Where ``embodmocap skills`` writes one sequence's clips."""
    return layout.sequence(seq).skills_dir


def scene_mesh_path(layout: SessionLayout, scene: str) -> Path:
    """The sequence's scene mesh: the simplified one when Stage I wrote it, else the raw one."""
    sc = layout.scene(scene)
    for p in (sc.mesh_simplified, sc.mesh_raw):
        if p.is_file():
            return p
    raise InputError(sc.mesh_raw, "missing scene mesh needed to find the surfaces the body touches",
                     f"run `embodmocap scene {layout.root}` first")


@dataclass(frozen=True)
class SkillsOutputs:
    """What ``embodmocap skills`` produced for one sequence."""

    name: str
    path: Path
    """``skills.json``."""
    figures: dict
    """Clip counts, as in the stage manifest."""
    skipped: tuple[str, ...]
    """Steps that were up to date and not redone."""


@tracked_stage
def run(config: SkillsConfig, session: str | Path, seq: str | None = None, *, force: bool = False) -> SkillsOutputs:
    """Find the skill clips of sequence ``seq`` of ``session`` (the only one when None)."""
    from embodmocap.body.model import load_body_model
    from embodmocap.io.manifest import load_manifest
    from embodmocap.io.mesh_file import read_mesh_ply
    from embodmocap.io.smpl_file import read_smpl_npz
    from embodmocap.io.stage_files import SkillsFile, write_skills

    layout = SessionLayout(Path(session))
    manifest = load_manifest(layout.manifest)
    entry = manifest.sequence(seq)
    sl = layout.sequence(entry.name)
    if not sl.smpl_world.is_file():
        raise InputError(sl.smpl_world, "missing world SMPL motion",
                         f"run `embodmocap motion {layout.root} --seq {entry.name}` first")
    mesh_path = scene_mesh_path(layout, entry.scene)
    out_dir = skills_dir(layout, entry.name)
    out_dir.mkdir(parents=True, exist_ok=True)
    inputs = [sl.smpl_world, mesh_path, manifest.body_model]
    sm = StageManifest(sl.skills_manifest, "skills", {"skills": asdict(config)}, inputs=inputs, root=layout.root)
    fp = STEPS.fingerprint("clips", config, reads={"sequences/<seq>/smpl_world.npz": sl.smpl_world,
                                                   "scene mesh": mesh_path, "body model": manifest.body_model})
    path = sl.skills_json
    with sm.step("clips", fp, force=force) as st:
        if st.run:
            params, _frames = read_smpl_npz(sl.smpl_world)
            body = load_body_model(manifest.body_model)
            mv, mf, _ = read_mesh_ply(mesh_path)
            clips, surfaces = clips_of_motion(params, body, np.asarray(mv), np.asarray(mf), config)
            write_skills(path, SkillsFile(layout.root.name, entry.name, float(params.fps), len(params), clips,
                                          asdict(config)))
            st.record([path], clip_figures(clips, surfaces))
    log.info("skills for %s: %s", entry.name, path)
    return SkillsOutputs(entry.name, path, sm.figures(), tuple(sm.skipped))


def find_skills(session: str | Path, seq: str | None = None, *, config: SkillsConfig = SkillsConfig(),
                force: bool = False) -> Path:
    """:func:`run`, for scripts written before it: returns the path of ``skills.json``."""
    return run(config, session, seq, force=force).path
