"""Evaluation metrics as pure numpy functions.

Every function takes arrays, checks their shapes on entry (ValueError on a mismatch), and returns
plain floats (or arrays where documented); none reads or writes files. Argument order is always
*(prediction/estimate, truth)*. Positions come in **metres**; the unit of each result is in its
name or docstring. A metric of an empty set (no valid pixel, no weighted keypoint, too few
frames) is NaN rather than an error, so a report can show "n/a" for one sequence and go on.

Motion metrics follow the world-grounded human-motion literature (WHAM, GVHMR) so that numbers are
comparable with published tables:

- ``w_mpjpe`` (GVHMR's "WA2-MPJPE" / WHAM's "W-MPJPE_100"): 100-frame chunks, each aligned by the
  similarity transform (Umeyama with scale) fitted on the chunk's first two frames;
  ``w_mpjpe_all_starts`` the same for a chunk starting at every frame (where a clip is cut matters);
- ``wa_mpjpe`` (GVHMR's "WAA-MPJPE" / WHAM's "WA-MPJPE_100"): the same with the similarity fitted
  on the whole chunk;
- ``rte_pct``: root translation error after one rigid (no scale) alignment of the whole
  trajectory, divided by the ground-truth path length, in percent;
- ``jitter``: third finite difference times fps^3, in units of 10 m/s^3 (GVHMR's table unit);
- ``foot_skating``: predicted foot-point motion (mm/frame) while the truth says the foot rests.

The alignment choices are parameters (``with_scale``) for those who want the rigid variants.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from embodmocap.geometry.similarity import weighted_umeyama

F = NDArray[np.float64]

#: The four SMPL foot-sole vertices (left heel, left toe, right heel, right toe) GVHMR and WHAM
#: track for foot sliding, on the official 6890-vertex SMPL mesh.
SMPL_FOOT_SKATING_VERTEX_IDS: tuple[int, ...] = (3216, 3387, 6617, 6787)


# ----------------------------------------------------------------------------------- alignment


def umeyama(src: ArrayLike, dst: ArrayLike, with_scale: bool = True) -> tuple[F, F, F]:
    """Least-squares similarity (or rigid) transform taking ``src`` onto ``dst``, batched.

    Args:
        src: (..., N, 3) points.
        dst: (..., N, 3) corresponding points.
        with_scale: fit a scale (similarity) or keep s = 1 (rigid).

    Returns:
        ``(s (...,), R (..., 3, 3), t (..., 3))`` minimising ``sum_n |dst_n - (s R src_n + t)|^2``
        (Umeyama 1991): with means ``mu``, centred points ``x = src - mu_src``, ``y = dst -
        mu_dst``, ``Sigma = y^T x / N = U D V^T``, ``S = diag(1, 1, sign det(U V^T))``:
        ``R = U S V^T``, ``s = trace(D S) / (|x|^2 / N)``, ``t = mu_dst - s R mu_src``.
        R is a proper rotation (no reflection). s = 1 where ``src`` has no spread.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim < 2 or src.shape[-1] != 3:
        raise ValueError(f"umeyama needs src and dst of the same shape (..., N, 3); got {src.shape}, {dst.shape}")
    # The shared closed form with all weights equal (the monocular stitching uses its weights).
    return weighted_umeyama(src, dst, None, with_scale)


def _apply_sim(s: F, R: F, t: F, points: F) -> F:
    """``s R p + t`` for transforms (...,) (..., 3, 3) (..., 3) and points (..., N, 3)."""
    return s[..., None, None] * np.einsum("...ij,...nj->...ni", R, points) + t[..., None, :]


def _check_joints(pred: ArrayLike, gt: ArrayLike, name: str) -> tuple[F, F]:
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[-1] != 3:
        raise ValueError(f"{name} needs pred and gt of the same shape (T, J, 3); got {pred.shape}, {gt.shape}")
    return pred, gt


# ----------------------------------------------------------------------------------- joint errors


def mpjpe(pred: ArrayLike, gt: ArrayLike) -> float:
    """Mean per-joint position error without any alignment, millimetres.

    ``1000 * mean_{t,j} |pred_tj - gt_tj|`` for pred, gt (T, J, 3) in metres.
    """
    pred, gt = _check_joints(pred, gt, "mpjpe")
    return float(1000.0 * np.linalg.norm(pred - gt, axis=-1).mean())


