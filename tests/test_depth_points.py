"""Issue 29: a limb joint that only one view sees (the other view's detection too weak to
triangulate) is placed with the seeing view's depth on the person mask, near the true joint, where
the triangulation had nothing or a point filled over the gap far off; joints both views see, views
without masks and the switch off leave the points as they were."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from embodmocap.motion.depth_points import DepthPointsConfig, one_view_pairs, place_one_view_joints
from test_free_space import K, _keypoints, body  # noqa: F401 - fixture
from test_seen_surface import _scene

CFG = DepthPointsConfig(min_conf=0.5, other_max_conf=0.3)


def _inputs(body, frames: int = 3):
    """The true body's COCO points (17, 3), the triangulation as two views leave it (view 2 blind
    to the left elbow and wrist: those points filled over the gap, 15 cm off), the views'
    detections, cameras and depth (with masks) per view."""
    verts, kp3, weights = body
    depth, masks, kp2, Twc = _scene(body, frames)
    kp2[:, 1, 9, 2] = 0.2  # view 2 guesses the left wrist, too weakly to triangulate
    points = np.stack([kp3] * frames).astype(np.float64)
    points[:, [7, 9]] += [0.0, 0.15, 0.0]  # what a fill over the gap left there
    conf = np.full((frames, 17), 0.9)
    conf[:, [7, 9]] = 0.2
    filled = np.zeros((frames, 17), dtype=bool)
    filled[:, [7, 9]] = True
    views = [(depth[v], (640, 480), masks[v]) for v in range(2)]
    return kp3, points, conf, filled, kp2, Twc, views


def test_a_joint_only_one_view_sees_is_placed_at_its_depth_near_the_truth(body):
    kp3, points, conf, filled, kp2, Twc, views = _inputs(body)
    who = one_view_pairs(kp2, CFG)
    assert (who[:, [7, 9]] == 0).all()  # view 1 alone sees the left elbow and wrist
    assert (np.delete(who, [7, 9], axis=1) == -1).all()  # everything else both views see
    p, c, f, placed = place_one_view_joints(points, conf, filled, kp2, np.stack([K, K]), Twc, views, CFG)
    assert placed[:, [7, 9]].all() and placed.sum() == 2 * len(points)
    err = np.linalg.norm(p[:, [7, 9]] - kp3[[7, 9]], axis=-1)
    # Against 15 cm before: the surface view 1 measured, a limb's half thickness further on.
    assert err.max() < 0.035, err
    assert np.allclose(c[:, [7, 9]], CFG.conf_scale * 0.9) and not f[:, [7, 9]].any()
    # Joints both views see keep their triangulated points, confidences and flags.
    rest = np.delete(np.arange(17), [7, 9])
    assert np.array_equal(p[:, rest], points[:, rest]) and np.array_equal(c[:, rest], conf[:, rest])
    assert np.array_equal(f[:, rest], filled[:, rest])


def test_no_masks_no_depth_or_off_leaves_the_points(body):
    kp3, points, conf, filled, kp2, Twc, views = _inputs(body)
    Ks = np.stack([K, K])
    no_masks = [(d, s, None) for d, s, _ in views]
    for args in ((no_masks, CFG), ([None, None], CFG), (views, replace(CFG, min_conf=0.95))):
        p, c, f, placed = place_one_view_joints(points, conf, filled, kp2, Ks, Twc, args[0], args[1])
        assert not placed.any()
        assert np.array_equal(p, points) and np.array_equal(c, conf) and np.array_equal(f, filled)


def test_a_joint_hidden_from_the_seeing_views_depth_is_not_placed(body):
    """A detection off the person (the mask says background there) has no depth to read."""
    kp3, points, conf, filled, kp2, Twc, views = _inputs(body)
    kp2[:, 0, 9, :2] += [150.0, 0.0]  # view 1's left wrist detection 150 px off the body
    p, c, f, placed = place_one_view_joints(points, conf, filled, kp2, np.stack([K, K]), Twc, views, CFG)
    assert not placed[:, 9].any() and placed[:, 7].all()
    assert np.array_equal(p[:, 9], points[:, 9])


def test_by_default_a_leg_point_a_weak_second_view_triangulates_is_kept_an_arm_guess_is_not(body):
    """The other view's 0.2 detection is at the triangulation's threshold (0.1) or above. By default
    an arm joint guessed that weakly is placed by the view that sees it (``arm_other_max_conf``
    0.5: the hard detector's guess of a hidden elbow or wrist), a leg joint keeps its triangulated
    point (``other_max_conf`` 0.1)."""
    kp3, points, conf, filled, kp2, Twc, views = _inputs(body)
    kp2[:, 1, 13, 2] = 0.2  # view 2 guesses the left knee too
    cfg = DepthPointsConfig()
    assert cfg.other_max_conf == 0.1 and cfg.arm_other_max_conf == 0.5 and cfg.min_conf > 0
    p, c, f, placed = place_one_view_joints(points, conf, filled, kp2, np.stack([K, K]), Twc, views, cfg)
    assert placed[:, [7, 9]].all() and not placed[:, 13].any() and placed.sum() == 2 * len(points)
    assert np.linalg.norm(p[:, [7, 9]] - kp3[[7, 9]], axis=-1).max() < 0.035
    assert np.array_equal(p[:, 13], points[:, 13])
    # With the arms' bound at the legs' (0.1), the guessed wrist keeps its triangulated point.
    p, c, f, placed = place_one_view_joints(points, conf, filled, kp2, np.stack([K, K]), Twc, views,
                                            replace(cfg, arm_other_max_conf=0.1))
    assert placed[:, 7].all() and not placed[:, 9].any() and placed.sum() == len(points)
    assert np.array_equal(p[:, 9], points[:, 9])
