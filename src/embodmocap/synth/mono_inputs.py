"""The studio writes the monocular pipeline's ``precomputed`` inputs as real models would give them.

Scene model (Pi3-like), per chunk of ``chunk`` frames overlapping by ``overlap`` (the plan of
:func:`embodmocap.mono.files.plan_chunks`): the true cameras and a ray-cast point map of the true
scene *and* the true body (a point-map model sees the person too), at ``map_width`` x
``map_height``, then everything a model gets wrong:

- a random similarity per chunk (scale in ``scale_range``, any rotation, translation of a few
  metres): each chunk is in a frame and unit of its own;
- depth-dependent noise along each pixel's ray (relative std ``depth_noise`` x depth / 3 m), a
  small per-frame pose error (``pose_noise_deg``, ``centre_noise_m``), and a confidence that falls
  with depth;
- missing regions: ``holes`` random rectangles per frame with confidence 0 and junk points.

Human model: the truth in each camera, through :func:`embodmocap.synth.perception.body_prior`
with :class:`PriorNoiseConfig` (the realistic prior's errors: 7 deg per joint, depth 10 % off with
0.5 s correlation), or exact with ``noise=False``.

Needs the sequence's Stage II output (``<view>/cameras.npz`` for the sequence frames' raw frames).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from embodmocap.body.model import load_body_model
from embodmocap.geometry.raycast import cast_rays, raycasting_scene
from embodmocap.geometry.similarity import similarity_matrix, transform_poses
from embodmocap.io.ground_truth import read_truth_sequence
from embodmocap.io.layout import SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.mesh_file import read_mesh_ply
from embodmocap.io.stage_files import read_cameras
from embodmocap.mono.files import HumanSeq, chunk_file_name, plan_chunks, write_chunk, write_human_npz
from embodmocap.synth.perception import HARD_PRIOR_NOISE, PriorNoiseConfig, body_prior
from embodmocap.types import SmplParams

#: Named body-prior settings for the studio's camera-space body (benchmarks' ``--prior``):
#: ``realistic`` (7 deg per joint, depth 10 % off along the ray with 0.5 s correlation, the body's
#: size unchanged) and ``hard`` ("realistic+shape bias": plus a per-session shape error whose
#: height is ~3 % off, the depth made size-consistent with it).
PRIOR_PRESETS: dict[str, PriorNoiseConfig] = {"realistic": PriorNoiseConfig(), "hard": HARD_PRIOR_NOISE}


@dataclass(frozen=True)
class MonoInputConfig:
    """How the studio imitates a point-map model and a camera-space body regressor."""

    chunk: int = 64
    """Frames per chunk (as ``embodmocap mono --chunk``)."""
    overlap: int = 16
    """Frames shared by consecutive chunks (as ``--overlap``)."""
    map_width: int = 64
    """Point-map width, pixels (Pi3 works at a reduced resolution)."""
    map_height: int = 48
    """Point-map height, pixels."""
    noise: bool = True
    """Model errors on (False: exact point maps, cameras and body, only the per-chunk similarity)."""
    scale_range: tuple[float, float] = (0.3, 3.0)
    """Range of each chunk's random scale (log-uniform)."""
    depth_noise: float = 0.02
    """Relative depth noise at 3 m (grows linearly with depth)."""
    pose_noise_deg: float = 0.2
    """Std of the per-frame camera rotation error, degrees."""
    centre_noise_m: float = 0.005
    """Std of the per-frame camera centre error, metres (before the chunk's scale)."""
    holes: int = 2
    """Missing rectangles per frame (confidence 0, junk points), each up to a quarter of the map."""
    prior: PriorNoiseConfig = PriorNoiseConfig()
    """Errors of the camera-space body (used when ``noise``); named presets in :data:`PRIOR_PRESETS`
    (``realistic``, ``hard`` = with a persistent, size-consistent shape error)."""


