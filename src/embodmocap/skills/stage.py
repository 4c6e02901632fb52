"""``embodmocap skills``: cut a fitted sequence into skill clips and write ``skills.json``.

Reads (through :class:`SessionLayout`): ``sequences/<seq>/smpl_world.npz``, the session's body
model and the sequence's scene mesh (the simplified one when Stage I wrote it). Writes
``sequences/<seq>/skills/skills.json`` (:mod:`embodmocap.skills.files`) and the stage manifest
``sequences/<seq>/skills/manifest.json``: the one step ``clips`` is skipped when the motion, the
mesh, the body model and the settings are unchanged (``--force`` redoes it); the file is written
atomically, so an interrupted run leaves the old file or none.
"""

from __future__ import annotations

import logging
from dataclasses import asdict
from pathlib import Path

import numpy as np

from embodmocap.errors import InputError
from embodmocap.io.layout import SessionLayout
from embodmocap.io.stage_manifest import StageManifest, fingerprint, path_fingerprint, tracked_stage
from embodmocap.skills.config import SkillsConfig

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


def clips_of_motion(params, body, mesh_vertices, mesh_faces, cfg: SkillsConfig = SkillsConfig()):
    """The skill clips of a world motion in a scene mesh (no files): ``(clips, surfaces)``.

    Args:
        params: :class:`~embodmocap.types.SmplParams` in the mesh's world (Z up, metres).
        body: the body model.
        mesh_vertices, mesh_faces: (N, 3), (F, 3) scene mesh.
        cfg: settings.
    """
    import torch

    from embodmocap.skills.clips import find_clips
    from embodmocap.skills.contact import body_contacts, find_surfaces, part_vertex_ids

    # The lowest body point over the motion is a floor height hint (the cap above it drops ceilings).
    step = max(len(params) // 64, 1)
    with torch.no_grad():
        v = body.forward(params.betas, params.global_orient[::step], params.body_pose[::step], params.transl[::step])
    hint = float(v.vertices[..., 2].min())
    surfaces = find_surfaces(mesh_vertices, mesh_faces, hint, cfg)
    contacts = body_contacts(params, body, surfaces, part_vertex_ids(body, params.betas), cfg)
    return find_clips(contacts, surfaces, float(params.fps), cfg), surfaces


@tracked_stage
def find_skills(session: str | Path, seq: str | None = None, *, config: SkillsConfig = SkillsConfig(),
                force: bool = False) -> Path:
    """Find the skill clips of sequence ``seq`` of ``session``; returns the path of ``skills.json``."""
    from embodmocap.body.model import load_body_model
    from embodmocap.io.manifest import load_manifest
    from embodmocap.io.mesh_file import read_mesh_ply
    from embodmocap.io.smpl_file import read_smpl_npz
    from embodmocap.skills.files import SkillsFile, write_skills

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
    fp = fingerprint(asdict(config), *[path_fingerprint(p) for p in inputs if p is not None])
    path = sl.skills_json
    with sm.step("clips", fp, force=force) as st:
        if st.run:
            params, _frames = read_smpl_npz(sl.smpl_world)
            body = load_body_model(manifest.body_model)
            mv, mf, _ = read_mesh_ply(mesh_path)
            clips, surfaces = clips_of_motion(params, body, np.asarray(mv), np.asarray(mf), config)
            write_skills(path, SkillsFile(layout.root.name, entry.name, float(params.fps), len(params), clips,
                                          asdict(config)))
            counts = {}
            for c in clips:
                counts[c.skill] = counts.get(c.skill, 0) + 1
            st.record([path], {"clips": len(clips), **{f"clips_{k}": v for k, v in sorted(counts.items())},
                               "surfaces": len(surfaces.boxes)})
    log.info("skills for %s: %s", entry.name, path)
    return path
