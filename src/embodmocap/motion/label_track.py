"""Left/right labels of each view's limbs tracked through time (before the two views are compared).

A detector that confuses the sides of a limb pair (the left knee labelled right and the right one
left) does so for runs of frames, and with two views the geometry cannot say which view is wrong
(swapping either makes them agree) and often sees nothing at all (a confusion along the epipolar
line leaves no reprojection error). Measured on ten hard studio sessions after the geometric swap
check (:mod:`embodmocap.motion.swaps`), 20-90 frames per session still had an arm or leg pair
the wrong way round in one view: a leg pair from frame 0 to 21, an arm pair for 27 frames, each
putting the triangulated limb 0.2-0.9 m off.

Each view's own trajectories tell: where the labels flip, both points of a pair jump to where the
other one was a frame before. So per view and group (arms, legs) a two-state chain (labels as
given / exchanged) over the frames is solved exactly (Viterbi): a transition between two frames
costs the torso-relative distance the pair's points move under the two frames' states (each point
capped, so one outlier cannot decide), and every frame in the exchanged state costs
``flip_cost`` (the detector is right most of the time, so the labels change only where the
trajectories insist). Positions are relative to the view's torso centre and in torso lengths, so
the person's walking and the handheld camera's motion do not count as movement. Frames where the
two points of a pair are never seen together carry no evidence and keep the state of their
neighbours.

One view (a one-phone sequence) has no second view to agree with, and its trajectories cannot say
which side of a jump had the labels right; its depth can: the arms' points lifted with it lie
nearer the shoulder of their own side (``depth_side_m``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray

#: COCO-17 limb groups whose left/right labels are tracked (pairs exchanged together).
TRACKED_GROUPS: dict[str, tuple[tuple[int, int], ...]] = {
    "arms": ((7, 8), (9, 10)),
    "legs": ((13, 14), (15, 16)),
}


@dataclass(frozen=True)
class LabelTrackConfig:
    """How each view's left/right limb labels are tracked through time."""

    enabled: bool = True
    """Track the labels (False: keep the detector's)."""
    min_conf: float = 0.3
    """Points below this confidence are not evidence (the triangulation's threshold)."""
    flip_cost: float = 0.01
    """Cost of a frame in the exchanged state, torso lengths. A run of labels is exchanged when
    the jumps at its two ends (and the views' disagreement inside it) shrink by more than this
    times its length: a pair 0.3 torso lengths apart gains ~1.2 at the two ends, so a confusion
    of up to ~100 frames is undone, while the detector's labels stand wherever the trajectories do
    not insist. Measured on ten hard studio sessions (issue 11, third pass; the tracking alone,
    before ``switch_cost`` existed): (frame, view, group) limb pairs still the wrong way round 465
    with the geometric check alone -> 228 (0.05), 215 (0.03), 58 (0.015), 44 (0.008); with the
    defaults 37 (47 after the geometric check that follows in Stage IV)."""
    cap: float = 0.6
    """Each point's movement between two frames counts at most this much, torso lengths."""
    switch_cost: float = 0.15
    """Cost of a view's labels changing state between two frames its trajectories compare, torso
    lengths: where the two points of a pair overlap in the image (arms crossing in front of the
    body, legs passing), the detector's jitter alone can make exchanging them look a little
    better; a real confusion gains about twice the pair's separation at each end."""
    max_gap: int = 4
    """Frames more than this apart (no pair seen in between) are not compared. Across a longer
    gap the limb moves too far for its position to tell its side, and a confusion at the
    sequence's start (no past to undo it) was carried over the gap into correct labels: on the
    hard studio seed 0, view 2's arms were swapped in frames 0-3, unseen in 5-13, and the chain
    exchanged the correct labels of frames 14-22 to match (10 frames apart), putting the
    triangulated left wrist 10-22 cm off and W-MPJPE of the chunks starting there at 100-168 mm
    (issue 29). 10 -> 4: that session's worst chunk start 167.5 -> 76.1 mm, W-MPJPE 29.2 -> 28.1,
    PA 17.5 -> 16.8; four other hard sessions unchanged (BENCHMARKS.md, session 7)."""
    geometry_px: float = 100.0
    """With two views: a frame's mean reprojection error of the group (pixels) that costs as much
    as one torso length of movement (two views labelled differently do not meet)."""
    cap_px: float = 60.0
    """Each point's reprojection error counts at most this much, pixels."""
    geometry_switch: float = 0.3
    """With two views: cost of a view changing state at a frame where only the views' agreement
    (not its own trajectories) speaks."""
    anatomy_m: float = 0.0
    """With two views, legs only: a frame whose two views' leg labels, triangulated, put the knees
    this many metres nearer the other side's hip than their own
    (:func:`embodmocap.motion.swaps.limb_side_score`) costs as much as one torso length of
    movement (at most ``anatomy_cap_m``). Where one view sees the legs overlapping (from the side)
    and the other has them exchanged from the first frame to where they cross, neither view's
    trajectories nor the views' agreement say which view is wrong, and exchanging the right
    view's labels can cost least (issue 29, indoor seed 4: view 1's correct legs exchanged in
    frames 0-10, view 2's wrong ones kept, the fitted left foot 30-34 cm off). 0 = off, the
    default: on six hard studio sessions (2026-12-04, benchmarks/history/2026-12-04-s8-edges2.md)
    0.3 took that seed's W-MPJPE c100 from 103.1 to 64.7 mm (first five frames 84.8 -> 40.7 mm,
    WA 28.9 -> 23.8 mm) but outdoor seed 1's from 28.3 to 42.1 mm (its frames 33-36 1-2 mm
    worse, which the two-frame alignment magnifies); with the arms judged too, outdoor seed 5
    went from 108.7 to 454.6 mm."""
    partial_torso: bool = False
    """Off by default (session 10): with it on, hard outdoor studio seed 3 (its sub-frame sync from
    the new geometric estimate) had its legs exchanged over frames 33-48 and W-MPJPE c100 246 mm
    instead of 37 (session 11: every frame after a view's last whole torso was centred, see
    ``partial_frames``); on seed 1 it halves the first five frames' error. When on: a frame before the view's first whole torso (or after its last) that sees part of it (both
    shoulders or both hips) is centred on them (with the offset to the whole torso's centre of the nearest frame
    that sees it all) instead of on the neighbours' centre: the trajectories of a person
    entering the view are measured against where their torso is
    (:func:`embodmocap.motion.temporal._partial_centres`). False: the centre interpolated, or held
    from the first whole torso."""
    free_after_gap: tuple[str, ...] = ("legs",)
    """Groups (``"legs"``, ``"arms"``) whose labels, with two views, may go back from exchanged to
    as given at no cost at the frame just before a view's own trajectory comparisons resume after
    more than ``max_gap`` frames without any: nothing compares the frames on either side, so a
    carried exchange is a guess (the detector is right most of the time; going the other way, to
    exchanged, still costs a switch). Empty: the state is carried across. Session 11 (random-phase
    studio sessions), hard outdoor seed 7: view 2's legs exchanged by the detector in frames
    154-158 and 163 (the chain undid them), one leg hidden in 159-164 (158 -> 165: 7 frames without
    a pair to compare), and the exchange carried into the right labels of 165-179 (the sequence's
    end: 15 frames of ``flip_cost`` cost less than the 0.3 of a switch, the views' agreement a
    tie), the fitted feet 15-30 cm off; with the legs freed W-MPJPE c100 33.0 -> 28.8, WA 23.7 ->
    20.4 mm; seeds 0-6 and 9 unchanged but seed 4 (its leg_sides pass relabels six more frames:
    W c100 68.4 -> 68.3 in memory, 67.9 -> 68.1 in the stored output, WA +0.1 mm). Freeing both directions broke indoor seed 6 (view 1's legs, right in frames 47-48
    after a whole-body miss, taken as exchanged: WA 28.2 -> 31.3 mm); freeing the arms too, seed
    4's WA 24.1 -> 25.8 mm; freeing every frame of a gap, outdoor seed 5's W c100 41.9 -> 337 mm."""
    partial_frames: int | None = 8
    """With ``partial_torso``: only frames at most this many frames before the view's first whole
    torso (after its last) are centred on the part they see; None: every such frame (session 10's
    rule). Session 11 (random-phase studio sessions): hard outdoor seed 3's view 2 sees the whole
    torso in frames 1-19 only, and every later frame centred on frame 19's offset exchanged its
    correct arms in frames 1-8 (W-MPJPE c100 32.1 -> 242.6 mm); with 8 (or 4) that seed is
    unchanged by ``partial_torso``, whose effect on seed 1 (the person entering view 1 seven frames
    before its first whole torso) stays: first five frames 28.3 -> 23.3 mm, WA 21.01 -> 20.88 mm,
    but W-MPJPE c100 28.0 -> 29.8 mm (its anchor frames' right arm); so ``partial_torso`` stays off."""
    anatomy_cap_m: float = 0.2
    """The most a frame's wrong-side vote counts, metres (one wild triangulated point must not
    decide)."""
    fresh_start: bool = True
    """With two views: a view's labels choose their state freely at its first evidence in the
    sequence (its trajectories or the two views' agreement): there is no earlier state to change
    from, so no switch is paid there and only ``flip_cost`` and the evidence decide (one view, a
    one-phone sequence: not applied, not measured there). False: the detector's
    labels are the state before the first evidence and leaving them costs ``geometry_switch`` or
    ``switch_cost``. Only the sequence's start: after a gap inside the sequence the state is still
    carried (hard outdoor seed 3, view 2's arms: the state carried across frames 20-31 is the
    right one; freed there, frames 0-31 all took the wrong one). Measured on the hard outdoor
    studio seed 5 (issue 29): view 2 has the arms exchanged in frames 32-35, the first frames in
    which anyone sees the person; its elbows overlap, so its own trajectories cannot tell, and the
    views' agreement (1-3 px better exchanged) did not pay the 0.3 of a switch: the triangulated
    elbows were 19-24 cm off at the first placeable frames (33, 34: W-MPJPE's anchors), the fit's
    left elbow 9 cm, W-MPJPE c100 107.2 -> 59.3 mm with this on. On the ten hard seeds the only
    other change was one frame of view 1's legs at seed 3's start (frame 32, unplaced)."""
    depth_side_m: float = 0.3
    """One view (a one-phone sequence), arms only: its elbows and wrists lifted with the view's
    depth (labels as the state has them) that lie nearer the other side's shoulder than their own
    (:func:`embodmocap.motion.swaps.limb_side_score` with the wrists, summed over the points
    seen) by more than ``depth_side_margin_m`` cost the frame that excess over this many metres,
    in torso lengths (at most one a frame). One view's trajectories cannot say which side of a
    jump had the labels right: on the hard studio seed 3 (one phone) the detector had the arms
    exchanged in frames 0-6 and right from frame 7; the chain kept 0-6 and exchanged 7-21 (the
    longer run at ``flip_cost``), the lifted right wrist on the left one, 45 cm behind its
    shoulder, and the fitted arms 30-40 cm off. The depth tells: over the ten hard studio seeds'
    20 views (each lifted on its own) the summed vote was below -0.1 m in 204 of 222 frames with
    the arms exchanged and in 10 of 1394 with them right (single frames). On: seed 3's one phone
    W-MPJPE c100 145.3 -> 96.5 mm (two phones 59.7), WA 29.7 -> 22.3, PA 28.2 -> 20.1 mm; seed 4
    161.7 -> 157.9 (its arms exchanged in frames 156-176 put right, WA 54.6 -> 49.3); seeds 0, 1
    and 2 unchanged (benchmarks/history/2026-12-06-s13-onephone.md). The legs are not
    judged: the hips are too close (below -0.1 m in 88 of 250 exchanged frames and 37 of 1646
    right ones). 0 = off (one view's labels tracked by its trajectories alone)."""
    depth_side_margin_m: float = 0.1
    """The part of a wrong-side vote (metres) that costs nothing with ``depth_side_m``: a wrist
    reaching across the body, a hidden elbow lifted on what hides it."""


