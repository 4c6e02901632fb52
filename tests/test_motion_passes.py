"""Stage IV's declared passes (:mod:`embodmocap.motion.passes`): each pass alone on a small
synthetic walk with a known answer, the loop's order and reports, and a switch that changes
exactly what its pass does."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from embodmocap.body.model import load_body_model
from embodmocap.errors import InputError
from embodmocap.geometry.transforms import R_ZUP_YUP, look_at_T
from embodmocap.geometry.triangulation import projection_matrices
from embodmocap.motion.config import MotionConfig
from embodmocap.motion.passes import PASSES, PHASES, Evidence, PassContext, Start, run_passes
from embodmocap.motion.quality import QualityConfig, frame_quality
from embodmocap.motion.swaps import COCO17_SWAP_GROUPS
from embodmocap.types import SmplParams

T = 60
K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
BY_NAME = {p.name: p for p in PASSES}


@pytest.fixture(scope="module")
def walk():
    """60 frames of a body walking along +x (legs and arms swinging, the left arm raised), seen by
    two cameras at different heights; the truth's params and COCO-17 points, the cameras and the
    views' exact 2D keypoints (confidence 0.9)."""
    model = load_body_model(None)
    go = (Rotation.from_euler("z", np.full((T, 1), 0.2)) * Rotation.from_matrix(R_ZUP_YUP)).as_rotvec()
    phase = np.linspace(0, 2 * np.pi, T)
    pose = np.zeros((T, 69))
    pose[:, 0] = 0.5 * np.sin(phase)  # left hip
    pose[:, 3] = -0.5 * np.sin(phase)  # right hip
    pose[:, 9] = 0.4 * (1 + np.cos(phase))  # left knee
    pose[:, 12] = 0.4 * (1 - np.cos(phase))  # right knee
    pose[:, 15 * 3 + 0] = -1.2  # left arm raised forwards (left and right differ)
    pose[:, 16 * 3 + 2] = 1.1  # right arm down
    truth = SmplParams(np.zeros(10), go, pose, np.column_stack([np.linspace(0, 1.5, T), np.zeros(T), np.full(T, 0.9)]),
                       30.0, "neutral")
    with torch.no_grad():
        coco = model.from_params(truth, dtype=torch.float64).coco17.numpy()
    centre = np.array([0.75, 0.0, 1.0])
    T_wc = np.broadcast_to(np.stack([look_at_T(centre + 3.5 * np.array([np.cos(a), np.sin(a), h]), centre)
                                     for a, h in ((0.9, 0.1), (2.2, 0.8))]), (T, 2, 4, 4)).copy()
    P = projection_matrices(K, T_wc)
    uvw = np.einsum("tvab,tjb->tvja", P, np.concatenate([coco, np.ones((T, 17, 1))], axis=-1))
    kp = np.concatenate([uvw[..., :2] / uvw[..., 2:], np.full(uvw.shape[:-1] + (1,), 0.9)], axis=-1)
    return model, truth, coco, T_wc, P, kp


def _ctx(walk, cfg=MotionConfig(), **kw):
    model, truth, coco, T_wc, P, kp = walk
    return PassContext(cfg, ("v1", "v2"), np.stack([K, K]), T_wc, P=P, model=model, **kw)


def _ev(walk, kp=None, **kw):
    kp = walk[5] if kp is None else kp
    return Evidence(kp, np.zeros((T, 2, len(COCO17_SWAP_GROUPS)), dtype=bool), **kw)


def _only(name):
    return (BY_NAME[name],)


def _coco(model, params):
    with torch.no_grad():
        return model.from_params(params, dtype=torch.float64).coco17.numpy()


def _exchange(kp, view, frames, pairs):
    out = kp.copy()
    for a, b in pairs:
        out[frames, view, a], out[frames, view, b] = kp[frames, view, b], kp[frames, view, a]
    return out


def test_passes_are_declared_once_in_phase_order_with_a_documented_switch():
    names = [p.name for p in PASSES]
    assert len(set(names)) == len(names)
    order = list(PHASES)
    assert [order.index(p.phase) for p in PASSES] == sorted(order.index(p.phase) for p in PASSES)
    from embodmocap.io.steps import setting
    for p in PASSES:
        if p.switch is not None:
            setting(MotionConfig(), p.switch)  # a real config field (raises otherwise)


