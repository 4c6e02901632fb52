"""Chunk stitching: each chunk aligned to the previous one by a confidence-weighted Umeyama
similarity on the overlapping frames' points and camera centres, composed recursively.

Chunk ``k`` predicts, in its own frame, poses ``T^k_i`` and local points ``p^k_i(u)``; its world
points are ``X^k_i(u) = R^k_i p^k_i(u) + c^k_i``. With ``S_k`` (4x4 similarity) mapping chunk ``k``
into the stitched frame (``S_0 = I``), chunk ``k`` is aligned on the frames ``O`` it shares with
chunk ``k-1``:

    S_k = argmin_S  sum_{i in O, u}  w_i(u) |S_(k-1) X^(k-1)_i(u) - S X^k_i(u)|^2
                  + lambda sum_{i in O} |S_(k-1) c^(k-1)_i - S c^k_i|^2

with ``w_i(u) = sqrt(conf^(k-1)_i(u) conf^k_i(u))`` on a regular pixel grid (pixels below
``min_conf`` in either chunk left out), ``lambda`` giving the centres ``centre_weight`` of the
total weight, solved in closed form (:func:`~embodmocap.geometry.similarity.weighted_umeyama`)
and re-weighted with a Cauchy kernel against outliers; the scale is then taken as the ratio of
the two sides' weighted spreads (:func:`symmetric_scale`: least squares shrinks a noisy chunk and
the shrinkage compounds along the video). Writing ``Y = S_(k-1) X^(k-1)`` (already
stitched) makes the composition implicit: ``S_k = S_(k-1) S_(k-1 <- k)``.

An alignment that cannot be trusted (too few overlapping frames or points, a residual over
``max_rel_residual`` of the scene's depth, point maps of different sizes), and a chunk the scene
model failed on (SfM: no model) and the one after it, start a new *segment* (``S_k = I`` in a frame of its own) with a warning; never a silent jump.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.similarity import (apply_similarity, robust_umeyama, similarity_matrix, transform_poses,
                                            weighted_umeyama)
from embodmocap.mono.config import StitchConfig
from embodmocap.mono.files import ChunkPrediction
from embodmocap.mono.roles import SceneModel
from embodmocap.progress import progress

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ChunkRecord:
    """How one chunk was placed (what ``mono_manifest.json`` lists).

    Attributes:
        start, end: sequence frames ``[start, end)``.
        segment: the segment it belongs to.
        S: (4, 4) similarity chunk frame -> segment's stitched frame.
        aligned: placed by an overlap alignment (False for a segment's first chunk).
        overlap_frames, overlap_points: what the alignment used.
        residual_rel: weighted median point residual / median point depth (NaN if not aligned).
        reason: why a new segment started here ("" otherwise).
    """

    start: int
    end: int
    segment: int
    S: NDArray[np.float64]
    aligned: bool
    overlap_frames: int = 0
    overlap_points: int = 0
    residual_rel: float = float("nan")
    reason: str = ""

    def as_json(self) -> dict:
        s = float(np.cbrt(np.linalg.det(self.S[:3, :3])))
        return {"start": self.start, "end": self.end, "segment": self.segment, "aligned": self.aligned,
                "scale": round(s, 6), "S": np.round(self.S, 6).tolist(), "overlap_frames": self.overlap_frames,
                "overlap_points": self.overlap_points,
                "residual_rel": None if not np.isfinite(self.residual_rel) else round(self.residual_rel, 5),
                **({"reason": self.reason} if self.reason else {})}


@dataclass
class StitchResult:
    """Every frame's pose in its segment's stitched frame (units of the segment's first chunk).

    Attributes:
        T_stitch_cam: (T, 4, 4) rigid camera-to-stitched poses.
        segment: (T,) segment of each frame.
        chunk_scale: (T,) scale of the similarity of the chunk that placed each frame (local
            point maps times this are in stitched units).
        chunks: one record per chunk.
        warnings: one line per segment break.
        metric: the scene model's units are metres.
        failed: (T,) bool, frames placed by a chunk the scene model failed on (their poses are
            meaningless: no metric scale, flagged invalid).
    """

    T_stitch_cam: NDArray[np.float64]
    segment: NDArray[np.int64]
    chunk_scale: NDArray[np.float64]
    chunks: list[ChunkRecord] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    metric: bool = False
    failed: NDArray[np.bool_] | None = None


#: Called after each chunk is placed: (prediction, S_k, indices of the frames it owns, segment).
Visit = Callable[[ChunkPrediction, NDArray, NDArray, int], None]


def grid(H: int, W: int, n: int) -> tuple[NDArray, NDArray]:
    """Row and column indices of a regular grid of about ``n`` pixels over an (H, W) map."""
    step = max(1, int(round(np.sqrt(H * W / max(n, 1)))))
    return np.arange(step // 2, H, step), np.arange(step // 2, W, step)


def align_overlap(Y: NDArray, conf_y: NDArray, cy: NDArray, X: NDArray, conf_x: NDArray, cx: NDArray,
                  cfg: StitchConfig) -> tuple[NDArray | None, dict]:
    """The similarity taking the new chunk's overlap onto the stitched one.

    Args:
        Y: (n, h, w, 3) stitched points of the overlapping frames (grid-sampled); ``conf_y`` (n, h, w).
        cy: (n, 3) their stitched camera centres.
        X: (n, h, w, 3) the new chunk's world points of the same frames and pixels; ``conf_x``.
        cx: (n, 3) the new chunk's camera centres.

    Returns:
        ``S`` (4, 4) or None when refused, and a dict: ``points``, ``residual_rel``, ``reason``.
    """
    n = len(Y)
    info = {"points": 0, "residual_rel": float("nan"), "reason": ""}
    if n < cfg.min_overlap_frames:
        info["reason"] = f"{n} overlapping frames (< {cfg.min_overlap_frames})"
        return None, info
    if Y.shape != X.shape:
        info["reason"] = f"point maps of different sizes {Y.shape[1:3]} vs {X.shape[1:3]}"
        return None, info
    ok = (conf_y >= cfg.min_conf) & (conf_x >= cfg.min_conf)
    ok &= np.all(np.isfinite(Y), axis=-1) & np.all(np.isfinite(X), axis=-1)
    info["points"] = int(ok.sum())
    if ok.sum() < cfg.min_points:
        info["reason"] = f"{int(ok.sum())} usable overlap points (< {cfg.min_points})"
        return None, info
    w = np.sqrt(conf_y[ok] * conf_x[ok]).astype(np.float64)
    src, dst = X[ok].astype(np.float64), Y[ok].astype(np.float64)
    wc = np.full(n, cfg.centre_weight / max(1 - cfg.centre_weight, 1e-9) * w.sum() / n)
    src_all, dst_all, w_all = np.concatenate([src, cx]), np.concatenate([dst, cy]), np.concatenate([w, wc])
    if cfg.robust_iterations > 0:
        s, R, t, w_fin = robust_umeyama(src_all, dst_all, w_all, iterations=cfg.robust_iterations)
    else:
        s, R, t = weighted_umeyama(src_all, dst_all, w_all)
        w_fin = w_all
    if cfg.symmetric_scale:
        s, t = symmetric_scale(src_all, dst_all, w_fin, R)
    S = similarity_matrix(s, R, t)
    r = np.linalg.norm(apply_similarity(S, src) - dst, axis=-1)
    frame_of = np.broadcast_to(np.arange(n)[:, None, None], ok.shape)[ok]
    depth = np.linalg.norm(dst - cy[frame_of], axis=-1)
    rel = float(_wmedian(r, w) / max(np.median(depth), 1e-12))
    info["residual_rel"] = rel
    if not np.isfinite(rel) or rel > cfg.max_rel_residual or not (np.isfinite(s) and s > 0):
        info["reason"] = f"overlap residual {rel:.3f} of the scene depth (> {cfg.max_rel_residual})"
        return None, info
    return S, info


def symmetric_scale(src: NDArray, dst: NDArray, w: NDArray, R: NDArray) -> tuple[float, NDArray]:
    """Scale and translation of the alignment with ``R`` fixed, from the ratio of the weighted
    spreads: ``s = sqrt(Σ w |y − μ_y|² / Σ w |x − μ_x|²)``, ``t = μ_y − s R μ_x``.

    Umeyama's least-squares scale ``tr(D E) / var_x`` is attenuated when ``x`` is noisy (its
    variance holds the noise too): with both chunks' points noisy, each alignment shrinks the new
    chunk a little and the shrinkage compounds along the video (a 60 s studio view: the local
    scale drifted from −1.4 % to +1.2 % of the global one). Both sides carry noise in proportion to
    their own units (a point-map model's relative depth noise), so the spread ratio is unbiased;
    on noise-free points it equals Umeyama's.
    """
    W = w.sum()
    mx, my = (w[:, None] * src).sum(0) / W, (w[:, None] * dst).sum(0) / W
    vx = (w * ((src - mx) ** 2).sum(1)).sum() / W
    vy = (w * ((dst - my) ** 2).sum(1)).sum() / W
    s = float(np.sqrt(vy / max(vx, 1e-300)))
    return s, my - s * R @ mx


def _wmedian(x: NDArray, w: NDArray) -> float:
    o = np.argsort(x)
    cw = np.cumsum(w[o])
    return float(x[o][min(np.searchsorted(cw, 0.5 * cw[-1]), len(x) - 1)])


def stitch(model: SceneModel, plan: list[tuple[int, int]], cfg: StitchConfig, visit: Visit | None = None) -> StitchResult:
    """Run the scene model chunk by chunk and place every chunk (see the module's equations).

    Only the previous chunk's overlap (grid-sampled) is kept between chunks, so memory does not
    grow with the video; ``visit`` sees each chunk's full prediction once, after it is placed.
    """
    T = plan[-1][1] if plan else 0
    res = StitchResult(np.tile(np.eye(4), (T, 1, 1)), np.zeros(T, np.int64), np.ones(T), failed=np.zeros(T, bool))
    owned_until = 0
    segment = -1
    prev = None  # (frames (n,), Y (n,h,w,3), conf (n,h,w), centres (n,3), rows, cols)
    for start, end in progress(plan, "mono: scene model", unit="chunk"):
        frames = np.arange(start, end, dtype=np.int64)
        pred = model.predict(frames)
        res.metric = res.metric or pred.metric
        H, W = pred.conf.shape[1:]
        rows, cols = grid(H, W, cfg.points_per_frame)
        S, info, reason = None, {"points": 0, "residual_rel": float("nan")}, "first chunk"
        n_ov = 0
        if pred.failure:
            reason = f"the scene model failed on it: {pred.failure}"
        elif prev is not None and prev[6]:
            reason = f"the previous chunk failed ({prev[6]})"
        elif prev is not None:
            shared = np.intersect1d(prev[0], frames)
            n_ov = len(shared)
            ip = np.searchsorted(prev[0], shared)
            ic = shared - start
            if prev[4].shape == rows.shape and prev[5].shape == cols.shape:
                X = pred.world_points(ic, rows, cols)
                cx = pred.T_world_cam[ic, :3, 3]
                S, info = align_overlap(prev[1][ip], prev[2][ip], prev[3][ip], X, pred.conf[ic][:, rows][:, :, cols], cx, cfg)
            else:
                info = {"points": 0, "residual_rel": float("nan"), "reason": "point maps of different sizes"}
            reason = info["reason"]
        aligned = S is not None
        if not aligned:
            segment += 1
            S = np.eye(4)
            if prev is not None or pred.failure:
                msg = (f"chunk {start}..{end - 1} could not be aligned to the previous one ({reason}): frames from "
                       f"{max(owned_until, start)} on are segment {segment}, in a frame and scale of their own")
                log.warning(msg)
                res.warnings.append(msg)
        own = np.arange(max(owned_until, start), end) - start
        s_k = float(np.cbrt(np.linalg.det(S[:3, :3])))
        f_own = frames[own]
        res.T_stitch_cam[f_own] = transform_poses(S, pred.T_world_cam[own])
        res.segment[f_own] = segment
        res.chunk_scale[f_own] = s_k
        res.chunks.append(ChunkRecord(start, end, segment, S, aligned, n_ov, int(info.get("points", 0)),
                                      float(info.get("residual_rel", float("nan"))),
                                      "" if aligned or (prev is None and not pred.failure) else reason))
        if visit is not None:
            visit(pred, S, own, segment)
        owned_until = end
        # Keep the chunk's grid-sampled points, stitched, for the next alignment (it uses the frames
        # the two chunks share; the grid is small, so keeping every frame costs little).
        Yk = apply_similarity(S, pred.world_points(slice(None), rows, cols).reshape(len(frames), -1, 3))
        prev = (frames, Yk.reshape(len(frames), len(rows), len(cols), 3), pred.conf[:, rows][:, :, cols],
                apply_similarity(S, pred.T_world_cam[:, :3, 3][None])[0], rows, cols, pred.failure)
        if pred.failure:
            res.failed[f_own] = True
    return res
