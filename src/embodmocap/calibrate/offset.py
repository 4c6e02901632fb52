"""Initial yaw-only offset of a view's VIO world in the scene's world (Stage III).

Both worlds are gravity-aligned (Z up) and metric, so they differ by a rotation about Z and a
translation: ``x_world = s * R_z(yaw) @ x_vio + t`` with ``s = 1`` unless a free scale is asked
for. Given the VIO camera centres of registered frames and their registered (scene) centres, the
closed form is a weighted 2D Procrustes problem in XY for the yaw; the translation follows from
the weighted means (Z included) and the scale from the centred 3D spreads.

Registration can fail badly on a few frames (repeated texture, a frame full of performer), so
:func:`robust_yaw_offset` first finds the consensus by RANSAC over 2-frame samples (two centres
fix yaw, translation and scale), refits on the inliers, then reweights the residuals with a robust
kernel (iteratively reweighted least squares).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.transforms import rot_z

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class YawOffset:
    """``T_world_vio``: a rotation about Z, a translation and (optionally) a scale.

    Attributes:
        yaw_rad: rotation about the world Z axis, radians, in (-pi, pi].
        t: (3,) translation, metres (where the VIO origin lands in the world).
        scale: VIO-to-world scale (1 for a rigid offset).
    """

    yaw_rad: float
    t: NDArray[np.float64]
    scale: float = 1.0

    def __post_init__(self) -> None:
        t = np.array(self.t, dtype=np.float64, copy=True).reshape(3)
        t.setflags(write=False)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "yaw_rad", float(self.yaw_rad))
        object.__setattr__(self, "scale", float(self.scale))

    @property
    def R(self) -> NDArray[np.float64]:
        """(3, 3) rotation about Z by ``yaw_rad``."""
        return rot_z(self.yaw_rad)

    @property
    def T(self) -> NDArray[np.float64]:
        """(4, 4) ``T_world_vio`` = [[scale * R, t], [0, 1]] (a similarity when scale != 1)."""
        T = np.eye(4)
        T[:3, :3] = self.scale * self.R
        T[:3, 3] = self.t
        return T

    def apply_points(self, x_vio: NDArray) -> NDArray[np.float64]:
        """(..., 3) VIO-world points -> scene-world points."""
        return self.scale * np.asarray(x_vio, dtype=np.float64) @ self.R.T + self.t

    def apply(self, T_vio_cam: NDArray) -> NDArray[np.float64]:
        """(..., 4, 4) camera-to-VIO poses -> camera-to-world poses.

        The rotation stays orthonormal under a free scale: only camera centres are scaled.
        """
        T_vio_cam = np.asarray(T_vio_cam, dtype=np.float64)
        out = np.array(T_vio_cam, copy=True)
        out[..., :3, :3] = self.R @ T_vio_cam[..., :3, :3]
        out[..., :3, 3] = self.apply_points(T_vio_cam[..., :3, 3])
        return out


def fit_yaw_offset(vio_centres: NDArray, world_centres: NDArray, weights: NDArray | None = None,
                   free_scale: bool = False) -> YawOffset:
    """Weighted least-squares yaw (+ translation, + optional scale) mapping VIO onto world points.

    Minimises ``sum_i w_i |s R_z(yaw) v_i + t - w_i|^2`` in closed form: the yaw by 2D Procrustes on
    the centred XY coordinates (Z does not depend on the yaw), the scale (if free) from the centred
    3D coordinates, the translation from the weighted means.

    Args:
        vio_centres: (N, 3) points in the VIO world (e.g. camera centres), metres.
        world_centres: (N, 3) the same points in the scene's world.
        weights: (N,) non-negative weights, or None for all ones.
        free_scale: also fit a scale; otherwise it is 1.

    Raises:
        ValueError: shapes differ, fewer than 2 points with weight, or no horizontal spread (the
            yaw is then undetermined).
    """
    v, w = _pair(vio_centres, world_centres)
    wt = np.ones(len(v)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if wt.shape != (len(v),) or np.any(wt < 0) or not np.all(np.isfinite(wt)):
        raise ValueError(f"weights must be ({len(v)},) non-negative and finite, got shape {wt.shape}")
    if np.sum(wt > 0) < 2:
        raise ValueError("a yaw offset needs at least 2 points with positive weight")
    wn = wt / wt.sum()
    mv, mw = wn @ v, wn @ w
    a, b = v - mv, w - mw
    # Procrustes in 2D: the yaw maximising sum w <R a, b> is atan2(sum w a x b, sum w a . b).
    cross = wn @ (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    dot = wn @ (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])
    spread = wn @ np.sum(a[:, :2] ** 2, axis=1)
    if spread < 1e-12:
        raise ValueError("the VIO points have no horizontal spread: the yaw is undetermined")
    yaw = float(np.arctan2(cross, dot))
    R = rot_z(yaw)
    scale = 1.0
    if free_scale:
        # s = sum w <R a, b> / sum w |a|^2 over all three axes (Z scales too).
        scale = float((wn @ np.sum((a @ R.T) * b, axis=1)) / (wn @ np.sum(a ** 2, axis=1)))
    return YawOffset(yaw, mw - scale * (R @ mv), scale)


def residuals(offset: YawOffset, vio_centres: NDArray, world_centres: NDArray) -> NDArray[np.float64]:
    """(N,) distances, metres, between the mapped VIO points and the world points."""
    v, w = _pair(vio_centres, world_centres)
    return np.linalg.norm(offset.apply_points(v) - w, axis=1)


@dataclass(frozen=True)
class RobustOffsetConfig:
    """Settings of :func:`robust_yaw_offset`."""

    inlier_threshold_m: float = 0.15
    """A frame is an inlier when its mapped VIO centre lies within this distance (metres) of its
    registered centre. Registration errors are a few centimetres and VIO drift over a sequence a
    few more; wrong registrations are off by decimetres to metres."""
    ransac_iterations: int = 500
    """Random 2-frame samples tried (fewer when there are fewer distinct pairs: then all are)."""
    min_sample_spread_m: float = 0.05
    """Samples whose two VIO centres are closer than this horizontally are skipped (their yaw is
    ill-conditioned)."""
    kernel: Literal["cauchy", "huber"] = "cauchy"
    """Robust kernel of the reweighting: Cauchy (weights fall to ~0 for gross errors) or Huber."""
    kernel_scale_m: float = 0.03
    """Scale of the robust kernel, metres (residuals well below it keep full weight)."""
    irls_iterations: int = 10
    """Reweighting rounds after RANSAC (each a closed-form weighted refit)."""
    free_scale: bool = False
    """Also fit a VIO-to-world scale (normally 1: both worlds are metric)."""
    seed: int = 0
    """Seed of the RANSAC sampling."""
    orientation_weight_m: float = 2.0
    """:func:`chain_yaw_offset`: weight of each frame's camera orientation in the yaw, as a lever
    length in metres (the horizontal camera axes, scaled by it, join the centres in the fit).
    Registered orientations are good to ~0.1-0.3 deg while centres scatter by centimetres, so a
    lever of a few metres lets the whole chain's orientations fix the yaw. 0 = centres only."""


