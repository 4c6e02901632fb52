"""Check registered view frames against the phone's own VIO (Stage III, between registration and
the offset fit).

A registration is a camera pose in the scene's world; the VIO gives the same camera's pose in the
phone's world. Whatever the (unknown) offset between the two worlds, the *relative* motion between
two frames must be the same in both: ``inv(T_reg_a) @ T_reg_b == inv(T_vio_a) @ T_vio_b`` up to
registration noise and a little VIO drift. A frame registered to the wrong place (repeated texture,
a look-alike wall) breaks that, and so does a whole run of consecutive frames registered
consistently wrong (each agrees with its neighbours, but not with the rest of the view).

:func:`check_against_vio`:

1. cuts the registered frames (in time order) into *runs*: consecutive frames whose relative
   motions agree with the VIO's within ``max_m`` / ``max_deg``;
2. joins runs that agree with each other (compared through their frames nearest in time, so VIO
   drift over long gaps does not count against them) into groups;
3. keeps the largest group (most frames; ties: more pose inliers) and rejects every other run.

Conventions: ``T_*`` are camera-to-world (4, 4), OpenCV cameras, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.transforms import invert_T, rotation_angle


@dataclass(frozen=True)
class VioCheck:
    """Which registered frames agree with the VIO.

    Attributes:
        accepted: (R,) bool, the frame belongs to the kept group.
        run: (R,) int64 run label of each frame (0, 1, ... in time order).
        runs: number of runs.
        rejected_runs: runs outside the kept group.
        rejected_frames: frames outside the kept group.
        max_m: translation disagreement limit used, metres.
        max_deg: rotation disagreement limit used, degrees.
    """

    accepted: NDArray[np.bool_]
    run: NDArray[np.int64]
    runs: int
    rejected_runs: int
    rejected_frames: int
    max_m: float
    max_deg: float

    def report(self) -> dict:
        """The figures ``calibration.json`` keeps (plain JSON types)."""
        return {"runs": int(self.runs), "rejected_runs": int(self.rejected_runs),
                "rejected_frames": int(self.rejected_frames), "accepted_frames": int(self.accepted.sum()),
                "max_disagreement_m": self.max_m, "max_disagreement_deg": self.max_deg}


def relative_disagreement(T_reg_a: NDArray, T_reg_b: NDArray, T_vio_a: NDArray, T_vio_b: NDArray,
                          ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """How much the registered relative motion a -> b differs from the VIO's.

    Args:
        T_reg_a, T_reg_b: (..., 4, 4) registered camera-to-world poses (scene world).
        T_vio_a, T_vio_b: (..., 4, 4) the same frames' VIO camera-to-world poses.

    Returns:
        ``(metres (...,), degrees (...,))``: translation and rotation of
        ``inv(rel_vio) @ rel_reg`` with ``rel = inv(T_a) @ T_b`` (both measured in camera a).
    """
    rel_reg = invert_T(np.asarray(T_reg_a, dtype=np.float64)) @ np.asarray(T_reg_b, dtype=np.float64)
    rel_vio = invert_T(np.asarray(T_vio_a, dtype=np.float64)) @ np.asarray(T_vio_b, dtype=np.float64)
    D = invert_T(rel_vio) @ rel_reg
    return np.linalg.norm(D[..., :3, 3], axis=-1), np.degrees(rotation_angle(D[..., :3, :3]))


def check_against_vio(T_reg: NDArray, T_vio: NDArray, inliers: NDArray | None = None,
                      max_m: float = 0.10, max_deg: float = 3.0) -> VioCheck:
    """Runs of registered frames that agree with the VIO, and the one group that is kept.

    Args:
        T_reg: (R, 4, 4) registered poses of the frames, in time order.
        T_vio: (R, 4, 4) the VIO poses of the same frames.
        inliers: (R,) pose inliers per frame (breaks ties between equal-sized groups), or None.
        max_m: largest translation disagreement of two frames' relative motion, metres.
        max_deg: largest rotation disagreement, degrees.
    """
    T_reg = np.asarray(T_reg, dtype=np.float64).reshape(-1, 4, 4)
    T_vio = np.asarray(T_vio, dtype=np.float64).reshape(-1, 4, 4)
    n = len(T_reg)
    if n == 0:
        return VioCheck(np.zeros(0, bool), np.zeros(0, np.int64), 0, 0, 0, max_m, max_deg)
    inl = np.ones(n) if inliers is None else np.asarray(inliers, dtype=np.float64)

    # 1. Runs of consecutive frames that agree.
    dm, dd = relative_disagreement(T_reg[:-1], T_reg[1:], T_vio[:-1], T_vio[1:])
    cut = (dm > max_m) | (dd > max_deg)
    run = np.r_[0, np.cumsum(cut)].astype(np.int64)
    k = int(run[-1]) + 1
    first = np.searchsorted(run, np.arange(k), side="left")
    last = np.searchsorted(run, np.arange(k), side="right") - 1

    # 2. Join runs that agree, compared through their frames nearest in time (a before b: a's
    # last frame and b's first). All pairs at once: k is small unless the view is hopeless.
    parent = np.arange(k)

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    if k > 1:
        a, b = np.triu_indices(k, 1)
        pm, pd = relative_disagreement(T_reg[last[a]], T_reg[first[b]], T_vio[last[a]], T_vio[first[b]])
        for i, j in zip(a[(pm <= max_m) & (pd <= max_deg)], b[(pm <= max_m) & (pd <= max_deg)]):
            ri, rj = root(int(i)), root(int(j))
            if ri != rj:
                parent[max(ri, rj)] = min(ri, rj)
    group = np.array([root(int(r)) for r in run], dtype=np.int64)

    # 3. The largest group (frames, then inliers, then earliest) is kept.
    labels = np.unique(group)
    size = np.array([np.sum(group == g) for g in labels])
    weight = np.array([inl[group == g].sum() for g in labels])
    best = labels[np.lexsort((labels, -weight, -size))[0]]
    accepted = group == best
    rejected_runs = len(np.unique(run[~accepted]))
    return VioCheck(accepted, run, k, rejected_runs, int((~accepted).sum()), max_m, max_deg)


def off_chain_frames(T_reg: NDArray, T_vio: NDArray, accepted: NDArray, max_m: float = 0.10, max_deg: float = 3.0,
                     min_m: float = 0.05, min_deg: float = 1.0, spread: float = 3.0, offset_cfg=None) -> NDArray[np.bool_]:
    """(R,) True for accepted frames that sit off the offset of their whole chain.

    The run check compares neighbours, so an error that grows gradually along a run (15, 10, 9,
    4, 2 cm: each step agrees within the limit) passes it. Here the offset is fitted on every
    accepted frame at once (:func:`embodmocap.calibrate.offset.chain_yaw_offset`, robust) and each
    frame is compared with it: a frame whose registered centre is further than the limit from its
    VIO centre through that offset, or whose orientation differs by more than the rotation limit,
    is off the chain. The limits adapt to the view's own scatter (``spread`` robust standard
    deviations of the residuals) between ``min_m`` / ``min_deg`` and ``max_m`` / ``max_deg``, so a
    noisy but right view (plain walls) keeps its frames while a sharp one drops a 6 cm ramp.

    Args:
        T_reg: (R, 4, 4) registered poses; T_vio: (R, 4, 4) the same frames' VIO poses.
        accepted: (R,) bool, the frames kept by :func:`check_against_vio`.
    """
    from embodmocap.calibrate.offset import RobustOffsetConfig, chain_yaw_offset

    T_reg = np.asarray(T_reg, dtype=np.float64).reshape(-1, 4, 4)
    T_vio = np.asarray(T_vio, dtype=np.float64).reshape(-1, 4, 4)
    acc = np.asarray(accepted, dtype=bool)
    out = np.zeros(len(T_reg), dtype=bool)
    if acc.sum() < 3:
        return out
    try:
        fit = chain_yaw_offset(T_vio[acc], T_reg[acc], offset_cfg or RobustOffsetConfig())
    except ValueError:  # the chain cannot fix a yaw: nothing to compare with
        return out
    mapped = fit.offset.apply(T_vio[acc])
    dm = np.linalg.norm(mapped[:, :3, 3] - T_reg[acc, :3, 3], axis=1)
    dd = np.degrees(rotation_angle(np.swapaxes(mapped[:, :3, :3], -1, -2) @ T_reg[acc, :3, :3]))
    lim_m = float(np.clip(spread * 1.4826 * np.median(dm), min_m, max_m))
    lim_d = float(np.clip(spread * 1.4826 * np.median(dd), min_deg, max_deg))
    out[np.flatnonzero(acc)] = (dm > lim_m) | (dd > lim_d)
    return out