def test_the_loop_reports_every_pass_of_the_phase_in_order_and_skips_what_does_not_apply(walk):
    kp = walk[5][:, :1]
    ctx = PassContext(MotionConfig(), ("v1",), K[None], walk[3][:, :1])  # one view: no swap check
    ev, reports = run_passes("keypoints", _ev(walk, kp[:, :]), ctx)
    assert [r["pass"] for r in reports] == ["label_track", "fix_swaps", "temporal"]
    assert [(r["on"], r["ran"]) for r in reports] == [(True, True), (True, False), (True, True)]
    assert reports[0]["labels_tracked"] == {"v1_arms": 0, "v1_legs": 0} and reports[2]["keypoints_dropped"] == 0
    np.testing.assert_array_equal(ev.keypoints2d, kp)  # clean keypoints: nothing changed
    off = replace(MotionConfig(), fix_swaps=False, temporal=replace(MotionConfig().temporal, enabled=False))
    _, reports = run_passes("keypoints", _ev(walk), _ctx(walk, off))
    assert [(r["on"], r["ran"]) for r in reports] == [(True, True), (False, False), (False, False)]


def test_label_track_undoes_a_view_whose_arm_labels_are_exchanged(walk):
    from embodmocap.motion.label_track import TRACKED_GROUPS

    kp = walk[5]
    bad = _exchange(kp, 0, slice(20, 30), TRACKED_GROUPS["arms"])
    ev, rep = run_passes("keypoints", _ev(walk, bad), _ctx(walk), _only("label_track"))
    np.testing.assert_allclose(ev.keypoints2d, kp)
    assert rep[0]["labels_tracked"]["v1_arms"] > 0 and rep[0]["labels_tracked"]["v2_arms"] == 0


def test_fix_swaps_undoes_swapped_legs_and_flags_them(walk):
    kp = walk[5]
    bad = _exchange(kp, 1, slice(10, 21), COCO17_SWAP_GROUPS["legs"])
    ev, rep = run_passes("keypoints", _ev(walk, bad), _ctx(walk), _only("fix_swaps"))
    np.testing.assert_allclose(ev.keypoints2d, kp)
    g = list(COCO17_SWAP_GROUPS).index("legs")
    assert ev.swapped[10:21, 1, g].all() and ev.swapped.sum() == 11
    assert rep[0]["swaps_undone"]["v2"]["legs"] == 11 and rep[0]["swaps_undone"]["v1"]["legs"] == 0


def _guessed(kp):
    """view 1's left wrist guessed 80 px off (confidence 0.45) in the first four frames, then found."""
    out = kp.copy()
    out[:4, 0, 9, :2] += [80.0, -50.0]
    out[:4, 0, 9, 2] = 0.45
    return out


def test_temporal_drops_a_guessed_run_and_nothing_else(walk):
    bad = _guessed(walk[5])
    ev, rep = run_passes("keypoints", _ev(walk, bad), _ctx(walk), _only("temporal"))
    dropped = ev.keypoints2d[..., 2] == 0
    assert dropped[:4, 0, 9].all() and rep[0]["keypoints_dropped"] == dropped.sum() == 4
    np.testing.assert_array_equal(ev.keypoints2d[..., :2], bad[..., :2])  # only confidences change


def test_switching_a_pass_off_changes_exactly_what_it_does(walk):
    from embodmocap.motion.label_track import TRACKED_GROUPS

    kp = walk[5]
    bad = _exchange(_guessed(kp), 1, slice(10, 21), COCO17_SWAP_GROUPS["legs"])
    on, _ = run_passes("keypoints", _ev(walk, bad), _ctx(walk))
    off, rep = run_passes("keypoints", _ev(walk, bad),
                          _ctx(walk, replace(MotionConfig(), temporal=replace(MotionConfig().temporal, enabled=False))))
    assert not rep[2]["ran"]
    differ = (on.keypoints2d != off.keypoints2d).any(-1)
    assert differ.sum() == 4 and differ[:4, 0, 9].all()  # the guessed run, kept with temporal off
    np.testing.assert_array_equal(on.swapped, off.swapped)
    # The swap is undone either way (by the tracking or the swap check).
    legs = [j for pair in TRACKED_GROUPS["legs"] for j in pair]
    np.testing.assert_allclose(on.keypoints2d[:, :, legs], kp[:, :, legs])