def track_labels(kp: NDArray, cfg: LabelTrackConfig = LabelTrackConfig(),
                 groups: dict[str, tuple[tuple[int, int], ...]] = TRACKED_GROUPS, P: NDArray | None = None,
                 extra: dict[str, NDArray] | None = None, lift: Callable[[NDArray], NDArray] | None = None
                 ) -> tuple[NDArray, NDArray[np.bool_]]:
    """Exchange each view's limb labels where its own trajectories (and, with ``P`` and two
    views, the two views' agreement) say they are the wrong way round.

    Args:
        kp: (T, V, 17, 3) COCO-17 pixels and confidence of every view.
        cfg: settings.
        groups: name -> left/right pairs exchanged together.
        P: (T, V, 3, 4) or (V, 3, 4) projection matrices: with two views the chain runs over both
            views' states at once, and a frame whose two views' labels disagree (their rays do not
            meet, :attr:`LabelTrackConfig.geometry_px`) costs its reprojection error; None = each
            view on its own.
        extra: group name -> (T, 4) more cost of the two views' joint states (with ``P`` and two
            views only; e.g. :func:`embodmocap.motion.leg_sides.side_costs`).
        lift: one view only: (T, 17, 3) the view's keypoints -> (T, 17, 3) world points lifted
            with its depth (NaN: none; :mod:`embodmocap.motion.lift`), for
            :attr:`LabelTrackConfig.depth_side_m` (None: not judged).

    Returns:
        (keypoints (a new array), exchanged (T, V, G) bool per group in ``groups`` order).
    """
    from embodmocap.motion.temporal import _torso_relative

    kp = np.array(kp, dtype=np.float64, copy=True)
    T, V = kp.shape[:2]
    flipped = np.zeros((T, V, len(groups)), dtype=bool)
    if not cfg.enabled or T < 2:
        return kp, flipped
    rels = [_torso_relative(kp[:, v], cfg.min_conf, cfg.partial_torso, cfg.partial_frames) for v in range(V)]
    side = depth_side_costs(lift(kp[:, 0]), groups, cfg) if lift is not None and V == 1 and cfg.depth_side_m > 0 else {}
    for g, pairs in enumerate(groups.values()):
        # Per view: (T-1... key frames) transition costs [prev state, this state] between frames.
        trans = [_transitions(rels[v], kp[:, v, :, 2] >= cfg.min_conf, pairs, cfg) if rels[v] is not None
                 else np.zeros((T, 2, 2)) for v in range(V)]
        if P is not None and V == 2:
            geo, anat = _disagreement(P, kp, pairs, cfg, list(groups)[g])  # (T, 2), (T, 4)
            if extra and list(groups)[g] in extra:
                anat = anat + extra[list(groups)[g]]
            states = _viterbi_pair(trans, geo, cfg, anat, list(groups)[g] in cfg.free_after_gap)
        else:
            states = np.stack([_viterbi(trans[v], cfg, side.get(list(groups)[g])) for v in range(V)], -1)
        for v in range(V):
            st = states[:, v]
            flipped[:, v, g] = st
            for a, b in pairs:
                kp[st, v, a], kp[st, v, b] = kp[st, v, b].copy(), kp[st, v, a].copy()
    return kp, flipped


