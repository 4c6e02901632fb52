"""Stage III: put both moving views in the scene's world.

``run(config, session, seq)`` reads top to bottom as the recipe:

1. ``register_<view>``: a sample of each view's frames registered into the Stage I sparse model
   (SIFT on the background only, candidates by retrieval, absolute pose with the known intrinsics);
2. ``offset``: per view, the yaw-only rigid offset ``T_world_vio`` between the VIO camera centres
   and the registered ones, robust to wrong registrations (RANSAC + reweighting);
3. ``refine``: both views' yaw + translation refined jointly with the paper's losses (cross-view
   track on the performer, Chamfer of each view's background depth against the scene mesh,
   reprojection of the registered matches), Adam and Levenberg-Marquardt on the same residuals,
   the better kept;
   -> ``calibration.json`` (offsets before/after, residual report, registered fractions, warnings);
4. ``geosync``: with both views in the scene's world (whatever their time offset), the offset at
   which the two views' keypoint rays meet, to a fraction of a frame; ``sync.json`` gets it, its
   agreement with the laser and the final choice, which Stage IV applies (sub-frame) ->
   ``<view>/cameras_world.npz`` (per-frame cameras in the scene's world, with that offset).

A refinement that diverges, or moves a view further from its registration than the configured
limits, is reported with its numbers (and the registration-only offset is kept when it diverged).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from embodmocap.calibrate.config import CalibrateConfig  # noqa: F401 (re-exported: defined in config.py)
from embodmocap.calibrate.consistency import check_against_vio, off_chain_frames
from embodmocap.calibrate.offset import YawOffset, chain_yaw_offset
from embodmocap.calibrate.refine import ViewData, refine_offsets
from embodmocap.calibrate.register import (Registration, load_or_build_scene_index, load_view_frames,
                                           register_frames, select_frames)
from embodmocap.errors import InputError
from embodmocap.geometry.transforms import rotation_angle
from embodmocap.io.atomic import write_json
from embodmocap.io.captures import open_capture
from embodmocap.io.frame_stack import read_depth_m, read_mask
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.stage_files import (
    CameraFile, RegistrationFile, read_cameras, read_keypoints2d, read_registration, sequence_fps, write_cameras,
    write_registration,
)
from embodmocap.io.stage_manifest import StageManifest, Upstream, amend_output, fingerprint, path_fingerprint, tracked_stage

log = logging.getLogger(__name__)

CALIBRATION_VERSION = 1


@dataclass(frozen=True)
class CalibrateOutputs:
    """What Stage III produced for one sequence."""

    name: str
    T_world_vio: dict[str, np.ndarray]
    report: dict
    skipped: tuple[str, ...]


@tracked_stage
def run(cfg: CalibrateConfig, session: str | Path, seq: str | None = None, *, force: bool = False) -> CalibrateOutputs:
    """Run Stage III for sequence ``seq`` (the only one when None)."""
    lay = SessionLayout(Path(session))
    entry = load_manifest(lay.manifest).sequence(seq)
    scene = lay.scene(entry.scene)
    out = lay.sequence(entry.name)
    if not (scene.sfm_dir / "sparse").is_dir() or not scene.mesh_raw.is_file():
        raise InputError(scene.root, "Stage I outputs are missing", f"run `embodmocap scene {lay.root} --scene {entry.scene}` first")
    for v in VIEWS:
        if not out.view(v).cameras.is_file() or not out.view(v).keypoints.is_file():
            raise InputError(out.view(v).root, "Stage II outputs are missing", f"run `embodmocap sequence {lay.root} --seq {entry.name}` first")
    sm = StageManifest(out.calibrate_manifest, "calibrate", cfg, root=lay.root, upstream=[
        Upstream(scene.manifest, "scene", f"embodmocap scene {lay.root} --scene {entry.scene}"),
        Upstream(out.manifest, "sequence", f"embodmocap sequence {lay.root} --seq {entry.name}")],
        inputs=[scene.sfm_dir, scene.mesh_raw, *[getattr(out.view(v), k) for v in VIEWS
                                                  for k in ("cameras", "keypoints", "masks", "depth")]])
    skipped: list[str] = []
    upstream = fingerprint(path_fingerprint(scene.sfm_dir / "sparse"), path_fingerprint(scene.mesh_raw),
                           *[path_fingerprint(out.view(v).cameras) for v in VIEWS])

    # 1. Registration per view.
    index = None
    regs = {}
    pending = {}  # views whose registrations disagree with their VIO: placed by the performer or an error
    for v in VIEWS:
        vl = out.view(v)
        reg_path = vl.registration
        fp = fingerprint("register", REGISTER_VERSION, upstream, path_fingerprint(vl.masks) if vl.masks.is_file() else None,
                         cfg.register, cfg.vio_max_disagreement_m, cfg.vio_max_disagreement_deg)
        if not force and sm.is_current(f"register_{v}", fp):
            skipped.append(f"register_{v}")
        else:
            t0 = time.perf_counter()
            # One index per scene, cached next to the scene's outputs and reused by every sequence.
            index = index or load_or_build_scene_index(scene.sfm_dir, cfg.register, scene.root / "register_index.npz")
            cams = read_cameras(vl.cameras)
            T_vio = np.asarray(cams["T_world_cam"], dtype=np.float64)
            ts = select_frames(T_vio, cfg.register.num_frames)
            frames, K, _ = load_view_frames(vl, open_capture(entry.views[v].capture), ts)
            reg = _register_view(cfg, frames, K, index, T_vio, f"{entry.name} {v}")
            check = check_against_vio(reg.T_world_cam, T_vio[reg.t], reg.inliers,
                                      cfg.vio_max_disagreement_m, cfg.vio_max_disagreement_deg)
            try:
                _check_view(cfg, entry.views[v].capture, v, reg, check)  # before anything of the view is written
            except _VioDisagreement as err:
                if not cfg.place_by_performer:
                    raise
                pending[v] = (err, reg, check, fp, t0)
                continue
            # Frames the run check kept but that sit off the whole chain's offset (an error ramping
            # up along a run passes the neighbour-to-neighbour test): out of the fit as well.
            off = off_chain_frames(reg.T_world_cam, T_vio[reg.t], check.accepted, cfg.vio_max_disagreement_m,
                                   cfg.vio_max_disagreement_deg, offset_cfg=cfg.offset)
            _save_registration(reg_path, reg, check, off)
            sm.record(f"register_{v}", fp, [reg_path], time.perf_counter() - t0, {
                f"{v}_frames_tried": int(len(reg.attempted)), f"{v}_frames_registered": int(len(reg.t)),
                f"{v}_registered_fraction": round(reg.registered_fraction, 3),
                f"{v}_vio_rejected_runs": check.rejected_runs, f"{v}_vio_rejected_frames": check.rejected_frames,
                f"{v}_vio_off_chain_frames": int(off.sum()),
                f"{v}_register_seconds": {k: round(s, 2) for k, s in reg.seconds.items()},
            })
        regs[v] = _load_registration(reg_path)
    for v, (err, reg, check, fp, t0) in pending.items():
        T_place = _place_by_performer(cfg, lay, entry, v, regs, err)  # raises err when it does not fit
        # None of its frames is trusted: all stay out of the fit, the offset is the placement.
        _save_registration(out.view(v).registration, reg, replace(check, accepted=np.zeros(len(reg.t), dtype=bool)),
                           None, T_place)
        sm.record(f"register_{v}", fp, [out.view(v).registration], time.perf_counter() - t0, {
            f"{v}_frames_tried": int(len(reg.attempted)), f"{v}_frames_registered": int(len(reg.t)),
            f"{v}_registered_fraction": round(reg.registered_fraction, 3), f"{v}_placed_by_performer": True,
            f"{v}_register_seconds": {k: round(s, 2) for k, s in reg.seconds.items()},
        })
        regs[v] = _load_registration(out.view(v).registration)
    # (Older registration files read with every frame accepted and none off the chain: the typed reader.)

    # 2. Initial yaw-only offsets.
    init: dict[str, YawOffset] = {}
    init_report = {}
    for v in VIEWS:
        cams = read_cameras(out.view(v).cameras)
        r = regs[v]
        acc = np.asarray(r["accepted"], dtype=bool)
        runs = np.asarray(r["run"])
        off = np.asarray(r["off_chain"], dtype=bool)
        if "T_world_vio_performer" in r:  # placed through the performer (step 1): no frame of its own
            init[v] = _yaw_offset_of(r["T_world_vio_performer"])
            init_report[v] = {"inliers": 0, "registered": int(len(r["t"])), "vio_consistent": 0,
                              "median_residual_m": None, "placement": "performer"}
        else:
            # Only the VIO-consistent chain: frames of rejected runs never reach the fit.
            fit = chain_yaw_offset(cams["T_world_cam"][r["t"][acc]], r["T_world_cam"][acc], cfg.offset)
            init[v] = fit.offset
            init_report[v] = {"inliers": int(fit.num_inliers), "registered": int(len(r["t"])),
                              "vio_consistent": int(acc.sum()),
                              "median_residual_m": float(np.median(fit.residuals_m[fit.inliers])) if fit.num_inliers else None,
                              "placement": "registration"}
        by_runs = ~acc & ~off  # rejected by the run check (off-chain frames are counted apart)
        init_report[v]["vio_check"] = {
            "runs": int(len(np.unique(runs))), "rejected_runs": int(len(np.unique(runs[by_runs]))),
            "rejected_frames": int((~acc).sum()), "off_chain_frames": int(off.sum()),
            "max_disagreement_m": cfg.vio_max_disagreement_m, "max_disagreement_deg": cfg.vio_max_disagreement_deg}

    # 3. Joint refinement. Its cross-view keypoint pairs are frame pairs: meaningful when the
    # slicing is within about a frame of the true sync, i.e. unless a view had no laser event.
    slicing = _sync_record(out, entry.name)["slicing"]["source"]
    use_tracks = slicing != "start"
    fp_ref = fingerprint("refine", upstream, *[path_fingerprint(out.view(v).registration) for v in VIEWS],
                         cfg.offset, cfg.refine, cfg.refine_views, cfg.chamfer_frames, cfg.chamfer_points_per_frame,
                         cfg.scene_points, cfg.track_frames, use_tracks)
    calib_path = out.calibration
    if not force and sm.is_current("refine", fp_ref):
        skipped.append("refine")
    else:
        t0 = time.perf_counter()
        report = _refine(cfg, lay, entry, init, regs, init_report, use_tracks)
        write_json(calib_path, report)
        sm.record("refine", fp_ref, [calib_path], time.perf_counter() - t0, {
            f"{v}_{k}": report["views"][v][k] for v in VIEWS for k in ("refine_shift_m", "refine_yaw_deg")})
    report = json.loads(calib_path.read_text())
    T_world_vio = {v: np.asarray(report["views"][v]["T_world_vio"]) for v in VIEWS}

    # 4. Geometric sync: with both views in one world (whatever their time offset), the offset is
    # where both views' keypoint rays meet (sequence.geosync); sync.json gets the final choice
    # among laser, manual and geometric (sequence.sync_record); the per-frame world cameras carry
    # the sub-frame offset Stage IV applies.
    _geosync_step(cfg, out, entry.name, T_world_vio, path_fingerprint(calib_path), sm, force, skipped,
                  {v: (lambda p=entry.views[v].capture: open_capture(p)) for v in VIEWS})
    report = json.loads(calib_path.read_text())
    for w in report.get("warnings", []):
        log.warning("%s: %s", entry.name, w)
    return CalibrateOutputs(entry.name, {v: np.asarray(report["views"][v]["T_world_vio"]) for v in VIEWS},
                            report, tuple(skipped))


REGISTER_VERSION = 3


def _register_view(cfg: CalibrateConfig, frames, K, index, T_vio: np.ndarray, name: str) -> Registration:
    """Register one view's frames: a few by retrieval first, the rest by pose from their coarse,
    VIO-checked offset; frames that still fail are retried against more retrieval candidates.

    Retrieval ranks key frames by appearance, which repetitive or plain walls fool; once a coarse
    offset is known, the key frames that see what each VIO camera sees are the right candidates.
    """
    rc = cfg.register
    pick = np.zeros(len(frames), dtype=bool)
    pick[np.unique(np.linspace(0, len(frames) - 1, min(rc.coarse_frames, len(frames))).round().astype(int))] = True
    retrieval = replace(rc, candidates="retrieval")
    first = register_frames([f for f, p in zip(frames, pick) if p], K, index, retrieval)
    coarse = _coarse_offset(cfg, first, T_vio)
    if coarse is None:  # retrieval failed on the sample: try it with more candidates
        wider = replace(retrieval, num_candidates=rc.num_candidates * cfg.retry_candidates_factor)
        log.info("%s: no VIO-consistent coarse offset from %d frames; retrying with %d candidates", name,
                 int(pick.sum()), wider.num_candidates)
        first = register_frames([f for f, p in zip(frames, pick) if p], K, index, wider)
        coarse = _coarse_offset(cfg, first, T_vio)
    rest = [f for f, p in zip(frames, pick) if not p]
    if coarse is None:
        log.info("%s: still no coarse offset; registering every frame by retrieval", name)
        reg = first.merged(register_frames(rest, K, index, retrieval))
    else:
        predicted = {int(f[0]): coarse.apply(T_vio[int(f[0])]) for f in rest}
        reg = first.merged(register_frames(rest, K, index, replace(rc, candidates="auto"), predicted))
    if reg.registered_fraction < cfg.retry_below_fraction:
        # Rare now: retry only the frames that failed, against more retrieval candidates.
        failed = set(int(t) for t in reg.attempted) - set(int(t) for t in reg.t)
        wider = replace(retrieval, num_candidates=rc.num_candidates * cfg.retry_candidates_factor)
        log.info("%s: %.0f%% registered; retrying %d frames with %d candidates", name, 100 * reg.registered_fraction,
                 len(failed), wider.num_candidates)
        retry = register_frames([f for f in frames if int(f[0]) in failed], K, index, wider)
        keep = ~np.isin(reg.attempted, retry.attempted)
        reg = Registration(reg.attempted[keep], reg.attempted_inliers[keep], reg.t, reg.T_world_cam, reg.inliers,
                           reg.reproj_error_px, reg.correspondences, (), reg.seconds).merged(retry)
    return reg


def _coarse_offset(cfg: CalibrateConfig, reg: Registration, T_vio: np.ndarray) -> YawOffset | None:
    """The offset of the VIO-consistent frames of a first registration, or None when fewer than 3
    frames agree (or they cannot fix the yaw)."""
    if len(reg.t) < 3:
        return None
    check = check_against_vio(reg.T_world_cam, T_vio[reg.t], reg.inliers, cfg.vio_max_disagreement_m,
                              cfg.vio_max_disagreement_deg)
    if check.accepted.sum() < 3:
        return None
    try:
        return chain_yaw_offset(T_vio[reg.t[check.accepted]], reg.T_world_cam[check.accepted], cfg.offset).offset
    except ValueError:
        return None


def _check_view(cfg: CalibrateConfig, capture: Path, v: str, reg: Registration, check) -> None:
    """One clear error for a view that cannot be calibrated (names the capture and the likely cause)."""
    n_tried, n_reg = len(reg.attempted), len(reg.t)
    if n_reg < cfg.min_registered_frames or n_reg < cfg.min_registered_fraction * max(n_tried, 1):
        raise InputError(capture, f"view {v}: only {n_reg} of {n_tried} sampled frames registered to the scene model "
                         f"(need {100 * cfg.min_registered_fraction:.0f} %)", "likely causes: too little background "
                         "texture, the wrong scene capture, very different lighting, or the performer filling the view")
    n_ok = int(check.accepted.sum())
    if n_ok < cfg.min_registered_frames or n_ok < cfg.min_consistent_fraction * n_reg:
        raise _VioDisagreement(capture, f"view {v}: its registered frames disagree with its own VIO motion almost everywhere "
                         f"(largest consistent group {n_ok} of {n_reg} frames, {check.runs} runs)",
                         "likely causes: the sequence was not filmed in this scene (wrong scene capture in "
                         "session.toml), broken VIO poses, or too little background texture / very different "
                         "lighting for registration to be reliable")


class _VioDisagreement(InputError):
    """The view's registered frames disagree with its VIO (a view the performer may still place)."""


