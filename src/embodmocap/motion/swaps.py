"""Left/right swaps of 2D keypoints, found and undone with the other views.

2D pose detectors sometimes label a limb pair the wrong way round in one view (the left elbow and
wrist placed on the right arm, or the whole skeleton mirrored), often for many frames in a row and
with high confidence. Two views then disagree: the rays of a swapped pair do not meet, the pair is
triangulated in the wrong place or dropped, and the fit is pulled.

For every frame, each view's pairs are swapped in turn (all pairs of one group at once: arms,
legs, face) and the frame re-triangulated; a swap is kept when it lowers the frame's reprojection
error by at least half. With two views, swapping either view makes them agree, so the geometry
cannot say which view was wrong; the body decides (:func:`_mislabelled`): shoulders, hips and ears
must lie the right way round for where the nose faces, each elbow (knee) must hang from the
shoulder (hip) of its side. Frames where that cannot be told are left as they are.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.triangulation import TriangulationConfig, triangulate

log = logging.getLogger(__name__)

#: COCO-17 left/right pairs, grouped as detectors confuse them. Order matters: the torso pairs go
#: first, so that the limbs are judged against shoulders and hips already put right.
COCO17_SWAP_GROUPS: dict[str, tuple[tuple[int, int], ...]] = {
    "shoulders": ((5, 6),),
    "hips": ((11, 12),),
    "face": ((1, 2), (3, 4)),
    "arms": ((7, 8), (9, 10)),
    "legs": ((13, 14), (15, 16)),
}
_NOSE, _L_SHOULDER, _R_SHOULDER, _L_ELBOW, _R_ELBOW = 0, 5, 6, 7, 8
_L_HIP, _R_HIP, _L_KNEE, _R_KNEE, _L_EAR, _R_EAR = 11, 12, 13, 14, 3, 4
_L_WRIST, _R_WRIST, _L_ANKLE, _R_ANKLE = 9, 10, 15, 16

@dataclass(frozen=True)
class SwapConfig:
    """How left/right swaps are found."""

    min_error_px: float = 8.0
    """Frames whose mean reprojection error over the group's points (each capped at ``cap_px``)
    is below this are consistent already and left alone."""
    min_gain: float = 0.5
    """A swap is kept when it brings the frame's error below this fraction of the unswapped one."""
    cap_px: float = 60.0
    """Per-point reprojection errors are capped at this before averaging (one wild point must not
    decide)."""
    bone_tol: float = 0.3
    """Arms and legs: a bone (shoulder-elbow, elbow-wrist, hip-knee, knee-ankle) whose triangulated
    length is off the sequence's median by more than this fraction is implausible. With two views a
    swap along the epipolar lines (cameras at one height, a horizontal confusion) leaves no
    reprojection error but puts the limbs at wrong depths: the view whose swap makes every bone
    plausible again (and no reprojection worse by ``bone_max_extra_px``) is swapped back. The
    expected length of each bone is the same on both sides: the length most frames of either side
    share (:func:`embodmocap.motion.ik.symmetric_length`). 0 = off."""
    bone_max_extra_px: float = 5.0
    """Largest increase of the group's reprojection error a bone-length swap may cause, pixels."""
    bone_continuity: bool = True
    """A run of frames that the bone lengths would swap back in one view is left alone where the
    swapped labels continue that view's neighbouring frames worse than its own labels do
    (:func:`_continuity_gain` below 0): the bones say only that one of the two views is wrong,
    and with a side view that sees one arm well and the other weakly, swapping its labels for one
    frame can make every bone plausible (the weak side's points dropped below the triangulation's
    confidence) while its trajectories say the labels were right. Hard indoor studio seed 4
    (issue 29): view 1's arms exchanged at frame 100 alone, the triangulated left wrist 18 cm off
    at W-MPJPE's second chunk anchor. False: every run the bones choose is swapped."""


