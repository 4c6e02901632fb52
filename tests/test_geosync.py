"""Geometric sync, SE(3)/keypoint resampling and the sync record's choice, on truth-fed data.

Two cameras circle a moving skeleton-like point set 90 degrees apart; view 2's frames are taken at
a known (integer or fractional) offset from view 1's. Projections are exact plus Gaussian pixel
noise, so every expected number comes from the construction, not from the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.geometry.interpolate import bracket, interp_keypoints, interp_poses
from embodmocap.geometry.rotations import slerp as slerp_quat
from embodmocap.geometry.transforms import look_at_T, matrix_to_quat, quat_to_matrix, rotation_angle
from embodmocap.sequence.geosync import (
    GeoSyncConfig, epipolar_distance, geometric_sync, midpoint_reprojection_error, shift_costs,
)
from embodmocap.sequence.subframe import resample_view
from embodmocap.sequence.sync_record import decide

FPS = 30.0
K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
J = 17


def joints(t: np.ndarray) -> np.ndarray:
    """(N, J, 3) points at times t (s): a body walking a circle with limbs swinging at 1 Hz."""
    base = np.stack([0.8 * np.cos(0.6 * t), 0.8 * np.sin(0.6 * t), np.ones_like(t)], -1)
    off = np.random.default_rng(1).normal(0, 0.3, (J, 3))
    ph = np.random.default_rng(2).uniform(0, 6, J)
    swing = 0.3 * np.sin(2 * np.pi * t[:, None] + ph)[..., None] * np.array([1.0, 0.6, 0.4])
    return base[:, None] + off + swing


def cameras(t: np.ndarray, az0: float) -> np.ndarray:
    az = az0 + 0.15 * t
    c = np.stack([3.2 * np.cos(az), 3.2 * np.sin(az), 1.5 + 0.05 * np.sin(t)], -1)
    return look_at_T(c, np.tile([0.0, 0.0, 1.0], (len(t), 1)))


def project(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    pc = np.einsum("tji,tnj->tni", T[:, :3, :3], X - T[:, None, :3, 3])
    uv = pc @ K.T
    return uv[..., :2] / uv[..., 2:]


def two_views(offset_frames: float, n: int = 180, noise_px: float = 1.5, seed: int = 0):
    """View 1 frame k at time k/fps; view 2 frame k films the instant k/fps - offset/fps, so the
    instant view 1 films at t is filmed by view 2 at t + offset/fps."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / FPS
    t2 = t - offset_frames / FPS
    T1, T2 = cameras(t, 0.0), cameras(t2, np.pi / 2)
    kp = []
    for T, tt in ((T1, t), (T2, t2)):
        xy = project(T, joints(tt)) + rng.normal(0, noise_px, (n, J, 2))
        kp.append(np.concatenate([xy, np.ones((n, J, 1))], -1))
    return T1, kp[0], t, T2, kp[1], t


# --------------------------------------------------------------------------- two-view geometry


def test_rays_meet_only_at_the_right_pairing():
    T1, kp1, _, T2, kp2, _ = two_views(0.0, n=10, noise_px=0.0)
    err = midpoint_reprojection_error(K, T1[:, None], kp1[..., :2], K, T2[:, None], kp2[..., :2])
    assert err.shape == (10, J) and np.all(err < 1e-6)
    d = epipolar_distance(K, T1[:, None], kp1[..., :2], K, T2[:, None], kp2[..., :2])
    assert np.all(np.abs(d) < 1e-6)
    # Another frame's keypoints in view 2: the rays miss by the motion.
    wrong = midpoint_reprojection_error(K, T1[:-3, None], kp1[:-3, :, :2], K, T2[3:, None], kp2[3:, :, :2])
    assert np.median(wrong) > 0.5


def test_epipolar_distance_matches_a_reference_fundamental_matrix():
    rng = np.random.default_rng(3)
    T1, T2 = cameras(np.array([0.0]), 0.0)[0], cameras(np.array([0.0]), 1.0)[0]
    x1, x2 = rng.uniform(0, 640, (5, 2)), rng.uniform(0, 480, (5, 2))
    # Reference: F from the projection matrices, F = [e2]x P2 P1^+.
    P1 = K @ np.linalg.inv(T1)[:3]
    P2 = K @ np.linalg.inv(T2)[:3]
    C1 = T1[:, 3]
    e2 = P2 @ C1
    ex = np.array([[0, -e2[2], e2[1]], [e2[2], 0, -e2[0]], [-e2[1], e2[0], 0]])
    Fr = ex @ P2 @ np.linalg.pinv(P1)
    for a, b in zip(x1, x2):
        line = Fr @ np.r_[a, 1.0]
        ref = abs(line @ np.r_[b, 1.0]) / np.linalg.norm(line[:2])
        got = abs(float(epipolar_distance(K, T1, a, K, T2, b)))
        assert got == pytest.approx(ref, rel=1e-6)


