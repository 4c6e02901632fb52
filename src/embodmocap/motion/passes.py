"""Stage IV's keypoint checks and initialisation: one declared list of passes, run in order by one loop.

Every pass has the same signature, ``run(ev, ctx) -> (ev, report)``: the evidence so far
(:class:`Evidence`: the views' 2D keypoints and, once triangulated, the 3D keypoints, their
confidences, the placeable frames, the fit's start and, after the fit, the fitted motion) and the
sequence's fixed facts (:class:`PassContext`: config, cameras, body model...) in; the evidence with
what the pass changed, and a small JSON report of what it did, out. The pass modules
(:mod:`~embodmocap.motion.label_track`, :mod:`~embodmocap.motion.swaps`...) keep their own
functions; the passes here only wrap them.

:data:`PASSES` declares them in the order they run, each with its phase (``keypoints``: the views'
2D keypoints before the triangulation, in the ``triangulate`` step; ``start``: the 3D keypoints and
the fit's starting body before the SMPLify, in the ``fit`` step; ``fitted``: the fitted motion,
after it), the setting that switches it (:attr:`Pass.switch`) and when it applies at all (e.g.
with two views, with a body prior). :func:`run_passes` runs one phase and returns the reports that
:mod:`embodmocap.motion.solve` writes into ``motion_manifest.json`` (``keypoint_passes``,
``fit_passes``: which passes ran, in which order, and their figures).

A new pass is a function with this signature (in its own module, or a wrapper here) and one line
in :data:`PASSES`; its switch is a :class:`~embodmocap.motion.config.MotionConfig` field declared
in the step of its phase (:mod:`embodmocap.motion.steps`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Callable, Mapping

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.motion.config import MotionConfig

log = logging.getLogger(__name__)

#: The phases, in the order they run, and the step each belongs to.
PHASES = {"keypoints": "triangulate", "start": "fit", "fitted": "fit"}


@dataclass(frozen=True)
class Start:
    """The fit's starting body and its pull towards a body prior.

    Attributes:
        init: the :class:`~embodmocap.types.SmplParams` the fit starts from.
        kp_init: the keypoint-started params (IK; None where no frame could place the torso).
        prior_view: the view whose body prior started it (None: the keypoints did).
        prior_pose: (T, 69) the pose the fit is pulled towards (None: no pull).
        prior_weight: (T,) that pull's weight per frame (None: 1 everywhere).
    """

    init: object
    kp_init: object = None
    prior_view: str | None = None
    prior_pose: NDArray | None = None
    prior_weight: NDArray | None = None


@dataclass(frozen=True)
class Evidence:
    """What the passes read and hand on (T frames, V views, COCO-17 joints; world metres, pixels).

    Attributes:
        keypoints2d: (T, V, 17, 3) the views' 2D keypoints (u, v, confidence) as the passes left them.
        swapped: (T, V, G) bool: where a left/right group was swapped back (``keypoints3d.npz``'s
            ``swapped``; None: not recorded).
        points: (T, 17, 3) the 3D keypoints (NaN: none); None before the triangulation.
        conf: (T, 17) the confidence the fit gives each 3D keypoint.
        filled: (T, 17) bool: 3D keypoints filled over a gap, not triangulated (None: not recorded).
        valid: (T,) bool: frames where the body can be placed.
        start: the fit's start (None before the ``start`` phase makes it).
        params: the fitted motion (``fitted`` phase); quality: its per-frame quality
            (:class:`~embodmocap.motion.quality.FrameQuality`).
    """

    keypoints2d: NDArray
    swapped: NDArray | None
    points: NDArray | None = None
    conf: NDArray | None = None
    filled: NDArray | None = None
    valid: NDArray | None = None
    start: Start | None = None
    params: object = None
    quality: object = None


@dataclass(frozen=True)
class PassContext:
    """The sequence's fixed facts that passes read (never change).

    Attributes:
        cfg: Stage IV's settings.
        names: the views (``("v1", "v2")``, or one).
        K: (V, 3, 3) intrinsics; T_world_cam: (T, V, 4, 4) the cameras on view 1's instants.
        P: (T, V, 3, 4) projection matrices (None: one view, nothing to triangulate).
        label: the sequence (log lines); source: what an error names (``keypoints3d.npz``).
        model, layout, fps, gender: the body model, the detector's keypoint layout, the frame rate,
            the session's gender (None: neutral); ``fit`` step only.
        priors: view -> (camera-space body prior per frame, (T,) has-estimate); empty: none.
        cameras: view -> mapping with ``T_world_cam`` (the body prior's frames).
        quality_of: fitted params -> their :class:`~embodmocap.motion.quality.FrameQuality`.
        depth: view -> ``(depth_mm, (width, height), masks)``, the views' depth and person masks
            (:func:`embodmocap.motion.stage.quality_depth`; None: not read).
        lift: one view: its (T, 17, 3) keypoints -> (T, 17, 3) world points lifted with its depth
            (:func:`embodmocap.motion.solve.lift_view`; None: no depth, or two views).
    """

    cfg: MotionConfig
    names: tuple[str, ...]
    K: NDArray
    T_world_cam: NDArray
    P: NDArray | None = None
    label: str = ""
    source: object = None
    model: object = None
    layout: str = "COCO17"
    fps: float = 30.0
    gender: str | None = None
    priors: Mapping | None = None
    cameras: Mapping | None = None
    quality_of: Callable | None = None
    depth: Mapping | None = None
    lift: Callable | None = None


@dataclass(frozen=True)
class Pass:
    """One declared pass.

    Attributes:
        name: its name (the manifest's reports).
        phase: ``keypoints``, ``start`` or ``fitted`` (:data:`PHASES`).
        switch: the setting that switches it, as written in the docs (``None``: always on).
        on: cfg -> whether the switch is on.
        applies: (evidence, context) -> whether the sequence gives it anything to work on (a
            one-view sequence has no swap check, a keypoint start no prior to gate...).
        run: the pass itself.
        doc: one line for the documentation.
    """

    name: str
    phase: str
    switch: str | None
    on: Callable[[MotionConfig], bool]
    applies: Callable[[Evidence, PassContext], bool]
    run: Callable[[Evidence, PassContext], tuple[Evidence, dict]]
    doc: str = ""


def run_passes(phase: str, ev: Evidence, ctx: PassContext, passes: tuple[Pass, ...] | None = None
               ) -> tuple[Evidence, list[dict]]:
    """The passes of ``phase`` (declared order) on ``ev``, each where its switch is on and it
    applies; and one report per pass: ``{"pass", "on", "ran", **its figures}``."""
    reports = []
    for p in (PASSES if passes is None else passes):
        if p.phase != phase:
            continue
        on = bool(p.on(ctx.cfg))
        ran = on and bool(p.applies(ev, ctx))
        report: dict = {}
        if ran:
            ev, report = p.run(ev, ctx)
        reports.append({"pass": p.name, "on": on, "ran": ran, **report})
    return ev, reports


def report_of(reports: list[dict], name: str) -> dict:
    """The report of pass ``name`` among ``reports`` ({} when it did not run)."""
    return next((r for r in reports if r["pass"] == name and r["ran"]), {})


# -- keypoints: each view's 2D keypoints, before the triangulation ------------------------------------

def label_track(ev: Evidence, ctx: PassContext) -> tuple[Evidence, dict]:
    """Each view's left/right limb labels tracked through time (:mod:`embodmocap.motion.label_track`)."""
    from embodmocap.motion.label_track import TRACKED_GROUPS, track_labels

    # P None: one view, its trajectories and (with ctx.lift) the side its depth puts each arm on
    kp, tracked = track_labels(ev.keypoints2d, ctx.cfg.label_track, P=ctx.P, lift=ctx.lift)
    return replace(ev, keypoints2d=kp), {"labels_tracked": {
        f"{v}_{g}": int(tracked[:, i, k].sum()) for i, v in enumerate(ctx.names) for k, g in enumerate(TRACKED_GROUPS)}}


def fix_swaps(ev: Evidence, ctx: PassContext) -> tuple[Evidence, dict]:
    """Left/right swaps that the two views' geometry exposes undone (:mod:`embodmocap.motion.swaps`)."""
    from embodmocap.motion.swaps import COCO17_SWAP_GROUPS, fix_swaps as undo

    kp, swapped = undo(ctx.P, ev.keypoints2d, ctx.cfg.triangulation)
    return replace(ev, keypoints2d=kp, swapped=swapped), {"swaps_undone": {
        v: {g: int(swapped[:, i, k].sum()) for k, g in enumerate(COCO17_SWAP_GROUPS)} for i, v in enumerate(ctx.names)}}


def drop_guessed(ev: Evidence, ctx: PassContext) -> tuple[Evidence, dict]:
    """Runs of limb keypoints that jump off their own trajectory and back dropped
    (:mod:`embodmocap.motion.temporal`)."""
    from embodmocap.motion.temporal import drop_guessed_runs

    kp, guessed = drop_guessed_runs(ev.keypoints2d, ctx.cfg.temporal)
    return replace(ev, keypoints2d=kp), {"keypoints_dropped": int(guessed.sum())}


# -- start: the 3D keypoints and the fit's starting body ----------------------------------------------

def leg_sides(ev: Evidence, ctx: PassContext) -> tuple[Evidence, dict]:
    """The two views' leg labels re-tracked with the side of the starting body's pelvis each
    triangulated knee and ankle lies on; the legs re-triangulated where they changed
    (:mod:`embodmocap.motion.leg_sides`)."""
    import torch

    from embodmocap.geometry.triangulation import projection_matrices, triangulate
    from embodmocap.motion.leg_sides import relabel_legs

    # The starting body as the start passes will make it (the prior snapped onto the 3D points, or
    # without a prior the keypoint start): only its hip axis is read, which the leg labels it
    # judges hardly move.
    try:
        if ctx.cfg.use_body_prior and ctx.priors:
            probe, _ = prior_start(replace(ev, start=Start(init=None)), ctx)
        else:
            probe, _ = keypoint_start(ev, ctx)
    except InputError:  # no start at all: the start passes say so themselves
        return ev, {"legs_relabelled": {}}
    if probe.start is None or probe.start.init is None:
        return ev, {"legs_relabelled": {}}
    with torch.no_grad():
        joints = ctx.model.joints_from_params(probe.start.init, dtype=torch.float64).numpy()
    P = projection_matrices(ctx.K, ctx.T_world_cam)
    kp, changed = relabel_legs(ev.keypoints2d, P, joints[:, 1], joints[:, 2], ctx.cfg.label_track, ctx.cfg.leg_sides)
    report = {"legs_relabelled": {v: int(changed[:, i].sum()) for i, v in enumerate(ctx.names)}}
    if not changed.any():
        return ev, report
    tri = triangulate(P, kp[..., :2], kp[..., 2], ctx.cfg.triangulation)
    return replace(ev, keypoints2d=kp, points=tri.points, conf=tri.conf, filled=tri.filled), report


def depth_points(ev: Evidence, ctx: PassContext) -> tuple[Evidence, dict]:
    """Limb joints one view sees and the other does not, placed with the seeing view's depth
    (:mod:`embodmocap.motion.depth_points`)."""
    from embodmocap.motion.depth_points import depth_of_views, place_one_view_joints

    points, conf, filled, placed = place_one_view_joints(
        ev.points, ev.conf, ev.filled, ev.keypoints2d, ctx.K, ctx.T_world_cam, depth_of_views(ctx.depth, ctx.names),
        ctx.cfg.depth_points)
    report = {"joints_placed": int(placed.sum())}
    if not placed.any():
        return ev, report
    return replace(ev, points=points, conf=conf, filled=filled), report


def weakest_view_conf(ev: Evidence, ctx: PassContext) -> tuple[Evidence, dict]:
    """Each 3D keypoint's confidence lowered to its weakest used view's (``kp3d_conf = "min"``),
    and none for a point a view made from a guess (``kp3d_min_view_conf``)."""
    # A point is as trustworthy as its weakest view: with two views, one wrong 2D point moves
    # the triangulated point along the other view's ray without any reprojection error.
    c2 = np.nan_to_num(ev.keypoints2d[..., 2])
    used = c2 >= ctx.cfg.triangulation.min_conf
    weakest = np.where(used, c2, np.inf).min(axis=1)
    conf = ev.conf
    if ctx.cfg.kp3d_conf == "min":
        conf = np.where(np.isfinite(weakest), np.minimum(conf, weakest), conf)
    lowered = int((conf < ev.conf).sum())
    # A view's detection below kp3d_min_view_conf is a guess (a hidden joint placed from context,
    # several times a seen one's jitter): a point triangulated with it has the guess's depth along
    # the other view's ray. It leaves the 3D term (the views' own 2D terms keep it, each at its
    # confidence; depth_points, next, may place the joint with the seeing view's depth, and its
    # placed points keep their weight). One view's points (lifted with its depth) are not
    # triangulated.
    guess = (used.sum(axis=1) >= 2) & (weakest < ctx.cfg.kp3d_min_view_conf) & (conf > 0)
    conf = np.where(guess, 0.0, conf)
    return replace(ev, conf=conf), {"points_lowered": lowered, "points_dropped_guess": int(guess.sum())}


def bone_gate(ev: Evidence, ctx: PassContext) -> tuple[Evidence, dict]:
    """3D keypoints that break the body's bone lengths or torso shape get no weight
    (:mod:`embodmocap.motion.ik`)."""
    from embodmocap.motion.ik import (betas_from_bone_lengths, implausible_points, implausible_torso,
                                      observed_bone_lengths, rest_skeleton, torso_anchors)

    cfg, points, conf3 = ctx.cfg, ev.points, ev.conf
    sk = rest_skeleton(ctx.model, ctx.layout)
    seen = np.isfinite(points).all(-1) & (np.nan_to_num(conf3) >= cfg.smplify.min_conf)
    b_bones = betas_from_bone_lengths(sk, observed_bone_lengths(points, seen))
    # Torso points that break the torso's shape first: the limbs are judged from the torso.
    torso_bad = implausible_torso(sk, b_bones, points, seen, cfg.torso_tol_m)
    seen = seen & ~torso_bad
    # An elbow (knee) whose shoulder (hip) was not triangulated is judged against the
    # shoulder of the torso placed on the other torso points.
    anchors = torso_anchors(sk, b_bones, points, seen) if cfg.bone_anchor_torso else None
    gated = implausible_points(sk, b_bones, points, seen, cfg.bone_tol, anchors) | torso_bad
    return replace(ev, conf=np.where(gated, 0.0, conf3)), {"points_dropped": int(gated.sum()),
                                                           "torso_points_dropped": int(torso_bad.sum())}


def keypoint_start(ev: Evidence, ctx: PassContext) -> tuple[Evidence, dict]:
    """The body placed on the 3D keypoints alone: shape from bone lengths, torso, limb IK
    (:func:`embodmocap.motion.init.init_from_keypoints`)."""
    from embodmocap.motion.init import init_from_keypoints

    cfg = ctx.cfg
    # One view: an unsure end point was lifted from what its pixel shows (maybe what hides it),
    # so a hidden limb is bent to reach only a confident one (MotionConfig.reach_min_conf_one_view).
    reach = cfg.reach_min_conf_one_view if len(ctx.names) == 1 else 0.0
    try:
        kp_init = init_from_keypoints(ctx.model, running_median(ev.points, cfg.init_median_frames), ev.conf, ctx.fps,
                                      ctx.gender or "neutral", cfg.smplify.min_conf, ctx.layout, reach_min_conf=reach)
    except ValueError as err:
        if not (cfg.use_body_prior and ctx.priors):
            raise InputError(ctx.source, f"cannot place a starting body in sequence {ctx.label}: {err}",
                             "both views must see the hips and shoulders in some frames; or give a body prior "
                             "(body_prior in session.toml)") from err
        return replace(ev, start=Start(init=None)), {"placed": False}
    return replace(ev, start=Start(init=kp_init, kp_init=kp_init)), {"placed": True}


def prior_start(ev: Evidence, ctx: PassContext) -> tuple[Evidence, dict]:
    """The view's camera-space body prior moved into the world and snapped onto the 3D keypoints
    (:func:`embodmocap.motion.init.init_from_prior`); its pose is what the fit is pulled towards."""
    from embodmocap.motion.init import init_from_prior, snap_to_keypoints

    v_best = max(ctx.priors, key=lambda v: ctx.priors[v][1].mean())
    prior, has = ctx.priors[v_best]
    T = len(ev.points)
    init = init_from_prior(ctx.model, prior, ctx.cameras[v_best]["T_world_cam"][:T], ctx.fps, ctx.gender or "neutral")
    # The prior's depth can be far off; start where the triangulation says the body is.
    init = snap_to_keypoints(ctx.model, init, ev.points, ev.conf)
    return replace(ev, start=replace(ev.start, init=init, prior_view=v_best, prior_pose=init.body_pose)), {
        "view": v_best, "frames_with_estimate": round(float(has.mean()), 4)}


def prefer_keypoints_pass(ev: Evidence, ctx: PassContext) -> tuple[Evidence, dict]:
    """Frames where the prior-started body is grossly further from the 3D keypoints than the
    keypoint-started one start from the keypoints, with no pull towards the prior
    (:func:`embodmocap.motion.init.prefer_keypoints`)."""
    from embodmocap.motion.init import prefer_keypoints

    s = ev.start
    # Where the prior disagrees with the triangulation (a flipped body, limbs elsewhere),
    # the triangulation wins: start there from the keypoints, and do not pull to the prior.
    init, worse = prefer_keypoints(ctx.model, s.init, s.kp_init, ev.points, ev.conf, ctx.cfg.smplify.min_conf,
                                   ctx.cfg.prior_disagree_m, ctx.layout)
    return (replace(ev, start=replace(s, init=init, prior_weight=(~worse).astype(np.float64))),
            {"frames_from_keypoints": int(worse.sum())})


def prior_limbs(ev: Evidence, ctx: PassContext) -> tuple[Evidence, dict]:
    """Per limb, the prior's pose the 3D keypoints contradict taken from the keypoint start
    (:mod:`embodmocap.motion.prior_limbs`)."""
    from embodmocap.motion.prior_limbs import gate_prior_limbs, limb_columns

    s = ev.start
    # Only triangulated points judge a limb: points filled over a gap are interpolated,
    # and where both ends were wrong they contradict a right prior (studio indoor seed 2).
    measured = ev.points if ev.filled is None else np.where(ev.filled[..., None], np.nan, ev.points)
    prior_pose, limbs_gated = gate_prior_limbs(ctx.model, s.prior_pose, s.init, s.kp_init, measured, ev.conf,
                                               ctx.cfg.smplify.min_conf, ctx.cfg.prior_limb_disagree_m, ctx.layout)
    # The fit starts there too: from the prior's wrong limb it stays in that basin.
    init = replace(s.init, body_pose=np.where(limb_columns(limbs_gated), prior_pose, s.init.body_pose))
    return (replace(ev, start=replace(s, init=init, prior_pose=prior_pose)),
            {"limbs_from_keypoints": int(limbs_gated.sum())})


def propagate(ev: Evidence, ctx: PassContext) -> tuple[Evidence, dict]:
    """Limb starts that both views and the 3D points reject take the pose carried over from the
    frames where the limb fits its evidence (:mod:`embodmocap.motion.propagate`)."""
    from embodmocap.motion.propagate import propagate_limbs
    from embodmocap.motion.smplify import KeypointBody

    sm = ctx.cfg.smplify
    init, carried = propagate_limbs(KeypointBody(ctx.model, layout=ctx.layout), ev.start.init, ev.points, ev.conf,
                                    ctx.K, ctx.T_world_cam, ev.keypoints2d, sm.kp3d_scale_m, sm.reproj_scale_px,
                                    sm.min_conf)
    return replace(ev, start=replace(ev.start, init=init)), {"limb_starts": int(carried.sum())}


def turn_unplaced(ev: Evidence, ctx: PassContext) -> tuple[Evidence, dict]:
    """Unplaceable frames (holding a neighbour's orientation) turned the way the views that see
    them say (:mod:`embodmocap.motion.unplaced`)."""
    from embodmocap.motion.smplify import KeypointBody
    from embodmocap.motion.unplaced import turn_unplaced as turn

    init, angle = turn(KeypointBody(ctx.model, layout=ctx.layout), ev.start.init, ev.valid, ctx.K, ctx.T_world_cam,
                       ev.keypoints2d, ctx.cfg.smplify.reproj_scale_px, ctx.cfg.smplify.min_conf)
    return replace(ev, start=replace(ev.start, init=init)), {"frames_turned": int((angle != 0).sum())}


# -- fitted: the SMPLify's motion ---------------------------------------------------------------------

def edge_repair(ev: Evidence, ctx: PassContext) -> tuple[Evidence, dict]:
    """Limbs the views contradict at the edges of placeable runs carried from their first fine
    frame (:mod:`embodmocap.motion.edge_repair`); the quality recomputed where it changed."""
    params, n = carry_edge_limbs(ctx.cfg, ev.params, ev.valid, ctx.quality_of, ev.quality)
    quality = ctx.quality_of(params) if n else ev.quality
    return replace(ev, params=params, quality=quality), {"limb_frames_carried": n}


def carry_edge_limbs(cfg: MotionConfig, params, valid: NDArray, quality_of: Callable, quality=None):
    """:func:`embodmocap.motion.edge_repair.repair_edges` with Stage IV's settings: ``params``
    with the contradicted limbs at run edges carried, and the number of (frame, limb) pairs changed
    (``quality``: ``params``'s when the caller has it)."""
    from embodmocap.motion.edge_repair import repair_edges

    return repair_edges(params, valid, lambda p: quality_of(p).joint_off_m, cfg.quality.suspect_m,
                        cfg.quality.repair_frames, None if quality is None else quality.joint_off_m)


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


def _always(ev: Evidence, ctx: PassContext) -> bool:
    return True


def _has_prior(ev: Evidence, ctx: PassContext) -> bool:
    return ev.start is not None and ev.start.prior_view is not None and ev.start.kp_init is not None


#: Stage IV's passes in the order they run (one line each; see the module docstring).
PASSES: tuple[Pass, ...] = (
    Pass("label_track", "keypoints", "label_track.enabled", lambda c: c.label_track.enabled, _always, label_track,
         "each view's left/right limb labels tracked through time"),
    Pass("fix_swaps", "keypoints", "fix_swaps", lambda c: c.fix_swaps, lambda ev, ctx: ctx.P is not None, fix_swaps,
         "left/right swaps the two views' geometry exposes undone (two views)"),
    Pass("temporal", "keypoints", "temporal.enabled", lambda c: c.temporal.enabled, _always, drop_guessed,
         "guessed runs of limb keypoints (off their own trajectory and back) dropped"),
    Pass("leg_sides", "start", "leg_sides.side_m", lambda c: c.leg_sides.side_m > 0,
         lambda ev, ctx: len(ctx.names) == 2 and ctx.model is not None, leg_sides,
         "both views' leg labels re-tracked with the starting body's pelvis side (two views)"),
    Pass("weakest_view_conf", "start", "kp3d_conf", lambda c: c.kp3d_conf == "min" or c.kp3d_min_view_conf > 0,
         _always, weakest_view_conf,
         "3D keypoint confidence lowered to the weakest view's (`kp3d_conf = \"min\"`), none where a view guessed "
         "(`kp3d_min_view_conf`)"),
    Pass("depth_points", "start", "depth_points.min_conf", lambda c: c.depth_points.min_conf > 0,
         lambda ev, ctx: len(ctx.names) == 2 and bool(ctx.depth), depth_points,
         "limb joints one view sees placed with its depth (two views, depth and masks read)"),
    Pass("bone_gate", "start", "bone_tol", lambda c: c.bone_tol > 0, _always, bone_gate,
         "3D keypoints breaking the bone lengths or the torso's shape get no weight (`bone_tol` > 0)"),
    Pass("keypoint_start", "start", None, lambda c: True, _always, keypoint_start,
         "the keypoint start: shape from bone lengths, torso, limb IK (always: the fit needs a start)"),
    Pass("prior_start", "start", "use_body_prior", lambda c: c.use_body_prior, lambda ev, ctx: bool(ctx.priors),
         prior_start, "the body prior moved into the world, snapped onto the 3D keypoints (with a prior)"),
    Pass("prefer_keypoints", "start", "prefer_keypoints", lambda c: c.prefer_keypoints, _has_prior,
         prefer_keypoints_pass, "frames where the prior is grossly off start from the keypoints, no pull"),
    Pass("prior_limbs", "start", "prior_limb_disagree_m", lambda c: c.prior_limb_disagree_m > 0, _has_prior,
         prior_limbs, "per limb, the prior's pose the 3D keypoints contradict taken from the keypoints"),
    Pass("propagate", "start", "propagate_limbs", lambda c: c.propagate_limbs, _always, propagate,
         "rejected limb starts carried over from the frames where the limb fits"),
    Pass("turn_unplaced", "start", "turn_unplaced", lambda c: c.turn_unplaced,
         lambda ev, ctx: ev.start.prior_view is None and not ev.valid.all(), turn_unplaced,
         "unplaceable frames turned the way the views say (keypoint starts)"),
    Pass("edge_repair", "fitted", "quality.repair_frames", lambda c: c.quality.repair_frames > 0, _always,
         edge_repair, "after the fit: contradicted limbs at run edges carried from the first fine frame"),
)
