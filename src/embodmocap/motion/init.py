"""Starting points for the world-space SMPLify.

- :func:`init_from_prior`: a camera-space body prior (one view's regressor output) moved into the
  world through that view's cameras, frame by frame, keeping each frame's pelvis where the
  regressor put it.
- :func:`init_from_keypoints`: no prior: shape from bone lengths, the torso fitted rigidly, the
  limbs by analytic IK (:mod:`embodmocap.motion.ik`).

Frames with nothing to go on (an all-zero prior row, or no hips/shoulders) are filled from their
neighbours: rotations by normalised quaternion interpolation, positions linearly, the ends held.
"""

from __future__ import annotations

import logging
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from embodmocap.body.model import BodyModel
from embodmocap.geometry.transforms import R_ZUP_YUP, rot_z
from embodmocap.motion.body_points import body_keypoints
from embodmocap.motion.fill import fill_linear, fill_rotations
from embodmocap.motion.ik import init_ik
from embodmocap.types import COCO17_NAMES, SmplParams

log = logging.getLogger(__name__)


class CameraPrior(Protocol):
    """What :func:`init_from_prior` reads (e.g. :class:`embodmocap.io.body_prior.BodyPriorSeq`)."""

    global_orient_cam: NDArray  # (T, 3) axis-angle, camera frame (OpenCV axes)
    body_pose: NDArray  # (T, 69)
    betas: NDArray  # (T, B)
    transl_cam: NDArray  # (T, 3) SMPL transl in the camera frame, metres


def init_from_prior(model: BodyModel, prior: CameraPrior, T_world_cam: NDArray, fps: float = 30.0,
                    gender: str = "neutral") -> SmplParams:
    """World-space parameters from a camera-space prior and the view's cameras.

    Per frame t, with ``R, c`` the rotation and centre of ``T_world_cam[t]`` and ``J0(b)`` the
    rest pelvis (:meth:`BodyModel.pelvis_offset`)::

        global_orient_w = R * global_orient_cam
        pelvis_w        = R (transl_cam + J0(b_t)) + c        (the regressor's pelvis, per frame)
        transl_w        = pelvis_w - J0(b)                    (b = median of the valid b_t)

    so the pelvis stays where the regressor put it even though the betas become one shared set.
    Rows that are all zeros are missing and are interpolated from their neighbours.

    Args:
        model: body model (for ``J0``).
        prior: (T,) rows of camera-space parameters (see :class:`CameraPrior`).
        T_world_cam: (T, 4, 4) camera-to-world of the same frames (OpenCV axes).

    Raises:
        ValueError: mismatched lengths or no valid frame.
    """
    go_c = np.array(prior.global_orient_cam, dtype=np.float64)
    pose = np.asarray(prior.body_pose, dtype=np.float64)
    betas_t = np.asarray(prior.betas, dtype=np.float64)
    tr_c = np.asarray(prior.transl_cam, dtype=np.float64)
    Twc = np.array(T_world_cam, dtype=np.float64)
    T = len(go_c)
    if Twc.shape != (T, 4, 4):
        raise ValueError(f"T_world_cam must be (T={T}, 4, 4) like the prior, got {Twc.shape}")
    if pose.shape != (T, 69) or tr_c.shape != (T, 3) or betas_t.ndim != 2 or len(betas_t) != T:
        raise ValueError(f"prior arrays disagree: global_orient {go_c.shape}, body_pose {pose.shape}, "
                         f"betas {betas_t.shape}, transl {tr_c.shape}")
    rows = np.concatenate([go_c, pose, betas_t, tr_c], 1)
    valid = np.isfinite(rows).all(1) & (np.abs(np.nan_to_num(rows)).sum(1) > 0)
    if not valid.any():
        raise ValueError("the body prior has no valid frame (all rows are zero or non-finite)")
    if not valid.all():
        log.info("body prior: %d of %d frames missing, interpolated", int((~valid).sum()), T)

    R, c = Twc[:, :3, :3], Twc[:, :3, 3]
    go_w = (Rotation.from_matrix(R) * Rotation.from_rotvec(np.nan_to_num(go_c))).as_rotvec()
    pelvis_w = np.einsum("tij,tj->ti", R, np.nan_to_num(tr_c) + model.pelvis_offset(np.nan_to_num(betas_t))) + c
    betas = np.median(betas_t[valid], axis=0)

    rot = fill_rotations(np.concatenate([go_w, np.nan_to_num(pose)], 1).reshape(T, 24, 3), valid).reshape(T, 72)
    transl = fill_linear(pelvis_w, valid) - model.pelvis_offset(betas)
    return SmplParams(betas=betas, global_orient=rot[:, :3], body_pose=rot[:, 3:], transl=transl, fps=fps, gender=gender)


_I = {n: i for i, n in enumerate(COCO17_NAMES)}


