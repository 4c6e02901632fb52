"""Runs of a view's 2D limb keypoints that jump off their own trajectory (embodmocap.motion.temporal):
a detector's guess at the start of a sequence is judged against the frames after it."""

from __future__ import annotations

import numpy as np

from embodmocap.motion.temporal import TemporalConfig, drop_guessed_runs, temporal_outliers

ON = TemporalConfig(enabled=True, middle=False, flag_min_conf=0.0)


def _person(T: int = 80, seed: int = 0) -> np.ndarray:
    """(T, 1, 17, 3) one view of a person walking across the image (torso ~100 px), the right
    wrist (10) circling in front of the body, 1.5 px detector noise, confidence 0.8."""
    rng = np.random.default_rng(seed)
    t = np.arange(T)
    centre = np.column_stack([200 + 3.0 * t, 240 + 5 * np.sin(t / 10)])  # walks right
    offsets = np.zeros((17, 2))
    offsets[[5, 6, 11, 12]] = [[-25, -50], [25, -50], [-15, 50], [15, 50]]  # shoulders, hips
    offsets[[7, 8, 9, 10]] = [[-35, 0], [35, 0], [-40, 40], [40, 40]]
    offsets[[13, 14, 15, 16]] = [[-15, 100], [15, 100], [-15, 150], [15, 150]]
    xy = centre[:, None] + offsets[None]
    xy[:, 10] += 25 * np.column_stack([np.cos(t / 8), np.sin(t / 8)])  # the wrist moves smoothly
    xy += rng.normal(0, 1.5, xy.shape)
    return np.concatenate([xy, np.full((T, 17, 1), 0.8)], -1)[:, None]


def test_a_guess_at_the_start_is_judged_by_the_frames_after_it():
    kp = _person()
    bad = kp.copy()
    bad[:5, 0, 10, :2] += [60, -40]  # frames 0-4: the wrist guessed 0.7 torso lengths off
    bad[:5, 0, 10, 2] = 0.45
    flags = temporal_outliers(bad, ON)
    assert flags[:5, 0, 10].all()
    assert flags.sum() == 5
    out, dropped = drop_guessed_runs(bad, ON)
    assert (out[:5, 0, 10, 2] == 0).all() and (out[5:, 0, 10, 2] == 0.8).all()
    assert bad[0, 0, 10, 2] == 0.45  # the input is not modified
    np.testing.assert_array_equal(dropped, flags)


def test_a_run_in_the_middle_needs_the_middle_rule():
    kp = _person()
    bad = kp.copy()
    bad[30:38, 0, 10, :2] -= [70, 30]
    assert not temporal_outliers(bad, ON)[30:38].any()
    flags = temporal_outliers(bad, TemporalConfig(enabled=True, middle=True))
    assert flags[30:38, 0, 10].all() and flags.sum() == 8


def test_clean_trajectories_and_off_flag_nothing():
    kp = _person(seed=1)
    assert not temporal_outliers(kp, TemporalConfig(enabled=True, middle=True)).any()
    bad = kp.copy()
    bad[:5, 0, 10, :2] += [60, -40]
    assert not temporal_outliers(bad, TemporalConfig(enabled=False)).any()


def test_weak_detections_shape_the_trajectory_but_are_not_dropped():
    kp = _person()
    bad = kp.copy()
    bad[:5, 0, 10, :2] += [60, -40]
    bad[:5, 0, 10, 2] = 0.2
    assert temporal_outliers(bad, ON)[:5, 0, 10].all()
    assert not temporal_outliers(bad, TemporalConfig(enabled=True, middle=False, flag_min_conf=0.3)).any()


def test_one_stray_frame_after_a_correct_start_does_not_drop_the_start():
    """Studio seed 3 (outdoor): the first 6 frames of a run were right and frame 6 strayed ~0.4
    torso lengths before the wrist came back; the single step 5 -> 6 cut the start off and the
    start rule dropped the correct frames. With ``confirm_frames`` 3 (an option, off by default)
    the jump must hold for the frames after it."""
    kp = _person(seed=2)
    bad = kp.copy()
    bad[6, 0, 10, :2] += [-33, 14]  # one wayward detection, ~0.36 torso lengths off
    bad[6, 0, 10, 2] = 0.54
    confirm = TemporalConfig(enabled=True, middle=False, flag_min_conf=0.0, confirm_frames=3)
    assert not temporal_outliers(bad, confirm)[:6, 0, 10].any()
    # A start guess that stays off for several frames is still dropped when the jump holds.
    worse = bad.copy()
    worse[:6, 0, 10, :2] += [60, -40]
    assert temporal_outliers(worse, confirm)[:6, 0, 10].all()
    # With the single step deciding (the default, confirm_frames 1) the correct start is dropped.
    assert temporal_outliers(bad, ON)[:6, 0, 10].all()


def test_the_first_frame_after_a_gap_of_a_fast_moving_person_is_kept():
    """Issue 29 (outdoor seed 5): the person enters the view at 40 px a frame (torso 100 px) while
    the wrists swing forwards; every detection is right. The torso centre of the run's first
    frames must be theirs (a centred window, not the median of the frames after them, 1.5
    frames' motion off), else the first frame's wrist sits a jump away from the next frames and
    is dropped."""
    T, start = 40, 10
    t = np.arange(T)
    centre = np.column_stack([100 + 40.0 * t, 240 + 0 * t])
    offsets = np.zeros((17, 2))
    offsets[[5, 6, 11, 12]] = [[-25, -50], [25, -50], [-15, 50], [15, 50]]
    offsets[[7, 8, 9, 10]] = [[-35, 0], [35, 0], [-40, 40], [40, 40]]
    offsets[[13, 14, 15, 16]] = [[-15, 100], [15, 100], [-15, 150], [15, 150]]
    xy = centre[:, None] + offsets[None]
    swing = 15.0 * (t - start)  # the wrists swing forwards relative to the body, 15 px a frame
    xy[:, [9, 10], 0] += swing[:, None]
    kp = np.concatenate([xy, np.full((T, 17, 1), 0.9)], -1)[:, None].copy()
    kp[:start, :, :, 2] = 0.0  # not in view before frame 10
    kp[start + 1, :, 9, 2] = 0.0  # one wrist missed in the second frame (a gap of one frame)
    flags = temporal_outliers(kp, TemporalConfig())
    assert not flags.any(), np.argwhere(flags)
