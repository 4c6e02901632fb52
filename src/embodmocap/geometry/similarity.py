"""Similarity transforms (scale, rotation, translation): weighted Umeyama fit and helpers.

A similarity maps a point ``x`` to ``s R x + t`` (``s > 0``, ``R`` a rotation). As a 4x4 matrix
``S = [[s R, t], [0, 1]]``, so composition is a matrix product and a chain of chunk alignments is
``S_0k = S_01 @ S_12 @ ... @ S_(k-1)k``. Every function accepts any leading batch shape ``...``.

:func:`weighted_umeyama` is the closed form of Umeyama (1991) with per-point weights ``w``:
minimise ``sum_i w_i |y_i - (s R x_i + t)|^2``. With ``W = sum w``,
``mu_x = sum w x / W``, ``Sigma = sum w (y - mu_y)(x - mu_x)^T / W = U D V^T``,
``E = diag(1, 1, sign det(U V^T))``: ``R = U E V^T``, ``s = tr(D E) / (sum w |x - mu_x|^2 / W)``,
``t = mu_y - s R mu_x``. With all weights equal this is ``evaluate.metrics.umeyama`` (which calls it).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.rotations import rotvec_between, rotvec_to_matrix

F = NDArray[np.float64]


def weighted_umeyama(src: F, dst: F, weights: F | None = None, with_scale: bool = True) -> tuple[F, F, F]:
    """Least-squares similarity ``dst ~ s R src + t`` with per-point weights.

    Args:
        src: (..., N, 3) points.
        dst: (..., N, 3) corresponding points.
        weights: (..., N) non-negative weights (None: all 1). Points of weight 0 do not count.
        with_scale: fit ``s``; else ``s = 1`` (a rigid fit).

    Returns:
        ``s`` (...), ``R`` (..., 3, 3), ``t`` (..., 3). ``s = 1`` where the weighted source has
        no spread (a single point), ``R = I`` and ``t`` the mean offset where the total weight is 0.

    Raises:
        ValueError: mismatched shapes or negative / non-finite weights.
    """
    x = np.asarray(src, dtype=np.float64)
    y = np.asarray(dst, dtype=np.float64)
    if x.shape != y.shape or x.ndim < 2 or x.shape[-1] != 3:
        raise ValueError(f"src and dst must both be (..., N, 3), got {x.shape} and {y.shape}")
    w = np.ones(x.shape[:-1]) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != x.shape[:-1]:
        raise ValueError(f"weights must be {x.shape[:-1]}, got {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weights must be finite and >= 0")
    W = w.sum(axis=-1)  # (...)
    safe = np.where(W > 0, W, 1.0)
    wn = w / safe[..., None]
    mu_x = np.einsum("...n,...nc->...c", wn, x)
    mu_y = np.einsum("...n,...nc->...c", wn, y)
    xc = x - mu_x[..., None, :]
    yc = y - mu_y[..., None, :]
    sigma = np.einsum("...n,...ni,...nj->...ij", wn, yc, xc)  # (..., 3, 3)
    U, D, Vt = np.linalg.svd(sigma)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    E = np.ones(D.shape)
    E[..., 2] = d
    R = (U * E[..., None, :]) @ Vt
    var_x = np.einsum("...n,...n->...", wn, np.sum(xc**2, axis=-1))
    if with_scale:
        s = np.where(var_x > 1e-300, np.sum(D * E, axis=-1) / np.where(var_x > 1e-300, var_x, 1.0), 1.0)
    else:
        s = np.ones(var_x.shape)
    none = W <= 0
    if np.any(none):
        R = np.where(none[..., None, None], np.eye(3), R)
        s = np.where(none, 1.0, s)
    t = mu_y - s[..., None] * np.einsum("...ij,...j->...i", R, mu_x)
    return s, R, t


def robust_umeyama(src: F, dst: F, weights: F | None = None, scale_m: float | None = None,
                   iterations: int = 5) -> tuple[F, F, F, F]:
    """Weighted Umeyama re-weighted (IRLS) with a Cauchy kernel, for correspondences with outliers.

    Args:
        src, dst: (N, 3) points.
        weights: (N,) prior weights (confidences); None = 1.
        scale_m: Cauchy scale in ``dst`` units; None = 1.5 x the weighted median residual of the
            previous iteration (adapts to an unknown unit).
        iterations: re-weighting rounds after the first plain fit.

    Returns:
        ``s``, ``R`` (3, 3), ``t`` (3,) and the final per-point weights (N,) (prior x robust).
    """
    w0 = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    s, R, t = weighted_umeyama(src, dst, w0)
    w = w0
    for _ in range(iterations):
        r = np.linalg.norm(apply_similarity(similarity_matrix(s, R, t), src) - dst, axis=-1)
        c = scale_m if scale_m is not None else 1.5 * max(_weighted_median(r, w0), 1e-12)
        w = w0 / (1.0 + (r / c) ** 2)
        s, R, t = weighted_umeyama(src, dst, w)
    return s, R, t, w


def _weighted_median(x: F, w: F) -> float:
    order = np.argsort(x)
    cw = np.cumsum(w[order])
    if cw[-1] <= 0:
        return float(np.median(x))
    return float(x[order][np.searchsorted(cw, 0.5 * cw[-1])])


def similarity_matrix(s: F, R: F, t: F) -> F:
    """(..., 4, 4) matrix ``[[s R, t], [0, 1]]`` of a similarity: ``s`` (...), ``R`` (..., 3, 3), ``t`` (..., 3)."""
    s = np.asarray(s, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    out = np.zeros(R.shape[:-2] + (4, 4))
    out[..., :3, :3] = s[..., None, None] * R
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def similarity_parts(S: F) -> tuple[F, F, F]:
    """``s`` (...), ``R`` (..., 3, 3), ``t`` (..., 3) of similarity matrices (..., 4, 4) (``s`` from the determinant)."""
    S = np.asarray(S, dtype=np.float64)
    A = S[..., :3, :3]
    s = np.cbrt(np.linalg.det(A))
    return s, A / s[..., None, None], S[..., :3, 3].copy()


def apply_similarity(S: F, points: F) -> F:
    """Points (..., N, 3) mapped by similarity matrices (..., 4, 4) (broadcast over ``...``)."""
    S = np.asarray(S, dtype=np.float64)
    return np.einsum("...ij,...nj->...ni", S[..., :3, :3], points) + S[..., None, :3, 3]


def transform_poses(S: F, T_world_cam: F) -> F:
    """Camera poses (..., 4, 4) (camera-to-world, rigid) moved into the frame a similarity ``S``
    (4, 4) maps to: the rotation becomes ``R_S R``, the centre ``s R_S c + t``; the pose stays rigid
    (the camera frame's unit becomes the new world's, so camera-frame points scale by ``s``)."""
    s, R, t = similarity_parts(S)
    T = np.asarray(T_world_cam, dtype=np.float64)
    out = np.array(T, copy=True)
    out[..., :3, :3] = R @ T[..., :3, :3]
    out[..., :3, 3] = s * np.einsum("ij,...j->...i", R, T[..., :3, 3]) + t
    return out


def rotation_between(a: F, b: F) -> F:
    """(3, 3) smallest rotation taking unit direction ``a`` (3,) onto ``b`` (3,) (Rodrigues);
    a half turn about an axis orthogonal to ``a`` when they are opposite."""
    return rotvec_to_matrix(rotvec_between(a, b))


def mean_rotation(Rs: F, weights: F | None = None) -> F:
    """(3, 3) chordal L2 mean of rotations (N, 3, 3): the rotation nearest the (weighted) sum."""
    Rs = np.asarray(Rs, dtype=np.float64)
    w = np.ones(len(Rs)) if weights is None else np.asarray(weights, dtype=np.float64)
    M = np.einsum("n,nij->ij", w, Rs)
    U, _, Vt = np.linalg.svd(M)
    E = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ E @ Vt
