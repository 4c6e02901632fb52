"""Camera trajectories, VIO drift and IMU of the synthetic studio."""

from __future__ import annotations

import numpy as np
import pytest

from embodmocap.geometry.transforms import invert_T, is_rigid, make_T, rot_z, rotation_angle
from embodmocap.synth import trajectory as tr
from embodmocap.synth.scene import build_scene

FPS = 30.0


def _rot_speed_deg_s(T):
    dR = np.swapaxes(T[:-1, :3, :3], 1, 2) @ T[1:, :3, :3]
    return np.rad2deg(rotation_angle(dR)) * FPS


def _performer_path(spec, n, rng):
    """A wandering pelvis path inside the walk area (what the motion part produces)."""
    lo, hi = spec.walk_area_min_xy, spec.walk_area_max_xy
    t = np.arange(n) / FPS
    ph = rng.uniform(0, 2 * np.pi, 2)
    xy = (lo + hi) / 2 + (hi - lo) / 2 * 0.9 * np.column_stack([np.sin(0.4 * t + ph[0]), np.sin(0.27 * t + ph[1])])
    return np.column_stack([xy, np.full(n, 0.92)])


def _inside_furniture(spec, xy, grow=0.0):
    hit = np.zeros(len(xy), bool)
    for f in spec.furniture.values():
        c, s = np.cos(f.yaw), np.sin(f.yaw)
        rel = xy - f.centre_xy
        lx, ly = c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]
        hit |= (np.abs(lx) < f.size[0] / 2 + grow) & (np.abs(ly) < f.size[1] / 2 + grow)
    return hit


@pytest.mark.parametrize("preset,seed", [("indoor", 0), ("indoor", 1), ("outdoor", 2)])
def test_scene_walk_is_smooth_inside_and_looks_at_the_room(preset, seed):
    built = build_scene(preset, np.random.default_rng(seed))
    spec = built.spec
    T = tr.scene_walk(spec, 20.0, FPS, np.random.default_rng(seed))
    assert T.shape == (600, 4, 4) and np.all(is_rigid(T))
    c = T[:, :3, 3]
    assert np.all(c[:, :2] > spec.floor_min_xy + 0.3) and np.all(c[:, :2] < spec.floor_max_xy - 0.3)
    assert not _inside_furniture(spec, c[:, :2], grow=0.1).any()
    assert np.all((c[:, 2] > 1.2) & (c[:, 2] < 1.6))
    speed = np.linalg.norm(np.diff(c, axis=0), axis=1) * FPS
    assert 0.25 < speed.mean() < 0.55 and np.percentile(speed, 99) < 0.9
    assert np.percentile(_rot_speed_deg_s(T), 99) < 120
    # OpenCV axes: the optical axis never points more than ~45 deg below the horizon, x is level.
    z = T[:, :3, 2]
    assert np.all(np.rad2deg(np.arcsin(-z[:, 2])) < 45)
    assert np.all(np.abs(T[:, 2, 0]) < 0.05)
    # It turns around: the viewing direction covers the full circle.
    yaw = np.arctan2(z[:, 1], z[:, 0])
    assert len(np.unique(np.floor((yaw + np.pi) / (np.pi / 4)))) == 8