@pytest.mark.parametrize("offset", [0.0, 4.0, -9.0, 0.4, -0.3, 6.5, -12.75])
def test_geometric_sync_recovers_integer_and_fractional_offsets(offset):
    T1, kp1, t1, T2, kp2, t2 = two_views(offset)
    res = geometric_sync(K, T1, kp1, t1, K, T2, kp2, t2, FPS, search_s=1.0)
    assert res.found and res.message == ""
    assert res.shift == round(offset) or abs(res.shift - offset) <= 1
    assert abs(res.offset_frames - offset) < 0.1, res
    assert res.offset_s == pytest.approx(res.offset_frames / FPS, abs=1e-9)
    assert res.confidence > 0.5 and res.std_frames < 0.1


def test_geometric_sync_is_unbiased_under_heavy_noise():
    # Interpolating noisy samples would favour half frames; the instrument keeps it unbiased.
    errs = []
    for s, o in enumerate([0.0, 0.5, -0.5, 0.25, 0.0, 0.5]):
        T1, kp1, t1, T2, kp2, t2 = two_views(o, noise_px=4.0, seed=s)
        errs.append(geometric_sync(K, T1, kp1, t1, K, T2, kp2, t2, FPS, 1.0).offset_frames - o)
    # (Scoring interpolated keypoints directly was off by 0.3-0.7 frames here.)
    assert abs(np.mean(errs)) < 0.15 and np.max(np.abs(errs)) < 0.4


def test_a_still_performer_gives_no_confident_offset():
    n = 120
    t = np.arange(n) / FPS
    T1, T2 = cameras(t * 0, 0.0), cameras(t * 0, np.pi / 2)
    X = np.repeat(joints(np.zeros(1)), n, axis=0)
    rng = np.random.default_rng(0)
    kp1 = np.concatenate([project(T1, X) + rng.normal(0, 1.5, (n, J, 2)), np.ones((n, J, 1))], -1)
    kp2 = np.concatenate([project(T2, X) + rng.normal(0, 1.5, (n, J, 2)), np.ones((n, J, 1))], -1)
    res = geometric_sync(K, T1, kp1, t, K, T2, kp2, t, FPS, 1.0)
    assert res.confidence < GeoSyncConfig().min_confidence


def test_no_common_keypoints_is_reported_not_guessed():
    T1, kp1, t1, T2, kp2, t2 = two_views(0.0, n=60)
    kp2[..., 2] = 0.0
    res = geometric_sync(K, T1, kp1, t1, K, T2, kp2, t2, FPS, 0.5)
    assert not res.found and "pairs" in res.message and math.isnan(res.offset_s)
    costs, counts = shift_costs(K, T1, kp1, K, T2, kp2, np.array([0, 1]))
    assert np.all(np.isnan(costs)) and np.all(counts == 0)


def test_offset_seconds_follow_the_views_clocks():
    # View 2 drops a frame early on: its frame times, not its indices, give the seconds.
    T1, kp1, t1, T2, kp2, t2 = two_views(2.0)
    keep = np.r_[0:5, 6:len(t2)]
    T2d, kp2d, t2d = T2[keep], kp2[keep], t2[keep]
    res = geometric_sync(K, T1, kp1, t1, K, T2d, kp2d, t2d, FPS, 1.0)
    assert res.offset_s * FPS == pytest.approx(2.0, abs=0.1)


# --------------------------------------------------------------------------- resampling


def test_bracket_and_interp_keypoints():
    t = np.array([0.0, 1.0, 2.0])
    i0, w, ok = bracket(t, np.array([-0.5, 0.0, 0.25, 1.0, 2.0, 2.5]))
    assert i0.tolist() == [0, 0, 0, 1, 1, 1] and np.allclose(w, [0, 0, 0.25, 0, 1, 1])
    assert ok.tolist() == [False, True, True, True, True, False]
    kp = np.array([[[0.0, 0, 1]], [[10.0, 20, 0.5]], [[20.0, 40, 0.0]]])
    out = interp_keypoints(kp, t, np.array([0.5, 1.0, 1.2, 1.7, 3.0]))
    assert np.allclose(out[0], [5, 10, 0.5]) and np.allclose(out[1], [10, 20, 0.5])
    assert np.allclose(out[2], [10, 20, 0.5])  # only the nearer neighbour saw it: taken as is
    assert out[3, 0, 2] == 0.0 and out[4, 0, 2] == 0.0  # only the farther one saw it; outside the span