def _frame_error(P: NDArray, xy: NDArray, conf: NDArray, tcfg: TriangulationConfig, cap: float,
                 joints: list[int], X_rest: NDArray | None = None,
                 frames: NDArray | None = None) -> tuple[NDArray, NDArray]:
    """(T,) mean capped reprojection error over ``joints`` of each frame, and (T, J, 3) the
    triangulated points (no gap filling, no rejection). ``X_rest``: (T, J, 3) the points of the
    other joints, triangulated from the same keypoints as here: only ``joints`` are triangulated.
    ``frames``: only these frames are triangulated (the error is +inf and the points are
    ``X_rest``'s elsewhere; needs ``X_rest``). Each point's triangulation is its own: the same
    bits as triangulating every joint of every frame."""
    sub = list(joints) if X_rest is not None else list(range(xy.shape[2]))
    if frames is not None and len(frames) == 0:
        return np.full(len(X_rest), np.inf), np.array(X_rest, copy=True)
    if frames is not None:
        P = P[frames] if np.ndim(P) == 4 else P
        xy, conf = xy[frames], conf[frames]
    tri = triangulate(P, xy[:, :, sub], conf[:, :, sub], TriangulationConfig(min_conf=tcfg.min_conf, reject_px=np.inf,
                                                                           max_gap_frames=0, drop_unresolved=False))
    err = np.minimum(tri.reproj_err_px[:, [sub.index(j) for j in joints]], cap)  # (T, j, V)
    seen = np.isfinite(err)
    mean = np.where(seen, err, 0.0).sum((1, 2)) / np.maximum(seen.sum((1, 2)), 1)
    if X_rest is None:
        return mean, tri.points
    X = np.array(X_rest, copy=True)
    if frames is None:
        X[:, sub] = tri.points
        return mean, X
    X[np.ix_(frames, sub)] = tri.points
    full = np.full(len(X), np.inf)
    full[frames] = mean
    return full, X


def _swap(kp: NDArray, pairs: tuple[tuple[int, int], ...]) -> NDArray:
    out = kp.copy()
    for a, b in pairs:
        out[..., [a, b], :] = kp[..., [b, a], :]
    return out


def _mislabelled(points: NDArray, group: str) -> NDArray[np.bool_]:
    """(T,) True where the 3D COCO-17 skeleton has ``group`` the wrong way round, or where that
    cannot be told (a needed point missing): such frames never take a swap.

    Torso pairs and the face: with Z up, a body facing ``f`` (from the mid-shoulders towards the
    nose, horizontally) has its left side towards ``z x f``. Limbs: each elbow (knee) hangs from
    the shoulder (hip) of its own side.
    """
    p = points
    def d(a, b):  # noqa: E306
        return np.linalg.norm(p[:, a] - p[:, b], axis=-1)

    with np.errstate(invalid="ignore"):
        if group in ("arms", "legs"):
            score = limb_side_score(points, group)
            return ~(score > 0)
        mid = 0.5 * (p[:, _L_SHOULDER] + p[:, _R_SHOULDER])
        facing = p[:, _NOSE] - mid
        left = np.stack([-facing[:, 1], facing[:, 0], np.zeros(len(p))], axis=-1)  # z x facing
        pair = {"shoulders": (_L_SHOULDER, _R_SHOULDER), "hips": (_L_HIP, _R_HIP), "face": (_L_EAR, _R_EAR)}[group]
        side = np.sum((p[:, pair[0]] - p[:, pair[1]]) * left, axis=-1)
        return ~(side > 0)


def limb_side_score(points: NDArray, group: str, ends: bool = False) -> NDArray:
    """(T,) metres: how much nearer each elbow (knee) is to the shoulder (hip) of its own side
    than to the other's, summed over the sides seen (positive: labelled the right way round; NaN
    where no side can be told). One seen side is enough (the other limb is often occluded).

    Args:
        points: (T, 17, 3) COCO-17 points (NaN = missing); group: ``arms`` or ``legs``;
        ends: judge the wrists (ankles) against the shoulders (hips) too.
    """
    (l_end, r_end), (l_root, r_root) = (((_L_ELBOW, _R_ELBOW), (_L_SHOULDER, _R_SHOULDER)) if group == "arms"
                                        else ((_L_KNEE, _R_KNEE), (_L_HIP, _R_HIP)))
    pairs = [(l_end, r_end)] + ([(_L_WRIST, _R_WRIST) if group == "arms" else (_L_ANKLE, _R_ANKLE)] if ends else [])

    def d(a, b):  # noqa: E306
        return np.linalg.norm(points[:, a] - points[:, b], axis=-1)

    votes = np.stack([v for lft, rgt in pairs for v in (d(lft, r_root) - d(lft, l_root), d(rgt, l_root) - d(rgt, r_root))])
    seen = np.isfinite(votes).any(axis=0)
    return np.where(seen, np.nansum(votes, axis=0), np.nan)


