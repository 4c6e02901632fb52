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
4. outputs: ``calibration.json`` (offsets before/after, residual report, registered fractions,
   warnings) and ``<view>/cameras_world.npz`` (per-frame cameras in the scene's world).

A refinement that diverges, or moves a view further from its registration than the configured
limits, is reported with its numbers (and the registration-only offset is kept when it diverged).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from embodmocap.calibrate.offset import RobustOffsetConfig, YawOffset, robust_yaw_offset
from embodmocap.calibrate.refine import RefineConfig, ViewData, refine_offsets
from embodmocap.calibrate.register import RegisterConfig, build_scene_index, load_view_frames, register_frames, sample_frames
from embodmocap.errors import InputError
from embodmocap.geometry.transforms import rotation_angle
from embodmocap.io.atomic import write_json, write_npz
from embodmocap.io.captures import open_capture
from embodmocap.io.frame_stack import read_depth_m, read_mask
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.stage_manifest import StageManifest, Upstream, fingerprint, path_fingerprint, tracked_stage

log = logging.getLogger(__name__)

CALIBRATION_VERSION = 1


@dataclass(frozen=True)
class CalibrateConfig:
    """How Stage III registers and refines the two views."""

    register: RegisterConfig = field(default_factory=RegisterConfig)
    """Registration of view frames into the scene's sparse model."""
    offset: RobustOffsetConfig = field(default_factory=RobustOffsetConfig)
    """Robust yaw-only fit of the initial offset."""
    refine: RefineConfig = field(default_factory=RefineConfig)
    """Joint refinement (losses, weights, solvers)."""
    refine_views: bool = True
    """Run the joint refinement (False = keep the registration-only offsets)."""
    retry_below_fraction: float = 0.5
    """A view registering fewer of its sampled frames than this is registered again against
    ``retry_candidates_factor`` times more candidate key frames."""
    retry_candidates_factor: int = 3
    """How many times more candidate key frames the retry matches against."""
    min_registered_fraction: float = 0.1
    """Fewer registered frames than this fraction of those tried is an error for the view."""
    min_registered_frames: int = 5
    """Fewer registered frames than this is an error for the view."""
    max_refine_shift_m: float = 0.15
    """A refinement moving a view further than this from its registration offset is warned about."""
    max_refine_yaw_deg: float = 3.0
    """A refinement turning a view more than this from its registration offset is warned about."""
    chamfer_frames: int = 30
    """Frames per view whose background depth feeds the Chamfer term (evenly spread)."""
    chamfer_points_per_frame: int = 400
    """Background points per frame for the Chamfer term."""
    scene_points: int = 50000
    """Points sampled on the scene mesh for the Chamfer term."""


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
    from embodmocap.sequence.stage import _pick_sequence

    lay = SessionLayout(Path(session))
    entry = _pick_sequence(load_manifest(lay.manifest), seq)
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
    for v in VIEWS:
        vl = out.view(v)
        reg_path = vl.registration
        fp = fingerprint("register", upstream, path_fingerprint(vl.masks) if vl.masks.is_file() else None, cfg.register)
        if not force and sm.is_current(f"register_{v}", fp):
            skipped.append(f"register_{v}")
        else:
            t0 = time.perf_counter()
            index = index or build_scene_index(scene.sfm_dir, cfg.register)
            cams = np.load(vl.cameras)
            ts = sample_frames(len(cams["raw_frames"]), cfg.register.num_frames)
            frames, K, _ = load_view_frames(vl, open_capture(entry.views[v].capture), ts)
            reg = register_frames(frames, K, index, cfg.register)
            if reg.registered_fraction < cfg.retry_below_fraction:
                # Retrieval can rank the right key frames low (repetitive texture, distant views):
                # match against more candidates before giving up on the view.
                wider = replace(cfg.register, num_candidates=cfg.register.num_candidates * cfg.retry_candidates_factor)
                log.info("%s %s: %.0f%% registered with %d candidates; retrying with %d", entry.name, v,
                         100 * reg.registered_fraction, cfg.register.num_candidates, wider.num_candidates)
                retry = register_frames(frames, K, index, wider)
                if retry.registered_fraction > reg.registered_fraction:
                    reg = retry
            _save_registration(reg_path, reg)
            sm.record(f"register_{v}", fp, [reg_path], time.perf_counter() - t0, {
                f"{v}_frames_tried": int(len(reg.attempted)), f"{v}_frames_registered": int(len(reg.t)),
                f"{v}_registered_fraction": round(reg.registered_fraction, 3),
                f"{v}_register_seconds": {k: round(s, 2) for k, s in reg.seconds.items()},
            })
        regs[v] = np.load(reg_path)
        n_tried, n_reg = len(regs[v]["attempted"]), len(regs[v]["t"])
        if n_reg < cfg.min_registered_frames or n_reg < cfg.min_registered_fraction * max(n_tried, 1):
            raise InputError(entry.views[v].capture, f"view {v}: only {n_reg} of {n_tried} sampled frames registered "
                             "to the scene model", "likely causes: too little background texture, the wrong scene "
                             "capture, very different lighting, or the performer filling the view")

    # 2. Initial yaw-only offsets.
    init: dict[str, YawOffset] = {}
    init_report = {}
    for v in VIEWS:
        cams = np.load(out.view(v).cameras)
        r = regs[v]
        fit = robust_yaw_offset(cams["T_world_cam"][r["t"], :3, 3], r["T_world_cam"][:, :3, 3], cfg.offset)
        init[v] = fit.offset
        init_report[v] = {"inliers": int(fit.num_inliers), "registered": int(len(r["t"])),
                          "median_residual_m": float(np.median(fit.residuals_m[fit.inliers])) if fit.num_inliers else None}

    # 3. Joint refinement.
    fp_ref = fingerprint("refine", upstream, *[path_fingerprint(out.view(v).registration) for v in VIEWS],
                         cfg.offset, cfg.refine, cfg.refine_views, cfg.chamfer_frames, cfg.chamfer_points_per_frame)
    calib_path = out.calibration
    if not force and sm.is_current("refine", fp_ref):
        skipped.append("refine")
    else:
        t0 = time.perf_counter()
        report = _refine(cfg, lay, entry, init, regs, init_report)
        write_json(calib_path, report)
        outs = [calib_path]
        for v in VIEWS:
            cams = np.load(out.view(v).cameras)
            T = np.asarray(report["views"][v]["T_world_vio"]) @ cams["T_world_cam"]
            write_npz(out.view(v).cameras_world, version=np.int64(1), K=cams["K"], width=cams["width"],
                      height=cams["height"], T_world_cam=T, raw_frames=cams["raw_frames"])
            outs.append(out.view(v).cameras_world)
        sm.record("refine", fp_ref, outs, time.perf_counter() - t0, {
            f"{v}_{k}": report["views"][v][k] for v in VIEWS for k in ("refine_shift_m", "refine_yaw_deg")})
    report = json.loads(calib_path.read_text())
    for w in report.get("warnings", []):
        log.warning("%s: %s", entry.name, w)
    return CalibrateOutputs(entry.name, {v: np.asarray(report["views"][v]["T_world_vio"]) for v in VIEWS},
                            report, tuple(skipped))


def _save_registration(path: Path, reg) -> None:
    """Registered poses and their 2D-3D inlier matches (flattened with a frame column)."""
    fr = np.concatenate([np.full(len(c.xy), c.t) for c in reg.correspondences]) if reg.correspondences else np.zeros(0, int)
    xy = np.concatenate([c.xy for c in reg.correspondences]) if reg.correspondences else np.zeros((0, 2))
    xyz = np.concatenate([c.xyz for c in reg.correspondences]) if reg.correspondences else np.zeros((0, 3))
    write_npz(path, version=np.int64(1), attempted=reg.attempted, attempted_inliers=reg.attempted_inliers, t=reg.t,
              T_world_cam=reg.T_world_cam, inliers=reg.inliers, reproj_error_px=reg.reproj_error_px,
              match_frames=fr, match_xy=xy, match_xyz=xyz)


def build_view_data(cfg: CalibrateConfig, lay: SessionLayout, seq: str, v: str, init: YawOffset, reg) -> ViewData:
    """The refinement's input for one view: initial cameras, background cloud, registered matches."""
    from embodmocap.calibrate import losses as L

    vl = lay.sequence(seq).view(v)
    cams = np.load(vl.cameras)
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
    ok_frames = np.asarray(reg["t"])[agree <= cfg.offset.inlier_threshold_m]
    keep = np.isin(reg["match_frames"], ok_frames)
    matches = L.Matches2D3D.from_arrays(reg["match_frames"][keep], reg["match_xy"][keep], reg["match_xyz"][keep])
    return ViewData(T_world_cam=init.apply(cams["T_world_cam"]), K=cams["K"], background=cloud,
                    matches=matches, T_world_vio_init=init.T)


def _refine(cfg: CalibrateConfig, lay: SessionLayout, entry, init: dict, regs: dict, init_report: dict) -> dict:
    from embodmocap.calibrate import losses as L
    from embodmocap.scene.mesh import read_mesh_ply

    warnings: list[str] = []
    views = {v: build_view_data(cfg, lay, entry.name, v, init[v], regs[v]) for v in VIEWS}
    result = None
    if cfg.refine_views:
        mv, mf, _ = read_mesh_ply(lay.scene(entry.scene).mesh_raw)
        scene_pts = L.ScenePoints.from_mesh(mv, mf, cfg.scene_points)
        tracks = _track_pairs(lay, entry.name)
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


def _track_pairs(lay: SessionLayout, seq: str):
    """Cross-view performer correspondences from the Stage II keypoints, back-projected with depth."""
    from embodmocap.calibrate import losses as L

    sl = lay.sequence(seq)
    kp = {v: np.load(sl.view(v).keypoints)["keypoints"] for v in VIEWS}
    cams = {v: np.load(sl.view(v).cameras) for v in VIEWS}
    corr = L.KeypointCorrespondences(kp["v1"], kp["v2"]).correspondences()
    if len(corr.frames) == 0:
        return None
    return L.track_pairs_from_depth(
        corr, VIEWS, tuple((lambda t, v=v: read_depth_m(sl.view(v).depth, t)) for v in VIEWS),
        tuple(cams[v]["K"] for v in VIEWS),
        tuple((int(cams[v]["width"]), int(cams[v]["height"])) for v in VIEWS),
    )