def _load_registration(path: Path) -> dict:
    """A view's registration (checked by the typed reader) as a dict the stage can complete."""
    return dict(read_registration(path).items())


def _yaw_offset_of(T: np.ndarray) -> YawOffset:
    T = np.asarray(T, dtype=np.float64)
    return YawOffset(float(np.arctan2(T[1, 0], T[0, 0])), T[:3, 3].copy(), 1.0)


def _place_by_performer(cfg: CalibrateConfig, lay: SessionLayout, entry, v: str, regs: dict, err: InputError) -> np.ndarray:
    """``T_world_vio`` (4, 4) of view ``v`` from the performer both views film, or ``err`` raised.

    The other view's offset comes from its own VIO-consistent registrations; each cross-view
    keypoint pair (back-projected with depth) gives a point in the world through the other view
    and the same point in ``v``'s VIO world; the robust yaw fit of the second onto the first
    places ``v``. Kept only when ``v``'s background depth then lies on the scene mesh (a capture
    of another scene does not)."""
    from embodmocap.calibrate import losses as L
    from embodmocap.calibrate.offset import robust_yaw_offset
    from embodmocap.scene.mesh import read_mesh_ply

    others = [w for w in VIEWS if w != v and w in regs]
    note = "; placing it through the performer filmed by the other view did not fit the scene either"
    if not others or _sync_record(lay.sequence(entry.name), entry.name)["slicing"]["source"] == "start":
        raise err
    w = others[0]
    sl = lay.sequence(entry.name)
    r = regs[w]
    cams = {x: np.load(sl.view(x).cameras) for x in (v, w)}
    acc = np.asarray(r["accepted"], dtype=bool)
    T_w = chain_yaw_offset(cams[w]["T_world_cam"][r["t"][acc]], r["T_world_cam"][acc], cfg.offset).offset.T
    tracks = _track_pairs(lay, entry.name, cfg.track_frames)
    if tracks is None or len(tracks) < 20:
        raise InputError(err.path, err.problem + note, err.fix) from err
    f = tracks.frames.numpy()
    p = {tracks.view_a: tracks.p_a.numpy(), tracks.view_b: tracks.p_b.numpy()}

    def world(T_cams, pts):
        return np.einsum("nij,nj->ni", T_cams[f, :3, :3], pts) + T_cams[f, :3, 3]

    target = world(T_w @ cams[w]["T_world_cam"], p[w])
    fit = robust_yaw_offset(world(cams[v]["T_world_cam"], p[v]), target, cfg.offset)
    # Check on the scene mesh: the view's background through the placement.
    data = build_view_data(cfg, lay, entry.name, v, fit.offset, {**{"t": np.zeros(0, np.int64)},
                           "accepted": np.zeros(0, bool), "match_frames": np.zeros(0, np.int64),
                           "match_xy": np.zeros((0, 2)), "match_xyz": np.zeros((0, 3)),
                           "T_world_cam": np.zeros((0, 4, 4))})
    mv, mf, _ = read_mesh_ply(lay.scene(entry.scene).mesh_raw)
    scene_pts = L.ScenePoints.from_mesh(mv, mf, cfg.scene_points)

    def on_mesh(data) -> float:
        """Share of a view's background points within ``performer_on_mesh_m`` of the mesh."""
        bg = data.background
        if bg is None or not len(bg):
            return 0.0
        Tc = np.asarray(data.T_world_cam)[bg.frames.numpy()]
        q = np.einsum("nij,nj->ni", Tc[:, :3, :3], bg.p_cam.numpy()) + Tc[:, :3, 3]
        d, _ = scene_pts.tree.query(q, distance_upper_bound=cfg.performer_on_mesh_m, workers=1)
        return float(np.mean(np.isfinite(d)))

    on = on_mesh(data)
    # The registered view's own share is the yardstick: a scan that missed part of what the views
    # see lowers both alike, a view of another scene only its own.
    on_w = on_mesh(build_view_data(cfg, lay, entry.name, w, _yaw_offset_of(T_w), r))
    log.info("%s %s: placed through the performer in %s (%d keypoint pairs, %d inliers); %.0f%% of its background "
             "on the scene mesh (%s: %.0f%%)", entry.name, v, w, len(f), fit.num_inliers, 100 * on, w, 100 * on_w)
    if fit.num_inliers < 20 or on < cfg.performer_min_on_mesh * on_w:
        raise InputError(err.path, err.problem + note + f" ({100 * on:.0f} % of its background on the mesh)",
                         err.fix) from err
    log.warning("%s %s: %s; placed through the performer instead (%.0f%% of its background on the scene mesh)",
                entry.name, v, err.problem, 100 * on)
    return fit.offset.T