def test_interp_poses_matches_a_reference_slerp():
    from scipy.spatial.transform import Rotation, Slerp

    rng = np.random.default_rng(5)
    R = Rotation.random(6, random_state=7)
    T = np.tile(np.eye(4), (6, 1, 1))
    T[:, :3, :3] = R.as_matrix()
    T[:, :3, 3] = rng.normal(size=(6, 3))
    t = np.cumsum(rng.uniform(0.5, 1.5, 6))
    q = rng.uniform(t[0], t[-1], 20)
    got, ok = interp_poses(T, t, q)
    ref = Slerp(t, R)(q).as_matrix()
    assert ok.all() and np.all(rotation_angle(np.swapaxes(got[:, :3, :3], 1, 2) @ ref) < 1e-6)
    tr = np.stack([np.interp(q, t, T[:, k, 3]) for k in range(3)], -1)
    assert np.allclose(got[:, :3, 3], tr)
    same, _ = interp_poses(T, t, t)
    assert np.allclose(same, T, atol=1e-9)
    qa = matrix_to_quat(T[:2, :3, :3])
    assert np.allclose(quat_to_matrix(slerp_quat(qa[0], -qa[1], 1.0)), T[1, :3, :3], atol=1e-9)  # double cover


def test_resampling_view2_at_the_true_offset_reproduces_view1_instants():
    offset = 0.4
    T1, kp1, t1, T2, kp2, t2 = two_views(offset, noise_px=0.0)
    kp2r, T2r = resample_view(kp2, T2, t2, t1 + offset / FPS)
    # The resampled view 2 sees view 1's instants: its rays now meet view 1's.
    err_sync = midpoint_reprojection_error(K, T1[1:-1, None], kp1[1:-1, :, :2], K, T2r[1:-1, None], kp2r[1:-1, :, :2])
    err_near = midpoint_reprojection_error(K, T1[1:-1, None], kp1[1:-1, :, :2], K, T2[1:-1, None], kp2[1:-1, :, :2])
    assert np.median(err_sync) < 0.2 * np.median(err_near)
    assert kp2r[-1, :, 2].max() == 0.0  # past view 2's last frame: not seen


# --------------------------------------------------------------------------- the choice


def _record(laser_offset_s, slicing="laser"):
    views = {"v1": {"frame": 10, "confidence": 0.9}, "v2": {"frame": 14, "confidence": 0.8}}
    lv = {v: {"found": laser_offset_s is not None, "confidence": views[v]["confidence"]} for v in views}
    return {"version": 2, "views": views, "slicing": {"source": slicing, "offset_s": 1.0},
            "sources": {"laser": {"views": lv, "offset_s": laser_offset_s}}, "agreement": None,
            "chosen": {"source": slicing, "offset_s": 1.0, "residual_s": 0.0, "residual_frames": 0.0, "final": False},
            "warnings": []}


def _geo(residual_frames, confidence=0.9):
    T1, kp1, t1, T2, kp2, t2 = two_views(residual_frames, n=90)
    res = geometric_sync(K, T1, kp1, t1, K, T2, kp2, t2, FPS, 1.0)
    from dataclasses import replace

    return replace(res, confidence=confidence)


def test_choice_prefers_geometric_when_it_agrees_with_the_laser():
    rec = decide(_record(1.0), _geo(0.4), GeoSyncConfig(), FPS, {"v1": "sync_v1.png"}, "s")
    assert rec["chosen"]["source"] == "geometric" and rec["agreement"]["agree"]
    assert rec["chosen"]["residual_frames"] == pytest.approx(0.4, abs=0.1)
    assert rec["chosen"]["offset_s"] == pytest.approx(1.0 + rec["chosen"]["residual_s"])
    assert rec["warnings"] == [] and rec["chosen"]["final"]