def test_weakest_view_conf_lowers_a_point_to_its_weakest_view(walk):
    kp = walk[5].copy()
    kp[3, 0, 5, 2] = 0.6  # view 1's left shoulder less sure in frame 3
    kp[2, 1, 7, 2] = 0.3  # view 2's left elbow guessed in frame 2 (below kp3d_min_view_conf)
    kp[4, 1, 6, 2] = 0.05  # below the triangulation's threshold: that view was not used
    conf = np.full((T, 17), 0.8)
    cfg = MotionConfig()
    assert cfg.kp3d_conf == "min" and cfg.kp3d_min_view_conf == 0.5
    ev, rep = run_passes("start", _ev(walk, kp, points=walk[2], conf=conf), _ctx(walk, cfg), _only("weakest_view_conf"))
    expect = conf.copy()
    expect[3, 5] = 0.6
    expect[2, 7] = 0.0  # the guess's point leaves the 3D term
    np.testing.assert_array_equal(ev.conf, expect)
    assert rep[0]["points_lowered"] == 2 and rep[0]["points_dropped_guess"] == 1
    # Off (0): the guessed point is only lowered to its weakest view's confidence.
    ev, rep = run_passes("start", _ev(walk, kp, points=walk[2], conf=conf),
                         _ctx(walk, replace(cfg, kp3d_min_view_conf=0.0)), _only("weakest_view_conf"))
    expect[2, 7] = 0.3
    np.testing.assert_array_equal(ev.conf, expect)
    assert rep[0]["points_dropped_guess"] == 0
    # One view (a one-phone sequence's points, lifted with its depth): nothing is triangulated
    # from a guess, so its 0.3 elbow is only lowered.
    model, truth, coco, T_wc, P, _ = walk
    one = PassContext(cfg, ("v1",), K[None], T_wc[:, :1], P=P[:, :1], model=model)
    ev = Evidence(kp[:, 1:], np.zeros((T, 1, len(COCO17_SWAP_GROUPS)), dtype=bool), points=walk[2], conf=conf)
    ev, rep = run_passes("start", ev, one, _only("weakest_view_conf"))
    assert ev.conf[2, 7] == 0.3 and rep[0]["points_dropped_guess"] == 0


def test_bone_gate_drops_a_wrist_off_its_forearm(walk):
    model, truth, coco = walk[:3]
    points = coco.copy()
    points[5:8, 10] += [0.0, 0.35, 0.1]  # right wrist 36 cm off in frames 5-7
    ev, rep = run_passes("start", _ev(walk, points=points, conf=np.full((T, 17), 0.9)), _ctx(walk),
                         _only("bone_gate"))
    gated = ev.conf == 0
    assert gated[5:8, 10].all() and gated.sum() == 3
    assert rep[0]["points_dropped"] == 3 and rep[0]["torso_points_dropped"] == 0


def test_keypoint_start_places_the_body_on_the_points_or_says_why_not(walk):
    model, truth, coco = walk[:3]
    conf = np.full((T, 17), 0.9)
    ev, rep = run_passes("start", _ev(walk, points=coco, conf=conf), _ctx(walk), _only("keypoint_start"))
    assert rep[0]["placed"] and ev.start.init is ev.start.kp_init and ev.start.prior_view is None
    assert np.linalg.norm(_coco(model, ev.start.init) - coco, axis=-1).mean() < 0.03
    blind = coco.copy()
    blind[:, [5, 6, 11, 12]] = np.nan  # no torso anywhere
    with pytest.raises(InputError, match="cannot place a starting body"):
        run_passes("start", _ev(walk, points=blind, conf=conf), _ctx(walk, label="seq0", priors={}),
                   _only("keypoint_start"))


