"""A starting body from triangulated keypoints alone: shape from bone lengths, analytic IK.

No regressor is needed (a user on a CPU machine, or anyone with only 2D keypoints). Three steps,
all vectorised over frames:

1. :func:`betas_from_bone_lengths`: the length of each observed bone (upper arms, forearms,
   thighs, shins: one per left/right pair, the value most frames share, :func:`symmetric_length`;
   shoulder and hip width, trunk: the median) over the sequence, and the betas whose rest
   skeleton has those lengths (Gauss-Newton on the first betas, a small ridge keeps them near 0).
2. :func:`place_torso`: per frame, the rigid rotation and translation that put the rest body's hips
   and shoulders on the triangulated ones (weighted Kabsch; hips count more, the spine bends), then
   the remaining trunk rotation between hips and shoulders shared by the three spine joints.
3. :func:`limb_ik`: per limb (hip-knee-ankle, shoulder-elbow-wrist), the root joint's swing that
   points the upper bone at the observed middle joint and its twist that puts the hinge (knee,
   elbow) axis normal to the plane of the observed limb, then the hinge joint's swing that points
   the lower bone at the observed end joint. A limb bent less than ``min_bend_deg`` keeps the
   swing's twist (the plane is undefined when it is straight). Where the end point is seen but
   the middle joint is not (one view's depth gives the wrist, the elbow is hidden), the limb
   filled from its neighbours is turned and bent to reach the end point (:func:`reach_end`).

Frames where a step has nothing to go on (too few torso points, a limb not seen) take the
rotation interpolated from their neighbours (:func:`embodmocap.motion.fill.fill_rotations`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from embodmocap.body.joints import coco17_matrix, face_vertex_ids
from embodmocap.motion.fill import fill_linear, fill_rotations
from embodmocap.geometry.rotations import rotvec_between as _swing

# COCO-17 indices.
_LSHO, _RSHO, _LELB, _RELB, _LWRI, _RWRI = 5, 6, 7, 8, 9, 10
_LHIP, _RHIP, _LKNE, _RKNE, _LANK, _RANK = 11, 12, 13, 14, 15, 16
_TORSO = (_LSHO, _RSHO, _LHIP, _RHIP)
#: Torso weights of the rigid fit: the hips fix the pelvis, the shoulders (which the spine moves)
#: only help with the facing direction.
_TORSO_W = np.array([0.5, 0.5, 1.0, 1.0])
#: Bones whose observed lengths give the shape: pairs of COCO-17 points (the trunk is the segment
#: between the hip and shoulder midpoints, handled apart).
BONES: tuple[tuple[int, int], ...] = (
    (_LSHO, _LELB), (_RSHO, _RELB), (_LELB, _LWRI), (_RELB, _RWRI), (_LHIP, _LKNE), (_RHIP, _RKNE),
    (_LKNE, _LANK), (_RKNE, _RANK), (_LSHO, _RSHO), (_LHIP, _RHIP),
)
#: (root joint, hinge joint, end joint, COCO middle point, COCO end point, hinge axis in the
#: hinge joint's frame) of the four limbs: knees flex about +x, the left elbow about -y and the
#: right one about +y (as :data:`embodmocap.motion.terms.HINGES`).
LIMBS: tuple[tuple[int, int, int, int, int, tuple[float, float, float]], ...] = (
    (1, 4, 7, _LKNE, _LANK, (1.0, 0.0, 0.0)),
    (2, 5, 8, _RKNE, _RANK, (1.0, 0.0, 0.0)),
    (16, 18, 20, _LELB, _LWRI, (0.0, -1.0, 0.0)),
    (17, 19, 21, _RELB, _RWRI, (0.0, 1.0, 0.0)),
)
_SPINE = (3, 6, 9)


@dataclass(frozen=True)
class RestSkeleton:
    """The body model's rest skeleton as an affine function of the betas (B used).

    joints(b) = J0 + Jd @ b: (24, 3); keypoints(b) = K0 + Kd @ b: (17, 3) COCO-17 points of the
    keypoint layout in the rest pose (SMPL canonical frame, Y up). parents: (24,).
    """

    J0: NDArray
    Jd: NDArray  # (24, 3, B)
    K0: NDArray
    Kd: NDArray  # (17, 3, B)
    parents: NDArray

    def joints(self, b: NDArray) -> NDArray:
        return self.J0 + self.Jd @ b

    def keypoints(self, b: NDArray) -> NDArray:
        return self.K0 + self.Kd @ b


def rest_skeleton(model, layout: str = "COCO17") -> RestSkeleton:
    """:class:`RestSkeleton` of ``model`` for keypoints of ``layout``. A model without face
    vertex ids gets the face rows from the head joint (they are not used here)."""
    a = model.arrays
    Jr = a["J_regressor"]
    J0 = Jr @ a["v_template"]
    Jd = np.einsum("jv,vcb->jcb", Jr, a["shapedirs"])
    try:
        ids = face_vertex_ids(model.vertex_ids)
        F0, Fd = a["v_template"][ids], a["shapedirs"][ids]
    except (KeyError, ValueError):
        F0, Fd = np.repeat(J0[15:16], 5, 0), np.repeat(Jd[15:16], 5, 0)
    A = coco17_matrix(layout)
    K0 = A @ np.concatenate([J0, F0])
    Kd = np.einsum("kj,jcb->kcb", A, np.concatenate([Jd, Fd]))
    parents = np.asarray(model.parents, dtype=np.int64).copy()
    parents[0] = -1
    return RestSkeleton(J0, Jd, K0, Kd, parents)


def _seen(points: NDArray, conf: NDArray, min_conf: float) -> NDArray[np.bool_]:
    return np.isfinite(points).all(-1) & (np.nan_to_num(conf) >= min_conf)


#: Left/right pairs of :data:`BONES` (indices into it): a body is symmetric, so each pair has one length.
BONE_PAIRS: tuple[tuple[int, int], ...] = ((0, 1), (2, 3), (4, 5), (6, 7))


def symmetric_length(d_left: NDArray, d_right: NDArray, tol: float = 0.1, min_frames: int = 3) -> float:
    """One length for a left/right pair of bones from their per-frame lengths (T,) each (NaN where
    not seen): the densest value of both sides' lengths pooled (the length with the most others
    within ``tol``, relative), refined as the median of those.

    A plain median is skewed when a limb swap in one view lasts for a good part of the sequence
    (with two views it triangulates the limbs at wrong depths: bones too long or too short, by an
    amount that changes as the limbs move), and the two sides can then even agree with each other
    on a wrong length; the right length is the one most frames share. NaN with fewer than
    ``min_frames`` lengths.
    """
    d = np.concatenate([np.asarray(d_left, dtype=np.float64).ravel(), np.asarray(d_right, dtype=np.float64).ravel()])
    d = np.sort(d[np.isfinite(d) & (d > 0)])
    if len(d) < min_frames:
        return float("nan")
    # For each length x, how many lie in [x / (1 + tol), x * (1 + tol)] (sorted: two searches).
    lo = np.searchsorted(d, d / (1.0 + tol), side="left")
    hi = np.searchsorted(d, d * (1.0 + tol), side="right")
    k = int(np.argmax(hi - lo))
    return float(np.median(d[lo[k]:hi[k]]))


def observed_bone_lengths(points: NDArray, seen: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Length of each of :data:`BONES` and of the trunk over the frames that see both ends
    ((len(BONES) + 1,), NaN when never seen): left/right pairs by :func:`symmetric_length`, the
    widths and the trunk by their median."""
    out = np.full(len(BONES) + 1, np.nan)
    d = np.full((len(points), len(BONES)), np.nan)
    for k, (a, b) in enumerate(BONES):
        ok = seen[:, a] & seen[:, b]
        d[ok, k] = np.linalg.norm(points[ok, a] - points[ok, b], axis=-1)
        if ok.sum() >= 3:
            out[k] = np.median(d[ok, k])
    for l, r in BONE_PAIRS:
        out[l] = out[r] = symmetric_length(d[:, l], d[:, r])
    ok = seen[:, list(_TORSO)].all(1)
    if ok.sum() >= 3:
        mid = lambda i, j: 0.5 * (points[ok, i] + points[ok, j])  # noqa: E731
        out[-1] = np.median(np.linalg.norm(mid(_LSHO, _RSHO) - mid(_LHIP, _RHIP), axis=-1))
    return out


