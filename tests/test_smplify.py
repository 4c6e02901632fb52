"""World-space SMPLify: terms (gradients, known answers), initialisation, fits against the truth."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from embodmocap.body.model import load_body_model
from embodmocap.geometry.transforms import invert_T, look_at_T
from embodmocap.io.body_prior import BodyPriorSeq
from embodmocap.motion import terms as TM
from embodmocap.motion.init import init_from_keypoints, init_from_prior
from embodmocap.motion.smplify import (
    HeldPoseBody, KeypointBody, SmplifyConfig, ViewObservations, _blend_weights, fit_world_smpl, window_ranges,
)
from embodmocap.synth.motion import script_motion
from embodmocap.synth.scene import build_scene
from embodmocap.types import SmplParams

FPS = 30.0
BETAS = np.array([0.5, -0.3, 0.2, 0.0, 0.1, 0, 0, 0, 0, 0])
#: SMPL joints that COCO-17 observes directly (hips, knees, ankles, shoulders, elbows, wrists).
#: The spine chain, collars, feet and hands can move without moving any COCO keypoint, so no
#: keypoint fit can recover them; errors are measured on these.
LIMB_JOINTS = [1, 2, 4, 5, 7, 8, 16, 17, 18, 19, 20, 21]


@pytest.fixture(scope="module")
def body():
    return load_body_model(None)


@pytest.fixture(scope="module")
def motion(body):
    """4 s of scripted walking/turning in a generated room, with its joints and COCO-17."""
    spec = build_scene("indoor", np.random.default_rng(0)).spec
    params = script_motion(spec, body, BETAS, 4.0, FPS, np.random.default_rng(0)).params
    out = body.from_params(params, dtype=torch.float64)
    return params, out.joints.numpy(), out.coco17.numpy()


K = np.array([[700.0, 0.0, 360.0], [0.0, 700.0, 480.0], [0.0, 0.0, 1.0]])


def _cameras(centre: np.ndarray, T: int) -> dict[str, np.ndarray]:
    """Two views' (T, 4, 4) cameras 4 m from ``centre``, looking at it; v2 slowly orbits."""
    out = {}
    for name, a0, rate in (("v1", 0.3, 0.0), ("v2", 1.9, 0.004)):
        ang = a0 + rate * np.arange(T)
        out[name] = np.stack([look_at_T(centre + [4 * np.cos(a), 4 * np.sin(a), 0.3], centre) for a in ang])
    return out


def _views(coco: np.ndarray, noise_px: float = 0.0, seed: int = 1) -> list[ViewObservations]:
    """Two views whose keypoints are the exact projections of ``coco`` (+ Gaussian pixel noise)."""
    rng = np.random.default_rng(seed)
    T = len(coco)
    views = []
    for name, cams in _cameras(coco.reshape(-1, 3).mean(0), T).items():
        Tcw = invert_T(cams)
        p = np.einsum("tij,tkj->tki", Tcw[:, :3, :3], coco) + Tcw[:, None, :3, 3]
        uv = p @ K.T
        uv = uv[..., :2] / uv[..., 2:] + rng.normal(size=(T, 17, 2)) * noise_px
        views.append(ViewObservations(K, cams, np.concatenate([uv, np.ones((T, 17, 1))], -1), name))
    return views


def _perturbed(params: SmplParams, seed: int = 2) -> SmplParams:
    rng = np.random.default_rng(seed)
    T = len(params)
    return SmplParams(
        betas=params.betas + rng.normal(size=10) * 0.5,
        global_orient=params.global_orient + rng.normal(size=(T, 3)) * 0.1,
        body_pose=params.body_pose + rng.normal(size=(T, 69)) * 0.1,
        transl=params.transl + rng.normal(size=3) * 0.1 + rng.normal(size=(T, 3)) * 0.02,
        fps=params.fps,
    )


def _joints(body, params: SmplParams) -> tuple[np.ndarray, np.ndarray]:
    out = body.from_params(params, dtype=torch.float64)
    return out.joints.numpy(), out.coco17.numpy()