def _save_registration(path: Path, reg, check=None, off_chain=None, T_world_vio_performer=None) -> None:
    """Registered poses and their 2D-3D inlier matches (flattened with a frame column), and the
    VIO check's verdict per registered frame (``accepted``: kept by the run check and on the
    whole chain's offset; ``run``; ``off_chain``: kept by the run check but off the chain)."""
    fr = np.concatenate([np.full(len(c.xy), c.t) for c in reg.correspondences]) if reg.correspondences else np.zeros(0, int)
    xy = np.concatenate([c.xy for c in reg.correspondences]) if reg.correspondences else np.zeros((0, 2))
    xyz = np.concatenate([c.xyz for c in reg.correspondences]) if reg.correspondences else np.zeros((0, 3))
    acc = np.ones(len(reg.t), dtype=bool) if check is None else check.accepted
    run = np.zeros(len(reg.t), dtype=np.int64) if check is None else check.run
    off = np.zeros(len(reg.t), dtype=bool) if off_chain is None else np.asarray(off_chain, dtype=bool)
    acc = acc & ~off
    write_registration(path, RegistrationFile(
        version=np.int64(REGISTER_VERSION), attempted=reg.attempted, attempted_inliers=reg.attempted_inliers,
        t=reg.t, T_world_cam=reg.T_world_cam, inliers=reg.inliers, reproj_error_px=reg.reproj_error_px,
        match_frames=fr, match_xy=xy, match_xyz=xyz, accepted=acc, run=run, off_chain=off,
        T_world_vio_performer=None if T_world_vio_performer is None else np.asarray(T_world_vio_performer)))