def _transitions(rel: NDArray, seen: NDArray, pairs, cfg: LabelTrackConfig) -> NDArray:
    """(T, 2, 2) cost of going from frame t-1's state (first index) to frame t's (second): the
    torso-relative distance the pairs' points move from the last frame (within ``max_gap``) where
    that pair was seen to frame t, under the two states. Row 0 is zero. ``rel`` (T, J, 2),
    ``seen`` (T, J). Between a pair's sightings the state is carried (frames with no evidence cost
    nothing, and any change of state in between is paid at the next sighting, see
    :func:`_viterbi`'s carried chain)."""
    T = len(rel)
    ok = np.isfinite(rel).all(-1) & seen
    out = np.zeros((T, 2, 2))
    for a, b in pairs:
        both = np.flatnonzero(ok[:, a] & ok[:, b])
        for t0, t1 in zip(both[:-1], both[1:]):
            if t1 - t0 > cfg.max_gap:
                continue
            same = _d(rel[t1, a], rel[t0, a], cfg.cap) + _d(rel[t1, b], rel[t0, b], cfg.cap)
            cross = _d(rel[t1, a], rel[t0, b], cfg.cap) + _d(rel[t1, b], rel[t0, a], cfg.cap)
            # Paid at t1 against t0's state: with the state carried through t0+1..t1-1 unchanged,
            # the chain's step t1-1 -> t1 sees t0's state as its previous one.
            out[t1] += np.array([[same, cross], [cross, same]])
    return out


