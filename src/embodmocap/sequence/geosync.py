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
   epipolar line of view 1's, the only direction that timing can change, in the frames around the
   best shift (each with its own camera): a parabola through them gives the value and slope at the
   centre, ``d(f) ~ a + b f``, view 2's keypoint interpolated in time, and ``f`` is the robust
   instrumental-variable zero of all pairs' lines (unbiased by noise, see the function); the same
   is done with the views' roles swapped and the two are averaged (each way alone leans a little
   towards its interpolated view's earlier frames); if it leaves ``[-0.5, 0.5]`` the centre moves
   to the neighbour and the fit is repeated.
3. **Confidence**: how distinct the minimum is (how many standard errors the best cost lies below
   its strongest rival: another local minimum ``distinct_s`` or more away, or the rim of the
   searched range) times how precise the sub-frame fit is (its standard error); a performer
   standing still gives a flat, bumpy cost and a low confidence, never a wrong confident answer.

The result is an offset in **seconds**: the instant view 1 films at its time ``t`` (seconds after
its slicing event) is filmed by view 2 at its time ``t + offset_s``.

Every function is pure and vectorised over frames, joints and shifts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.raycast import pixel_rays
from embodmocap.parallel import map_in_threads

F = NDArray[np.floating]

#: Version of the algorithm (in Stage III's fingerprint: a change redoes the step).
GEOSYNC_VERSION = 5


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
    huber_px: float = 3.0
    """Huber threshold of the sub-frame fit's epipolar residuals, pixels."""
    consistency_parts: int = 4
    """The sub-frame fit is repeated on this many consecutive parts of the sequence; parts that
    disagree beyond their errors (a camera error imitating a time offset) widen the error."""
    window_frames: int = 3
    """Half-width of the time window through which view 2's keypoints are interpolated in the
    sub-frame fit (a line through 2W+1 samples), frames; the instrument uses the next W+1."""
    min_pairs: int = 60
    """Fewest joint pairs seen in both views at a shift for that shift to be scored."""
    min_overlap: float = 0.5
    """A shift must pair at least this fraction of the sequence's frames."""
    distinct_s: float = 0.2
    """Rival minima of the cost curve are looked for at least this far from the best, seconds
    (confidence)."""
    distinct_sigmas: tuple[float, float] = (2.0, 6.0)
    """The best cost this many standard errors below the second best gives a distinctness of 0 /
    1 (linear in between; part of the confidence)."""
    min_confidence: float = 0.3
    """Geometric results below this confidence are reported but never chosen."""
    agree_frames: float = 1.0
    """Laser and geometric offsets further apart than this (frames) are a warning."""
    laser_dot_agree_m: float = 0.15
    """The two views' last sightings of the laser dot, put in the scene's world, further apart than
    this (metres) are two different spots (a speck of texture taken for the dot in a view): the
    laser offset is then not used (see :mod:`embodmocap.sequence.laser_check`)."""
    prefer: str = "auto"
    """Which source wins when both exist: ``auto`` (geometric when it agrees with the laser within
    ``agree_frames``, when it disagrees with every laser candidate at confidence >=
    ``override_confidence``, or when it is more confident than the laser; else laser), ``laser``
    or ``geometric``."""
    override_confidence: float = 0.6
    """A geometric offset at least this confident that no pair of laser events agrees with (within
    ``agree_frames``) replaces the laser, with a warning; below it the more confident source wins."""
    pair_cost_ratio: float = 0.9
    """A geometric sync not confident enough to give the offset still chooses between pairs of
    laser events: the pair whose shift has the lowest reprojection cost (best of the shifts within
    a frame of it) wins when that cost is at most this fraction of every other pair's. Pairs are
    seconds apart, where the cost differs by far more than between neighbouring shifts."""
    manual_error_frames: float = 5.0
    """Manual ``sync_frame`` values that a confident geometric sync (>= ``manual_error_confidence``)
    puts further off than this many frames are an error (``sync_force = true`` in session.toml keeps
    them); between ``agree_frames`` and this, a warning."""
    manual_error_confidence: float = 0.8
    """Confidence of the geometric sync above which it may call manual sync frames wrong."""
    subframe_shrink: bool = True
    """When the geometric offset agrees with laser or manual frames, apply the expected sub-frame
    residual given both, not the geometric one alone: the frames put it within a frame (each view
    quantises the event to its own frame clock: a triangular spread on (-1, 1) frame), the geometry
    measures it with ``std_frames``; an imprecise measurement is shrunk towards the frames'
    (:func:`embodmocap.sequence.sync_record.subframe_residual`). False = the geometric value as is."""

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
    return _midpoint_error(_Rays.of(K1, T1, x1), _Rays.of(K2, T2, x2))


