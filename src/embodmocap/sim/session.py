"""A fitted sequence as the simulator needs it: motion, body model, scene mesh, height field, MJCF.

Reads, through :class:`SessionLayout` only, ``sequences/<seq>/smpl_world.npz``, the session
manifest (scene and body model) and the scene mesh (``mesh_simplified.ply`` when Stage I wrote it,
else ``mesh_raw.ply``), like the other exports; for ``sim check`` also ``mesh_raw.ply`` beside the
simplified mesh, the full-resolution mesh it was made from (penetration depth is measured on it).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.geometry.heightmap import HeightMap
from embodmocap.io.heightmap_file import write_heightmap
from embodmocap.io.layout import SessionLayout
from embodmocap.sim.config import HumanoidConfig, SceneCollisionConfig
from embodmocap.sim.model import hinge_names, performer_mjcf, reference_qpos
from embodmocap.sim.scene import cached_convex_pieces, crop_scene, heightfield_mjcf, pieces_mjcf, support_heightmap
from embodmocap.types import SmplParams

log = logging.getLogger(__name__)

#: Version of the files this package writes (reference npz, sim_check.json).
SIM_FORMAT_VERSION = 1


@dataclass(frozen=True)
class SimSequence:
    """One fitted sequence and its scene.

    Attributes:
        session: the session folder; name: the sequence.
        params: world SMPL motion (Z up); frames: (T,) sequence frame numbers.
        body_model: the session's body model.
        scene_vertices: (N, 3), scene_faces: (F, 3) the scene mesh, world metres.
        inputs: the files it was read from (motion, scene mesh, body model), for fingerprints;
            empty for a sequence made in memory.
        detail_vertices: (N', 3), detail_faces: (F', 3) the full-resolution mesh the scene mesh
            was simplified from (Stage I's ``mesh_raw.ply``), world metres; None when the scene
            mesh is itself full resolution (or none was given).
    """

    session: Path
    name: str
    params: SmplParams
    frames: NDArray
    body_model: object
    scene_vertices: NDArray
    scene_faces: NDArray
    inputs: tuple[Path, ...] = ()
    detail_vertices: NDArray | None = None
    detail_faces: NDArray | None = None

    @property
    def rest_joints(self) -> NDArray[np.float64]:
        """(24, 3) rest joints for the fitted betas."""
        return self.body_model.rest_joints(self.params.betas)

    def with_params(self, params: SmplParams) -> "SimSequence":
        """The same sequence and scene with other motion (e.g. a constructed or repaired one)."""
        return SimSequence(self.session, self.name, params, np.arange(len(params)), self.body_model,
                           self.scene_vertices, self.scene_faces, detail_vertices=self.detail_vertices,
                           detail_faces=self.detail_faces)


def load_sequence(session: str | Path, seq: str | None = None, *, detail: bool = False) -> SimSequence:
    """Read sequence ``seq`` (or the session's only one) of ``session``; InputError names what is missing.

    With ``detail``, also the full-resolution mesh (``mesh_raw.ply``) when the scene mesh read is
    the simplified one (:attr:`SimSequence.detail_vertices`)."""
    from embodmocap.body.model import load_body_model
    from embodmocap.io.amass import read_amass
    from embodmocap.io.manifest import load_manifest
    from embodmocap.io.mesh_file import read_mesh_ply

    layout = SessionLayout(Path(session))
    manifest = load_manifest(layout.manifest)
    entry = manifest.sequence(seq)
    sl = layout.sequence(entry.name)
    if not sl.smpl_world.is_file():
        raise InputError(sl.smpl_world, "no fitted motion", f"run `embodmocap motion {layout.root} --seq {entry.name}` first")
    params, frames = read_amass(sl.smpl_world)
    scene = layout.scene(entry.scene)
    mesh = scene.mesh_simplified if scene.mesh_simplified.is_file() else scene.mesh_raw
    if not mesh.is_file():
        raise InputError(mesh, "no scene mesh", f"run `embodmocap scene {layout.root}` first")
    v, f, _ = read_mesh_ply(mesh)
    dv = df = None
    detail = scene.mesh_raw if detail and mesh != scene.mesh_raw and scene.mesh_raw.is_file() else None
    if detail is not None:
        dv, df, _ = read_mesh_ply(detail)
        dv, df = np.asarray(dv, dtype=np.float64), np.asarray(df, dtype=np.int64)
    return SimSequence(layout.root, entry.name, params, np.asarray(frames), load_body_model(manifest.body_model),
                       np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64),
                       inputs=tuple(Path(x) for x in (sl.smpl_world, mesh, detail, manifest.body_model) if x is not None),
                       detail_vertices=dv, detail_faces=df)


def body_vertices(body_model, params: SmplParams, chunk: int = 512) -> NDArray[np.float32]:
    """(T, V, 3) posed vertices of every frame, world metres (computed in chunks of frames)."""
    import torch

    out = []
    for s in range(0, len(params), chunk):
        e = min(s + chunk, len(params))
        with torch.no_grad():
            o = body_model.forward(params.betas, params.global_orient[s:e], params.body_pose[s:e], params.transl[s:e],
                                   dtype=torch.float32)
        out.append(o.vertices.numpy())
    return np.concatenate(out) if out else np.zeros((0, body_model.num_vertices, 3), np.float32)


def sequence_heightmap(sq: SimSequence, cfg: SceneCollisionConfig = SceneCollisionConfig(),
                       verts: NDArray | None = None) -> HeightMap:
    """The support height map under the sequence's footprint (see :func:`support_heightmap`)."""
    verts = body_vertices(sq.body_model, sq.params) if verts is None else verts
    flat = verts.reshape(-1, 3)
    lo, hi = flat[:, :2].min(axis=0) - cfg.margin_m, flat[:, :2].max(axis=0) + cfg.margin_m
    return support_heightmap(sq.scene_vertices, sq.scene_faces, float(flat[:, 2].max()) + cfg.cap_above_motion_m,
                             cell_m=cfg.heightmap_cell_m, xy_lo=lo, xy_hi=hi)


def scene_pieces(sq: SimSequence, cfg: SceneCollisionConfig = SceneCollisionConfig(),
                 verts: NDArray | None = None) -> list[tuple[NDArray, NDArray]]:
    """Convex pieces of the scene mesh around the sequence (the heightfield's footprint and cap),
    :func:`embodmocap.sim.scene.cached_convex_pieces`, cached under ``sequences/<seq>/sim/`` when the
    session folder exists."""
    verts = body_vertices(sq.body_model, sq.params) if verts is None else verts
    flat = verts.reshape(-1, 3)
    lo, hi = flat[:, :2].min(axis=0) - cfg.margin_m, flat[:, :2].max(axis=0) + cfg.margin_m
    v, f = crop_scene(sq.scene_vertices, sq.scene_faces, lo, hi, float(flat[:, 2].max()) + cfg.cap_above_motion_m)
    cache = None
    if SessionLayout(sq.session).manifest.is_file():
        cache = SessionLayout(sq.session).sequence(sq.name).sim_dir
    return cached_convex_pieces(v, f, cache, threshold=cfg.coacd_threshold, max_pieces=cfg.coacd_max_pieces,
                                resolution=cfg.coacd_resolution, convex_tolerance=cfg.convex_tolerance)


def sequence_mjcf(sq: SimSequence, hcfg: HumanoidConfig = HumanoidConfig(),
                  scfg: SceneCollisionConfig = SceneCollisionConfig(), *, keyframes: bool = True,
                  heightmap: HeightMap | None = None) -> tuple[str, HeightMap, NDArray]:
    """MJCF text of the performer in the scene; returns ``(xml, heightmap, reference qpos (T, NQ))``.

    The scene is the support heightfield, convex pieces of the mesh over the same footprint and
    under the same cap (``scfg.collision``: ``coacd`` or ``both``; cached in the sequence's
    ``sim/`` folder by mesh hash), or both."""
    need = heightmap is None or scfg.collision != "heightfield"
    verts = body_vertices(sq.body_model, sq.params) if need else None
    hm = sequence_heightmap(sq, scfg, verts) if heightmap is None else heightmap
    assets, geoms = [], []
    if scfg.collision in ("heightfield", "both"):
        asset, geom = heightfield_mjcf(hm)
        assets.append(asset)
        geoms.append(geom)
    if scfg.collision in ("coacd", "both"):
        pieces = scene_pieces(sq, scfg, verts)
        asset, geom = pieces_mjcf(pieces)
        assets.append(asset)
        geoms.append(geom)
        log.info("scene collision: %d convex pieces", len(pieces))
    asset, geom = "\n".join(assets), "\n".join(geoms)
    qpos = reference_qpos(sq.params, sq.rest_joints)
    times = np.arange(len(qpos)) / sq.params.fps
    xml = performer_mjcf(sq.body_model, sq.params.betas, hcfg, scene_assets=asset, scene_geoms=geom,
                         keyframes=qpos if keyframes else None, key_times=times, model_name=f"embodmocap_{sq.name}")
    return xml, hm, qpos


def export_mjcf(session: str | Path, seq: str | None = None, out: str | Path | None = None, *,
                humanoid: HumanoidConfig = HumanoidConfig(),
                scene: SceneCollisionConfig = SceneCollisionConfig()) -> Path:
    """Write the MuJoCo bundle of a sequence into the folder ``out`` (replaced atomically).

    Files: ``<seq>.xml`` (performer + scene heightfield and/or convex pieces, ``scene.collision``,
    + one keyframe per motion frame),
    ``<seq>_reference.npz`` (qpos per frame, fps, frames, joint names) and ``scene_heightfield.npz``
    (the support height map, :func:`embodmocap.export.mimickit.write_heightmap` format). Default
    ``out``: ``sequences/<seq>/export/mjcf``.
    """
    from embodmocap.io.atomic import atomic_dir, write_npz, write_text

    sq = load_sequence(session, seq)
    out = Path(out) if out is not None else SessionLayout(sq.session).sequence(sq.name).exports_dir / "mjcf"
    xml, hm, qpos = sequence_mjcf(sq, humanoid, scene)
    with atomic_dir(out) as tmp:
        write_text(tmp / f"{sq.name}.xml", xml)
        write_npz(tmp / f"{sq.name}_reference.npz", version=np.int64(SIM_FORMAT_VERSION), qpos=qpos,
                  fps=np.float64(sq.params.fps), frames=np.asarray(sq.frames), betas=np.asarray(sq.params.betas),
                  joint_names=np.array(["root"] + hinge_names()))
        write_heightmap(tmp / "scene_heightfield.npz", hm)
    log.info("wrote MuJoCo bundle %s (%d keyframes, heightfield %dx%d)", out, len(qpos), *hm.heights.shape)
    return out