def build_view_data(cfg: CalibrateConfig, lay: SessionLayout, seq: str, v: str, init: YawOffset, reg) -> ViewData:
    """The refinement's input for one view: initial cameras, background cloud, registered matches."""
    from embodmocap.calibrate import losses as L

    vl = lay.sequence(seq).view(v)
    cams = read_cameras(vl.cameras)
    T = len(cams["raw_frames"])
    width = int(cams["width"])
    frames = np.unique(np.linspace(0, T - 1, min(cfg.chamfer_frames, T)).astype(np.int64))
    has_masks = vl.masks.is_file()
    cloud = L.background_cloud(
        lambda t: read_depth_m(vl.depth, t),
        (lambda t: read_mask(vl.masks, t, width)) if has_masks else None,
        frames, cams["K_depth"], points_per_frame=cfg.chamfer_points_per_frame,
    )
    # Only matches of frames whose registration agrees with the offset: a wrongly registered frame
    # brings 2D-3D matches that are consistent with a wrong pose, and through the VIO pose they
    # reproject hundreds of pixels off (seen: one such frame outweighed every other term).
    agree = np.linalg.norm(init.apply_points(cams["T_world_cam"][reg["t"], :3, 3]) - reg["T_world_cam"][:, :3, 3], axis=1)
    accepted = np.asarray(reg["accepted"], dtype=bool) if "accepted" in reg else np.ones(len(reg["t"]), bool)
    # Frames of runs the VIO check rejected never reach the fit, however close they happen to be.
    ok_frames = np.asarray(reg["t"])[(agree <= cfg.offset.inlier_threshold_m) & accepted]
    keep = np.isin(reg["match_frames"], ok_frames)
    matches = L.Matches2D3D.from_arrays(reg["match_frames"][keep], reg["match_xy"][keep], reg["match_xyz"][keep])
    return ViewData(T_world_cam=init.apply(cams["T_world_cam"]), K=cams["K"], background=cloud,
                    matches=matches, T_world_vio_init=init.T)


