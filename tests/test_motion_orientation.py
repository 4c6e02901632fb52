"""The torso orientation term (motion.orientation): known answers, and a noisy fit whose heading
wobbles without it."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from embodmocap.body.model import load_body_model
from embodmocap.motion.orientation import torso_acc_term, torso_frames
from embodmocap.motion.smplify import SmplifyConfig, fit_world_smpl
from embodmocap.synth.motion import script_motion
from embodmocap.synth.scene import build_scene
from test_smplify import BETAS, FPS, LIMB_JOINTS, _joints, _mpjpe, _perturbed, _views


def _heading_deg(joints: np.ndarray) -> np.ndarray:
    """(T,) the torso's heading about the world's Z (degrees) of SMPL joints (T, 24, 3)."""
    R = torso_frames(torch.as_tensor(joints)).numpy()
    return np.degrees(np.arctan2(R[:, 1, 2], R[:, 0, 2]))


def _turning_torso(yaw: np.ndarray) -> np.ndarray:
    """(T, 24, 3) joints whose pelvis, hips, neck and shoulders (the rest zero) are a fixed torso
    facing +X at yaw 0, turned by ``yaw`` (T,) radians about Z."""
    rest = np.zeros((24, 3))
    rest[1], rest[2] = [0.0, 0.09, -0.08], [0.0, -0.09, -0.08]  # left hip on +Y (facing +X)
    rest[12], rest[16], rest[17] = [0.0, 0.0, 0.5], [0.0, 0.18, 0.45], [0.0, -0.18, 0.45]
    R = Rotation.from_rotvec(np.outer(yaw, [0.0, 0.0, 1.0])).as_matrix()
    return np.einsum("tij,nj->tni", R, rest) + np.array([1.0, 2.0, 0.9])


def test_torso_frame_and_its_acceleration_known_answers():
    t = np.arange(30, dtype=np.float64)
    # Heading: the frame's forward axis points along the turned +X.
    yaw = np.radians(np.linspace(-60, 60, 30))
    assert np.allclose(_heading_deg(_turning_torso(yaw)), np.degrees(yaw), atol=1e-9)
    R = torso_frames(torch.as_tensor(_turning_torso(yaw))).numpy()
    assert np.allclose(np.einsum("tji,tjk->tik", R, R), np.eye(3), atol=1e-12) and np.allclose(np.linalg.det(R), 1.0)
    # A constant angular acceleration a costs a^2 (per frame^2; exactly a^2 + w^4 about one axis, w
    # the rate, here under 0.03 rad per frame); a constant rate w only w^4.
    a = 0.002
    got = float(torso_acc_term(torch.as_tensor(_turning_torso(0.5 * a * (t - 14.5) ** 2))))
    assert got == pytest.approx(a ** 2, rel=0.05)
    w = 0.05
    assert float(torso_acc_term(torch.as_tensor(_turning_torso(w * t)))) == pytest.approx(w ** 4, rel=0.05)
    # A 5-degree wobble of alternate frames (the keypoints' jitter) costs what its acceleration says.
    wobble = np.radians(5.0) * (-1.0) ** t
    inner = float(torso_acc_term(torch.as_tensor(_turning_torso(wobble))))
    assert inner == pytest.approx((4 * np.radians(5.0)) ** 2, rel=0.05)
    # Translation does not count; fewer than three frames cost nothing.
    moved = _turning_torso(np.zeros(30)) + 0.5 * 0.02 * t[:, None, None] ** 2
    assert float(torso_acc_term(torch.as_tensor(moved))) < 1e-20
    assert float(torso_acc_term(torch.as_tensor(_turning_torso(wobble[:2])))) == 0.0


def test_the_cut_at_unplaced_frames_drops_only_the_differences_that_span_a_boundary():
    # Frames 10-14 unplaced (their heading a wrong guess 1 rad off, held); the placed ones turn at a
    # constant angular acceleration a. With the cut the jumps at 9-10 and 14-15 cost nothing, and
    # what is left is a^2 over the second differences inside one run (mean over all T - 2).
    t = np.arange(30, dtype=np.float64)
    a = 0.002
    yaw = 0.5 * a * (t - 14.5) ** 2
    yaw[10:15] = 1.0
    placed = np.ones(30)
    placed[10:15] = 0.0
    J = torch.as_tensor(_turning_torso(yaw))
    full = float(torso_acc_term(J))
    cut = float(torso_acc_term(J, torch.as_tensor(placed)))
    inside = 8 + 13  # triples wholly in frames 0-9 and 15-29; those in 10-14 cost 0 (held)
    assert cut == pytest.approx(a ** 2 * inside / 28, rel=0.05)
    assert full > 1e3 * cut  # the jumps dominate without the cut
    # All frames placed: the cut changes nothing.
    assert float(torso_acc_term(J, torch.ones(30, dtype=J.dtype))) == pytest.approx(full, rel=1e-12)


@pytest.fixture(scope="module")
def walk():
    body = load_body_model(None)
    spec = build_scene("indoor", np.random.default_rng(0)).spec
    params = script_motion(spec, body, BETAS, 3.0, FPS, np.random.default_rng(0)).params
    out = body.from_params(params, dtype=torch.float64)
    return body, params, out.joints.numpy(), out.coco17.numpy()


@pytest.mark.slow
def test_the_term_removes_the_heading_wobble_of_noisy_hip_and_shoulder_keypoints(walk):
    """Keypoints with a detector's jitter (2 cm in 3D, 6 px in 2D): without the term the fitted
    torso's heading wobbles around the truth's from frame to frame; with it the heading error
    drops and the observed joints are no worse."""
    body, params, joints, coco = walk
    rng = np.random.default_rng(3)
    noisy = coco + rng.normal(size=coco.shape) * 0.02
    views = _views(coco, noise_px=6.0, seed=4)
    init = _perturbed(params)
    truth = _heading_deg(joints)
    out = {}
    for w in (0.0, 10.0):
        cfg = SmplifyConfig(device="cpu", w_orient_acc=w)
        res = fit_world_smpl(body, noisy, np.ones(coco.shape[:2]), views, init, None, cfg)
        j, _ = _joints(body, res.params)
        err = (_heading_deg(j) - truth + 180.0) % 360.0 - 180.0
        out[w] = (np.abs(err), _mpjpe(j[:, LIMB_JOINTS], joints[:, LIMB_JOINTS]))
    (off, limbs_off), (on, limbs_on) = out[0.0], out[10.0]
    assert np.median(off) > 1.0  # the wobble is there without the term
    assert np.median(on) < 0.7 * np.median(off) and on.mean() < 0.8 * off.mean()
    assert limbs_on < limbs_off + 0.002
