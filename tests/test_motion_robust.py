"""Stage IV against a hard detector's failure modes (issue 11): bone lengths that a long limb swap
cannot skew, the bone check of an arm whose shoulder no view saw, and limb starts carried over
from the frames where the limb fits its keypoints."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from embodmocap.body.joints import smpl_to_coco17
from embodmocap.body.model import load_body_model
from embodmocap.geometry.transforms import look_at_T
from embodmocap.motion.ik import (betas_from_bone_lengths, implausible_points, observed_bone_lengths,
                                  rest_skeleton, symmetric_length, torso_anchors)
from embodmocap.motion.propagate import limb_costs, propagate_limbs
from embodmocap.motion.smplify import KeypointBody
from embodmocap.synth.motion import script_motion
from embodmocap.synth.scene import build_scene

BETAS = np.array([0.5, -0.3, 0.2, 0, 0, 0, 0, 0, 0, 0])
K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])


@pytest.fixture(scope="module")
def body():
    return load_body_model(None)


@pytest.fixture(scope="module")
def motion(body):
    """3 s of scripted motion: params and the true COCO-17 points (T, 17, 3)."""
    spec = build_scene("indoor", np.random.default_rng(5)).spec
    params = script_motion(spec, body, BETAS, 3.0, 30.0, np.random.default_rng(5)).params
    return params, _coco(body, params)


def _coco(body, params):
    with torch.no_grad():
        out = body.from_params(params, dtype=torch.float64)
        return smpl_to_coco17(out.joints, out.vertices, body.vertex_ids, "COCO17").numpy()


def test_pair_length_is_the_one_most_frames_share(motion):
    """A swap run over 55 % of the frames makes both upper arms too long, by amounts that change
    as the arms move, and the two sides even agree with each other there: a per-side median (or
    one over the frames where the sides agree) is pulled off, the densest length is not."""
    _, kp = motion
    T = len(kp)
    true = np.linalg.norm(kp[:, 5] - kp[:, 7], axis=-1)
    rng = np.random.default_rng(0)
    d_left, d_right = true.copy(), true.copy()
    run = np.arange(T) < int(0.55 * T)
    wrong = rng.uniform(1.5, 2.0, run.sum()) * true[run]
    d_left[run], d_right[run] = wrong, wrong * rng.uniform(0.95, 1.05, run.sum())
    d_left[rng.random(T) < 0.2] = np.nan  # unseen now and then
    L = symmetric_length(d_left, d_right)
    assert abs(L - np.median(true)) < 0.01
    for d in (d_left, d_right):  # what a per-side median gives
        assert abs(np.nanmedian(d) - np.median(true)) > 0.05
    assert np.isnan(symmetric_length(np.full(5, np.nan), np.array([0.3, np.nan, np.nan, np.nan, np.nan])))


def test_observed_lengths_give_the_shape_despite_a_long_swap(body, motion):
    params, kp = motion
    sk = rest_skeleton(body)
    T = len(kp)
    bad = kp.copy()
    run = slice(0, int(0.45 * T))
    # The arms of one view swapped along the epipolar lines: both elbows and wrists pushed out.
    bad[run, [7, 8, 9, 10]] += np.array([0.0, 0.0, 0.25])
    seen = np.ones((T, 17), dtype=bool)
    L_true = observed_bone_lengths(kp, seen)
    L = observed_bone_lengths(bad, seen)
    np.testing.assert_allclose(L[:4], L_true[:4], atol=0.01)
    b = betas_from_bone_lengths(sk, L)
    assert np.abs(b - betas_from_bone_lengths(sk, L_true)).max() < 0.5


def test_an_elbow_whose_shoulder_is_unseen_is_checked_against_the_placed_torso(body, motion):
    _, kp = motion
    T = len(kp)
    sk = rest_skeleton(body)
    seen = np.ones((T, 17), dtype=bool)
    b = betas_from_bone_lengths(sk, observed_bone_lengths(kp, seen))
    pts = kp.copy()
    frames = np.arange(10, 25)
    pts[frames, 6] = np.nan  # the right shoulder: no view saw it
    seen[frames, 6] = False
    # A wrong elbow guess: 60 % further from the shoulder, the wrist where it is.
    pts[frames, 8] = kp[frames, 6] + 1.6 * (kp[frames, 8] - kp[frames, 6])
    anchors = torso_anchors(sk, b, pts, seen)
    # The placed torso's shoulder is where the true one is (the other three torso points are exact).
    assert np.linalg.norm(anchors[frames, 6] - kp[frames, 6], axis=-1).max() < 0.03
    plain = implausible_points(sk, b, pts, seen, 0.3)
    anchored = implausible_points(sk, b, pts, seen, 0.3, anchors)
    assert not plain[frames, 8].any()  # without the anchor nothing checks this elbow
    assert anchored[frames, 8].all()
    # Only the wrong elbows are flagged (and the wrist, now 60 cm from that elbow, is judged
    # against the shoulder's reach instead: plausible).
    others = np.ones((T, 17), dtype=bool)
    others[frames, 8] = False
    assert not anchored[others].any()


def _two_views(T):
    centre = np.array([0.0, 0.0, 1.0])
    cams = [look_at_T(centre + 3.5 * np.array([np.cos(a), np.sin(a), h]), centre) for a, h in ((0.3, 0.1), (1.9, 0.5))]
    return np.broadcast_to(np.stack(cams), (T, 2, 4, 4)).copy()


def _project(points, T_wc):
    """(T, V, 17, 3) pixels + confidence 0.9 of world points (T, 17, 3)."""
    R, c = T_wc[..., :3, :3], T_wc[..., :3, 3]
    cam = np.einsum("tvba,tvjb->tvja", R, points[:, None] - c[:, :, None])
    uv = cam[..., :2] / cam[..., 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    return np.concatenate([uv, np.full(uv.shape[:-1] + (1,), 0.9)], axis=-1)


def test_limb_start_rejected_by_its_keypoints_is_carried_over_from_good_frames(body, motion):
    """The first frames start with the right arm bent the wrong way (as from an elbow triangulated
    at a wrong depth); the start carried over from the next frames, where the arm fits both views
    and the 3D points, replaces it there and nowhere else."""
    params, kp = motion
    T = len(kp)
    T_wc = _two_views(T)
    kp2d = _project(kp, T_wc)
    conf3 = np.full((T, 17), 0.9)
    bad = np.array(params.body_pose, dtype=np.float64).reshape(T, 23, 3).copy()
    first = np.arange(0, 6)
    for j, rv in ((16, [0.0, 0.0, 1.4]), (18, [0.0, 1.6, 0.0])):  # right shoulder and elbow (SMPL 17, 19)
        bad[first, j] = (Rotation.from_rotvec(rv) * Rotation.from_rotvec(bad[first, j])).as_rotvec()
    start = replace(params, body_pose=bad.reshape(T, 69))
    kb = KeypointBody(body, layout="COCO17")
    cost0, _ = limb_costs(kb, start, kp, conf3, np.stack([K, K]), T_wc, kp2d, 0.05, 20.0, 0.1)
    assert (cost0[first, 3] > 2.0).all() and (cost0[6:, 3] < 0.1).all()  # the right arm is limb 3
    out, taken = propagate_limbs(kb, start, kp, conf3, np.stack([K, K]), T_wc, kp2d, 0.05, 20.0, 0.1)
    assert taken[first, 3].all() and taken.sum() == len(first)
    wrist = lambda p: np.linalg.norm(_coco(body, p)[first, 10] - kp[first, 10], axis=-1)  # noqa: E731
    assert wrist(start).min() > 0.2
    assert wrist(out).max() < 0.06  # the arm held from frame 6: a fifth of a second of motion off
    np.testing.assert_array_equal(np.asarray(out.body_pose)[6:], np.asarray(start.body_pose)[6:])


def test_evaluation_aligns_chunks_on_valid_frames_and_reports_the_flagged_ones(motion):
    """Frames the fit flagged invalid are left out of the errors (each chunk is aligned on its first
    two *valid* frames), counted, and the figures with them kept are reported beside."""
    from embodmocap.evaluate.session import SequenceTruth, motion_errors

    params, _ = motion
    T = len(params)
    rng = np.random.default_rng(2)
    truth_j = rng.normal(size=(T, 24, 3)) * 0.3 + np.linspace(0, 3, T)[:, None, None] * [1.0, 0, 0]
    truth = SequenceTruth(truth_j, {}, {}, {}, np.ones(T, dtype=bool))
    pred = truth_j + rng.normal(size=truth_j.shape) * 0.01
    pred[:2, 20:] += 0.5  # the first two frames: a hand half a metre off, flagged invalid
    valid = np.ones(T, dtype=bool)
    valid[:2] = False
    frames = np.arange(T)
    e = motion_errors(pred, frames, truth, valid)
    assert e["invalid_frames"] == 2 and e["evaluated_frames"] == T - 2
    assert e["w_mpjpe_mm"] < 25  # aligned on frames 2 and 3: only the 1 cm noise
    assert e["w_mpjpe_mm_incl_invalid"] > 2 * e["w_mpjpe_mm"]  # frames 0-1 would tilt the alignment
    assert "w_mpjpe_mm_incl_invalid" not in motion_errors(pred, frames, truth, np.ones(T, dtype=bool))