@pytest.mark.parametrize("preset,seed", [("indoor", 3), ("indoor", 4), ("outdoor", 5)])
def test_follow_views_keep_distance_separation_and_room(preset, seed):
    built = build_scene(preset, np.random.default_rng(seed))
    spec = built.spec
    rng = np.random.default_rng(seed)
    P = _performer_path(spec, 450, rng)
    v1, v2 = tr.follow_views(spec, P, FPS, rng, tr.FollowConfig())
    assert v1.shape == v2.shape == (450, 4, 4) and np.all(is_rigid(v1)) and np.all(is_rigid(v2))
    lo, hi = spec.floor_min_xy, spec.floor_max_xy
    azimuths = []
    for T in (v1, v2):
        c = T[:, :3, 3]
        d = np.linalg.norm(c[:, :2] - P[:, :2], axis=1)
        assert np.all((d >= 1.5) & (d <= 4.0)), (d.min(), d.max())
        assert np.all((c[:, :2] > lo + 0.3) & (c[:, :2] < hi - 0.3))
        assert np.all((c[:, 2] >= 1.3) & (c[:, 2] <= 1.6))
        assert np.percentile(np.linalg.norm(np.diff(c, axis=0), axis=1) * FPS, 99) < 2.0
        assert np.percentile(_rot_speed_deg_s(T), 99) < 90
        # Aimed at the performer: the pelvis projects near the image centre.
        pc = np.einsum("tji,tj->ti", T[:, :3, :3], P - c)
        assert np.all(pc[:, 2] > 1.0)
        assert np.percentile(np.degrees(np.arctan(np.linalg.norm(pc[:, :2], axis=1) / pc[:, 2])), 95) < 8
        azimuths.append(np.arctan2(c[:, 1] - P[:, 1], c[:, 0] - P[:, 0]))
        assert _inside_furniture(spec, c[:, :2]).mean() < 0.05
    sep = np.degrees(np.abs(np.angle(np.exp(1j * (azimuths[0] - azimuths[1])))))
    assert np.all((sep >= 60) & (sep <= 120)), (sep.min(), sep.max())


def test_random_T_scene_vio_is_gravity_aligned():
    for s in range(20):
        T = tr.random_T_scene_vio(np.random.default_rng(s), max_offset_m=3.0)
        assert is_rigid(T)
        assert np.allclose(T[:3, 2], [0, 0, 1]) and np.allclose(T[2, :3], [0, 0, 1])
        assert np.all(np.abs(T[:2, 3]) <= 3.0) and abs(T[2, 3]) <= 1.0
    yaws = [np.arctan2(tr.random_T_scene_vio(np.random.default_rng(s))[1, 0], tr.random_T_scene_vio(np.random.default_rng(s))[0, 0]) for s in range(50)]
    assert np.ptp(yaws) > np.pi  # spread over the circle


def test_drift_is_small_slow_and_starts_at_zero():
    spec = build_scene("indoor", np.random.default_rng(0)).spec
    T = tr.scene_walk(spec, 10.0, FPS, np.random.default_rng(0))
    cfg = tr.DriftConfig()
    ends_t, ends_yaw = [], []
    for s in range(40):
        Td = tr.add_drift(T, FPS, np.random.default_rng(s), cfg)
        assert np.all(is_rigid(Td))
        D = Td @ invert_T(T)  # the drift transform per frame
        assert np.allclose(D[0], np.eye(4), atol=1e-12)
        assert np.allclose(D[:, :3, 2], [0, 0, 1], atol=1e-9)  # still gravity-aligned (yaw only)
        step = np.linalg.norm(np.diff(Td[:, :3, 3] - T[:, :3, 3], axis=0), axis=1)
        assert step.max() < 5e-4  # no jumps: < 0.5 mm per frame
        ends_t.append(np.linalg.norm(Td[-1, :2, 3] - T[-1, :2, 3]))
        ends_yaw.append(np.degrees(rotation_angle(D[-1, :3, :3])))
    # After 10 s: horizontal spread ~0.75 cm per axis, yaw ~0.075 deg (sqrt(2) for the 2D norm).
    assert 0.004 < np.sqrt(np.mean(np.square(ends_t))) < 0.02
    assert 0.03 < np.sqrt(np.mean(np.square(ends_yaw))) < 0.15
    assert max(ends_t) < 0.05


