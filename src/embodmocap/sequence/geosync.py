"""Geometric sync: the time offset at which the two views' keypoint rays meet.

Once each view is registered to the scene (Stage III, independently of time), both views' cameras
live in one world. At the right time offset, the ray through a joint's 2D keypoint in view 1 and
the ray through the same joint in view 2 meet at the joint; at a wrong offset the performer has
moved between the two instants and the rays miss each other by about the distance moved. So:

1. **Integer search** (:func:`shift_costs`): for every shift ``s`` in a window, pair view 1's
   frame ``t`` with view 2's frame ``t + s``, triangulate every joint seen in both (midpoint of
   the two rays) and reproject it; the cost is the mean over pairs of the squared reprojection
   error clipped at ``clip_px`` (clipping keeps a wrong detection from outweighing the rest).
2. **Sub-frame refinement** (:func:`subframe_shift`): view 2's keypoints are interpolated in time
   around the best shift. Interpolating between two noisy samples and scoring the result is
   biased: the average of two samples is less noisy than either, so any score prefers half
   frames. Instead the refinement uses the signed distance ``d`` of view 2's keypoint from the
   epipolar line of view 1's, at the best shift and at its two neighbours (each with its own
   camera): ``d(f) ~ d(0) + f (d(+1) - d(-1)) / 2`` is the linear interpolation of view 2's
   keypoint in time projected on the only direction that timing can change, and its noise does
   not depend on ``f``. ``f`` is the robust (Huber) least-squares zero of all pairs' lines; if it
   leaves ``[-0.5, 0.5]`` the centre moves to the neighbour and the fit is repeated.
3. **Confidence**: how distinct the minimum is (best cost against the best cost more than
   ``distinct_frames`` away) times how precise the sub-frame fit is (its standard error); a
   performer standing still gives a flat cost and a low confidence, never a wrong confident answer.

The result is an offset in **seconds**: the instant view 1 films at its time ``t`` (seconds after
its slicing event) is filmed by view 2 at its time ``t + offset_s``.

Every function is pure and vectorised over frames, joints and shifts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F = NDArray[np.floating]


@dataclass(frozen=True)
class GeoSyncConfig:
    """Settings of the geometric sync (Stage III) and of the choice between sync sources."""

    enabled: bool = True
    """Run the geometric sync after registration (False = the laser / manual frames are final)."""
    search_s: float = 1.0
    """Half-width of the offset search around the laser sync, seconds."""
    search_s_without_laser: float = 5.0
    """Half-width of the search when a view has no laser event (slicing then starts at each
    view's first frame), seconds."""
    min_keypoint_confidence: float = 0.3
    """Keypoints below this confidence are not used."""
    clip_px: float = 25.0
    """Reprojection errors are clipped at this many pixels in the cost (robustness)."""
    huber_px: float = 4.0
    """Huber threshold of the sub-frame fit's epipolar residuals, pixels."""
    min_pairs: int = 60
    """Fewest joint pairs seen in both views at a shift for that shift to be scored."""
    min_overlap: float = 0.5
    """A shift must pair at least this fraction of the sequence's frames."""
    distinct_frames: int = 3
    """The second-best cost is taken at least this many frames from the best (confidence)."""
    min_confidence: float = 0.3
    """Geometric results below this confidence are reported but never chosen."""
    agree_frames: float = 1.0
    """Laser and geometric offsets further apart than this (frames) are a warning."""
    prefer: str = "auto"
    """Which source wins when both exist: ``auto`` (geometric when it agrees with the laser within
    ``agree_frames`` or is more confident, else laser), ``laser`` or ``geometric``."""

    def __post_init__(self) -> None:
        if self.prefer not in ("auto", "laser", "geometric"):
            from embodmocap.errors import InputError

            raise InputError(None, f"geosync.prefer = {self.prefer!r}", "use auto, laser or geometric")


@dataclass(frozen=True)
class GeoSyncResult:
    """Outcome of :func:`geometric_sync`.

    Attributes:
        offset_s: view 2's time minus view 1's time for the same instant, seconds (relative to the
            slicing both views' timelines came from); NaN when no offset could be scored.
        offset_frames: the same in sequence frames.
        shift: best integer shift (frames).
        confidence: in [0, 1] (module docstring).
        std_frames: standard error of the sub-frame offset, frames.
        cost_px: root of the best (clipped) mean squared reprojection error, pixels.
        pairs: joint pairs behind the best cost.
        shifts, costs, counts: (S,) the searched shifts, their costs (px^2; NaN where too few
            pairs) and pair counts.
        message: why there is no result, or "".
    """

    offset_s: float
    offset_frames: float
    shift: int
    confidence: float
    std_frames: float
    cost_px: float
    pairs: int
    shifts: NDArray[np.int64]
    costs: F
    counts: NDArray[np.int64]
    message: str = ""

    @property
    def found(self) -> bool:
        return math.isfinite(self.offset_s)

    def to_json(self) -> dict:
        def num(x, nd):
            return round(float(x), nd) if math.isfinite(float(x)) else None

        return {"offset_s": num(self.offset_s, 6), "offset_frames": num(self.offset_frames, 4),
                "integer_shift": int(self.shift), "confidence": num(self.confidence, 3),
                "std_frames": num(self.std_frames, 4), "cost_px": num(self.cost_px, 3), "pairs": int(self.pairs),
                "message": self.message,
                "curve": {"shifts": self.shifts.tolist(), "cost_px2": [num(c, 3) for c in self.costs],
                          "pairs": self.counts.tolist()}}


# --------------------------------------------------------------------------- two-view geometry


def _rays(K: F, T_world_cam: F, xy: F) -> tuple[F, F]:
    """Camera centres (..., 3) and unit ray directions (..., 3) in the world of pixels xy (..., 2)."""
    Kinv = np.linalg.inv(K)
    h = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
    d_cam = np.einsum("...ij,...j->...i", Kinv, h)
    d = np.einsum("...ij,...j->...i", T_world_cam[..., :3, :3], d_cam)
    return np.broadcast_to(T_world_cam[..., :3, 3], d.shape), d / np.linalg.norm(d, axis=-1, keepdims=True)


def _project(K: F, T_world_cam: F, X: F) -> tuple[F, F]:
    """Pixels (..., 2) and depth (...) of world points X (..., 3)."""
    R, c = T_world_cam[..., :3, :3], T_world_cam[..., :3, 3]
    pc = np.einsum("...ji,...j->...i", R, X - c)
    z = pc[..., 2]
    uv = np.einsum("...ij,...j->...i", K, pc)
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    return uv[..., :2] / zs[..., None], z


def midpoint_reprojection_error(K1: F, T1: F, x1: F, K2: F, T2: F, x2: F) -> F:
    """Mean reprojection error (px) over both views of the midpoint of two rays.

    Args:
        K1, K2: (..., 3, 3) intrinsics; T1, T2: (..., 4, 4) ``T_world_cam``; x1, x2: (..., 2)
            pixels of the same point in each view. Leading shapes broadcast.

    Returns:
        (...) error in pixels; ``inf`` where the rays are parallel or the midpoint lies behind a
        camera (the pairing cannot be right).
    """
    c1, d1 = _rays(K1, T1, x1)
    c2, d2 = _rays(K2, T2, x2)
    w0 = c1 - c2
    b = np.sum(d1 * d2, axis=-1)
    d = np.sum(d1 * w0, axis=-1)
    e = np.sum(d2 * w0, axis=-1)
    den = 1.0 - b * b  # unit directions: a = c = 1
    ok = den > 1e-8
    den = np.where(ok, den, 1.0)
    s = (b * e - d) / den
    u = (e - b * d) / den
    X = 0.5 * ((c1 + s[..., None] * d1) + (c2 + u[..., None] * d2))
    p1, z1 = _project(K1, T1, X)
    p2, z2 = _project(K2, T2, X)
    err = 0.5 * (np.linalg.norm(p1 - x1, axis=-1) + np.linalg.norm(p2 - x2, axis=-1))
    return np.where(ok & (z1 > 0) & (z2 > 0), err, np.inf)


def epipolar_distance(K1: F, T1: F, x1: F, K2: F, T2: F, x2: F) -> F:
    """Signed distance (px) of x2 (..., 2) from the epipolar line of x1 (..., 2) in view 2.

    Shapes as :func:`midpoint_reprojection_error`. The sign is that of ``l . x2`` with
    ``l = F x1``, so it is consistent for one pair of frames whatever the point's position.
    """
    T21 = np.linalg.inv(T2) @ T1  # view 1 camera -> view 2 camera
    R, t = T21[..., :3, :3], T21[..., :3, 3]
    tx = np.zeros(t.shape[:-1] + (3, 3))
    tx[..., 0, 1], tx[..., 0, 2] = -t[..., 2], t[..., 1]
    tx[..., 1, 0], tx[..., 1, 2] = t[..., 2], -t[..., 0]
    tx[..., 2, 0], tx[..., 2, 1] = -t[..., 1], t[..., 0]
    Fm = np.swapaxes(np.linalg.inv(K2), -1, -2) @ tx @ R @ np.linalg.inv(K1)
    h1 = np.concatenate([x1, np.ones(x1.shape[:-1] + (1,))], axis=-1)
    h2 = np.concatenate([x2, np.ones(x2.shape[:-1] + (1,))], axis=-1)
    line = np.einsum("...ij,...j->...i", Fm, h1)
    norm = np.maximum(np.linalg.norm(line[..., :2], axis=-1), 1e-12)
    return np.sum(line * h2, axis=-1) / norm


# --------------------------------------------------------------------------- search


def _pairs(T: int, T2: int, shift: NDArray[np.int64]) -> tuple[NDArray, NDArray, NDArray]:
    """(S, T) view-1 frames, view-2 frames ``t + s`` (clipped) and whether they exist."""
    t = np.arange(T)[None, :]
    t2 = t + shift[:, None]
    ok = (t2 >= 0) & (t2 < T2)
    return np.broadcast_to(t, t2.shape), np.clip(t2, 0, T2 - 1), ok


def shift_costs(K1: F, T1: F, kp1: F, K2: F, T2: F, kp2: F, shifts: NDArray, cfg: GeoSyncConfig = GeoSyncConfig(),
                chunk: int = 16) -> tuple[F, NDArray[np.int64]]:
    """Cost of every integer shift (view 2 frame ``t + s`` paired with view 1 frame ``t``).

    Args:
        K1, K2: (3, 3) intrinsics. T1: (T, 4, 4), T2: (T2, 4, 4) per-frame ``T_world_cam``.
        kp1: (T, J, 3), kp2: (T2, J, 3) keypoints (x, y, confidence).
        shifts: (S,) integer shifts to score.

    Returns:
        ``costs`` (S,) mean of ``min(err, clip_px)^2`` over the pairs (NaN where fewer than
        ``cfg.min_pairs`` pairs or less than ``cfg.min_overlap`` of the frames pair up) and
        ``counts`` (S,) pairs scored.
    """
    shifts = np.asarray(shifts, dtype=np.int64)
    T, Tv2 = len(kp1), len(kp2)
    costs = np.full(len(shifts), np.nan)
    counts = np.zeros(len(shifts), dtype=np.int64)
    for a in range(0, len(shifts), chunk):  # chunks bound memory on long sequences
        sh = shifts[a:a + chunk]
        t1, t2, ok = _pairs(T, Tv2, sh)
        k1, k2 = kp1[t1], kp2[t2]  # (s, T, J, 3)
        use = ok[..., None] & (k1[..., 2] >= cfg.min_keypoint_confidence) & (k2[..., 2] >= cfg.min_keypoint_confidence)
        err = midpoint_reprojection_error(K1, T1[t1][:, :, None], k1[..., :2], K2, T2[t2][:, :, None], k2[..., :2])
        e2 = np.minimum(err, cfg.clip_px) ** 2
        n = use.sum(axis=(1, 2))
        c = np.where(use, e2, 0.0).sum(axis=(1, 2)) / np.maximum(n, 1)
        frames_ok = ok.sum(axis=1) >= cfg.min_overlap * T
        costs[a:a + chunk] = np.where((n >= cfg.min_pairs) & frames_ok, c, np.nan)
        counts[a:a + chunk] = n
    return costs, counts


def subframe_shift(K1: F, T1: F, kp1: F, K2: F, T2: F, kp2: F, shift: int,
                   cfg: GeoSyncConfig = GeoSyncConfig(), iterations: int = 8) -> tuple[float, float, int]:
    """Fractional part of the offset around integer ``shift`` (module docstring, step 2).

    Returns:
        ``(f, std, pairs)``: the offset is ``shift + f`` frames with ``f`` in [-1, 1]; ``std`` its
        standard error in frames (inf when the performer does not move enough to tell); ``pairs``
        the joint pairs used.
    """
    T, Tv2 = len(kp1), len(kp2)
    t = np.arange(T)
    t2 = t + shift
    ok = (t2 - 2 >= 0) & (t2 + 2 < Tv2)
    t, t2 = t[ok], t2[ok]
    c = cfg.min_keypoint_confidence
    use = kp1[t, :, 2] >= c
    for k in range(-2, 3):
        use &= kp2[t2 + k, :, 2] >= c
    if not use.any():
        return 0.0, math.inf, 0
    x1 = kp1[t, :, :2]

    def d(k):
        return epipolar_distance(K1, T1[t][:, None], x1, K2, T2[k][:, None], kp2[k, :, :2])[use]

    dm2, dm1, d0, dp1, dp2 = (d(t2 + k) for k in range(-2, 3))
    # The slope of d in time, g, from the two neighbours; noise in g would shrink a plain least
    # squares answer towards 0 by g^2 / (g^2 + noise) -- badly when the performer moves slowly.
    # So the zero is found with an instrument z, the slope from the samples two frames away:
    # its noise is independent of g's and of d0's, so E[z g] is the true slope squared and
    # f = -sum(z d0) / sum(z g) is unbiased (view 1's noise is common to all five and cancels).
    g = 0.5 * (dp1 - dm1)
    z = 0.25 * (dp2 - dm2)
    good = np.isfinite(d0) & np.isfinite(g) & np.isfinite(z)
    d0, g, z = d0[good], g[good], z[good]
    if len(d0) < cfg.min_pairs:
        return 0.0, math.inf, int(len(d0))
    f = 0.0
    w = np.ones_like(d0)
    for _ in range(iterations):  # iteratively reweighted (Huber) instrumental-variable fit
        den = float(np.sum(w * z * g))
        if den <= 1e-9 * max(len(g), 1):
            return 0.0, math.inf, int(len(d0))
        f = float(-np.sum(w * z * d0) / den)
        r = np.abs(d0 + f * g)
        w = np.where(r <= cfg.huber_px, 1.0, cfg.huber_px / np.maximum(r, 1e-12))
    r = d0 + f * g
    dof = max(len(r) - 1, 1)
    sigma2 = float(np.sum(w * r * r) / dof)
    den = float(np.sum(w * z * g))
    std = math.sqrt(sigma2 * float(np.sum(w * w * z * z))) / den if den > 0 else math.inf
    return float(np.clip(f, -1.0, 1.0)), std, int(len(d0))


def geometric_sync(K1: F, T1: F, kp1: F, times1_s: F, K2: F, T2: F, kp2: F, times2_s: F, fps: float,
                   search_s: float, cfg: GeoSyncConfig = GeoSyncConfig()) -> GeoSyncResult:
    """The offset (seconds) that makes the two views' keypoint rays meet.

    Args:
        K1, K2: (3, 3) intrinsics of each view.
        T1: (T, 4, 4), T2: (T2, 4, 4) world cameras of each view's sequence frames.
        kp1: (T, J, 3), kp2: (T2, J, 3) the performer's keypoints (x, y, confidence).
        times1_s: (T,), times2_s: (T2,) each frame's time on its own view's clock, seconds after
            the view's slicing event (a view at a steady rate has ``k / fps``).
        fps: the sequence frame rate.
        search_s: half-width of the searched offsets, seconds.

    Returns:
        :class:`GeoSyncResult` (``found`` False with a message when nothing could be scored).
    """
    kp1, kp2 = np.asarray(kp1, float), np.asarray(kp2, float)
    T1, T2 = np.asarray(T1, float), np.asarray(T2, float)
    if kp1.ndim != 3 or kp2.ndim != 3 or len(T1) != len(kp1) or len(T2) != len(kp2):
        raise ValueError(f"shapes: kp1 {kp1.shape}, T1 {T1.shape}, kp2 {kp2.shape}, T2 {T2.shape}")
    S = max(int(math.ceil(search_s * fps)), 1)
    shifts = np.arange(-S, S + 1)
    costs, counts = shift_costs(K1, T1, kp1, K2, T2, kp2, shifts, cfg)

    def none(msg: str) -> GeoSyncResult:
        return GeoSyncResult(math.nan, math.nan, 0, 0.0, math.inf, math.nan, 0, shifts, costs, counts, msg)

    if not np.isfinite(costs).any():
        return none(f"no shift within +-{search_s:g} s pairs {cfg.min_pairs} joints seen in both views")
    i = int(np.nanargmin(costs))
    s = int(shifts[i])
    far = np.abs(shifts - s) >= cfg.distinct_frames
    second = np.nanmin(costs[far]) if np.isfinite(costs[far]).any() else np.nan
    distinct = float(np.clip(1.0 - costs[i] / second, 0.0, 1.0)) if np.isfinite(second) and second > 0 else 0.0
    f, std, n = subframe_shift(K1, T1, kp1, K2, T2, kp2, s, cfg)
    for _ in range(2):  # the zero lies nearer a neighbour: centre the linearisation there
        if abs(f) <= 0.5 or not math.isfinite(std):
            break
        s2 = s + int(np.sign(f))
        f2, std2, n2 = subframe_shift(K1, T1, kp1, K2, T2, kp2, s2, cfg)
        if not math.isfinite(std2):
            break
        s, f, std, n = s2, f2, std2, n2
    if not math.isfinite(std):
        f, std = 0.0, math.inf
    precise = math.exp(-((std / 0.25) ** 2)) if math.isfinite(std) else 0.0
    offset_frames = s + f
    # Seconds from the views' own clocks: the paired frames' time difference at the integer shift
    # (dropped frames and unequal rates included), plus the fraction of a frame.
    t = np.arange(len(kp1))
    t2 = t + s
    ok = (t2 >= 0) & (t2 < len(kp2))
    t1s, t2s = np.asarray(times1_s, float), np.asarray(times2_s, float)
    base = float(np.median(t2s[t2[ok]] - t1s[t[ok]])) if ok.any() else s / fps
    return GeoSyncResult(base + f / fps, offset_frames, s, distinct * precise, std, float(np.sqrt(costs[i])), n,
                         shifts, costs, counts)
