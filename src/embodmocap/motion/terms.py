"""World-space SMPLify loss terms: small pure torch functions, each returning a scalar.

Every term is an *unweighted mean*, so its weight in :class:`~embodmocap.motion.smplify.SmplifyConfig`
says how much it counts regardless of the number of frames. Units of each term:

=================== ==================================================================== =========
term                value                                                                unit
=================== ==================================================================== =========
kp3d                confidence-weighted mean of ``rho(|J - Y|^2)``                        1 (robust)
reproj              confidence-weighted mean of ``rho(|pi(J) - y|^2)`` over views         1 (robust)
joint_vel / _acc    mean squared norm of the 1st / 2nd frame difference of joints         m^2
transl_vel / _acc   same for the SMPL translation                                         m^2
pose_prior          mean squared axis-angle difference to a prior body pose               rad^2
joint_limits        mean over frames of squared hinge violations (knees, elbows)          rad^2
joint_range         mean over frames of squared violations of per-axis anatomical ranges  rad^2
shape_prior         mean squared beta                                                     1
=================== ==================================================================== =========

``rho`` is a robust kernel (:func:`embodmocap.geometry.robust.robust_rho`: ``l2``, ``huber`` or
``geman_mcclure``) of the squared residual norm divided by ``scale**2``, so a residual of one
``scale`` costs about 1 (Huber) or 0.5 (Geman-McClure) and gross outliers stop pulling.

Missing observations are marked by zero confidence; their targets may be NaN (they are replaced
by zeros before use, so no NaN reaches the gradient).
"""

from __future__ import annotations

import numpy as np
import torch
from numpy.typing import NDArray

from embodmocap.geometry.robust import robust_rho

#: (SMPL joint id, axis, sign) of one-way hinges: ``sign * angle`` must stay >= 0. Knees flex
#: about +x of the SMPL joint frame; the left elbow flexes about -y and the right one about +y.
HINGES: tuple[tuple[int, int, float], ...] = ((4, 0, 1.0), (5, 0, 1.0), (18, 1, -1.0), (19, 1, 1.0))


def _weighted_robust_mean(s: torch.Tensor, conf: torch.Tensor, kind: str, scale: float) -> torch.Tensor:
    """``sum(conf * rho(s)) / sum(conf)``; 0 when nothing has confidence."""
    return (conf * robust_rho(s, kind, scale)).sum() / conf.sum().clamp(min=1e-12)