def _camera_prior(model, truth, T_wc):
    """The truth as a camera-space regressor of view 1 would give it (exact)."""
    from types import SimpleNamespace

    R, c = T_wc[:, 0, :3, :3], T_wc[:, 0, :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    go_cam = (Rotation.from_matrix(Rt) * Rotation.from_rotvec(np.array(truth.global_orient))).as_rotvec()
    j0 = model.pelvis_offset(truth.betas)
    transl_cam = np.einsum("tab,tb->ta", Rt, truth.transl + j0 - c) - j0
    return SimpleNamespace(global_orient_cam=go_cam, body_pose=truth.body_pose, betas=np.tile(truth.betas, (T, 1)),
                           transl_cam=transl_cam)


def test_prior_start_moves_the_prior_into_the_world(walk):
    model, truth, coco, T_wc = walk[:4]
    priors = {"v1": (_camera_prior(model, truth, T_wc), np.ones(T, bool)),
              "v2": (_camera_prior(model, truth, T_wc), np.r_[np.ones(T // 2, bool), np.zeros(T - T // 2, bool)])}
    cams = {v: {"T_world_cam": T_wc[:, 0]} for v in ("v1", "v2")}
    ev = _ev(walk, points=coco, conf=np.full((T, 17), 0.9), start=Start(init=None))
    ev, rep = run_passes("start", ev, _ctx(walk, priors=priors, cameras=cams), _only("prior_start"))
    assert ev.start.prior_view == "v1" and rep[0] == {"pass": "prior_start", "on": True, "ran": True, "view": "v1",
                                                        "frames_with_estimate": 1.0}
    assert np.linalg.norm(_coco(model, ev.start.init) - coco, axis=-1).max() < 1e-6
    np.testing.assert_allclose(ev.start.prior_pose, truth.body_pose, atol=1e-12)


def _turned(params, frames, deg):
    go = np.array(params.global_orient)
    go[frames] = (Rotation.from_euler("z", np.radians(deg)) * Rotation.from_rotvec(go[frames])).as_rotvec()
    return replace(params, global_orient=go)


def test_prefer_keypoints_starts_the_frames_where_the_prior_is_off_from_the_keypoints(walk):
    model, truth, coco = walk[:3]
    prior = _turned(truth, slice(5, 10), 180.0)  # the prior's body flipped in frames 5-9
    ev = _ev(walk, points=coco, conf=np.full((T, 17), 0.9),
             start=Start(init=prior, kp_init=truth, prior_view="v1", prior_pose=prior.body_pose))
    ev, rep = run_passes("start", ev, _ctx(walk), _only("prefer_keypoints"))
    worse = np.zeros(T, bool)
    worse[5:10] = True
    np.testing.assert_array_equal(ev.start.prior_weight, (~worse).astype(float))
    np.testing.assert_allclose(ev.start.init.global_orient, truth.global_orient)
    assert rep[0]["frames_from_keypoints"] == 5
    # Without a keypoint start there is nothing to prefer: the pass does not apply.
    _, rep = run_passes("start", replace(ev, start=replace(ev.start, kp_init=None)), _ctx(walk),
                        _only("prefer_keypoints"))
    assert rep[0]["on"] and not rep[0]["ran"]


def test_prior_limbs_takes_the_contradicted_limb_from_the_keypoints(walk):
    from embodmocap.motion.prior_limbs import limb_columns

    model, truth, coco = walk[:3]
    prior_pose = truth.body_pose.copy()
    prior_pose[:, 3 * 15:3 * 16] += [0.0, 0.0, 1.4]  # left shoulder swung ~80 deg in every frame
    init = replace(truth, body_pose=prior_pose)
    ev = _ev(walk, points=coco, conf=np.full((T, 17), 0.9),
             start=Start(init=init, kp_init=truth, prior_view="v1", prior_pose=prior_pose))
    cfg = replace(MotionConfig(), prior_limb_disagree_m=0.1)
    ev, rep = run_passes("start", ev, _ctx(walk, cfg), _only("prior_limbs"))
    assert rep[0]["limbs_from_keypoints"] == T  # the left arm, in every frame
    cols = limb_columns(np.tile([True, False, False, False], (T, 1)))
    np.testing.assert_allclose(ev.start.prior_pose[cols], truth.body_pose[cols])
    np.testing.assert_array_equal(ev.start.init.body_pose, ev.start.prior_pose)
    assert not MotionConfig().prior_limb_disagree_m > 0  # off by default: the loop skips it
    _, rep = run_passes("start", ev, _ctx(walk), _only("prior_limbs"))
    assert not rep[0]["on"]


def test_propagate_carries_a_rejected_limb_start_from_its_neighbours(walk):
    model, truth, coco, T_wc, P, kp = walk
    pose = truth.body_pose.copy()
    pose[20:23, 3 * 18:3 * 19] += [0.0, 1.5, 0.0]  # right elbow bent the wrong way in frames 20-22
    start = replace(truth, body_pose=pose)
    ev = _ev(walk, points=coco, conf=np.full((T, 17), 0.9), start=Start(init=start))
    ev, rep = run_passes("start", ev, _ctx(walk), _only("propagate"))
    err = lambda p: np.linalg.norm(_coco(model, p)[20:23, 10] - coco[20:23, 10], axis=-1)  # noqa: E731
    assert err(start).min() > 0.1 and err(ev.start.init).max() < 0.03
    assert rep[0]["limb_starts"] >= 3


def test_turn_unplaced_faces_unplaceable_frames_the_way_the_views_say(walk):
    model, truth = walk[:2]
    valid = np.arange(T) >= 10
    start = _turned(truth, slice(0, 10), 75.0)  # held the wrong way where the body cannot be placed
    ev = _ev(walk, points=walk[2], conf=np.full((T, 17), 0.9), valid=valid, start=Start(init=start))
    ev, rep = run_passes("start", ev, _ctx(walk), _only("turn_unplaced"))
    yaw = lambda p: np.degrees(Rotation.from_rotvec(np.array(p.global_orient)).as_euler("zyx")[:, 0])  # noqa: E731
    err = np.abs((yaw(ev.start.init) - yaw(truth) + 180) % 360 - 180)
    assert err[:10].max() < 20 and rep[0]["frames_turned"] == 10
    np.testing.assert_array_equal(ev.start.init.global_orient[10:], truth.global_orient[10:])
    # A prior start keeps the prior's own orientation: the pass does not apply.
    _, rep = run_passes("start", replace(ev, start=Start(init=start, prior_view="v1")), _ctx(walk),
                        _only("turn_unplaced"))
    assert not rep[0]["ran"]


def test_edge_repair_carries_a_contradicted_leg_at_the_start_from_the_first_fine_frame(walk):
    model, truth, coco, T_wc, P, kp = walk
    qcfg = QualityConfig(repair_frames=5)
    cfg = replace(MotionConfig(), quality=qcfg)
    pose = truth.body_pose.copy()
    pose[:3, 3 * 3:3 * 4] += [1.2, 0.0, 0.0]  # left knee bent far off in the first three frames

    def quality_of(p):
        return frame_quality(_coco(model, p), np.stack([K, K]), T_wc, kp, kp, coco, None, ("v1", "v2"), qcfg)

    fitted = replace(truth, body_pose=pose)
    ev = _ev(walk, points=coco, valid=np.ones(T, bool), params=fitted, quality=quality_of(fitted))
    ev, rep = run_passes("fitted", ev, _ctx(walk, cfg, quality_of=quality_of))
    err = lambda p: np.linalg.norm(_coco(model, p)[:3, 15] - coco[:3, 15], axis=-1)  # noqa: E731 (left ankle)
    assert err(fitted).min() > 0.3 and err(ev.params).max() < 0.12  # the leg moves: frame 3's is near, not exact
    assert rep[0]["limb_frames_carried"] == 3
    # The left leg's local rotations (hip, knee, ankle, foot) are frame 3's; nothing else moved.
    leg = np.concatenate([np.arange(3 * (j - 1), 3 * j) for j in (1, 4, 7, 10)])
    np.testing.assert_array_equal(ev.params.body_pose[:3][:, leg], np.tile(pose[3, leg], (3, 1)))
    rest = np.setdiff1d(np.arange(69), leg)
    np.testing.assert_array_equal(ev.params.body_pose[:, rest], pose[:, rest])
    np.testing.assert_array_equal(ev.params.body_pose[3:], truth.body_pose[3:])
    assert not ev.quality.suspect[:3].any()
    # Off by default: the fitted motion is left as it is.
    same, rep = run_passes("fitted", replace(ev, params=fitted), _ctx(walk, quality_of=quality_of))
    assert same.params is fitted and not rep[0]["on"]
