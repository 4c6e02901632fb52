"""World-space SMPLify (Stage IV): fit SMPL motion to triangulated 3D and per-view 2D keypoints.

Cameras and the scene are fixed; the unknowns are one shape ``betas`` (B,) for the sequence and
per-frame ``global_orient`` (T, 3), ``body_pose`` (T, 69) and ``transl`` (T, 3) in the scene world
(Z up, metres). The objective is a weighted sum of the terms of :mod:`embodmocap.motion.terms`.

Four stages (the paper's two phases, with the pose freed in two steps between them):

1. **Phase 1 (global)** — shape, root orientation and translation (``body_pose`` fixed at the
   init) on the 3D keypoint term, the smoothness terms and the shape prior: it puts the body where
   the keypoints are before the limbs are allowed to move.
2. **Torso** — adds the trunk's joints (spine, neck, collars, head) to the free parameters.
3. **Limbs** — the limbs' joints (hips, knees, ankles, shoulders, elbows, wrists) instead: each
   limb settles on its keypoints with the trunk in place, so a limb error cannot twist the trunk.
4. **Phase 2 (all)** — everything, with all terms (3D keypoints, reprojection in every view,
   smoothness, pose prior, joint limits and anatomical ranges, shape prior).

Stages 2 and 3 use the 3D, smoothness and joint-limit terms; they are optional and off by default
(``torso_iterations`` / ``limbs_iterations`` 0: after the keypoint start, whose own steps are
global, torso and limbs, they changed nothing measurable and slowed phase 2 from poor starts). Which SMPL points the keypoints are
depends on the layout of the detector that produced them (the hips differ:
:data:`embodmocap.body.joints.HIP_DEFINITIONS`); a body model without the face vertex ids fits
without the five face keypoints (warned).

Speed: the body is evaluated by :class:`KeypointBody`, SMPL restricted to what the terms see
(24 joints by forward kinematics and the 5 face vertices COCO-17 needs), which equals
:class:`~embodmocap.body.model.BodyModel` exactly but skips skinning the 6,890 vertices; all frames
of a window are one batch. Adam (or L-BFGS, ``cfg.solver``) runs each phase. In phase 1 the pose
is held, so the body comes from :class:`HeldPoseBody` (its pose-dependent part built once); phase 2
of each window ends when that window's own loss stops falling (``cfg.phase2_stop_tol``).

Long sequences are cut into overlapping windows (``window_frames`` / ``overlap_frames``). Betas
must be shared, so with more than one window they are fitted first by both phases on
``shape_frames`` frames spread evenly over the whole sequence (smoothness off there: the frames
are not consecutive), then held fixed while each window runs both phases. Window results are
blended linearly across overlaps (translations linearly, rotations by normalised quaternion
blending). A sequence that fits in one window is fitted in one go with betas free in both phases.
The windows are fitted in ``cfg.workers`` contiguous batches, this process's and one per worker process (fresh
interpreters, never forks: :mod:`embodmocap.motion.fit_workers`; the same answer as one process), or
in as many as the cores ``embodmocap run`` lent the stage when that is more
(:func:`embodmocap.parallel.lent_cores`).

Threads: the fit sets ``torch.set_num_threads(cfg.threads)`` while it runs and restores the
previous count after (process-global: fits run in parallel threads of one process should share
one setting).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np
import torch
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter1d

from embodmocap.body.joints import coco17_matrix, face_vertex_ids
from embodmocap.body.model import BodyModel
from embodmocap.geometry.rotations import rotvec_to_matrix_torch as axis_angle_to_matrix
from embodmocap.geometry.rotations import smooth_rotvecs
from embodmocap.motion import terms as TM
from embodmocap.motion.config import SmplifyConfig  # noqa: F401 (defined with the stage's settings)
from embodmocap.motion.fit_workers import run_pieces, start_workers
from embodmocap.motion.floor import floor_term
from embodmocap.motion.windows import blend_states as _blend, blend_weights as _blend_weights, window_ranges  # noqa: F401
from embodmocap.parallel import cores_to_use
from embodmocap.progress import progress
from embodmocap.types import SmplParams

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------
# Configuration and results
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ViewObservations:
    """One view's cameras and 2D keypoints, for the reprojection term.

    K: (3, 3) intrinsics, pixels. T_world_cam: (T, 4, 4) camera-to-world of each sequence frame
    (OpenCV axes, scene world). keypoints: (T, 17, 3) COCO-17 pixel x, y and confidence (0 or NaN
    = missing). name: label used in the results (default ``view<i>``).
    """

    K: NDArray
    T_world_cam: NDArray
    keypoints: NDArray
    name: str = ""


@dataclass(frozen=True)
class SmplifyResult:
    """The fitted motion and how well it fits.

    params: world-space SMPL parameters (betas (B,), per-frame rotations and translation).
    terms_before / terms_after: each weighted term of the phase-2 objective (name -> value) at
    the init and at the result, over the whole sequence (``reproj/<view>`` per view).
    reproj_px: per view, the median reprojection error of the fitted COCO-17 keypoints over the
    keypoints with confidence, pixels (NaN if none).
    seconds: wall time of the fit; phase_seconds: "shape", "phase1", "phase2" wall times
    (summed over windows); windows: (start, end) frame ranges fitted.
    """

    params: SmplParams
    terms_before: dict[str, float]
    terms_after: dict[str, float]
    reproj_px: dict[str, float]
    seconds: float
    phase_seconds: dict[str, float] = field(default_factory=dict)
    windows: tuple[tuple[int, int], ...] = ()


# ---------------------------------------------------------------------------------------------
# The keypoint body: SMPL joints + face vertices without full skinning
# ---------------------------------------------------------------------------------------------


#: SMPL joints freed in the torso stage (spine, neck, collars, head) and the limbs stage.
TORSO_JOINTS: tuple[int, ...] = (3, 6, 9, 12, 13, 14, 15)
LIMB_JOINTS: tuple[int, ...] = (1, 2, 4, 5, 7, 8, 16, 17, 18, 19, 20, 21)
#: SMPL joints whose rotation moves no COCO-17 keypoint (or only the face): feet, wrists, hands,
#: collars, neck, head.
UNPINNED_JOINTS: tuple[int, ...] = (10, 11, 20, 21, 22, 23, 13, 14, 12, 15)
#: COCO-17 keypoints of the trunk and head (face, shoulders, hips): the only ones the global and
#: torso stages fit.
_TRUNK_KEYPOINTS = np.array([1.0] * 7 + [0.0] * 4 + [1.0] * 2 + [0.0] * 4)


class KeypointBody:
    """SMPL evaluated only where SMPLify looks: the 24 joints and the COCO-17 keypoints.

    Joints follow from the shaped rest joints by forward kinematics (pose blend shapes do not move
    joints); the 5 face vertices are skinned alone. Results equal
    :meth:`BodyModel.forward`'s ``joints`` and ``coco17``.
    """

    def __init__(self, model: BodyModel, dtype: torch.dtype = torch.float64, device: str | torch.device = "cpu",
                 layout: str = "COCO17") -> None:
        a = model.arrays
        try:
            ids = face_vertex_ids(model.vertex_ids)
            self.has_face = True
        except (KeyError, ValueError):
            # No face vertices on this mesh: the face keypoints follow the head joint and must not
            # be fitted (the caller drops them).
            ids = np.zeros(5, dtype=np.int64)
            self.has_face = False
        tt = lambda x: torch.as_tensor(np.ascontiguousarray(x), dtype=dtype, device=device)  # noqa: E731
        Jr = a["J_regressor"]
        self.num_betas = model.num_betas
        self.J_template = tt(Jr @ a["v_template"])  # (24, 3)
        self.J_dirs = tt(np.einsum("jv,vcb->jcb", Jr, a["shapedirs"]))  # (24, 3, B)
        self.f_template = tt(a["v_template"][ids])  # (5, 3)
        self.f_dirs = tt(a["shapedirs"][ids])  # (5, 3, B)
        # Pose blend shapes of the face vertices: only the joints whose rotation moves them (an
        # exactly-zero block of posedirs adds nothing; fewer features per frame and step).
        pd = np.asarray(a["posedirs"][ids]).reshape(len(ids), 3, 23, 9)
        blend = np.flatnonzero(np.abs(pd).sum((0, 1, 3)) > 0)
        self.pose_joints = torch.as_tensor(blend + 1, device=device)  # rows of the (T, 24) rotations
        self.f_posedirs = tt(pd[:, :, blend].reshape(len(ids), 3, 9 * len(blend)))  # (5, 3, 9 P)
        self.f_weights = tt(a["weights"][ids])  # (5, 24)
        A = coco17_matrix(layout)
        if not self.has_face:
            A[:5, 24:] = 0.0
            A[:5, 15] = 1.0
        self.coco = tt(A)  # (17, 29)
        parents = np.asarray(model.parents, dtype=np.int64).copy()
        parents[0] = -1
        self.parents = torch.as_tensor(parents, device=device)
        # Forward kinematics level by level of the tree (one batched product per level, 7 below the root),
        # over only the joints whose world rotation something needs (those with children, or that
        # move the face vertices); a leaf's position follows from its parent. Session 9 composed
        # them by pointer jumping (3 rounds over all 20 such joints: fewer ops, 3x the products),
        # which paid for a 180-frame window (cost per op) but not for the batched windows of a
        # long sequence (thousands of frames a step: cost per 3x3 product, issue 30).
        weighted = np.flatnonzero(np.abs(a["weights"][ids]).sum(0) > 0)
        self.face_joints = torch.as_tensor(weighted, device=device)  # joints that skin the face vertices
        self.f_weights = self.f_weights[:, weighted]  # (5, F)
        inner = set(parents[1:].tolist()) | set(weighted.tolist()) | {0}
        depth = {0: 0}
        for j in range(1, 24):  # SMPL lists every parent before its children
            depth[j] = depth[parents[j]] + 1
        order = sorted(inner, key=lambda j: (depth[j], j))  # level by level: row k of the world transforms
        slot = {j: k for k, j in enumerate(order)}
        self.inner = torch.as_tensor(order, device=device)
        self.levels = []  # (first row, end row, parent rows within the level above) below the root
        first = 0
        for lv in range(1, max(depth[j] for j in order) + 1):
            rows = [k for k, j in enumerate(order) if depth[j] == lv]
            par = [slot[parents[order[k]]] - first for k in rows]  # every parent sits on the level above
            self.levels.append((rows[0], rows[-1] + 1, torch.as_tensor(par, device=device)))
            first = rows[0]
        self.parent_slot = torch.as_tensor([slot[parents[j]] for j in range(1, 24)], device=device)  # (23,)
        self.face_slot = torch.as_tensor([slot[j] for j in weighted.tolist()], device=device)
        self.dtype, self.device = dtype, torch.device(device)

    def __call__(self, betas: torch.Tensor, global_orient: torch.Tensor, body_pose: torch.Tensor,
                 transl: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Joints (T, 24, 3) and COCO-17 keypoints (T, 17, 3) for betas (B,) and per-frame
        global_orient (T, 3), body_pose (T, 69), transl (T, 3)."""
        T = global_orient.shape[0]
        b = torch.nn.functional.pad(betas, (0, self.num_betas - betas.shape[-1]))
        J_rest = self.J_template + self.J_dirs @ b  # (24, 3)
        R_local = axis_angle_to_matrix(torch.cat([global_orient, body_pose], -1).reshape(T, 24, 3))
        bone = J_rest[1:] - J_rest[self.parents[1:]]  # (23, 3) rest offset from the parent
        offset = torch.cat([J_rest[:1], bone], 0)[self.inner]  # (n, 3) local translation of each inner joint
        # World rotation and position of each level's joints from their parents' (rows in level
        # order: every parent's row comes before its children's).
        # Gathers along the joint axis by index_select: its backward adds into the source's rows
        # (index_add) instead of advanced indexing's sorted, accumulating index_put.
        R_in = R_local.index_select(1, self.inner)  # (T, n, 3, 3)
        Rs, ts = [R_in[:, :1]], [offset[:1].expand(T, 1, 3)]
        for lo, hi, par in self.levels:
            Rp = Rs[-1].index_select(1, par)
            Rs.append(Rp @ R_in[:, lo:hi])
            ts.append((Rp @ offset[lo:hi, :, None])[..., 0] + ts[-1].index_select(1, par))
        R, t = torch.cat(Rs, 1), torch.cat(ts, 1)
        # Every joint's position from its parent's world transform (the inner joints' equal ``t``).
        pos = torch.cat([t[:, :1], (R.index_select(1, self.parent_slot) @ bone[..., None])[..., 0]
                         + t.index_select(1, self.parent_slot)], 1)
        # Face vertices: shape + pose blend shapes, then linear blend skinning by the joints that
        # carry weight on them.
        v_posed = (self.f_template + self.f_dirs @ b).expand(T, -1, -1)
        if len(self.pose_joints):
            eye = torch.eye(3, dtype=R_local.dtype, device=R_local.device)
            feat = (R_local.index_select(1, self.pose_joints) - eye).reshape(T, -1)
            v_posed = v_posed + torch.einsum("vck,tk->tvc", self.f_posedirs, feat)
        local = v_posed[:, :, None, :] - J_rest[self.face_joints]  # (T, 5, F, 3) vertex relative to each rest joint
        moved = (torch.einsum("tjab,tvjb->tvja", R.index_select(1, self.face_slot), local)
                 + pos.index_select(1, self.face_joints)[:, None])
        face = (self.f_weights[None, :, :, None] * moved).sum(2)
        joints = pos + transl[:, None]
        face = face + transl[:, None]
        coco = torch.einsum("kj,tjc->tkc", self.coco, torch.cat([joints, face], 1))
        return joints, coco


