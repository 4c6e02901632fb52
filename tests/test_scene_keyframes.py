"""Key frames: motion spacing, blurriest-in-group dropping, tracking-jump exclusion, bad input."""

from __future__ import annotations



from pathlib import Path

import cv2
import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.geometry.transforms import make_T, rot_z
from embodmocap.scene.config import SceneConfig
from embodmocap.scene.keyframes import (
    blur_scores, detect_jumps, drop_blurriest, motion_keyframes, select_keyframes, sharpness,
)
from embodmocap.types import Capture, CameraTrajectory, Intrinsics

FPS = 30.0


def _traj(centres, yaws=None) -> CameraTrajectory:
    n = len(centres)
    yaws = np.zeros(n) if yaws is None else yaws
    return CameraTrajectory(np.arange(n) / FPS, np.arange(n), make_T(rot_z(yaws), centres))


def _walk(n=300, speed=0.5) -> np.ndarray:
    """A straight walk along x at ``speed`` m/s."""
    return np.column_stack([np.arange(n) * speed / FPS, np.zeros(n), np.full(n, 1.4)])


def test_translation_steps_respect_the_threshold():
    cfg = SceneConfig()
    traj = _traj(_walk())
    rows = motion_keyframes(traj, cfg, indoor=True)
    gaps = np.diff(traj.centres[rows, 0])
    step = 0.5 / FPS
    assert rows[0] == 0
    assert np.all(gaps >= 0.10 - 1e-9)
    assert np.all(gaps < 0.10 + step + 1e-9)  # taken at the first frame past the threshold
    # Outdoor uses the larger step.
    rows_out = motion_keyframes(traj, cfg, indoor=False)
    assert np.all(np.diff(traj.centres[rows_out, 0]) >= 0.15 - 1e-9)
    assert len(rows_out) < len(rows)


def test_rotation_alone_makes_key_frames():
    n = 200
    yaws = np.radians(np.arange(n) * 1.0)  # 1 degree per frame, standing still
    traj = _traj(np.zeros((n, 3)), yaws)
    rows = motion_keyframes(traj, SceneConfig(keyframe_step_deg=14.5), indoor=True)
    np.testing.assert_array_equal(rows, np.arange(0, n, 15))


def test_drop_blurriest_in_each_group():
    sharp = np.array([5, 1, 7, 8, 3, 9, 2, 6, 0.5, 4])
    keep = drop_blurriest(sharp, 4)
    # Groups [5 1 7 8] and [3 9 2 6] lose 1 and 2; the partial group [0.5 4] is kept whole.
    np.testing.assert_array_equal(np.flatnonzero(~keep), [1, 6])
    assert drop_blurriest(sharp, 1).all()


class _ImageFrames:
    """A real in-memory FrameSource: fixed RGB images, counting reads."""

    def __init__(self, images):
        self.images = images
        self.reads = []

    def __len__(self):
        return len(self.images)

    def rgb(self, index):
        self.reads.append(index)
        return self.images[index]

    def depth_m(self, index):
        return np.ones((12, 16), np.float32)

    def confidence(self, index):
        return None


def _capture(images, traj) -> Capture:
    K = Intrinsics(100, 100, 79.5, 59.5, 160, 120)
    return Capture(Path("/data/scene_cap"), "strayscanner", len(images), FPS, K, K.scaled(16, 12), traj,
                   _ImageFrames(images), timestamps_s=np.arange(len(images)) / FPS)


def _texture(seed: int) -> np.ndarray:
    g = np.random.default_rng(seed)
    small = (g.random((15, 20, 3)) * 255).astype(np.uint8)
    return cv2.resize(small, (160, 120), interpolation=cv2.INTER_NEAREST)


def test_blur_scores_rank_a_blurred_frame_lowest_and_read_each_frame_once():
    sharp_img = _texture(0)
    blurred = cv2.GaussianBlur(sharp_img, (0, 0), 3.0)
    assert sharpness(blurred) < 0.3 * sharpness(sharp_img)
    images = [sharp_img, blurred, _texture(1), _texture(2)]
    cap = _capture(images, _traj(_walk(4)))
    scores = blur_scores(cap, [3, 1, 0, 2])
    assert np.argmin(scores) == 1  # input order kept
    assert cap.frames.reads == [0, 1, 2, 3]  # each read once, in increasing order
    keep: dict = {}
    np.testing.assert_array_equal(blur_scores(cap, [3, 1], keep=keep), scores[[0, 1]])
    assert sorted(keep) == [1, 3] and all(np.array_equal(keep[i], images[i]) for i in keep)


