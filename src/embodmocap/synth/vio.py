"""VIO errors of a handheld phone that a rigid offset cannot absorb (the studio's hard camera preset).

:func:`embodmocap.synth.trajectory.add_drift` models the studio's historic drift: a random walk in
*time*, 0.75 cm after 10 s, whatever the phone does. A real ARKit track errs with the *motion*:

- a scale error: VIO integrates the IMU and tracks features at an estimated depth, so its
  displacements are a few per mille to a couple of per cent too long or too short;
- drift that grows with the path walked (the usual "x % of the distance travelled"), in a direction
  that wanders slowly;
- a yaw drift that grows with the turning and walking (degrees per metre of path).

Over a view's seconds these give each frame its own error (centimetres, growing along the path), so
one yaw + translation cannot put every frame of the view in the scene: what Stage III must handle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class VioErrorConfig:
    """Path-dependent VIO errors of the two sequence views (the scene scan keeps the studio's
    time drift). All zero (the default) = the studio's historic views."""

    drift_percent_of_path: tuple[float, float] = (0.0, 0.0)
    """Range of the translation drift per view, per cent of the path walked: after walking L metres
    the view's VIO is off by about this share of L, in a slowly wandering direction (vertical a
    third of horizontal). ARKit on a handheld phone: about 0.5-1.5 %."""
    scale_error_percent: tuple[float, float] = (0.0, 0.0)
    """Range of the magnitude of the view's VIO scale error, per cent (sign drawn per view): its
    displacements from its first frame are this much too long or too short."""
    yaw_drift_deg_per_m: tuple[float, float] = (0.0, 0.0)
    """Range of the yaw drift per metre of path, degrees (a random walk in path length)."""
    wander_m: float = 2.0
    """Path length over which the drift's direction changes (Gaussian smoothing of its direction
    noise, metres)."""

    @property
    def active(self) -> bool:
        """True when any error is non-zero."""
        return any(r[1] > 0 for r in (self.drift_percent_of_path, self.scale_error_percent, self.yaw_drift_deg_per_m))


#: The hard camera preset's VIO errors (``SynthConfig.cameras = "hard"``).
HARD_VIO = VioErrorConfig(drift_percent_of_path=(1.0, 2.0), scale_error_percent=(1.0, 2.0),
                          yaw_drift_deg_per_m=(0.1, 0.3))


def add_path_errors(T_vio_cam: NDArray, rng: np.random.Generator, cfg: VioErrorConfig) -> NDArray[np.float64]:
    """The view's VIO poses (T, 4, 4) with ``cfg``'s scale error, path drift and yaw drift; frame 0
    unchanged (the VIO world is defined at the first frame).

    Frame ``t`` becomes ``D(t) @ S(T(t))``: ``S`` scales the camera centre's displacement from
    frame 0 by ``1 + s``; ``D(t)`` turns by ``psi(t)`` about frame 0's centre and shifts by
    ``d(t)``; ``d`` and ``psi`` are integrals over the path length walked so far.
    """
    from scipy.ndimage import gaussian_filter1d

    T = np.array(T_vio_cam, dtype=np.float64, copy=True)
    n = len(T)
    if n < 2 or not cfg.active:
        return T
    p = T[:, :3, 3]
    p0 = p[0].copy()
    s = rng.uniform(*cfg.scale_error_percent) / 100.0 * rng.choice([-1.0, 1.0])
    step = np.r_[0.0, np.linalg.norm(np.diff(p, axis=0), axis=1)]  # (T,) metres walked per frame
    path = np.cumsum(step)
    # Direction noise smoothed over `wander_m` of path (resampled on a path-length grid).
    grid = np.linspace(0.0, max(path[-1], 1e-6), max(int(path[-1] / 0.02), 2))
    sigma = max(cfg.wander_m / max(grid[1] - grid[0], 1e-9), 1.0)
    noise = gaussian_filter1d(rng.standard_normal((len(grid), 4)), sigma, axis=0, mode="nearest")
    noise /= np.sqrt((noise**2).mean(axis=0)) + 1e-12  # unit RMS per component
    g = np.stack([np.interp(path, grid, noise[:, k]) for k in range(4)], axis=1)
    horiz = g[:, :2] / np.sqrt(2.0)
    direction = np.c_[horiz, g[:, 2:3] / 3.0]
    d = rng.uniform(*cfg.drift_percent_of_path) / 100.0 * np.cumsum(direction * step[:, None], axis=0)
    psi = np.deg2rad(rng.uniform(*cfg.yaw_drift_deg_per_m)) * np.cumsum(g[:, 3] * step)
    c, sn = np.cos(psi), np.sin(psi)
    Rz = np.zeros((n, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -sn, sn, c, 1.0
    scaled = p0 + (1.0 + s) * (p - p0)
    T[:, :3, 3] = np.einsum("nij,nj->ni", Rz, scaled - p0) + p0 + d
    T[:, :3, :3] = Rz @ T[:, :3, :3]
    return T