def init_from_keypoints(model: BodyModel, points: NDArray, conf: NDArray, fps: float = 30.0,
                        gender: str = "neutral", min_conf: float = 0.1, layout: str = "COCO17",
                        reach_min_conf: float = 0.0) -> SmplParams:
    """A posed body on the triangulated keypoints, no regressor needed (:mod:`embodmocap.motion.ik`).

    Shape from the observed bone lengths, the root and trunk from a rigid fit of the hips and
    shoulders, the limbs by analytic IK; frames whose torso is not seen are interpolated.

    Args:
        points: (T, 17, 3) COCO-17-ordered keypoints of ``layout`` (whose hip definition,
            :data:`embodmocap.body.joints.HIP_DEFINITIONS`) in the world (Z up), metres (NaN = missing).
        conf: (T, 17) confidences; below ``min_conf`` counts as missing.
        reach_min_conf: see :func:`embodmocap.motion.ik.init_ik`.

    Raises:
        ValueError: bad shapes, or no frame with three of the hips and shoulders.
    """
    betas, go, pose, transl, _ = init_ik(model, points, conf, layout, min_conf, reach_min_conf=reach_min_conf)
    return SmplParams(betas=betas, global_orient=go, body_pose=pose, transl=transl, fps=fps, gender=gender)


def snap_to_keypoints(model: BodyModel, params: SmplParams, points: NDArray, conf: NDArray,
                      min_conf: float = 0.1, min_joints: int = 4) -> SmplParams:
    """Move each frame of ``params`` so that its COCO-17 joints sit on the triangulated ones.

    A monocular prior's depth is often tens of centimetres off, and the world SMPLify's robust 3D
    term (a few centimetres of scale) gives almost no pull from that far away. So before fitting,
    each frame's translation is shifted by the median (per axis) of ``points - joints`` over the
    joints seen with confidence >= ``min_conf``; frames with fewer than ``min_joints`` such joints
    take the shift interpolated from their neighbours. Rotations, pose and shape are kept.

    Args:
        model: the body model.
        params: (T frames) world parameters, e.g. from :func:`init_from_prior`.
        points: (T, 17, 3) triangulated COCO-17 keypoints, NaN where missing.
        conf: (T, 17) their confidence.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.shape != (len(params), 17, 3) or np.shape(conf) != (len(params), 17):
        raise ValueError(f"points must be ({len(params)}, 17, 3) and conf ({len(params)}, 17), "
                         f"got {points.shape} and {np.shape(conf)}")
    coco = body_keypoints(model, params)[1]
    seen = np.isfinite(points).all(axis=-1) & (np.asarray(conf) >= min_conf)
    diff = np.where(seen[..., None], points - coco, np.nan)
    ok = seen.sum(axis=1) >= min_joints
    if not ok.any():
        return params
    with np.errstate(all="ignore"):
        shift = np.nanmedian(np.where(ok[:, None, None], diff, 0.0), axis=1)  # (T, 3)
    shift = fill_linear(np.where(ok[:, None], shift, 0.0), ok)
    from dataclasses import replace

    return replace(params, transl=np.asarray(params.transl) + shift)


def prefer_keypoints(model, init, kp_init, points: NDArray, conf: NDArray, min_conf: float, margin_m: float,
                     layout: str = "COCO17"):
    """``init`` with the frames where it is more than ``margin_m`` further from the 3D keypoints
    than ``kp_init`` (median over the triangulated joints) taken from ``kp_init``; and those frames
    (T,) bool. Betas stay ``init``'s."""
    from dataclasses import replace

    seen = np.isfinite(points).all(-1) & (np.nan_to_num(conf) >= min_conf)

    def err(p):
        kp = body_keypoints(model, p, layout)[1]
        d = np.where(seen, np.linalg.norm(kp - np.nan_to_num(points), axis=-1), 0.0)
        n = seen.sum(1)
        # Median over the seen joints of each frame (frames with none: 0, nothing to disagree with).
        d = np.sort(np.where(seen, d, np.inf), axis=1)
        mid = np.take_along_axis(d, np.clip((n - 1) // 2, 0, None)[:, None], 1)[:, 0]
        mid2 = np.take_along_axis(d, np.clip(n // 2, 0, None)[:, None], 1)[:, 0]
        return np.where(n > 0, 0.5 * (mid + np.where(n > 0, mid2, 0.0)), 0.0)

    kp_same_shape = replace(kp_init, betas=init.betas,
                            transl=np.asarray(kp_init.transl) + model.pelvis_offset(kp_init.betas) - model.pelvis_offset(init.betas))
    worse = err(init) > err(kp_same_shape) + margin_m
    if not worse.any():
        return init, worse
    pick = lambda a, b: np.where(worse.reshape((-1,) + (1,) * (np.ndim(a) - 1)), b, a)  # noqa: E731
    return replace(init, global_orient=pick(init.global_orient, kp_same_shape.global_orient),
                   body_pose=pick(init.body_pose, kp_same_shape.body_pose),
                   transl=pick(init.transl, kp_same_shape.transl)), worse


def with_fps(params, fps: float, gender: str | None):
    from dataclasses import replace

    return replace(params, fps=float(fps), gender=gender or params.gender)
