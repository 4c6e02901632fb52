"""Stage IV: world-space SMPL motion with the cameras and the scene fixed.

``run(config, session, seq)`` reads top to bottom as the recipe:

1. ``triangulate``: both views' COCO-17 keypoints (Stage II), left/right swaps undone, triangulated
   with the cameras in the scene's world (Stage III): confidence-weighted DLT over all frames at
   once, short gaps filled, long gaps flagged -> ``keypoints3d.npz``;
2. ``fit``: the world SMPLify (shape, translation and orientation first; then everything) on the
   3D keypoints, each view's 2D keypoints (both with the SMPL points of the detector's layout),
   smoothness, anatomical joint ranges and the pose prior, started from the camera-space body
   prior moved into the world, or without a prior from the 3D keypoints alone (shape from bone
   lengths, torso fit, limb IK: :mod:`embodmocap.motion.ik`); the prior loses to the triangulation
   where it is grossly off; limbs whose start their keypoints reject take the pose carried over
   from the frames where they fit (:mod:`embodmocap.motion.propagate`). Too few triangulated joints is one clear error; frames where the body
   cannot be placed are flagged ``valid = False`` -> ``smpl_fit.npz``;
3. ``align``: with contact markers in the manifest, the yaw + translation that puts the feet on
   the markers, applied to the body (pelvis-consistent) and the cameras; refused, with the
   residual, when the markers disagree -> ``smpl_world.npz``, ``joints_world.npz`` and
   ``<view>/cameras_final.npz`` (the final outputs, also written without markers).

Each step is fingerprinted in ``motion_manifest.json`` and skipped when its inputs and settings
did not change.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.geometry.triangulation import projection_matrices, triangulate
from embodmocap.io.atomic import write_npz
from embodmocap.io.layout import VIEWS, SessionLayout, SequenceLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.smpl_file import read_smpl_npz, read_smpl_valid, write_smpl_npz
from embodmocap.io.stage_files import read_cameras, read_keypoints2d, read_keypoints3d, sequence_fps
from embodmocap.io.stage_manifest import StageManifest, Upstream, fingerprint, path_fingerprint, tracked_stage
from embodmocap.motion.config import MotionConfig  # noqa: F401 (re-exported: defined in config.py)
from embodmocap.motion.contact import align_to_contacts, apply_alignment, apply_alignment_to_cameras
from embodmocap.motion.init import init_from_keypoints, init_from_prior, snap_to_keypoints
from embodmocap.motion.label_track import TRACKED_GROUPS, track_labels
from embodmocap.motion.smplify import ViewObservations, fit_world_smpl
from embodmocap.motion.swaps import COCO17_SWAP_GROUPS, fix_swaps
from embodmocap.motion.temporal import drop_guessed_runs
from embodmocap.sequence.subframe import synced_views

log = logging.getLogger(__name__)

KEYPOINTS3D_VERSION = 1


@dataclass(frozen=True)
class MotionOutputs:
    """What Stage IV produced for one sequence."""

    name: str
    layout: SequenceLayout
    figures: dict
    skipped: tuple[str, ...]


@tracked_stage
def run(cfg: MotionConfig, session: str | Path, seq: str | None = None, *, force: bool = False) -> MotionOutputs:
    """Run Stage IV for sequence ``seq`` (the only one when None)."""
    from embodmocap.body.model import load_body_model

    lay = SessionLayout(Path(session))
    manifest = load_manifest(lay.manifest)
    entry = manifest.sequence(seq)
    out = lay.sequence(entry.name)
    for v in VIEWS:
        vl = out.view(v)
        if not vl.keypoints.is_file():
            raise InputError(vl.keypoints, "Stage II outputs are missing", f"run `embodmocap sequence {lay.root} --seq {entry.name}` first")
        if not vl.cameras_world.is_file():
            raise InputError(vl.cameras_world, "Stage III outputs are missing", f"run `embodmocap calibrate {lay.root} --seq {entry.name}` first")
    sm = StageManifest(out.motion_manifest, "motion", cfg, root=lay.root, upstream=[
        Upstream(lay.scene(entry.scene).manifest, "scene", f"embodmocap scene {lay.root} --scene {entry.scene}"),
        Upstream(out.manifest, "sequence", f"embodmocap sequence {lay.root} --seq {entry.name}"),
        Upstream(out.calibrate_manifest, "calibrate", f"embodmocap calibrate {lay.root} --seq {entry.name}")],
        inputs=[manifest.body_model, *[getattr(out.view(v), k) for v in VIEWS
                                       for k in ("keypoints", "cameras_world", "body_prior")]])
    skipped: list[str] = []
    cams = {v: read_cameras(out.view(v).cameras_world) for v in VIEWS}
    kps = {v: read_keypoints2d(out.view(v).keypoints).keypoints for v in VIEWS}
    # Sub-frame sync: view 2's keypoints and cameras at view 1's instants (cams_raw: each view's own frames).
    cams_raw, (cams, kps) = cams, synced_views(out, cams, kps)
    T = min(len(kps[v]) for v in VIEWS)
    fps = sequence_fps(out)

    def step(name: str, fp: str) -> bool:
        if not force and sm.is_current(name, fp):
            skipped.append(name)
            return False
        return True

    # 1. Triangulation.
    fp_tri = fingerprint("triangulate", cfg.triangulation, cfg.fix_swaps, cfg.label_track, cfg.temporal,
                         *[path_fingerprint(p) for v in VIEWS for p in (out.view(v).keypoints, out.view(v).cameras_world)])
    if step("triangulate", fp_tri):
        t0 = time.perf_counter()
        K = np.stack([cams[v]["K"] for v in VIEWS])
        P = projection_matrices(K, np.stack([cams[v]["T_world_cam"][:T] for v in VIEWS], axis=1))
        kp = np.stack([kps[v][:T] for v in VIEWS], axis=1)  # (T, V, 17, 3)
        kp, tracked = track_labels(kp, cfg.label_track, P=P)
        if cfg.fix_swaps:
            kp, swapped = fix_swaps(P, kp, cfg.triangulation)
        else:
            swapped = np.zeros((T, len(VIEWS), len(COCO17_SWAP_GROUPS)), dtype=bool)
        kp, guessed = drop_guessed_runs(kp, cfg.temporal)
        tri = triangulate(P, kp[..., :2], kp[..., 2], cfg.triangulation)
        write_npz(out.keypoints3d, version=np.int64(KEYPOINTS3D_VERSION), points=tri.points, conf=tri.conf,
                  reproj_err_px=tri.reproj_err_px, filled=tri.filled, views=np.array(VIEWS), keypoints2d=kp,
                  swapped=swapped, swap_groups=np.array(list(COCO17_SWAP_GROUPS)))
        seen = np.isfinite(tri.points[..., 0])
        sm.record("triangulate", fp_tri, [out.keypoints3d], time.perf_counter() - t0, {
            "triangulated_fraction": round(float(seen.mean()), 4),
            "filled_fraction": round(float(tri.filled.mean()), 4),
            "long_gaps": len(tri.long_gaps),
            "keypoints_dropped_temporal": int(guessed.sum()),
            "limb_labels_tracked": {f"{v}_{g}": int(tracked[:, i, k].sum()) for i, v in enumerate(VIEWS) for k, g in enumerate(TRACKED_GROUPS)},
            "triangulation_reproj_px_median": _nanmedian(tri.reproj_err_px),
            **{f"{v}_swaps_undone": {g: int(swapped[:, i, k].sum()) for k, g in enumerate(COCO17_SWAP_GROUPS)}
               for i, v in enumerate(VIEWS)},
        })
        if tri.long_gaps:
            worst = max(tri.long_gaps, key=lambda g: g[2] - g[1])
            log.warning("%s: %d gaps in the 3D keypoints are too long to fill (the longest: joint %d, frames %d-%d); "
                        "the fit relies on the 2D keypoints and smoothness there", entry.name, len(tri.long_gaps), *worst)

    # 2. SMPLify.
    model = load_body_model(manifest.body_model)
    priors = _priors(lay, entry.name, T, cfg) if cfg.use_body_prior else {}
    layout = keypoint_layout(out, entry.name)
    fp_fit = fingerprint("fit", cfg.smplify, cfg.use_body_prior, cfg.min_prior_fraction, cfg.min_frame_joints,
                         cfg.max_poor_fraction, cfg.min_valid_joints, cfg.prior_disagree_m, cfg.bone_tol,
                         cfg.bone_anchor_torso, cfg.propagate_limbs, cfg.kp3d_conf,
                         cfg.init_median_frames, layout,
                         path_fingerprint(out.keypoints3d), *[path_fingerprint(out.view(v).body_prior) for v in priors],
                         # the model's content, not its absolute path: a moved session redoes nothing
                         path_fingerprint(manifest.body_model) if manifest.body_model else model.source)
    if step("fit", fp_fit):
        if cfg.kp3d_conf not in ("mean", "min"):
            raise ValueError(f"MotionConfig.kp3d_conf must be 'mean' or 'min', got {cfg.kp3d_conf!r}")
        t0 = time.perf_counter()
        k3 = read_keypoints3d(out.keypoints3d)
        valid = placeable_frames(out.keypoints3d, entry.name, k3["points"], k3["conf"], cfg)
        # The 2D keypoints as the triangulation step left them (left/right swaps undone).
        kp2d = k3["keypoints2d"] if "keypoints2d" in k3.files else np.stack([kps[v][:T] for v in VIEWS], axis=1)
        views = [ViewObservations(K=cams[v]["K"], T_world_cam=cams[v]["T_world_cam"][:T], keypoints=kp2d[:, i], name=v)
                 for i, v in enumerate(VIEWS)]
        min_conf = cfg.smplify.min_conf
        points, conf3 = k3["points"], k3["conf"]
        if cfg.kp3d_conf == "min":
            # A point is as trustworthy as its weakest view: with two views, one wrong 2D point moves
            # the triangulated point along the other view's ray without any reprojection error.
            c2 = np.nan_to_num(kp2d[..., 2])
            used = c2 >= cfg.triangulation.min_conf
            weakest = np.where(used, c2, np.inf).min(axis=1)
            conf3 = np.where(np.isfinite(weakest), np.minimum(conf3, weakest), conf3)
        if cfg.bone_tol > 0:
            from embodmocap.motion.ik import (betas_from_bone_lengths, implausible_points, observed_bone_lengths,
                                              rest_skeleton, torso_anchors)

            sk = rest_skeleton(model, layout)
            seen = np.isfinite(points).all(-1) & (np.nan_to_num(conf3) >= min_conf)
            b_bones = betas_from_bone_lengths(sk, observed_bone_lengths(points, seen))
            # An elbow (knee) whose shoulder (hip) was not triangulated is judged against the
            # shoulder of the torso placed on the other torso points.
            anchors = torso_anchors(sk, b_bones, points, seen) if cfg.bone_anchor_torso else None
            gated = implausible_points(sk, b_bones, points, seen, cfg.bone_tol, anchors)
            conf3 = np.where(gated, 0.0, conf3)
        else:
            gated = np.zeros(points.shape[:2], dtype=bool)
        try:
            kp_init = init_from_keypoints(model, running_median(points, cfg.init_median_frames), conf3, fps,
                                          manifest.gender or "neutral", min_conf, layout)
        except ValueError as err:
            kp_init = None
            if not priors:
                raise InputError(out.keypoints3d, f"cannot place a starting body in sequence {entry.name}: {err}",
                                 "both views must see the hips and shoulders in some frames; or give a body prior "
                                 "(body_prior in session.toml)") from err
        prior_pose, v_best, prior_w, n_replaced = None, None, None, 0
        if priors:
            v_best = max(priors, key=lambda v: priors[v][1].mean())
            prior, has = priors[v_best]
            init = init_from_prior(model, prior, cams[v_best]["T_world_cam"][:T], fps, manifest.gender or "neutral")
            # The prior's depth can be far off; start where the triangulation says the body is.
            init = snap_to_keypoints(model, init, points, conf3)
            prior_pose = init.body_pose
            if kp_init is not None:
                # Where the prior disagrees with the triangulation (a flipped body, limbs elsewhere),
                # the triangulation wins: start there from the keypoints, and do not pull to the prior.
                init, worse = prefer_keypoints(model, init, kp_init, points, conf3, min_conf,
                                               cfg.prior_disagree_m, layout)
                prior_w, n_replaced = (~worse).astype(np.float64), int(worse.sum())
            log.info("%s: initialised from the %s body prior (%.0f%% of frames; %d frames from the keypoints)",
                     entry.name, v_best, 100 * has.mean(), n_replaced)
        else:
            init = kp_init
        init = _with_fps(init, fps, manifest.gender)
        n_propagated = 0
        if cfg.propagate_limbs:
            from embodmocap.motion.propagate import propagate_limbs
            from embodmocap.motion.smplify import KeypointBody

            # Limbs whose start both views and the 3D points reject take the pose carried over from
            # the frames where the limb fits its evidence.
            init, carried = propagate_limbs(
                KeypointBody(model, layout=layout), init, points, conf3, np.stack([cams[v]["K"] for v in VIEWS]),
                np.stack([cams[v]["T_world_cam"][:T] for v in VIEWS], axis=1), kp2d, cfg.smplify.kp3d_scale_m,
                cfg.smplify.reproj_scale_px, min_conf)
            n_propagated = int(carried.sum())
        res = fit_world_smpl(model, points, conf3, views, init, prior_pose, cfg.smplify, layout=layout,
                             prior_weight=prior_w)
        write_smpl_npz(out.smpl_fit, _with_fps(res.params, fps, manifest.gender), valid=valid)
        sm.record("fit", fp_fit, [out.smpl_fit], time.perf_counter() - t0, {
            "init": f"body prior {v_best}" if v_best else "keypoints",
            "init_frames_from_keypoints": n_replaced if v_best else int(T),
            "keypoint_layout": layout,
            "points_dropped_bone_length": int(gated.sum()),
            "limb_starts_propagated": n_propagated,
            "valid_frames": int(valid.sum()), "invalid_frames": int((~valid).sum()),
            "terms_before": res.terms_before, "terms_after": res.terms_after,
            **{f"{v}_reproj_px": round(float(res.reproj_px[v]), 3) for v in VIEWS},
            "fit_seconds": {k: round(float(x), 2) for k, x in res.phase_seconds.items()},
        })

    # 3. Contact alignment (always writes the final outputs).
    contacts = [(c.frame, np.asarray(c.xyz)) for c in entry.contacts] if cfg.align_contacts else []
    fp_align = fingerprint("align", cfg.contact, cfg.align_contacts, [(f, x.tolist()) for f, x in contacts],
                           path_fingerprint(out.smpl_fit), *[path_fingerprint(out.view(v).cameras_world) for v in VIEWS])
    if step("align", fp_align):
        t0 = time.perf_counter()
        params, frames = read_smpl_npz(out.smpl_fit)
        valid = read_smpl_valid(out.smpl_fit)
        # Every contact figure is written on every run: the stage manifest merges figures, and a
        # stale message from an earlier run must not survive.
        T_align = np.eye(4)
        figures = {"contact_alignment": "none (no contacts)", "contact_residuals_before_m": [],
                   "contact_residuals_after_m": [], "contact_message": ""}
        if contacts:
            bad = [f for f, _ in contacts if not 0 <= f < len(params)]
            if bad:
                raise InputError(lay.manifest, f"sequence {entry.name}: contact frames {bad} outside 0..{len(params) - 1}",
                                 "give contact frames in sequence frames (after sync and slicing)")
            al = align_to_contacts(model, params, contacts, cfg.contact)
            figures.update({"contact_residuals_before_m": [round(float(r), 4) for r in al.residuals_before_m],
                            "contact_residuals_after_m": [round(float(r), 4) for r in al.residuals_after_m],
                            "contact_alignment": "refused" if al.refused else "applied"})
            if al.refused:
                log.warning("%s: contact alignment refused: %s", entry.name, al.message)
                figures["contact_message"] = al.message
            else:
                T_align = al.T
                params = apply_alignment(model, params, T_align)
        write_smpl_npz(out.smpl_world, params, frames, valid=valid)
        body = model.from_params(params, dtype=__import__("torch").float64)
        write_npz(out.joints_world, version=np.int64(1), joints=body.joints.detach().numpy(),
                  coco17=body.coco17.detach().numpy(), frames=frames)
        outs = [out.smpl_world, out.joints_world]
        for v in VIEWS:
            c = cams_raw[v]
            write_npz(out.view(v).cameras_final, version=np.int64(1), K=c["K"], width=c["width"], height=c["height"],
                      T_world_cam=apply_alignment_to_cameras(c["T_world_cam"], T_align), raw_frames=c["raw_frames"])
            outs.append(out.view(v).cameras_final)
        figures["T_align"] = T_align.tolist()
        sm.record("align", fp_align, outs, time.perf_counter() - t0, figures)
    return MotionOutputs(entry.name, out, sm.figures(), tuple(skipped))


def keypoint_layout(out: SequenceLayout, seq: str) -> str:
    """The layout of the detector behind the sequence's 2D keypoints (``keypoints2d.npz``'s
    ``layout``; COCO17 for files written before it was recorded). Views that disagree fall back
    to COCO17 with a warning (one hip definition serves the 3D points of both)."""
    found = []
    for v in VIEWS:
        found.append(str(read_keypoints2d(out.view(v).keypoints).layout))  # COCO17 for files without it
    if len(set(found)) > 1:
        log.warning("%s: the views' keypoints come from different layouts %s; fitting with COCO-17 hips", seq, found)
        return "COCO17"
    return found[0]


def running_median(points: NDArray, frames: int) -> NDArray:
    """(T, J, 3) points through a centred running median of ``frames`` frames per coordinate,
    ignoring NaN (a point stays NaN where it was NaN: only the seen ones are replaced)."""
    if frames <= 1:
        return points
    from numpy.lib.stride_tricks import sliding_window_view

    h = frames // 2
    pad = np.concatenate([np.full((h,) + points.shape[1:], np.nan), points, np.full((h,) + points.shape[1:], np.nan)])
    win = sliding_window_view(pad, 2 * h + 1, axis=0)  # (T, J, 3, w)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(win, axis=-1)
    return np.where(np.isfinite(points), med, np.nan)


def placeable_frames(path: Path, seq: str, points: NDArray, conf: NDArray, cfg: MotionConfig) -> NDArray[np.bool_]:
    """(T,) frames where the body can be placed (see :attr:`MotionConfig.min_valid_joints`).

    Raises:
        InputError: more than ``cfg.max_poor_fraction`` of the frames have fewer than
            ``cfg.min_frame_joints`` triangulated joints.
    """
    # Any triangulated point counts (the triangulation already ignored weak detections); points
    # filled over short gaps count too: they are what the fit follows there.
    seen = np.isfinite(points).all(-1)
    n = seen.sum(1)
    poor = float((n < cfg.min_frame_joints).mean()) if len(n) else 1.0
    if poor > cfg.max_poor_fraction:
        raise InputError(path, f"sequence {seq}: {100 * poor:.0f}% of the {len(n)} frames have fewer than "
                         f"{cfg.min_frame_joints} triangulated joints (at most {100 * cfg.max_poor_fraction:.0f}% "
                         "allowed): too little to place a body",
                         "check that both views see the performer (keypoints2d.npz, the sync and the cameras)")
    torso = seen[:, [5, 6, 11, 12]].sum(1)
    return (n >= cfg.min_valid_joints) & (torso >= 2)


def prefer_keypoints(model, init, kp_init, points: NDArray, conf: NDArray, min_conf: float, margin_m: float,
                     layout: str = "COCO17"):
    """``init`` with the frames where it is more than ``margin_m`` further from the 3D keypoints
    than ``kp_init`` (median over the triangulated joints) taken from ``kp_init``; and those frames
    (T,) bool. Betas stay ``init``'s."""
    import torch
    from dataclasses import replace

    from embodmocap.body.joints import smpl_to_coco17

    seen = np.isfinite(points).all(-1) & (np.nan_to_num(conf) >= min_conf)

    def err(p):
        with torch.no_grad():
            out = model.from_params(p, dtype=torch.float64)
            kp = smpl_to_coco17(out.joints, out.vertices, model.vertex_ids, layout).numpy()
        d = np.where(seen, np.linalg.norm(kp - np.nan_to_num(points), axis=-1), 0.0)
        n = seen.sum(1)
        # Median over the seen joints of each frame (frames with none: 0, nothing to disagree with).
        d = np.sort(np.where(seen, d, np.inf), axis=1)
        mid = np.take_along_axis(d, np.clip((n - 1) // 2, 0, None)[:, None], 1)[:, 0]
        mid2 = np.take_along_axis(d, np.clip(n // 2, 0, None)[:, None], 1)[:, 0]
        return np.where(n > 0, 0.5 * (mid + np.where(n > 0, mid2, 0.0)), 0.0)

    kp_same_shape = replace(kp_init, betas=init.betas,
                            transl=np.asarray(kp_init.transl) + model.pelvis_offset(kp_init.betas) - model.pelvis_offset(init.betas))
    worse = err(init) > err(kp_same_shape) + margin_m
    if not worse.any():
        return init, worse
    pick = lambda a, b: np.where(worse.reshape((-1,) + (1,) * (np.ndim(a) - 1)), b, a)  # noqa: E731
    return replace(init, global_orient=pick(init.global_orient, kp_same_shape.global_orient),
                   body_pose=pick(init.body_pose, kp_same_shape.body_pose),
                   transl=pick(init.transl, kp_same_shape.transl)), worse


def _with_fps(params, fps: float, gender: str | None):
    from dataclasses import replace

    return replace(params, fps=float(fps), gender=gender or params.gender)


def _priors(lay: SessionLayout, seq: str, T: int, cfg: MotionConfig) -> dict:
    """view -> (prior with one row per sequence frame 0..T-1, (T,) bool has-estimate), for the views
    whose prior covers at least ``cfg.min_prior_fraction`` of the frames."""
    from embodmocap.io.body_prior import body_priors_by_frame

    return body_priors_by_frame({v: lay.sequence(seq).view(v).body_prior for v in VIEWS}, T, cfg.min_prior_fraction, seq)


def _nanmedian(a: NDArray) -> float | None:
    a = np.asarray(a, dtype=np.float64)
    return round(float(np.nanmedian(a)), 3) if np.isfinite(a).any() else None
