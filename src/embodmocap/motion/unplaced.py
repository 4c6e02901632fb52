"""The facing of the body in frames that cannot be placed, from the views that still see it.

A frame is unplaceable when too few joints are triangulated (one view sees nobody, e.g. its
operator is still walking into position). The keypoint start fills such a run by holding the
orientation of the nearest placeable frame; the fit then has only the other view's 2D keypoints
there, whose robust kernel writes off the large residuals of a body that faces the wrong way, so
the held orientation stays. Measured on the outdoor studio seed (2026-12-02): view 1 blind over
the first 32 frames while the performer turned by about 77 degrees; the fit kept the body 61-69
degrees off in yaw there (root within 14-26 mm), and any measure that reads those frames (W-MPJPE
with its two-frame alignment on them: 150 mm against 35 mm without them) was ruined.

Here each unplaceable frame's orientation is tried turned about the vertical through the pelvis
(SMPL's pelvis does not move when the root rotation changes) by every ``step_deg``; the turn whose
keypoints reproject best into the views that see the frame (robust cost, the fit's kernel and
scale) is taken when it beats the held one by ``min_gain``, then the turns are smoothed over
neighbouring frames on the circle. Placeable frames are not touched. Only the fit's own inputs
are used.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from embodmocap.motion import terms as TM


@dataclass(frozen=True)
class UnplacedConfig:
    """How the facing of unplaceable frames is searched."""

    step_deg: float = 15.0
    """Spacing of the tried turns about Z, degrees (360 / step_deg candidates)."""
    min_observations: int = 6
    """A frame is turned only when at least this many 2D keypoints (all views) see it."""
    min_gain: float = 1.0
    """...and the best turn's summed robust reprojection cost (Geman-McClure, 0..1 per keypoint)
    is lower than the held orientation's by at least this."""
    smooth_frames: int = 7
    """The chosen turns are averaged on the circle over this many neighbouring frames."""


def _turn_costs(body, params, frames: NDArray, angles: NDArray, K: NDArray, T_world_cam: NDArray, kp2d: NDArray,
                scale2_px: float, min_conf: float) -> tuple[NDArray, NDArray]:
    """Robust reprojection cost (A, F) of ``frames`` turned by each of ``angles`` (A,) radians
    about Z, and the number of 2D observations (F,)."""
    A, F = len(angles), len(frames)
    go = Rotation.from_rotvec(np.asarray(params.global_orient, dtype=np.float64)[frames])
    orient = np.stack([(Rotation.from_rotvec([0.0, 0.0, a]) * go).as_rotvec() for a in angles])  # (A, F, 3)
    tile = lambda x: np.broadcast_to(np.asarray(x, dtype=np.float64)[frames], (A, F) + np.shape(x)[1:])  # noqa: E731
    tt = lambda x: torch.as_tensor(np.array(x, dtype=np.float64), dtype=torch.float64)  # noqa: E731
    with torch.no_grad():
        _, coco = body(tt(params.betas), tt(orient.reshape(A * F, 3)), tt(tile(params.body_pose).reshape(A * F, -1)),
                       tt(tile(params.transl).reshape(A * F, 3)))
        cams = np.broadcast_to(T_world_cam[frames], (A,) + T_world_cam[frames].shape).reshape((A * F,) + T_world_cam.shape[1:])
        uv, z = TM.project(coco, tt(K), tt(cams))  # (A*F, V, 17, 2), (A*F, V, 17)
        obs = np.broadcast_to(np.nan_to_num(kp2d[frames, ..., :2]), (A,) + kp2d[frames, ..., :2].shape)
        s2 = ((uv - tt(obs.reshape((A * F,) + obs.shape[2:]))) ** 2).sum(-1)
        r2 = (s2 / (s2 + scale2_px ** 2)).numpy().reshape(A, F, *s2.shape[1:])
        z = z.numpy().reshape(A, F, *z.shape[1:])
    c2 = np.nan_to_num(kp2d[frames, ..., 2])
    ok = np.isfinite(kp2d[frames, ..., :2]).all(-1) & (c2 >= min_conf)  # (F, V, 17)
    ok_a = ok[None] & (z > 0.05)
    return np.where(ok_a, r2, 0.0).sum((2, 3)), ok.sum((1, 2))


def turn_unplaced(body, params, valid: NDArray, K: NDArray, T_world_cam: NDArray, kp2d: NDArray, scale2_px: float,
                  min_conf: float, cfg: UnplacedConfig = UnplacedConfig()) -> tuple[object, NDArray[np.float64]]:
    """``params`` with the unplaceable frames' root orientation turned about Z to face the way the
    views that see them say (module docstring).

    Args:
        body: a :class:`embodmocap.motion.smplify.KeypointBody`; params: SmplParams, T frames.
        valid: (T,) bool placeable frames (never changed).
        K: (V, 3, 3); T_world_cam: (T, V, 4, 4); kp2d: (T, V, 17, 3) pixels and confidence.
        scale2_px: the fit's robust reprojection scale; min_conf: weaker keypoints are ignored.

    Returns:
        The new params and (T,) the turn applied to each frame, radians (0 where none).
    """
    valid = np.asarray(valid, dtype=bool)
    T = len(valid)
    turn = np.zeros(T)
    bad = np.flatnonzero(~valid)
    if len(bad) == 0 or not valid.any():
        return params, turn
    angles = np.radians(np.arange(-180.0, 180.0, cfg.step_deg))
    cost, count = _turn_costs(body, params, bad, angles, K, T_world_cam, kp2d, scale2_px, min_conf)
    held = cost[int(np.argmin(np.abs(angles)))]
    best = cost.argmin(0)
    take = (count >= cfg.min_observations) & (held - cost[best, np.arange(len(bad))] >= cfg.min_gain)
    if not take.any():
        return params, turn
    # Circular mean of the chosen turns over neighbouring unplaceable frames (held frames count 0).
    u = np.where(take[:, None], np.stack([np.cos(angles[best]), np.sin(angles[best])], -1), [1.0, 0.0])
    h = max(cfg.smooth_frames, 1) // 2
    pos = np.arange(len(bad))
    near = (np.abs(pos[:, None] - pos[None]) <= h) & (np.abs(bad[:, None] - bad[None]) <= h)
    m = near.astype(np.float64) @ u
    turn[bad] = np.arctan2(m[:, 1], m[:, 0])
    go = Rotation.from_rotvec(np.asarray(params.global_orient, dtype=np.float64)[bad])
    orient = np.array(params.global_orient, dtype=np.float64)
    orient[bad] = (Rotation.from_rotvec(turn[bad, None] * [0.0, 0.0, 1.0]) * go).as_rotvec()
    return replace(params, global_orient=orient), turn