def pa_mpjpe(pred: ArrayLike, gt: ArrayLike) -> float:
    """Procrustes-aligned MPJPE, millimetres.

    Each frame's prediction is aligned to the truth by its own similarity (Umeyama with scale on
    the frame's J joints): ``1000 * mean_{t,j} |s_t R_t pred_tj + t_t - gt_tj|``.
    pred, gt: (T, J, 3) metres.
    """
    pred, gt = _check_joints(pred, gt, "pa_mpjpe")
    s, R, t = umeyama(pred, gt, with_scale=True)
    return float(1000.0 * np.linalg.norm(_apply_sim(s, R, t, pred) - gt, axis=-1).mean())


def _chunked_error(pred: F, gt: F, chunk: int, fit_frames: int | None, with_scale: bool) -> float:
    """Mean joint error (mm) over the frames of all chunks, each chunk's prediction aligned by a
    transform fitted on its first ``fit_frames`` frames (None = the whole chunk). A last chunk
    shorter than ``chunk`` is kept when it has >= 2 frames; a single left-over frame is dropped."""
    if chunk < 2:
        raise ValueError(f"chunk must be >= 2 frames (an alignment needs two), got {chunk}")
    T = len(pred)
    errors = []
    full = T // chunk
    if full:
        # Full chunks are aligned in one batched call: (C, chunk, J, 3).
        p = pred[: full * chunk].reshape(full, chunk, *pred.shape[1:])
        g = gt[: full * chunk].reshape(full, chunk, *gt.shape[1:])
        errors.append(_aligned_chunk_errors(p, g, fit_frames, with_scale).ravel())
    a = full * chunk
    if T - a >= 2:
        errors.append(_aligned_chunk_errors(pred[None, a:], gt[None, a:], fit_frames, with_scale).ravel())
    if not errors:
        return float("nan")
    return float(1000.0 * np.concatenate(errors).mean())


def _aligned_chunk_errors(p: F, g: F, fit_frames: int | None, with_scale: bool) -> F:
    """(C, L, J) joint errors (m) of chunks p, g (C, L, J, 3) after the per-chunk alignment."""
    C, L, J, _ = p.shape
    k = L if fit_frames is None else fit_frames
    s, R, t = umeyama(p[:, :k].reshape(C, k * J, 3), g[:, :k].reshape(C, k * J, 3), with_scale)
    aligned = _apply_sim(s, R, t, p.reshape(C, L * J, 3)).reshape(C, L, J, 3)
    return np.linalg.norm(aligned - g, axis=-1)


def w_mpjpe(pred: ArrayLike, gt: ArrayLike, chunk: int = 100, with_scale: bool = True) -> float:
    """World MPJPE (WHAM "W-MPJPE_100", GVHMR "WA2-MPJPE"), millimetres.

    The sequence is cut into consecutive chunks of ``chunk`` frames (a last, shorter chunk is
    kept when it has >= 2 frames). In each chunk ``c`` the prediction is moved by the transform
    ``(s_c, R_c, t_c) = umeyama(pred[first two frames], gt[first two frames])`` fitted on all
    joints of the chunk's first two frames, and

        W-MPJPE = 1000 * mean over every kept frame t and joint j of |s_c R_c pred_tj + t_c - gt_tj|

    It measures drift within ``chunk`` frames of a known start. ``with_scale=True`` (default) is
    the published definition (GVHMR's and WHAM's ``first_align_joints`` fit a similarity);
    ``False`` fits a rigid transform instead. pred, gt: (T, J, 3) metres.
    """
    pred, gt = _check_joints(pred, gt, "w_mpjpe")
    return _chunked_error(pred, gt, chunk, 2, with_scale)