def _dot(a: F, b: F) -> F:
    """``sum(a * b, axis=-1)`` of (..., 3) arrays as three products (no reduction loop)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


@dataclass(frozen=True)
class _Rays:
    """Keypoint rays of one view: camera centres c (..., 3), unit directions d (..., 3), the
    pixels xy (..., 2) and ``A = K R^T`` (..., 3, 3), world offsets from the centre -> homogeneous
    pixels (its last row gives the depth). Taken once per frame and joint, then indexed by frame
    for every pairing of the two views' frames."""

    c: F
    d: F
    xy: F
    A: F

    @staticmethod
    def of(K: F, T_world_cam: F, xy: F) -> "_Rays":
        c, d = pixel_rays(K, T_world_cam, xy)
        A = np.asarray(K) @ np.swapaxes(np.asarray(T_world_cam)[..., :3, :3], -1, -2)
        return _Rays(np.asarray(T_world_cam)[..., :3, 3], d, np.asarray(xy), A)

    def frames(self, t: NDArray) -> "_Rays":
        """Frames ``t`` of per-frame rays (c, A of shape (T, 1, ...), d, xy (T, J, ...))."""
        return _Rays(self.c[t], self.d[t], self.xy[t], self.A[t])


def _midpoint_error(r1: _Rays, r2: _Rays) -> F:
    """:func:`midpoint_reprojection_error` of two sets of rays (shapes broadcast)."""
    c1, d1, c2, d2 = r1.c, r1.d, r2.c, r2.d
    w0 = c1 - c2
    b = _dot(d1, d2)
    d = _dot(d1, w0)
    e = _dot(d2, w0)
    den = 1.0 - b * b  # unit directions: a = c = 1
    ok = den > 1e-8
    den = np.where(ok, den, 1.0)
    s = (b * e - d) / den
    u = (e - b * d) / den
    X = 0.5 * ((c1 + s[..., None] * d1) + (c2 + u[..., None] * d2))
    err = 0.0
    for r in (r1, r2):
        q = X - r.c
        A = r.A
        z = A[..., 2, 0] * q[..., 0] + A[..., 2, 1] * q[..., 1] + A[..., 2, 2] * q[..., 2]
        zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
        du = (A[..., 0, 0] * q[..., 0] + A[..., 0, 1] * q[..., 1] + A[..., 0, 2] * q[..., 2]) / zs - r.xy[..., 0]
        dv = (A[..., 1, 0] * q[..., 0] + A[..., 1, 1] * q[..., 1] + A[..., 1, 2] * q[..., 2]) / zs - r.xy[..., 1]
        err = err + np.sqrt(du * du + dv * dv)
        ok = ok & (z > 0)
    return np.where(ok, 0.5 * err, np.inf)


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
    # line = Fm [x1, 1], as explicit products (broadcast frames against joints)
    u1, v1 = x1[..., 0], x1[..., 1]
    la, lb, lc = (Fm[..., i, 0] * u1 + Fm[..., i, 1] * v1 + Fm[..., i, 2] for i in range(3))
    norm = np.maximum(np.sqrt(la * la + lb * lb), 1e-12)
    return (la * x2[..., 0] + lb * x2[..., 1] + lc) / norm


# --------------------------------------------------------------------------- search


def _pairs(T: int, T2: int, shift: NDArray[np.int64]) -> tuple[NDArray, NDArray, NDArray]:
    """(S, T) view-1 frames, view-2 frames ``t + s`` (clipped) and whether they exist."""
    t = np.arange(T)[None, :]
    t2 = t + shift[:, None]
    ok = (t2 >= 0) & (t2 < T2)
    return np.broadcast_to(t, t2.shape), np.clip(t2, 0, T2 - 1), ok


