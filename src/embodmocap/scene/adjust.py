"""Stage I drift correction of the scan's key frames: bundle adjustment with the phone's VIO as a prior.

A phone's VIO drifts slowly: over a 15 s scan the key frames' poses wander by 0.5-1.5 cm and a
few hundredths of a degree. Points triangulated from key frames of different moments then disagree
by that much, and a performer view registered later against one part of the room inherits that
part's error as a bias common to all its frames (issue 13: 1-3 cm). A plain bundle adjustment
removes the drift only where the images pin it down and slides along the directions they hardly
constrain (plain walls, a nearly straight walk); here the VIO stays in the problem as what it is
good at, the *relative* motion between consecutive key frames:

- unknowns: per key frame a small world-side correction ``C_k`` (rotation vector ``w_k`` about the
  first key frame's centre ``p0``, translation ``t_k``), and every 3D point;
  corrected pose ``R'_k = exp(w_k) R_k``, ``c'_k = exp(w_k) (c_k - p0) + p0 + t_k``;
- reprojection of every observation of the triangulated model (pixels / ``reproj_sigma_px``, Huber);
- the drift as a random walk: ``(C_{k+1} - C_k)`` divided by the spread VIO drift reaches in the
  time between the two key frames (``drift_m_per_10s`` / ``drift_deg_per_10s`` times
  ``sqrt(dt / 10 s)``; tilt drifts ``tilt_ratio`` as much as yaw: gravity keeps it);
- the world stays the capture's: ``C_0`` (the first key frame, where the VIO world is set) held at
  zero (``anchor_m`` / ``anchor_deg``).

It is solved as one sparse non-linear least squares (SciPy, finite differences over a known
sparsity pattern). Whether the result is used is decided on evidence the capture itself has:
the RMS reprojection error must fall by at least ``min_adjust_gain``, the corrections must be
plausible for the VIO (no step between consecutive key frames beyond ``max_prior_step`` times
the drift the VIO reaches in that time) and no key frame
may move more than ``max_pose_change_m``. The frames between key frames (the mesh fuses many more)
get the key frames' correction interpolated on SE(3) (:func:`propagate_correction`), so the
sparse model, the mesh and Stage III all live in the same corrected world.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.rotations import rotvec_to_matrix as _rotvecs_to_matrices
from embodmocap.geometry.transforms import invert_T

if TYPE_CHECKING:
    from embodmocap.scene.config import SfmConfig

log = logging.getLogger("embodmocap.scene.sfm")


@dataclass(frozen=True)
class DriftCorrection:
    """Outcome of :func:`adjust_with_vio_prior`.

    Attributes:
        T_world_cam: (K, 4, 4) key frame camera-to-world poses to use: the corrected ones when
            ``accepted``, else the capture's.
        accepted: whether the correction passed the checks.
        reason: why it was not accepted ("" when it was).
        figures: ``rms_before_px``, ``rms_after_px``, ``gain``, ``prior_rms``, ``prior_max``, ``median_change_m``,
            ``max_change_m``, ``max_change_deg``, ``observations``, ``iterations``, ``seconds``.
    """

    T_world_cam: NDArray[np.float64]
    accepted: bool
    reason: str = ""
    figures: dict = field(default_factory=dict)


def apply_correction(params: NDArray, T: NDArray, p0: NDArray) -> NDArray[np.float64]:
    """Poses ``T`` (K, 4, 4) corrected by world-side ``params`` (K, 6) = (rotation vector about
    ``p0`` (3,), translation) -> (K, 4, 4)."""
    R = _rotvecs_to_matrices(params[:, :3])
    out = np.array(T, dtype=np.float64, copy=True)
    out[:, :3, :3] = R @ T[:, :3, :3]
    out[:, :3, 3] = np.einsum("kij,kj->ki", R, T[:, :3, 3] - p0) + p0 + params[:, 3:]
    return out


def _observations(rec, ids: list[int]):
    """(image index (N,), point index (N,), xy (N, 2) COLMAP pixels, points (P, 3), PINHOLE params)."""
    pid_index: dict[int, int] = {}
    img, pt, xy = [], [], []
    for k, image_id in enumerate(ids):
        for p in rec.image(image_id).points2D:
            if p.has_point3D():
                img.append(k)
                pt.append(pid_index.setdefault(int(p.point3D_id), len(pid_index)))
                xy.append(p.xy)
    X = np.zeros((len(pid_index), 3))
    for pid, j in pid_index.items():
        X[j] = rec.point3D(pid).xyz
    cam = rec.cameras[rec.image(ids[0]).camera_id]
    return (np.asarray(img, np.int64), np.asarray(pt, np.int64), np.asarray(xy, np.float64).reshape(-1, 2), X,
            np.asarray(cam.params, dtype=np.float64)[:4])


def adjust_with_vio_prior(rec, ids: list[int], T_prior: NDArray, times_s: NDArray, cfg: SfmConfig) -> DriftCorrection:
    """Drift-corrected key frame poses from the triangulated model ``rec`` (pycolmap Reconstruction,
    poses = ``T_prior``), the capture's poses as a random-walk prior (module docstring).

    Args:
        rec: the model triangulated with ``T_prior`` held fixed (not modified).
        ids: (K,) COLMAP image ids of the key frames, in time order.
        T_prior: (K, 4, 4) the capture's camera-to-world poses of ``ids``.
        times_s: (K,) their capture times, seconds, non-decreasing.
        cfg: the ``SfmConfig`` (fields ``drift_*``, ``tilt_ratio``, ``anchor_*``, ``reproj_sigma_px``,
            ``min_adjust_gain``, ``max_prior_step``, ``max_pose_change_m``, ``adjust_max_iterations``).
    """
    t0 = time.perf_counter()
    T_prior = np.asarray(T_prior, dtype=np.float64)
    n = len(ids)
    img, pt, xy, X0, (fx, fy, cx, cy) = _observations(rec, ids)
    p0 = T_prior[0, :3, 3].copy()
    R0, c0 = T_prior[:, :3, :3], T_prior[:, :3, 3]
    dt = np.maximum(np.diff(np.asarray(times_s, dtype=np.float64)), 1e-3)
    walk = np.sqrt(dt / 10.0)[:, None]
    rot = np.deg2rad(cfg.drift_deg_per_10s) * np.array([cfg.tilt_ratio, cfg.tilt_ratio, 1.0])
    sig_walk = np.hstack([walk * rot, walk * np.full(3, cfg.drift_m_per_10s)])  # (K-1, 6)
    sig_walk = np.maximum(sig_walk, np.array([1e-5] * 3 + [1e-4] * 3))  # key frames a moment apart
    sig_anchor = np.array([np.deg2rad(cfg.anchor_deg)] * 3 + [cfg.anchor_m] * 3)
    npts, nobs = len(X0), len(img)

    def reproj(q, X, jac=False):
        """(N, 2) pixel residuals; with ``jac`` also (N, 2, 6) and (N, 2, 3) Jacobians against the
        key frame's correction and the point (the rotation taken as a small world-side turn about
        ``p0`` on top of the current one: exact at q = 0, and the corrections stay far below 1 deg)."""
        Rw = _rotvecs_to_matrices(q[:, :3])
        R = Rw @ R0
        c = np.einsum("kij,kj->ki", Rw, c0 - p0) + p0 + q[:, 3:]
        RT = np.swapaxes(R, 1, 2)[img]  # (N, 3, 3)
        Xn = X[pt]
        Xc = (RT @ (Xn - c[img])[:, :, None])[:, :, 0]  # R^T (X - c)
        z = np.where(np.abs(Xc[:, 2]) < 1e-6, 1e-6, Xc[:, 2])
        r = np.column_stack([fx * Xc[:, 0] / z + cx, fy * Xc[:, 1] / z + cy]) - xy
        if not jac:
            return r
        P = np.zeros((len(z), 2, 3))
        P[:, 0, 0], P[:, 0, 2] = fx / z, -fx * Xc[:, 0] / z**2
        P[:, 1, 1], P[:, 1, 2] = fy / z, -fy * Xc[:, 1] / z**2
        Jp = P @ RT  # d pixel / d X
        v = Xn - p0
        skew = np.zeros((len(z), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
        skew -= np.swapaxes(skew, 1, 2)
        return r, np.concatenate([Jp @ skew, -Jp], axis=2), Jp

    # The prior is linear in the corrections: residual A @ q.ravel() (anchor, then random-walk steps).
    A = np.zeros((6 * n, 6 * n))
    A[np.arange(6), np.arange(6)] = 1.0 / sig_anchor
    r_idx = 6 + np.arange(6 * (n - 1))
    A[r_idx, np.arange(6 * (n - 1)) + 6] = 1.0 / sig_walk.ravel()
    A[r_idx, np.arange(6 * (n - 1))] = -1.0 / sig_walk.ravel()
    q0 = np.zeros((n, 6))
    rms0 = float(np.sqrt(np.mean(np.sum(reproj(q0, X0) ** 2, axis=1))))
    q, X, iterations = _levenberg_marquardt(reproj, A, q0, X0, img, pt, cfg)
    rms1 = float(np.sqrt(np.mean(np.sum(reproj(q, X) ** 2, axis=1))))
    T_adj = apply_correction(q, T_prior, p0)
    change = np.linalg.norm(T_adj[:, :3, 3] - c0, axis=1)
    turn = np.degrees(np.linalg.norm(q[:, :3], axis=1))
    steps = np.abs((q[1:] - q[:-1]) / sig_walk)  # whitened random-walk steps (K-1, 6)
    prior_rms = float(np.sqrt(np.mean(steps**2))) if n > 1 else 0.0
    prior_max = float(steps.max()) if n > 1 else 0.0
    gain = 1.0 - rms1 / max(rms0, 1e-12)
    figures = {
        "rms_before_px": round(rms0, 4), "rms_after_px": round(rms1, 4), "gain": round(gain, 4),
        "prior_rms": round(prior_rms, 3), "prior_max": round(prior_max, 3),
        "median_change_m": round(float(np.median(change)), 5),
        "max_change_m": round(float(change.max()), 5), "max_change_deg": round(float(turn.max()), 4),
        "observations": int(nobs), "iterations": int(iterations), "seconds": round(time.perf_counter() - t0, 3),
    }
    reason = ""
    if not np.all(np.isfinite(T_adj)):
        reason = "the adjustment diverged"
    elif gain < cfg.min_adjust_gain:
        reason = f"it lowers the reprojection error only {100 * gain:.1f} % (< {100 * cfg.min_adjust_gain:.1f} %)"
    elif prior_max > cfg.max_prior_step:
        reason = (f"its corrections disagree with the VIO (a step between key frames of {prior_max:.1f} times the "
                  f"drift VIO reaches in that time, > {cfg.max_prior_step})")
    elif change.max() > cfg.max_pose_change_m:
        reason = f"it moves a key frame {100 * change.max():.1f} cm (> {100 * cfg.max_pose_change_m:.1f} cm)"
    if reason:
        log.info("sparse model: drift correction not used: %s; keeping the capture's poses", reason)
        return DriftCorrection(T_prior.copy(), False, reason, figures)
    log.info("sparse model: drift correction of the key frames %.2f cm median, %.2f cm max, reprojection %.3f -> "
             "%.3f px (%.1f s)", 100 * figures["median_change_m"], 100 * figures["max_change_m"], rms0, rms1,
             figures["seconds"])
    return DriftCorrection(T_adj, True, "", figures)


_HUBER = 2.0  # observations beyond this many reprojection sigmas count linearly


def _levenberg_marquardt(reproj, A: NDArray, q: NDArray, X: NDArray, img: NDArray, pt: NDArray, cfg: SfmConfig):
    """Minimise the Huber-robust reprojection cost of ``reproj(q, X)`` (N, 2) plus ``|A q|^2`` over
    the key frames' corrections ``q`` (K, 6) and the points ``X`` (P, 3): Gauss-Newton with the
    points eliminated (Schur complement on the key frames' 6K unknowns) and Levenberg-Marquardt
    damping on that reduced system; each observation sees one key frame and one point, so the
    normal equations are sums of small per-observation blocks. Returns (q, X, iterations)."""
    n, npts = len(q), len(X)
    sigma = cfg.reproj_sigma_px
    H_prior = A.T @ A

    def cost(q_, X_):
        e = np.linalg.norm(reproj(q_, X_), axis=1) / sigma
        rho = np.where(e <= _HUBER, e**2, 2 * _HUBER * e - _HUBER**2)
        prior = A @ q_.ravel()
        return float(rho.sum() + prior @ prior)

    # Pairs of observations of the same point (each with itself too): where the points' elimination
    # couples two key frames. Fixed structure, so found once.
    nobs = len(img)
    order = np.argsort(pt, kind="stable")
    track = np.bincount(pt, minlength=npts)
    start = np.concatenate([[0], np.cumsum(track)[:-1]])
    reps = track[pt[order]]
    a_pos = np.repeat(np.arange(nobs), reps)
    offset = np.arange(int(reps.sum())) - np.repeat(np.cumsum(reps) - reps, reps)
    pair_a, pair_b = order[a_pos], order[start[pt[order][a_pos]] + offset]
    pair_key = img[pair_a] * n + img[pair_b]
    by_key = np.argsort(pair_key, kind="stable")  # pairs in key order: each chunk sums runs of equal keys
    pair_a, pair_b, pair_key = pair_a[by_key], pair_b[by_key], pair_key[by_key]
    by_img, by_pt = _GroupSum(img, n), _GroupSum(pt, npts)
    lam, it, current = 1e-4, 0, cost(q, X)
    for it in range(1, cfg.adjust_max_iterations + 1):
        r, Jc, Jp = reproj(q, X, jac=True)
        e = np.linalg.norm(r, axis=1) / sigma
        w = (np.where(e <= _HUBER, 1.0, _HUBER / np.maximum(e, 1e-12)) / sigma**2)[:, None, None]
        wJc, wJp = w * Jc, w * Jp
        Hcc = by_img(np.swapaxes(wJc, 1, 2) @ Jc)
        Hpp = by_pt(np.swapaxes(wJp, 1, 2) @ Jp)
        Hcp = np.swapaxes(wJc, 1, 2) @ Jp  # (N, 6, 3)
        gc = by_img((np.swapaxes(wJc, 1, 2) @ r[:, :, None])[:, :, 0])
        gp = by_pt((np.swapaxes(wJp, 1, 2) @ r[:, :, None])[:, :, 0])
        H = H_prior.copy()
        for k in range(n):
            H[6 * k:6 * k + 6, 6 * k:6 * k + 6] += Hcc[k]
        g = gc.ravel() + H_prior @ q.ravel()
        # Points are well conditioned (triangulation angle >= min_tri_angle_deg); a tiny ridge guards
        # the odd near-degenerate one.
        ridge = 1e-9 * np.trace(Hpp, axis1=1, axis2=2)[:, None, None] + 1e-12
        Hinv = np.linalg.inv(Hpp + ridge * np.eye(3))
        HcpHinv = Hcp @ Hinv[pt]  # (N, 6, 3)
        coupling = np.zeros((n * n, 36))
        for lo in range(0, len(pair_a), 200_000):  # chunks keep the (pairs, 6, 6) products small
            sl = slice(lo, lo + 200_000)
            blocks = (HcpHinv[pair_a[sl]] @ np.swapaxes(Hcp[pair_b[sl]], 1, 2)).reshape(-1, 36)
            keys = pair_key[sl]
            first = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
            coupling[keys[first]] += np.add.reduceat(blocks, first, axis=0)
        S = H - coupling.reshape(n, n, 6, 6).transpose(0, 2, 1, 3).reshape(6 * n, 6 * n)
        rhs = -(g - by_img((HcpHinv @ gp[pt][:, :, None])[:, :, 0]).ravel())
        done = True
        for _ in range(12):
            try:
                dq = np.linalg.solve(S + lam * np.diag(np.diag(S)), rhs)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            dq = dq.reshape(n, 6)
            dX = -(Hinv @ (gp + by_pt((np.swapaxes(Hcp, 1, 2) @ dq[img][:, :, None])[:, :, 0]))[:, :, None])[:, :, 0]
            q_new, X_new = q + dq, X + dX
            new = cost(q_new, X_new)
            if np.isfinite(new) and new < current:
                # Converged when the cost stalls or the key frames move by less than 0.02 mm / 0.2 urad.
                done = (current - new) < 1e-9 * current or (np.abs(dq[:, 3:]).max() < 2e-5
                                                          and np.abs(dq[:, :3]).max() < 2e-7)
                q, X, current, lam = q_new, X_new, new, max(lam / 3, 1e-8)
                break
            lam *= 5
        if done:  # converged, or no step lowers the cost any more
            break
    return q, X, it


class _GroupSum:
    """Sums of per-item rows by group, ``out[g] = sum(values[index == g])``, for a fixed index
    (sorted once, then one ``np.add.reduceat`` per call)."""

    def __init__(self, index: NDArray, size: int):
        self.order = np.argsort(index, kind="stable")
        sorted_index = index[self.order]
        self.first = np.flatnonzero(np.r_[True, sorted_index[1:] != sorted_index[:-1]])
        self.groups = sorted_index[self.first]
        self.size = size

    def __call__(self, values: NDArray) -> NDArray[np.float64]:
        out = np.zeros((self.size,) + values.shape[1:])
        out[self.groups] = np.add.reduceat(values[self.order], self.first, axis=0)
        return out


def correction_of(T_prior: NDArray, T_fixed: NDArray) -> NDArray[np.float64]:
    """World-side corrections ``C_k = T_fixed[k] @ inverse(T_prior[k])`` (K, 4, 4) of corrected poses."""
    return np.asarray(T_fixed, dtype=np.float64) @ invert_T(np.asarray(T_prior, dtype=np.float64))


def propagate_correction(t_key: NDArray, C_key: NDArray, t: NDArray, T: NDArray) -> NDArray[np.float64]:
    """The key frames' drift correction carried over to other frames of the same capture.

    A frame between key frames k and k+1 (by time) gets the rotation slerped between the world-side
    corrections ``C_k``'s and ``C_{k+1}``'s and the shift of its own camera centre interpolated
    linearly between what ``C_k`` and ``C_{k+1}`` do to it (SE(3) as SO(3) x R^3, like
    :mod:`embodmocap.geometry.interpolate`); before the first / after the last key frame the
    nearest key frame's correction applies. A key frame itself comes out as ``C_k @ T_k``.

    Args:
        t_key: (K,) key frame times (or frame indices), strictly increasing.
        C_key: (K, 4, 4) their world-side corrections (:func:`correction_of`).
        t: (M,) times of the frames to correct (same unit as ``t_key``).
        T: (M, 4, 4) their capture poses (camera-to-world).

    Returns:
        (M, 4, 4) corrected camera-to-world poses.
    """
    from scipy.spatial.transform import Rotation, Slerp

    from embodmocap.geometry.interpolate import bracket

    T = np.asarray(T, dtype=np.float64)
    C = np.asarray(C_key, dtype=np.float64)
    t_key = np.asarray(t_key, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if len(t_key) == 1:
        return C[0] @ T
    i0, w, _ = bracket(t_key, t)
    R_C = Slerp(t_key, Rotation.from_matrix(C[:, :3, :3]))(np.clip(t, t_key[0], t_key[-1])).as_matrix()
    c = T[:, :3, 3]
    shift0 = np.einsum("mij,mj->mi", C[i0, :3, :3], c) + C[i0, :3, 3] - c
    shift1 = np.einsum("mij,mj->mi", C[i0 + 1, :3, :3], c) + C[i0 + 1, :3, 3] - c
    out = T.copy()
    out[:, :3, :3] = R_C @ T[:, :3, :3]
    out[:, :3, 3] = c + (1.0 - w)[:, None] * shift0 + w[:, None] * shift1
    return out


def corrected_poses(sfm_dir, t: NDArray, T: NDArray) -> NDArray[np.float64]:
    """Capture poses ``T`` (M, 4, 4) at times ``t`` (M,) seconds with the drift correction the sparse
    model in ``sfm_dir`` applied to its key frames (``summary.json`` ``drift_correction``), carried
    over by :func:`propagate_correction`; ``T`` unchanged when the model has no accepted correction."""
    return carry_drift(read_drift_correction(sfm_dir), t, T)


def read_drift_correction(sfm_dir) -> dict | None:
    """The sparse model's ``summary.json`` ``drift_correction`` record (None without one)."""
    import json
    from pathlib import Path

    path = Path(sfm_dir) / "summary.json"
    return json.loads(path.read_text()).get("drift_correction") if path.is_file() else None


def carry_drift(drift: dict | None, t: NDArray, T: NDArray) -> NDArray[np.float64]:
    """Capture poses ``T`` (M, 4, 4) at times ``t`` (M,) seconds with a sparse model's key-frame
    drift correction (``summary.json`` ``drift_correction``: ``accepted``, ``times_s``,
    ``T_correction``) carried over by :func:`propagate_correction`; a copy of ``T`` when there
    is no accepted correction."""
    if not drift or not drift.get("accepted"):
        return np.asarray(T, dtype=np.float64).copy()
    C = np.asarray(drift["T_correction"], dtype=np.float64).reshape(-1, 4, 4)
    return propagate_correction(np.asarray(drift["times_s"], dtype=np.float64), C, t, T)


def _rms_reprojection(rec) -> float:
    """RMS reprojection error (pixels) over every observation of a 3D point in the model."""
    sq, n = 0.0, 0
    xyz = {pid: p.xyz for pid, p in rec.points3D.items()}
    for image in rec.images.values():
        obs = [(p.xy, xyz[p.point3D_id]) for p in image.points2D if p.has_point3D()]
        if not obs:
            continue
        xy = np.array([o[0] for o in obs])
        X = np.array([o[1] for o in obs])
        P = image.cam_from_world().matrix()
        cam = rec.cameras[image.camera_id]
        Xc = X @ P[:, :3].T + P[:, 3]
        proj = np.asarray(cam.img_from_cam(Xc), dtype=np.float64)[:, :2]
        sq += float(np.sum((proj - xy) ** 2))
        n += len(xy)
    return float(np.sqrt(sq / max(n, 1)))


def _fit_similarity(T_from: NDArray, T_to: NDArray) -> NDArray[np.float64]:
    """(4, 4) similarity ``S = [s R | t]`` putting cameras ``T_from`` (K, 4, 4) on ``T_to`` (K, 4, 4):
    R the chordal mean of the per-camera rotations (orientations fix the tilt, which centres on a
    nearly level path would not), then s and t by least squares on the centres."""
    M = np.einsum("kij,klj->il", T_to[:, :3, :3], T_from[:, :3, :3])  # sum R_to R_from^T
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    a = T_from[:, :3, 3] - T_from[:, :3, 3].mean(0)
    b = T_to[:, :3, 3] - T_to[:, :3, 3].mean(0)
    s = float(np.sum((a @ R.T) * b) / max(np.sum(a * a), 1e-12))
    S = np.eye(4)
    S[:3, :3] = s * R
    S[:3, 3] = T_to[:, :3, 3].mean(0) - s * R @ T_from[:, :3, 3].mean(0)
    return S
