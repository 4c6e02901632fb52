"""The body's stature (rest-pose height) as a function of its shape, and the smallest shape change
that gives a wanted stature.

The rest-pose mesh is ``v(b) = v_template + shapedirs @ b`` (linear in the betas ``b``); the
stature is its extent along the model's up axis (SMPL: +Y), ``h(b) = max_i v_iy(b) - min_i v_iy(b)``.
For fixed top / bottom vertices ``h`` is linear in ``b`` with gradient
``g = shapedirs[top, y] - shapedirs[bottom, y]``, so the minimum-norm change reaching a height
``h*`` is ``b' = b + g (h* - h(b)) / |g|^2`` (a few rounds, in case the top or bottom vertex
changes with the shape).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

#: The model's up axis in its canonical frame (SMPL: Y up).
UP_AXIS = 1


def stature(model, betas: NDArray) -> NDArray[np.float64]:
    """(...,) rest-pose height in metres of a body with ``betas`` (..., B) (B <= the model's)."""
    a = model._arrays
    b = model._betas_np(betas)
    y = a["v_template"][:, UP_AXIS] + np.einsum("vb,...b->...v", a["shapedirs"][:, UP_AXIS, :], b)
    return y.max(axis=-1) - y.min(axis=-1)


def betas_for_stature(model, betas: NDArray, height_m: float, rounds: int = 4) -> NDArray[np.float64]:
    """(B,) the betas closest to ``betas`` (B,) (Euclidean, in the model's shape space) whose rest-pose
    height is ``height_m``; the returned vector has the model's full number of betas."""
    a = model._arrays
    dirs = a["shapedirs"][:, UP_AXIS, :]  # (V, B)
    b = model._betas_np(np.asarray(betas, dtype=np.float64)).copy()
    for _ in range(rounds):
        y = a["v_template"][:, UP_AXIS] + dirs @ b
        top, bot = int(np.argmax(y)), int(np.argmin(y))
        g = dirs[top] - dirs[bot]
        gap = float(height_m) - float(y[top] - y[bot])
        if abs(gap) < 1e-9 or not np.any(g):
            break
        b = b + g * gap / float(g @ g)
    return b