class HeldPoseBody:
    """:class:`KeypointBody` while the body pose is held (phase 1: only betas, the root's
    orientation and the translation move), without its forward kinematics at every step.

    With the joints' local rotations fixed, the body in its root's frame is an affine function of
    the betas (rest joints, bones and face vertices are linear in them; the kinematic chain and
    the skinning are linear in those), and the world body is that rotated by the root and moved:
    ``X = J0(b) + R(global_orient) (E0 + D (b - b0)) + transl``. :meth:`rest` evaluates ``E0`` and
    ``D`` once (the full body at ``b0`` and at ``b0`` plus each unit beta, root at identity); a
    call is then one small product per frame instead of the whole chain. Equal to the keypoint
    body up to rounding (``tests/test_smplify.py``).
    """

    def __init__(self, body: KeypointBody, betas0: torch.Tensor) -> None:
        self.body, self.b0 = body, betas0.detach().clone()  # a copy: the fit steps the betas in place
        self.rows = body.coco.sum(1)[:, None]  # (17, 1) weight of the root offset in each keypoint (1 for every layout)

    def _root(self, betas: torch.Tensor) -> torch.Tensor:
        b = torch.nn.functional.pad(betas, (0, self.body.num_betas - betas.shape[-1]))
        return self.body.J_template[0] + self.body.J_dirs[0] @ b  # (3,) the root joint at rest

    @torch.no_grad()
    def rest(self, pose: torch.Tensor) -> torch.Tensor:
        """(T, 41, 3, 1 + B): the 24 joints and 17 keypoints relative to the root joint, root
        orientation identity and no translation, at ``b0`` (last axis 0) and their change per unit
        of each beta, for the held body pose (T, 69)."""
        T, B = pose.shape[0], self.b0.shape[0]
        zero = torch.zeros(T, 3, dtype=pose.dtype, device=pose.device)
        steps = torch.cat([torch.zeros(1, B, dtype=pose.dtype, device=pose.device),
                           torch.eye(B, dtype=pose.dtype, device=pose.device)]) + self.b0
        out = []
        for b in steps:
            joints, coco = self.body(b, zero, pose, zero)
            J0 = self._root(b)
            out.append(torch.cat([joints - J0, coco - self.rows * J0], 1))
        X = torch.stack(out, -1)
        return torch.cat([X[..., :1], X[..., 1:] - X[..., :1]], -1)

    def __call__(self, betas: torch.Tensor, global_orient: torch.Tensor, rest: torch.Tensor,
                 transl: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Joints (T, 24, 3) and COCO-17 keypoints (T, 17, 3) like :class:`KeypointBody`, with
        :meth:`rest` in the body pose's place."""
        local = rest[..., 0] + rest[..., 1:] @ (betas - self.b0)  # (T, 41, 3)
        R = axis_angle_to_matrix(global_orient)  # (T, 3, 3)
        moved = local @ R.transpose(-1, -2) + transl[:, None]
        J0 = self._root(betas)
        return moved[:, :24] + J0, moved[:, 24:] + self.rows * J0


# ---------------------------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Data:
    """All observations as tensors, frames on axis 0 (sliceable into windows)."""

    kp3d: torch.Tensor  # (T, 17, 3), finite (0 where missing; kp2d likewise)
    conf3d: torch.Tensor  # (T, 17)
    K: torch.Tensor  # (V, 3, 3)
    T_world_cam: torch.Tensor  # (T, V, 4, 4)
    kp2d: torch.Tensor  # (T, V, 17, 2)
    conf2d: torch.Tensor  # (T, V, 17)
    prior: torch.Tensor | None  # (T, 69)
    prior_conf: torch.Tensor | None  # (T,)
    edge: torch.Tensor | None = None  # (T, 24, 1 + V) or (T,) edge velocity weights (TM.edge_hold_weights)
    floor: torch.Tensor | None = None  # () the scene's floor height (motion.floor), None = no floor term

    def slice(self, idx: slice | torch.Tensor) -> "_Data":
        cut = lambda x: None if x is None else x[idx]  # noqa: E731
        return _Data(cut(self.kp3d), cut(self.conf3d), self.K, cut(self.T_world_cam), cut(self.kp2d),
                     cut(self.conf2d), cut(self.prior), cut(self.prior_conf), cut(self.edge), self.floor)


def _check_inputs(kp3d, kp3d_conf, views: Sequence[ViewObservations], init: SmplParams, prior, model_betas: int) -> int:
    T = len(init)
    if T == 0:
        raise ValueError("init has no frames: nothing to fit")
    if kp3d.shape != (T, 17, 3):
        raise ValueError(f"kp3d must be (T={T}, 17, 3) like init, got {kp3d.shape}")
    if kp3d_conf.shape != (T, 17):
        raise ValueError(f"kp3d_conf must be (T={T}, 17), got {kp3d_conf.shape}")
    for i, v in enumerate(views):
        name = v.name or f"view{i}"
        if np.shape(v.K) != (3, 3):
            raise ValueError(f"view {name}: K must be (3, 3), got {np.shape(v.K)}")
        if np.shape(v.T_world_cam) != (T, 4, 4):
            raise ValueError(f"view {name}: T_world_cam must be (T={T}, 4, 4), got {np.shape(v.T_world_cam)}")
        if np.shape(v.keypoints) != (T, 17, 3):
            raise ValueError(f"view {name}: keypoints must be (T={T}, 17, 3) pixels + confidence, got {np.shape(v.keypoints)}")
        if not np.all(np.isfinite(v.K)) or not np.all(np.isfinite(v.T_world_cam)):
            raise ValueError(f"view {name}: K and T_world_cam must be finite")
    if init.betas.shape[0] > model_betas:
        raise ValueError(f"init has {init.betas.shape[0]} betas, the body model {model_betas}")
    if prior is not None and np.shape(prior) != (T, 69):
        raise ValueError(f"prior_body_pose must be (T={T}, 69), got {np.shape(prior)}")
    for name in ("global_orient", "body_pose", "transl", "betas"):
        if not np.all(np.isfinite(getattr(init, name))):
            raise ValueError(f"init.{name} has non-finite values")
    return T


def _to_data(kp3d, kp3d_conf, views, prior, cfg: SmplifyConfig, dtype, device, valid=None) -> _Data:
    tt = lambda x: torch.as_tensor(np.array(x, dtype=np.float64), dtype=dtype, device=device)  # noqa: E731
    T = len(kp3d)
    conf3 = np.where(np.isfinite(kp3d).all(-1) & (np.nan_to_num(kp3d_conf) >= cfg.min_conf), kp3d_conf, 0.0)
    V = len(views)
    if V:
        K = np.stack([v.K for v in views])
        Twc = np.stack([v.T_world_cam for v in views], 1)
        kp = np.stack([np.asarray(v.keypoints, dtype=np.float64) for v in views], 1)  # (T, V, 17, 3)
    else:
        K, Twc, kp = np.zeros((0, 3, 3)), np.zeros((T, 0, 4, 4)), np.zeros((T, 0, 17, 3))
    c2 = np.nan_to_num(kp[..., 2])
    c2 = np.where(np.isfinite(kp[..., :2]).all(-1) & (c2 >= cfg.min_conf), c2, 0.0)
    prior_t = prior_c = None
    if prior is not None:
        prior = np.asarray(prior, dtype=np.float64)
        ok = np.isfinite(prior).all(-1) & (np.abs(np.nan_to_num(prior)).sum(-1) > 0)  # all-zero row = missing
        prior_t, prior_c = tt(np.where(ok[:, None], np.nan_to_num(prior), 0.0)), tt(ok.astype(np.float64))
    on = cfg.w_edge_vel > 0 and cfg.edge_frames > 0  # edge weights per frame (and joint), sliced with the windows
    edge = TM.edge_weights(np.ones(T, dtype=bool) if valid is None else valid, cfg.edge_frames)
    edge = tt(TM.edge_hold_weights(edge, c2 > 0, cfg.edge_hold)) if on else None
    # Targets finite (0 where missing, their confidence 0): the terms need not clean them at every step.
    fin = lambda x: np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)  # noqa: E731
    return _Data(tt(fin(kp3d)), tt(conf3), tt(K), tt(Twc), tt(fin(kp[..., :2])), tt(c2), prior_t, prior_c, edge)


