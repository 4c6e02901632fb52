"""Contact-marker alignment: the yaw + translation that puts the performer's feet on the markers.

The paper's optional post-processing (supplement, "Contact Label & Optimization"): the performer
starts and ends a sequence standing on markers whose 3D positions were read off the scene mesh.
At each annotated frame the *contact point* of the body (the centre of the lowest points of both
feet) should sit on its marker; a rigid correction of the whole sequence that does so removes the
few centimetres Stage III may leave. The world is gravity-aligned, so the correction is a yaw
about +Z plus a translation (horizontal by default).

How it differs from the official release (reference notes, section 5), on purpose:

- **Closed form, not gradient descent.** A yaw + XY translation fitted to point pairs in the least
  squares sense is a 2D Procrustes problem with an exact SVD-free solution (an ``atan2``), so there
  is no learning rate, iteration count or local minimum.
- **Yaw about the contacts' centroid**, not the world origin. With the origin as pivot a small yaw
  moves the contacts by ``yaw x distance-from-origin``, which the translation must then undo: the
  two parameters trade off and the fit is ill-conditioned far from the origin. About the
  centroid, the translation is exactly the mean offset and the yaw only turns the contacts'
  spread.
- **The feet, not the pelvis**, as the paper says: the pelvis is ~10-20 cm off the feet's centre
  in a normal stance, and that offset turns with the body's heading, so aligning the pelvis puts
  differently oriented stances off their markers.
- **Z** is left alone by default (the floor from Stage I is trusted); ``fit_z`` also fits a height
  shift. The height gap is always reported.
- **Never silently skipped**: when the markers disagree with the motion beyond
  :attr:`ContactConfig.max_residual_m` after the fit, or the correction is implausibly large, the
  result says ``refused=True`` with a message naming the worst contact; the caller decides.
- **Yaw needs a baseline**: one marker (or several at nearly the same place) only fixes the
  translation; the yaw is not fitted rather than fitted to noise.

Robustness: contacts are few (typically 2-10) and annotated by hand, so a contact that disagrees
is an annotation error (wrong frame, wrong marker) rather than noise to be down-weighted. The fit
is plain least squares over all contacts and a disagreement is reported, naming the contact,
instead of being hidden by a robust kernel.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.geometry.transforms import is_rigid, make_T, rot_z
from embodmocap.motion.config import ContactConfig  # noqa: F401 (defined with the stage's settings)
from embodmocap.types import SmplParams

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ContactAlignment:
    """Result of :func:`align_to_contacts`.

    Attributes:
        T: (4, 4) the correction to apply (new world <- old world): a yaw about +Z and a
            translation. The identity when ``refused``.
        T_fit: (4, 4) the fitted correction, also when it was refused (for diagnosis).
        yaw_deg: fitted yaw, degrees (0 when the markers gave no baseline).
        shift_m: (3,) fitted translation of the contacts' centroid, metres.
        frames: (N,) sequence frame of each contact, in the order given.
        residuals_before_m: (N,) distance from each contact point to its marker before the fit
            (horizontal, or 3D with ``fit_z``), metres.
        residuals_after_m: (N,) the same after applying ``T_fit``.
        height_gap_m: (N,) marker z minus contact-point z after ``T_fit``, metres (not corrected
            unless ``fit_z``).
        yaw_fitted: whether the markers' spread allowed a yaw fit.
        refused: True when the fit is not to be applied (see ``message``).
        message: one line: what was done, or why it was refused, naming the worst contact.
    """

    T: NDArray[np.float64]
    T_fit: NDArray[np.float64]
    yaw_deg: float
    shift_m: NDArray[np.float64]
    frames: NDArray[np.int64]
    residuals_before_m: NDArray[np.float64]
    residuals_after_m: NDArray[np.float64]
    height_gap_m: NDArray[np.float64]
    yaw_fitted: bool
    refused: bool
    message: str


def contact_points(model, params: SmplParams, frames: NDArray, sole_band_m: float = 0.01) -> NDArray[np.float64]:
    """(N, 3) contact point of the body at sequence frames ``frames`` (N,), in the params' frame.

    Per foot (vertex ids from :func:`embodmocap.body.vertex_sets.foot_vertex_ids`: the rest-pose
    vertices nearest the ankle/foot joints and below the ankle), the *sole patch* is the foot's
    vertices within ``sole_band_m`` of its lowest vertex (lowest = smallest world z). A foot's
    point is the patch's mean x, y and its lowest z; the contact point is the mean of the two
    feet's points (the paper's "centre of the lowest points of both feet").
    """
    from embodmocap.body.vertex_sets import foot_vertex_ids

    frames = np.asarray(frames, dtype=np.int64)
    left, right = foot_vertex_ids(model, params.betas)
    out = model.forward(
        params.betas, params.global_orient[frames], params.body_pose[frames], params.transl[frames],
        dtype=torch.float64,
    )
    v = out.vertices.detach().cpu().numpy()  # (N, V, 3)
    feet = [v[:, ids] for ids in (left, right)]  # 2 x (N, F, 3)
    points = []
    for foot in feet:  # two feet, each vectorised over contacts
        low = foot[..., 2].min(axis=1)  # (N,)
        sole = foot[..., 2] <= low[:, None] + sole_band_m  # (N, F)
        xy = (foot[..., :2] * sole[..., None]).sum(axis=1) / sole.sum(axis=1)[:, None]
        points.append(np.concatenate([xy, low[:, None]], axis=1))
    return 0.5 * (points[0] + points[1])


def align_to_contacts(
    model, params: SmplParams, contacts: Sequence[tuple[int, NDArray]], cfg: ContactConfig = ContactConfig()
) -> ContactAlignment:
    """Fit the yaw + translation putting the body's contact points on their markers.

    Args:
        model: the body model (:class:`embodmocap.body.model.BodyModel`).
        params: world-space SMPL parameters (Z up, metres), one row per sequence frame.
        contacts: ``(frame, xyz)`` pairs: a sequence frame (index into ``params``) where the
            performer stands on a marker, and the marker's (3,) position in the world, metres.
        cfg: fit and refusal settings.

    The fit, with ``p_i`` the contact points (:func:`contact_points`), ``c_i`` the markers,
    bars their means and primes their horizontal deviations from the means:

        yaw = atan2(sum_i p'_i x c'_i, sum_i p'_i . c'_i)     (2D cross and dot products)
        T(x) = Rz(yaw) (x - p_bar) + p_bar + s,   s_xy = c_bar_xy - p_bar_xy,
        s_z = mean_i(c_iz - p_iz) with ``fit_z``, else 0

    which minimises ``sum_i |T(p_i) - c_i|^2`` over the horizontal coordinates exactly (and the
    vertical one with ``fit_z``). Without a baseline (``cfg.min_yaw_baseline_m``) yaw = 0.

    Raises:
        InputError: no contacts, a frame outside the sequence, a marker that is not 3 finite
            numbers, or a body that is not finite at a contact frame.
    """
    frames, markers = _check_contacts(params, contacts)
    p = contact_points(model, params, frames, cfg.sole_band_m)
    if not np.all(np.isfinite(p)):
        raise InputError(None, f"the body is not finite at contact frames {frames.tolist()}",
                         "check the SMPL fit of those frames")
    dims = 3 if cfg.fit_z else 2
    before = np.linalg.norm((markers - p)[:, :dims], axis=1)

    p_bar, c_bar = p.mean(axis=0), markers.mean(axis=0)
    pd, cd = (p - p_bar)[:, :2], (markers - c_bar)[:, :2]
    spread = float(np.sqrt((cd ** 2).sum(axis=1).mean()))
    yaw_fitted = spread >= cfg.min_yaw_baseline_m
    cross = np.sum(pd[:, 0] * cd[:, 1] - pd[:, 1] * cd[:, 0])
    dot = np.sum(pd[:, 0] * cd[:, 0] + pd[:, 1] * cd[:, 1])
    yaw = float(np.arctan2(cross, dot)) if yaw_fitted else 0.0
    shift = np.array([c_bar[0] - p_bar[0], c_bar[1] - p_bar[1], c_bar[2] - p_bar[2] if cfg.fit_z else 0.0])
    R = rot_z(yaw)
    T_fit = make_T(R, p_bar + shift - R @ p_bar)

    moved = p @ R.T + T_fit[:3, 3]
    after = np.linalg.norm((markers - moved)[:, :dims], axis=1)
    gap = markers[:, 2] - moved[:, 2]
    worst = int(np.argmax(after))
    yaw_deg = float(np.rad2deg(yaw))
    shift_norm = float(np.linalg.norm(shift))
    where = f"contact {worst} (frame {frames[worst]}) is {after[worst]:.3f} m from its marker"

    problems = []
    if after[worst] > cfg.max_residual_m:
        problems.append(f"markers disagree with the motion after the fit: {where} "
                        f"(> max_residual_m {cfg.max_residual_m:g})")
    if abs(yaw_deg) > cfg.max_yaw_deg:
        problems.append(f"yaw correction {yaw_deg:.2f} deg exceeds max_yaw_deg {cfg.max_yaw_deg:g}")
    if shift_norm > cfg.max_shift_m:
        problems.append(f"shift {shift_norm:.3f} m exceeds max_shift_m {cfg.max_shift_m:g}")
    refused = bool(problems)
    yaw_note = "" if yaw_fitted else (f"; yaw not fitted (markers spread {spread:.3f} m "
                                      f"< min_yaw_baseline_m {cfg.min_yaw_baseline_m:g})")
    if refused:
        message = "refused: " + "; ".join(problems) + "; check the contact frames and markers" + yaw_note
        log.warning("contact alignment %s", message)
    else:
        message = (f"applied: yaw {yaw_deg:.3f} deg, shift {np.round(shift, 4).tolist()} m, residual "
                   f"{before.max():.3f} -> {after.max():.3f} m (worst: {where}){yaw_note}")
        log.info("contact alignment %s", message)
    return ContactAlignment(
        T=np.eye(4) if refused else T_fit, T_fit=T_fit, yaw_deg=yaw_deg, shift_m=shift, frames=frames,
        residuals_before_m=before, residuals_after_m=after, height_gap_m=gap,
        yaw_fitted=yaw_fitted, refused=refused, message=message,
    )


def apply_alignment(model, params: SmplParams, T: NDArray) -> SmplParams:
    """``params`` moved rigidly by ``T`` (4, 4, new world <- old world), pelvis-consistent.

    Uses :meth:`BodyModel.params_for_world_frame`: ``global_orient' = R global_orient`` and the
    translation chosen so that every vertex ``v`` becomes ``R v + t`` (SMPL rotates about the rest
    pelvis, not the origin, so ``transl`` is not simply ``R transl + t``).
    """
    return model.params_for_world_frame(params, T)


def apply_alignment_to_cameras(T_world_cam: NDArray, T: NDArray) -> NDArray[np.float64]:
    """Camera-to-world poses (..., 4, 4) after the world correction ``T`` (4, 4): ``T @ T_world_cam``.

    A world point ``X`` seen by a camera is ``T X`` after the correction; the corrected camera
    ``T T_world_cam`` sees it at the same camera coordinates, hence the same pixel. (In the
    paper's world-to-camera form: ``R' = R R_c^T``, ``t' = t - R R_c^T t_c``.)
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not bool(is_rigid(T)):
        raise ValueError(f"T must be a rigid 4x4 transform, got shape {T.shape}")
    T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
    if T_world_cam.shape[-2:] != (4, 4):
        raise ValueError(f"T_world_cam must be (..., 4, 4), got {T_world_cam.shape}")
    return T @ T_world_cam


def _check_contacts(params: SmplParams, contacts: Sequence[tuple[int, NDArray]]) -> tuple[NDArray, NDArray]:
    """(frames (N,) int64, markers (N, 3) float64) from ``contacts``, or InputError."""
    fix = "give contacts as (sequence frame, [x, y, z] in metres) pairs in the session manifest"
    if len(contacts) == 0:
        raise InputError(None, "no contacts to align to", fix)
    frames, markers = [], []
    for i, item in enumerate(contacts):
        try:
            frame, xyz = item
            frame_i = int(frame)
            xyz_a = np.asarray(xyz, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise InputError(None, f"contact {i} is not a (frame, xyz) pair: {item!r} ({err})", fix) from None
        if frame_i != frame or not 0 <= frame_i < len(params):
            raise InputError(None, f"contact {i}: frame {frame!r} outside the sequence's 0..{len(params) - 1}", fix)
        if xyz_a.shape != (3,) or not np.all(np.isfinite(xyz_a)):
            raise InputError(None, f"contact {i} (frame {frame_i}): marker {xyz!r} is not 3 finite numbers", fix)
        frames.append(frame_i)
        markers.append(xyz_a)
    return np.array(frames, dtype=np.int64), np.stack(markers)


__all__ = [
    "ContactAlignment", "ContactConfig", "align_to_contacts", "apply_alignment", "apply_alignment_to_cameras",
    "contact_points",
]
