"""Windows of a long Stage IV fit: where they lie and how their results are blended.

A sequence longer than ``window_frames`` is fitted in evenly spaced windows of that length which
overlap; the fitted windows are cross-faded over the overlaps (translations linearly, rotations by
sign-aligned normalised quaternion blending). Split from :mod:`embodmocap.motion.smplify`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation


def window_ranges(T: int, length: int, overlap: int) -> list[tuple[int, int]]:
    """Evenly spaced windows ``[start, end)`` of ``length`` frames covering ``0..T``, neighbours
    sharing at least ``overlap`` frames; one window when ``T <= length``."""
    if length <= overlap or overlap < 0:
        raise ValueError(f"window length {length} must exceed the overlap {overlap} >= 0")
    if T <= length:
        return [(0, T)]
    n = math.ceil((T - overlap) / (length - overlap))
    starts = np.round(np.linspace(0, T - length, n)).astype(int)
    return [(int(s), int(s) + length) for s in starts]


def blend_weights(ranges: list[tuple[int, int]], T: int, ramp: int) -> NDArray[np.float64]:
    """(n, T) blend weight of each window per frame: a trapezoid rising over ``ramp`` frames at
    inner window edges, normalised to sum 1 per frame (linear cross-fade in a ``ramp`` overlap)."""
    w = np.zeros((len(ranges), T))
    for k, (s, e) in enumerate(ranges):
        t = np.arange(s, e) + 0.5
        up = np.ones(e - s) if s == 0 else np.clip((t - s) / max(ramp, 1), 0, 1)
        down = np.ones(e - s) if e == T else np.clip((e - t) / max(ramp, 1), 0, 1)
        w[k, s:e] = np.minimum(up, down)
    return w / w.sum(0, keepdims=True)


def blend_states(ranges: list[tuple[int, int]], states: list, T: int, ramp: int) -> tuple[NDArray, NDArray, NDArray]:
    """Blend window results: (T, 3) global_orient, (T, 69) body_pose, (T, 3) transl.

    ``states``: per window of ``ranges``, its fitted ``go`` (W, 3), ``pose`` (W, 69) and ``transl``
    (W, 3) torch tensors (``smplify._State``)."""
    w = blend_weights(ranges, T, ramp)
    quat = np.zeros((T, 24, 4))
    transl = np.zeros((T, 3))
    for k, ((s, e), st) in enumerate(zip(ranges, states)):
        rot = np.concatenate([st.go.cpu().numpy(), st.pose.cpu().numpy()], 1).reshape(-1, 3)
        q = Rotation.from_rotvec(rot).as_quat().reshape(e - s, 24, 4)
        # q and -q are one rotation: flip to the hemisphere of what is accumulated so far.
        sign = np.where((q * quat[s:e]).sum(-1, keepdims=True) < 0, -1.0, 1.0)
        quat[s:e] += w[k, s:e, None, None] * sign * q
        transl[s:e] += w[k, s:e, None] * st.transl.cpu().numpy()
    quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
    rot = Rotation.from_quat(quat.reshape(-1, 4)).as_rotvec().reshape(T, 72)
    return rot[:, :3], rot[:, 3:], transl
