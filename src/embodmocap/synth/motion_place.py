"""The scripted performer's skinning and placement (:mod:`embodmocap.synth.motion`, step 3 of its
docstring), kept apart so that module stays small: the body posed in chunks of frames, the feet
kept still in locked pieces, each frame lifted onto the floor and the furniture tops. Private to
the studio."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.synth.motion_base import _L_ANKLE, _R_ANKLE, SLAB_DEPTH, _in_footprint, _supports
from embodmocap.synth.spec import SceneSpec


def _place(body, betas, go, body_pose, xy, lock, on_furniture, J0, spec: SceneSpec, chunk: int) -> NDArray:
    """SMPL ``transl`` (T, 3): pelvis at the planned xy (feet kept still in locked pieces),
    lifted onto the supports (see :mod:`embodmocap.synth.motion`). Furniture holds the body up only in
    interaction frames (``on_furniture``): elsewhere a heel brushing a sofa's front while walking
    away must not lift the performer onto it."""
    T = len(go)
    transl = np.zeros((T, 3))
    anchors: dict[int, NDArray] = {}
    supports = [(f.top_z, f, SLAB_DEPTH.get(f.name, np.inf)) for f in _supports(spec)]
    for s in range(0, T, chunk):
        sl = slice(s, min(s + chunk, T))
        base = np.concatenate([xy[sl] - J0[:2], np.full((sl.stop - sl.start, 1), -J0[2])], axis=1)
        out = body.forward(betas, go[sl], body_pose[sl], base)
        v = out.vertices.detach().cpu().numpy().astype(np.float64)
        j = out.joints.detach().cpu().numpy().astype(np.float64)
        feet = 0.5 * (j[:, _L_ANKLE, :2] + j[:, _R_ANKLE, :2])
        shift = np.zeros((len(v), 2))
        for k, seg in enumerate(lock[sl]):
            if seg < 0:
                continue
            anchors.setdefault(int(seg), feet[k])  # first frame of the locked run
            shift[k] = anchors[int(seg)] - feet[k]
        v[..., :2] += shift[:, None]
        lift = -v[..., 2].min(axis=1)  # floor
        z_floor = v[..., 2] + lift[:, None]
        for top, f, slab in supports:
            over = _in_footprint(f, v[..., :2]) & (z_floor > top - slab)
            low = np.where(over, v[..., 2], np.inf).min(axis=1)
            active = on_furniture[sl] & np.isfinite(low)
            lift = np.maximum(lift, np.where(active, top - low, -np.inf))
        transl[sl] = base + np.concatenate([shift, lift[:, None]], axis=1)
    return transl