def _sync_record(out, seq: str) -> dict:
    """Stage II's sync.json (version 2), or one clear error."""
    from embodmocap.sequence.sync_record import SYNC_RECORD_VERSION

    if not out.sync.is_file():
        raise InputError(out.sync, "Stage II's sync.json is missing", f"run `embodmocap sequence --seq {seq}` first")
    rec = json.loads(out.sync.read_text())
    if rec.get("version") != SYNC_RECORD_VERSION:
        raise InputError(out.sync, f"sync.json is version {rec.get('version')}, this Stage III needs {SYNC_RECORD_VERSION}",
                         f"rerun `embodmocap sequence --seq {seq}` (it redoes the sync and the slicing)")
    return rec


def _geosync_step(cfg: CalibrateConfig, out, seq: str, T_world_vio: dict, calib_fp, sm: StageManifest, force: bool,
                  skipped: list[str], captures: dict) -> dict:
    """Geometric sync on the refined cameras; writes the final sync record and ``cameras_world``."""
    from embodmocap.sequence.geosync import GEOSYNC_VERSION, geometric_sync
    from embodmocap.sequence.subframe import frame_times
    from embodmocap.sequence.laser_check import laser_dot_check
    from embodmocap.sequence.sync_record import decide

    rec = _sync_record(out, seq)
    fp = fingerprint("geosync", GEOSYNC_VERSION, {k: rec[k] for k in ("views", "slicing")}, rec["sources"].get("laser"),
                     rec["sources"].get("manual"), calib_fp, *[path_fingerprint(out.view(v).keypoints) for v in VIEWS],
                     *[path_fingerprint(out.view(v).cameras) for v in VIEWS], cfg.geosync)
    if not force and sm.is_current("geosync", fp) and rec.get("chosen", {}).get("final"):
        skipped.append("geosync")
        return rec
    t0 = time.perf_counter()
    fps = sequence_fps(out)
    cams = {v: read_cameras(out.view(v).cameras) for v in VIEWS}
    world = {v: T_world_vio[v] @ cams[v]["T_world_cam"] for v in VIEWS}
    geo = None
    if cfg.geosync.enabled:
        data = [(cams[v]["K"], world[v], read_keypoints2d(out.view(v).keypoints).keypoints, frame_times(cams[v], fps))
                for v in VIEWS]
        search = cfg.geosync.search_s_without_laser if rec["slicing"]["source"] == "start" else cfg.geosync.search_s
        geo = geometric_sync(*data[0], *data[1], fps=fps, search_s=search, cfg=cfg.geosync)
        log.info("%s: geometric sync %+.3f frames from the slicing (confidence %.2f, +-%.3f frames)%s", seq,
                 geo.offset_frames, geo.confidence, geo.std_frames, f": {geo.message}" if geo.message else "")
    sheets = {v: str(out.root / d["contact_sheet"]) for v, d in rec["sources"]["laser"]["views"].items()
              if d.get("contact_sheet")}
    # The laser events as places in the world: one dot is one place in both views.
    dot_check = laser_dot_check(rec, captures, T_world_vio, cfg.geosync.laser_dot_agree_m)
    rec = decide(rec, geo, cfg.geosync, fps, sheets, seq, dot_check)
    write_json(out.sync, rec)
    amend_output(out.manifest, out.sync)  # Stage II's file, completed here: not a change behind its back
    for w in rec["warnings"]:
        log.warning("%s", w)
    outs = [out.sync]
    for v in VIEWS:
        # time_offset_s: the sub-frame sync Stage IV applies to this view (sync.json's residual).
        write_cameras(out.view(v).cameras_world, CameraFile(
            version=np.int64(1), K=cams[v]["K"], width=cams[v]["width"], height=cams[v]["height"], T_world_cam=world[v],
            raw_frames=cams[v]["raw_frames"], time_offset_s=np.float64(rec["chosen"]["residual_s"] if v == VIEWS[1] else 0.0)))
        outs.append(out.view(v).cameras_world)
    ch = rec["chosen"]
    sm.record("geosync", fp, outs, time.perf_counter() - t0, {
        "sync_source": ch["source"], "sync_offset_s": round(ch["offset_s"], 6), "sync_residual_frames": ch["residual_frames"],
        "geometric_offset_frames": None if geo is None or not geo.found else round(geo.offset_frames, 4),
        "geometric_confidence": None if geo is None else round(geo.confidence, 3),
        "laser_minus_geometric_frames": (rec["agreement"] or {}).get("laser_minus_geometric_frames"),
        "laser_dot_gap_m": None if dot_check is None or dot_check.gap_m is None else round(dot_check.gap_m, 4),
    })
    return rec


