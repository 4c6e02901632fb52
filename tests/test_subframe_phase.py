"""The geometric sync's sub-frame part against a known phone phase (issue 29).

Two views film the skeleton-like point set of ``test_geosync`` (exact projections plus Gaussian
pixel noise), view 2 a known fraction of a frame off view 1: in phase (0, as the studio's phones
were before ``SynthConfig.phone_phase``) and +-0.4 frame. Every expected number comes from the
construction.

Tolerances: with 4 px of noise per view the estimate's seed-to-seed spread is about 0.09 frame
(measured over 16 seeds), so the mean of 8 seeds has a standard error of about 0.03 frame; its
bias must stay within 0.06 frame (2 standard errors); each seed within 4 of its own reported
standard errors (an honest error bar). The old estimator's mechanism is kept here as a reference
(a straight line's value at the window centre, one way, the instrument against the same epipolar
line as the value): with the noise in view 1 alone it leans -0.04 frame (3 standard errors of the
12-seed mean), the estimator of ``geosync`` (both ways averaged) half that or less.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_geosync import FPS, J, K, cameras, joints, project

from embodmocap.sequence.geosync import GeoSyncConfig, _iv_fit, epipolar_distance, geometric_sync, subframe_shift
from embodmocap.sequence.sync_record import decide, subframe_residual


def views(phase: float, noise_px: tuple[float, float], seed: int, n: int = 180):
    """View 1 frame k films time k/fps, view 2 frame k time (k - phase)/fps: the instant view 1
    films at t, view 2 films at t + phase frames."""
    rng = np.random.default_rng([seed, 29])
    t = np.arange(n) / FPS
    t2 = t - phase / FPS
    out = []
    for T, tt, s in ((cameras(t, 0.0), t, noise_px[0]), (cameras(t2, np.pi / 2), t2, noise_px[1])):
        xy = project(T, joints(tt)) + rng.normal(0, s, (n, J, 2))
        out += [T, np.concatenate([xy, np.ones((n, J, 1))], -1), t]
    return out


def old_one_way(T1, kp1, T2, kp2, W: int = 3) -> float:
    """Reference: the sub-frame estimate before session 10 at shift 0 (no screens, no parts)."""
    R = 2 * W + 2
    t = np.arange(R, len(kp1) - R)
    ks = np.arange(-R, R + 1)
    D = np.stack([epipolar_distance(K, T1[t][:, None], kp1[t, :, :2], K, T2[t + k][:, None], kp2[t + k, :, :2])
                  for k in ks], -1).reshape(-1, len(ks))
    inner = np.abs(ks) <= W
    a = D[:, inner].mean(1)  # a straight line's value at the centre: the window's mean
    b = D[:, inner] @ ks[inner] / np.sum(ks[inner] ** 2)
    outer = ks[ks > W]
    z = (D[:, ks > W] - D[:, ks < -W][:, ::-1]) @ outer / (2.0 * np.sum(outer * outer))
    return _iv_fit(a, b, z, 3.0, 8)[0]


@pytest.mark.parametrize("phase", [0.0, 0.4, -0.4])
def test_the_sub_frame_phase_is_found_in_phase_and_off_phase(phase):
    errs, stds = [], []
    for seed in range(8):
        T1, kp1, t1, T2, kp2, t2 = views(phase, (4.0, 4.0), seed)
        res = geometric_sync(K, T1, kp1, t1, K, T2, kp2, t2, FPS, search_s=1.0)
        assert res.found and math.isfinite(res.std_frames)
        errs.append(res.offset_frames - phase)
        stds.append(res.std_frames)
    errs, stds = np.array(errs), np.array(stds)
    assert abs(errs.mean()) < 0.06, errs
    assert np.all(np.abs(errs) < 4.0 * stds), (errs, stds)


def test_noise_in_the_line_view_no_longer_tilts_the_estimate():
    old, new = [], []
    for seed in range(12):
        T1, kp1, _, T2, kp2, _ = views(0.0, (4.0, 0.0), seed)
        old.append(old_one_way(T1, kp1, T2, kp2))
        new.append(subframe_shift(K, T1, kp1, K, T2, kp2, 0)[0])
    old, new = np.mean(old), np.mean(new)
    assert old < -0.025, old  # the old estimator's lean (the studio's in-phase sessions: 0.2-0.34 frame off)
    assert abs(new) < 0.5 * abs(old), (old, new)


def test_the_applied_residual_weighs_the_measurement_by_its_error():
    rng = np.random.default_rng(5)
    # The laser frames' own spread of the true residual: triangular on (-1, 1) frame.
    truth = rng.uniform(-0.5, 0.5, 4000) + rng.uniform(-0.5, 0.5, 4000)
    for std in (0.05, 0.25, 0.5):
        g = truth + rng.normal(0, std, truth.size)
        kept = np.array([subframe_residual(x, std) for x in g])
        rms_raw, rms_kept = (float(np.sqrt(np.mean((x - truth) ** 2))) for x in (g, kept))
        assert rms_kept <= rms_raw + 1e-3
        if std >= 0.25:  # an imprecise measurement: weighing it with the frames pays
            assert rms_kept < 0.85 * rms_raw
    assert subframe_residual(0.3, 0.02) == pytest.approx(0.3, abs=0.01)  # precise: kept
    assert subframe_residual(0.3, math.inf) == 0.0  # nothing measured: the frames' own 0
    assert 0.0 < subframe_residual(0.3, 0.25) < 0.3


def test_the_choice_and_the_manual_path_apply_the_weighed_residual():
    from test_geosync import _geo, _manual_record, _record

    geo = _geo(0.4)
    want = subframe_residual(geo.offset_s * FPS, geo.std_frames)
    rec = decide(_record(1.0), geo, GeoSyncConfig(), FPS, {}, "s")
    assert rec["chosen"]["source"] == "geometric"
    assert rec["chosen"]["residual_frames"] == pytest.approx(want, abs=1e-3)
    rec = decide(_manual_record(), geo, GeoSyncConfig(), FPS, {}, "s")
    assert rec["sources"]["manual"]["subframe_applied"]
    assert rec["chosen"]["residual_frames"] == pytest.approx(want, abs=1e-3)
    rec = decide(_manual_record(), geo, GeoSyncConfig(), FPS, {}, "s", subframe_sync=False)
    assert rec["chosen"]["residual_frames"] == 0.0
    raw = decide(_record(1.0), geo, GeoSyncConfig(subframe_shrink=False), FPS, {}, "s")
    assert raw["chosen"]["residual_frames"] == pytest.approx(geo.offset_frames, abs=1e-3)