def _switch_cost(trans: NDArray, geo_seen: NDArray | None, cfg: LabelTrackConfig) -> NDArray:
    """(T,) cost of a view changing state at frame t: ``switch_cost`` where its own trajectories
    compare frame t with an earlier one (the change is paid for by that evidence), ``geometry_switch``
    where only the two views' agreement speaks, otherwise prohibitive: across frames without
    evidence the state is carried, so the next comparison is made against the right labels."""
    own = np.abs(trans).sum((1, 2)) > 0
    cost = np.where(own, cfg.switch_cost, 1e9)
    if geo_seen is not None:
        cost = np.where(~own & geo_seen, cfg.geometry_switch, cost)
    if cfg.fresh_start and geo_seen is not None:  # two views (measured there; one view: unchanged)
        cost = np.where(_fresh(own | geo_seen), 0.0, cost)
    return cost


def _after_gap(own: NDArray, max_gap: int) -> NDArray[np.bool_]:
    """(T,) the frame just before a view's own comparisons (``own`` (T,) bool) resume, where they
    resume more than ``max_gap`` frames after the last frame that had one: the state carried
    across that stretch is not tied to anything the view's trajectories said
    (:attr:`LabelTrackConfig.free_after_gap`). One frame only: inside the stretch a switch still
    costs what it did, so single frames there do not toggle on the views' agreement alone."""
    t = np.arange(len(own))
    last = np.maximum.accumulate(np.where(own, t, -1))  # last own frame up to t
    nxt = np.concatenate([own[1:], [False]])
    return ~own & nxt & (last >= 0) & (t - last > max_gap)