def _refine(cfg: CalibrateConfig, lay: SessionLayout, entry, init: dict, regs: dict, init_report: dict,
            use_tracks: bool = True) -> dict:
    from embodmocap.calibrate import losses as L
    from embodmocap.io.mesh_file import read_mesh_ply

    warnings: list[str] = []
    views = {v: build_view_data(cfg, lay, entry.name, v, init[v], regs[v]) for v in VIEWS}
    result = None
    if cfg.refine_views:
        mv, mf, _ = read_mesh_ply(lay.scene(entry.scene).mesh_raw)
        scene_pts = L.ScenePoints.from_mesh(mv, mf, cfg.scene_points)
        tracks = _track_pairs(lay, entry.name, cfg.track_frames) if use_tracks else None
        if not use_tracks:
            warnings.append("no laser sync: the views were sliced from their first frames, so cross-view keypoint "
                            "pairs are not used by the refinement")
        result = refine_offsets(views, cfg.refine, scene=scene_pts, tracks=tracks)
        warnings += list(result.warnings)
        if result.diverged:
            warnings.append(f"refinement diverged ({result.message}); the registration-only offsets are kept")
    report = {"version": CALIBRATION_VERSION, "sequence": entry.name, "scene": entry.scene, "views": {}, "warnings": warnings}
    for v in VIEWS:
        T0 = init[v].T
        T1 = result.views[v].T_world_vio if result is not None and not result.diverged else T0
        D = T1 @ np.linalg.inv(T0)
        shift, yaw = float(np.linalg.norm(D[:3, 3])), float(np.degrees(rotation_angle(D[:3, :3])))
        if shift > cfg.max_refine_shift_m or yaw > cfg.max_refine_yaw_deg:
            warnings.append(f"view {v}: refinement disagrees with registration by {100 * shift:.1f} cm / {yaw:.2f} deg "
                            f"(limits {100 * cfg.max_refine_shift_m:.0f} cm / {cfg.max_refine_yaw_deg} deg)")
        report["views"][v] = {
            "T_world_vio_registration": T0.tolist(), "T_world_vio": T1.tolist(),
            "refine_shift_m": round(shift, 5), "refine_yaw_deg": round(yaw, 4),
            "registered_fraction": float(len(regs[v]["t"]) / max(len(regs[v]["attempted"]), 1)),
            "vio_check": init_report[v]["vio_check"],
            "offset_fit": init_report[v],
        }
    if result is not None:
        report["refine"] = {
            "solver": result.solver, "iterations": result.iterations, "loss_before": result.loss_before,
            "loss_after": result.loss_after, "terms_before": result.terms_before, "terms_after": result.terms_after,
            "residuals_before": result.stats_before, "residuals_after": result.stats_after,
            "diverged": result.diverged, "message": result.message,
            "solvers": {k: {"loss": r.loss_final, "iterations": r.iterations, "seconds": round(r.seconds, 3)}
                        for k, r in result.runs.items()},
        }
    return report