def smooth_motion(go: NDArray, pose: NDArray, transl: NDArray, sigma: float,
                  valid: NDArray | None = None) -> tuple[NDArray, NDArray, NDArray]:
    """Per-frame SMPL rotations (T, 3) ``go``, (T, 69) ``pose`` and translations (T, 3) smoothed
    through time by a Gaussian of ``sigma`` frames (rotations as quaternions,
    :func:`~embodmocap.geometry.rotations.smooth_rotvecs`), each run of ``valid`` (T,) frames on
    its own (an unplaced frame's body is a guess that must not leak into its placed neighbours;
    the unplaced frames themselves are left as given). ``valid`` None = one run."""
    go, pose, transl = (np.array(x, dtype=np.float64) for x in (go, pose, transl))
    T = len(go)
    ok = np.ones(T, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2]):  # runs [a, b) of valid frames
        go[a:b] = smooth_rotvecs(go[a:b], sigma)
        pose[a:b] = smooth_rotvecs(pose[a:b].reshape(b - a, 23, 3), sigma).reshape(b - a, 69)
        transl[a:b] = gaussian_filter1d(transl[a:b], sigma, axis=0, mode="nearest")
    return go, pose, transl


# ---------------------------------------------------------------------------------------------
# Objective
# ---------------------------------------------------------------------------------------------