def write_mono_inputs(session: str | Path, seq: str | None = None, view: str = "v1",
                      cfg: MonoInputConfig = MonoInputConfig(), seed: int = 0, human_only: bool = False) -> dict:
    """Write ``perception/<seq>/<view>/mono_scene/chunk_*.npz`` and ``mono_human.npz``.

    ``human_only``: write only ``mono_human.npz`` (no ray casting; the chunk files stay as they
    are). The random draws are the same as a full run's, so with the same seed the body gets the
    same errors as a full run with this ``cfg`` would give it (e.g. another ``prior`` on the same
    scene inputs).

    Returns the truth the tests need: ``T_scene_cam`` (T, 4, 4) true cameras of the sequence
    frames, ``chunk_similarity`` (list of (4, 4): true scene frame -> chunk frame).
    """
    lay = SessionLayout(Path(session))
    man = load_manifest(lay.manifest)
    entry = man.sequence(seq)
    cams = read_cameras(lay.sequence(entry.name).view(view).cameras)
    gt = read_truth_sequence(lay.ground_truth.sequence(entry.name))
    info = json.loads(lay.ground_truth.info.read_text())
    raw = np.asarray(cams.raw_frames, dtype=np.int64)
    T = len(raw)
    start = int(gt[f"{view}_motion_start"])
    offset = float(info.get("view_time_offset_frames", {}).get(view, 0.0))
    motion = np.clip(np.rint(start + raw + offset).astype(np.int64), 0, len(gt["transl"]) - 1)
    T_sc = np.asarray(gt[f"{view}_T_scene_cam"], dtype=np.float64)[raw]
    rng = np.random.default_rng(seed)
    model = load_body_model(man.body_model)
    fps = float(gt["fps"])
    truth = SmplParams(gt["betas"], gt["global_orient"][motion], gt["body_pose"][motion], gt["transl"][motion], fps=fps)
    with torch.no_grad():
        verts = model.from_params(truth, dtype=torch.float64).vertices.numpy()

    # true point maps: scene mesh (one BVH) and the body (one BVH per frame), nearest hit
    mv, mf, _ = read_mesh_ply(lay.ground_truth.scene_mesh(entry.scene))
    scene_bvh = raycasting_scene(mv, mf)
    W, H = cfg.map_width, cfg.map_height
    K = np.asarray(cams.K, dtype=np.float64)
    sx, sy = W / float(cams.width), H / float(cams.height)
    u = ((np.arange(W) + 0.5) / sx - 0.5 - K[0, 2]) / K[0, 0]
    v = ((np.arange(H) + 0.5) / sy - 0.5 - K[1, 2]) / K[1, 1]
    d_cam = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((H, W))), axis=-1).reshape(-1, 3)
    z = np.empty((T, H, W)) if not human_only else np.ones((T, H, W))
    faces = np.asarray(model.faces)
    for t in range(T if not human_only else 0):
        R, c = T_sc[t, :3, :3], T_sc[t, :3, 3]
        zs = cast_rays(scene_bvh, c, d_cam @ R.T)["t_hit"]
        zb = cast_rays(raycasting_scene((verts[t] - c) @ R, faces), np.zeros(3), d_cam)["t_hit"]
        z[t] = np.minimum(zs, zb).reshape(H, W)
    local = d_cam.reshape(H, W, 3)[None] * z[..., None]  # (T, H, W, 3)
    hit = np.isfinite(z)

    folder = lay.perception(entry.name, view).mono_scene_dir
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("chunk_*.npz") if not human_only else ():
        old.unlink()
    sims = []
    for a, b in plan_chunks(T, cfg.chunk, cfg.overlap):
        s = float(np.exp(rng.uniform(*np.log(cfg.scale_range))))
        G = similarity_matrix(np.float64(s), Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix(),
                              rng.normal(size=3) * 2.0)
        sims.append(G)
        poses = np.array(T_sc[a:b])
        pts = np.where(hit[a:b, ..., None], local[a:b], 0.0)
        conf = np.where(hit[a:b], 1.0, 0.0)
        if cfg.noise:
            n = b - a
            zz = np.where(hit[a:b], z[a:b], 0.0)
            pts = pts * (1.0 + rng.normal(size=zz.shape) * cfg.depth_noise * zz / 3.0)[..., None]
            dR = Rotation.from_rotvec(rng.normal(size=(n, 3)) * np.deg2rad(cfg.pose_noise_deg)).as_matrix()
            poses[:, :3, :3] = poses[:, :3, :3] @ dR
            poses[:, :3, 3] += rng.normal(size=(n, 3)) * cfg.centre_noise_m
            conf = conf * rng.uniform(0.7, 1.0, size=conf.shape) / (1.0 + (zz / 4.0) ** 2)
            for i in range(n):
                for _ in range(cfg.holes):
                    h, w = rng.integers(1, H // 2 + 1), rng.integers(1, W // 2 + 1)
                    r0, c0 = rng.integers(0, H - h + 1), rng.integers(0, W - w + 1)
                    conf[i, r0:r0 + h, c0:c0 + w] = 0.0
                    pts[i, r0:r0 + h, c0:c0 + w] = rng.uniform(0.1, 10.0, size=(h, w, 3))
        if not human_only:
            write_chunk(folder / chunk_file_name(a), np.arange(a, b), transform_poses(G, poses), s * pts, conf)

    if cfg.noise:
        prior = body_prior(truth, T_sc, model, rng, cfg.prior, frame_ids=np.arange(T))
        human = HumanSeq(np.array(prior.global_orient_cam), np.array(prior.body_pose), np.array(prior.betas),
                         np.array(prior.transl_cam), np.ones(T, bool))
    else:
        exact = body_prior(truth, T_sc, model, rng, PriorNoiseConfig(0, 0, 0, 0, 0), frame_ids=np.arange(T))
        human = HumanSeq(np.array(exact.global_orient_cam), np.array(exact.body_pose), np.array(exact.betas),
                         np.array(exact.transl_cam), np.ones(T, bool))
    write_human_npz(lay.perception(entry.name, view).mono_human, human)
    return {"T_scene_cam": T_sc, "chunk_similarity": sims, "motion_frames": motion}