def shift_costs(K1: F, T1: F, kp1: F, K2: F, T2: F, kp2: F, shifts: NDArray, cfg: GeoSyncConfig = GeoSyncConfig(),
                chunk: int = 16, return_var: bool = False, threads: int | None = None):
    """Cost of every integer shift (view 2 frame ``t + s`` paired with view 1 frame ``t``).

    Args:
        K1, K2: (3, 3) intrinsics. T1: (T, 4, 4), T2: (T2, 4, 4) per-frame ``T_world_cam``.
        kp1: (T, J, 3), kp2: (T2, J, 3) keypoints (x, y, confidence).
        shifts: (S,) integer shifts to score.

    Returns:
        ``costs`` (S,) mean of ``min(err, clip_px)^2`` over the pairs (NaN where fewer than
        ``cfg.min_pairs`` pairs or less than ``cfg.min_overlap`` of the frames pair up) and
        ``counts`` (S,) pairs scored; with ``return_var`` also (S,) the variance of the clipped
        squared errors (the cost's standard error is ``sqrt(var / counts)``).

    The chunks of ``chunk`` shifts are scored on ``threads`` threads (:func:`embodmocap.parallel.lent_cores`
    when None); each is computed as alone, so the costs do not depend on the threads.
    """
    shifts = np.asarray(shifts, dtype=np.int64)
    T, Tv2 = len(kp1), len(kp2)
    rays1, rays2 = _frame_rays(K1, T1, kp1), _frame_rays(K2, T2, kp2)
    costs = np.full(len(shifts), np.nan)
    counts = np.zeros(len(shifts), dtype=np.int64)
    var = np.full(len(shifts), np.nan)

    def score(a: int) -> tuple[F, F, F]:
        """The chunk of shifts from ``a``: costs, variances, counts."""
        t1, t2, ok = _pairs(T, Tv2, shifts[a:a + chunk])
        k1, k2 = kp1[t1], kp2[t2]  # (s, T, J, 3)
        use = ok[..., None] & (k1[..., 2] >= cfg.min_keypoint_confidence) & (k2[..., 2] >= cfg.min_keypoint_confidence)
        err = _midpoint_error(rays1.frames(t1), rays2.frames(t2))
        e2 = np.minimum(err, cfg.clip_px) ** 2
        n = use.sum(axis=(1, 2))
        c = np.where(use, e2, 0.0).sum(axis=(1, 2)) / np.maximum(n, 1)
        v = np.where(use, e2 * e2, 0.0).sum(axis=(1, 2)) / np.maximum(n, 1) - c * c
        frames_ok = ok.sum(axis=1) >= cfg.min_overlap * T
        return np.where((n >= cfg.min_pairs) & frames_ok, c, np.nan), v, n

    starts = range(0, len(shifts), chunk)  # chunks bound memory on long sequences
    for a, (c, v, n) in zip(starts, map_in_threads(score, starts, threads)):
        costs[a:a + chunk], var[a:a + chunk], counts[a:a + chunk] = c, v, n
    return (costs, counts, var) if return_var else (costs, counts)


def _frame_rays(K: F, T_world_cam: F, kp: F) -> _Rays:
    """:class:`_Rays` of every frame (T) and joint (J) of keypoints kp (T, J, 3)."""
    return _Rays.of(K, np.asarray(T_world_cam)[:, None], kp[..., :2])