def test_disagreement_is_a_warning_with_both_numbers_and_the_sheets():
    rec = decide(_record(1.0), _geo(3.0, confidence=0.5), GeoSyncConfig(), FPS, {"v1": "/x/sync_v1.png"}, "s")
    assert not rec["agreement"]["agree"]
    w = rec["warnings"][0]
    assert "disagree" in w and "/x/sync_v1.png" in w and "+30.00 frames" in w
    assert rec["chosen"]["source"] == "laser"  # laser confidence 0.8 > geometric 0.5
    rec = decide(_record(1.0), _geo(3.0, confidence=0.95), GeoSyncConfig(), FPS, {}, "s")
    assert rec["chosen"]["source"] == "geometric"


def _manual_record():
    rec = _record(1.0, slicing="manual")
    rec["sources"]["manual"] = {"frames": {"v1": 10, "v2": 14}, "offset_s": 1.0}
    return rec


def test_manual_frames_give_the_integer_and_the_geometry_the_sub_frame_part():
    rec = decide(_manual_record(), _geo(0.3), GeoSyncConfig(), FPS, {}, "s")
    assert rec["chosen"]["source"] == "manual" and rec["chosen"]["residual_frames"] == pytest.approx(0.3, abs=0.1)
    m = rec["sources"]["manual"]
    assert m["subframe_applied"] and m["subframe_frames"] == rec["chosen"]["residual_frames"]
    assert m["geometric_minus_manual_frames"] == pytest.approx(0.3, abs=0.1) and rec["warnings"] == []
    # Turned off in session.toml: measured and recorded, not applied.
    off = decide(_manual_record(), _geo(0.3), GeoSyncConfig(), FPS, {}, "s", subframe_sync=False)
    assert off["chosen"]["residual_s"] == 0.0 and not off["sources"]["manual"]["subframe_applied"]
    assert off["sources"]["manual"]["geometric_minus_manual_frames"] == m["geometric_minus_manual_frames"]
    # An unconfident geometric sync adds nothing.
    low = decide(_manual_record(), _geo(0.3, confidence=0.1), GeoSyncConfig(), FPS, {}, "s")
    assert low["chosen"]["residual_s"] == 0.0 and low["warnings"] == []


def test_manual_frames_the_geometry_contradicts_warn_then_stop_unless_forced():
    rec = decide(_manual_record(), _geo(3.0), GeoSyncConfig(), FPS, {}, "s")
    assert rec["chosen"]["residual_s"] == 0.0 and len(rec["warnings"]) == 1
    w = rec["warnings"][0]
    assert "view v2's sync_frame = 14" in w and "frame 17.0" in w  # the view, the given frame, the estimate
    # Beyond five frames at high confidence: one clear error naming the key that forces the frames.
    with pytest.raises(InputError) as err:
        decide(_manual_record(), _geo(8.0, confidence=0.95), GeoSyncConfig(), FPS, {}, "s")
    msg = str(err.value)
    assert "v2" in msg and "sync_frame = 14" in msg and "frame 22.0" in msg and "sync_force = true" in msg
    forced = decide(_manual_record(), _geo(8.0, confidence=0.95), GeoSyncConfig(), FPS, {}, "s", sync_force=True)
    assert forced["chosen"]["source"] == "manual" and forced["chosen"]["residual_s"] == 0.0 and len(forced["warnings"]) == 1
    # Not confident enough to call the frames wrong: a warning only.
    assert decide(_manual_record(), _geo(8.0, confidence=0.5), GeoSyncConfig(), FPS, {}, "s")["chosen"]["source"] == "manual"


def test_no_source_is_an_error():
    rec = decide(_record(None, slicing="start"), _geo(2.0), GeoSyncConfig(), FPS, {}, "s")
    assert rec["chosen"]["source"] == "geometric" and rec["chosen"]["residual_frames"] == pytest.approx(2.0, abs=0.1)
    with pytest.raises(InputError, match="no laser event"):
        decide(_record(None, slicing="start"), _geo(2.0, confidence=0.1), GeoSyncConfig(), FPS, {}, "s")


def _candidates_record():
    """View 1 went dark twice (frames 40 and 10, alike); view 2 once (frame 14): sliced at the
    best-scoring pair 40/14 (offset -26 frames); the pair 10/14 (offset +4 frames) is the other."""
    rec = _record(-26 / FPS, slicing="candidates")
    rec["slicing"]["offset_s"] = -26 / FPS
    rec["sources"]["laser"]["pairs"] = [
        {"frames": {"v1": 40, "v2": 14}, "offset_s": -26 / FPS, "score": 0.72, "overlap_s": 5.0, "feasible": True},
        {"frames": {"v1": 10, "v2": 14}, "offset_s": 4 / FPS, "score": 0.64, "overlap_s": 6.0, "feasible": True}]
    return rec