#: Bones (parent, child) of each limb group, both sides.
_LIMB_BONES = {
    "arms": ((_L_SHOULDER, _L_ELBOW), (_R_SHOULDER, _R_ELBOW), (_L_ELBOW, 9), (_R_ELBOW, 10)),
    "legs": ((_L_HIP, _L_KNEE), (_R_HIP, _R_KNEE), (_L_KNEE, 15), (_R_KNEE, 16)),
}


def _implausible_bones(points: NDArray, bones, lengths: NDArray, tol: float) -> NDArray:
    """(T,) number of ``bones`` whose length in ``points`` (T, 17, 3) is more than ``tol`` off
    ``lengths``; a bone with a missing end counts as implausible (it cannot vouch for a labelling)."""
    out = np.zeros(len(points))
    for (a, b), L in zip(bones, lengths):
        d = np.linalg.norm(points[:, a] - points[:, b], axis=-1)
        with np.errstate(invalid="ignore"):
            out += ~(np.abs(d - L) <= tol * L)
    return out


def _runs(mask: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """[start, end) of each run of True."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


def _continuity_gain(kp: NDArray, v: int, run: tuple[int, int], pairs, min_conf: float) -> float:
    """How much swapping view ``v``'s pairs over ``run`` shortens the 2D jumps at the run's ends
    (pixels; positive = the swapped labels continue their neighbours better)."""
    a, b = run
    joints = [j for pair in pairs for j in pair]
    gain = 0.0
    for inside, outside in ((a, a - 1), (b - 1, b)):
        if outside < 0 or outside >= len(kp):
            continue
        k_in, k_out = kp[inside, v], kp[outside, v]
        ok = (k_in[joints, 2] >= min_conf) & (k_out[joints, 2] >= min_conf)
        if not ok.any():
            continue
        raw = np.linalg.norm(k_in[joints, :2] - k_out[joints, :2], axis=-1)
        sw = np.linalg.norm(_swap(k_in, pairs)[joints, :2] - k_out[joints, :2], axis=-1)
        gain += float(np.sum((raw - sw)[ok]))
    return gain


def _bone_swaps(P, kp, X0, base, name, pairs, g, swapped, tcfg, cfg) -> tuple[NDArray, int]:
    """Two views, arms or legs: swap back the view whose swap makes the group's bones plausible
    (see :attr:`SwapConfig.bone_tol`); marks ``swapped`` in place; returns the keypoints and how
    many frames were changed."""
    from embodmocap.motion.ik import symmetric_length

    bones = _LIMB_BONES[name]
    d = [np.linalg.norm(X0[:, a] - X0[:, b], axis=-1) for a, b in bones]
    # The expected lengths: one per left/right pair, the value most frames share (a long swapped
    # run skews a plain median of each side).
    L = np.array([symmetric_length(d[0], d[1])] * 2 + [symmetric_length(d[2], d[3])] * 2)
    if not np.isfinite(L).all():
        return kp, 0
    joints = [j for pair in pairs for j in pair]
    n0 = _implausible_bones(X0, bones, L, cfg.bone_tol)
    best_n, best_v = n0.copy(), np.full(len(kp), -1)
    for v in range(kp.shape[1]):
        trial = kp.copy()
        trial[:, v] = _swap(kp[:, v], pairs)
        # only the frames where a swap may be taken (a bone implausible as given)
        err, Xv = _frame_error(P, trial[..., :2], trial[..., 2], tcfg, cfg.cap_px, joints, X0, np.flatnonzero(n0 >= 1))
        nv = _implausible_bones(Xv, bones, L, cfg.bone_tol)
        ok = (nv == 0) & (n0 >= 1) & (nv < best_n) & (err <= base + cfg.bone_max_extra_px)
        best_n, best_v = np.where(ok, nv, best_n), np.where(ok, v, best_v)
    if cfg.bone_continuity:
        # Runs whose swap breaks the view's own trajectories at their ends are not swapped.
        for v in range(kp.shape[1]):
            for a, b in _runs(best_v == v):
                if _continuity_gain(kp, v, (a, b), pairs, tcfg.min_conf) < 0:
                    best_v[a:b] = -1
    t_idx = np.flatnonzero(best_v >= 0)
    for t in t_idx:
        kp[t, best_v[t]] = _swap(kp[t, best_v[t]], pairs)
        swapped[t, best_v[t], g] = True
    if len(t_idx):
        log.info("left/right %s swapped back by bone lengths in %d frames", name, len(t_idx))
    return kp, len(t_idx)


def fix_swaps(P: NDArray, keypoints: NDArray, tcfg: TriangulationConfig = TriangulationConfig(),
              cfg: SwapConfig = SwapConfig(),
              groups: dict[str, tuple[tuple[int, int], ...]] = COCO17_SWAP_GROUPS) -> tuple[NDArray, NDArray[np.bool_]]:
    """Undo left/right swaps of COCO-17 keypoints (see the module docstring).

    Args:
        P: (V, 3, 4) or (T, V, 3, 4) projection matrices (world Z up).
        keypoints: (T, V, 17, 3) pixels and confidence of each view.
        tcfg: the triangulation settings (its ``min_conf``).
        cfg: swap detection settings.
        groups: name -> left/right index pairs swapped together.

    Returns:
        (keypoints with the swaps undone (T, V, 17, 3), swapped (T, V, G) bool per group in
        ``groups`` order).
    """
    kp = np.array(keypoints, dtype=np.float64, copy=True)
    T, V = kp.shape[:2]
    names = list(groups)
    swapped = np.zeros((T, V, len(names)), dtype=bool)
    # The points of the keypoints as they stand (every joint triangulated once; then only the
    # joints of the group at hand, whose keypoints alone a group's swaps change).
    X_now = None
    for g, name in enumerate(names):
        joints = [j for pair in groups[name] for j in pair]
        base, X0 = _frame_error(P, kp[..., :2], kp[..., 2], tcfg, cfg.cap_px, joints, X_now)
        X_now = X0
        if V == 2 and name in _LIMB_BONES and cfg.bone_tol > 0:
            kp, n_bone = _bone_swaps(P, kp, X0, base, name, groups[name], g, swapped, tcfg, cfg)
            if n_bone:
                base, X_now = _frame_error(P, kp[..., :2], kp[..., 2], tcfg, cfg.cap_px, joints, X0)
        bad = base >= cfg.min_error_px
        if not bad.any():
            continue
        best_err, best_view = base.copy(), np.full(T, -1)
        trials = []
        for v in range(V):
            trial = kp.copy()
            trial[:, v] = _swap(kp[:, v], groups[name])
            # only the frames where a swap may be taken (bad: the runs judged below lie within them)
            err, Xv = _frame_error(P, trial[..., :2], trial[..., 2], tcfg, cfg.cap_px, joints, X0, np.flatnonzero(bad))
            trials.append((err, Xv))
            # With 3+ views only the wrong view's swap lowers the error.
            ok = bad & (err < cfg.min_gain * base) & (err < best_err)
            best_err = np.where(ok, err, best_err)
            best_view = np.where(ok, v, best_view)
        if V == 2:
            # Two views agree after swapping either one: decide per run of frames, by which view's
            # labels jump at the run's ends (the swapped one does), else by the body's anatomy.
            fixed_view = np.full(T, -1)
            for run in _runs(best_view >= 0):
                gains = [_continuity_gain(kp, v, run, groups[name], tcfg.min_conf) for v in range(V)]
                if max(gains) > 0:
                    fixed_view[run[0]:run[1]] = int(np.argmax(gains))
                else:
                    for v in range(V):
                        right = ~_mislabelled(trials[v][1][run[0]:run[1]], name)
                        if right.mean() > 0.5:
                            fixed_view[run[0]:run[1]] = v
                            break
            best_view = fixed_view
        t_idx = np.flatnonzero(best_view >= 0)
        for t in t_idx:
            v = best_view[t]
            kp[t, v] = _swap(kp[t, v], groups[name])
            swapped[t, v, g] = True
        if len(t_idx):
            X_now = _frame_error(P, kp[..., :2], kp[..., 2], tcfg, cfg.cap_px, joints, X_now)[1]
            log.info("left/right %s swapped back in %d frames (%s)", name, len(t_idx),
                     ", ".join(f"view {v}: {int((best_view == v).sum())}" for v in range(V) if (best_view == v).any()))
    return kp, swapped
