"""Stage III: put the moving views (two, or one for a one-phone sequence) in the scene's world.

``run(config, session, seq)`` reads top to bottom as the recipe:

1. ``register_<view>``: a sample of each view's frames registered into the Stage I sparse model
   (SIFT on the background only, candidates by retrieval, absolute pose with the known intrinsics);
2. ``offset``: per view, the yaw-only rigid offset ``T_world_vio`` between the VIO camera centres
   and the registered ones, robust to wrong registrations (RANSAC + reweighting);
3. ``refine``: both views' yaw + translation refined jointly with the paper's losses (cross-view
   track on the performer, Chamfer of each view's background depth against the scene mesh,
   reprojection of the registered matches), Adam and Levenberg-Marquardt on the same residuals,
   the better kept; with ``presync`` (off by default) the track term pairs view 2's points at view 1's instants, by
   the sub-frame sync measured first on the registration-only cameras (:mod:`embodmocap.calibrate.presync`);
   -> ``calibration.json`` (offsets before/after, residual report, registered fractions, warnings);
4. ``geosync``: with both views in the scene's world (whatever their time offset), the offset at
   which the two views' keypoint rays meet, to a fraction of a frame (measured on the cameras
   ``sync_cameras`` names: the refined ones by default, or the registration-only ones, which the
   performer's keypoints took no part in); ``sync.json`` gets it, its
   agreement with the laser and the final choice, which Stage IV applies (sub-frame) ->
   ``<view>/cameras_world.npz`` (per-frame cameras in the scene's world, with that offset).

A one-phone sequence runs the same steps on its one view: registration, the offset, and the
refinement without the cross-view track term (Chamfer + reprojection, as a view alone); no
geometric sync (``sync.json`` was final in Stage II) and no placement through the performer.

The decisions are pure functions in :mod:`embodmocap.calibrate.solve` (arrays and configs in,
results out); this module loads the files, fingerprints each step, calls them and writes.

A refinement that diverges, or moves a view further from its registration than the configured
limits, is reported with its numbers (and the registration-only offset is kept when it diverged).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from embodmocap.calibrate import solve
from embodmocap.calibrate.config import CalibrateConfig  # noqa: F401 (re-exported: defined in config.py)
from embodmocap.calibrate.offset import YawOffset
from embodmocap.calibrate.refine import ViewData
from embodmocap.calibrate.register import load_or_build_scene_index, one_library_thread
from embodmocap.calibrate.solve import CALIBRATION_VERSION, REGISTER_VERSION, ViewInputs  # noqa: F401 (re-exported)
from embodmocap.calibrate.steps import STEPS
from embodmocap.errors import InputError
from embodmocap.io.captures import open_capture
from embodmocap.sequence.laser_check import observe_laser_dots
from embodmocap.sequence.sync_record import UNPAIRED_SLICING
from embodmocap.io.frame_stack import read_depth_m, read_mask
from embodmocap.io.layout import SessionLayout, SequenceLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.stage_files import (
    SYNC_RECORD_VERSION, read_calibration, read_cameras, read_keypoints2d, read_registration, read_sync, sequence_fps,
    write_calibration, write_cameras, write_registration, write_sync,
)
from embodmocap.io.stage_manifest import StageManifest, Upstream, require_step, tracked_stage

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CalibrateOutputs:
    """What Stage III produced for one sequence."""

    name: str
    T_world_vio: dict[str, np.ndarray]
    report: dict
    skipped: tuple[str, ...]


@tracked_stage
def run(cfg: CalibrateConfig, session: str | Path, seq: str | None = None, *, force: bool = False,
        only_register: bool = False, scene_running: bool = False) -> CalibrateOutputs | None:
    """Run Stage III for sequence ``seq`` (the only one when None).

    ``only_register``: step 1 only, for ``embodmocap run`` on several cores (:mod:`embodmocap.schedule`),
    which starts it while Stage I still fuses the mesh: of Stage I it needs only the finished
    ``sfm`` step; a view that must be placed through the performer (which needs the mesh) is left
    to the whole stage. The manifest then ends ``partial`` and nothing is returned.

    ``scene_running``: the whole stage while Stage I still runs its last steps (``floor``,
    ``simplify``, which Stage III does not read), for the same scheduler: of Stage I it needs the
    finished ``sfm`` and ``mesh`` steps (:func:`require_step`) in place of the finished stage.
    """
    lay = SessionLayout(Path(session))
    entry = load_manifest(lay.manifest).sequence(seq)
    scene = lay.scene(entry.scene)
    out = lay.sequence(entry.name)
    names = entry.view_names  # ("v1", "v2"), or ("v1",) for a one-phone sequence
    scene_up = Upstream(scene.manifest, "scene", f"embodmocap scene {lay.root} --scene {entry.scene}")
    if only_register or scene_running:
        # Stage I is still running (embodmocap.schedule): the steps this call reads must be done.
        for step in ("sfm",) if only_register else ("sfm", "mesh"):
            require_step(scene_up, step)
    if not scene.sfm_model.is_dir() or not (only_register or scene.mesh_raw.is_file()):
        raise InputError(scene.root, "Stage I outputs are missing", f"run `embodmocap scene {lay.root} --scene {entry.scene}` first")
    for v in names:
        if not out.view(v).cameras.is_file() or not out.view(v).keypoints.is_file():
            raise InputError(out.view(v).root, "Stage II outputs are missing", f"run `embodmocap sequence {lay.root} --seq {entry.name}` first")
    sm = StageManifest(out.calibrate_manifest, "calibrate", cfg, root=lay.root, upstream=[
        *([] if only_register or scene_running else [scene_up]),
        Upstream(out.manifest, "sequence", f"embodmocap sequence {lay.root} --seq {entry.name}")],
        inputs=[scene.sfm_dir, scene.mesh_raw, *[getattr(out.view(v), k) for v in names
                                                  for k in ("cameras", "keypoints", "masks", "depth")]])
    sm.partial = only_register
    label = f"sequence {entry.name}"
    upstream = {"scenes/<scene>/sfm/sparse": scene.sfm_model, "scenes/<scene>/mesh_raw.ply": scene.mesh_raw,
                "<view>/cameras.npz": {v: out.view(v).cameras for v in names}}
    views = {v: view_inputs(out, v, entry.views[v].capture) for v in names}

    @functools.lru_cache(maxsize=1)
    def points():  # the scene mesh sampled for the Chamfer term, read when a step needs it
        from embodmocap.io.mesh_file import read_mesh_ply

        mv, mf, _ = read_mesh_ply(scene.mesh_raw)
        return solve.scene_points(cfg, mv, mf)

    # 1. Registration per view.
    index = None
    regs = {}
    fp_reg = {}
    fp_placed = {}
    pending = {}  # views whose registrations disagree with their VIO: placed by the performer or an error
    for v in names:
        vl = out.view(v)
        # A registration reads no mesh; a view placed through the performer did (its check on the
        # mesh), so its record holds the fingerprint with the mesh, which a rerun recognises.
        reg_reads = {**upstream, "<view>/masks.npy": vl.masks if vl.masks.is_file() else None}
        fp_reg[v] = STEPS.fingerprint("register", cfg, reads={**reg_reads, "scenes/<scene>/mesh_raw.ply": None})
        fp_placed[v] = STEPS.fingerprint("register", cfg, reads=reg_reads) if scene.mesh_raw.is_file() else None
        if fp_placed[v] is not None and not force and sm.is_current(f"register_{v}", fp_placed[v]):
            fp_reg[v] = fp_placed[v]
    # One pool of threads (one per core) does all of the registration's work: the features of each
    # view frame as soon as its reader thread has decoded it (one reader per view, decoding the
    # video up to the last frame wanted: the decoder releases the GIL), the key frames' descriptors
    # of the scene's index, then the views' matches and poses, one view after the other. Every
    # task's result is its own (one thread inside OpenCV and BLAS), whatever runs beside it.
    todo = [v for v in names if force or not sm.is_current(f"register_{v}", fp_reg[v])]
    stack = contextlib.ExitStack()
    reader = pool = None
    frames = {}
    try:
        if todo:
            stack.enter_context(one_library_thread())
            pool = stack.enter_context(ThreadPoolExecutor(max(1, cfg.register.workers or os.cpu_count() or 1),
                                                          thread_name_prefix="register"))
            reader = stack.enter_context(ThreadPoolExecutor(len(todo), thread_name_prefix="register-frames"))
            for v in todo:
                frames[v] = solve.registration_features(cfg, views[v], pool, reader)
        for v in names:
            vl = out.view(v)
            with sm.step(f"register_{v}", fp_reg[v], force=force, label=label) as step:
                if step.run:
                    # One index per scene, cached next to the scene's outputs and reused by every sequence.
                    index = index or load_or_build_scene_index(scene.sfm_dir, cfg.register, scene.register_index, pool)
                    rv = solve.register_view(cfg, views[v], index, view_name=v, label=f"{entry.name} {v}",
                                             source=entry.views[v].capture, frames=frames.pop(v).result(), pool=pool)
                    # (raises before anything of the view is written)
                    if rv.disagreement is not None:
                        if not cfg.place_by_performer:
                            raise rv.disagreement
                        pending[v] = (rv, step.postpone())
                        if not only_register:
                            step.fp = fp_reg[v] = fp_placed[v]  # recorded below, once the mesh has checked the placement
                        continue
                    write_registration(vl.registration, solve.registration_file(rv.reg, rv.check, rv.off_chain))
                    step.record([vl.registration], solve.register_figures(v, rv))
            regs[v] = _load_registration(vl.registration)
    finally:
        for f in frames.values():  # a view left after an error: its frames are not wanted
            f.cancel()
        if reader is not None:
            reader.shutdown(wait=True)  # (its frames' tasks are all on the pool then)
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        stack.close()
    if only_register:
        return None
    slicing = _sync_record(out, entry.name)["slicing"]["source"]
    for v, (rv, step) in pending.items():
        # raises the view's error when the performer does not place it either
        T_place = solve.place_by_performer(cfg, v, views, regs, rv.disagreement, slicing, points, entry.name)
        write_registration(out.view(v).registration, solve.performer_registration(rv, T_place))
        step.record([out.view(v).registration], solve.register_figures(v, rv, placed_by_performer=True))
        regs[v] = _load_registration(out.view(v).registration)

    # 2. Initial yaw-only offsets (older registration files read with every frame accepted).
    init, init_report = solve.initial_offsets(cfg, views, regs)

    # 3. Joint refinement. Its cross-view keypoint pairs are frame pairs: meaningful when the
    # slicing is within about a frame of the true sync, i.e. unless a view had no laser event.
    use_tracks = slicing not in UNPAIRED_SLICING and len(names) > 1
    # With cfg.presync the track pairs are taken at the sub-frame sync measured on the registration
    # cameras (calibrate.presync): the sync record and the keypoints are then inputs of this step.
    presync = cfg.presync and use_tracks
    rec = _sync_record(out, entry.name)
    fp_ref = STEPS.fingerprint("refine", cfg, after={"register": fp_reg}, context={
        "use_tracks": use_tracks, "presync_geosync": cfg.geosync if presync else None,
        "subframe_sync": entry.subframe_sync if presync else None, "sync_force": entry.sync_force if presync else None},
        reads={**upstream, "<view>/registration.npz": {v: out.view(v).registration for v in names},
               "sync.json": [{k: rec[k] for k in ("views", "slicing", "sources")}] if presync else None,
               "<view>/keypoints2d.npz": {v: out.view(v).keypoints for v in names} if use_tracks else None})
    calib_path = out.calibration
    with sm.step("refine", fp_ref, force=force, label=label) as step:
        if step.run:
            fps = sequence_fps(out)
            pre = solve.presync_step(cfg, rec, views, init, fps, entry.name, entry.subframe_sync,
                                     entry.sync_force) if presync else None
            report = solve.refine_report(cfg, views, init, regs, init_report, points, use_tracks,
                                         sequence=entry.name, scene=entry.scene, presync=pre, fps=fps)
            write_calibration(calib_path, report)
            step.record([calib_path], {f"{v}_{k}": report["views"][v][k] for v in names
                                       for k in ("refine_shift_m", "refine_yaw_deg")} | {"one_view": entry.one_view})
    report = read_calibration(calib_path).record
    T_world_vio = {v: np.asarray(report["views"][v]["T_world_vio"]) for v in names}

    # 4. Geometric sync: with both views in one world (whatever their time offset), the offset is
    # where both views' keypoint rays meet (sequence.geosync); final_sync.json gets the final choice
    # among laser, manual and geometric (sequence.sync_record); the per-frame world cameras carry
    # the sub-frame offset Stage IV applies.
    rec = _sync_record(out, entry.name)
    # The refined offsets, not calibration.json's bytes: the report also holds the solver's timings,
    # which would make every rerun of the refinement redo this step (and differ between two runs).
    fp_geo = STEPS.fingerprint("geosync", cfg, context={"subframe_sync": entry.subframe_sync, "sync_force": entry.sync_force},
                               reads={"sync.json": [{k: rec[k] for k in ("views", "slicing")}, rec["sources"].get("laser"),
                                                    rec["sources"].get("manual")],
                                      "calibration.json": [{v: report["views"][v]["T_world_vio"] for v in names},
                                                           {v: report["views"][v].get("drift") for v in names},
                                                           *([{v: report["views"][v]["T_world_vio_registration"] for v in names}]
                                                             if cfg.sync_cameras == "registration" else [])],
                                      "<view>/keypoints2d.npz": {v: out.view(v).keypoints for v in names},
                                      "<view>/cameras.npz": {v: out.view(v).cameras for v in names}})
    with sm.step("geosync", fp_geo, force=force, label=label) as step:
        if step.run:
            sheets = {v: str(out.sync_sheet(v)) for v, d in rec["sources"]["laser"]["views"].items()
                      if d.get("contact_sheet")}
            # One dot seen by two views is one place; one view has nothing to compare. The captures
            # are opened and the dots looked up on a second thread while the offset is searched.
            with ThreadPoolExecutor(1, thread_name_prefix="laser-dots") as pool:
                dots = pool.submit(observe_laser_dots, rec, {v: (lambda p=entry.views[v].capture: open_capture(p))
                                                             for v in names}).result if len(names) > 1 else None
                geo = solve.geometric_sync(cfg, rec, solve.drift_corrected(views, report), T_world_vio, sequence_fps(out),
                                           sheets, entry.name, dots, entry.subframe_sync, entry.sync_force,
                                           solve.sync_measure_cameras(cfg, views, report))
            write_sync(out.final_sync, geo.record)  # Stage II's sync.json stays Stage II's
            for w in geo.record["warnings"]:
                log.warning("%s", w)
            for v in names:
                write_cameras(out.view(v).cameras_world, geo.cameras_world[v])
            step.record([out.final_sync, *[out.view(v).cameras_world for v in names]], geo.figures)
    report = read_calibration(calib_path).record
    for w in report.get("warnings", []):
        log.warning("%s: %s", entry.name, w)
    return CalibrateOutputs(entry.name, {v: np.asarray(report["views"][v]["T_world_vio"]) for v in names},
                            report, tuple(sm.skipped))


def view_inputs(out: SequenceLayout, v: str, capture: str | Path | None = None) -> ViewInputs:
    """One view's Stage II files as :class:`~embodmocap.calibrate.solve.ViewInputs`: cameras and
    keypoints read (checked), depth and masks read frame by frame from their memory-mapped stacks,
    colour frames from the view's capture (opened on first use; None without ``capture``)."""
    vl = out.view(v)
    cams = read_cameras(vl.cameras)
    width = int(cams["width"])
    raw = np.asarray(cams["raw_frames"], dtype=np.int64)
    opened = functools.lru_cache(maxsize=1)(lambda: open_capture(capture))
    return ViewInputs(
        cameras=cams, keypoints=read_keypoints2d(vl.keypoints).keypoints,
        depth_m=lambda t: read_depth_m(vl.depth, t),
        mask=(lambda t: read_mask(vl.masks, t, width)) if vl.masks.is_file() else None,
        rgb=None if capture is None else (lambda t: opened().frames.rgb(int(raw[t]))))


def _sync_record(out, seq: str) -> dict:
    """Stage II's sync.json (version 2), or one clear error."""
    if not out.sync.is_file():
        raise InputError(out.sync, "Stage II's sync.json is missing", f"run `embodmocap sequence --seq {seq}` first")
    rec = read_sync(out.sync).record
    if rec.get("version") != SYNC_RECORD_VERSION:
        raise InputError(out.sync, f"sync.json is version {rec.get('version')}, this Stage III needs {SYNC_RECORD_VERSION}",
                         f"rerun `embodmocap sequence --seq {seq}` (it redoes the sync and the slicing)")
    return rec


def _load_registration(path: Path) -> dict:
    """A view's registration (checked by the typed reader) as a dict the stage can complete."""
    return dict(read_registration(path).items())


def build_view_data(cfg: CalibrateConfig, lay: SessionLayout, seq: str, v: str, init: YawOffset, reg) -> ViewData:
    """:func:`embodmocap.calibrate.solve.build_view_data` of a view of a session on disk."""
    return solve.build_view_data(cfg, view_inputs(lay.sequence(seq), v), init, reg)


#: Kept for scripts written against the stage (the function is :func:`solve.yaw_offset_of`).
_yaw_offset_of = solve.yaw_offset_of
