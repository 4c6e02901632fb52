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
4. ``floor``: the gravity check: the tilt of the mesh's floor (dominant low near-horizontal
   plane) from horizontal, a manifest figure, with a warning above ``floor_tilt_warn_deg``;
5. ``simplify``: a light mesh for viewers and physics (``mesh_simplified.ply``).

The decisions are pure functions in :mod:`embodmocap.scene.solve` (the capture and the config in,
arrays out); this module opens the capture, fingerprints each step, calls them and writes.

The world is the scene capture's own VIO world: metric and gravity-aligned (Z up), so the mesh and
the model share it without any alignment. Each step is skipped when its fingerprint (config,
inputs, upstream steps) matches the stage manifest and its outputs exist, so a run that was
interrupted resumes at the first unfinished step.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from embodmocap.io.captures import open_capture
from embodmocap.io.layout import SceneLayout, SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.mesh_file import as_stored, read_mesh_ply, write_mesh_ply
from embodmocap.io.stage_files import read_keyframes, write_keyframes
from embodmocap.io.stage_manifest import StageManifest, tracked_stage
from embodmocap.parallel import import_in_background, library_threads
from embodmocap.scene import solve
from embodmocap.scene.adjust import read_drift_correction
from embodmocap.scene.config import SceneConfig
from embodmocap.scene.depth import check_depth
from embodmocap.scene.sfm import build_sparse_model
from embodmocap.scene.solve import KEYFRAMES_VERSION  # noqa: F401 (re-exported)
from embodmocap.scene.steps import FLOOR_VERSION, SIMPLIFY_VERSION, STEPS  # noqa: F401 (re-exported)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SceneOutputs:
    """What Stage I produced for one scene."""

    name: str
    layout: SceneLayout
    figures: dict
    """Quality figures and timings, as in the stage manifest."""
    skipped: tuple[str, ...]
    """Steps that were up to date and not redone."""


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
    log.info("scene %s: %s capture, %d frames, %s", name, capture.format, capture.num_frames,
             "indoor" if indoor else "outdoor")
    # Bad depth is found before anything is written (not after the key frames and half a mesh).
    check_depth(capture, cfg, indoor)
    out.root.mkdir(parents=True, exist_ok=True)
    sm = StageManifest(out.manifest, "scene", cfg, inputs=[entry.capture], root=lay.root)
    label = f"scene {name}"

    # 1. Key frames.
    fp_kf = STEPS.fingerprint("keyframes", cfg, reads={"scene capture": Path(entry.capture)},
                              context={"indoor": indoor})
    decoded: dict = {}  # the key frames as the blur test decoded them, for the sparse model's images
    with sm.step("keyframes", fp_kf, force=force, label=label) as step:
        if step.run:
            kf = solve.select_keyframes(capture, cfg, indoor)
            decoded = kf.frames
            rec = kf.record
            write_keyframes(out.keyframes, {"version": rec["version"], "capture": str(entry.capture),
                                       **{k: x for k, x in rec.items() if k != "version"}})
            step.record([out.keyframes], kf.figures)
    kf = read_keyframes(out.keyframes)
    frame_ids, T_kf = kf["frame_ids"], kf["T_world_cam"]

    # 2. Sparse model (before the mesh: the mesh is fused with its drift correction of the key frames).
    fp_sfm = STEPS.fingerprint("sfm", cfg, after={"keyframes": fp_kf})
    with sm.step("sfm", fp_sfm, force=force, label=label) as step:
        if step.run:
            images, poses, times = solve.sfm_images(capture, frame_ids, T_kf, cfg, decoded)
            # The mesh step after this one needs Open3D, whose import is seconds of CPU: done on the
            # other core while COLMAP (native, GIL released) builds the model on this one.
            import_in_background("embodmocap.io.open3d_core")
            with library_threads(1, ("blas",)):  # the drift adjustment's small solves (see parallel.py)
                model = build_sparse_model(images, capture.rgb_intrinsics, poses, out.sfm_dir, cfg.sfm, times_s=times)
            step.record([out.sfm_dir], {
                "sfm_images": len(images), "sfm_points": model.num_points,
                "sfm_mean_track_length": round(model.mean_track_length, 3),
                "sfm_mean_reproj_error_px": round(model.mean_reproj_error_px, 4),
            })
            del images  # not held through the mesh's fusion
    decoded = {}

    # 3. TSDF fusion + clean-up.
    fp_mesh = STEPS.fingerprint("mesh", cfg, after={"keyframes": fp_kf, "sfm": fp_sfm if cfg.sfm.refine_poses else None})
    stored = None  # the mesh just made, as mesh_raw.ply stores it (8-bit colours), for steps 4 and 5
    with sm.step("mesh", fp_mesh, force=force, label=label) as step:
        if step.run:
            drift = read_drift_correction(out.sfm_dir) if cfg.sfm.refine_poses else None
            mesh = solve.fuse_mesh(capture, cfg, indoor, label=name, source=entry.capture, drift=drift)
            write_mesh_ply(out.mesh_raw, mesh.vertices, mesh.faces, mesh.colors)
            step.record([out.mesh_raw], mesh.figures)
            # Exactly what reading the file back gives (a rerun's steps 4 and 5 read it), without the
            # read. Same thread on purpose: in another, its ~1 GB of temporaries would not reuse the
            # memory the fusion freed (glibc keeps one heap per thread) and the peak would rise.
            stored = as_stored(mesh.vertices, mesh.faces, mesh.colors)
            del mesh

    def stored_mesh():
        return stored if stored is not None else read_mesh_ply(out.mesh_raw)

    # 4. Gravity check: a Z-up world has a horizontal floor; a tilted one means wrong gravity.
    if cfg.floor_tilt_warn_deg > 0:
        fp_floor = STEPS.fingerprint("floor", cfg, after={"mesh": fp_mesh})
        with sm.step("floor", fp_floor, force=force, label=label) as step:
            if step.run:
                step.record([], floor_figures(*stored_mesh()[:2], cfg))
        _warn_floor(sm.figures(), cfg, name, capture.format)

    # 5. Simplified mesh.
    if cfg.simplify_voxel_m > 0:
        fp_simple = STEPS.fingerprint("simplify", cfg, after={"mesh": fp_mesh})
        with sm.step("simplify", fp_simple, force=force, label=label) as step:
            if step.run:
                simple = solve.simplified(*stored_mesh(), cfg)
                write_mesh_ply(out.mesh_simplified, simple.vertices, simple.faces, simple.colors)
                step.record([out.mesh_simplified], simple.figures)
    del stored

    if sm.skipped:
        log.info("scene %s: up to date, skipped: %s", name, ", ".join(sm.skipped))
    return SceneOutputs(name, out, sm.figures(), tuple(sm.skipped))