@dataclass
class _State:
    """Parameters of one window (leaf tensors)."""

    betas: torch.Tensor  # (B,)
    go: torch.Tensor  # (W, 3)
    pose: torch.Tensor  # (W, 69)
    transl: torch.Tensor  # (W, 3)


def _terms(body: KeypointBody, s: _State, d: _Data, cfg: SmplifyConfig, phase: float, names: list[str],
           smooth: bool = True, gnc: float = 1.0, w3d: float | None = None) -> dict[str, torch.Tensor]:
    """Weighted terms of ``phase`` for the state ``s`` on data ``d``: 1 (3D keypoints, smoothness,
    shape), 1.25 (the same on the trunk's keypoints only), 1.5 (1 + joint limits and ranges), 2 (all).
    ``gnc`` >= 1 widens the robust scales of the keypoint terms by that factor (terms times its
    square: the same weight for small residuals, more pull from far ones). ``w3d`` replaces
    ``cfg.w_kp3d`` (its schedule)."""
    joints, coco = body(s.betas, s.go, s.pose, s.transl)
    conf3d = d.conf3d
    if phase == 1.25:  # global and torso stages: the limbs, still at their start, must not tilt the trunk
        conf3d = conf3d * torch.as_tensor(_TRUNK_KEYPOINTS, dtype=conf3d.dtype, device=conf3d.device)
    out = {"kp3d": (cfg.w_kp3d if w3d is None else w3d) * gnc ** 2 * TM.kp3d_term(coco, d.kp3d, conf3d, cfg.kp3d_kernel, gnc * cfg.kp3d_scale_m, clean=False)}
    if smooth:
        out["joint_vel"] = cfg.w_joint_vel * TM.velocity_term(joints)
        out["joint_acc"] = cfg.w_joint_acc * TM.acceleration_term(joints)
        out["transl_vel"] = cfg.w_transl_vel * TM.velocity_term(s.transl)
        out["transl_acc"] = cfg.w_transl_acc * TM.acceleration_term(s.transl)
        if d.edge is not None:
            out["edge_vel"] = cfg.w_edge_vel * TM.edge_velocity_term(joints, d.edge, d.T_world_cam[..., :3, 3])
    out["shape_prior"] = cfg.w_shape_prior * TM.shape_prior_term(s.betas)
    if d.floor is not None and cfg.w_floor > 0:
        out["floor"] = cfg.w_floor * floor_term(joints, d.floor)
    if phase <= 1.25:
        return out
    if phase == 1.5:  # torso and limbs stages: the pose moves, the 2D terms wait for phase 2
        out["joint_limits"] = cfg.w_joint_limits * TM.joint_limits_term(s.pose)
        out["joint_range"] = cfg.w_joint_range * TM.joint_range_term(s.pose)
        return out
    if names:  # one projection into every view, one term per view
        per_view = TM.reproj_view_terms(coco, d.K, d.T_world_cam, d.kp2d, d.conf2d, cfg.reproj_kernel,
                                        gnc * cfg.reproj_scale_px, clean=False)
        for v, name in enumerate(names):
            out[f"reproj/{name}"] = cfg.w_reproj * gnc ** 2 * per_view[v]
    if d.prior is not None:
        out["pose_prior"] = cfg.w_pose_prior * TM.pose_prior_term(s.pose, d.prior, d.prior_conf)
    elif cfg.w_rest_pose > 0:
        joints = UNPINNED_JOINTS + ((7, 8) if cfg.rest_pose_ankles else ())
        idx = [3 * (j - 1) + a for j in joints for a in range(3)]
        out["rest_pose"] = cfg.w_rest_pose * (s.pose[:, idx] ** 2).sum(-1).mean()
    out["joint_limits"] = cfg.w_joint_limits * TM.joint_limits_term(s.pose)
    out["joint_range"] = cfg.w_joint_range * TM.joint_range_term(s.pose)
    return out