def _mpjpe(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b, axis=-1).mean())


# ------------------------------------------------------------------------------- keypoint body


def test_keypoint_body_equals_the_body_model(body):
    rng = np.random.default_rng(0)
    T = 7
    b, go, pose, tr = rng.normal(size=10), rng.normal(size=(T, 3)), 0.4 * rng.normal(size=(T, 69)), rng.normal(size=(T, 3))
    pose[0] = 0.0  # the zero pose is a singular point of naive Rodrigues
    ref = body.forward(b, go, pose, tr, dtype=torch.float64)
    t = lambda x: torch.as_tensor(x)  # noqa: E731
    joints, coco = KeypointBody(body)(t(b), t(go), t(pose), t(tr))
    assert torch.allclose(joints, ref.joints, atol=1e-7)
    assert torch.allclose(coco, ref.coco17, atol=1e-7)



def test_held_pose_body_equals_the_body_model_for_any_betas_root_and_translation(body):
    """Phase 1's body (pose held, its pose-dependent part evaluated once at other betas) gives the
    body model's joints and keypoints at new betas, root orientations and translations."""
    rng = np.random.default_rng(1)
    T = 6
    b0, pose = rng.normal(size=10), 0.4 * rng.normal(size=(T, 69))
    t = lambda x: torch.as_tensor(x)  # noqa: E731
    betas = t(b0.copy())
    held = HeldPoseBody(KeypointBody(body), betas)
    rest = held.rest(t(pose))
    for _ in range(3):
        betas += t(rng.normal(size=10))  # in place, as the fit's optimiser steps them
        go, tr = rng.normal(size=(T, 3)), rng.normal(size=(T, 3))
        ref = body.forward(betas.numpy(), go, pose, tr, dtype=torch.float64)
        joints, coco = held(betas, t(go), rest, t(tr))
        assert torch.allclose(joints, ref.joints, atol=1e-7)
        assert torch.allclose(coco, ref.coco17, atol=1e-7)


# ------------------------------------------------------------------------------- terms


def _gradcheck(fn, *inputs) -> None:
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_gradients_of_every_term_match_finite_differences():
    g = torch.Generator().manual_seed(0)
    r = lambda *s: torch.randn(*s, generator=g, dtype=torch.float64)  # noqa: E731
    T, J, V = 4, 5, 2
    pred = r(T, J, 3).requires_grad_()
    # Residuals of a few cm either side of the robust scale, so every kernel branch is used.
    target, conf = pred.detach() + r(T, J, 3) * 0.05, torch.rand(T, J, generator=g, dtype=torch.float64)
    for kind in ("l2", "huber", "geman_mcclure"):
        _gradcheck(lambda p: TM.kp3d_term(p, target, conf, kind, 0.05), pred)
    # Reprojection: points about 3 m in front of cameras that look along +y of the world.
    cams = torch.as_tensor(np.stack([look_at_T(np.array([x, -3.0, 0.0]), np.array([0.0, 0.0, 0.0])) for x in (0.0, 1.0)]))
    Twc = cams[None].expand(T, V, 4, 4)
    Kt = torch.as_tensor(K)[None].expand(V, 3, 3)
    pts = (r(T, J, 3) * 0.3).requires_grad_()
    kp2d = r(T, V, J, 2) * 30 + 400
    conf2 = torch.rand(T, V, J, generator=g, dtype=torch.float64)
    for kind in ("huber", "geman_mcclure"):
        _gradcheck(lambda p: TM.reproj_term(p, Kt, Twc, kp2d, conf2, kind, 20.0), pts)
    x = r(6, 3, 3).requires_grad_()
    _gradcheck(TM.velocity_term, x)
    _gradcheck(TM.acceleration_term, x)
    pose = (r(T, 69) * 0.5).requires_grad_()
    prior, prior_conf = r(T, 69) * 0.5, torch.tensor([1.0, 0.0, 1.0, 0.5], dtype=torch.float64)
    _gradcheck(lambda p: TM.pose_prior_term(p, prior, prior_conf), pose)
    _gradcheck(TM.joint_limits_term, pose)
    _gradcheck(TM.shape_prior_term, r(10).requires_grad_())


