"""The camera-space body's depth refined against 2D keypoints (``--human-depth keypoints``), the
user's height (``--scale.height-m``) and the studio's shape-biased prior (``HARD_PRIOR_NOISE``):
synthetic bodies in front of a camera with known truth."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter1d

from embodmocap.body.model import load_body_model
from embodmocap.body.stature import betas_for_stature, stature
from embodmocap.mono.config import DepthRefineConfig
from embodmocap.mono.files import HumanSeq
from embodmocap.mono.refine import refine_human, sequence_betas
from embodmocap.synth.perception import HARD_PRIOR_NOISE, PriorNoiseConfig, body_prior
from embodmocap.types import SmplParams

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
FPS = 30.0


@pytest.fixture(scope="module")
def model():
    return load_body_model(None)


def _walker(T: int = 120, seed: int = 0) -> SmplParams:
    """A person upright in front of an identity camera (world = OpenCV camera frame), 2.5-4 m away,
    walking sideways with a smoothly changing pose."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) / FPS
    # SMPL's Y-up, facing +Z -> camera's -Y up, facing the camera (-Z): 180 deg about X
    go = np.tile([np.pi, 0.0, 0.0], (T, 1))
    pose = gaussian_filter1d(rng.normal(size=(T, 69)), 6, axis=0) * 0.6
    transl = np.stack([0.8 * np.sin(0.7 * t), 0.1 * np.ones(T), 3.2 + 0.7 * np.sin(0.4 * t)], 1)
    return SmplParams(np.array([0.5, -0.3, 0.2, 0, 0, 0, 0, 0, 0, 0.0]), go, pose, transl, fps=FPS)


def _keypoints(model, params: SmplParams, rng, px_std: float = 1.0) -> np.ndarray:
    """(T, 17, 3) the true COCO-17 projections with pixel noise, confidence 0.9."""
    with torch.no_grad():
        X = model.from_params(params, dtype=torch.float64).coco17.numpy()
    uv = np.einsum("ij,tkj->tki", K, X)
    uv = uv[..., :2] / uv[..., 2:]
    uv = uv + rng.normal(size=uv.shape) * px_std
    return np.concatenate([uv, np.full(uv.shape[:2] + (1,), 0.9)], -1)


def _human(prior) -> HumanSeq:
    T = len(prior.transl_cam)
    return HumanSeq(np.array(prior.global_orient_cam), np.array(prior.body_pose), np.array(prior.betas),
                    np.array(prior.transl_cam), np.ones(T, bool))


def _pelvis(model, h: HumanSeq) -> np.ndarray:
    return model.pelvis_offset(h.betas) + h.transl


def test_refinement_recovers_the_priors_depth_error(model):
    """The studio's realistic prior (depth 10 % off along the ray, 0.5 s correlation, 7 deg per
    joint): the refined pelvis depth error is a fraction of the prior's. It is measured against
    the depth where a body of the sequence's (median) shape looks as large as the truth: what no
    image can tell (that shape's size error, here -2.8 % from the prior's per-frame shape noise
    over 4 s) stays. Left: a bias of about -2 % from the prior's pose errors (a joint-angle error
    foreshortens the limbs on average: the skeleton looks smaller, so it is put nearer)."""
    truth = _walker()
    rng = np.random.default_rng(1)
    T_wc = np.tile(np.eye(4), (len(truth), 1, 1))
    h = _human(body_prior(truth, T_wc, model, rng, PriorNoiseConfig()))
    true_p = model.pelvis_offset(truth.betas) + truth.transl
    err0 = _pelvis(model, h)[:, 2] / true_p[:, 2] - 1
    res = refine_human(h, model, _keypoints(model, truth, rng), K, FPS, DepthRefineConfig())
    size = stature(model, res.human.betas[0]) / stature(model, truth.betas)
    err1 = _pelvis(model, res.human)[:, 2] / (size * true_p[:, 2]) - 1
    assert np.abs(err0).mean() > 0.06 and err0.std() > 0.03  # the prior's error is there
    assert np.abs(err1).mean() < 0.4 * np.abs(err0).mean()
    assert err1.std() < 0.6 * err0.std()
    assert abs(np.median(err1)) < 0.035
    st = res.stats
    assert st["source"] == "keypoints" and st["frames_refined"] >= 0.95 * len(truth)
    assert st["reproj_px_after_median"] < st["reproj_px_before_median"]
    # one shape for the sequence: every row the valid frames' median betas
    assert np.allclose(res.human.betas, np.median(h.betas, axis=0)[None], atol=1e-12)


