"""Stage I: the metric, gravity-aligned scene mesh and sparse model of one scene capture.

``run(config, session, scene)`` reads top to bottom as the recipe:

1. ``keyframes``: key frames by camera motion, the blurriest of each small group dropped, frames
   around tracking jumps excluded (written to ``keyframes.json`` with their poses);
2. ``sfm``: SIFT on the key frames, pairs from the known poses, triangulation with the capture's
   poses and intrinsics held fixed, optionally (``sfm.refine_poses``) the VIO drift of the key
   frames corrected by a bundle adjustment with the VIO as a prior and the points triangulated
   again (``sfm/``: database + model for Stage III);
3. ``mesh``: every frame with a trusted pose and enough valid depth (a fine motion step, many more
   than the key frames), with the sparse model's drift correction carried over to it, LiDAR depth
   (optionally refined by a learned model) weighted by its confidence and truncated at the sensor's
   range, fused in an Open3D TSDF; colour mesh extracted and cleaned without dropping real
   structure (``mesh_raw.ply``);
4. ``simplify``: a light mesh for viewers and physics (``mesh_simplified.ply``).

The world is the scene capture's own VIO world: metric and gravity-aligned (Z up), so the mesh and
the model share it without any alignment. Each step is skipped when its fingerprint (config,
inputs, upstream steps) matches the stage manifest and its outputs exist, so a run that was
interrupted resumes at the first unfinished step.
"""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from embodmocap.errors import InputError
from embodmocap.io.atomic import write_json
from embodmocap.io.captures import open_capture
from embodmocap.io.layout import SceneLayout, SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.stage_manifest import StageManifest, fingerprint, path_fingerprint, tracked_stage
from embodmocap.scene.adjust import corrected_poses
from embodmocap.scene.config import SceneConfig
from embodmocap.scene.depth import DepthStats, check_depth, fusion_frames, prefetch
from embodmocap.scene.keyframes import choose_keyframes, fusion_rows
from embodmocap.scene.mesh import clean_mesh, mesh_stats, read_mesh_ply, simplify_mesh, write_mesh_ply
from embodmocap.scene.sfm import build_sparse_model
from embodmocap.scene.tsdf import fuse_open3d

log = logging.getLogger(__name__)

KEYFRAMES_VERSION = 1


@dataclass(frozen=True)
class SceneOutputs:
    """What Stage I produced for one scene."""

    name: str
    layout: SceneLayout
    figures: dict
    """Quality figures and timings, as in the stage manifest."""
    skipped: tuple[str, ...]
    """Steps that were up to date and not redone."""


def _cfg_part(cfg: SceneConfig, prefixes: tuple[str, ...]) -> dict:
    """The config fields a step depends on (so changing e.g. SfM options keeps the mesh)."""
    return {f.name: getattr(cfg, f.name) for f in fields(cfg) if f.name.startswith(prefixes)}


_KEYFRAME_FIELDS = ("keyframe_", "blur_", "jump_", "min_keyframes")
_MESH_FIELDS = ("min_confidence", "depth_", "voxel_", "sdf_", "integrate_every", "min_component", "floater_",
                "confidence_", "fuse_", "structure_", "jump_")
_SIMPLIFY_FIELDS = ("simplify_",)
_SFM_FIELDS = ("sfm",)