def test_terms_known_answers():
    p = torch.zeros(1, 2, 3, dtype=torch.float64)
    t = torch.tensor([[[0.0, 0.0, 0.05], [float("nan"), 0.0, 0.0]]], dtype=torch.float64)
    conf = torch.ones(1, 2, dtype=torch.float64)
    # A residual of one scale costs 1 in L2 and 1/2 in Geman-McClure; the NaN target is ignored.
    assert float(TM.kp3d_term(p, t, conf, "l2", 0.05)) == pytest.approx(1.0)
    assert float(TM.kp3d_term(p, t, conf, "geman_mcclure", 0.05)) == pytest.approx(0.5)
    x = torch.arange(5, dtype=torch.float64)[:, None] ** 2  # accelerations 2 everywhere
    assert float(TM.acceleration_term(x)) == pytest.approx(4.0)
    assert float(TM.velocity_term(torch.arange(4.0)[:, None])) == pytest.approx(1.0)
    pose = torch.zeros(2, 69, dtype=torch.float64)
    pose[0, 3 * 3] = 1.0  # left knee flexed: allowed
    pose[0, 17 * 3 + 1] = -1.0  # left elbow flexed (about -y): allowed
    assert float(TM.joint_limits_term(pose)) == 0.0
    pose[1, 4 * 3] = -0.2  # right knee hyper-extended by 0.2 rad
    assert float(TM.joint_limits_term(pose)) == pytest.approx(0.04 / 2)
    # Projection through a camera at the origin looking along +z: the principal point.
    uv, z = TM.project(torch.tensor([[[0.0, 0.0, 2.0]]], dtype=torch.float64), torch.as_tensor(K)[None],
                       torch.eye(4, dtype=torch.float64)[None, None])
    assert uv[0, 0, 0].tolist() == pytest.approx([360.0, 480.0]) and float(z[0, 0, 0]) == 2.0


# ------------------------------------------------------------------------------- init


def test_init_from_prior_round_trip_and_gaps(body, motion):
    params, joints, _ = motion
    T = len(params)
    cams = _cameras(joints[:, 0].mean(0), T)["v2"]  # a moving camera
    R, c = cams[:, :3, :3], cams[:, :3, 3]
    # Camera-space prior of the same bodies, each frame with a different betas estimate of which
    # the median is the truth; the pelvis is kept per frame, as a regressor reports it.
    rng = np.random.default_rng(3)
    sign = np.array([1.0, -1.0, 0.0])[np.arange(T) % 3][:, None]  # as many above as below
    betas_t = params.betas + sign * rng.normal(size=(1, 10)) * 0.2
    pelvis_w = params.transl + body.pelvis_offset(params.betas)
    go_cam = (Rotation.from_matrix(R).inv() * Rotation.from_rotvec(np.array(params.global_orient))).as_rotvec()
    transl_cam = np.einsum("tji,tj->ti", R, pelvis_w - c) - body.pelvis_offset(betas_t)
    prior = BodyPriorSeq(go_cam, params.body_pose, betas_t, transl_cam, np.arange(T))
    back = init_from_prior(body, prior, cams)
    assert np.allclose(back.betas, params.betas, atol=1e-9)
    assert np.allclose(_joints(body, back)[0], joints, atol=1e-6)

    # Missing rows (all zeros) are interpolated from their neighbours: smooth motion, small error.
    rows = [np.array(a) for a in (go_cam, params.body_pose, betas_t, transl_cam)]
    gaps = np.r_[0:3, 40:44, T - 2 : T]
    for a in rows:
        a[gaps] = 0.0
    filled = init_from_prior(body, BodyPriorSeq(*rows, np.arange(T)), cams)
    err = np.linalg.norm(_joints(body, filled)[0] - joints, axis=-1).max(1)
    assert np.all(np.isfinite(filled.global_orient))
    assert err[np.setdiff1d(np.arange(T), gaps)].max() < 1e-6
    assert err[40:44].max() < 0.05  # 4 frames of walking bridged within 5 cm


