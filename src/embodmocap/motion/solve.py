"""Stage IV's decisions as pure functions: arrays, typed stage data and configs in, results out.

No function here takes a path, opens a file or touches a manifest: :mod:`embodmocap.motion.stage`
loads Stage II/III's files with :mod:`embodmocap.io.stage_files` (both views already on view 1's
instants, :func:`embodmocap.sequence.subframe.synced_views`), calls these one step at a time (so
each step is fingerprinted and resumable) and writes what they return. :func:`solve` chains the
same steps in memory, for the benchmark's variants and for tests:

1. :func:`triangulate_views`: left/right swaps undone, confidence-weighted DLT over all frames
   (``keypoints3d.npz``);
2. :func:`fit_motion`: the world SMPLify started from the body prior or the keypoints
   (``smpl_fit.npz``);
3. :func:`align_motion`: the contact-marker alignment and the final body, joints and cameras
   (``smpl_world.npz``, ``joints_world.npz``, ``<view>/cameras_final.npz``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.geometry.triangulation import projection_matrices, triangulate
from embodmocap.io.layout import VIEWS
from embodmocap.io.stage_files import CameraFile, Keypoints3DFile, WorldJointsFile
from embodmocap.motion.body_points import body_keypoints
from embodmocap.motion.config import MotionConfig
from embodmocap.motion.contact import align_to_contacts, apply_alignment, apply_alignment_to_cameras
from embodmocap.motion.init import prefer_keypoints, with_fps  # noqa: F401 (prefer_keypoints re-exported)
from embodmocap.motion.label_track import TRACKED_GROUPS
from embodmocap.motion.passes import Evidence, PassContext, carry_edge_limbs, report_of, run_passes
from embodmocap.motion.smplify import ViewObservations, fit_world_smpl
from embodmocap.motion.swaps import COCO17_SWAP_GROUPS

log = logging.getLogger(__name__)

KEYPOINTS3D_VERSION = 1


@dataclass(frozen=True)
class Triangulated:
    """The triangulation step's results: ``keypoints3d.npz``, the manifest figures, the gaps
    too long to fill ((joint, first, last) frames)."""

    file: Keypoints3DFile
    figures: dict
    long_gaps: list = field(default_factory=list)


def triangulate_views(cfg: MotionConfig, cams: Mapping[str, Mapping], kps: Mapping[str, NDArray], T: int,
                      label: str = "") -> Triangulated:
    """Both views' 2D keypoints triangulated with their world cameras (one view: :func:`lift_view`).

    Args:
        cams: view -> mapping with ``K`` (3, 3) and ``T_world_cam`` (>= T, 4, 4) (both views on
            view 1's instants); kps: view -> (>= T, 17, 3) keypoints; T: frames; label: the
            sequence (log lines).
    """
    K = np.stack([cams[v]["K"] for v in VIEWS])
    T_wc = np.stack([cams[v]["T_world_cam"][:T] for v in VIEWS], axis=1)  # (T, V, 4, 4)
    P = projection_matrices(K, T_wc)
    kp = np.stack([kps[v][:T] for v in VIEWS], axis=1)  # (T, V, 17, 3)
    # The keypoint passes (label tracking, swaps undone, guessed runs dropped: motion.passes).
    ev, reports = run_passes("keypoints", Evidence(kp, np.zeros((T, len(VIEWS), len(COCO17_SWAP_GROUPS)), dtype=bool)),
                             PassContext(cfg, VIEWS, K, T_wc, P=P, label=label))
    kp, swapped = ev.keypoints2d, ev.swapped
    tri = triangulate(P, kp[..., :2], kp[..., 2], cfg.triangulation)
    file = Keypoints3DFile(version=np.int64(KEYPOINTS3D_VERSION), points=tri.points, conf=tri.conf,
                           reproj_err_px=tri.reproj_err_px, filled=tri.filled, views=np.array(VIEWS), keypoints2d=kp,
                           swapped=swapped, swap_groups=np.array(list(COCO17_SWAP_GROUPS)))
    seen = np.isfinite(tri.points[..., 0])
    figures = {
        "triangulated_fraction": round(float(seen.mean()), 4),
        "filled_fraction": round(float(tri.filled.mean()), 4),
        "long_gaps": len(tri.long_gaps),
        "keypoints_dropped_temporal": report_of(reports, "temporal").get("keypoints_dropped", 0),
        "limb_labels_tracked": _labels_tracked(reports, VIEWS),
        "triangulation_reproj_px_median": _nanmedian(tri.reproj_err_px),
        **{f"{v}_swaps_undone": {g: int(swapped[:, i, k].sum()) for k, g in enumerate(COCO17_SWAP_GROUPS)}
           for i, v in enumerate(VIEWS)},
        "keypoint_passes": reports,
    }
    if tri.long_gaps:
        worst = max(tri.long_gaps, key=lambda g: g[2] - g[1])
        log.warning("%s: %d gaps in the 3D keypoints are too long to fill (the longest: joint %d, frames %d-%d); "
                    "the fit relies on the 2D keypoints and smoothness there", label, len(tri.long_gaps), *worst)
    return Triangulated(file, figures, list(tri.long_gaps))


def lift_view(cfg: MotionConfig, cams: Mapping[str, Mapping], kps: Mapping[str, NDArray], T: int,
              depth_at, rgb_size: tuple[int, int], label: str = "") -> Triangulated:
    """A one-phone sequence's 3D keypoints: its view's 2D keypoints (limb labels tracked, guessed
    runs dropped, as before a triangulation) lifted into the world with the view's person depth
    (:mod:`embodmocap.motion.lift`); the file has the triangulation's layout with ``one_view`` true.

    Args:
        cams: the one view -> mapping with ``K`` (3, 3) and ``T_world_cam`` (>= T, 4, 4);
        kps: the view -> (>= T, 17, 3) keypoints; T: frames;
        depth_at: frame -> (h, w) the view's depth in metres on the person only (0 elsewhere,
            :func:`embodmocap.motion.lift.person_depth`); rgb_size: (width, height) of its images.
    """
    from embodmocap.motion.lift import lift_figures, lift_keypoints, reprojection_px

    (v,) = cams
    kp = np.asarray(kps[v][:T], dtype=np.float64)[:, None]  # (T, 1, 17, 3)
    K, T_wc = np.asarray(cams[v]["K"]), np.asarray(cams[v]["T_world_cam"])[:T]
    # The same keypoint passes as before a triangulation (the swap check needs two views).
    min_conf = cfg.triangulation.min_conf
    # The label tracking judges the side each arm is on with the depth (LabelTrackConfig.depth_side_m):
    # the detections lifted as labelled, before the lower-bound rule (which reads the labels).
    plain = replace(cfg.lift, behind_occluder=False)
    ev, reports = run_passes("keypoints", Evidence(kp, np.zeros((T, 1, len(COCO17_SWAP_GROUPS)), dtype=bool)),
                             PassContext(cfg, (v,), K[None], T_wc[:, None], label=label, lift=lambda k: lift_keypoints(
                                 k, K, T_wc, depth_at, rgb_size, plain, min_conf, 0).points))
    kp = ev.keypoints2d
    lifted = lift_keypoints(kp[:, 0], K, T_wc, depth_at, rgb_size, cfg.lift, min_conf, cfg.triangulation.max_gap_frames)
    file = Keypoints3DFile(version=np.int64(KEYPOINTS3D_VERSION), points=lifted.points, conf=lifted.conf,
                           reproj_err_px=reprojection_px(lifted.points, K, T_wc, kp[:, 0]), filled=lifted.filled,
                           views=np.array([v]), keypoints2d=kp, swapped=np.zeros((T, 1, len(COCO17_SWAP_GROUPS)), bool),
                           swap_groups=np.array(list(COCO17_SWAP_GROUPS)), one_view=np.bool_(True))
    figures = {
        "one_view": True,
        "lifted_fraction": round(float(np.isfinite(lifted.points[..., 0]).mean()), 4),
        "filled_fraction": round(float(lifted.filled.mean()), 4),
        "long_gaps": len(lifted.long_gaps),
        "keypoints_dropped_temporal": report_of(reports, "temporal").get("keypoints_dropped", 0),
        "limb_labels_tracked": _labels_tracked(reports, (v,)),
        **lift_figures(lifted, kp[:, 0], min_conf),
        "keypoint_passes": reports,
    }
    log.info("%s: one view: %.0f%% of the 3D keypoints lifted with %s's depth (no triangulation)", label,
             100 * figures["lifted_fraction"], v)
    return Triangulated(file, figures, list(lifted.long_gaps))


@dataclass(frozen=True)
class Fitted:
    """The fit step's results: the world motion (with the frame rate and gender), (T,) frames
    where the body can be placed, the manifest figures."""

    params: object
    valid: NDArray
    figures: dict
    quality: object = None  # FrameQuality (embodmocap.motion.quality): per-frame figures and the suspect flag


def fit_motion(cfg: MotionConfig, model, k3: Keypoints3DFile, cams: Mapping[str, Mapping], kps: Mapping[str, NDArray],
               T: int, fps: float, priors: Mapping, layout: str = "COCO17", gender: str | None = None, *,
               label: str = "", source: object = None, depth: Mapping | None = None,
               floor_z: float | None = None) -> Fitted:
    """The world SMPLify on the 3D and both views' 2D keypoints.

    Args:
        model: the body model; k3: the triangulation (:func:`triangulate_views`' file);
        cams, kps: as for :func:`triangulate_views`; fps: the sequence frame rate;
        priors: view -> (camera-space body prior with one row per frame 0..T-1, (T,) bool has-estimate)
            (:func:`embodmocap.io.body_prior.body_priors_by_frame`; empty: start from the keypoints);
        layout: the detector's keypoint layout; gender: the session's (None: neutral);
        label: the sequence (messages); source: what an error names (``keypoints3d.npz``);
        depth: view -> ``(depth_mm, (width, height))``, the view's depth stack ((T', h, w) uint16
            millimetres, Stage II's ``depth.npy``) for the quality's free-space test (None or a view
            left out: not tested there); a third item, the view's packed person masks (Stage II's
            ``masks.npy``, None: none), for the seen-surface test.
        floor_z: Stage I's floor height (:func:`embodmocap.motion.floor.scene_floor_z`; None: no
            floor term).

    Raises:
        InputError: too few triangulated joints, or no starting body without a prior.
    """
    if cfg.kp3d_conf not in ("mean", "min"):
        raise ValueError(f"MotionConfig.kp3d_conf must be 'mean' or 'min', got {cfg.kp3d_conf!r}")
    names = [v for v in VIEWS if v in cams]  # two views, or one (its 3D points lifted with depth)
    valid = placeable_frames(source, label, k3["points"], k3["conf"], cfg)
    # The 2D keypoints as the triangulation step left them (left/right swaps undone).
    kp2d = k3["keypoints2d"] if "keypoints2d" in k3.files else np.stack([kps[v][:T] for v in names], axis=1)
    views = [ViewObservations(K=cams[v]["K"], T_world_cam=cams[v]["T_world_cam"][:T], keypoints=kp2d[:, i], name=v)
             for i, v in enumerate(names)]
    filled = k3["filled"] if "filled" in k3.files else None
    K, T_wc = np.stack([cams[v]["K"] for v in names]), np.stack([cams[v]["T_world_cam"][:T] for v in names], axis=1)
    used = {"kp2d": kp2d, "k3": k3}  # what the fit uses (a start pass may re-label: leg_sides)
    ctx = PassContext(cfg, tuple(names), K, T_wc, label=label, source=source, model=model, layout=layout, fps=fps,
                      gender=gender, priors=priors, cameras=cams, depth=depth,
                      quality_of=lambda p: fit_quality(cfg, model, p, layout, cams, kps, used["kp2d"], used["k3"], T,
                                                       depth))
    # The start passes (confidences, bone-length gate, keypoint and prior starts, limbs carried,
    # unplaceable frames turned: motion.passes), then the fit from their start.
    ev = Evidence(kp2d, k3["swapped"] if "swapped" in k3.files else None, k3["points"], k3["conf"], filled, valid)
    ev, reports = run_passes("start", ev, ctx)
    start, points, conf3 = ev.start, ev.points, ev.conf
    if ev.keypoints2d is not kp2d:  # labels changed at the start: the fit and its quality see them
        used.update(kp2d=ev.keypoints2d, k3=replace(k3, keypoints2d=ev.keypoints2d, points=ev.points, filled=ev.filled))
        views = [replace(o, keypoints=ev.keypoints2d[:, i]) for i, o in enumerate(views)]
    if start.prior_view:
        log.info("%s: initialised from the %s body prior (%.0f%% of frames; %d frames from the keypoints)", label,
                 start.prior_view, 100 * priors[start.prior_view][1].mean(),
                 report_of(reports, "prefer_keypoints").get("frames_from_keypoints", 0))
    init = with_fps(start.init, fps, gender)
    res = fit_world_smpl(model, points, conf3, views, init, start.prior_pose, cfg.smplify, layout=layout,
                         prior_weight=start.prior_weight, valid=valid, floor_z=floor_z)
    # The per-frame quality figures and the suspect flag; with QualityConfig.repair_frames, limbs the
    # views contradict at the edges of placeable runs first take the first fine frame's pose.
    t_quality = time.perf_counter()
    fitted, after = run_passes("fitted", replace(ev, params=res.params, quality=ctx.quality_of(res.params)), ctx)
    params, quality, reports = fitted.params, fitted.quality, reports + after
    t_quality = time.perf_counter() - t_quality
    v_best = start.prior_view
    figures = {
        "init": f"body prior {v_best}" if v_best else "keypoints",
        "init_frames_from_keypoints": report_of(reports, "prefer_keypoints").get("frames_from_keypoints", 0)
        if v_best else int(T),
        "prior_limbs_from_keypoints": report_of(reports, "prior_limbs").get("limbs_from_keypoints", 0),
        "keypoint_layout": layout,
        "points_dropped_bone_length": report_of(reports, "bone_gate").get("points_dropped", 0),
        "limb_starts_propagated": report_of(reports, "propagate").get("limb_starts", 0),
        "unplaced_frames_turned": report_of(reports, "turn_unplaced").get("frames_turned", 0),
        "valid_frames": int(valid.sum()), "invalid_frames": int((~valid).sum()),
        "suspect_frames": int((quality.suspect & valid).sum()),
        "edge_limb_frames_carried": report_of(reports, "edge_repair").get("limb_frames_carried", 0),
        "terms_before": res.terms_before, "terms_after": res.terms_after,
        **{f"{v}_reproj_px": round(float(res.reproj_px[v]), 3) for v in names},
        "one_view": len(names) == 1,
        "fit_seconds": {**{k: round(float(x), 2) for k, x in res.phase_seconds.items()},
                        "quality": round(t_quality, 2)},
        "fit_passes": reports,
    }
    if (quality.suspect & valid).any():
        bad = np.flatnonzero(quality.suspect & valid)
        log.warning("%s: %d placeable frames are suspect (a limb %.0f cm or more from every view that sees it, "
                    "the worst %.0f cm at frame %d; or in space a view's depth saw empty; or away from the person "
                    "surface a view measured at a detection): flagged `suspect` in "
                    "smpl_world.npz", label, len(bad), 100 * cfg.quality.suspect_m,
                    100 * np.nanmax(np.nan_to_num(quality.limb_off_m[bad])),
                    int(bad[np.nanargmax(np.nan_to_num(quality.limb_off_m[bad]))]))
    return Fitted(with_fps(params, fps, gender), valid, figures, quality)


def repair_run_edges(cfg: MotionConfig, model, params, valid: NDArray, layout: str, cams: Mapping[str, Mapping],
                     kps: Mapping[str, NDArray], k3: Keypoints3DFile, T: int, quality=None):
    """``params`` with the limbs the views contradict at the edges of placeable runs carried from
    their first fine frame (:func:`embodmocap.motion.edge_repair.repair_edges`; off with
    ``cfg.quality.repair_frames`` 0), and the number of (frame, limb) pairs changed. Inputs as
    :func:`fit_quality` (the 2D keypoints the fit used are ``k3``'s); ``quality``: ``params``'s
    when the caller has it."""
    if cfg.quality.repair_frames <= 0:
        return params, 0
    names = [v for v in VIEWS if v in cams]
    kp2d = k3["keypoints2d"] if "keypoints2d" in k3.files else np.stack([kps[v][:T] for v in names], axis=1)
    return carry_edge_limbs(cfg, params, valid, lambda p: fit_quality(cfg, model, p, layout, cams, kps, kp2d, k3, T),
                            quality)


def fit_quality(cfg: MotionConfig, model, params, layout: str, cams: Mapping[str, Mapping], kps: Mapping[str, NDArray],
                kp2d: NDArray, k3: Keypoints3DFile, T: int, depth: Mapping | None = None):
    """The per-frame quality of fitted ``params`` (:func:`embodmocap.motion.quality.frame_quality`):
    against the 2D keypoints the fit used (``kp2d`` (T, V, 17, 3)), the detector's (``kps``), the
    triangulation ``k3``, with the cameras ``cams`` (all on view 1's instants), and the views'
    ``depth`` (as :func:`fit_motion`; the free-space test, off with ``cfg.quality.free_space_m`` 0;
    the seen-surface test with the views' person masks, off with ``cfg.quality.surface_m`` 0).

    The body's mesh and the depth tests are figures of each frame alone: they are computed in
    pieces of frames (:func:`frame_pieces`, fixed by ``T`` alone) on as many threads as the fit may
    use cores (:func:`quality_threads`; torch, NumPy and SciPy's k-d tree release the GIL), and the
    answer does not depend on that number."""
    from embodmocap.motion.quality import frame_quality

    filled = k3["filled"] if "filled" in k3.files else None
    names = [v for v in VIEWS if v in cams]  # two views, or one (a one-phone sequence)
    K, T_world_cam = np.stack([cams[v]["K"] for v in names]), np.stack([cams[v]["T_world_cam"][:T] for v in names], axis=1)
    raw = np.stack([kps[v][:T] for v in names], axis=1)
    kp2d = np.asarray(kp2d)[:T]
    pieces = frame_pieces(T)
    parts = map_threads(lambda s: _frame_figures(cfg, model, params, layout, names, K, T_world_cam, kp2d, raw, depth, s),
                        pieces, quality_threads(cfg))
    fitted, free, surface, front = (None if parts[0][i] is None else np.concatenate([p[i] for p in parts])
                                    for i in range(4))
    return frame_quality(fitted, K, T_world_cam, kp2d, raw, k3["points"], filled, tuple(names), cfg.quality, free,
                         surface, front)


#: Frames a piece of :func:`fit_quality`'s per-frame work takes (its pieces start at multiples of
#: it: a batch cut there gives the same bits as the whole, SIMD lanes and BLAS tiles included).
QUALITY_PIECE_FRAMES = 128


def frame_pieces(T: int, frames: int = QUALITY_PIECE_FRAMES) -> list[slice]:
    """Contiguous slices covering ``range(T)``, each ``frames`` long but the last (one for T = 0)."""
    return [slice(a, min(a + frames, T)) for a in range(0, max(T, 1), frames)]


def quality_threads(cfg: MotionConfig) -> int:
    """Threads :func:`fit_quality` runs its pieces on: the cores the fit's windows may use
    (``smplify.workers``, or the cores ``embodmocap run`` lent the stage), at most the usable ones."""
    from embodmocap.parallel import cores_to_use

    return cores_to_use(cfg.smplify.workers)


def map_threads(fn, items: Sequence, threads: int) -> list:
    """``[fn(x) for x in items]`` on up to ``threads`` threads (in order; here alone for 1), each
    with one torch thread: the pieces are the parallelism (torch's own pool would spin beside them).
    Only for work whose bits do not depend on the thread that does it (no shared state)."""
    import torch

    from embodmocap.parallel import map_in_threads

    if min(int(threads), len(items)) <= 1:
        return [fn(x) for x in items]
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return map_in_threads(fn, items, threads)
    finally:
        torch.set_num_threads(before)


def _frame_figures(cfg: MotionConfig, model, params, layout: str, names: list[str], K: NDArray, T_world_cam: NDArray,
                   kp2d: NDArray, raw: NDArray, depth: Mapping | None, s: slice):
    """:func:`fit_quality`'s figures of frames ``s`` alone: the fitted keypoints (t, 17, 3) and the
    free-space, seen-surface and in-front figures (None: the test is off)."""
    import torch

    from embodmocap.body.joints import smpl_to_coco17

    with torch.no_grad():
        out = model.from_params(replace(params, global_orient=params.global_orient[s], body_pose=params.body_pose[s],
                                        transl=params.transl[s]), dtype=torch.float64)
        fitted = smpl_to_coco17(out.joints, out.vertices, model.vertex_ids, layout).numpy()
    Tw = T_world_cam[s]
    # each view's depth stack and masks from frame s.start on (frames past their ends are not judged)
    got = [(depth or {}).get(v) for v in names]
    sizes = [g[1] if g else (0, 0) for g in got]
    stacks = [g[0][s] if g else None for g in got]
    masks = [g[2][s] if g and len(g) > 2 and g[2] is not None else None for g in got]
    free = surface = front = None
    if depth and cfg.quality.free_space_m > 0:
        from embodmocap.motion.free_space import free_space_limbs

        free = free_space_limbs(out.vertices.numpy(), model.lbs_weights, K, Tw, sizes, stacks,
                                cfg.quality.free_space_m, cfg.quality.free_space_window_px)
    if depth and (cfg.quality.surface_m > 0 or cfg.quality.front_m > 0):
        from embodmocap.motion.seen_surface import joint_in_front, unexplained_surface

        if cfg.quality.surface_m > 0:
            surface = unexplained_surface(out.vertices.numpy(), K, Tw, sizes, stacks, masks, raw[s],
                                          cfg.quality.surface_conf, cfg.quality.surface_window_px,
                                          cfg.quality.surface_quantile)
        if cfg.quality.front_m > 0:
            front = joint_in_front(fitted, K, Tw, sizes, stacks, masks, kp2d[s], raw[s], cfg.quality.front_conf,
                                   cfg.quality.front_window_px)
    return fitted, free, surface, front


@dataclass(frozen=True)
class Aligned:
    """The align step's results: the final motion, its frames and valid flags, the joints of the
    final body, view -> final cameras, the manifest figures."""

    params: object
    frames: NDArray
    valid: NDArray
    joints: WorldJointsFile
    cameras_final: dict[str, CameraFile]
    figures: dict


def align_motion(cfg: MotionConfig, model, params, frames: NDArray, valid: NDArray,
                 contacts: Sequence[tuple[int, NDArray]], cams: Mapping[str, Mapping], *, label: str = "",
                 source: object = None) -> Aligned:
    """With contact markers, the yaw + translation that puts the feet on them, applied to the body
    (pelvis-consistent) and the cameras (refused, with the residual, when the markers disagree);
    then the final body's joints.

    Args:
        params, frames, valid: the fitted motion (:func:`fit_motion`); contacts: (sequence frame,
            (3,) world point) per marker (empty: no alignment); cams: view -> its ``cameras_world``
            (each view's own frames); label: the sequence; source: what an error names (the manifest).
    """
    # Every contact figure is written on every run: the stage manifest merges figures, and a
    # stale message from an earlier run must not survive.
    T_align = np.eye(4)
    figures = {"contact_alignment": "none (no contacts)", "contact_residuals_before_m": [],
               "contact_residuals_after_m": [], "contact_message": ""}
    if contacts:
        bad = [f for f, _ in contacts if not 0 <= f < len(params)]
        if bad:
            raise InputError(source, f"sequence {label}: contact frames {bad} outside 0..{len(params) - 1}",
                             "give contact frames in sequence frames (after sync and slicing)")
        al = align_to_contacts(model, params, contacts, cfg.contact)
        figures.update({"contact_residuals_before_m": [round(float(r), 4) for r in al.residuals_before_m],
                        "contact_residuals_after_m": [round(float(r), 4) for r in al.residuals_after_m],
                        "contact_alignment": "refused" if al.refused else "applied"})
        if al.refused:
            log.warning("%s: contact alignment refused: %s", label, al.message)
            figures["contact_message"] = al.message
        else:
            T_align = al.T
            params = apply_alignment(model, params, T_align)
    joints24, coco17 = body_keypoints(model, params)
    joints = WorldJointsFile(version=np.int64(1), joints=joints24, coco17=coco17, frames=frames)
    final = {v: CameraFile(version=np.int64(1), K=cams[v]["K"], width=cams[v]["width"], height=cams[v]["height"],
                           T_world_cam=apply_alignment_to_cameras(cams[v]["T_world_cam"], T_align),
                           raw_frames=cams[v]["raw_frames"]) for v in VIEWS if v in cams}
    figures["T_align"] = T_align.tolist()
    return Aligned(params, frames, valid, joints, final, figures)


@dataclass(frozen=True)
class MotionInputs:
    """Everything Stage IV reads, in memory.

    Attributes:
        sequence: the name (messages).
        model: the body model.
        cameras: view -> ``cameras_world`` (each view's own frames).
        keypoints: view -> (T, 17, 3) the Stage II keypoints.
        fps: the sequence frame rate.
        synced_cameras, synced_keypoints: the same on view 1's instants (the sub-frame sync,
            :func:`embodmocap.sequence.subframe.synced_views`); None: the views' own.
        priors: view -> (body prior per frame, (T,) has-estimate); empty: no prior.
        layout: the detector's keypoint layout; gender: the session's.
        contacts: (sequence frame, (3,) world point) per contact marker.
        floor_z: Stage I's floor height, world metres (None: no floor term).
        lift_depth: one-phone sequences: ``(depth_at, rgb_size)`` of the view, what
            :func:`lift_view` reads (:func:`embodmocap.motion.stage.view_depth`).
    """

    sequence: str
    model: object
    cameras: dict[str, CameraFile]
    keypoints: dict[str, NDArray]
    fps: float
    synced_cameras: dict | None = None
    synced_keypoints: dict | None = None
    priors: dict = field(default_factory=dict)
    layout: str = "COCO17"
    gender: str | None = None
    contacts: list = field(default_factory=list)
    lift_depth: tuple | None = None
    floor_z: float | None = None


@dataclass(frozen=True)
class MotionResult:
    """What Stage IV decides for one sequence (the content of its files)."""

    keypoints3d: Keypoints3DFile
    fit: Fitted
    final: Aligned


def solve(cfg: MotionConfig, inputs: MotionInputs) -> MotionResult:
    """Stage IV in memory: the same steps, in the same order, as :func:`embodmocap.motion.stage.run`."""
    cams = inputs.synced_cameras if inputs.synced_cameras is not None else inputs.cameras
    kps = inputs.synced_keypoints if inputs.synced_keypoints is not None else inputs.keypoints
    T = min(len(kps[v]) for v in kps)
    if len(kps) == 1:  # one phone: lifted with its depth
        if inputs.lift_depth is None:
            raise ValueError("a one-view MotionInputs needs lift_depth (the view's depth reader and image size)")
        tri = lift_view(cfg, cams, kps, T, *inputs.lift_depth, label=inputs.sequence)
    else:
        tri = triangulate_views(cfg, cams, kps, T, inputs.sequence)
    priors = inputs.priors if cfg.use_body_prior else {}
    fit = fit_motion(cfg, inputs.model, tri.file, cams, kps, T, inputs.fps, priors, inputs.layout, inputs.gender,
                     label=inputs.sequence, floor_z=inputs.floor_z)
    contacts = list(inputs.contacts) if cfg.align_contacts else []
    final = align_motion(cfg, inputs.model, fit.params, np.arange(len(fit.params), dtype=np.int64), fit.valid,
                         contacts, inputs.cameras, label=inputs.sequence)
    return MotionResult(tri.file, fit, final)


def placeable_frames(path, seq: str, points: NDArray, conf: NDArray, cfg: MotionConfig) -> NDArray[np.bool_]:
    """(T,) frames where the body can be placed (see :attr:`MotionConfig.min_valid_joints`);
    ``path`` is what the error names (``keypoints3d.npz``).

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


def _labels_tracked(reports: list[dict], names) -> dict:
    """The ``label_track`` pass's counts per view and group (0 where it did not run)."""
    got = report_of(reports, "label_track").get("labels_tracked", {})
    return {f"{v}_{g}": got.get(f"{v}_{g}", 0) for v in names for g in TRACKED_GROUPS}


def _nanmedian(a: NDArray) -> float | None:
    a = np.asarray(a, dtype=np.float64)
    return round(float(np.nanmedian(a)), 3) if np.isfinite(a).any() else None