def test_imu_at_rest_reads_gravity_up_in_the_camera_frame():
    R = np.column_stack([[0, -1, 0], [0, 0, -1], [1, 0, 0]]).astype(float)  # looking along +x, level
    T = np.repeat(make_T(R, np.array([0.0, 0.0, 1.4]))[None], 90, axis=0)
    t, acc, gyr = tr.synth_imu(T, FPS, np.random.default_rng(0), rate_hz=100.0)
    assert t[0] == 0 and np.allclose(np.diff(t), 0.01) and t[-1] == pytest.approx(89 / FPS, abs=0.01)
    # World up (+Z) is camera -y for a level OpenCV camera.
    assert np.allclose(acc.mean(0), [0, -9.81, 0], atol=0.08)
    assert np.linalg.norm(acc.mean(0)) == pytest.approx(9.81, abs=0.08)
    assert np.allclose(gyr.mean(0), 0, atol=0.005)
    assert 0.01 < acc.std(0).mean() < 0.04


def test_imu_of_a_known_motion():
    """Constant yaw rate plus a horizontal sine: the gyro reads the rate about camera -y, the
    accelerometer the sine's acceleration plus gravity, in the camera frame."""
    n = 150
    t = np.arange(n) / FPS
    w = 0.6  # rad/s about +Z
    R0 = np.column_stack([[0, -1, 0], [0, 0, -1], [1, 0, 0]]).astype(float)
    R = rot_z(w * t) @ R0
    pos = np.column_stack([0.2 * np.sin(2 * t), np.zeros(n), np.full(n, 1.4)])
    ti, acc, gyr = tr.synth_imu(make_T(R, pos), FPS, np.random.default_rng(1), accel_sigma=0, gyro_sigma=0,
                                accel_bias_sigma=0, gyro_bias_sigma=0)
    inner = (ti > 0.5) & (ti < t[-1] - 0.5)  # away from the spline's free ends
    assert np.allclose(gyr[inner], [0, -w, 0], atol=1e-3)
    a_world = np.column_stack([-0.8 * np.sin(2 * ti), np.zeros_like(ti), np.full_like(ti, 9.81)])
    Ri = rot_z(w * ti) @ R0
    expect = np.einsum("nji,nj->ni", Ri, a_world)
    assert np.allclose(acc[inner], expect[inner], atol=0.02)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_scene_walk_glance_sees_the_floor_inside_the_loop(seed):
    """With `glance_every_s` the 15 s scan stops, looks down and turns round: the walk area's floor
    (where the performer walks) falls inside its depth frustums (hfov 67 deg, 4:3, 5 m), which the
    outward-only walk never manages; the turn stays a handheld one (< 120 deg/s, < 45 deg down)."""
    spec = build_scene("indoor", np.random.default_rng([seed, 1])).spec
    lo, hi = np.asarray(spec.walk_area_min_xy), np.asarray(spec.walk_area_max_xy)
    g = np.stack(np.meshgrid(np.arange(lo[0], hi[0], 0.05), np.arange(lo[1], hi[1], 0.05), indexing="ij"), -1)
    P = np.column_stack([g.reshape(-1, 2), np.zeros(g.shape[0] * g.shape[1])])
    tx = np.tan(np.radians(33.5))

    def seen(T):
        out = np.zeros(len(P), bool)
        for Tk in T[::3]:
            pc = (P - Tk[:3, 3]) @ Tk[:3, :3]
            z = pc[:, 2]
            out |= (z > 0.05) & (z < 5.0) & (np.abs(pc[:, 0]) < tx * z) & (np.abs(pc[:, 1]) < 0.75 * tx * z)
        return out.mean()

    T = tr.scene_walk(spec, 15.0, FPS, np.random.default_rng([seed, 5]),
                      tr.SceneWalkConfig(glance_every_s=15.0, turns_per_lap=0.0))
    T0 = tr.scene_walk(spec, 15.0, FPS, np.random.default_rng([seed, 5]), tr.SceneWalkConfig(turns_per_lap=0.0))
    assert seen(T) > 0.8 and seen(T0) < 0.3
    assert np.percentile(_rot_speed_deg_s(T), 99) < 120
    assert np.all(np.rad2deg(np.arcsin(-T[:, :3, 2][:, 2])) < 45)