def w_mpjpe_all_starts(pred: ArrayLike, gt: ArrayLike, chunk: int = 100, with_scale: bool = True,
                       batch: int = 256) -> F:
    """W-MPJPE of the chunk starting at every possible frame, millimetres: (S,) per start.

    :func:`w_mpjpe` cuts the sequence at frames 0, chunk, 2 chunk, ...: its figure depends on which
    frames happen to anchor a chunk, and a user who cuts a clip anywhere (or aligns on the first
    frames of a sequence) sees the anchor wherever it falls. Here chunk ``s`` covers frames
    ``s .. s + chunk - 1`` for every ``s = 0 .. T - chunk`` (S = T - chunk + 1 starts), each
    aligned by the similarity fitted on its own first two frames, and its value is the mean joint
    error over the chunk's frames. A sequence shorter than ``chunk`` (but with >= 2 frames) is one
    chunk of all its frames (S = 1), as :func:`w_mpjpe` keeps a short last chunk. The median over
    starts is the typical clip, the maximum the worst place to cut. pred, gt: (T, J, 3) metres;
    ``batch`` starts are aligned at once (memory: batch x chunk x J x 3 floats). Empty (0,) when
    T < 2.
    """
    pred, gt = _check_joints(pred, gt, "w_mpjpe_all_starts")
    if chunk < 2:
        raise ValueError(f"chunk must be >= 2 frames (an alignment needs two), got {chunk}")
    T = len(pred)
    if T < 2:
        return np.zeros(0)
    L = min(chunk, T)
    starts = np.arange(T - L + 1)
    out = []
    for b in range(0, len(starts), batch):
        idx = starts[b:b + batch, None] + np.arange(L)[None]  # (S_b, L) frames of each chunk
        out.append(_aligned_chunk_errors(pred[idx], gt[idx], 2, with_scale).mean(axis=(1, 2)))
    return 1000.0 * np.concatenate(out)


def frame_errors_mm(pred: ArrayLike, gt: ArrayLike) -> F:
    """(T,) mean joint error of each frame with no alignment at all, millimetres:
    ``1000 * mean_j |pred_tj - gt_tj|``. pred, gt: (T, J, 3) metres."""
    pred, gt = _check_joints(pred, gt, "frame_errors_mm")
    return 1000.0 * np.linalg.norm(pred - gt, axis=-1).mean(axis=-1)


def wa_mpjpe(pred: ArrayLike, gt: ArrayLike, chunk: int = 100, with_scale: bool = True) -> float:
    """World-aligned MPJPE (WHAM "WA-MPJPE_100", GVHMR "WAA-MPJPE"), millimetres.

    As :func:`w_mpjpe` but each chunk's transform is fitted on all joints of *all* the chunk's
    frames: ``(s_c, R_c, t_c) = umeyama(pred[chunk], gt[chunk])``. pred, gt: (T, J, 3) metres.
    """
    pred, gt = _check_joints(pred, gt, "wa_mpjpe")
    return _chunked_error(pred, gt, chunk, None, with_scale)


def rte_pct(pred_root: ArrayLike, gt_root: ArrayLike, with_scale: bool = False) -> float:
    """Root translation error (GVHMR/WHAM "RTE"), percent of the ground-truth path length.

    One transform aligns the whole predicted root trajectory to the truth,
    ``(s, R, t) = umeyama(pred_root, gt_root)`` (rigid, s = 1, by default as in GVHMR's
    ``compute_rte``; ``with_scale=True`` fits a similarity), and

        RTE = 100 * mean_t |s R pred_t + t - gt_t| / L,   L = sum_t |gt_{t+1} - gt_t|

    pred_root, gt_root: (T, 3) metres (e.g. the pelvis joint). NaN when the truth does not move
    (L = 0).
    """
    pred = np.asarray(pred_root, dtype=np.float64)
    gt = np.asarray(gt_root, dtype=np.float64)
    if pred.shape != gt.shape or pred.ndim != 2 or pred.shape[-1] != 3:
        raise ValueError(f"rte_pct needs pred_root and gt_root of the same shape (T, 3); got {pred.shape}, {gt.shape}")
    length = float(np.linalg.norm(np.diff(gt, axis=0), axis=-1).sum())
    if length <= 0:
        return float("nan")
    s, R, t = umeyama(pred, gt, with_scale)
    err = np.linalg.norm(_apply_sim(s, R, t, pred) - gt, axis=-1)
    return float(100.0 * err.mean() / length)


