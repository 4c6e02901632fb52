"""Array helpers shared by the six skill tasks: one code path for numpy and torch.

Every task function takes batched arrays (leading batch axis ``N``; a single environment is
``N = 1``) of one kind, numpy or torch, and returns the same kind. The few operations they need
go through :func:`ops`, which picks the backend from the first array; nothing else differs, so the
numpy and torch results agree to floating-point rounding (tests/test_skills_tasks.py checks it).

Conventions (the project's): Z-up world, metres, seconds. A body rotation ``R`` is a (N, 3, 3)
matrix whose columns are the body's axes in the world: x forward, y left, z up (the MuJoCo
humanoid's body frames, :mod:`embodmocap.sim.model`). The character's **heading frame** has its
origin at the root, x along the root's forward axis projected on the ground, z up.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class _Numpy:
    exp, sqrt, abs = staticmethod(np.exp), staticmethod(np.sqrt), staticmethod(np.abs)
    where = staticmethod(np.where)

    @staticmethod
    def sum(x, axis):
        return x.sum(axis=axis)

    @staticmethod
    def clip(x, lo, hi):
        return np.clip(x, lo, hi)

    @staticmethod
    def stack(xs, axis):
        return np.stack(xs, axis=axis)

    @staticmethod
    def cat(xs, axis):
        return np.concatenate(xs, axis=axis)

    @staticmethod
    def swap(x):
        return np.swapaxes(x, -1, -2)

    @staticmethod
    def like(value, ref):
        return np.asarray(value, dtype=ref.dtype)

    @staticmethod
    def index(x):
        return x.astype(np.int64)


class _Torch:
    def __init__(self) -> None:
        import torch

        self.t = torch
        self.exp, self.sqrt, self.abs, self.where = torch.exp, torch.sqrt, torch.abs, torch.where

    def sum(self, x, axis):
        return x.sum(dim=axis)

    def clip(self, x, lo, hi):
        return self.t.clamp(x, lo, hi)

    def stack(self, xs, axis):
        return self.t.stack(xs, dim=axis)

    def cat(self, xs, axis):
        return self.t.cat(xs, dim=axis)

    def swap(self, x):
        return x.transpose(-1, -2)

    def like(self, value, ref):
        return self.t.as_tensor(value, dtype=ref.dtype, device=ref.device)

    def index(self, x):
        return x.long()


_NUMPY = _Numpy()
_TORCH: _Torch | None = None


def is_torch(x: Any) -> bool:
    """Whether ``x`` is a torch tensor (without importing torch when it is not)."""
    return type(x).__module__.startswith("torch")


def ops(x: Any):
    """The backend of ``x``: numpy's or torch's versions of the few operations the tasks use."""
    global _TORCH
    if is_torch(x):
        if _TORCH is None:
            _TORCH = _Torch()
        return _TORCH
    return _NUMPY


def norm(x, axis: int = -1):
    """Euclidean norm along ``axis``."""
    o = ops(x)
    return o.sqrt(o.sum(x * x, axis))


def sqnorm(x, axis: int = -1):
    """Squared Euclidean norm along ``axis``."""
    return ops(x).sum(x * x, axis)


def unit(x, axis: int = -1, eps: float = 1e-9):
    """``x`` scaled to unit length along ``axis`` (zero vectors stay zero)."""
    n = norm(x, axis)
    return x / (n[..., None] + eps) if axis == -1 else x / (n + eps)


def heading_frame(root_rot):
    """(N, 3, 3) rotation of the heading frame in the world (columns: forward on the ground, left, up).

    ``root_rot``: (N, 3, 3) root body rotation. A root whose forward axis points straight up or
    down (lying) has no horizontal forward; its up axis then gives the heading (the way the
    head points), which is continuous through that pose for a body lying on its back or front.
    """
    o = ops(root_rot)
    f = root_rot[:, :2, 0]
    up = root_rot[:, :2, 2]
    fn = norm(f)
    # Blend towards the up axis's direction as the forward axis turns vertical (smooth, never 0/0).
    w = o.clip(fn / 0.3, 0.0, 1.0)[:, None]
    fxy = unit(w * unit(f) + (1 - w) * unit(up))
    zero = fxy[:, :1] * 0
    x = o.cat([fxy, zero], -1)
    y = o.cat([-fxy[:, 1:2], fxy[:, :1], zero], -1)
    z = o.cat([zero, zero, zero + 1], -1)
    return o.stack([x, y, z], -1)


def to_heading(vectors, root_rot, H=None):
    """World vectors (N, ..., 3) into the heading frame (rotation only); ``H`` the heading frame
    (:func:`heading_frame`) when already at hand."""
    H = heading_frame(root_rot) if H is None else H
    shape = vectors.shape
    v = vectors.reshape(shape[0], -1, 3)
    return (v @ H).reshape(shape)


def points_to_heading(points, root_pos, root_rot, H=None):
    """World points (N, ..., 3) into the heading frame (relative to the root, then rotated)."""
    shape = points.shape
    p = points.reshape(shape[0], -1, 3) - root_pos[:, None, :]
    return to_heading(p, root_rot, H).reshape(shape)


def facing_2d(root_rot):
    """(N, 2) the character's front-facing direction on the ground (unit), world frame."""
    return heading_frame(root_rot)[:, :2, 0]


def rot6d(R):
    """(N, 6) the first two columns of (N, 3, 3) rotations, column after column (Zhou et al.'s 6D)."""
    o = ops(R)
    return o.cat([R[:, :, 0], R[:, :, 1]], -1)


def far_speed_reward(root_pos, root_vel, goal_xy, speed: float = 1.5, k: float = 2.0):
    """``exp(-k (speed - d* . v_2d)^2)``: walking towards ``goal_xy`` at ``speed`` m/s.

    ``d*`` is the horizontal unit vector from the root to ``goal_xy`` (N, 2); ``root_vel`` (N, 3).
    """
    o = ops(root_pos)
    d = unit(goal_xy - root_pos[:, :2])
    v = o.sum(d * root_vel[:, :2], -1)
    return o.exp(-k * (speed - v) ** 2)
