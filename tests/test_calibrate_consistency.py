"""The VIO check of registered frames, the chain offset fit and the frame selection, on poses
with known answers (no images)."""

from __future__ import annotations

import numpy as np

from embodmocap.calibrate.consistency import check_against_vio, off_chain_frames, relative_disagreement
from embodmocap.calibrate.offset import RobustOffsetConfig, YawOffset, chain_yaw_offset, robust_yaw_offset
from embodmocap.calibrate.register import select_frames
from embodmocap.geometry.transforms import make_T, rot_z


def _walk(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 4, 4) a camera walking a 3 m arc at 1.4 m height, panning, looking roughly horizontal."""
    s = np.linspace(0, 1, n)
    yaw = 0.8 * s + 0.1 * np.sin(9 * s)
    C = np.column_stack([3 * np.cos(s), 3 * np.sin(s), 1.4 + 0.05 * np.sin(5 * s)])
    # OpenCV camera looking along +x of the yaw frame: z forward, x right, y down.
    R0 = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)
    R = np.stack([rot_z(y) @ R0 for y in yaw])
    return make_T(R, C)


def _jitter(T: np.ndarray, rng: np.random.Generator, m: float, deg: float) -> np.ndarray:
    out = T.copy()
    out[:, :3, 3] += rng.normal(0, m, (len(T), 3))
    for i in range(len(T)):
        out[i, :3, :3] = rot_z(np.radians(rng.normal(0, deg))) @ out[i, :3, :3]
    return out


def test_relative_disagreement_ignores_the_offset():
    rng = np.random.default_rng(0)
    T_vio = _walk(20, rng)
    off = YawOffset(0.7, np.array([1.0, -2.0, 0.1]))
    m, d = relative_disagreement(off.apply(T_vio[:-1]), off.apply(T_vio[1:]), T_vio[:-1], T_vio[1:])
    assert m.max() < 1e-9 and d.max() < 1e-6


def test_a_consistently_wrong_run_is_rejected_and_the_rest_kept():
    rng = np.random.default_rng(1)
    T_vio = _walk(60, rng)
    true = YawOffset(-1.1, np.array([0.3, 0.5, 0.0]))
    T_reg = _jitter(true.apply(T_vio), rng, 0.01, 0.2)
    # Frames 20-34 registered consistently wrong (a look-alike wall): 40 cm and 6 deg off together.
    wrong = YawOffset(np.radians(6), np.array([0.4, 0.1, 0.0]))
    T_reg[20:35] = wrong.apply(T_reg[20:35])
    # Two isolated wrong frames.
    T_reg[5, :3, 3] += [0.0, 0.5, 0.0]
    T_reg[50, :3, 3] += [0.3, 0.0, 0.2]
    chk = check_against_vio(T_reg, T_vio)
    bad = np.zeros(60, bool)
    bad[20:35] = bad[5] = bad[50] = True
    np.testing.assert_array_equal(chk.accepted, ~bad)
    assert chk.rejected_frames == 17 and chk.rejected_runs == 3
    # The centres-only robust fit alone keeps the wrong run partly (it is within its 15 cm gate at
    # some frames); after the check, the chain fit is close to the truth.
    fit = chain_yaw_offset(T_vio[chk.accepted], T_reg[chk.accepted])
    C = T_vio[:, :3, 3]
    assert np.linalg.norm(fit.offset.apply_points(C) - true.apply_points(C), axis=1).mean() < 0.01
    assert abs(np.degrees(fit.offset.yaw_rad - true.yaw_rad)) < 0.2


def test_an_error_ramping_along_a_run_passes_the_run_check_but_not_the_chain_check():
    rng = np.random.default_rng(3)
    T_vio = _walk(80, rng)
    true = YawOffset(0.4, np.array([-1.0, 2.0, 0.0]))
    T_reg = _jitter(true.apply(T_vio), rng, 0.008, 0.15)
    # Frames 30-37 drift off and back (2, 4, 9, 10, 15, 10, 4, 2 cm): each step is within 10 cm.
    ramp = np.array([0.02, 0.04, 0.09, 0.10, 0.15, 0.10, 0.04, 0.02])
    T_reg[30:38, :3, 3] += ramp[:, None] * np.array([0.6, 0.8, 0.0])
    chk = check_against_vio(T_reg, T_vio)
    assert chk.accepted.all()  # the neighbour-to-neighbour test lets the ramp through
    off = off_chain_frames(T_reg, T_vio, chk.accepted)
    # The frames 9 cm or more off are caught (limit: 5 cm here, the view's scatter being small);
    # none of the right frames is.
    np.testing.assert_array_equal(np.flatnonzero(off), 30 + np.flatnonzero(ramp >= 0.09))
    # A noisy but right view (4 cm scatter) keeps every frame: the limit follows its scatter.
    noisy = _jitter(true.apply(T_vio), np.random.default_rng(4), 0.025, 0.3)
    assert off_chain_frames(noisy, T_vio, np.ones(80, bool)).sum() <= 1


def test_registrations_of_another_scene_disagree_everywhere():
    rng = np.random.default_rng(2)
    T_vio = _walk(40, rng)
    # Poses scattered at random (what registration into the wrong model gives).
    R = np.stack([rot_z(a) @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float) for a in rng.uniform(-np.pi, np.pi, 40)])
    T_reg = make_T(R, rng.uniform(-3, 3, (40, 3)))
    chk = check_against_vio(T_reg, T_vio)
    assert chk.accepted.sum() <= 2 and chk.runs >= 35


def test_orientations_tighten_the_yaw_of_a_short_chain():
    rng = np.random.default_rng(3)
    T_vio = _walk(200, rng)[:25]  # a short stretch: centres span ~0.4 m, a weak lever for the yaw
    true = YawOffset(0.4, np.array([0.2, -0.1, 0.0]))
    errs = {"centres": [], "chain": []}
    for k in range(20):
        r = np.random.default_rng(100 + k)
        T_reg = _jitter(true.apply(T_vio), r, 0.02, 0.2)
        c = robust_yaw_offset(T_vio[:, :3, 3], T_reg[:, :3, 3], RobustOffsetConfig())
        p = chain_yaw_offset(T_vio, T_reg, RobustOffsetConfig())
        errs["centres"].append(abs(np.degrees(c.offset.yaw_rad - true.yaw_rad)))
        errs["chain"].append(abs(np.degrees(p.offset.yaw_rad - true.yaw_rad)))
    assert np.median(errs["chain"]) < 0.25 < np.median(errs["centres"])


def test_select_frames_spreads_over_time_and_motion():
    rng = np.random.default_rng(4)
    walk = _walk(300, rng)
    # 300 frames standing still, then 300 walking: the walk gets most of the samples.
    T = np.concatenate([np.repeat(walk[:1], 300, axis=0), walk])
    sel = select_frames(T, 60)
    assert 50 <= len(sel) <= 60 and np.all(np.diff(sel) > 0)
    assert np.sum(sel >= 300) > 2 * np.sum(sel < 300) and np.sum(sel < 300) >= 3
    np.testing.assert_array_equal(select_frames(T[:40], 60), np.arange(40))
    # Never a frame with a broken pose.
    T[310:320] = np.nan
    assert not np.any((select_frames(T, 60) >= 310) & (select_frames(T, 60) < 320))