def _model_lengths(sk: RestSkeleton, b: NDArray) -> tuple[NDArray, NDArray]:
    """Rest lengths (L,) of :data:`BONES` + trunk and their Jacobian (L, B) w.r.t. the betas."""
    P = sk.keypoints(b)
    segs = [(P[a] - P[c], sk.Kd[a] - sk.Kd[c]) for a, c in BONES]
    segs.append((0.5 * (P[_LSHO] + P[_RSHO] - P[_LHIP] - P[_RHIP]),
                 0.5 * (sk.Kd[_LSHO] + sk.Kd[_RSHO] - sk.Kd[_LHIP] - sk.Kd[_RHIP])))
    L = np.array([np.linalg.norm(d) for d, _ in segs])
    Jac = np.stack([(d / max(np.linalg.norm(d), 1e-9)) @ D for d, D in segs])
    return L, Jac


def betas_from_bone_lengths(sk: RestSkeleton, lengths: NDArray, n_betas: int = 10, ridge_m: float = 0.01,
                            iterations: int = 8) -> NDArray[np.float64]:
    """Betas (B,) whose rest skeleton has the observed bone ``lengths`` (see
    :func:`observed_bone_lengths`; NaN entries are ignored).

    Gauss-Newton on the first ``n_betas`` betas of ``min((L - L_obs)^2) + ridge_m^2 |b|^2``: a beta of
    one unit is worth ``ridge_m`` metres of summed length error, which keeps unobserved directions
    of the shape space at zero.
    """
    B = sk.Jd.shape[-1]
    n = min(n_betas, B)
    b = np.zeros(B)
    ok = np.isfinite(lengths)
    if ok.sum() < 3:
        return b
    for _ in range(iterations):
        L, Jac = _model_lengths(sk, b)
        r, Jn = (L - lengths)[ok], Jac[ok][:, :n]
        H = Jn.T @ Jn + ridge_m ** 2 * np.eye(n)
        g = Jn.T @ r + ridge_m ** 2 * b[:n]
        step = np.linalg.solve(H, g)
        b[:n] -= step
        if np.abs(step).max() < 1e-4:
            break
    return np.clip(b, -4.0, 4.0)