def _fresh(evidence: NDArray) -> NDArray[np.bool_]:
    """(T,) frames up to and including the first with ``evidence`` (T,) bool: a state chosen
    there changes nothing that was seen (:attr:`LabelTrackConfig.fresh_start`)."""
    first = int(np.argmax(evidence)) if evidence.any() else len(evidence)
    return np.arange(len(evidence)) <= first


def depth_side_costs(points: NDArray, groups: dict[str, tuple[tuple[int, int], ...]],
                     cfg: LabelTrackConfig) -> dict[str, NDArray]:
    """group -> (T, 2) cost of the labels as given (column 0) and exchanged (column 1) from one
    view's keypoints lifted with its depth (``points`` (T, 17, 3), labels as given, NaN: none):
    the arms' wrong-side vote beyond ``depth_side_margin_m`` over ``depth_side_m``, at most one
    (:attr:`LabelTrackConfig.depth_side_m`); zero where no side can be told. Exchanging a group's
    labels flips the sign of its vote (each end takes the other's point)."""
    from embodmocap.motion.swaps import limb_side_score

    out = {}
    if "arms" in groups:
        score = np.nan_to_num(limb_side_score(points, "arms", ends=True))
        cost = np.clip((np.stack([-score, score], -1) - cfg.depth_side_margin_m) / cfg.depth_side_m, 0.0, 1.0)
        out["arms"] = cost
    return out


def _viterbi(trans: NDArray, cfg: LabelTrackConfig, node: NDArray | None = None) -> NDArray[np.bool_]:
    """(T,) best two-state path for one view: ``trans`` (T, 2, 2), ``flip_cost`` per exchanged frame,
    ``node`` (T, 2) more cost of each frame's states (None: none; :func:`depth_side_costs`)."""
    T = len(trans)
    unit = np.array([0.0, cfg.flip_cost]) + (np.zeros((T, 2)) if node is None else node)
    sw = _switch_cost(trans, None, cfg)
    acc = unit[0].copy()
    back = np.zeros((T, 2), dtype=np.int64)
    for t in range(1, T):
        tot = acc[:, None] + trans[t] + sw[t] * (1.0 - np.eye(2))
        back[t] = np.argmin(tot, axis=0)
        acc = tot.min(axis=0) + unit[t]
    s = int(np.argmin(acc))
    out = np.zeros(T, dtype=bool)
    for t in range(T - 1, -1, -1):
        out[t] = bool(s)
        s = back[t, s]
    return out


