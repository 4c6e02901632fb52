"""Frames with nothing to go on, filled from their neighbours: rotations by normalised quaternion
interpolation, values linearly, the ends held. Used by the initialisation (:mod:`embodmocap.motion.init`,
:mod:`embodmocap.motion.ik`) and the limb propagation (:mod:`embodmocap.motion.propagate`)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation


def _interp_index(valid: NDArray[np.bool_]) -> tuple[NDArray, NDArray, NDArray]:
    """For every frame: the previous and next valid frame and the weight of the next one.

    Valid frames map to themselves (weight 0); frames before the first / after the last valid
    frame hold it.
    """
    T = len(valid)
    idx = np.flatnonzero(valid)
    t = np.arange(T)
    k = np.clip(np.searchsorted(idx, t, side="right") - 1, 0, len(idx) - 1)
    prev = idx[k]
    nxt = idx[np.clip(k + 1, 0, len(idx) - 1)]
    prev = np.where(t < idx[0], idx[0], prev)
    span = np.maximum(nxt - prev, 1)
    w = np.clip((t - prev) / span, 0.0, 1.0)
    w = np.where(valid, 0.0, w)
    return prev, nxt, w


def fill_rotations(rotvec: NDArray, valid: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Axis-angle (T, J, 3) with the invalid frames interpolated (nlerp) between valid ones."""
    prev, nxt, w = _interp_index(valid)
    T, J = rotvec.shape[:2]
    q = Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_quat().reshape(T, J, 4)
    qa, qb = q[prev], q[nxt]
    qb = np.where((qa * qb).sum(-1, keepdims=True) < 0, -qb, qb)  # shortest way round
    qi = (1.0 - w)[:, None, None] * qa + w[:, None, None] * qb
    qi /= np.linalg.norm(qi, axis=-1, keepdims=True)
    return Rotation.from_quat(qi.reshape(-1, 4)).as_rotvec().reshape(T, J, 3)


def fill_linear(x: NDArray, valid: NDArray[np.bool_]) -> NDArray[np.float64]:
    """(T, ...) values with the invalid frames linearly interpolated between valid ones."""
    prev, nxt, w = _interp_index(valid)
    w = w.reshape((-1,) + (1,) * (x.ndim - 1))
    return (1.0 - w) * x[prev] + w * x[nxt]