#: (parent, child) COCO-17 points along the limbs, parents first.
_LIMB_BONES: tuple[tuple[int, int], ...] = (
    (_LSHO, _LELB), (_RSHO, _RELB), (_LHIP, _LKNE), (_RHIP, _RKNE),
    (_LELB, _LWRI), (_RELB, _RWRI), (_LKNE, _LANK), (_RKNE, _RANK),
)


def implausible_points(sk: RestSkeleton, b: NDArray, points: NDArray, seen: NDArray[np.bool_],
                       tol: float = 0.3, anchors: NDArray | None = None) -> NDArray[np.bool_]:
    """(T, 17) limb points whose bone to the parent point is more than ``tol`` (relative) longer
    or shorter than the body's (shape ``b``).

    With two views a detector's left/right confusion or a wrong guess along the epipolar line
    triangulates without a reprojection error, at the wrong depth: the bone lengths give it away.
    A point whose parent is itself implausible is judged against the grandparent (the sum of the
    two bones, as an upper bound only). ``anchors`` (T, 17, 3), finite where known: where a
    shoulder or hip was not triangulated, the elbow or knee is judged against the anchor's
    (:func:`torso_anchors`: the torso placed on the other torso points), so an arm whose shoulder
    no view saw is checked too.
    """
    P = sk.keypoints(b)
    bad = np.zeros(seen.shape, dtype=bool)
    parent_of = {c: p for p, c in _LIMB_BONES}
    if anchors is not None:
        use_anchor = ~seen & np.isfinite(anchors).all(-1)
        points = np.where(use_anchor[..., None], anchors, points)
        seen = seen | use_anchor
    with np.errstate(invalid="ignore"):
        for par, child in _LIMB_BONES:
            L = np.linalg.norm(P[child] - P[par])
            d = np.linalg.norm(points[:, child] - points[:, par], axis=-1)
            ok_par = seen[:, par] & ~bad[:, par]
            wrong = ok_par & seen[:, child] & (np.abs(d - L) > tol * L)
            gp = parent_of.get(par)
            if gp is not None:
                # The parent unusable: the grandparent bounds the reach.
                reach = L + np.linalg.norm(P[par] - P[gp])
                dg = np.linalg.norm(points[:, child] - points[:, gp], axis=-1)
                use_gp = ~ok_par & seen[:, gp] & ~bad[:, gp] & seen[:, child]
                wrong |= use_gp & (dg > (1 + tol) * reach)
            bad[:, child] = wrong
    if anchors is not None:
        bad &= ~use_anchor
    return bad