@tracked_stage
def run(cfg: SceneConfig, session: str | Path, scene: str | None = None, *, force: bool = False) -> SceneOutputs:
    """Run Stage I for ``scene`` of the session at ``session`` (the only scene when None)."""
    lay = SessionLayout(Path(session))
    manifest = load_manifest(lay.manifest)
    entry = manifest.scene(scene)
    name = entry.name
    indoor = entry.indoor
    out = lay.scene(name)
    capture = open_capture(entry.capture)
    skipped: list[str] = []
    log.info("scene %s: %s capture, %d frames, %s", name, capture.format, capture.num_frames,
             "indoor" if indoor else "outdoor")
    # Bad depth is found before anything is written (not after the key frames and half a mesh).
    check_depth(capture, cfg, indoor)
    out.root.mkdir(parents=True, exist_ok=True)
    sm = StageManifest(out.manifest, "scene", cfg, inputs=[entry.capture], root=lay.root)

    # 1. Key frames.
    fp_kf = fingerprint("keyframes", KEYFRAMES_VERSION, path_fingerprint(entry.capture), indoor,
                        _cfg_part(cfg, _KEYFRAME_FIELDS))
    if not force and sm.is_current("keyframes", fp_kf):
        skipped.append("keyframes")
    else:
        t0 = time.perf_counter()
        sel = choose_keyframes(capture, cfg, indoor)
        T = capture.trajectory.T_world_cam[sel.rows]
        write_json(out.keyframes, {
            "version": KEYFRAMES_VERSION, "capture": str(entry.capture), "indoor": indoor,
            "frame_ids": sel.frame_ids, "T_world_cam": T, "sharpness": np.nan_to_num(sel.sharpness, nan=-1.0),
            "dropped_blurry": sel.dropped_blurry, "excluded_jumps": sel.excluded_jumps,
        })
        sm.record("keyframes", fp_kf, [out.keyframes], time.perf_counter() - t0, {
            "keyframes": len(sel), "keyframes_dropped_blurry": len(sel.dropped_blurry),
            "frames_excluded_jumps": len(sel.excluded_jumps),
        })
    kf = read_keyframes(out)
    frame_ids, T_kf = kf["frame_ids"], kf["T_world_cam"]

    # 2. Sparse model (before the mesh: the mesh is fused with its drift correction of the key frames).
    fp_sfm = fingerprint("sfm", fp_kf, cfg.sfm)
    if not force and sm.is_current("sfm", fp_sfm):
        skipped.append("sfm")
    else:
        t0 = time.perf_counter()
        pick = _evenly(len(frame_ids), cfg.sfm.max_images)
        names = [f"kf_{int(i):06d}" for i in frame_ids[pick]]
        images = [(n, capture.frames.rgb(int(i))) for n, i in zip(names, frame_ids[pick])]
        times = np.interp(frame_ids[pick], capture.trajectory.frame_ids, capture.trajectory.timestamps_s)
        model = build_sparse_model(images, capture.rgb_intrinsics, T_kf[pick], out.sfm_dir, cfg.sfm, times_s=times)
        sm.record("sfm", fp_sfm, [out.sfm_dir], time.perf_counter() - t0, {
            "sfm_images": len(names), "sfm_points": model.num_points,
            "sfm_mean_track_length": round(model.mean_track_length, 3),
            "sfm_mean_reproj_error_px": round(model.mean_reproj_error_px, 4),
        })

    # 3. TSDF fusion + clean-up.
    fp_mesh = fingerprint("mesh", fp_kf, fp_sfm if cfg.sfm.refine_poses else None, _cfg_part(cfg, _MESH_FIELDS))
    if not force and sm.is_current("mesh", fp_mesh):
        skipped.append("mesh")
    else:
        t0 = time.perf_counter()
        # Every trusted frame (fine motion step), not only the SfM key frames: coverage of ceilings,
        # far walls and furniture sides comes from the frames between key frames.
        rows = fusion_rows(capture, cfg)[:: max(1, cfg.integrate_every)]
        ids, poses = capture.trajectory.frame_ids[rows], corrected_poses(
            out.sfm_dir, capture.trajectory.timestamps_s[rows], capture.trajectory.T_world_cam[rows])
        stats = DepthStats()
        frames = prefetch(fusion_frames(capture, ids, poses, cfg, indoor, refine=_depth_refiner(cfg), stats=stats))
        v, f, c = fuse_open3d(_progress(frames, len(ids), f"scene {name}: fusing"), cfg.voxel_m(indoor),
                              cfg.sdf_trunc_m(indoor), cfg.depth_trunc_m(indoor))
        t_fuse = time.perf_counter() - t0
        v, f, c = clean_mesh(v, f, c, cfg)
        if len(f) == 0:
            raise InputError(entry.capture, "the fused mesh is empty after clean-up",
                             "check that the depth maps and poses belong together")
        write_mesh_ply(out.mesh_raw, v, f, c)
        st = mesh_stats(v, f)
        sm.record("mesh", fp_mesh, [out.mesh_raw], time.perf_counter() - t0, {
            "mesh_vertices": st["vertices"], "mesh_faces": st["faces"], "mesh_area_m2": round(st["area_m2"], 3),
            "fused_frames": stats.fused_frames, "fusion_candidates": len(ids),
            "depth_pixels_used_fraction": round(stats.used_fraction, 4),
            "fusion_fps": round(stats.fused_frames / max(t_fuse, 1e-9), 2),
        })

    # 4. Simplified mesh.
    if cfg.simplify_voxel_m > 0:
        fp_simple = fingerprint("simplify", fp_mesh, _cfg_part(cfg, _SIMPLIFY_FIELDS))
        if not force and sm.is_current("simplify", fp_simple):
            skipped.append("simplify")
        else:
            t0 = time.perf_counter()
            v, f, c = read_mesh_ply(out.mesh_raw)
            vs, fs, cs = simplify_mesh(v, f, c, cfg.simplify_voxel_m)
            write_mesh_ply(out.mesh_simplified, vs, fs, cs)
            st = mesh_stats(vs, fs)
            sm.record("simplify", fp_simple, [out.mesh_simplified], time.perf_counter() - t0, {
                "simplified_vertices": st["vertices"], "simplified_faces": st["faces"],
            })

    if skipped:
        log.info("scene %s: up to date, skipped: %s", name, ", ".join(skipped))
    return SceneOutputs(name, out, sm.figures(), tuple(skipped))


def read_keyframes(out: SceneLayout) -> dict:
    """``keyframes.json`` as arrays: frame_ids (K,), T_world_cam (K,4,4), sharpness (K,)."""
    import json

    data = json.loads(out.keyframes.read_text())
    if data.get("version") != KEYFRAMES_VERSION:
        raise InputError(out.keyframes, f"unknown version {data.get('version')}", "re-run `embodmocap scene`")
    return {
        "frame_ids": np.asarray(data["frame_ids"], dtype=np.int64),
        "T_world_cam": np.asarray(data["T_world_cam"], dtype=np.float64).reshape(-1, 4, 4),
        "sharpness": np.asarray(data["sharpness"], dtype=np.float64),
    }


def _evenly(n: int, k: int) -> np.ndarray:
    """Up to ``k`` indices spread evenly over ``range(n)``."""
    if n <= k:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, k)).astype(np.int64))


def _depth_refiner(cfg: SceneConfig):
    """The refinement hook for :func:`fusion_frames`, or None for plain LiDAR depth."""
    if cfg.depth_refine == "none":
        return None
    from embodmocap.perception.depth_refine import make_depth_refiner

    # Output at the sensor's resolution: the TSDF runs at depth resolution.
    refiner = make_depth_refiner(cfg.depth_refine, model=cfg.depth_refine_model, output="depth")
    return lambda rgb, depth, conf: refiner.refine([rgb], [depth])[0]


def _progress(it, total: int, desc: str):
    """A progress bar on a terminal; a start and an end log line otherwise."""
    if sys.stderr.isatty():
        from tqdm import tqdm

        yield from tqdm(it, total=total, desc=desc, unit="frame")
        return
    log.info("%s %d frames", desc, total)
    yield from it