def _track_pairs(lay: SessionLayout, seq: str, max_frames: int = 0):
    """Cross-view performer correspondences from the Stage II keypoints, back-projected with depth;
    from at most ``max_frames`` evenly spread frames (0 = all)."""
    from dataclasses import replace as _replace

    from embodmocap.calibrate import losses as L

    sl = lay.sequence(seq)
    kp = {v: read_keypoints2d(sl.view(v).keypoints).keypoints for v in VIEWS}
    cams = {v: read_cameras(sl.view(v).cameras) for v in VIEWS}
    corr = L.KeypointCorrespondences(kp["v1"], kp["v2"]).correspondences()
    n = min(len(kp["v1"]), len(kp["v2"]))
    if 0 < max_frames < n:
        keep = np.isin(corr.frames, np.unique(np.linspace(0, n - 1, max_frames).round().astype(np.int64)))
        corr = _replace(corr, frames=corr.frames[keep], xy_a=corr.xy_a[keep], xy_b=corr.xy_b[keep],
                        weight=corr.weight[keep], behind_surface_m=corr.behind_surface_m[keep])
    if len(corr.frames) == 0:
        return None
    return L.track_pairs_from_depth(
        corr, VIEWS, tuple((lambda t, v=v: read_depth_m(sl.view(v).depth, t)) for v in VIEWS),
        tuple(cams[v]["K"] for v in VIEWS),
        tuple((int(cams[v]["width"]), int(cams[v]["height"])) for v in VIEWS),
    )


#: The public name of :func:`_track_pairs` (the benchmark rebuilds Stage III with it).
track_pairs = _track_pairs