#: The six pairs of torso points (shoulders, hips) whose distances :func:`implausible_torso` checks.
_TORSO_PAIRS: tuple[tuple[int, int], ...] = ((_LSHO, _RSHO), (_LHIP, _RHIP), (_LSHO, _LHIP), (_RSHO, _RHIP),
                                             (_LSHO, _RHIP), (_RSHO, _LHIP))


def implausible_torso(sk: RestSkeleton, b: NDArray, points: NDArray, seen: NDArray[np.bool_],
                      tol_m: float = 0.1) -> NDArray[np.bool_]:
    """(T, 17) shoulders and hips that do not fit the body's torso (shape ``b``).

    The trunk bends and twists, but the distances between its four keypoints change little when
    it does (the hips lie near the axes of the spine's bends; a 20 degree side bend changes a
    shoulder-hip distance by about 5 cm of its 50). A point triangulated from a wrong detection
    (an occluded hip guessed in one view, a shoulder of the wrong side) breaks them, and the
    rigid torso fit of the keypoint start then turns the whole body (measured on the hard outdoor
    studio session: one shoulder 48 cm off turned the start 100 degrees, and the frames around it,
    interpolated towards it, by 20-65). Per frame, while a pair of seen torso points is more than
    ``tol_m`` metres longer or shorter than the rest body's, the point of a failing pair whose
    pairs deviate most in all is marked (a wrong point bends every distance it is in). Frames
    with fewer than three seen torso points are left alone (nothing to check them against).
    0 = off.
    """
    bad = np.zeros(seen.shape, dtype=bool)
    if tol_m <= 0:
        return bad
    P = sk.keypoints(b)
    idx = list(_TORSO)
    pos = {k: i for i, k in enumerate(idx)}
    L = np.array([np.linalg.norm(P[a] - P[c]) for a, c in _TORSO_PAIRS])
    ok = seen[:, idx].copy()  # (T, 4)
    with np.errstate(invalid="ignore"):
        d = np.stack([np.linalg.norm(points[:, a] - points[:, c], axis=-1) for a, c in _TORSO_PAIRS], 1)
    dev = np.nan_to_num(np.abs(d - L), nan=0.0)  # (T, 6)
    check = ok.sum(1) >= 3
    for _ in range(2):  # at most two of four points go (then fewer than three are left)
        live = np.stack([ok[:, pos[a]] & ok[:, pos[c]] for a, c in _TORSO_PAIRS], 1) & check[:, None]
        e = np.where(live, dev, 0.0)
        fails = e > tol_m
        # Among the points of a failing pair, the one whose pairs deviate most in all: a wrong
        # point bends every distance it is in, most of them below the tolerance.
        score, suspect = np.zeros(ok.shape), np.zeros(ok.shape, dtype=bool)
        for k, (a, c) in enumerate(_TORSO_PAIRS):
            for q in (pos[a], pos[c]):
                score[:, q] += e[:, k]
                suspect[:, q] |= fails[:, k]
        score = np.where(suspect, score, -1.0)
        drop = fails.any(1) & (ok.sum(1) >= 3)
        if not drop.any():
            break
        worst = np.argmax(score, axis=1)
        rows = np.flatnonzero(drop)
        ok[rows, worst[rows]] = False
        bad[rows, np.asarray(idx)[worst[rows]]] = True
    return bad


