"""The camera-space body's depth refined against the image's 2D keypoints (``--human-depth keypoints``).

A camera-space regressor (VIMO, HMR, ...) gets the body's pose and shape roughly right but its
translation, the depth above all, is its weakest output: a crop-based weak-perspective camera
turned into a full-perspective one, smoothed over a window. Every real input also has Stage II's
2D keypoints (COCO-17 with confidences), which say where the joints are in the image; the size of
the skeleton in the image fixes its depth once the body's size is known. So, with ONE shape for
the sequence ``beta`` (the median of the valid frames' betas, the shape the world file keeps, or
the shape of the user's ``--scale.height-m``, :func:`embodmocap.body.stature.betas_for_stature`)
and each frame's pose, each frame's translation is solved so that the body's COCO-17 points
``X_k`` (camera frame, model's translation) moved by ``d`` reproject onto the detected ones:

    d_t = argmin_d  sum_k  w_k rho(|pi(X_k + d) - u_k|^2),   pi(P) = (f_x P_x / P_z + c_x, f_y P_y / P_z + c_y)

(``w_k`` the detector's confidence, ``rho`` Cauchy with a scale of ``cauchy_rel`` x the person's
size in the image), by damped Gauss-Newton with iteratively re-weighted least squares, vectorised
over frames (a 3x3 system per frame). The correction of a solved frame is kept as a log depth
factor ``l_t = log(z*_t / z_t)`` of the pelvis and a lateral offset ``e_t = p*_xy - e^{l_t} p_xy``
(``p`` the model's pelvis, ``p*`` the refined one); both are median-filtered and Gaussian-smoothed
over time (the truth moves smoothly; the solve's noise does not) and interpolated over frames
without enough keypoints. The refined pelvis is ``p*_t = e^{l_t} p_t + (e_t, 0)``.

What this cannot correct: the body's size. A regressor that believes the person is 3 % smaller
places them 3 % nearer and the image looks the same; only the real height (``--scale.height-m``)
removes that.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter1d, median_filter

from embodmocap.mono.files import HumanSeq


@dataclass(frozen=True)
class RefineResult:
    """The refined body and what the refinement did (``stats`` go into ``mono_manifest.json``)."""

    human: HumanSeq
    stats: dict


def sequence_betas(model, human: HumanSeq, height_m: float | None = None) -> tuple[NDArray[np.float64], dict]:
    """One shape for the sequence: the median of the valid frames' betas, moved (minimum change)
    to the given stature when ``height_m`` is set. Returns (B,) betas (the model's count) and facts."""
    from embodmocap.body.stature import betas_for_stature, stature

    valid = np.asarray(human.valid, bool)
    b = model._betas_np(np.median(human.betas[valid], axis=0))
    info = {"model_height_m": round(float(stature(model, b)), 4)}
    if height_m is not None:
        b = betas_for_stature(model, b, float(height_m))
        info["height_m"] = round(float(stature(model, b)), 4)
    return b, info


def body_keypoints(model, human: HumanSeq, betas: NDArray, transl: NDArray, layout: str = "COCO17",
                   batch: int = 256) -> NDArray[np.float64]:
    """(T, 17, 3) the body's COCO-17 points in the camera frame with shape ``betas`` (B,) and
    translation ``transl`` (T, 3) (rows of invalid frames are computed too; callers ignore them)."""
    import torch

    from embodmocap.body.joints import smpl_to_coco17

    T = len(transl)
    out = np.zeros((T, 17, 3))
    for a in range(0, T, batch):
        b = min(T, a + batch)
        with torch.no_grad():
            o = model.forward(betas, human.global_orient[a:b], human.body_pose[a:b], transl[a:b], dtype=torch.float64)
        out[a:b] = smpl_to_coco17(o.joints, o.vertices, model.vertex_ids, layout).numpy()
    return out


def solve_translation(X: NDArray, kp: NDArray, K: NDArray, use: NDArray, *, iterations: int = 10,
                      cauchy_rel: float = 0.05, min_conf: float = 0.3) -> tuple[NDArray, NDArray, NDArray]:
    """Per frame, the translation ``d`` (3,) moving the points ``X`` so they reproject onto ``kp``.

    Args:
        X: (n, J, 3) points in the camera frame (metres), in front of the camera.
        kp: (n, J, 3) detected pixels x, y and confidence (0 = not detected).
        K: (3, 3) intrinsics of the keypoints' image.
        use: (n,) frames to solve (others return d = 0).
        iterations: Gauss-Newton / re-weighting rounds.
        cauchy_rel: Cauchy scale as a share of the detected person's size (px).
        min_conf: keypoints below this confidence are not used.

    Returns:
        d (n, 3); the weighted median reprojection error (px) before and after, (n,) each.
    """
    X = np.asarray(X, dtype=np.float64)
    n = len(X)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    uv = kp[..., :2]
    w0 = np.where(kp[..., 2] >= min_conf, kp[..., 2], 0.0) * use[:, None]
    seen = w0 > 0
    hi = np.where(seen[..., None], uv, -np.inf).max(axis=1)
    lo = np.where(seen[..., None], uv, np.inf).min(axis=1)
    size = (hi - lo).max(axis=-1)  # the detected person's larger extent, px (-inf: none seen)
    size = np.where(np.isfinite(size) & (size > 1.0), size, 1.0)
    c2 = (cauchy_rel * size) ** 2
    d = np.zeros((n, 3))

    def project(P):
        z = np.maximum(P[..., 2], 1e-3)
        return np.stack([fx * P[..., 0] / z + cx, fy * P[..., 1] / z + cy], -1), z

    def residual_px(P):
        q, _ = project(P)
        return np.linalg.norm(q - uv, axis=-1)

    err0 = _weighted_median(residual_px(X), w0)
    for _ in range(iterations):
        P = X + d[:, None]
        q, z = project(P)
        r = q - uv  # (n, J, 2)
        w = w0 / (1.0 + (r**2).sum(-1) / c2[:, None])  # Cauchy IRLS weights
        # d pi / d P (2 x 3) per point
        Jx = np.stack([fx / z, np.zeros_like(z), -fx * P[..., 0] / z**2], -1)
        Jy = np.stack([np.zeros_like(z), fy / z, -fy * P[..., 1] / z**2], -1)
        A = np.einsum("nj,nja,njb->nab", w, Jx, Jx) + np.einsum("nj,nja,njb->nab", w, Jy, Jy)
        g = np.einsum("nj,nja,nj->na", w, Jx, r[..., 0]) + np.einsum("nj,nja,nj->na", w, Jy, r[..., 1])
        A = A + np.eye(3)[None] * (1e-6 * np.trace(A, axis1=1, axis2=2)[:, None, None] + 1e-9)
        step = np.linalg.solve(A, -g[..., None])[..., 0]
        # keep the body in front of the camera: at most half of its depth per step
        zp = X[:, 0, 2] + d[:, 2]
        lim = np.minimum(1.0, 0.5 * zp / np.maximum(np.abs(step[:, 2]), 1e-12))
        d = d + np.where(use[:, None], step * lim[:, None], 0.0)
    err1 = _weighted_median(residual_px(X + d[:, None]), w0)
    return d, err0, err1


def _weighted_median(v: NDArray, w: NDArray) -> NDArray:
    """(n,) per-row weighted median of v (n, J) with weights w (n, J); NaN where no weight."""
    order = np.argsort(v, axis=1)
    vs = np.take_along_axis(v, order, 1)
    ws = np.take_along_axis(w, order, 1)
    cw = np.cumsum(ws, axis=1)
    tot = cw[:, -1:]
    k = np.argmax(cw >= 0.5 * tot, axis=1)
    out = vs[np.arange(len(v)), k]
    return np.where(tot[:, 0] > 0, out, np.nan)


def refine_human(human: HumanSeq, model, keypoints: NDArray | None, K: NDArray, fps: float, cfg,
                 height_m: float | None = None, layout: str = "COCO17") -> RefineResult:
    """The camera-space body with one shape for the sequence and, with ``keypoints`` (T, 17, 3),
    each frame's translation refined against them (module docstring). ``cfg``:
    :class:`~embodmocap.mono.config.DepthRefineConfig`. Without keypoints (``None``: ``--human-depth
    model``) only the shape is made one (and its size change, with ``height_m``, moves each pelvis
    along its ray by the same factor, as a regressor would have placed that body)."""
    valid = np.asarray(human.valid, bool)
    T = len(valid)
    if not valid.any() or (keypoints is None and height_m is None):
        # nothing to refine: the model's body as it is (per-frame betas kept)
        return RefineResult(human, {"source": "model", "frames_refined": 0})
    b_med, info = sequence_betas(model, human, None)
    betas = b_med if height_m is None else sequence_betas(model, human, height_m)[0]
    p_model = model.pelvis_offset(human.betas) + human.transl  # (T, 3) the model's pelvis
    # a body of another size (the user's height) placed where it looks as large: depth scales with it
    p0 = p_model * float(_stature(model, betas) / info["model_height_m"])
    stats = {**info, "source": "model" if keypoints is None else "keypoints",
             "height_m": round(float(_stature(model, betas)), 4)}
    if keypoints is None:
        out = HumanSeq(human.global_orient, human.body_pose, np.repeat(betas[None], T, 0),
                       p0 - model.pelvis_offset(betas), valid)
        return RefineResult(out, {**stats, "frames_refined": 0})

    kp = np.asarray(keypoints, dtype=np.float64)
    X = body_keypoints(model, human, betas, p0 - model.pelvis_offset(betas), layout)
    n_kp = ((kp[..., 2] >= cfg.min_conf)).sum(1)
    use = valid & (n_kp >= cfg.min_keypoints) & (X[:, :, 2].min(1) > 0.05)
    d, err0, err1 = solve_translation(X, kp, K, use, iterations=cfg.iterations, cauchy_rel=cfg.cauchy_rel,
                                      min_conf=cfg.min_conf)
    p1 = p0 + d
    ok = use & (p1[:, 2] > 0.05) & np.isfinite(p1).all(1)
    l = np.zeros(T)
    l[ok] = np.log(p1[ok, 2] / p0[ok, 2])
    ok &= np.abs(l) <= np.log(cfg.max_factor)
    e = np.zeros((T, 2))
    e[ok] = p1[ok, :2] - np.exp(l[ok])[:, None] * p0[ok, :2]
    l_s, e_s, filled = _smooth(l, e, ok, valid, cfg, fps)
    p_ref = np.exp(l_s)[:, None] * p0
    p_ref[:, :2] += e_s
    out = HumanSeq(human.global_orient, human.body_pose, np.repeat(betas[None], T, 0),
                   p_ref - model.pelvis_offset(betas), valid)
    fac = np.exp(l_s[valid])
    stats.update({
        "frames_refined": int(ok.sum()), "frames_interpolated": int((filled & valid).sum()),
        "frames_model": int((valid & ~ok & ~filled).sum()),
        "depth_factor_median": round(float(np.median(fac)), 5),
        "depth_factor_p10": round(float(np.percentile(fac, 10)), 5),
        "depth_factor_p90": round(float(np.percentile(fac, 90)), 5),
        "lateral_cm_median": round(float(100 * np.median(np.linalg.norm(e_s[valid], axis=1))), 3),
        "reproj_px_before_median": _r(np.nanmedian(err0[ok])) if ok.any() else None,
        "reproj_px_after_median": _r(np.nanmedian(err1[ok])) if ok.any() else None,
    })
    return RefineResult(out, stats)


def _stature(model, betas):
    from embodmocap.body.stature import stature

    return stature(model, betas)


def _r(x) -> float | None:
    return round(float(x), 4) if np.isfinite(x) else None


def _smooth(l: NDArray, e: NDArray, ok: NDArray, valid: NDArray, cfg, fps: float):
    """Median filter then Gaussian smoothing of the solved frames' corrections (normalised
    convolution: gaps do not pull towards 0), linear interpolation over unsolved frames (constant
    beyond the ends). Returns l (T,), e (T, 2) and which frames were filled (T,) bool."""
    T = len(l)
    if not ok.any():
        return np.zeros(T), np.zeros((T, 2)), np.zeros(T, bool)
    idx = np.flatnonzero(ok)
    t = np.arange(T)
    vals = np.column_stack([l, e])[idx]
    if cfg.median_frames > 1 and len(idx) >= cfg.median_frames:
        vals = median_filter(vals, size=(cfg.median_frames, 1), mode="nearest")
    full = np.column_stack([np.interp(t, idx, vals[:, k]) for k in range(3)])
    sigma = cfg.smooth_s * fps
    if sigma >= 0.5:
        wgt = np.zeros(T)
        wgt[idx] = 1.0
        acc = np.zeros((T, 3))
        acc[idx] = vals
        num = gaussian_filter1d(acc, sigma, axis=0, mode="nearest")
        den = gaussian_filter1d(wgt, sigma, mode="nearest")
        sm = np.where(den[:, None] > 1e-3, num / np.maximum(den, 1e-12)[:, None], full)
        full = np.where(ok[:, None] | (den[:, None] > 0.2), sm, full)
    return full[:, 0], full[:, 1:], ~ok