@dataclass(frozen=True)
class RobustYawFit:
    """Result of :func:`robust_yaw_offset`.

    Attributes:
        offset: the fitted ``T_world_vio``.
        inliers: (N,) bool, residual below the inlier threshold.
        residuals_m: (N,) distances between mapped VIO centres and registered centres, metres.
        weights: (N,) final robust weights (0 for outliers).
    """

    offset: YawOffset
    inliers: NDArray[np.bool_]
    residuals_m: NDArray[np.float64]
    weights: NDArray[np.float64]

    @property
    def num_inliers(self) -> int:
        return int(np.sum(self.inliers))


def robust_yaw_offset(vio_centres: NDArray, world_centres: NDArray,
                      cfg: RobustOffsetConfig = RobustOffsetConfig(),
                      weights: NDArray | None = None) -> RobustYawFit:
    """Yaw offset robust to wrong registrations: RANSAC (2-frame samples), refit, then IRLS.

    Args:
        vio_centres: (N, 3) VIO camera centres of the registered frames.
        world_centres: (N, 3) their registered centres in the scene's world.
        cfg: settings.
        weights: (N,) optional prior weights (e.g. from inlier counts), multiplied into the refits.

    Raises:
        ValueError: fewer than 2 frames, or no two frames spread enough to fix the yaw.
    """
    v, w = _pair(vio_centres, world_centres)
    prior = np.ones(len(v)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if prior.shape != (len(v),):
        raise ValueError(f"weights must be ({len(v)},), got {prior.shape}")
    best = _ransac(v, w, cfg)
    inl = residuals(best, v, w) < cfg.inlier_threshold_m
    # The 2-frame model is noisy: refit on its inliers until the inlier set settles.
    for _ in range(5):
        if inl.sum() < 2:
            break
        best = _fit_or_keep(v, w, prior * inl, cfg.free_scale, best)
        new = residuals(best, v, w) < cfg.inlier_threshold_m
        if np.array_equal(new, inl):
            break
        inl = new
    wk = prior * inl
    for _ in range(cfg.irls_iterations):
        r = residuals(best, v, w)
        gate = r < cfg.inlier_threshold_m
        wk = prior * gate * _kernel_weights(r, cfg.kernel, cfg.kernel_scale_m)
        if np.sum(wk > 0) < 2:
            break
        best = _fit_or_keep(v, w, wk, cfg.free_scale, best)
    r = residuals(best, v, w)
    inl = r < cfg.inlier_threshold_m
    wk = prior * inl * _kernel_weights(r, cfg.kernel, cfg.kernel_scale_m)
    log.debug("yaw offset: %d of %d inliers, yaw %.3f deg, median residual %.3f m", inl.sum(), len(v),
              np.degrees(best.yaw_rad), float(np.median(r[inl])) if inl.any() else float("nan"))
    return RobustYawFit(best, inl, r, wk)


def _kernel_weights(r: NDArray, kernel: str, scale: float) -> NDArray[np.float64]:
    """IRLS weights of a robust kernel: Cauchy 1 / (1 + (r/c)^2), Huber min(1, c / r)."""
    if kernel == "cauchy":
        return 1.0 / (1.0 + (r / scale) ** 2)
    if kernel == "huber":
        return np.minimum(1.0, scale / np.maximum(r, 1e-12))
    raise ValueError(f"unknown kernel {kernel!r}")


def _fit_or_keep(v, w, weights, free_scale: bool, fallback: YawOffset) -> YawOffset:
    try:
        return fit_yaw_offset(v, w, weights, free_scale)
    except ValueError:  # inliers without horizontal spread: keep the previous model
        return fallback


def _ransac(v: NDArray, w: NDArray, cfg: RobustOffsetConfig) -> YawOffset:
    """Best 2-frame model by inlier count (ties: smaller truncated squared error), vectorised over
    all samples at once."""
    n = len(v)
    if n < 2:
        raise ValueError("a yaw offset needs at least 2 registered frames")
    i, j = _samples(n, cfg.ransac_iterations, cfg.seed)
    dv, dw = v[j] - v[i], w[j] - w[i]
    ok = np.linalg.norm(dv[:, :2], axis=1) >= cfg.min_sample_spread_m
    if not ok.any():
        raise ValueError(f"no two registered frames lie {cfg.min_sample_spread_m} m apart horizontally: "
                         "the yaw is undetermined")
    i, j, dv, dw = i[ok], j[ok], dv[ok], dw[ok]
    yaw = np.arctan2(dv[:, 0] * dw[:, 1] - dv[:, 1] * dw[:, 0], dv[:, 0] * dw[:, 0] + dv[:, 1] * dw[:, 1])
    scale = np.linalg.norm(dw, axis=1) / np.linalg.norm(dv, axis=1) if cfg.free_scale else np.ones(len(i))
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((len(i), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    # Translation from the sample's midpoint (symmetric in the two frames).
    mv, mw = (v[i] + v[j]) / 2, (w[i] + w[j]) / 2
    t = mw - scale[:, None] * np.einsum("sab,sb->sa", R, mv)
    mapped = scale[:, None, None] * np.einsum("sab,nb->sna", R, v) + t[:, None]  # (S, N, 3)
    r2 = np.sum((mapped - w[None]) ** 2, axis=-1)
    thr2 = cfg.inlier_threshold_m ** 2
    count = np.sum(r2 < thr2, axis=1)
    cost = np.sum(np.minimum(r2, thr2), axis=1)
    k = np.lexsort((cost, -count))[0]
    return YawOffset(float(yaw[k]), t[k], float(scale[k]))


def _samples(n: int, iterations: int, seed: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Index pairs i < j: all of them when there are at most ``iterations``, else random ones."""
    if n * (n - 1) // 2 <= iterations:
        i, j = np.triu_indices(n, 1)
        return i.astype(np.int64), j.astype(np.int64)
    rng = np.random.default_rng(seed)
    i = rng.integers(0, n, iterations)
    j = (i + rng.integers(1, n, iterations)) % n  # never equal to i
    return i, j


def _pair(a: NDArray, b: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape != b.shape:
        raise ValueError(f"expected two (N, 3) point sets, got {a.shape} and {b.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError("points must be finite")
    return a, b


def fit_yaw_offset_poses(T_vio_cam: NDArray, T_world_cam: NDArray, weights: NDArray | None = None,
                         orientation_weight_m: float = 2.0) -> YawOffset:
    """Least-squares rigid yaw offset from whole camera poses: centres and orientations.

    Minimises ``sum_i w_i (|R v_i + t - c_i|^2 + L^2 sum_k |R a_ik - b_ik|^2)`` where ``v_i``,
    ``c_i`` are the VIO and registered camera centres, ``a_ik``, ``b_ik`` the horizontal parts of
    the camera's x and z axes in each world and ``L = orientation_weight_m``. Closed form: the
    direction pairs only add to the 2D Procrustes sums of the yaw; the translation follows from
    the weighted means of the centres.

    Args:
        T_vio_cam: (N, 4, 4) VIO camera-to-world poses.
        T_world_cam: (N, 4, 4) registered camera-to-world poses (scene world).
        weights: (N,) non-negative weights (None = all ones).
        orientation_weight_m: lever length ``L``, metres (0 = centres only).
    """
    A = np.asarray(T_vio_cam, dtype=np.float64).reshape(-1, 4, 4)
    B = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
    v, w = _pair(A[:, :3, 3], B[:, :3, 3])
    wt = np.ones(len(v)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if wt.shape != (len(v),) or np.any(wt < 0) or not np.all(np.isfinite(wt)) or wt.sum() <= 0:
        raise ValueError(f"weights must be ({len(v)},) non-negative, finite and not all 0")
    wn = wt / wt.sum()
    mv, mw = wn @ v, wn @ w
    a, b = v - mv, w - mw
    cross = wn @ (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    dot = wn @ (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])
    L2 = float(orientation_weight_m) ** 2
    for k in (0, 2):  # camera x (right) and z (forward): the y axis is nearly vertical
        da, db = A[:, :2, k], B[:, :2, k]
        cross += L2 * (wn @ (da[:, 0] * db[:, 1] - da[:, 1] * db[:, 0]))
        dot += L2 * (wn @ (da[:, 0] * db[:, 0] + da[:, 1] * db[:, 1]))
    if abs(cross) + abs(dot) < 1e-15:
        raise ValueError("neither the centres nor the orientations fix the yaw")
    yaw = float(np.arctan2(cross, dot))
    return YawOffset(yaw, mw - rot_z(yaw) @ mv, 1.0)


def chain_yaw_offset(T_vio_cam: NDArray, T_world_cam: NDArray, cfg: RobustOffsetConfig = RobustOffsetConfig(),
                     weights: NDArray | None = None) -> RobustYawFit:
    """The offset of a whole chain of registered frames (after the VIO check): the robust fit of
    :func:`robust_yaw_offset` on the centres finds the inliers and their weights, then the yaw
    and translation are refitted on whole poses (:func:`fit_yaw_offset_poses`, orientations
    included) with those weights, reweighting a few rounds. Falls back to the centres-only fit
    under a free scale or ``orientation_weight_m == 0``.

    Args:
        T_vio_cam: (N, 4, 4) VIO poses of the registered frames.
        T_world_cam: (N, 4, 4) their registered poses.
    """
    A = np.asarray(T_vio_cam, dtype=np.float64).reshape(-1, 4, 4)
    B = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
    fit = robust_yaw_offset(A[:, :3, 3], B[:, :3, 3], cfg, weights)
    if cfg.free_scale or cfg.orientation_weight_m <= 0 or fit.num_inliers < 2:
        return fit
    prior = np.ones(len(A)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    best, wk = fit.offset, fit.weights
    for _ in range(max(cfg.irls_iterations, 1)):
        if np.sum(wk > 0) < 2:
            break
        best = fit_yaw_offset_poses(A, B, wk, cfg.orientation_weight_m)
        r = residuals(best, A[:, :3, 3], B[:, :3, 3])
        wk = prior * (r < cfg.inlier_threshold_m) * _kernel_weights(r, cfg.kernel, cfg.kernel_scale_m)
    r = residuals(best, A[:, :3, 3], B[:, :3, 3])
    inl = r < cfg.inlier_threshold_m
    return RobustYawFit(best, inl, r, prior * inl * _kernel_weights(r, cfg.kernel, cfg.kernel_scale_m))