def torso_anchors(sk: RestSkeleton, b: NDArray, points: NDArray, seen: NDArray[np.bool_]) -> NDArray:
    """(T, 17, 3) the shoulders and hips of the rest body (shape ``b``) placed on the triangulated
    torso (:func:`place_torso`, with the spine), NaN elsewhere and in frames with fewer than three
    torso points seen. Points must be in the layout of ``sk``."""
    out = np.full(points.shape, np.nan)
    try:
        root, pelvis, spine, placed = place_torso(sk, b, points, seen)
    except ValueError:
        return out
    T = len(points)
    R_local = np.broadcast_to(np.eye(3), (T, 24, 3, 3)).copy()
    R_local[:, 0] = Rotation.from_rotvec(root).as_matrix()
    for j in _SPINE:
        R_local[:, j] = Rotation.from_rotvec(spine).as_matrix()
    Rw, pos = _fk(sk, b, R_local)
    # Shoulders and hips are combinations of joints only (no face vertices): the layout's rows.
    rel = sk.K0 + sk.Kd @ b - sk.joints(b)[0]  # rest keypoints about the rest pelvis
    Jrel = sk.joints(b) - sk.joints(b)[0]
    for k in _TORSO:
        # Each torso keypoint follows the joint it is nearest to in the rest pose, offset rigidly.
        j = int(np.argmin(np.linalg.norm(Jrel - rel[k], axis=-1)))
        out[:, k] = pelvis + pos[:, j] + np.einsum("tij,j->ti", Rw[:, j], rel[k] - Jrel[j])
    out[~placed] = np.nan
    return out


def _kabsch(q: NDArray, p: NDArray, w: NDArray) -> tuple[NDArray, NDArray]:
    """Per frame, the rotation R (T, 3, 3) and translation t (T, 3) minimising
    ``sum_i w_ti |R q_i + t - p_ti|^2`` for model points q (N, 3), targets p (T, N, 3), weights
    w (T, N) (zero = missing; each frame needs three non-collinear weighted points)."""
    ws = w.sum(1, keepdims=True).clip(min=1e-12)
    qc = (w[..., None] * q[None]).sum(1) / ws
    pc = (w[..., None] * p).sum(1) / ws
    H = np.einsum("tn,tni,tnj->tij", w, q[None] - qc[:, None], p - pc[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("tji,tkj->tik", Vt, U)))
    D = np.zeros_like(H)
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.einsum("tji,tjk,tlk->til", Vt, D, U)
    return R, pc - np.einsum("tij,tj->ti", R, qc)


def _fk(sk: RestSkeleton, b: NDArray, R_local: NDArray) -> tuple[NDArray, NDArray]:
    """World rotations (T, 24, 3, 3) and joint positions relative to the rest pelvis (T, 24, 3)
    (add the pelvis position) for local rotations (T, 24, 3, 3)."""
    J = sk.joints(b)
    T = len(R_local)
    Rw = np.zeros_like(R_local)
    pos = np.zeros((T, 24, 3))
    Rw[:, 0] = R_local[:, 0]
    for j in range(1, 24):
        p = sk.parents[j]
        Rw[:, j] = Rw[:, p] @ R_local[:, j]
        pos[:, j] = pos[:, p] + np.einsum("tij,j->ti", Rw[:, p], J[j] - J[p])
    return Rw, pos