def test_init_from_keypoints_faces_the_right_way(body, motion):
    params, joints, coco = motion
    init = init_from_keypoints(body, coco, np.ones(coco.shape[:2]))
    j, _ = _joints(body, init)
    assert np.linalg.norm(j[:, 0] - joints[:, 0], axis=-1).max() < 0.06  # shape and pose differ
    # Heading: SMPL's forward (+Z of its frame) mapped to the world, compared on the floor.
    fwd = lambda go: Rotation.from_rotvec(np.array(go)).apply([0.0, 0.0, 1.0])[:, :2]  # noqa: E731
    a, b = fwd(init.global_orient), fwd(params.global_orient)
    cos = (a * b).sum(1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 20.0


# ------------------------------------------------------------------------------- fits


def test_clean_fit_recovers_the_truth_and_lowers_every_term(body, motion):
    params, joints, coco = motion
    init = _perturbed(params)
    res = fit_world_smpl(body, coco, np.ones(coco.shape[:2]), _views(coco), init, None, SmplifyConfig(device="cpu"))
    j, c = _joints(body, res.params)
    j0, _ = _joints(body, init)
    # Observed joints to 1 cm (the unobservable spine/hands/feet are excluded, see LIMB_JOINTS).
    assert _mpjpe(j[:, LIMB_JOINTS], joints[:, LIMB_JOINTS]) < 0.01
    assert _mpjpe(c, coco) < 0.005
    assert _mpjpe(j0[:, LIMB_JOINTS], joints[:, LIMB_JOINTS]) > 0.05  # the init was far
    assert max(res.reproj_px.values()) < 2.0 and set(res.reproj_px) == {"v1", "v2"}
    for name, before in res.terms_before.items():
        if before > 0:
            assert res.terms_after[name] < before, name
    assert res.params.body_pose.shape == params.body_pose.shape and res.seconds > 0


def test_noisy_fit_beats_the_triangulated_keypoints(body, motion):
    params, joints, coco = motion
    rng = np.random.default_rng(5)
    noisy = coco + rng.normal(size=coco.shape) * 0.02
    conf = np.ones(coco.shape[:2])
    noisy[10, 3], conf[20, :5] = np.nan, 0.0  # missing points are fine
    prior_pose = params.body_pose + rng.normal(size=params.body_pose.shape) * 0.1  # a rough prior
    res = fit_world_smpl(body, noisy, conf, _views(coco, noise_px=6.0), _perturbed(params), prior_pose,
                         SmplifyConfig(device="cpu"))
    _, c = _joints(body, res.params)
    raw = np.nanmean(np.linalg.norm(noisy - coco, axis=-1))
    assert _mpjpe(c, coco) < 0.7 * raw


def test_windows_are_seamless_and_match_one_window(body, motion):
    params, joints, coco = motion
    init, views, conf = _perturbed(params), _views(coco), np.ones(coco.shape[:2])
    cfg = SmplifyConfig(device="cpu", window_frames=60, overlap_frames=15, shape_frames=60)
    res = fit_world_smpl(body, coco, conf, views, init, None, cfg)
    assert len(res.windows) == 3
    one = fit_world_smpl(body, coco, conf, views, init, None, SmplifyConfig(device="cpu"))
    _, c = _joints(body, res.params)
    _, c1 = _joints(body, one.params)
    assert np.linalg.norm(c - c1, axis=-1).max() < 0.02
    assert _mpjpe(c, coco) < 0.005
    # No jump at the seams: the fitted frame-to-frame motion follows the true one everywhere,
    # about as closely as the one-window fit does (max over frames and keypoints, metres/frame).
    # (The largest deviation of both is at the clip's sharpest turn, frame 100, not at a seam: the
    # acceleration term rounds it off; 8 mm/frame with w_kp3d 1, about 18 with the default 0.25.)
    dv = np.linalg.norm(np.diff(c, axis=0) - np.diff(coco, axis=0), axis=-1).max()
    assert dv < 0.025
    # At the seams (the windows' overlaps, where they are blended) no worse than the one window.
    seams = np.zeros(len(c) - 1, dtype=bool)
    for (_, e), (s, _) in zip(res.windows, res.windows[1:]):
        seams[s:e] = True
    dv_seam = np.linalg.norm(np.diff(c, axis=0) - np.diff(coco, axis=0), axis=-1)[seams].max()
    dv1_seam = np.linalg.norm(np.diff(c1, axis=0) - np.diff(coco, axis=0), axis=-1)[seams].max()
    assert dv_seam < dv1_seam + 0.003
    ev = np.linalg.norm(np.diff(c, axis=0) - np.diff(coco, axis=0), axis=-1)
    assert np.percentile(ev, 99) < 0.012


def test_window_ranges_and_blend_weights():
    assert window_ranges(100, 300, 30) == [(0, 100)]
    r = window_ranges(1800, 300, 30)
    assert r[0][0] == 0 and r[-1][1] == 1800
    assert all(b[0] < a[1] - 29 for a, b in zip(r, r[1:]))  # overlaps of at least 30 frames
    w = _blend_weights(r, 1800, 30)
    assert np.allclose(w.sum(0), 1.0) and w.min() >= 0
    with pytest.raises(ValueError, match="must exceed the overlap"):
        window_ranges(100, 30, 30)


# ------------------------------------------------------------------------------- bad input


def test_bad_inputs_raise_clear_errors(body, motion):
    params, joints, coco = motion
    T = len(params)
    conf, views = np.ones((T, 17)), _views(coco)
    with pytest.raises(ValueError, match=r"kp3d must be \(T=%d, 17, 3\)" % T):
        fit_world_smpl(body, coco[:-1], conf, views, params)
    with pytest.raises(ValueError, match="kp3d_conf must be"):
        fit_world_smpl(body, coco, conf[:, :5], views, params)
    bad = ViewObservations(K, views[0].T_world_cam[:-1], views[0].keypoints, "v1")
    with pytest.raises(ValueError, match="view v1: T_world_cam must be"):
        fit_world_smpl(body, coco, conf, [bad], params)
    bad = ViewObservations(K, views[0].T_world_cam, views[0].keypoints[..., :2], "v1")
    with pytest.raises(ValueError, match="view v1: keypoints must be"):
        fit_world_smpl(body, coco, conf, [bad], params)
    with pytest.raises(ValueError, match="prior_body_pose must be"):
        fit_world_smpl(body, coco, conf, views, params, np.zeros((T, 63)))
    with pytest.raises(ValueError, match="unknown solver"):
        fit_world_smpl(body, coco, conf, views, params, cfg=SmplifyConfig(solver="sgd"))
    with pytest.raises(ValueError, match="no frame has both hips"):
        init_from_keypoints(body, coco, np.zeros((T, 17)))
    with pytest.raises(ValueError, match="T_world_cam must be"):
        init_from_prior(body, BodyPriorSeq(params.global_orient, params.body_pose, np.zeros((T, 10)),
                                           params.transl, np.arange(T)), views[0].T_world_cam[:3])


def test_snap_to_keypoints_moves_a_far_init_onto_the_triangulation(body, motion):
    """A prior whose depth is 60 cm off (a monocular regressor's typical failure) is put back on the
    keypoints: frame by frame, by the median offset of the seen joints; frames with too few seen
    joints take the offset of their neighbours."""
    from embodmocap.motion.init import snap_to_keypoints

    params, _, coco = motion
    far = SmplParams(params.betas, params.global_orient, params.body_pose,
                     params.transl + np.array([0.6, -0.2, 0.1]), fps=params.fps)
    conf = np.ones(coco.shape[:2])
    points = coco.copy()
    points[10:14] = np.nan  # four frames with nothing triangulated
    snapped = snap_to_keypoints(body, far, points, conf)
    np.testing.assert_allclose(snapped.transl, params.transl, atol=1e-6)
    np.testing.assert_array_equal(snapped.body_pose, far.body_pose)
    with pytest.raises(ValueError, match="points must be"):
        snap_to_keypoints(body, far, points[:-1], conf)


# ------------------------------------------------------------------------------- speed paths (issue 30)


def test_reproj_view_terms_equal_each_view_alone(motion):
    _, _, coco = motion
    T = 20
    views = _views(coco[:T], noise_px=30.0)
    views[1].keypoints[3, 5:9, 2] = 0.0  # some missing detections in one view
    kp = torch.as_tensor(np.stack([v.keypoints for v in views], 1))
    Twc = torch.as_tensor(np.stack([v.T_world_cam for v in views], 1))
    Ks = torch.as_tensor(np.stack([v.K for v in views]))
    pred = torch.as_tensor(coco[:T]) + 0.03
    both = TM.reproj_view_terms(pred, Ks, Twc, kp[..., :2], kp[..., 2])
    for v in range(2):
        alone = TM.reproj_term(pred, Ks[v : v + 1], Twc[:, v : v + 1], kp[:, v : v + 1, :, :2], kp[:, v : v + 1, :, 2])
        assert float(both[v]) == pytest.approx(float(alone), rel=1e-12)
    assert float(both[0]) != pytest.approx(float(both[1]))


def test_plain_adam_takes_torch_adams_steps():
    from embodmocap.motion.smplify import _Adam

    rng = np.random.default_rng(0)
    x0, y0 = torch.as_tensor(rng.normal(size=(5, 3))), torch.as_tensor(rng.normal(size=7))
    loss = lambda x, y: ((x ** 2).sum() - 0.3 * x.prod() + ((y - 1.0) ** 4).sum() + (x[:, 0] * y[:5]).sum())  # noqa: E731
    xa, ya = x0.clone().requires_grad_(True), y0.clone().requires_grad_(True)
    xb, yb = x0.clone().requires_grad_(True), y0.clone().requires_grad_(True)
    ref = torch.optim.Adam([{"params": [xa], "lr": 0.1}, {"params": [ya], "lr": 0.05}])
    ours = _Adam([xb, yb])
    for it in range(40):
        lrs = [0.1 * (1 - it / 50), 0.05 * (1 - it / 60)]
        for g, lr in zip(ref.param_groups, lrs):
            g["lr"] = lr
        ref.zero_grad()
        loss(xa, ya).backward()
        ref.step()
        xb.grad = yb.grad = None
        loss(xb, yb).backward()
        ours.step(lrs)
    assert torch.equal(xa, xb) and torch.equal(ya, yb)
    assert not torch.equal(xa, x0)


def test_fit_twice_gives_the_same_answer_and_restores_torch_threads(body, motion):
    params, _, coco = motion
    T = 30
    views = _views(coco[:T], noise_px=2.0)
    init = SmplParams(betas=np.zeros(10), global_orient=params.global_orient[:T] + 0.1, body_pose=np.zeros((T, 69)),
                      transl=params.transl[:T] + 0.05, fps=FPS)
    cfg = SmplifyConfig(phase1_iterations=10, phase2_iterations=20, threads=1)
    before = torch.get_num_threads()
    a = fit_world_smpl(body, coco[:T], np.ones((T, 17)), views, init, cfg=cfg)
    assert torch.get_num_threads() == before
    b = fit_world_smpl(body, coco[:T], np.ones((T, 17)), views, init, cfg=cfg)
    for k in ("betas", "global_orient", "body_pose", "transl"):
        assert np.array_equal(getattr(a.params, k), getattr(b.params, k)), k
    assert a.terms_after == b.terms_after