def _viterbi_pair(trans: list[NDArray], geo: NDArray, cfg: LabelTrackConfig, anat: NDArray | None = None,
                  free_after_gap: bool = False) -> NDArray[np.bool_]:
    """(T, 2) best path over both views' states (four joint states; ``anat`` (T, 4) their
    anatomy costs, :func:`_disagreement`; ``free_after_gap``: the group's exchange may be dropped
    at no cost after a gap, :attr:`LabelTrackConfig.free_after_gap`)."""
    T = len(geo)
    S = [(0, 0), (1, 0), (0, 1), (1, 1)]
    geo_seen = np.abs(geo[:, 0] - geo[:, 1]) > 0
    sw = [_switch_cost(trans[v], geo_seen, cfg) for v in range(2)]
    # Back to the detector's labels at no cost where a view's comparisons resume after a gap
    # (free_after_gap): only that direction, since the detector is right most of the time, a
    # carried "as given" state is the likely one, a carried exchange a guess.
    back_free = [_after_gap(np.abs(trans[v]).sum((1, 2)) > 0, cfg.max_gap) if free_after_gap
                 else np.zeros(T, dtype=bool) for v in range(2)]

    def change(v, t, p, s):
        return 0.0 if p == s or (back_free[v][t] and p == 1 and s == 0) else sw[v][t]

    def node(t):
        a = np.zeros(4) if anat is None else anat[t]
        return np.array([cfg.flip_cost * (s1 + s2) + geo[t, 0 if s1 == s2 else 1] for s1, s2 in S]) + a

    acc = node(0)
    back = np.zeros((T, 4), dtype=np.int64)
    for t in range(1, T):
        tr = np.array([[trans[0][t][p1, s1] + trans[1][t][p2, s2] + change(0, t, p1, s1) + change(1, t, p2, s2)
                        for (s1, s2) in S] for (p1, p2) in S])
        tot = acc[:, None] + tr
        back[t] = np.argmin(tot, axis=0)
        acc = tot.min(axis=0) + node(t)
    k = int(np.argmin(acc))
    out = np.zeros((T, 2), dtype=bool)
    for t in range(T - 1, -1, -1):
        out[t] = S[k]
        k = back[t, k]
    return out


def _disagreement(P: NDArray, kp: NDArray, pairs, cfg: LabelTrackConfig, group: str = "") -> tuple[NDArray, NDArray]:
    """(T, 2) cost of the group's labels as given agreeing between the two views (column 0) and of
    view 2's exchanged (column 1): the mean reprojection error of the group's points (each capped at
    ``cap_px``) over ``geometry_px``; 0 where the group is not triangulated. And (T, 4) the anatomy
    cost of the joint states ``(v1, v2)`` = (0, 0), (1, 0), (0, 1), (1, 1)
    (:attr:`LabelTrackConfig.anatomy_m`; zeros when off or where the sides cannot be told):
    exchanging both views' labels mirrors the triangulated sides, so two triangulations say it
    all."""
    from embodmocap.geometry.triangulation import TriangulationConfig, triangulate
    from embodmocap.motion.swaps import _L_HIP, _R_HIP, limb_side_score

    joints = [j for pair in pairs for j in pair]
    tcfg = TriangulationConfig(min_conf=cfg.min_conf, reject_px=np.inf, max_gap_frames=0, drop_unresolved=False)
    legs = cfg.anatomy_m > 0 and group == "legs"
    # Only the points read here: the group's, and the hips the knees' side is judged from (each
    # point's triangulation is its own: the same bits as triangulating every joint).
    sub = joints + ([j for j in (_L_HIP, _R_HIP) if j not in joints] if legs else [])
    out, side = [], []
    for swap in (False, True):
        trial = kp.copy()
        if swap:
            for a, b in pairs:
                trial[:, 1, [a, b]] = kp[:, 1, [b, a]]
        tri = triangulate(P, trial[:, :, sub, :2], trial[:, :, sub, 2], tcfg)
        err = np.minimum(tri.reproj_err_px[:, list(range(len(joints)))], cfg.cap_px)  # (T, j, V)
        seen = np.isfinite(err)
        out.append(np.where(seen, err, 0.0).sum((1, 2)) / np.maximum(seen.sum((1, 2)), 1))
        if legs:
            points = np.full(kp.shape[:1] + kp.shape[2:3] + (3,), np.nan)
            points[:, sub] = tri.points
            side.append(np.nan_to_num(limb_side_score(points, group)))
    anat = np.zeros((len(kp), 4))
    if side:
        sx, sy = side  # as given, view 2 exchanged; states (1, 1) and (1, 0) mirror them
        score = np.stack([sx, -sy, sy, -sx], -1)
        anat = np.minimum(np.maximum(-score, 0.0), cfg.anatomy_cap_m) / cfg.anatomy_m
    return np.stack(out, -1) / cfg.geometry_px, anat


def _d(x: NDArray, y: NDArray, cap: float) -> float:
    return min(float(np.linalg.norm(x - y)), cap)