def _fill(rotvec: NDArray, ok: NDArray[np.bool_]) -> NDArray:
    if ok.all():
        return rotvec
    if not ok.any():
        return np.zeros_like(rotvec)
    return fill_rotations(rotvec[:, None], ok)[:, 0]


def place_torso(sk: RestSkeleton, b: NDArray, points: NDArray, seen: NDArray[np.bool_]
                ) -> tuple[NDArray, NDArray, NDArray, NDArray[np.bool_]]:
    """Root rotation vectors (T, 3), pelvis positions (T, 3), spine rotation vectors (T, 3) (each
    of the three spine joints'), and (T,) the frames actually placed (the rest interpolated).

    Raises:
        ValueError: no frame sees three of the four torso points.
    """
    T = len(points)
    idx = list(_TORSO)
    w = seen[:, idx] * _TORSO_W[None]
    placed = seen[:, idx].sum(1) >= 3
    if not placed.any():
        raise ValueError("no frame has both hips and both shoulders (or three of the four) triangulated: "
                         "cannot place the body")
    P = sk.keypoints(b)
    J = sk.joints(b)
    q = P[idx] - J[0]  # torso points relative to the rest pelvis
    p = np.nan_to_num(points[:, idx])
    R, t = _kabsch(q, np.where(placed[:, None, None], p, q[None]), np.where(placed[:, None], w, 1.0))
    root = _fill(Rotation.from_matrix(R).as_rotvec(), placed)
    R = Rotation.from_rotvec(root).as_matrix()
    pelvis = np.where(placed[:, None], t, np.nan)
    pelvis = fill_linear(np.nan_to_num(pelvis), placed)
    # The trunk's own rotation: shoulders about the pelvis, what the rigid fit left over.
    sh = seen[:, _LSHO] & seen[:, _RSHO] & placed
    spine = np.zeros((T, 3))
    if sh.any():
        m_l = np.einsum("tij,j->ti", R, P[_LSHO] - J[0])
        m_r = np.einsum("tij,j->ti", R, P[_RSHO] - J[0])
        o_l, o_r = p[:, 0] - pelvis, p[:, 1] - pelvis
        q2 = np.stack([m_l, m_r], 1)
        tgt = np.stack([o_l, o_r], 1)
        # Kabsch about the pelvis on the two shoulders and their cross product (a third direction).
        q3 = np.concatenate([q2, np.cross(m_l, m_r)[:, None]], 1)
        t3 = np.concatenate([tgt, np.cross(o_l, o_r)[:, None]], 1)
        H = np.einsum("tni,tnj->tij", q3, t3)
        U, _, Vt = np.linalg.svd(H)
        d = np.sign(np.linalg.det(np.einsum("tji,tkj->tik", Vt, U)))
        D = np.zeros_like(H)
        D[:, 0, 0] = D[:, 1, 1] = 1.0
        D[:, 2, 2] = d
        delta = np.einsum("tji,tjk,tlk->til", Vt, D, U)  # world rotation
        # Spread over the three spine joints: local Q = R^T delta^(1/3) R, so the chain's world
        # rotation becomes delta R.
        third = Rotation.from_rotvec(Rotation.from_matrix(delta).as_rotvec() / 3.0).as_matrix()
        Q = np.einsum("tji,tjk,tkl->til", R, third, R)
        spine = _fill(Rotation.from_matrix(Q).as_rotvec(), sh)
    return root, pelvis, spine, placed