def _distinctness(K1: F, T1: F, kp1: F, K2: F, T2: F, kp2: F, shifts: NDArray, costs: F, i: int, far_frames: int,
                  cfg: GeoSyncConfig) -> float:
    """In [0, 1]: how clearly shift ``i`` beats the strongest rival, the lowest other local minimum of
    the cost curve at least ``far_frames`` away (another instant the motion repeats, or noise on a
    flat curve); with no rival (one bowl), the lower rim of the scored range. Judged in standard
    errors of the pair-by-pair cost difference (both shifts share view 1's detections), mapped
    linearly from ``distinct_sigmas[0]`` (0) to ``[1]`` (1)."""
    c = np.where(np.isfinite(costs), costs, np.inf)
    lower_left = np.r_[True, c[1:] < c[:-1]]
    lower_right = np.r_[c[:-1] < c[1:], True]
    minima = np.flatnonzero(lower_left & lower_right & np.isfinite(c) & (np.abs(shifts - shifts[i]) >= far_frames))
    finite = np.flatnonzero(np.isfinite(costs))
    rivals = minima if len(minima) else np.array([finite[0], finite[-1]])
    rivals = rivals[np.abs(shifts[rivals] - shifts[i]) >= far_frames]
    if not len(rivals):
        return 0.0  # the scored range is too narrow to tell
    j = int(rivals[np.argmin(c[rivals])])
    e_best, e_rival = map_in_threads(lambda k: _pair_sq_errors(K1, T1, kp1, K2, T2, kp2, int(shifts[k]), cfg), (i, j))
    both = np.isfinite(e_best) & np.isfinite(e_rival)
    diff = (e_rival - e_best)[both]
    if len(diff) < 2:
        return 0.0
    z = float(np.mean(diff)) / max(float(np.std(diff)) / math.sqrt(len(diff)), 1e-12)
    lo, hi = cfg.distinct_sigmas
    return float(np.clip((z - lo) / (hi - lo), 0.0, 1.0))


def _pair_sq_errors(K1: F, T1: F, kp1: F, K2: F, T2: F, kp2: F, shift: int, cfg: GeoSyncConfig) -> F:
    """(T, J) clipped squared reprojection error of every pair at one shift; NaN where unused."""
    t1, t2, ok = _pairs(len(kp1), len(kp2), np.array([shift]))
    k1, k2 = kp1[t1[0]], kp2[t2[0]]
    use = ok[0][:, None] & (k1[..., 2] >= cfg.min_keypoint_confidence) & (k2[..., 2] >= cfg.min_keypoint_confidence)
    err = _midpoint_error(_frame_rays(K1, T1, kp1).frames(t1[0]), _frame_rays(K2, T2, kp2).frames(t2[0]))
    return np.where(use, np.minimum(err, cfg.clip_px) ** 2, np.nan)


def subframe_shift(K1: F, T1: F, kp1: F, K2: F, T2: F, kp2: F, shift: int,
                   cfg: GeoSyncConfig = GeoSyncConfig(), iterations: int = 8) -> tuple[float, float, int]:
    """Fractional part of the offset around integer ``shift`` (module docstring, step 2), the mean
    of both directions: view 2's keypoints interpolated against view 1's epipolar lines
    (:func:`subframe_one_way`) and view 1's against view 2's (the offset's sign flipped).

    One way alone leans towards the interpolated view's earlier frames by up to a tenth of a frame
    with the studio's detector noise (its seed-to-seed mean on the same motion; the other way leans
    as much towards its later frames), and it uses only the pairs whose window the interpolated
    view sees whole. The two means cancel that lean to first order. The standard error is the
    larger of the two ways' mean error (they share data, so no sqrt(2) gain is claimed) and half
    their difference (a difference beyond their errors is an error the estimate carries).

    Returns:
        ``(f, std, pairs)`` as :func:`subframe_one_way`; one way alone where the other has no
        estimate.
    """
    (f1, s1, n1), (f2, s2, n2) = map_in_threads(lambda way: subframe_one_way(*way, cfg, iterations), [
        (K1, T1, kp1, K2, T2, kp2, shift), (K2, T2, kp2, K1, T1, kp1, -shift)])
    if not math.isfinite(s2):
        return f1, s1, n1
    if not math.isfinite(s1):
        return -f2, s2, n2
    f = 0.5 * (f1 - f2)
    return f, max(0.5 * (s1 + s2), 0.5 * abs(f1 + f2)), n1 + n2