def floor_figures(vertices: np.ndarray, faces: np.ndarray, cfg: SceneConfig) -> dict:
    """``floor_tilt_deg`` (None when the mesh has no floor plane), ``floor_area_m2``, ``floor_z_m``
    and ``floor_tilt_ok`` of a mesh (vertices (V, 3), faces (F, 3), Z-up metres)."""
    from embodmocap.geometry.planes import find_floor

    floor = find_floor(vertices, faces)
    if floor is None:
        return {"floor_tilt_deg": None, "floor_area_m2": 0.0, "floor_z_m": None, "floor_tilt_ok": None}
    return {"floor_tilt_deg": round(floor.tilt_deg, 3), "floor_area_m2": round(floor.area_m2, 3),
            "floor_z_m": round(floor.height_m, 4), "floor_tilt_ok": floor.tilt_deg <= cfg.floor_tilt_warn_deg}


def _warn_floor(figures: dict, cfg: SceneConfig, name: str, fmt: str) -> None:
    """One log line when the floor is tilted or missing (every run, skipped step or not)."""
    tilt = figures.get("floor_tilt_deg")
    if tilt is None:
        log.warning("scene %s: no dominant floor plane in the mesh, so gravity could not be checked; look at "
                    "the mesh before going on (a tilted world breaks contacts and simulation)", name)
    elif tilt > cfg.floor_tilt_warn_deg:
        log.warning("scene %s: the floor of the mesh is %.1f deg off horizontal (more than %.1f): the %s capture's "
                    "gravity is wrong; check the export is complete (e.g. Record3D's initPose) and read it again",
                    name, tilt, cfg.floor_tilt_warn_deg, fmt)