def limb_ik(sk: RestSkeleton, b: NDArray, R_local: NDArray, pelvis: NDArray, points: NDArray,
            seen: NDArray[np.bool_], min_bend_deg: float = 15.0,
            reach: NDArray[np.bool_] | None = None) -> NDArray:
    """Local rotations (T, 24, 3, 3) with the four limbs' root and hinge joints set by analytic IK
    (see the module docstring); other joints as given in ``R_local``. ``reach`` (T, 17): the end
    points a limb whose middle joint is not seen is bent to reach (:func:`reach_end`; default:
    every seen one)."""
    R_local = R_local.copy()
    J = sk.joints(b)
    Rw, pos = _fk(sk, b, R_local)
    pos = pos + pelvis[:, None]
    T = len(points)
    sin_min = np.sin(np.deg2rad(min_bend_deg))
    for root, hinge, end, k_mid, k_end, axis in LIMBS:
        par = sk.parents[root]
        ok1 = seen[:, k_mid]
        ok2 = ok1 & seen[:, k_end]
        Rp = Rw[:, par]
        u = np.nan_to_num(points[:, k_mid]) - pos[:, root]  # upper bone, world
        f = np.nan_to_num(points[:, k_end] - points[:, k_mid])  # lower bone, world
        u_l = np.einsum("tji,tj->ti", Rp, u)  # in the parent's frame
        b1 = np.tile(J[hinge] - J[root], (T, 1))
        S = Rotation.from_rotvec(_swing(b1, u_l))
        # Twist about the upper bone so the hinge axis is normal to the observed limb's plane.
        n = np.cross(u, f)
        sin_bend = np.linalg.norm(n, axis=-1) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(f, axis=-1)).clip(min=1e-12)
        n_l = np.einsum("tji,tj->ti", Rp, n)
        ud = u_l / np.linalg.norm(u_l, axis=-1, keepdims=True).clip(min=1e-12)
        a0 = S.apply(np.tile(np.asarray(axis), (T, 1)))
        proj = lambda v: v - (v * ud).sum(-1, keepdims=True) * ud  # noqa: E731
        a0p, n_p = proj(a0), proj(n_l)
        phi = np.arctan2((np.cross(a0p, n_p) * ud).sum(-1), (a0p * n_p).sum(-1))
        # Beyond 90 degrees the limb would have to turn round to bend the allowed way: treat it as
        # a (slightly) over-straightened joint instead.
        phi = np.where(np.abs(phi) > np.pi / 2, phi - np.pi * np.sign(phi), phi)
        phi = np.where(ok2 & (sin_bend > sin_min), phi, 0.0)
        L_root = Rotation.from_rotvec(ud * phi[:, None]) * S
        rv_root = _fill(L_root.as_rotvec(), ok1)
        R_local[:, root] = Rotation.from_rotvec(rv_root).as_matrix()
        # The hinge joint: point the lower bone at the observed end point.
        Rh_par = Rp @ R_local[:, root]
        f_l = np.einsum("tji,tj->ti", Rh_par, f)
        b2 = np.tile(J[end] - J[hinge], (T, 1))
        rv_h = _fill(_swing(b2, f_l), ok2)
        R_local[:, hinge] = Rotation.from_rotvec(rv_h).as_matrix()
        # End point seen, middle joint not (a wrist lifted from one view's depth, its elbow
        # hidden): the filled limb can be far off, and the fit's robust term then writes the end
        # point off. Reach it instead, bent in the plane of the filled (neighbouring) pose.
        only_end = (seen if reach is None else reach)[:, k_end] & ~ok1
        if only_end.any():
            R_local[only_end, root], R_local[only_end, hinge] = reach_end(
                J[hinge] - J[root], sk.keypoints(b)[k_end] - J[hinge], np.asarray(axis), Rp[only_end],
                R_local[only_end, root], points[only_end, k_end] - pos[only_end, root])
    return R_local