def _clean(target: torch.Tensor, conf: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Targets with NaN rows zeroed and their confidence set to 0 (rows = all but the last axis)."""
    finite = torch.isfinite(target).all(-1)
    conf = torch.where(finite, conf, torch.zeros_like(conf))
    return torch.nan_to_num(target, nan=0.0, posinf=0.0, neginf=0.0), conf


def kp3d_term(pred: torch.Tensor, target: torch.Tensor, conf: torch.Tensor, kind: str = "geman_mcclure",
              scale: float = 0.05, clean: bool = True) -> torch.Tensor:
    """3D keypoint term.

    Args:
        pred: (T, J, 3) model keypoints, metres.
        target: (T, J, 3) triangulated keypoints, metres (NaN where missing).
        conf: (T, J) confidence >= 0 (0 = ignore).
        kind, scale: robust kernel and its scale in metres.
        clean: False when ``target`` is known to be finite with 0 confidence where missing (the
            fit's data, cleaned once instead of at every step).
    """
    if clean:
        target, conf = _clean(target, conf)
    s = ((pred - target) ** 2).sum(-1)
    return _weighted_robust_mean(s, conf, kind, scale)


def project(points: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor,
            min_depth: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor]:
    """Pinhole projection of world points into V cameras.

    Args:
        points: (T, J, 3) world points, metres.
        K: (V, 3, 3) intrinsics (pixels).
        T_world_cam: (T, V, 4, 4) camera-to-world, OpenCV axes (rigid).
        min_depth: depths below this are clamped (keeps the division finite behind the camera).

    Returns:
        uv (T, V, J, 2) pixels and depth (T, V, J) metres along the optical axis.
    """
    R = T_world_cam[..., :3, :3]  # (T, V, 3, 3) camera -> world
    c = T_world_cam[..., :3, 3]  # (T, V, 3) camera centre
    # world -> camera of a rigid transform is R^T (p - c): no matrix inverse needed.
    p_cam = torch.einsum("tvji,tvnj->tvni", R, points[:, None, :, :] - c[:, :, None, :])
    z = p_cam[..., 2]
    uvw = torch.einsum("vij,tvnj->tvni", K, p_cam / z.clamp(min=min_depth)[..., None])
    return uvw[..., :2], z


def reproj_view_terms(pred: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor, kp2d: torch.Tensor,
                      conf: torch.Tensor, kind: str = "geman_mcclure", scale: float = 20.0,
                      min_depth: float = 0.05, clean: bool = True) -> torch.Tensor:
    """:func:`reproj_term` of each view separately, from one projection into all of them: (V,)
    (the same arguments; what ``reproj_term`` gives for the views one at a time; ``clean`` as in
    :func:`kp3d_term`)."""
    if clean:
        kp2d, conf = _clean(kp2d, conf)
    uv, z = project(pred, K, T_world_cam)
    conf = torch.where(z.detach() > min_depth, conf, torch.zeros_like(conf))
    rho = robust_rho(((uv - kp2d) ** 2).sum(-1), kind, scale)  # (T, V, J)
    return (conf * rho).sum((0, 2)) / conf.sum((0, 2)).clamp(min=1e-12)


def reproj_term(pred: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor, kp2d: torch.Tensor,
                conf: torch.Tensor, kind: str = "geman_mcclure", scale: float = 20.0,
                min_depth: float = 0.05) -> torch.Tensor:
    """Per-view reprojection term, pixels.

    Args:
        pred: (T, J, 3) model keypoints in the world, metres.
        K: (V, 3, 3) intrinsics of each view.
        T_world_cam: (T, V, 4, 4) camera-to-world of each frame and view (OpenCV axes).
        kp2d: (T, V, J, 2) detected keypoints, pixels (NaN where missing).
        conf: (T, V, J) detection confidence (0 = ignore).
        kind, scale: robust kernel and its scale in pixels.
        min_depth: points closer than this to a camera (or behind it) do not count, metres.
    """
    kp2d, conf = _clean(kp2d, conf)
    uv, z = project(pred, K, T_world_cam)
    conf = torch.where(z.detach() > min_depth, conf, torch.zeros_like(conf))
    s = ((uv - kp2d) ** 2).sum(-1)
    return _weighted_robust_mean(s, conf, kind, scale)


def velocity_term(x: torch.Tensor) -> torch.Tensor:
    """Mean squared norm of the first frame difference of ``x`` (T, ..., D) over the last axis.

    For joints (T, 24, 3) or translations (T, 3), in m^2 per frame^2; 0 for fewer than 2 frames.
    """
    if x.shape[0] < 2:
        return x.sum() * 0.0
    return ((x[1:] - x[:-1]) ** 2).sum(-1).mean()


def edge_weights(valid: NDArray, n: int) -> NDArray:
    """(T,) 1.0 where the edge velocity term applies, else 0.0: the ``n`` frames of each run of
    placeable frames next to an unplaceable frame (``valid`` False) or to an end of the sequence
    (the frames that have well-seen neighbours on one side only). Unplaceable frames get 0: they
    are not scored, and holding them still would pin their neighbours to a guess.

    Args:
        valid: (T,) bool; n: frames covered at each edge of a run (0 = none).
    """
    valid = np.asarray(valid, dtype=bool)
    T = len(valid)
    if n <= 0 or T == 0:
        return np.zeros(T)
    # Distance (frames) from each frame to the nearest unplaceable frame or beyond either end.
    blocked = np.concatenate([[-1], np.flatnonzero(~valid), [T]])
    t = np.arange(T)
    right = blocked[np.searchsorted(blocked, t, side="left")] - t
    left = t - blocked[np.searchsorted(blocked, t, side="right") - 1]
    return (valid & (np.minimum(left, right) <= n)).astype(np.float64)


#: The COCO-17 keypoint whose detections tell whether each SMPL joint is seen (the joint's own
#: keypoint, or the nearest one: spine and collars the shoulders, neck and head the nose, feet
#: the ankles, hands the wrists; the pelvis has no articulation speed).
SMPL_EDGE_KEYPOINT: tuple[int, ...] = (0, 11, 12, 11, 13, 14, 5, 15, 16, 6, 15, 16, 0, 5, 6, 0, 5, 6, 7, 8, 9, 10, 9, 10)


def edge_hold_weights(frame_w: NDArray, seen: NDArray, mode: str = "unseen") -> NDArray:
    """(T, 24, 1 + V) weights of :func:`edge_velocity_term` per frame and SMPL joint: column 0
    holds the joint's whole articulation still, column 1 + v only its motion along view v's ray
    (``mode`` ``unseen``); with ``mode`` ``all``, ``frame_w`` itself (every joint held entirely).

    The term is there for what no keypoint pins. A joint that no view sees in the frame is held
    entirely; one that a single view sees is pinned across that view's ray by its detection, so
    only its depth along the ray (which a straight-line drift moves freely) is held; one that two
    views see is not held (both views' detections follow a real movement; holding it freezes,
    e.g., the legs of a walking body at the first frames after one view was blind).

    Args:
        frame_w: (T,) :func:`edge_weights`; seen: (T, V, 17) bool detections used by the fit;
        mode: ``unseen`` or ``all`` (:attr:`SmplifyConfig.edge_hold`).

    Raises:
        ValueError: another ``mode``.
    """
    if mode == "all":
        return np.asarray(frame_w, dtype=np.float64)
    if mode != "unseen":
        raise ValueError(f"SmplifyConfig.edge_hold must be 'unseen' or 'all', got {mode!r}")
    seen = np.asarray(seen, dtype=bool)[:, :, list(SMPL_EDGE_KEYPOINT)]  # (T, V, 24)
    n = seen.sum(1)
    w = np.asarray(frame_w, dtype=np.float64)[:, None]
    cols = [w * (n == 0)] + [w * ((n == 1) & seen[:, v]) for v in range(seen.shape[1])]
    return np.stack(cols, -1)


def edge_velocity_term(joints: torch.Tensor, weight: torch.Tensor, centres: torch.Tensor | None = None) -> torch.Tensor:
    """Weighted mean squared norm of the first frame difference of the joints relative to the
    root (joint 0): the articulation's speed, not the body's.

    Args:
        joints: (T, J, 3) metres; weight: (T,) per frame in [0, 1], or (T, J, 1 + V) per joint
            (:func:`edge_hold_weights`: the whole difference, then its component along the ray
            from view v's camera centre to the joint); a difference ``t -> t+1`` counts with the
            larger of its two frames' weights; centres: (T, V, 3) camera centres (with per-view
            columns).
    Returns:
        m^2 per frame^2: mean over joints and over all ``T - 1`` differences (those without
        weight count 0), so that each covered frame weighs the same in any sequence, like a
        frame of :func:`velocity_term`.
    """
    if joints.shape[0] < 2:
        return joints.sum() * 0.0
    rel = joints - joints[:, :1]
    d = rel[1:] - rel[:-1]  # (T-1, J, 3)
    w = torch.maximum(weight[1:], weight[:-1])
    if w.dim() == 1:
        return (w * (d ** 2).sum(-1).mean(-1)).mean()
    cost = w[..., 0] * (d ** 2).sum(-1)
    for v in range(w.shape[-1] - 1):
        ray = (joints[:-1] - centres[:-1, v, None]).detach()
        ray = ray / ray.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        cost = cost + w[..., 1 + v] * ((d * ray).sum(-1) ** 2)
    return cost.mean()


def acceleration_term(x: torch.Tensor) -> torch.Tensor:
    """Mean squared norm of the second frame difference of ``x`` (T, ..., D); 0 for T < 3."""
    if x.shape[0] < 3:
        return x.sum() * 0.0
    return ((x[2:] - 2.0 * x[1:-1] + x[:-2]) ** 2).sum(-1).mean()


def pose_prior_term(body_pose: torch.Tensor, prior: torch.Tensor, conf: torch.Tensor | None = None) -> torch.Tensor:
    """Pull towards a prior body pose: mean over frames of the squared axis-angle difference.

    Args:
        body_pose: (T, 69) axis-angle of joints 1..23.
        prior: (T, 69) prior body pose (e.g. the regressor's, moved to the world: body pose is
            frame independent).
        conf: (T,) per-frame weight (0 where the prior is missing); None = all 1.

    Axis-angle differences are a fair distance for the small corrections SMPLify makes; the
    release uses the same plain squared difference.
    """
    d = ((body_pose - prior) ** 2).sum(-1)
    if conf is None:
        return d.mean()
    return (conf * d).sum() / conf.sum().clamp(min=1e-12)


def joint_limits_term(body_pose: torch.Tensor, hinges: tuple[tuple[int, int, float], ...] = HINGES) -> torch.Tensor:
    """Hinge joints bend one way only: mean over frames of the summed squared violations.

    Args:
        body_pose: (T, 69) axis-angle of joints 1..23.
        hinges: (SMPL joint, axis, sign); the axis-angle component ``sign * pose[joint, axis]``
            below zero is penalised quadratically (knee hyper-extension, elbow bending backwards).
    """
    idx, sign = _constant(("hinges", hinges), body_pose, lambda: (
        [3 * (j - 1) + a for j, a, _ in hinges], [s for _, _, s in hinges]))
    v = torch.relu(-sign * body_pose[:, idx])
    return (v ** 2).sum(-1).mean() if len(body_pose) else body_pose.sum() * 0.0


_CONSTANTS: dict = {}


def _constant(key: tuple, like: torch.Tensor, make) -> tuple[torch.Tensor, torch.Tensor]:
    """The pair of tensors ``make()`` describes (integer indices stay int64, the rest ``like``'s
    dtype), on ``like``'s device, built once per key, dtype and device: the fit evaluates the terms
    hundreds of times with the same constants."""
    k = key + (like.dtype, like.device)
    if k not in _CONSTANTS:
        a, b = make()
        conv = lambda x: torch.as_tensor(np.asarray(x), device=like.device,  # noqa: E731
                                         dtype=torch.int64 if np.asarray(x).dtype.kind == "i" else like.dtype)
        _CONSTANTS[k] = (conv(a), conv(b))
    return _CONSTANTS[k]


def _range(lo_x, hi_x, lo_y, hi_y, lo_z, hi_z):
    return ((lo_x, hi_x), (lo_y, hi_y), (lo_z, hi_z))


#: Anatomical range of each body joint (SMPL joints 1..23) per axis-angle component of its local
#: rotation, radians: ``((x_lo, x_hi), (y_lo, y_hi), (z_lo, z_hi))``. SMPL's joint frames share the
#: canonical axes (X to the body's left, Y up, Z forward), so e.g. a hip's -x bends the thigh
#: forward (flexion), a knee's +x bends the shin back, the left shoulder's +z lifts the arm. The
#: figures are generous versions of textbook ranges of motion (hip flexion ~125 deg, knee ~150
#: deg, shoulder elevation ~180 deg, spine segments a few tens of degrees each): the term keeps a
#: fit from impossible poses, it does not prefer any possible one. For larger rotations the
#: components are not Euler angles, but the box stays a fair bound for the joints that turn far
#: (shoulders, hips), whose boxes are wide.
ANATOMICAL_RANGES: tuple[tuple[tuple[float, float], ...], ...] = (
    _range(-2.4, 0.7, -0.9, 0.9, -0.6, 1.3),    # 1 left hip
    _range(-2.4, 0.7, -0.9, 0.9, -1.3, 0.6),    # 2 right hip
    _range(-0.5, 0.9, -0.6, 0.6, -0.5, 0.5),    # 3 spine1
    _range(-0.1, 2.7, -0.4, 0.4, -0.3, 0.3),    # 4 left knee
    _range(-0.1, 2.7, -0.4, 0.4, -0.3, 0.3),    # 5 right knee
    _range(-0.4, 0.6, -0.5, 0.5, -0.4, 0.4),    # 6 spine2
    _range(-1.0, 1.0, -0.6, 0.6, -0.5, 0.5),    # 7 left ankle
    _range(-1.0, 1.0, -0.6, 0.6, -0.5, 0.5),    # 8 right ankle
    _range(-0.4, 0.6, -0.5, 0.5, -0.4, 0.4),    # 9 spine3
    _range(-0.5, 0.5, -0.4, 0.4, -0.4, 0.4),    # 10 left foot
    _range(-0.5, 0.5, -0.4, 0.4, -0.4, 0.4),    # 11 right foot
    _range(-0.7, 0.9, -0.9, 0.9, -0.6, 0.6),    # 12 neck
    _range(-0.4, 0.4, -0.5, 0.5, -0.5, 0.5),    # 13 left collar
    _range(-0.4, 0.4, -0.5, 0.5, -0.5, 0.5),    # 14 right collar
    _range(-0.7, 0.9, -0.9, 0.9, -0.6, 0.6),    # 15 head
    _range(-1.8, 1.8, -2.0, 1.6, -1.9, 1.8),    # 16 left shoulder
    _range(-1.8, 1.8, -1.6, 2.0, -1.8, 1.9),    # 17 right shoulder
    _range(-1.6, 1.6, -2.7, 0.1, -0.4, 0.4),    # 18 left elbow
    _range(-1.6, 1.6, -0.1, 2.7, -0.4, 0.4),    # 19 right elbow
    _range(-1.6, 1.6, -1.1, 1.1, -1.2, 1.2),    # 20 left wrist
    _range(-1.6, 1.6, -1.1, 1.1, -1.2, 1.2),    # 21 right wrist
    _range(-0.6, 0.6, -0.6, 0.6, -0.6, 0.6),    # 22 left hand
    _range(-0.6, 0.6, -0.6, 0.6, -0.6, 0.6),    # 23 right hand
)


def joint_range_term(body_pose: torch.Tensor, ranges=ANATOMICAL_RANGES) -> torch.Tensor:
    """Per-axis anatomical limits: mean over frames of the summed squared distances of each
    axis-angle component of ``body_pose`` (T, 69) outside its range (:data:`ANATOMICAL_RANGES`)."""
    lo, hi = _constant(("ranges", ranges), body_pose, lambda: tuple(np.asarray(ranges, dtype=np.float64).reshape(69, 2).T))
    v = torch.relu(lo - body_pose) + torch.relu(body_pose - hi)
    return (v ** 2).sum(-1).mean() if len(body_pose) else body_pose.sum() * 0.0


def shape_prior_term(betas: torch.Tensor) -> torch.Tensor:
    """Mean squared shape coefficient of ``betas`` (B,): SMPL betas are unit-variance PCA
    coefficients, so this is the (scaled) negative log-likelihood of the shape."""
    return (betas ** 2).mean()