def _optimise(params: list[torch.Tensor], lrs: list[float], loss_fn: Callable[[], torch.Tensor], iterations: int,
              cfg: SmplifyConfig, on_step: Callable[[int], None] | None = None) -> None:
    """Minimise ``loss_fn`` over ``params`` in place (Adam with cosine decay, or L-BFGS).
    ``on_step(it)`` is called before each Adam step (schedules that change the loss)."""
    if iterations <= 0 or not params:
        return
    if cfg.solver == "lbfgs":
        opt = torch.optim.LBFGS(params, lr=1.0, max_iter=iterations, history_size=20, line_search_fn="strong_wolfe",
                                tolerance_grad=1e-12, tolerance_change=1e-14)

        def closure() -> torch.Tensor:
            opt.zero_grad()
            loss = loss_fn()
            loss.backward()
            return loss

        opt.step(closure)
        return
    opt = _Adam(params)
    for it in progress(range(iterations), "SMPL fit pass", unit="step"):
        if on_step is not None:
            on_step(it)
        for p in params:
            p.grad = None
        loss_fn().backward()
        opt.step(_cosine_lrs(lrs, it, iterations, cfg))


def _cosine_lrs(lrs: list[float], it: int, iterations: int, cfg: SmplifyConfig) -> list[float]:
    """Each parameter's learning rate at step ``it`` of ``iterations``: cosine decay from ``lrs`` to
    ``cfg.lr_final_ratio`` of them."""
    frac = 0.5 * (1.0 + math.cos(math.pi * it / max(iterations - 1, 1)))
    return [lr * (cfg.lr_final_ratio + (1.0 - cfg.lr_final_ratio) * frac) for lr in lrs]


#: Steps over which phase 2's early stop measures a window's progress (SmplifyConfig.phase2_stop_tol).
STOP_SPAN = 10


def _optimise_windows(params: list[torch.Tensor], lrs: list[float],
                      loss_fn: Callable[[list[torch.Tensor], torch.Tensor | None], torch.Tensor], iterations: int,
                      cfg: SmplifyConfig, on_step: Callable[[int], None], fixed_from: int) -> list[int]:
    """Adam with cosine decay like :func:`_optimise`, each window stopped on its own progress;
    returns the steps each window took.

    ``params`` hold the windows on axis 0 (or are one window's, betas included: then it only
    stops); ``loss_fn(cur, rows)`` gives the (k,) losses of the windows ``rows`` (None = all) for
    their parameters ``cur``. From step ``fixed_from + STOP_SPAN`` (the objective no longer
    changes: the 3D weight and the robust scales have reached their set values) a window whose
    loss fell by less than ``cfg.phase2_stop_tol`` of itself over the last ``STOP_SPAN`` steps
    keeps its parameters and leaves the batch. A window's steps and its stop depend on its own
    loss only (Adam is elementwise, the losses are per window), so the answer does not depend on
    how the windows are grouped into batches or processes.
    """
    cur, rows, steps = list(params), None, None
    opt = _Adam(cur)
    hist: list[torch.Tensor] = []
    for it in progress(range(iterations), "SMPL fit pass", unit="step"):
        on_step(it)
        for p in cur:
            p.grad = None
        losses = loss_fn(cur, rows)
        losses.sum().backward()
        opt.step(_cosine_lrs(lrs, it, iterations, cfg))
        if steps is None:
            steps = [iterations] * len(losses)
        hist = (hist + [losses.detach()])[-(STOP_SPAN + 1):]
        if it < fixed_from + STOP_SPAN or it == iterations - 1:
            continue
        done = hist[0] - hist[-1] < cfg.phase2_stop_tol * hist[-1].abs()
        if not bool(done.any()):
            continue
        idx = torch.arange(len(done), device=done.device) if rows is None else rows
        for k in idx[done].tolist():
            steps[k] = it + 1
        if bool(done.all()):
            break
        keep = ~done
        with torch.no_grad():  # the stopped windows' results into the full tensors
            for full, c in zip(params, cur):
                full[idx[done]] = c[done]
        rows = idx[keep]
        cur = [c.detach()[keep].clone().requires_grad_(True) for c in cur]
        opt.params, opt.m, opt.v = cur, [m[keep] for m in opt.m], [v[keep] for v in opt.v]
        hist = [h[keep] for h in hist]
    if rows is not None:
        with torch.no_grad():
            for full, c in zip(params, cur):
                full[rows] = c
    return steps or []