def reach_end(b1: NDArray, b2: NDArray, axis: NDArray, R_parent: NDArray, R_root: NDArray, target: NDArray,
              max_bend_deg: float = 160.0, steps: int = 321) -> tuple[NDArray, NDArray]:
    """Two-bone IK from the end point alone: root and hinge rotations (N, 3, 3) that put the
    limb's end at ``target``, the bend plane kept from ``R_root``.

    The hinge turns about its ``axis`` (the allowed way, 0..``max_bend_deg``) so that the
    root-to-end distance matches ``|target|`` (straight when it is farther than the limb reaches,
    most bent when nearer); then the smallest rotation of the root takes the end onto the target,
    so the bend plane is the one ``R_root`` gave (e.g. interpolated from frames where the middle
    joint is seen).

    Args:
        b1: (3,) rest root-to-hinge bone; b2: (3,) rest hinge-to-end offset (in the hinge's frame).
        axis: (3,) hinge axis in the hinge joint's frame (positive turns bend the limb).
        R_parent: (N, 3, 3) world rotation of the root's parent; R_root: (N, 3, 3) its starting local
            rotation.
        target: (N, 3) end point minus root joint, world.
    """
    theta = np.deg2rad(np.linspace(0.0, max_bend_deg, steps))
    Rh_grid = Rotation.from_rotvec(axis[None] * theta[:, None])
    reach = np.linalg.norm(b1 + Rh_grid.apply(b2), axis=-1)  # (steps,)
    d = np.linalg.norm(target, axis=-1)
    k = np.abs(reach[None] - d[:, None]).argmin(1)
    Rh = Rh_grid[k].as_matrix()  # (N, 3, 3)
    e_l = np.einsum("nij,nj->ni", R_root, b1 + np.einsum("nij,j->ni", Rh, b2))  # in the parent's frame
    t_l = np.einsum("nji,nj->ni", R_parent, target)
    S = Rotation.from_rotvec(_swing(e_l, t_l)).as_matrix()
    return S @ R_root, Rh


def init_ik(model, points: NDArray, conf: NDArray, layout: str = "COCO17", min_conf: float = 0.1,
            bone_tol: float | None = None, reach_min_conf: float = 0.0) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray[np.bool_]]:
    """The whole starting body from triangulated keypoints.

    Args:
        model: the body model.
        points: (T, 17, 3) COCO-17-ordered keypoints of ``layout`` in the world (Z up), metres, NaN
            where missing.
        conf: (T, 17) their confidence; below ``min_conf`` counts as missing.
        bone_tol: when given, limb points whose bone length is off by more than this fraction
            (:func:`implausible_points`) are not used (interpolated from their neighbours).
        reach_min_conf: a limb whose middle joint is not seen is bent to reach its seen end point
            (:func:`reach_end`) only when that point's confidence is at least this; below, the
            limb keeps the pose filled from its neighbouring frames.

    Returns:
        betas (B,), global_orient (T, 3), body_pose (T, 69), transl (T, 3), placed (T,) bool
        (frames whose torso was seen; the others are interpolated).

    Raises:
        ValueError: bad shapes, or no frame with three of the hips and shoulders.
    """
    points = np.asarray(points, dtype=np.float64)
    conf = np.asarray(conf, dtype=np.float64)
    T = len(points)
    if points.shape != (T, 17, 3) or conf.shape != (T, 17):
        raise ValueError(f"points must be (T, 17, 3) and conf (T, 17), got {points.shape} and {conf.shape}")
    seen = _seen(points, conf, min_conf)
    sk = rest_skeleton(model, layout)
    b = betas_from_bone_lengths(sk, observed_bone_lengths(points, seen))
    if bone_tol is not None:
        seen = seen & ~implausible_points(sk, b, points, seen, bone_tol)
    root, pelvis, spine, placed = place_torso(sk, b, points, seen)
    R_local = np.broadcast_to(np.eye(3), (T, 24, 3, 3)).copy()
    R_local[:, 0] = Rotation.from_rotvec(root).as_matrix()
    for j in _SPINE:
        R_local[:, j] = Rotation.from_rotvec(spine).as_matrix()
    R_local = limb_ik(sk, b, R_local, pelvis, points, seen, reach=seen & (np.nan_to_num(conf) >= reach_min_conf))
    rv = Rotation.from_matrix(R_local.reshape(-1, 3, 3)).as_rotvec().reshape(T, 72)
    transl = pelvis - sk.joints(b)[0]
    return b, rv[:, :3], rv[:, 3:], transl, placed