def test_exact_keypoints_give_the_exact_depth(model):
    """Noise-free body and keypoints, the body's depth scaled by 1.15: the solve puts it back."""
    truth = _walker(T=40)
    T_wc = np.tile(np.eye(4), (len(truth), 1, 1))
    exact = _human(body_prior(truth, T_wc, model, np.random.default_rng(0), PriorNoiseConfig(0, 0, 0, 0, 0)))
    p = _pelvis(model, exact)
    off = HumanSeq(exact.global_orient, exact.body_pose, exact.betas, 1.15 * p - model.pelvis_offset(exact.betas),
                   exact.valid)
    kp = _keypoints(model, truth, np.random.default_rng(0), px_std=0.0)
    cfg = DepthRefineConfig(median_frames=1, smooth_s=0.0)
    res = refine_human(off, model, kp, K, FPS, cfg)
    assert np.abs(_pelvis(model, res.human) - p).max() < 1e-4  # 0.1 mm
    assert res.stats["reproj_px_after_median"] < 1e-3


def test_missing_keypoints_keep_the_model_depth(model):
    """Without keypoints (``--human-depth model`` or no keypoints file) and no height: the body
    is the model's, untouched."""
    truth = _walker(T=20)
    h = _human(body_prior(truth, np.tile(np.eye(4), (20, 1, 1)), model, np.random.default_rng(3), PriorNoiseConfig()))
    res = refine_human(h, model, None, K, FPS, DepthRefineConfig())
    assert res.human is h and res.stats["source"] == "model"


def test_height_option_sets_the_stature_with_the_smallest_change(model):
    b0 = np.array([0.5, -0.3, 0.2, 0.1, 0, 0, 0, 0, 0, 0.0])
    for want in (1.55, 1.80, 1.95):
        b = betas_for_stature(model, b0, want)
        assert abs(stature(model, b) - want) < 1e-6
    # minimal: the change is along the stature gradient (any other change of the same height is longer)
    b = betas_for_stature(model, b0, 1.80)
    eps = 1e-4
    g = np.array([(stature(model, b0 + eps * e) - stature(model, b0 - eps * e)) / (2 * eps) for e in np.eye(10)])
    d = b - b0
    assert abs(d @ g) / (np.linalg.norm(d) * np.linalg.norm(g)) > 0.999
    # through refine_human: the sequence's shape has the given height, the depth moves with the size
    truth = _walker(T=20)
    h = _human(body_prior(truth, np.tile(np.eye(4), (20, 1, 1)), model, np.random.default_rng(4), PriorNoiseConfig()))
    res = refine_human(h, model, None, K, FPS, DepthRefineConfig(), height_m=1.80)
    assert abs(stature(model, res.human.betas[0]) - 1.80) < 1e-6 and res.stats["height_m"] == 1.8
    b_med, info = sequence_betas(model, h)
    ratio = 1.80 / info["model_height_m"]
    assert np.allclose(_pelvis(model, res.human), ratio * _pelvis(model, h), rtol=2e-4)


def test_shape_bias_preset_is_size_consistent(model):
    """``HARD_PRIOR_NOISE``'s shape error: the height of the rest pose is ~3 % off (std over many
    draws), and the body is placed where it looks as large as the truth in the image (projected
    keypoints within ~1 % of the person's image size) while its depth is off by its size ratio."""
    rng = np.random.default_rng(0)
    truth_b = np.array([0.5, -0.3, 0.2, 0.1, 0, 0, 0, 0, 0, 0.0])
    bias = rng.normal(size=(5000, 10)) * HARD_PRIOR_NOISE.betas_bias_std
    rel = stature(model, truth_b + bias) / stature(model, truth_b) - 1
    assert 0.025 < rel.std() < 0.035
    truth = _walker(T=30)
    T_wc = np.tile(np.eye(4), (30, 1, 1))
    only_bias = PriorNoiseConfig(0, 0, 0, 0, 0, betas_bias_std=HARD_PRIOR_NOISE.betas_bias_std)
    for seed in range(3):
        h = _human(body_prior(truth, T_wc, model, np.random.default_rng(seed), only_bias))
        k = stature(model, h.betas[0]) / stature(model, truth.betas)
        assert abs(k - 1) > 0.003
        true_p = model.pelvis_offset(truth.betas) + truth.transl
        assert np.allclose(_pelvis(model, h), k * true_p, rtol=1e-9)
        kp_true = _keypoints(model, truth, rng, 0.0)
        kp_bias = _keypoints(model, SmplParams(h.betas[0], h.global_orient, h.body_pose, h.transl, fps=FPS), rng, 0.0)
        size = np.ptp(kp_true[..., 1], axis=1)
        assert np.abs(kp_bias[..., :2] - kp_true[..., :2]).max(axis=(1, 2)).max() < 0.03 * size.min()
        assert np.abs(np.ptp(kp_bias[..., 1], axis=1) / size - 1).max() < 0.015
    # off by default: no draw, the realistic prior's errors unchanged for a seed
    a = body_prior(truth, T_wc, model, np.random.default_rng(7), PriorNoiseConfig())
    b = body_prior(truth, T_wc, model, np.random.default_rng(7), PriorNoiseConfig(betas_bias_std=0.0))
    assert np.array_equal(a.transl_cam, b.transl_cam) and np.array_equal(a.betas, b.betas)