# ----------------------------------------------------------------------------------- smoothness


def jitter(joints: ArrayLike, fps: float) -> float:
    """Jitter (jerk magnitude), in units of **10 m/s^3** (GVHMR's table unit).

    ``mean_{t,j} |x_{t+3} - 3 x_{t+2} + 3 x_{t+1} - x_t| * fps^3 / 10`` for joints (T, J, 3) in
    metres: the third finite difference is the jerk times ``1/fps^3``. (10 m/s^3 = 0.01 km/s^3.)
    NaN with fewer than 4 frames.
    """
    x = np.asarray(joints, dtype=np.float64)
    if x.ndim != 3 or x.shape[-1] != 3:
        raise ValueError(f"jitter needs joints (T, J, 3), got {x.shape}")
    if fps <= 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if len(x) < 4:
        return float("nan")
    jerk = x[3:] - 3 * x[2:-1] + 3 * x[1:-2] - x[:-3]
    return float(np.linalg.norm(jerk, axis=-1).mean() * fps ** 3 / 10.0)


def foot_skating(pred_feet: ArrayLike, gt_feet: ArrayLike, thr_m: float = 0.01) -> float:
    """Foot skating (GVHMR/WHAM "FS"), millimetres per frame.

    For foot points (T, N, 3) in metres (e.g. the vertices :data:`SMPL_FOOT_SKATING_VERTEX_IDS`),
    a point is *in contact* between frames t and t+1 when the truth moves it less than ``thr_m``:
    ``|gt_{t+1,n} - gt_{t,n}| < thr_m``. FS is the mean predicted displacement over those
    (t, n): ``1000 * mean |pred_{t+1,n} - pred_{t,n}|``. NaN when nothing is in contact.
    """
    pred = np.asarray(pred_feet, dtype=np.float64)
    gt = np.asarray(gt_feet, dtype=np.float64)
    if pred.shape != gt.shape or pred.ndim != 3 or pred.shape[-1] != 3:
        raise ValueError(f"foot_skating needs pred and gt of the same shape (T, N, 3); got {pred.shape}, {gt.shape}")
    contact = np.linalg.norm(np.diff(gt, axis=0), axis=-1) < thr_m
    if not contact.any():
        return float("nan")
    return float(1000.0 * np.linalg.norm(np.diff(pred, axis=0), axis=-1)[contact].mean())


# ----------------------------------------------------------------------------------- images


def mask_iou_pct(pred_mask: ArrayLike, gt_mask: ArrayLike) -> float:
    """Mean per-frame mask IoU, percent.

    ``100 * mean_t |P_t & G_t| / |P_t | G_t|`` over frames (..., H, W) whose union is not empty
    (frames where both masks are empty say nothing about the segmentation and are left out).
    NaN when every union is empty. Masks: bool (non-zero = person).
    """
    p = np.asarray(pred_mask).astype(bool)
    g = np.asarray(gt_mask).astype(bool)
    if p.shape != g.shape or p.ndim < 2:
        raise ValueError(f"mask_iou_pct needs masks of the same shape (..., H, W); got {p.shape}, {g.shape}")
    p = p.reshape(-1, *p.shape[-2:])
    g = g.reshape(-1, *g.shape[-2:])
    inter = (p & g).sum(axis=(-2, -1))
    union = (p | g).sum(axis=(-2, -1))
    keep = union > 0
    if not keep.any():
        return float("nan")
    return float(100.0 * (inter[keep] / union[keep]).mean())


def reproj_err_px(joints2d_pred: ArrayLike, keypoints: ArrayLike) -> float:
    """Confidence-weighted mean reprojection error, pixels.

    ``sum_{t,j} c_tj |x_tj - k_tj| / sum_{t,j} c_tj`` for projected joints x (..., J, 2) and
    detected keypoints (..., J, 3) = (pixel x, pixel y, confidence c). Points with c <= 0 or a
    non-finite value on either side do not count. NaN when no point counts.
    """
    x = np.asarray(joints2d_pred, dtype=np.float64)
    k = np.asarray(keypoints, dtype=np.float64)
    if x.shape[-1] != 2 or k.shape != x.shape[:-1] + (3,):
        raise ValueError(
            f"reproj_err_px needs joints2d (..., J, 2) and keypoints (..., J, 3); got {x.shape}, {k.shape}"
        )
    d = np.linalg.norm(x - k[..., :2], axis=-1)
    c = k[..., 2]
    ok = np.isfinite(d) & np.isfinite(c) & (c > 0)
    if not ok.any():
        return float("nan")
    return float((c[ok] * d[ok]).sum() / c[ok].sum())


