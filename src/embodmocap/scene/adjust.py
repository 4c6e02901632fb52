"""Stage I drift correction of the key frames: bundle adjustment of the sparse model's poses and
points, mapped back onto the capture's poses (used by :mod:`embodmocap.scene.sfm` with
``SfmConfig.refine_poses``)."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.transforms import invert_T

if TYPE_CHECKING:
    from embodmocap.scene.sfm import SfmConfig

log = logging.getLogger("embodmocap.scene.sfm")


def _refine_poses(pycolmap, rec, ids: list[int], T_prior: NDArray, cfg: SfmConfig) -> NDArray[np.float64] | None:
    """Drift-corrected key frame poses (K, 4, 4) camera-to-world, or None to keep ``T_prior``.

    Bundle adjustment of poses and points (intrinsics fixed) on the triangulated model, mapped back
    onto ``T_prior`` (the capture's poses of ``ids``) by the similarity that fits them best. The
    correction each key frame got (its adjusted pose against its capture pose) is then smoothed
    over neighbouring key frames (running median of ``cfg.correction_window``): VIO drift is slow,
    while a key frame with few observations can slide in the adjustment on its own. None when the
    adjustment moved a key frame more than ``cfg.max_pose_change_m`` or changed the scale by > 2 %.
    """
    from scipy.ndimage import median_filter
    from scipy.spatial.transform import Rotation

    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = False
    opts.refine_principal_point = False
    opts.refine_extra_params = False
    rms0 = _rms_reprojection(rec)
    pycolmap.bundle_adjustment(rec, opts)
    rms1 = _rms_reprojection(rec)
    gain = 1.0 - rms1 / max(rms0, 1e-12)
    if not gain >= cfg.min_adjust_gain:
        log.info("sparse model: the adjustment lowers the reprojection error only %.1f %% (%.3f -> %.3f px); keeping "
                 "the capture's poses", 100 * gain, rms0, rms1)
        return None
    T_ba = []
    for image_id in ids:
        P = np.eye(4)
        P[:3, :4] = rec.image(image_id).cam_from_world().matrix()
        T_ba.append(invert_T(P))
    T_ba = np.stack(T_ba)
    T_prior = np.asarray(T_prior, dtype=np.float64)
    S = _fit_similarity(T_ba, T_prior)
    scale = float(np.cbrt(np.linalg.det(S[:3, :3])))
    T_adj = S @ T_ba
    T_adj[:, :3, :3] /= scale
    shift = T_adj[:, :3, 3] - T_prior[:, :3, 3]
    moved = np.linalg.norm(shift, axis=1)
    if (not np.all(np.isfinite(moved)) or moved.max() > cfg.max_pose_change_m
            or np.median(moved) > cfg.max_median_change_m or abs(scale - 1.0) > 0.02):
        log.warning("sparse model: the bundle adjustment moved a key frame %.1f cm from its capture pose (scale "
                    "%.4f); keeping the capture's poses", 100 * float(np.nanmax(moved)), scale)
        return None
    turn = Rotation.from_matrix(T_adj[:, :3, :3] @ np.swapaxes(T_prior[:, :3, :3], -1, -2)).as_rotvec()
    w = max(1, int(cfg.correction_window))
    shift = median_filter(shift, size=(w, 1), mode="nearest")
    turn = median_filter(turn, size=(w, 1), mode="nearest")
    T_out = T_prior.copy()
    T_out[:, :3, :3] = Rotation.from_rotvec(turn).as_matrix() @ T_prior[:, :3, :3]
    T_out[:, :3, 3] = T_prior[:, :3, 3] + shift
    log.info("sparse model: drift correction of the key frames %.2f cm median, %.2f cm max (adjustment scale %.5f)",
             100 * float(np.median(np.linalg.norm(shift, axis=1))), 100 * float(np.linalg.norm(shift, axis=1).max()), scale)
    return T_out


def _rms_reprojection(rec) -> float:
    """RMS reprojection error (pixels) over every observation of a 3D point in the model."""
    sq, n = 0.0, 0
    xyz = {pid: p.xyz for pid, p in rec.points3D.items()}
    for image in rec.images.values():
        obs = [(p.xy, xyz[p.point3D_id]) for p in image.points2D if p.has_point3D()]
        if not obs:
            continue
        xy = np.array([o[0] for o in obs])
        X = np.array([o[1] for o in obs])
        P = image.cam_from_world().matrix()
        cam = rec.cameras[image.camera_id]
        Xc = X @ P[:, :3].T + P[:, 3]
        proj = np.asarray(cam.img_from_cam(Xc), dtype=np.float64)[:, :2]
        sq += float(np.sum((proj - xy) ** 2))
        n += len(xy)
    return float(np.sqrt(sq / max(n, 1)))


def _fit_similarity(T_from: NDArray, T_to: NDArray) -> NDArray[np.float64]:
    """(4, 4) similarity ``S = [s R | t]`` putting cameras ``T_from`` (K, 4, 4) on ``T_to`` (K, 4, 4):
    R the chordal mean of the per-camera rotations (orientations fix the tilt, which centres on a
    nearly level path would not), then s and t by least squares on the centres."""
    M = np.einsum("kij,klj->il", T_to[:, :3, :3], T_from[:, :3, :3])  # sum R_to R_from^T
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    a = T_from[:, :3, 3] - T_from[:, :3, 3].mean(0)
    b = T_to[:, :3, 3] - T_to[:, :3, 3].mean(0)
    s = float(np.sum((a @ R.T) * b) / max(np.sum(a * a), 1e-12))
    S = np.eye(4)
    S[:3, :3] = s * R
    S[:3, 3] = T_to[:, :3, 3].mean(0) - s * R @ T_from[:, :3, 3].mean(0)
    return S
