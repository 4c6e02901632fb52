"""Resampling time series at other instants: camera poses on SE(3) and 2D keypoints.

Two phones never expose their frames at the same instants: even after sync, view 2's frame k is
taken a fraction of a frame before or after view 1's. To let both views observe the same instant,
view 2's observations are resampled at view 1's times:

- poses (:func:`interp_poses`): rotation by spherical linear interpolation (slerp) between the two
  bracketing samples, translation linearly (the "SE(3) as SO(3) x R^3" interpolation: for a phone
  moving a few centimetres per frame it is indistinguishable from the screw motion and cheaper);
- keypoints (:func:`interp_keypoints`): pixel positions linearly; the confidence of an interpolated
  point is the smaller of its two neighbours' (a point seen in only one neighbour has no partner to
  interpolate with: it takes the nearer neighbour as is when that one saw it, else 0).

Query times outside the samples' span are flagged invalid (confidence 0 / ``valid`` False); the
nearest end sample is returned there so the arrays stay finite.

All functions are vectorised over queries; ``t_src`` must increase strictly.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.rotations import matrix_to_quat, quat_to_matrix, slerp

F = NDArray[np.floating]

#: Queries within this many seconds of a sample (or of the span's ends) count as on it.
TIME_EPS_S = 1e-9


def bracket(t_src: F, t_query: F) -> tuple[NDArray[np.int64], F, NDArray[np.bool_]]:
    """Left sample index, interpolation weight and validity of every query time.

    Args:
        t_src: (N,) strictly increasing sample times, N >= 1.
        t_query: (M,) query times (same unit).

    Returns:
        ``i0`` (M,) int64 in ``0..N-2`` (0 when N == 1), ``w`` (M,) in [0, 1] so that the value at a
        query is ``(1 - w) * x[i0] + w * x[i0 + 1]``, and ``valid`` (M,) bool, the query lies within
        ``[t_src[0], t_src[-1]]`` (outside, ``w`` is clamped so the end sample is returned).
    """
    t_src = np.asarray(t_src, dtype=np.float64)
    t_query = np.asarray(t_query, dtype=np.float64)
    if t_src.ndim != 1 or len(t_src) < 1:
        raise ValueError(f"t_src must be (N >= 1,), got shape {t_src.shape}")
    if np.any(np.diff(t_src) <= 0):
        raise ValueError("t_src must increase strictly")
    valid = (t_query >= t_src[0] - TIME_EPS_S) & (t_query <= t_src[-1] + TIME_EPS_S)
    if len(t_src) == 1:
        return np.zeros(t_query.shape, np.int64), np.zeros(t_query.shape), valid & np.isfinite(t_query)
    i0 = np.clip(np.searchsorted(t_src, t_query, side="right") - 1, 0, len(t_src) - 2)
    w = np.clip((t_query - t_src[i0]) / (t_src[i0 + 1] - t_src[i0]), 0.0, 1.0)
    return i0.astype(np.int64), w, valid & np.isfinite(t_query)


def interp_poses(T_src: F, t_src: F, t_query: F) -> tuple[F, NDArray[np.bool_]]:
    """Rigid poses at query times: slerp of the rotation, linear translation.

    Args:
        T_src: (N, 4, 4) rigid transforms (e.g. ``T_world_cam``) sampled at ``t_src``.
        t_src: (N,) strictly increasing times.
        t_query: (M,) query times.

    Returns:
        ``(T (M, 4, 4), valid (M,))``; outside the span the nearest end pose is returned and
        ``valid`` is False.
    """
    T_src = np.asarray(T_src, dtype=np.float64)
    if T_src.ndim != 3 or T_src.shape[1:] != (4, 4) or len(T_src) != len(np.asarray(t_src)):
        raise ValueError(f"T_src must be (N, 4, 4) with N = len(t_src), got {T_src.shape}")
    i0, w, valid = bracket(t_src, t_query)
    i1 = np.minimum(i0 + 1, len(T_src) - 1)
    q = matrix_to_quat(T_src[:, :3, :3])
    R = quat_to_matrix(slerp(q[i0], q[i1], w))
    t = (1.0 - w)[:, None] * T_src[i0, :3, 3] + w[:, None] * T_src[i1, :3, 3]
    out = np.zeros((len(w), 4, 4))
    out[:, :3, :3] = R
    out[:, :3, 3] = t
    out[:, 3, 3] = 1.0
    return out, valid


def interp_keypoints(kp: F, t_src: F, t_query: F) -> F:
    """2D keypoints with confidence at query times.

    Args:
        kp: (N, J, 3) ``(x, y, confidence)`` per sample; confidence 0 = not seen.
        t_src: (N,) strictly increasing times.
        t_query: (M,) query times.

    Returns:
        (M, J, 3): positions interpolated linearly between the bracketing samples, confidence
        ``min(c0, c1)``; where only one neighbour saw the joint, the nearer neighbour's values if
        it is that one, else confidence 0; confidence 0 outside the samples' span.
    """
    kp = np.asarray(kp, dtype=np.float64)
    if kp.ndim != 3 or kp.shape[-1] != 3 or len(kp) != len(np.asarray(t_src)):
        raise ValueError(f"kp must be (N, J, 3) with N = len(t_src), got {kp.shape}")
    i0, w, valid = bracket(t_src, t_query)
    i1 = np.minimum(i0 + 1, len(kp) - 1)
    a, b = kp[i0], kp[i1]
    ww = w[:, None]
    xy = (1.0 - ww[..., None]) * a[..., :2] + ww[..., None] * b[..., :2]
    conf = np.minimum(a[..., 2], b[..., 2])
    # Seen in one neighbour only: the nearer neighbour as is when it is the seen one (no worse than
    # nearest-frame pairing; a neighbour's absence must not hide a sample), else not seen.
    near_a = np.broadcast_to(ww <= 0.5, conf.shape)
    near = np.where(near_a[..., None], a, b)
    one = (conf <= 0) & (near[..., 2] > 0)
    xy = np.where(one[..., None], near[..., :2], xy)
    conf = np.where(one, near[..., 2], conf)
    conf = np.where(valid[:, None], conf, 0.0)
    return np.concatenate([xy, conf[..., None]], axis=-1)