class _Adam:
    """Adam (default betas 0.9 / 0.999, eps 1e-8, no weight decay) with one learning rate per
    parameter given at each step: the arithmetic of ``torch.optim.Adam``'s single-tensor path op for
    op (the same steps to the bit), without its per-step bookkeeping and without the import of
    ``torch._dynamo`` that its constructor triggers (about 3 CPU s per process)."""

    def __init__(self, params: list[torch.Tensor], betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8) -> None:
        self.params, (self.b1, self.b2), self.eps, self.t = params, betas, eps, 0
        self.m = [torch.zeros_like(p) for p in params]
        self.v = [torch.zeros_like(p) for p in params]

    @torch.no_grad()
    def step(self, lrs: list[float]) -> None:
        self.t += 1
        bc1, bc2_sqrt = 1.0 - self.b1 ** float(self.t), (1.0 - self.b2 ** float(self.t)) ** 0.5
        for p, m, v, lr in zip(self.params, self.m, self.v, lrs):
            if p.grad is None:
                continue
            m.lerp_(p.grad, 1.0 - self.b1)
            v.mul_(self.b2).addcmul_(p.grad, p.grad, value=1.0 - self.b2)
            p.addcdiv_(m, (v.sqrt() / bc2_sqrt).add_(self.eps), value=-lr / bc1)


def _fit_window(body: KeypointBody, d: _Data, init: _State, cfg: SmplifyConfig, names: list[str], free_betas: bool,
                smooth: bool, timing: dict[str, float], label: str = "", batched: bool = False) -> _State:
    """Both phases on one window; returns the fitted (detached) state.

    ``batched``: ``init`` and ``d`` hold n equal windows on a leading axis ((n, W, ...) per-frame
    fields; betas and K shared, betas fixed). Each window's loss is its own (``torch.func.vmap``)
    and Adam is elementwise, so every window follows the steps it would alone (up to the order of
    floating-point sums); one autograd graph per step for all of them instead of one per window
    (the keypoint body's small tensors make the fit cost per graph, not per frame)."""
    s = _State(*(x.detach().clone().requires_grad_(True) for x in (init.betas, init.go, init.pose, init.transl)))
    if not free_betas:
        s.betas.requires_grad_(False)
    gnc = {"k": 1.0, "w3d": cfg.w_kp3d_start if cfg.w_kp3d > 0 else 0.0}  # w_kp3d = 0: no 3D term at all
    # total(phase): the loss of the state s; with ``bd`` (HeldPoseBody) its ``rest`` in the pose's
    # place (phase 1: the terms there do not read the pose itself).
    def total(phase, bd=body, pose=None):
        return lambda: sum(_terms(bd, _State(s.betas, s.go, s.pose if pose is None else pose, s.transl), d, cfg,
                                  phase, names, smooth, gnc["k"], gnc["w3d"]).values())

    # window_losses(phase): (params in phase 2's order, rows of the windows still fitted or None for
    # all) -> (k,) each window's own loss (phase 2's early stop, _optimise_windows).
    def window_losses(phase):
        f = total(phase)
        return lambda cur, rows: f().reshape(1)  # one window: never split

    if batched:  # (n, W, ...) windows: one loss per window through vmap, summed (gradients stay per window)
        fields = (d.kp3d, d.conf3d, d.K, d.T_world_cam, d.kp2d, d.conf2d, d.prior, d.prior_conf, d.edge, d.floor)
        dims = tuple(None if x is None or x is d.K or x is d.floor else 0 for x in fields)

        def per_window(phase, bd=body):
            def one(go, pose, transl, *dd):
                return sum(_terms(bd, _State(s.betas, go, pose, transl), _Data(*dd), cfg, phase, names, smooth,
                                  gnc["k"], gnc["w3d"]).values())
            return torch.func.vmap(one, in_dims=(0, 0, 0) + dims)

        def total(phase, bd=body, pose=None):
            vm = per_window(phase, bd)
            return lambda: vm(s.go, s.pose if pose is None else pose, s.transl, *fields).sum()

        def window_losses(phase):
            vm, cut = per_window(phase), {}

            def f(cur, rows):  # cur: go, transl, pose of the windows ``rows`` (None: all)
                key = None if rows is None else tuple(rows.tolist())
                if key not in cut:  # the data of the windows still fitted, sliced once per change
                    cut.clear()
                    cut[key] = fields if rows is None else tuple(x if dm is None else x[rows] for x, dm in zip(fields, dims))
                return vm(cur[0], cur[2], cur[1], *cut[key])
            return f
    t0 = time.perf_counter()
    p1 = ([s.betas] if free_betas else []) + [s.go, s.transl]
    lr1 = ([cfg.phase1_lr * cfg.betas_lr_scale] if free_betas else []) + [cfg.phase1_lr] * 2
    if cfg.phase1_iterations > 0:  # the pose is held: the body's pose-dependent part once (HeldPoseBody)
        held = HeldPoseBody(body, s.betas)
        rest = held.rest(s.pose.detach().reshape(-1, s.pose.shape[-1]))
        _optimise(p1, lr1, total(1.25, held, rest.reshape(s.pose.shape[:-1] + rest.shape[1:])),
                  cfg.phase1_iterations, cfg)
    # Torso, then limbs: the pose is free only on those joints (zeroed gradients elsewhere: with a
    # fresh Adam per stage, a zero gradient moves nothing).
    for joints, iters, phase in ((TORSO_JOINTS, cfg.torso_iterations, 1.25), (LIMB_JOINTS, cfg.limbs_iterations, 1.5)):
        if iters <= 0:
            continue
        mask = torch.zeros(23, 3, dtype=s.pose.dtype, device=s.pose.device)
        mask[[j - 1 for j in joints]] = 1.0
        hook = s.pose.register_hook(lambda g, m=mask.reshape(69): g * m)
        _optimise(p1 + [s.pose], lr1 + [cfg.stage_pose_lr], total(phase), iters, cfg)
        hook.remove()
    t1 = time.perf_counter()
    p2 = p1 + [s.pose]
    lr2 = ([cfg.phase2_lr * cfg.betas_lr_scale] if free_betas else []) + [cfg.phase2_lr] * 3
    n_gnc = max(int(cfg.gnc_fraction * cfg.phase2_iterations), 1)

    def schedule(it: int) -> None:  # geometric shrink from gnc_factor to 1, w_kp3d_start to w_kp3d
        left = max(1.0 - it / n_gnc, 0.0)
        gnc["k"] = cfg.gnc_factor ** left if cfg.gnc_factor > 1 else 1.0
        gnc["w3d"] = cfg.w_kp3d * (cfg.w_kp3d_start / cfg.w_kp3d) ** left if cfg.w_kp3d > 0 else 0.0

    if cfg.solver == "adam" and cfg.phase2_stop_tol > 0:
        steps = _optimise_windows(p2, lr2, window_losses(2), cfg.phase2_iterations, cfg, schedule, n_gnc)
        log.debug("smplify %sphase 2: steps per window %s of %d", label, steps, cfg.phase2_iterations)
    else:
        _optimise(p2, lr2, total(2), cfg.phase2_iterations, cfg, on_step=schedule)
    gnc["k"], gnc["w3d"] = 1.0, cfg.w_kp3d
    t2 = time.perf_counter()
    timing[f"{label}phase1"] = timing.get(f"{label}phase1", 0.0) + t1 - t0
    timing[f"{label}phase2"] = timing.get(f"{label}phase2", 0.0) + t2 - t1
    return _State(*(x.detach() for x in (s.betas, s.go, s.pose, s.transl)))


