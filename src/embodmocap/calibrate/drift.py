"""Slow VIO drift in Stage III: a view's correction as a piecewise-linear function of the frame.

A handheld VIO track errs with the path walked (a scale error, drift of a per cent or two of the
path), so one yaw + translation cannot put every frame of a view in the scene's world. The joint
refinement (:mod:`embodmocap.calibrate.refine`) then fits ``[yaw, tx, ty, tz]`` at knots spread over
the view's frames; this module holds the knots, their interpolation weights and the per-frame
transforms (numpy only: ``calibration.json`` readers need no solver).

Pivot form: ``[yaw, t]`` rotates about the view's pivot (its mean camera centre) and then
translates, i.e. the world-side transform ``[Rz(yaw) | pivot - Rz(yaw) pivot + t]``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray


def knot_frames(n_frames: int, spacing: int) -> NDArray[np.int64]:
    """(K,) frames of a view's drift knots: the first and last frame and evenly between them, at
    most ``spacing`` frames apart; one knot (frame 0: the rigid offset) when ``spacing`` <= 0 or
    the view is shorter than two spacings."""
    if spacing <= 0 or n_frames < 2 * spacing:
        return np.zeros(1, dtype=np.int64)
    k = int(math.ceil((n_frames - 1) / spacing)) + 1
    return np.linspace(0, n_frames - 1, k).round().astype(np.int64)


def knot_basis(n_frames: int, knots: NDArray) -> NDArray[np.float64]:
    """(T, K) piecewise-linear (hat) weights of each frame on the knots; rows sum to 1 (one knot:
    all ones). Frames outside the knots take the nearest knot's value."""
    knots = np.asarray(knots, dtype=np.float64)
    t = np.arange(n_frames, dtype=np.float64)
    if len(knots) == 1:
        return np.ones((n_frames, 1))
    return np.stack([np.interp(t, knots, np.eye(len(knots))[k]) for k in range(len(knots))], axis=1)


def drift_transforms(knot_frames_: NDArray, knots: NDArray, pivot: NDArray, n_frames: int) -> NDArray[np.float64]:
    """(T, 4, 4) world-side corrections ``[Rz(yaw_t) | pivot - Rz pivot + t_t]`` of every frame,
    with ``[yaw_t, t_t]`` interpolated between the knots (K,) / (K, 4) (pivot form, see
    :class:`embodmocap.calibrate.refine.ViewOffset`)."""
    p = knot_basis(n_frames, knot_frames_) @ np.asarray(knots, dtype=np.float64).reshape(-1, 4)
    c, s = np.cos(p[:, 0]), np.sin(p[:, 0])
    D = np.tile(np.eye(4), (n_frames, 1, 1))
    D[:, 0, 0], D[:, 0, 1], D[:, 1, 0], D[:, 1, 1] = c, -s, s, c
    piv = np.asarray(pivot, dtype=np.float64)
    D[:, :3, 3] = piv - np.einsum("nij,j->ni", D[:, :3, :3], piv) + p[:, 1:4]
    return D