def test_the_laser_pair_the_geometry_agrees_with_wins_over_the_best_scoring_one():
    rec = decide(_candidates_record(), _geo(30.4), GeoSyncConfig(), FPS, {}, "s")
    assert rec["sources"]["laser"]["consistent_pair"]["frames"] == {"v1": 10, "v2": 14}
    assert rec["agreement"]["agree"] and rec["chosen"]["source"] == "geometric"
    assert rec["chosen"]["offset_s"] * FPS == pytest.approx(4.4, abs=0.15) and not rec["chosen"]["overrides_laser"]
    assert any("v1 10" in w and "taken over" in w for w in rec["warnings"])
    # Not confident about the offset, the geometry still says which pair's rays meet better: the
    # laser offset of that pair is used (its cost is far lower than the other pair's).
    weak = decide(_candidates_record(), _geo(30.4, confidence=0.1), GeoSyncConfig(), FPS, {}, "s")
    assert weak["chosen"]["source"] == "laser" and weak["chosen"]["residual_frames"] == pytest.approx(30.0)
    c = weak["sources"]["laser"]["pair_costs_px2"]
    assert c[1] < 0.9 * c[0] and any("fit the geometry better" in w for w in weak["warnings"])
    # A flat cost curve tells nothing: the best-scoring pair, with a warning that the choice was blind.
    from dataclasses import replace

    g = _geo(30.4, confidence=0.1)
    blind = decide(_candidates_record(), replace(g, costs=np.where(np.isfinite(g.costs), 50.0, np.nan)), GeoSyncConfig(),
                   FPS, {}, "s")
    assert blind["chosen"]["source"] == "laser" and blind["chosen"]["residual_s"] == 0.0
    assert any("score alike" in w for w in blind["warnings"])
    # The geometry confirms the best-scoring pair (its rays meet far better there): no warning that
    # the choice was blind, and the record says which pair the geometry confirmed.
    sure = decide(_candidates_record(), _geo(0.2, confidence=0.1), GeoSyncConfig(), FPS, {}, "s")
    assert sure["chosen"]["source"] == "laser" and sure["chosen"]["residual_s"] == 0.0
    assert sure["sources"]["laser"]["geometry_confirms"] == {"v1": 40, "v2": 14}
    assert "consistent_pair" not in sure["sources"]["laser"]
    assert not any("score alike" in w for w in sure["warnings"])
    assert "geometry_confirms" not in blind["sources"]["laser"]


def test_a_pair_sharing_a_frame_with_a_pair_the_dot_check_rejected_is_not_revived():
    """The best pair's sightings are 2.3 m apart (one view took something else for the dot): an
    untrusted geometry that prefers another pair sharing one of its frames does not bring the
    laser back (a clear error asks for sync_frame); a pair with other frames in both views can."""
    from embodmocap.sequence.laser_check import DotCheck

    apart = DotCheck(gap_m=2.32, method="depth", limit_m=0.15, same_dot=False)
    weak = _geo(30.4, confidence=0.1)
    with pytest.raises(InputError, match="apart"):
        decide(_candidates_record(), weak, GeoSyncConfig(), FPS, {}, "s", dot_check=apart)
    rec = _candidates_record()
    rec["sources"]["laser"]["pairs"][1]["frames"] = {"v1": 10, "v2": 44}  # no frame shared
    ok = decide(rec, weak, GeoSyncConfig(), FPS, {}, "s", dot_check=apart)
    assert ok["chosen"]["source"] == "laser" and ok["sources"]["laser"]["consistent_pair"]["frames"] == {"v1": 10, "v2": 44}


def test_a_confident_geometry_that_no_laser_pair_agrees_with_replaces_the_laser():
    rec = decide(_record(1.0), _geo(12.0, confidence=0.7), GeoSyncConfig(), FPS, {}, "s")
    assert rec["chosen"]["source"] == "geometric" and rec["chosen"]["overrides_laser"]
    assert rec["chosen"]["residual_frames"] == pytest.approx(12.0, abs=0.15) and rec["chosen"]["confidence"] == 0.7
    assert any("disagree" in w and "the geometric offset is used" in w for w in rec["warnings"])