def depth_err_m2(pred_depth: ArrayLike, sensor_depth: ArrayLike, mask: ArrayLike) -> float:
    """Mean squared depth error over the person's valid pixels, square metres.

    ``mean over pixels i in V of (pred_i - sensor_i)^2`` for depth maps (..., H, W) in metres,
    where ``V`` = inside ``mask`` and both depths finite and > 0 (0 = no depth, the package's
    convention). NaN when ``V`` is empty.
    """
    p = np.asarray(pred_depth, dtype=np.float64)
    s = np.asarray(sensor_depth, dtype=np.float64)
    m = np.asarray(mask).astype(bool)
    if not p.shape == s.shape == m.shape:
        raise ValueError(f"depth_err_m2 needs pred, sensor and mask of one shape; got {p.shape}, {s.shape}, {m.shape}")
    with np.errstate(invalid="ignore"):
        valid = m & np.isfinite(p) & np.isfinite(s) & (p > 0) & (s > 0)
    if not valid.any():
        return float("nan")
    return float(((p[valid] - s[valid]) ** 2).mean())


# ----------------------------------------------------------------------------------- cameras, sync


def view_offset_err(T_est: ArrayLike, T_true: ArrayLike, centres: ArrayLike) -> tuple[float, float]:
    """Error of an estimated rigid view offset, ``(centimetres, degrees)``.

    ``T_est``, ``T_true``: (4, 4) offsets (e.g. ``T_scene_view``) mapping the view's frame into
    the scene. ``centres``: (N, 3) the view's camera centres in the view's own frame (the points
    the offset moves). Returns

        cm  = 100 * mean_n |T_est c_n - T_true c_n|
        deg = angle of R_est R_true^T   (the yaw difference for yaw-only offsets)
    """
    from embodmocap.geometry.transforms import apply_T, rotation_angle

    A = np.asarray(T_est, dtype=np.float64)
    B = np.asarray(T_true, dtype=np.float64)
    c = np.asarray(centres, dtype=np.float64)
    if A.shape != (4, 4) or B.shape != (4, 4) or c.ndim != 2 or c.shape[-1] != 3 or len(c) == 0:
        raise ValueError(
            f"view_offset_err needs T_est, T_true (4, 4) and centres (N>0, 3); got {A.shape}, {B.shape}, {c.shape}"
        )
    cm = 100.0 * np.linalg.norm(apply_T(A, c) - apply_T(B, c), axis=-1).mean()
    deg = np.rad2deg(rotation_angle(A[:3, :3] @ B[:3, :3].T))
    return float(cm), float(deg)


def sync_err_frames(est: ArrayLike, true: ArrayLike) -> float | F:
    """Synchronisation error, frames: ``|est - true|`` elementwise.

    ``est``, ``true``: sync frames (scalars, or arrays of one shape, e.g. one per view). Returns a
    float for scalars, else the array of absolute errors.
    """
    e = np.asarray(est, dtype=np.float64)
    t = np.asarray(true, dtype=np.float64)
    if e.shape != t.shape:
        raise ValueError(f"sync_err_frames needs est and true of one shape; got {e.shape}, {t.shape}")
    err = np.abs(e - t)
    return float(err) if err.ndim == 0 else err


__all__ = [
    "SMPL_FOOT_SKATING_VERTEX_IDS", "depth_err_m2", "foot_skating", "frame_errors_mm", "jitter", "mask_iou_pct",
    "mpjpe", "pa_mpjpe", "reproj_err_px", "rte_pct", "sync_err_frames", "umeyama", "view_offset_err", "w_mpjpe",
    "w_mpjpe_all_starts", "wa_mpjpe",
]
