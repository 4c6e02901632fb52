"""Limbs at the edges of a run of placeable frames that the views contradict, carried over from the
first frame that fits them (issue 29).

Inside a run a limb that no keypoint pins is held by the acceleration term between well-pinned
neighbours on both sides. At a run's first (last) frames there is a neighbour on one side only, and
the evidence there is often the weakest of the run: a view whose left/right labels the checks could
not tell without a past drops the limb, the other sees it occluded. The edge velocity term
(:attr:`SmplifyConfig.edge_hold`) holds only what no detection pins, so a limb one view sees weakly
can still drift along that view's ray into the first frames, 20-35 cm from where the views' raw
detections put it, while the frames a few steps later fit (issue 29's external sessions: a whole
leg or arm 30-36 cm off in the first 2-5 frames, flagged ``valid``).

After the fit, per run and limb (arm, leg): the frames from the run's edge up to the first frame
where the limb is within ``QualityConfig.suspect_m`` of every view that sees it
(:func:`embodmocap.motion.quality.joint_offsets`), at most ``max_frames``, take that frame's local
limb rotations (the articulation held still, as the edge hold does; the body itself keeps its
fitted motion). The stretch keeps the carried pose only when it brings the limb closer to what
the views see (mean over the stretch), so a limb that the views' own detections contradict by
mistake stays as fitted.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np
from numpy.typing import NDArray

#: Limb -> (COCO-17 joints judged: elbow and wrist, knee and ankle; SMPL joints whose local
#: rotations are carried: collar or hip down to the hand or foot).
LIMBS: dict[str, tuple[tuple[int, ...], tuple[int, ...]]] = {
    "left_arm": ((7, 9), (13, 16, 18, 20, 22)),
    "right_arm": ((8, 10), (14, 17, 19, 21, 23)),
    "left_leg": ((13, 15), (1, 4, 7, 10)),
    "right_leg": ((14, 16), (2, 5, 8, 11)),
}


def runs_of(valid: NDArray) -> list[tuple[int, int]]:
    """(first, last) frames of each run of True in ``valid`` (T,)."""
    v = np.concatenate([[False], np.asarray(valid, bool), [False]])
    d = np.diff(v.astype(np.int8))
    return list(zip(np.flatnonzero(d == 1).tolist(), (np.flatnonzero(d == -1) - 1).tolist()))


def edge_stretches(off: NDArray, valid: NDArray, limit_m: float, max_frames: int) -> list[tuple[list[int], int]]:
    """The stretches to carry for one limb: (frames, source frame) per run edge whose first (last)
    frame is off (``off`` (T,) the limb's distance from the views, NaN = unseen, counts as fine)
    and whose first fine frame lies within ``max_frames`` of the edge."""
    bad = np.nan_to_num(off, nan=0.0) > limit_m
    out = []
    for a, b in runs_of(valid):
        carried_to = a - 1  # the last frame the start's stretch took
        if bad[a]:
            fine = [t for t in range(a, min(b, a + max_frames) + 1) if not bad[t]]
            if fine:
                out.append((list(range(a, fine[0])), fine[0]))
                carried_to = fine[0] - 1
        if bad[b] and b > a:
            fine = [t for t in range(b, max(a, b - max_frames) - 1, -1) if not bad[t]]
            if fine and fine[0] > carried_to:
                out.append((list(range(fine[0] + 1, b + 1)), fine[0]))
    return out


def repair_edges(params, valid: NDArray, offsets: Callable[[object], NDArray], limit_m: float, max_frames: int,
                 off0: NDArray | None = None):
    """``params`` with the contradicted limbs at run edges carried from their first fine frame
    (module docstring), and the number of (frame, limb) pairs changed.

    Args:
        params: the fitted :class:`~embodmocap.types.SmplParams`; valid: (T,) placeable frames;
        offsets: params -> (T, 17) each COCO-17 joint's distance from the views that see it
            (NaN: unseen; :func:`embodmocap.motion.quality.joint_offsets` of the body's keypoints);
        limit_m: a limb further than this is contradicted; max_frames: longest stretch carried;
        off0: ``offsets(params)`` when the caller has it (None: computed here).
    """
    off0 = offsets(params) if off0 is None else off0
    pose = np.array(params.body_pose, dtype=np.float64, copy=True)
    plan = []
    for name, (coco, smpl) in LIMBS.items():
        limb_off = _limb_max(off0, coco)
        for frames, src in edge_stretches(limb_off, valid, limit_m, max_frames):
            cols = np.concatenate([np.arange(3 * (j - 1), 3 * j) for j in smpl])
            pose[np.ix_(frames, cols)] = pose[src, cols]
            plan.append((coco, frames, cols))
    if not plan:
        return params, 0
    trial = replace(params, body_pose=pose)
    off1 = offsets(trial)
    out = np.array(params.body_pose, dtype=np.float64, copy=True)
    n = 0
    for coco, frames, cols in plan:
        before, after = _limb_max(off0, coco)[frames], _limb_max(off1, coco)[frames]
        if np.nanmean(np.nan_to_num(after, nan=0.0)) < np.nanmean(np.nan_to_num(before, nan=0.0)):
            out[np.ix_(frames, cols)] = pose[np.ix_(frames, cols)]
            n += len(frames)
    return (replace(params, body_pose=out), n) if n else (params, 0)


def _limb_max(off: NDArray, coco: tuple[int, ...]) -> NDArray:
    """(T,) the largest of the limb joints' distances (NaN where none is seen)."""
    o = off[:, list(coco)]
    return np.where(np.isfinite(o).any(-1), np.nanmax(np.nan_to_num(o, nan=-1.0), axis=-1), np.nan)