# ---------------------------------------------------------------------------------------------
# Entry point
# ---------------------------------------------------------------------------------------------


def _device(cfg: SmplifyConfig) -> torch.device:
    """The fit's device; ``cuda`` without a CUDA device is one clear :class:`InputError`."""
    from embodmocap.device import resolve_device

    return torch.device(resolve_device(cfg.device))


def _check_config(cfg: SmplifyConfig) -> torch.dtype:
    if cfg.solver not in ("adam", "lbfgs"):
        raise ValueError(f"unknown solver {cfg.solver!r}: use adam or lbfgs")
    if cfg.dtype not in ("float32", "float64"):
        raise ValueError(f"dtype must be float32 or float64, got {cfg.dtype!r}")
    window_ranges(cfg.window_frames + 1, cfg.window_frames, cfg.overlap_frames)  # validates the pair
    return torch.float64 if cfg.dtype == "float64" else torch.float32


def _fit_windows(model: BodyModel, body: KeypointBody, data: _Data, start: _State, ranges: list[tuple[int, int]],
                 cfg: SmplifyConfig, names: list[str], timing: dict[str, float]) -> tuple[NDArray, ...]:
    """Betas on a subsample of the whole sequence, then each window with them fixed, blended.

    Returns (T, 3) global_orient, (T, 69) body_pose, (T, 3) transl and (B,) betas.
    """
    T = ranges[-1][1]
    t0 = time.perf_counter()
    # The other processes start now and import the fit while this one fits the shape (fit_workers:
    # fresh interpreters, never forks). Contiguous groups of windows, one batch per process: the same
    # answer whatever the number of processes, the windows being independent.
    # At most one process per usable core: on one core a second process only adds its imports.
    # `embodmocap run` lends the fit its idle second worker's core when nothing else is left to run
    # (parallel.lent_cores): the windows then take two processes whatever cfg.workers says.
    n_proc = max(min(cores_to_use(cfg.workers) if start.go.device.type == "cpu" else 1, len(ranges)), 1)
    with start_workers(n_proc - 1, (__name__,), cfg.threads) as pool:
        sub = np.unique(np.round(np.linspace(0, T - 1, min(cfg.shape_frames, T))).astype(np.int64))
        sub = torch.as_tensor(sub, device=start.go.device)
        sub_init = _State(start.betas, start.go[sub], start.pose[sub], start.transl[sub])
        shape = _fit_window(body, data.slice(sub), sub_init, cfg, names, free_betas=True, smooth=False,
                            timing=timing, label="shape_")
        timing["shape"] = time.perf_counter() - t0
        # Keep the init's pelvis where it was when the betas change: transl pivots on J0(betas).
        b0, b1 = start.betas.cpu().numpy(), shape.betas.cpu().numpy()
        shift = torch.as_tensor(model.pelvis_offset(b0) - model.pelvis_offset(b1), dtype=start.transl.dtype,
                                device=start.transl.device)
        # All windows have the same length (window_ranges): fitted together, one batch per process, then blended.
        idx = torch.as_tensor(np.stack([np.arange(s, e) for s, e in ranges]), device=start.go.device)  # (n, W)
        transl0 = start.transl[idx] + shift
        groups = np.array_split(np.arange(len(ranges)), n_proc)
        jobs = []
        for g in groups:
            i = idx[torch.as_tensor(g, device=idx.device)]
            jobs.append((body, data.slice(i), _State(shape.betas, start.go[i], start.pose[i], transl0[g]), cfg, names))
        parts = run_pieces(_fit_group, jobs, pool)
    for *_, t in parts:  # phase times summed over the windows of every process
        for k, v in t.items():
            timing[k] = timing.get(k, 0.0) + v
    go_w, pose_w, transl_w = (torch.as_tensor(np.concatenate(x)) for x in list(zip(*parts))[:3])
    states = [_State(shape.betas, go_w[k], pose_w[k], transl_w[k]) for k in range(len(ranges))]
    log.debug("smplify: %d windows of %d frames fitted in %d batch(es)", len(ranges), idx.shape[1], len(groups))
    go, pose, transl = _blend(ranges, states, T, cfg.overlap_frames)
    return go, pose, transl, b1


def _fit_group(body: KeypointBody, d: _Data, init: _State, cfg: SmplifyConfig,
               names: list[str]) -> tuple[NDArray, NDArray, NDArray, dict[str, float]]:
    """One process's batch of windows (betas fixed): fitted (n, W, 3) global_orient, (n, W, 69)
    body_pose, (n, W, 3) transl as numpy, and the phase times (a worker's job: module level, so it
    pickles by name)."""
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)  # a worker process: the parent's setting
    timing: dict[str, float] = {}
    f = _fit_window(body, d, init, cfg, names, free_betas=False, smooth=True, timing=timing, batched=True)
    return tuple(x.cpu().numpy() for x in (f.go, f.pose, f.transl)) + (timing,)


