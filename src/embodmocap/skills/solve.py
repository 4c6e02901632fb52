"""The skill clip finder's decisions as pure functions: a world motion, the body model and the
scene mesh in, the clips out; no paths, no file I/O (:mod:`embodmocap.skills.stage` reads and writes)."""

from __future__ import annotations

from embodmocap.skills.config import SkillsConfig


def clips_of_motion(params, body, mesh_vertices, mesh_faces, cfg: SkillsConfig = SkillsConfig()):
    """The skill clips of a world motion in a scene mesh: ``(clips, surfaces)``.

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


def clip_figures(clips, surfaces) -> dict:
    """The manifest's figures of a run: clips in all, clips per skill, surfaces found."""
    counts: dict[str, int] = {}
    for c in clips:
        counts[c.skill] = counts.get(c.skill, 0) + 1
    return {"clips": len(clips), **{f"clips_{k}": v for k, v in sorted(counts.items())}, "surfaces": len(surfaces.boxes)}
