"""The metric scale of a stitched segment from the feet on the floor (for sparse scene models).

The body-depth cue (:mod:`embodmocap.mono.scale`) needs scene-model points on the person; SfM has
none there (the person is masked out of its features). The floor gives another metric cue: the
human model is metric in its camera frame, the stitched world is not, and a foot in contact lies
on the floor plane of the stitched scene points.

With the stitched floor plane ``n . x + d = 0`` (``n`` unit, pointing up to the cameras, in
stitched units), frame ``t``'s stitched camera pose ``(R_t, c_t)`` (rotation and centre: rotations
carry no scale) and ``q_t`` the camera-space metric position of the foot's lowest sole vertex (the
foot vertex lowest along ``-n`` after the rotation ``R_t``), the foot on the floor means, in a
metric world ``m`` x the stitched one::

    m (n . c_t + d) + n . (R_t q_t) = 0      =>      m_t = -(n . R_t q_t) / (n . c_t + d)

i.e. the camera's metric height above the floor as the body sees it, over its stitched height (the
same as intersecting the foot's pixel ray with the plane: ``m_t = |q_t| / lambda_t``). Per frame
the lower foot (smaller ``n . R_t q_t``) is used; frames vote when its ray meets the floor at a
usable angle (``-n . R_t q_t / |q_t| >= min_down_cos``) and the foot is in contact: in the metric
world of the current estimate ``m`` the foot's centroid ``m c_t + R_t qbar_t`` moves slower than
``max_speed`` (central differences; the centroid, because the lowest vertex of a flat sole hops
between heel and toes) and its lowest point ``m c_t + R_t q_t`` lies within ``max_height`` of the
floor. Starting from the median over all
frames, ``m = median_t m_t`` over the contact frames, repeated ``iterations`` times. The spread
(MAD, p10, p90 over the voting frames) goes into the manifest with the number of frames.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.mono.config import FeetScaleConfig
from embodmocap.mono.scale import block_se_rel

#: SMPL joints of the feet: left ankle and left foot, right ankle and right foot.
_LEFT, _RIGHT = (7, 10), (8, 11)


def foot_vertices(model) -> NDArray[np.int64]:
    """(2, k) vertex indices of the left and right foot: rest-pose vertices whose nearest joint is
    that foot's ankle or toe joint and that lie below the ankle (the sole and the toes'
    underside); the shorter list is padded with its own first index (a repeat changes no minimum)."""
    import torch

    with torch.no_grad():
        out = model.forward(np.zeros((1, model.num_betas)), np.zeros((1, 3)), np.zeros((1, 69)), np.zeros((1, 3)),
                            dtype=torch.float64)
    V = out.vertices.numpy()[0]
    J = model.rest_joints(np.zeros(model.num_betas))
    near = np.argmin(np.linalg.norm(V[:, None] - J[None, :24], axis=-1), axis=1)
    sets = []
    for ids in (_LEFT, _RIGHT):
        sel = np.isin(near, ids) & (V[:, 1] < J[ids[0], 1])  # SMPL rest pose: +y up
        sets.append(np.flatnonzero(sel))
    k = max(len(a) for a in sets)
    return np.stack([np.concatenate([a, np.full(k - len(a), a[0])]) for a in sets])


def lowest_points(feet_cam: NDArray, R: NDArray, n: NDArray) -> NDArray[np.float64]:
    """(T, 2, 3) per frame and foot the camera-space metric position of the vertex lowest along
    ``-n`` in the stitched world's orientation.

    Args:
        feet_cam: (T, 2, k, 3) camera-space foot vertices (left, right), metres.
        R: (T, 3, 3) stitched camera rotations; ``n`` (3,) the floor's up normal (stitched frame).
    """
    h = np.einsum("tfkj,tij,i->tfk", feet_cam, R, n)  # n . R q per vertex
    k = np.argmin(h, axis=-1)
    return np.take_along_axis(feet_cam, k[..., None, None], axis=2)[:, :, 0]


def feet_scale(feet_cam: NDArray, T_stitch_cam: NDArray, valid: NDArray, plane: tuple[NDArray, float], fps: float,
               cfg: FeetScaleConfig, block_s: float = 2.0) -> dict:
    """The metric scale of one segment from its feet (see the module).

    Args:
        feet_cam: (T, 2, k, 3) camera-space foot vertices of the segment's frames, metres.
        T_stitch_cam: (T, 4, 4) stitched camera poses of the same frames (stitched units).
        valid: (T,) bool: the human model gave the frame.
        plane: (n (3,), d) the floor in the stitched frame, ``n`` pointing towards the cameras.
        fps: frame rate (for the feet's speed).
        block_s: block length of the standard error (seconds; ``ScaleConfig.block_s``).

    Returns:
        ``scale`` (metres per stitched unit; NaN with fewer than ``min_frames`` voting frames),
        ``mad_rel``, ``p10``, ``p90`` (over the voting frames' ``m_t``), ``frames`` (voting),
        ``se_rel`` (relative standard error, :func:`~embodmocap.mono.scale.block_se_rel`),
        ``per_frame`` ((T,) ``m_t`` of the lower foot, NaN where its ray misses the floor) and
        ``contact`` ((T,) bool, the voting frames).
    """
    n, d = np.asarray(plane[0], dtype=np.float64), float(plane[1])
    R, c = T_stitch_cam[:, :3, :3], T_stitch_cam[:, :3, 3]
    q = lowest_points(np.asarray(feet_cam, dtype=np.float64), R, n)  # (T, 2, 3)
    Rq = np.einsum("tij,tfj->tfi", R, q)  # (T, 2, 3) metric offsets camera -> foot, stitched axes
    # the speed is the foot's centroid's: a flat sole has many equally low vertices, and the lowest
    # one hops between heel and toes from frame to frame
    Rm = np.einsum("tij,tfj->tfi", R, np.asarray(feet_cam, dtype=np.float64).mean(axis=2))
    down = Rq @ n  # (T, 2) metric height of the foot relative to the camera (negative: below)
    lower = np.argmin(down, axis=1)
    dn = down[np.arange(len(q)), lower]
    cam_h = c @ n + d  # (T,) stitched height of the camera above the floor
    cos = -dn / np.maximum(np.linalg.norm(q[np.arange(len(q)), lower], axis=-1), 1e-9)
    ok = np.asarray(valid, bool) & (cam_h > 0) & (cos >= cfg.min_down_cos)
    m_t = np.where(ok, -dn / np.where(cam_h > 0, cam_h, np.nan), np.nan)
    nan = {"scale": float("nan"), "mad_rel": float("nan"), "p10": float("nan"), "p90": float("nan"), "frames": 0,
           "se_rel": float("nan"), "per_frame": m_t, "contact": np.zeros(len(q), bool)}
    if ok.sum() < cfg.min_frames:
        return nan
    m = float(np.nanmedian(m_t))
    contact = ok
    for _ in range(cfg.iterations):
        P = m * c[:, None, :] + Rm  # (T, 2, 3) metric foot centroids, stitched axes
        v = np.full((len(q), 2), np.inf)
        if len(q) >= 3:  # central differences; the ends take their neighbour's
            v[1:-1] = np.linalg.norm(P[2:] - P[:-2], axis=-1) * fps / 2
            v[0], v[-1] = v[1], v[-2]
        speed = v[np.arange(len(q)), lower]
        height = m * cam_h + dn
        contact = ok & (speed < cfg.max_speed) & (np.abs(height) < cfg.max_height)
        if contact.sum() < cfg.min_frames:
            return {**nan, "contact": contact}
        m = float(np.median(m_t[contact]))
    f = m_t[contact]
    return {"scale": m, "mad_rel": float(1.4826 * np.median(np.abs(f - m)) / m), "p10": float(np.percentile(f, 10)),
            "p90": float(np.percentile(f, 90)), "frames": int(contact.sum()),
            "se_rel": block_se_rel(f, np.flatnonzero(contact), fps, block_s), "per_frame": m_t, "contact": contact}


def stitched_floor(points: NDArray, T_stitch_cam: NDArray, inlier_rel: float) -> tuple[NDArray, float] | None:
    """The floor plane of a segment's stitched scene points, scale-free: the points are measured
    in units of their median distance from the mean camera centre, then
    :func:`~embodmocap.mono.gravity.floor_plane` finds the dominant plane below the cameras.
    Returns ``(n, d)`` in stitched units or None."""
    from embodmocap.mono.gravity import floor_plane

    P = np.asarray(points, dtype=np.float64)
    if len(P) < 10:
        return None
    c = T_stitch_cam[:, :3, 3]
    D = float(np.median(np.linalg.norm(P - c.mean(0), axis=1)))
    if not D > 0:
        return None
    pl = floor_plane(P / D, T_stitch_cam[:, :3, :3], c / D, inlier_m=inlier_rel, min_below=0.1)
    if pl is None:
        return None
    return pl[0], pl[1] * D