def fit_world_smpl(
    model: BodyModel,
    kp3d: NDArray,
    kp3d_conf: NDArray,
    views: Sequence[ViewObservations],
    init: SmplParams,
    prior_body_pose: NDArray | None = None,
    cfg: SmplifyConfig = SmplifyConfig(),
    layout: str = "COCO17",
    prior_weight: NDArray | None = None,
    valid: NDArray | None = None,
    floor_z: float | None = None,
) -> SmplifyResult:
    """Fit world-space SMPL motion to 3D and 2D keypoints with the cameras fixed.

    Args:
        model: the body model.
        kp3d: (T, 17, 3) triangulated COCO-17 keypoints in the world, metres (NaN = missing).
        kp3d_conf: (T, 17) their confidences.
        views: per-view cameras and 2D keypoints (may be empty: 3D term only).
        init: starting parameters, T frames (see :mod:`embodmocap.motion.init`).
        prior_body_pose: (T, 69) body pose to stay near (e.g. the regressor's), all-zero rows =
            missing; None = no pose prior.
        cfg: weights, schedules, windows, device.
        layout: the keypoint layout (its hip definition, :func:`embodmocap.body.joints.coco17_matrix`).
        prior_weight: (T,) per-frame weight of the pose prior (e.g. 0 where the prior disagrees
            with the triangulation); None = 1 wherever the prior has a row.
        valid: (T,) bool placeable frames: ``cfg.w_edge_vel`` also covers the frames next to
            unplaceable ones, not only the sequence's ends; None = every frame placeable.
        floor_z: the scene's floor height, world metres (:mod:`embodmocap.motion.floor`: no foot
            joint below it, ``cfg.w_floor``); None = no floor term.

    Returns:
        :class:`SmplifyResult`. Raises ValueError on inconsistent shapes or settings.
    """
    threads = torch.get_num_threads()
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    try:
        return _fit_world_smpl(model, kp3d, kp3d_conf, views, init, prior_body_pose, cfg, layout, prior_weight, valid,
                               floor_z)
    finally:
        torch.set_num_threads(threads)


def _fit_world_smpl(model, kp3d, kp3d_conf, views, init, prior_body_pose, cfg, layout, prior_weight, valid,
                    floor_z=None) -> SmplifyResult:
    t_start = time.perf_counter()
    kp3d, kp3d_conf = np.asarray(kp3d, dtype=np.float64), np.asarray(kp3d_conf, dtype=np.float64)
    T = _check_inputs(kp3d, kp3d_conf, views, init, prior_body_pose, model.num_betas)
    dtype, device = _check_config(cfg), _device(cfg)
    names = [v.name or f"view{i}" for i, v in enumerate(views)]
    body = KeypointBody(model, dtype, device, layout)
    if not body.has_face:
        log.warning("the body model has no face vertex ids: fitting without the nose, eyes and ears")
        kp3d_conf = kp3d_conf.copy()
        kp3d_conf[:, :5] = 0.0
        views = [ViewObservations(v.K, v.T_world_cam, np.concatenate(
            [np.zeros_like(np.asarray(v.keypoints)[:, :5]), np.asarray(v.keypoints)[:, 5:]], 1), v.name) for v in views]
    data = _to_data(kp3d, kp3d_conf, views, prior_body_pose, cfg, dtype, device, valid)
    if prior_weight is not None and data.prior_conf is not None:
        data = _Data(data.kp3d, data.conf3d, data.K, data.T_world_cam, data.kp2d, data.conf2d, data.prior,
                     data.prior_conf * torch.as_tensor(np.asarray(prior_weight, dtype=np.float64), dtype=dtype, device=device),
                     data.edge)
    if floor_z is not None:
        data = replace(data, floor=torch.as_tensor(float(floor_z), dtype=dtype, device=device))
    tt = lambda x: torch.as_tensor(np.array(x, dtype=np.float64), dtype=dtype, device=device)  # noqa: E731
    if cfg.init_smooth_frames > 0:  # a jittery start slows Adam under the smoothness terms (see the setting)
        go, pose, transl = smooth_motion(init.global_orient, init.body_pose, init.transl, cfg.init_smooth_frames, valid)
        init = replace(init, global_orient=go, body_pose=pose, transl=transl)
    start = _State(tt(init.betas), tt(init.global_orient), tt(init.body_pose), tt(init.transl))

    timing: dict[str, float] = {}
    ranges = window_ranges(T, cfg.window_frames, cfg.overlap_frames)
    if len(ranges) == 1:
        fitted = _fit_window(body, data, start, cfg, names, free_betas=True, smooth=True, timing=timing)
        go, pose, transl, betas = (x.cpu().numpy() for x in (fitted.go, fitted.pose, fitted.transl, fitted.betas))
    else:
        go, pose, transl, betas = _fit_windows(model, body, data, start, ranges, cfg, names, timing)

    # float64 out whatever the fit's dtype: the files and the stages after the fit are float64.
    go, pose, transl, betas = (np.asarray(x, dtype=np.float64) for x in (go, pose, transl, betas))
    if cfg.output_smooth_frames > 0:
        go, pose, transl = smooth_motion(go, pose, transl, cfg.output_smooth_frames, valid)
    params = SmplParams(betas=betas, global_orient=go, body_pose=pose, transl=transl, fps=init.fps, gender=init.gender)
    before = _evaluate(body, start, data, cfg, names)
    after_state = _State(tt(betas), tt(go), tt(pose), tt(transl))
    after = _evaluate(body, after_state, data, cfg, names)
    reproj = _median_reprojection(body, after_state, data, names)
    seconds = time.perf_counter() - t_start
    log.info("smplify: %d frames, %d window(s), loss %.4g -> %.4g in %.1f s", T, len(ranges),
             sum(before.values()), sum(after.values()), seconds)
    return SmplifyResult(params, before, after, reproj, seconds, {k: round(v, 3) for k, v in timing.items()}, tuple(ranges))


def _evaluate(body: KeypointBody, s: _State, d: _Data, cfg: SmplifyConfig, names: list[str]) -> dict[str, float]:
    with torch.no_grad():
        return {k: float(v) for k, v in _terms(body, s, d, cfg, 2, names).items()}


def _median_reprojection(body: KeypointBody, s: _State, d: _Data, names: list[str]) -> dict[str, float]:
    with torch.no_grad():
        _, coco = body(s.betas, s.go, s.pose, s.transl)
        uv, z = TM.project(coco, d.K, d.T_world_cam)
        err = torch.linalg.norm(uv - d.kp2d, dim=-1)  # (T, V, 17)
    out = {}
    for v, name in enumerate(names):
        e = err[:, v][(d.conf2d[:, v] > 0) & (z[:, v] > 0)]
        out[name] = float(e.median()) if e.numel() else float("nan")
    return out
