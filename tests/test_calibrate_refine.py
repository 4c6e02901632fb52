"""Joint refinement: recovery of known perturbed offsets on a synthetic box room."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from embodmocap.calibrate import losses as L
from embodmocap.calibrate.refine import RefineConfig, ViewData, refine_offsets
from embodmocap.geometry.transforms import invert_T, look_at_T, make_T, rot_z

W, H = 640, 480
K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
ROOM = (np.array([-3.0, -2.5, 0.0]), np.array([3.2, 2.4, 2.8]))


def box_mesh(lo, hi):
    """Vertices (8, 3) and faces (12, 3) of an axis-aligned box."""
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = [[a, b, c] for a, b, c, d in quads] + [[a, c, d] for a, b, c, d in quads]
    return v, np.array(f)


def trajectory(phase, n=40):
    s = np.linspace(0, 1, n)
    ang = phase + 0.8 * s
    c = np.stack([1.8 * np.cos(ang), 1.6 * np.sin(ang), 1.3 + 0.1 * np.sin(6 * s)], -1)
    return np.stack([look_at_T(ci, np.array([0.2, 0.0, 1.0])) for ci in c])


def in_view(T_world_cam, pts):
    """Camera points (N, 3) of world points and which project inside the image."""
    p = (pts - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    z = np.maximum(p[:, 2], 1e-9)
    u, v = K[0, 0] * p[:, 0] / z + K[0, 2], K[1, 1] * p[:, 1] / z + K[1, 2]
    ok = (p[:, 2] > 0.2) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    return p, np.stack([u, v], -1), ok


def offset(yaw_deg, t):
    return make_T(rot_z(np.radians(yaw_deg)), np.asarray(t, dtype=np.float64))


def make_world(noise=0.0, outliers=0.0, seed=0, views=("v1", "v2"), reproj_true=None, n=40, drift=None, phase=None):
    """ViewData of perturbed views, the scene, the track pairs and the true corrections.

    ``phase``: view 2 films this many frames later than view 1 (its track points are the
    performer's that much later) and the pairs carry each point's identity; None: same instants,
    no identities.

    ``drift``: view -> (T, 4, 4) a VIO error that changes frame by frame (world side, on top of
    the rigid one): the views' cameras are then ``inv(truth) @ inv(drift[t]) @ T_true[t]``."""
    rng = np.random.default_rng(seed)
    v, f = box_mesh(*ROOM)
    scene = L.ScenePoints.from_mesh(v, f, n_points=30000, seed=1)
    wall_pts = L.ScenePoints.from_mesh(v, f, n_points=60000, seed=2).points.numpy()
    sfm_pts = L.ScenePoints.from_mesh(v, f, n_points=1500, seed=3).points.numpy()
    truth = {"v1": offset(1.5, [0.06, -0.08, 0.03]), "v2": offset(-2.0, [-0.09, 0.05, -0.04])}
    phases = {"v1": 0.0, "v2": math.pi}
    T_true = {k: trajectory(phases[k], n) for k in views}
    out = {}
    for k in views:
        frames_c, pc, frames_m, xy, xyz = [], [], [], [], []
        for t in range(0, n, 4):
            p, _, ok = in_view(T_true[k][t], wall_pts)
            pick = rng.choice(np.nonzero(ok)[0], 150, replace=False)
            pc.append(p[pick] + noise * rng.standard_normal((150, 3)))
            frames_c.append(np.full(150, t))
        T_m = T_true[k] if reproj_true is None else reproj_true @ T_true[k]
        for t in range(0, n, 2):
            _, uv, ok = in_view(T_m[t], sfm_pts)
            pick = rng.choice(np.nonzero(ok)[0], 25, replace=False)
            xy.append(uv[pick] + noise * 100 * rng.standard_normal((25, 2)))
            xyz.append(sfm_pts[pick])
            frames_m.append(np.full(25, t))
        xy = np.concatenate(xy)
        bad = rng.random(len(xy)) < outliers
        xy[bad] = rng.uniform([0, 0], [W, H], (int(bad.sum()), 2))
        T_world_vio = invert_T(truth[k])  # the true VIO world is the identity here
        out[k] = ViewData(
            T_world_cam=invert_T(truth[k]) @ (T_true[k] if drift is None else invert_T(drift[k]) @ T_true[k]),
            K=K,
            background=L.BackgroundCloud(*map(_t, (np.concatenate(frames_c), np.concatenate(pc)))),
            matches=L.Matches2D3D.from_arrays(np.concatenate(frames_m), xy, np.concatenate(xyz)),
            T_world_vio_init=T_world_vio,
        )
    tracks = None
    if len(views) == 2:
        def performer(s):
            centre = np.stack([0.2 + 0.3 * np.sin(3 * s), 0.3 * np.cos(3 * s), 1.0 + 0 * s], -1)
            return (centre[:, None] + body[None]).reshape(-1, 3)  # (T * 12, 3)

        s = np.linspace(0, 1, n)
        body = rng.normal(0, 0.25, (12, 3))
        frames = np.repeat(np.arange(n), 12)
        pw = performer(s)
        pw_b = pw if phase is None else performer(s + phase * (s[1] - s[0]))
        pa = np.einsum("nji,nj->ni", T_true["v1"][frames, :3, :3], pw - T_true["v1"][frames, :3, 3])
        pb = np.einsum("nji,nj->ni", T_true["v2"][frames, :3, :3], pw_b - T_true["v2"][frames, :3, 3])
        pa += noise * rng.standard_normal(pa.shape)
        pb += noise * rng.standard_normal(pb.shape)
        bad = rng.random(len(pa)) < outliers
        pa[bad] += rng.normal(0, 0.5, (int(bad.sum()), 3))
        ids = None if phase is None else np.tile(np.arange(12), n)
        tracks = L.make_track_pairs(("v1", "v2"), frames, pa, pb, np.full(len(frames), 0.9), ids)
    return out, scene, tracks, {k: truth[k] for k in views}


def _t(a):
    import torch

    return torch.as_tensor(a)


def errors(result, truth):
    """Max translation (m) and yaw (deg) error of the refined corrections over views."""
    dt = max(np.linalg.norm(result.views[k].T_delta[:3, 3] - truth[k][:3, 3]) for k in truth)
    dyaw = max(
        abs(math.degrees(math.atan2(truth[k][1, 0], truth[k][0, 0]) - result.views[k].yaw_delta_rad)) for k in truth
    )
    return dt, dyaw


@pytest.fixture(scope="module")
def clean():
    return make_world()


@pytest.mark.parametrize("solver", ["adam", "lm"])
def test_recovers_perturbed_offsets_clean(clean, solver):
    views, scene, tracks, truth = clean
    res = refine_offsets(views, RefineConfig(solver=solver), scene=scene, tracks=tracks)
    dt, dyaw = errors(res, truth)
    assert dt < 0.005 and dyaw < 0.05, (dt, dyaw)
    assert res.solver == solver and not res.diverged and res.warnings == ()
    assert res.loss_after < 0.01 * res.loss_before
    assert set(res.terms_after) == {"track", "chamfer/v1", "chamfer/v2", "reproj/v1", "reproj/v2"}
    for k in truth:  # the refined VIO offset is the identity (true VIO world = scene world here)
        np.testing.assert_allclose(res.views[k].T_world_vio, np.eye(4), atol=0.01)
        np.testing.assert_allclose(res.views[k].T_world_cam, res.views[k].T_delta @ views[k].T_world_cam)


def test_adam_and_lm_agree_and_both_keeps_the_better(clean):
    views, scene, tracks, truth = clean
    res = refine_offsets(views, RefineConfig(solver="both"), scene=scene, tracks=tracks)
    adam, lm = res.runs["adam"], res.runs["lm"]
    assert np.max(np.abs(adam.x - lm.x)) < 2e-3
    assert res.loss_after == pytest.approx(min(adam.loss_final, lm.loss_final), rel=1e-9)
    assert res.solver == min(res.runs.values(), key=lambda r: r.loss_final).name


def test_degrades_gracefully_with_noise_and_outliers():
    views, scene, tracks, truth = make_world(noise=0.01, outliers=0.1, seed=4)
    res = refine_offsets(views, RefineConfig(solver="both"), scene=scene, tracks=tracks)
    dt, dyaw = errors(res, truth)
    assert dt < 0.015 and dyaw < 0.2, (dt, dyaw)
    assert not res.diverged and res.warnings == ()
    # L2 without robust kernels is pulled by the outliers: the robust kernels must help
    l2 = RefineConfig(solver="lm", track_kernel="l2", chamfer_kernel="l2", reproj_kernel="l2")
    dt2, _ = errors(refine_offsets(views, l2, scene=scene, tracks=tracks), truth)
    assert dt < dt2


@pytest.mark.parametrize("solver", ["adam", "lm"])
def test_single_view_mode(solver):
    views, scene, tracks, truth = make_world(views=("v1",), seed=5)
    assert tracks is None
    res = refine_offsets(views, RefineConfig(solver=solver), scene=scene)
    dt, dyaw = errors(res, truth)
    assert dt < 0.005 and dyaw < 0.05, (dt, dyaw)
    assert "track" not in res.terms_after


def test_tracks_of_a_missing_view_are_ignored(clean):
    views, scene, tracks, truth = clean
    res = refine_offsets({"v1": views["v1"]}, RefineConfig(solver="lm"), scene=scene, tracks=tracks)
    assert "track" not in res.terms_after
    assert errors(res, {"v1": truth["v1"]})[0] < 0.005


def test_contradictory_terms_are_reported():
    # registered matches say the camera is 30 cm elsewhere than the depth clouds do
    views, scene, _, truth = make_world(views=("v1",), seed=6, reproj_true=offset(0.0, [0.3, 0.0, 0.0]))
    res = refine_offsets(views, RefineConfig(solver="lm"), scene=scene)
    assert any(w.startswith("chamfer/v1") or w.startswith("reproj/v1") for w in res.warnings), res.warnings
    tight = refine_offsets(views, RefineConfig(solver="lm", max_translation_m=0.02), scene=scene)
    assert tight.diverged and "v1 moved" in tight.message


def test_loss_that_rises_is_flagged(clean):
    views, scene, tracks, _ = clean
    # an absurd Adam step size overshoots and never settles
    cfg = RefineConfig(solver="adam", adam_lr=3.0, adam_lr_final=3.0, adam_iterations=5, adam_clip_norm=0)
    res = refine_offsets(views, cfg, scene=scene, tracks=tracks)
    assert res.diverged and res.message


def test_nothing_to_refine_raises():
    with pytest.raises(ValueError, match="nothing to refine"):
        refine_offsets({"v1": ViewData(T_world_cam=trajectory(0.0), K=K)})
    views, _, _, _ = make_world(views=("v1",))
    with pytest.raises(ValueError, match="solver"):
        refine_offsets(views, replace(RefineConfig(), solver="sgd"))


def test_drift_knots_follow_a_vio_error_that_grows_along_the_view():
    # Each view's VIO drifts by 4 cm and 0.4 deg over its 120 frames (a handheld track's scale error
    # and path drift): no rigid offset fits every frame, the drift knots do.
    n = 120
    s = np.linspace(-0.5, 0.5, n)
    drift = {"v1": np.stack([offset(0.4 * x, [0.04 * x, -0.03 * x, 0.01 * x]) for x in s]),
             "v2": np.stack([offset(-0.3 * x, [-0.02 * x, 0.04 * x, 0.0]) for x in s])}
    views, scene, tracks, truth = make_world(n=n, drift=drift, seed=7)
    true_cams = {k: trajectory({"v1": 0.0, "v2": math.pi}[k], n) for k in truth}

    def centre_err_cm(res):
        return max(100 * np.median(np.linalg.norm(res.views[k].T_world_cam[:, :3, 3] - true_cams[k][:, :3, 3], axis=1))
                   for k in truth)

    rigid = refine_offsets(views, RefineConfig(solver="lm", drift_knot_frames=0), scene=scene, tracks=tracks)
    knots = refine_offsets(views, RefineConfig(solver="lm", drift_knot_frames=30), scene=scene, tracks=tracks)
    assert set(knots.terms_after) >= {"drift/v1", "drift/v2"} and len(knots.views["v1"].knot_frames) == 5
    assert not knots.diverged
    assert centre_err_cm(rigid) > 0.8, centre_err_cm(rigid)
    assert centre_err_cm(knots) < 0.3, centre_err_cm(knots)
    # The per-frame cameras are the knots' corrections, frame by frame (as calibration.json stores them).
    from embodmocap.calibrate.drift import drift_transforms

    o = knots.views["v1"]
    D = drift_transforms(o.knot_frames, o.knots, o.pivot, n)
    np.testing.assert_allclose(o.T_world_cam, D @ views["v1"].T_world_cam, atol=1e-12)


def test_track_phase_is_fitted_instead_of_moving_the_views():
    # View 2 films 0.45 frame after view 1 (the performer moves ~2 cm a frame). With only the
    # cross-view tracks and view 1's terms to place it, a frame-paired track term shifts view 2 by
    # the performer's motion over that fraction; fitting the phase keeps it where it belongs.
    views, scene, tracks, truth = make_world(seed=8, phase=0.45)
    views = {"v1": views["v1"], "v2": replace(views["v2"], background=None, matches=None)}
    cfg = RefineConfig(solver="lm", drift_knot_frames=0, track_phase=True)
    off = refine_offsets(views, replace(cfg, track_phase=False), scene=scene, tracks=tracks)
    on = refine_offsets(views, cfg, scene=scene, tracks=tracks)
    assert off.phase_frames is None and on.phase_frames == pytest.approx(0.45, abs=0.02)
    (dt_off, yaw_off), (dt_on, yaw_on) = errors(off, truth), errors(on, truth)
    assert dt_off > 0.002 and yaw_off > 0.3, (dt_off, yaw_off)
    assert dt_on < 0.001 and yaw_on < 0.1, (dt_on, yaw_on)
    # With drift knots (the phase's own column of the knot Jacobian) the knots take up the slow part
    # of the performer's motion, so less of the phase is seen, but it still helps.
    knots = {p: refine_offsets(views, replace(cfg, drift_knot_frames=15, track_phase=p), scene=scene, tracks=tracks)
             for p in (False, True)}
    assert 0.1 < knots[True].phase_frames < 0.5
    assert errors(knots[True], truth)[0] < 0.7 * errors(knots[False], truth)[0]


def test_track_steps_link_each_point_to_its_neighbouring_frames():
    frames = np.array([0, 0, 1, 3, 3, 1])
    track = np.array([0, 1, 0, 0, 1, 2])
    st = L.track_steps(frames, track)
    assert st.tolist() == [[-1, 2], [-1, 4], [0, 3], [2, -1], [1, -1], [-1, -1]]


def test_knot_frames_and_basis():
    from embodmocap.calibrate.drift import knot_basis, knot_frames

    assert knot_frames(100, 0).tolist() == [0] and knot_frames(80, 45).tolist() == [0]
    k = knot_frames(181, 45)
    assert k[0] == 0 and k[-1] == 180 and np.diff(k).max() <= 45 and len(k) == 5
    B = knot_basis(181, k)
    np.testing.assert_allclose(B.sum(1), 1.0)
    np.testing.assert_allclose(B[k], np.eye(len(k)))
    np.testing.assert_allclose(B @ k.astype(float), np.arange(181))  # linear in between


def test_world_cameras_and_drift_corrected_views_agree():
    # calibration.json's drift record -> per-frame cameras; the views handed to the geometric sync
    # carry the same cameras through the one T_world_vio.
    from embodmocap.calibrate import solve
    from embodmocap.calibrate.drift import drift_transforms
    from embodmocap.io.stage_files import CameraFile

    n = 100
    T_vio = trajectory(0.3, n)
    T_reg = offset(20.0, [0.5, -1.0, 0.1])
    kf = np.array([0, 33, 66, 99])
    knots = np.array([[0.001, 0.01, 0.0, 0.0], [0.0, -0.01, 0.02, 0.0], [-0.002, 0.0, 0.01, 0.005], [0.003, 0.02, -0.01, 0.0]])
    pivot = (T_reg @ T_vio)[:, :3, 3].mean(0)
    T_mean = offset(2.0, [0.01, 0.0, 0.0]) @ T_reg
    vr = {"T_world_vio_registration": T_reg.tolist(), "T_world_vio": T_mean.tolist(),
          "drift": {"knot_frames": kf.tolist(), "knots": knots.tolist(), "pivot": pivot.tolist()}}
    want = drift_transforms(kf, knots, pivot, n) @ T_reg @ T_vio
    np.testing.assert_allclose(solve.world_cameras(vr, T_vio), want, atol=1e-12)
    np.testing.assert_allclose(drift_transforms(kf, knots, pivot, n)[kf][:, :3, 3] - pivot
                               + np.einsum("nij,j->ni", drift_transforms(kf, knots, pivot, n)[kf][:, :3, :3], pivot),
                               knots[:, 1:], atol=1e-12)  # the knots' translations, pivot form
    cams = CameraFile(version=np.int64(1), K=K, width=np.int64(W), height=np.int64(H), T_world_cam=T_vio,
                      raw_frames=np.arange(n))
    views = {"v1": solve.ViewInputs(cameras=cams, keypoints=np.zeros((n, 17, 3)), depth_m=lambda t: None)}
    fixed = solve.drift_corrected(views, {"views": {"v1": vr}})
    np.testing.assert_allclose(T_mean @ fixed["v1"].cameras.T_world_cam, want, atol=1e-9)
    rigid = {k: v for k, v in vr.items() if k != "drift"}
    np.testing.assert_allclose(solve.world_cameras(rigid, T_vio), T_mean @ T_vio)
    assert solve.drift_corrected(views, {"views": {"v1": rigid}})["v1"] is views["v1"]
