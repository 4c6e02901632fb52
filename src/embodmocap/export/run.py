"""``embodmocap export``: read a sequence's Stage IV outputs and write one export format.

Reads, through :class:`SessionLayout` only: ``sequences/<seq>/smpl_world.npz`` (every format),
``joints_world.npz`` (csv), the scene mesh of the sequence's scene (glb, mimickit), the session
manifest (which scene, which body model). Writes under ``sequences/<seq>/export/`` unless ``out``
is given:

=========  ==========================  ===================================================
format     default output              contents
=========  ==========================  ===================================================
amass      ``<seq>_amass.npz``         AMASS-style SMPL params, Z up (:mod:`.amass`)
bvh        ``<seq>.bvh``               SMPL skeleton, Y up (:mod:`.bvh`)
glb        ``<seq>.glb``               scene + skinned animated body, Y up (:mod:`.gltf`)
mimickit   ``mimickit/`` (a folder)    motion pkl, skeleton json, scene OBJ + height map
csv        ``<seq>_joints.csv``        world joint positions per frame (:mod:`.csv_joints`)
trc        ``<seq>.trc``               OpenSim marker file of the world joints, Y up (:mod:`.trc`)
smplx      ``<seq>_smplx.npz``         SMPL-X-compatible params, hands zero (:mod:`.smplx_npz`)
robot      ``../robot/<robot>/``       robot motion: BeyondMimic CSV + npz, GMR pkl, scene
                                       MJCF, report (:mod:`embodmocap.robot`, extra ``robot``)
mjcf       ``mjcf/`` (a folder)        MuJoCo performer + scene heightfield + keyframes
                                       (:func:`embodmocap.sim.session.export_mjcf`, extra ``sim``)
training   ``SESSION/training/``       per-frame RGB, depth, cameras, camera-space SMPL, masks,
                                       keypoints, validity of every sequence and view
                                       (:mod:`.training`, ``docs/training.md``)
=========  ==========================  ===================================================
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from embodmocap.errors import InputError
from embodmocap.io.amass import read_amass, write_amass
from embodmocap.export.bvh import write_bvh
from embodmocap.export.csv_joints import write_joints_csv
from embodmocap.export.gltf import write_glb
from embodmocap.export.mimickit import write_mimickit
from embodmocap.export.config import ExportConfig
from embodmocap.io.layout import SessionLayout
from embodmocap.io.smpl_file import read_smpl_suspect, read_smpl_valid
from embodmocap.io.stage_files import read_world_joints
from embodmocap.progress import step

log = logging.getLogger(__name__)

#: The export formats, in the order the CLI lists them.
FORMATS: tuple[str, ...] = ("amass", "bvh", "glb", "mimickit", "csv", "robot", "mjcf", "training", "trc", "smplx")


def _need(path: Path, seq: str, session: Path, stage: str) -> Path:
    if not path.is_file():
        hint = {
            "motion": f"run `embodmocap motion {session} --seq {seq}` first",
            "scene": f"run `embodmocap scene {session}` first",
        }[stage]
        raise InputError(path, "missing file needed for the export", hint)
    return path


def _default_out(layout: SessionLayout, seq: str, to: str) -> Path:
    names = {"amass": f"{seq}_amass.npz", "bvh": f"{seq}.bvh", "glb": f"{seq}.glb", "mimickit": "mimickit", "csv": f"{seq}_joints.csv",
             "mjcf": "mjcf", "trc": f"{seq}.trc", "smplx": f"{seq}_smplx.npz"}
    return layout.sequence(seq).exports_dir / names[to]


def _scene_mesh(layout: SessionLayout, manifest, seq: str, prefer_simplified: bool) -> tuple:
    from embodmocap.io.mesh_file import read_mesh_ply

    scene = layout.scene(manifest.sequences[seq].scene)
    if prefer_simplified and scene.mesh_simplified.is_file():
        return read_mesh_ply(scene.mesh_simplified)
    return read_mesh_ply(_need(scene.mesh_raw, seq, layout.root, "scene"))


def _read_joints(path: Path, T: int) -> np.ndarray:
    joints = np.asarray(read_world_joints(path).joints, dtype=np.float64)
    if joints.shape != (T, 24, 3):
        raise InputError(path, f"joints {joints.shape} do not match the {T} frames of smpl_world.npz", "run the motion stage again")
    return joints


def export_sequence(session: str | Path, seq: str, to: str, out: str | Path | None = None, *,
                    config: ExportConfig = ExportConfig()) -> Path:
    """Export sequence ``seq`` of ``session`` to format ``to`` (one of :data:`FORMATS`).

    Returns the path written (a folder for ``mimickit``). Raises :class:`InputError` when a needed
    Stage IV (or Stage I) file is missing, naming the file and the command to run.
    """
    if to not in FORMATS:
        raise InputError(None, f"unknown export format {to!r}", f"choose one of {', '.join(FORMATS)}")
    with step(f"export {seq} as {to}"):
        return _export_sequence(session, seq, to, out, config)


def _export_sequence(session: str | Path, seq: str, to: str, out: str | Path | None, config: ExportConfig) -> Path:
    if to == "robot":
        return _export_robot(session, seq, out, config)
    if to == "training":
        return _export_training(session, seq, out, config)
    layout = SessionLayout(Path(session))
    seq_layout = layout.sequence(seq)
    params, frames = read_amass(_need(seq_layout.smpl_world, seq, layout.root, "motion"))
    out = Path(out) if out is not None else _default_out(layout, seq, to)
    log.info("exporting %s of %s (%d frames) as %s -> %s", seq, layout.root, len(params), to, out)

    # Every frame's flags travel with the motion: placed or not (``valid``), contradicted by a view (``suspect``).
    flags = (read_smpl_valid(seq_layout.smpl_world), read_smpl_suspect(seq_layout.smpl_world))
    if flags[0].all() and not flags[1].any():
        log.info("%s: every frame valid, none suspect", seq)
    else:
        log.info("%s: %d frames flagged invalid, %d suspect (the export carries the flags)", seq,
                 int((~flags[0]).sum()), int((flags[1] & flags[0]).sum()))
    if to == "amass":
        return write_amass(out, params, frames=frames, hands=config.amass_hands, flags=flags)
    if to == "csv":
        joints = _read_joints(_need(seq_layout.joints_world, seq, layout.root, "motion"), len(params))
        return write_joints_csv(out, joints, params.fps, frames, flags=flags)
    if to in ("trc", "smplx"):
        return _export_trc_smplx(seq_layout, layout.root, seq, to, out, params, frames, *flags)
    if to == "mjcf":
        from embodmocap.sim.config import SceneCollisionConfig
        from embodmocap.sim.session import export_mjcf

        return export_mjcf(layout.root, seq, out, scene=SceneCollisionConfig(heightmap_cell_m=config.heightmap_cell_m,
                                                                             collision=config.scene_collision))

    from embodmocap.body.model import load_body_model
    from embodmocap.io.manifest import load_manifest

    manifest = load_manifest(layout.manifest)
    if seq not in manifest.sequences:
        raise InputError(layout.manifest, f"no sequence {seq!r} in the manifest", f"use one of {sorted(manifest.sequences)}")
    model = load_body_model(manifest.body_model)
    if to == "bvh":
        return write_bvh(out, params, model, units=config.bvh_units, frames=frames)
    if to == "glb":
        return write_glb(out, params, model, _scene_mesh(layout, manifest, seq, prefer_simplified=False), frames=frames)
    # mimickit: a physics asset wants the lighter mesh when stage I wrote one.
    scene = _scene_mesh(layout, manifest, seq, prefer_simplified=True)
    return write_mimickit(out, params, model, scene, name=seq, loop_mode=config.mimickit_loop,
                          cell_m=config.heightmap_cell_m, frames=frames, flags=flags)


def _export_trc_smplx(seq_layout, root: Path, seq: str, to: str, out: Path, params, frames,
                      valid, suspect) -> Path:
    """``--to trc`` (the world joints, :mod:`.trc`) and ``--to smplx`` (:mod:`.smplx_npz`), each
    with the fit's ``valid`` and ``suspect`` flags (T,) bool."""
    if to == "smplx":
        from embodmocap.export.smplx_npz import write_smplx

        return write_smplx(out, params, frames=frames, valid=valid, suspect=suspect)
    from embodmocap.export.trc import write_trc

    joints = _read_joints(_need(seq_layout.joints_world, seq, root, "motion"), len(params))
    return write_trc(out, joints, params.fps, frames, valid=valid, suspect=suspect)


def _export_robot(session: str | Path, seq: str, out: str | Path | None, config: ExportConfig) -> Path:
    """``--to robot``: the same as ``embodmocap robot retarget`` (default output
    ``sequences/<seq>/robot/<robot>/``, or ``out``)."""
    from embodmocap.robot.stage import retarget_sequence

    return retarget_sequence(session, seq, robot=config.robot, robot_config_path=config.robot_config, out=out)


def _export_training(session: str | Path, seq: str | None, out: str | Path | None, config: ExportConfig) -> Path:
    """``--to training``: per-frame training data of the session's sequences (all of them when
    ``seq`` is None) in ``out`` (default ``SESSION/training/``; :mod:`embodmocap.export.training`)."""
    from embodmocap.export.training import export_training

    return export_training(session, seq, out, config=config)