def subframe_one_way(K1: F, T1: F, kp1: F, K2: F, T2: F, kp2: F, shift: int,
                     cfg: GeoSyncConfig = GeoSyncConfig(), iterations: int = 8) -> tuple[float, float, int]:
    """Fractional part of the offset around integer ``shift`` from view 2's keypoints interpolated
    in time against view 1's epipolar lines.

    For each pair (view 1 frame t, joint), ``d(k)`` is the signed epipolar distance of view 2's
    keypoint in frame ``t + shift + k``. A parabola through ``d(-W..W)`` (``W`` =
    ``cfg.window_frames``) gives the value ``a`` and slope ``b`` at ``k = 0``: view 2's keypoint
    interpolated in time, ``d(f) ~ a + b f``, with the noise of ``a`` cut by ``sqrt(3)`` (W = 3)
    and free of the curvature a straight line's value at ``k = 0`` carries (symmetric window:
    ``a`` and ``b`` have independent noise). Noise in ``b`` would shrink a plain
    least-squares ``f`` towards 0 (badly when the performer moves a pixel a frame against pixels of
    detector noise), so the zero is an instrumental-variable fit with the slope ``z`` from the
    samples just outside the window (``W+1..2W+2`` frames away): its noise is independent of ``a``'s
    and ``b``'s, so ``f = -sum(z a) / sum(z b)`` is unbiased. View 1's noise is common to all the
    samples of a pair and cancels in the slopes, but it tilts the pair's epipolar line, so the
    instrument's lines come from view 1's detections in the neighbouring frames. Huber weights on ``a + f b`` and a screen on each
    pair's line-fit residual keep outlier detections out.

    Returns:
        ``(f, std, pairs)``: the offset is ``shift + f`` frames with ``f`` in [-1, 1]; ``std`` its
        standard error in frames (inf when the performer does not move enough to tell); ``pairs``
        the joint pairs used.
    """
    W = int(cfg.window_frames)
    R = 2 * W + 2  # farthest sample of the instrument
    T, Tv2 = len(kp1), len(kp2)
    t = np.arange(T)
    t2 = t + shift
    ok = (t2 - R >= 0) & (t2 + R < Tv2) & (t >= 1) & (t + 1 < T)
    t, t2 = t[ok], t2[ok]
    c = cfg.min_keypoint_confidence
    use = (kp1[t, :, 2] >= c) & (kp1[t - 1, :, 2] >= c) & (kp1[t + 1, :, 2] >= c)
    for k in range(-R, R + 1):
        use &= kp2[t2 + k, :, 2] >= c
    if not use.any():
        return 0.0, math.inf, 0
    x1 = kp1[t, :, :2]
    ks = np.arange(-R, R + 1)
    # (n, 2R+1) epipolar distances of every used pair at every sample of its window.
    D = np.stack([epipolar_distance(K1, T1[t][:, None], x1, K2, T2[t2 + k][:, None], kp2[t2 + k, :, :2])[use]
                  for k in ks], axis=-1)
    inner = np.abs(ks) <= W
    kin = ks[inner].astype(float)
    # The value at k = 0 of a parabola through the window, not of a line: a line's value there is
    # the window's mean, d(0) + d''(0) * mean(k^2) / 2, which a limb that speeds up or slows down
    # moves by pixels, and the weighted sum over pairs does not cancel it (measured: -0.06 to -0.25
    # frame with 4 px detector noise and W = 3..5; the parabola's value: within +-0.02). The
    # slope of a symmetric window is the same for a line and a parabola.
    k2 = kin * kin
    n_in, s2, s4 = len(kin), float(k2.sum()), float((k2 * k2).sum())
    a = (s4 * D[:, inner].sum(axis=1) - s2 * (D[:, inner] @ k2)) / (n_in * s4 - s2 * s2)
    b = D[:, inner] @ kin / np.sum(kin * kin)
    outer = ks[ks > W].astype(float)
    # The instrument's epipolar lines come from view 1's neighbouring detections (frames t -+ 1),
    # not from frame t's: the noise of x1 tilts its line, which moves a and a slope taken against
    # the same line together (a second-order bias, about -0.1 frame with 4 px of noise in view 1
    # alone); with independent noise in the instrument's lines it averages out.
    xz = 0.5 * (kp1[t - 1, :, :2] + kp1[t + 1, :, :2])
    Dz = np.stack([epipolar_distance(K1, T1[t][:, None], xz, K2, T2[t2 + k][:, None], kp2[t2 + k, :, :2])[use]
                   for k in ks[np.abs(ks) > W]], axis=-1)
    far = ks[np.abs(ks) > W]
    pos, neg = Dz[:, far > 0], Dz[:, far < 0][:, ::-1]  # neg column j is -outer[j]
    z = (pos - neg) @ outer / (2.0 * np.sum(outer * outer))
    fit_rms = np.sqrt(np.mean((D[:, inner] - D[:, inner].mean(axis=1, keepdims=True) - b[:, None] * kin) ** 2, axis=1))
    good = np.isfinite(a) & np.isfinite(b) & np.isfinite(z) & np.isfinite(fit_rms)
    a, b, z, fit_rms = a[good], b[good], z[good], fit_rms[good]
    if len(a) < cfg.min_pairs:
        return 0.0, math.inf, int(len(a))
    # A detection off by tens of pixels in one sample bends the pair's line: leave such pairs out.
    keep = fit_rms <= 3.0 * max(float(np.median(fit_rms)), 1e-6)
    a, b, z = a[keep], b[keep], z[keep]
    frame = np.broadcast_to(np.arange(len(t))[:, None], use.shape)[use][good][keep]
    if len(a) < cfg.min_pairs:
        return 0.0, math.inf, int(len(a))
    f, std, w = _iv_fit(a, b, z, cfg.huber_px, iterations)
    if not math.isfinite(std):
        return 0.0, math.inf, int(len(a))
    # A small camera error mimics a time offset while the performer moves one way; when the
    # motion changes direction the imitation changes. So the fit is repeated on consecutive
    # parts of the sequence, and parts that disagree beyond their own errors widen the error.
    parts = np.array_split(np.unique(frame), cfg.consistency_parts)
    fs, ss = [], []
    for p in parts:
        sel = np.isin(frame, p)
        if sel.sum() >= max(cfg.min_pairs // 2, 10):
            fp, sp, _ = _iv_fit(a[sel], b[sel], z[sel], cfg.huber_px, iterations)
            if math.isfinite(sp):
                fs.append(fp)
                ss.append(sp)
    if len(fs) >= 2:
        fs, ss = np.array(fs), np.array(ss)
        chi2 = float(np.sum(((fs - f) / ss) ** 2)) / (len(fs) - 1)
        std *= math.sqrt(max(1.0, chi2))
    return float(np.clip(f, -1.0, 1.0)), std, int(len(a))


def _iv_fit(a: F, b: F, z: F, huber_px: float, iterations: int) -> tuple[float, float, F]:
    """Zero ``f`` of the lines ``a + b f`` with instrument ``z`` (Huber-reweighted), its standard
    error and the final weights; ``(0, inf, w)`` when the slopes carry no information."""
    f = 0.0
    w = np.ones_like(a)
    for _ in range(iterations):
        den = float(np.sum(w * z * b))
        if den <= 1e-9 * max(len(b), 1):
            return 0.0, math.inf, w
        f = float(-np.sum(w * z * a) / den)
        r = np.abs(a + f * b)
        w = np.where(r <= huber_px, 1.0, huber_px / np.maximum(r, 1e-12))
    r = a + f * b
    sigma2 = float(np.sum(w * r * r) / max(len(r) - 1, 1))
    den = float(np.sum(w * z * b))
    std = math.sqrt(sigma2 * float(np.sum(w * w * z * z))) / den if den > 0 else math.inf
    return f, std, w


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
    costs, counts, var = shift_costs(K1, T1, kp1, K2, T2, kp2, shifts, cfg, return_var=True)

    def none(msg: str) -> GeoSyncResult:
        return GeoSyncResult(math.nan, math.nan, 0, 0.0, math.inf, math.nan, 0, shifts, costs, counts, msg)

    if not np.isfinite(costs).any():
        return none(f"no shift within +-{search_s:g} s pairs {cfg.min_pairs} joints seen in both views")
    i = int(np.nanargmin(costs))
    s = int(shifts[i])
    distinct = _distinctness(K1, T1, kp1, K2, T2, kp2, shifts, costs, i, max(1, math.ceil(cfg.distinct_s * fps - 1e-9)), cfg)
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
    # Precision on the scale of a laser sync's own error (each view quantises the event to its own
    # frame clock: the difference of two uniform quantisations, sqrt(2/12) ~ 0.41 frame): a
    # geometric offset about as precise as that is worth choosing. (0.3 before the standard error
    # was made honest, session 10: it is now 1.3-2 times larger, and 0.3 dropped a right
    # geometric override of a false laser event below min_confidence.)
    precise = math.exp(-((std / 0.41) ** 2)) if math.isfinite(std) else 0.0
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
