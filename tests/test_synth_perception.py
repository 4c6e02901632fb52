"""Simulated detector outputs: visibility, 2D keypoint noise, mask noise, camera-space body prior."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from embodmocap.body.model import load_body_model
from embodmocap.errors import InputError
from embodmocap.geometry.transforms import apply_T, invert_T, make_T, rot_z
from embodmocap.io.body_prior import BodyPriorSeq, read_body_prior, write_body_prior
from embodmocap.synth.perception import (
    KeypointNoiseConfig, MaskNoiseConfig, PriorNoiseConfig, body_prior, joint_visibility,
    noisy_keypoints, noisy_mask, person_height_px, swap_mask,
)
from embodmocap.types import SmplParams

K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])


# ---------------------------------------------------------------- visibility


def test_visibility_known_answers():
    depth = np.full((1, 480, 640), 5.0)  # a wall 5 m in front of an identity camera
    pts = np.array([[[0, 0, 3.0],        # in front of the wall: visible
                     [0, 0, 5.05],       # just inside the wall (within the margin): visible
                     [0, 0, 5.15],       # halfway through the soft margin
                     [0, 0, 6.0],        # behind the wall
                     [10, 0, 3.0],       # outside the image
                     [0, 0, -1.0],       # behind the camera
                     [319.5 / 500 * 3.0 * 0.99, 0, 3.0]]])  # near the right border
    vis = joint_visibility(pts, K, np.eye(4)[None], depth, margin_m=0.1)
    np.testing.assert_allclose(vis[0, :6], [1, 1, 0.5, 0, 0, 0], atol=1e-9)
    assert 0 < vis[0, 6] < 1
    # No surface (depth 0, e.g. sky) hides nothing; a moved camera sees the same.
    assert joint_visibility(pts[:, 3:4], K, np.eye(4)[None], np.zeros((1, 480, 640)))[0, 0] == 1.0
    T = make_T(rot_z(0.7), [1.0, 2.0, 3.0])
    vis_moved = joint_visibility(apply_T(T, pts[0])[None], K, T[None], depth)
    np.testing.assert_allclose(vis_moved, vis, atol=1e-9)


# ---------------------------------------------------------------- 2D keypoints


def _standing_gt(T: int, rng) -> np.ndarray:
    """(T, 17, 2) a person ~270 px tall somewhere in a 640x480 image."""
    base = np.array([[0, 0], [5, -5], [-5, -5], [10, -2], [-10, -2], [25, 30], [-25, 30], [30, 80],
                     [-30, 80], [32, 125], [-32, 125], [15, 130], [-15, 130], [15, 195], [-15, 195],
                     [15, 265], [-15, 265]], float)
    return base[None] + rng.uniform([200, 80], [440, 120], size=(T, 1, 2))


def test_keypoint_noise_matches_config():
    rng = np.random.default_rng(0)
    gt = _standing_gt(4000, rng)
    cfg = KeypointNoiseConfig(outlier_rate=0.0, swap_rate=0.0, miss_rate=0.0)
    kp = noisy_keypoints(gt, np.ones((4000, 17)), rng, cfg)
    err = np.linalg.norm(kp[..., :2] - gt, axis=-1)
    sigma = cfg.rel_std * person_height_px(gt)[:, None]
    # Median of a 2D isotropic Gaussian's norm is sigma * sqrt(2 ln 2).
    assert np.median(err / sigma) == pytest.approx(np.sqrt(2 * np.log(2)), rel=0.05)
    assert 2.0 < np.median(err) < 4.0  # ~3 px at 640x480
    assert np.all((kp[..., 2] >= 0.7) & (kp[..., 2] <= 0.95))


def test_occluded_points_are_less_confident_and_noisier():
    rng = np.random.default_rng(1)
    gt = _standing_gt(3000, rng)
    vis = np.ones((3000, 17))
    vis[:, [9, 10, 15]] = 0.0  # wrists and an ankle hidden
    cfg = KeypointNoiseConfig(outlier_rate=0.0, swap_rate=0.0, miss_rate=0.0)
    kp = noisy_keypoints(gt, vis, rng, cfg)
    conf_hidden, conf_seen = kp[:, [9, 10, 15], 2], np.delete(kp[..., 2], [9, 10, 15], axis=1)
    assert conf_hidden.max() <= 0.4 and conf_seen.min() >= 0.7
    err = np.linalg.norm(kp[..., :2] - gt, axis=-1)
    ratio = np.median(err[:, [9, 10, 15]]) / np.median(np.delete(err, [9, 10, 15], axis=1))
    assert ratio == pytest.approx(cfg.occluded_std_scale, rel=0.1)


def test_outliers_and_swaps_at_configured_rates():
    rng = np.random.default_rng(2)
    T = 20000
    gt = _standing_gt(T, rng)
    cfg = KeypointNoiseConfig(rel_std=0.001, outlier_rate=0.03, swap_rate=0.01, miss_rate=0.0)
    kp = noisy_keypoints(gt, np.ones((T, 17)), rng, cfg)
    h = person_height_px(gt)[:, None]
    far = np.linalg.norm(kp[..., :2] - gt, axis=-1) > 0.08 * h
    # Points on the face/torso/hips are never swapped: their far points are outliers only.
    unswapped = [0, 1, 2, 3, 4, 5, 6, 11, 12]
    assert far[:, unswapped].mean() == pytest.approx(0.03, abs=0.004)
    conf_far = kp[:, unswapped, 2][far[:, unswapped]]
    assert np.all((conf_far >= 0.4) & (conf_far <= 0.7))  # outliers: moderate confidence
    # Leg swap: the left knee sits on the right knee's true position.
    swapped = np.linalg.norm(kp[:, 13, :2] - gt[:, 14], axis=-1) < 0.01 * h[:, 0]
    mean_len = np.mean(cfg.swap_frames)
    expected = 1 - (1 - cfg.swap_rate) ** mean_len  # some event covers the frame
    assert swapped.mean() == pytest.approx(expected, rel=0.2)
    # The swap mask is what happened (ignoring the few frames where an outlier hit the knee).
    rng2 = np.random.default_rng(3)
    m = swap_mask(5000, rng2, cfg)
    runs = np.diff(np.concatenate([[0], m[:, 1].astype(int), [0]]))
    lengths = np.nonzero(runs == -1)[0] - np.nonzero(runs == 1)[0]
    assert lengths.min() >= cfg.swap_frames[0]


def test_missing_person_when_mostly_out_of_view():
    rng = np.random.default_rng(4)
    gt = _standing_gt(10, rng)
    vis = np.ones((10, 17))
    vis[3] = 0.0
    vis[7, :12] = 0.0  # 5 of 17 visible < 30 %
    kp = noisy_keypoints(gt, vis, rng, KeypointNoiseConfig(miss_rate=0.0))
    assert np.all(kp[[3, 7]] == 0)
    assert np.all(np.delete(kp, [3, 7], axis=0)[..., 2] > 0)


# ---------------------------------------------------------------- masks


def test_mask_noise_stays_near_the_boundary():
    import cv2

    yy, xx = np.mgrid[:240, :320]
    mask = (yy - 120) ** 2 / 80**2 + (xx - 160) ** 2 / 50**2 < 1
    cfg = MaskNoiseConfig()
    a = noisy_mask(mask, np.random.default_rng(0), cfg)
    b = noisy_mask(mask, np.random.default_rng(0), cfg)
    np.testing.assert_array_equal(a, b)
    assert mask.sum() > 0 and not np.array_equal(a, mask)
    iou = (a & mask).sum() / (a | mask).sum()
    assert 0.85 < iou < 0.99
    # Every changed pixel lies within max_shift + band (+1 for rounding) of the true boundary.
    reach = cfg.max_shift_px + cfg.edge_band_px + 1
    dist_in = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 5)
    dist_out = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)
    changed = a != mask
    assert np.all(np.maximum(dist_in, dist_out)[changed] <= reach)
    assert not noisy_mask(np.zeros((20, 20), bool), np.random.default_rng(0), cfg).any()
    assert not mask[0, 0] and mask.dtype == bool  # input untouched


# ---------------------------------------------------------------- body prior


@pytest.fixture(scope="module")
def body():
    return load_body_model(None)


def _scene(T: int, rng):
    """A person walking slowly in a circle watched by a camera 3 m away (OpenCV axes)."""
    betas = np.zeros(10)
    betas[:3] = [0.4, -0.2, 0.3]
    yaw = np.linspace(0, 2 * np.pi, T)
    R_go = rot_z(yaw) @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    go = Rotation.from_matrix(R_go).as_rotvec()
    pose = 0.2 * np.sin(np.linspace(0, 20, T))[:, None] * rng.normal(size=(1, 69))
    transl = np.stack([0.5 * np.cos(yaw), 0.5 * np.sin(yaw), np.full(T, 0.9)], -1)
    params = SmplParams(betas, go, pose, transl, fps=30.0)
    # Camera at (-3, 0, 1.5) looking along +x (world): camera z = world x, camera x = -world y.
    R_wc = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    T_wc = np.repeat(make_T(R_wc, [-3.0, 0.0, 1.5])[None], T, 0)
    return params, T_wc


def test_noise_free_prior_is_the_exact_camera_space_body(body):
    rng = np.random.default_rng(0)
    params, T_wc = _scene(20, rng)
    zero = PriorNoiseConfig(pose_std_deg=0, orient_std_deg=0, betas_std=0, depth_rel_std=0, xy_std_m=0)
    prior = body_prior(params, T_wc, body, rng, zero)
    v_world = body.from_params(params, dtype=torch.float64).vertices.numpy()
    v_cam = body.forward(prior.betas, prior.global_orient_cam, prior.body_pose, prior.transl_cam,
                         dtype=torch.float64).vertices.numpy()
    np.testing.assert_allclose(v_cam, apply_T(invert_T(T_wc), v_world), atol=1e-6)
    np.testing.assert_array_equal(prior.frame_ids, np.arange(20))


def test_prior_noise_statistics(body):
    rng = np.random.default_rng(1)
    T = 3000
    params, T_wc = _scene(T, rng)
    cfg = PriorNoiseConfig()
    prior = body_prior(params, T_wc, body, rng, cfg)
    exact = body_prior(params, T_wc, body, rng, PriorNoiseConfig(0, 0, 0, 0, 0))
    J0 = body.pelvis_offset(prior.betas)
    J0_true = body.pelvis_offset(exact.betas)
    pel, pel_true = prior.transl_cam + J0, exact.transl_cam + J0_true
    ratio = pel[:, 2] / pel_true[:, 2]
    assert np.std(ratio) == pytest.approx(cfg.depth_rel_std, rel=0.3)
    assert abs(np.mean(ratio) - 1) < 0.05
    # Along the ray: the pelvis projects where it should (to within the small across-ray error).
    px = 500 * pel[:, :2] / pel[:, 2:]
    px_true = 500 * pel_true[:, :2] / pel_true[:, 2:]
    assert np.median(np.linalg.norm(px - px_true, axis=1)) < 5.0
    d_pose = (Rotation.from_rotvec(np.array(prior.body_pose).reshape(-1, 3))
              * Rotation.from_rotvec(np.array(exact.body_pose).reshape(-1, 3)).inv()).magnitude()
    # Each of 3 components has std s: the angle's RMS is s * sqrt(3).
    rms = np.sqrt(np.mean(d_pose**2))
    assert np.rad2deg(rms) == pytest.approx(cfg.pose_std_deg * np.sqrt(3), rel=0.2)
    assert np.std(prior.betas - exact.betas) == pytest.approx(cfg.betas_std, rel=0.2)
    # Temporally correlated: frame-to-frame change far below the error itself.
    assert np.std(np.diff(prior.betas[:, 0])) < 0.3 * np.std(prior.betas[:, 0] - exact.betas[:, 0])


# ---------------------------------------------------------------- body prior file


def test_body_prior_file_round_trip_and_bad_files(tmp_path):
    rng = np.random.default_rng(0)
    T = 7
    prior = BodyPriorSeq(rng.normal(size=(T, 3)), rng.normal(size=(T, 69)), rng.normal(size=(T, 10)),
                         rng.normal(size=(T, 3)), np.arange(10, 10 + T))
    path = write_body_prior(tmp_path / "p" / "body_prior.npz", prior)
    back = read_body_prior(path)
    for f in dataclasses.fields(BodyPriorSeq):
        np.testing.assert_array_equal(getattr(back, f.name), getattr(prior, f.name))
    with pytest.raises(InputError, match="not found"):
        read_body_prior(tmp_path / "nope.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="readable"):
        read_body_prior(tmp_path / "junk.npz")
    good = dict(np.load(path))
    for broken, match in [
        ({k: v for k, v in good.items() if k != "betas"}, "lacks"),
        ({**good, "version": np.int64(99)}, "version"),
        ({**good, "body_pose": good["body_pose"][:, :60]}, "malformed"),
        ({**good, "transl": np.full((T, 3), np.nan)}, "NaN"),
    ]:
        np.savez(tmp_path / "bad.npz", **broken)
        with pytest.raises(InputError, match=match):
            read_body_prior(tmp_path / "bad.npz")