def test_choose_keyframes_keeps_exactly_the_chosen_key_frames_pixels():
    from embodmocap.scene.keyframes import choose_keyframes

    cfg = SceneConfig(min_keyframes=2)
    n = 300
    images = [_texture(i) for i in range(n)]
    images[40] = cv2.GaussianBlur(images[40], (0, 0), 3.0)
    cap = _capture(images, _traj(_walk(n)))
    keep: dict = {}
    sel = choose_keyframes(cap, cfg, True, keep=keep)
    assert len(sel.dropped_blurry) > 0
    assert sorted(keep) == sorted(int(i) for i in sel.frame_ids)  # the dropped blurry ones are not kept
    assert all(np.array_equal(keep[i], images[i]) for i in keep)
    assert len(cap.frames.reads) == len(set(cap.frames.reads))  # every frame decoded once


def test_select_keyframes_drops_the_blurred_key_frame():
    cfg = SceneConfig(min_keyframes=2)
    traj = _traj(_walk(300))
    rows = motion_keyframes(traj, cfg, True)
    blur = np.full(len(traj), np.nan)
    blur[rows] = 100.0
    blur[rows[2]] = 1.0  # the blurry one in the first group of 4
    sel = select_keyframes(traj, blur, cfg, True)
    assert rows[2] in sel.dropped_blurry
    assert rows[2] not in sel.frame_ids
    assert len(sel.dropped_blurry) == len(rows) // 4
    assert sel.reasons()[int(rows[2])] == "blurry"


def test_clean_handheld_trajectory_has_no_jumps():
    from embodmocap.synth.scene import build_scene
    from embodmocap.synth.trajectory import scene_walk

    built = build_scene("indoor", np.random.default_rng(0))
    T = scene_walk(built.spec, 20.0, FPS, np.random.default_rng(1))
    traj = CameraTrajectory(np.arange(len(T)) / FPS, np.arange(len(T)), T)
    assert not detect_jumps(traj, FPS, SceneConfig()).any()


def test_glitch_is_excluded_alone_and_relocalisation_keeps_the_larger_part():
    c = _walk(300)
    glitch = c.copy()
    glitch[100:102] += [0.8, 0.3, 0.0]  # two frames thrown off, then back
    bad = detect_jumps(_traj(glitch), FPS, SceneConfig())
    np.testing.assert_array_equal(np.flatnonzero(bad), [100, 101])

    reloc = c.copy()
    reloc[220:] += [0.0, 0.6, 0.0]  # a permanent jump: the shorter side goes
    bad = detect_jumps(_traj(reloc), FPS, SceneConfig())
    np.testing.assert_array_equal(np.flatnonzero(bad), np.arange(220, 300))

    T = _traj(c).T_world_cam.copy()
    T[50, 0, 3] = np.nan
    bad = detect_jumps(CameraTrajectory(np.arange(300) / FPS, np.arange(300), T), FPS, SceneConfig())
    np.testing.assert_array_equal(np.flatnonzero(bad), [50])


def test_excluded_frames_are_never_key_frames_and_are_reported(caplog):
    c = _walk(300)
    c[100:102] += [0.8, 0.3, 0.0]
    traj = _traj(c)
    bad = detect_jumps(traj, FPS, SceneConfig())
    sel = select_keyframes(traj, None, SceneConfig(), True, bad, capture_path="cap")
    assert not np.isin([100, 101], sel.frame_ids).any()
    np.testing.assert_array_equal(sel.excluded_jumps, [100, 101])
    assert "2 of 300 frames excluded" in caplog.text


def test_too_few_key_frames_is_an_input_error_naming_the_capture():
    traj = _traj(_walk(20))  # 0.33 m of walking: 4 key frames
    with pytest.raises(InputError, match=r"scene_cap.*only \d+ usable key frames"):
        select_keyframes(traj, None, SceneConfig(), True, capture_path=Path("/data/scene_cap"))
