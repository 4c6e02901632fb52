"""Laser-dot sync: detection on synthetic studio sessions and on hand-made frame sequences with
distractors, occlusions and camera motion; manual override; errors; contact sheets."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from embodmocap.errors import InputError
from embodmocap.io.captures import open_capture
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.sequence.slicing import slice_views
from embodmocap.sequence.sync import (
    SyncConfig, SyncEvent, contact_sheet_size, detect_laser_event, find_dot_candidates, sync_events_from_json,
    sync_events_to_json, sync_views, write_contact_sheet,
)
from embodmocap.synth.config import SynthConfig
from embodmocap.synth.studio import synthesize
from embodmocap.types import CameraTrajectory, Capture, Intrinsics

# Small sessions, but RGB large enough (320x240) that the dot covers a few pixels.
SMALL = dict(seconds=1.5, scene_seconds=0.5, width=320, height=240, depth_width=64, depth_height=48)
SEEDS = [(3, "indoor"), (8, "indoor"), (4, "outdoor")]


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> dict[tuple[int, str], Path]:
    out = {}
    for seed, preset in SEEDS:
        root = tmp_path_factory.mktemp("sync") / f"{preset}{seed}"
        synthesize(SynthConfig(seed=seed, preset=preset, **SMALL), root)
        out[(seed, preset)] = root
    return out


def _views(root: Path) -> tuple[dict[str, Capture], dict]:
    lay = SessionLayout(root)
    caps = {v: open_capture(lay.view_capture("seq0", v)) for v in VIEWS}
    return caps, np.load(lay.ground_truth.sequence("seq0"))


# --------------------------------------------------------------------------- hand-made frames


class ArrayFrames:
    """A FrameSource over in-memory RGB frames (depth is a constant 2 m)."""

    def __init__(self, frames: list[np.ndarray]) -> None:
        self.frames = frames

    def __len__(self) -> int:
        return len(self.frames)

    def rgb(self, index: int) -> np.ndarray:
        return self.frames[index]

    def depth_m(self, index: int) -> np.ndarray:
        return np.full((48, 64), 2.0, np.float32)

    def confidence(self, index: int):
        return None


def _capture(frames: list[np.ndarray], fps: float = 30.0, path: str = "mem/view") -> Capture:
    H, W = frames[0].shape[:2]
    K = Intrinsics(300.0, 300.0, (W - 1) / 2, (H - 1) / 2, W, H)
    n = len(frames)
    traj = CameraTrajectory(np.arange(n) / fps, np.arange(n), np.tile(np.eye(4), (n, 1, 1)))
    return Capture(Path(path), "strayscanner", n, fps, K, K.scaled(64, 48), traj, ArrayFrames(frames),
                   timestamps_s=500.0 + np.arange(n) / fps)


def _wall(rng: np.random.Generator, H: int, W: int) -> np.ndarray:
    """A mottled grey wall (float RGB 0..255), large enough to pan over."""
    import cv2

    g = cv2.GaussianBlur(rng.normal(0, 1, (H, W)).astype(np.float32), (0, 0), 3)
    g = 140 + 25 * g / g.std()
    return np.repeat(g[..., None], 3, axis=2) * np.array([1.0, 1.0, 1.05])


def _paint_dot(img: np.ndarray, x: float, y: float, r: float = 3.0) -> None:
    """A saturated red core with a fading red glow, like a laser dot seen by a phone."""
    H, W = img.shape[:2]
    yy, xx = np.mgrid[:H, :W]
    d = np.hypot(xx - x, yy - y)
    glow = (d > r) & (d < 2.2 * r)
    a = (0.7 * (1 - (d[glow] - r) / (1.2 * r)))[:, None]
    img[glow] = img[glow] * (1 - a) + np.array([255.0, 15, 10]) * a
    img[d <= r] = (255, 15, 10)


def _sequence(n: int = 40, event: int = 25, pan_px: float = 0.0, hide: range = range(0), distractor: bool = False,
              shirt: bool = False, seed: int = 0, dot_start=(220.0, 130.0)) -> list[np.ndarray]:
    """Frames of a camera panning over a wall with a laser dot switched off at ``event``.

    Args:
        pan_px: camera pan per frame (x), plus a few px of hand shake.
        hide: frames in which a blue occluder (the performer's arm) covers the dot.
        distractor: a small saturated red sticker on the wall that never goes away.
        shirt: a red shirt (large red region with bright red specks) in view.
        dot_start: the dot's image position in frame 0 (before hand shake).
    """
    rng = np.random.default_rng(seed)
    H, W = 240, 320
    world = _wall(rng, H + 40, W + int(abs(pan_px) * n) + 80)
    x0 = 40 + max(0.0, -pan_px * n)  # the view's left edge on the wall in frame 0
    dot_world = (x0 + dot_start[0], 20 + dot_start[1])
    if distractor:
        _paint_dot(world, dot_world[0] - 90, dot_world[1] - 60, r=2.5)
    frames = []
    shake = rng.normal(0, 1.5, (n, 2))
    for f in range(n):
        ox, oy = x0 + pan_px * f + shake[f, 0], 20 + shake[f, 1]
        ix, iy = int(round(ox)), int(round(oy))
        img = world[iy:iy + H, ix:ix + W].copy()
        if f < event:
            _paint_dot(img, dot_world[0] - ix, dot_world[1] - iy)
        if f in hide:
            x, y = dot_world[0] - ix, dot_world[1] - iy
            img[int(y) - 25:int(y) + 25, int(x) - 20:int(x) + 20] = (40, 60, 150)
        if shirt:
            img[150:230, 20:90] = (200, 25, 30)
            img[170:174, 40:44] = (255, 10, 10)  # a bright fold of the shirt
        img += rng.normal(0, 2.0, img.shape)
        frames.append(np.clip(img, 0, 255).astype(np.uint8))
    return frames


def test_candidates_reject_shirt_and_keep_dot():
    img = _sequence(n=1, event=1, shirt=True)[0]
    c = find_dot_candidates(img, SyncConfig())
    assert len(c) == 1
    # The dot sits at (260, 150) in the world, the view starts at (40, 20) plus shake.
    assert abs(c.xy[0, 0] - 220) < 5 and abs(c.xy[0, 1] - 130) < 5


@pytest.mark.parametrize("pan, start_x", [(0.0, 160.0), (8.0, 290.0), (-10.0, 30.0)])
def test_exact_event_with_camera_motion(pan, start_x):
    frames = _sequence(n=40, event=25, pan_px=pan, seed=1, dot_start=(start_x, 130.0))
    ev = detect_laser_event(_capture(frames))
    assert ev is not None and ev.frame == 25, ev
    assert ev.method == "auto" and ev.confidence > 0.5 and ev.frames_seen == 25


def test_persistent_distractor_and_shirt_do_not_count():
    frames = _sequence(n=40, event=18, pan_px=3.0, distractor=True, shirt=True, seed=2, dot_start=(250.0, 130.0))
    assert len(find_dot_candidates(frames[30])) == 1  # the sticker, still in view after the event
    ev = detect_laser_event(_capture(frames))
    assert ev is not None and ev.frame == 18


def test_short_occlusion_is_not_the_event():
    frames = _sequence(n=45, event=30, hide=range(10, 12), seed=3)
    ev = detect_laser_event(_capture(frames))
    assert ev is not None and ev.frame == 30
    assert ev.frames_seen == 28  # seen in 0..29 except the 2 hidden frames


def test_long_occlusion_scores_below_the_switch_off():
    # Hidden for longer than absent_frames: the hidden stretch ends a track too, but the wall around
    # the dot changed (the occluder), so the real switch-off wins.
    frames = _sequence(n=55, event=40, hide=range(12, 25), seed=4)
    ev = detect_laser_event(_capture(frames))
    assert ev is not None and ev.frame == 40


def test_dot_leaving_the_view_is_not_an_event():
    # The camera pans away: the dot exits at the border while still on.
    frames = _sequence(n=40, event=100, pan_px=12.0, seed=5)
    assert detect_laser_event(_capture(frames)) is None


def test_no_dot_gives_none_and_sync_views_says_how_to_fix():
    cap = _capture(_sequence(n=30, event=0, seed=6), path="captures/seq7/v2")
    assert detect_laser_event(cap) is None
    with pytest.raises(InputError) as err:
        sync_views({"v2": cap}, {}, SyncConfig(), seq="seq7")
    msg = str(err.value)
    assert "captures/seq7/v2" in msg and "sync_frame = N" in msg and "[sequences.seq7.views.v2]" in msg


def test_event_outside_search_range_is_ignored():
    frames = _sequence(n=60, event=45, seed=7)
    assert detect_laser_event(_capture(frames), SyncConfig(search_s=1.0)) is None  # 30 frames searched
    assert detect_laser_event(_capture(frames), SyncConfig(search_s=2.0)).frame == 45


def test_downscaled_analysis_reports_full_resolution_position():
    import cv2

    small = _sequence(n=30, event=20, seed=8)
    big = [cv2.resize(f, (960, 720), interpolation=cv2.INTER_NEAREST) for f in small]
    ev_small = detect_laser_event(_capture(small))
    ev_big = detect_laser_event(_capture(big), SyncConfig(max_width=320))
    assert ev_small.frame == ev_big.frame == 20
    np.testing.assert_allclose(np.array(ev_big.dot_xy_before), (np.array(ev_small.dot_xy_before) + 0.5) * 3 - 0.5, atol=1.0)


# --------------------------------------------------------------------------- synthetic sessions


@pytest.mark.parametrize("key", SEEDS)
def test_exact_frame_on_synthetic_sessions(sessions, key):
    caps, gt = _views(sessions[key])
    events = sync_views(caps, {}, SyncConfig())
    for v in VIEWS:
        assert events[v].frame == int(gt[f"{v}_sync_frame"]), (key, v, events[v])
        assert events[v].method == "auto" and 0.3 < events[v].confidence <= 1.0


def test_painted_distractor_on_a_real_capture(sessions):
    caps, gt = _views(sessions[SEEDS[0]])
    cap = caps["v1"]

    class Painted(ArrayFrames):
        def __init__(self, inner):
            self.inner = inner

        def __len__(self):
            return len(self.inner)

        def rgb(self, i):
            img = self.inner.rgb(i).astype(np.float64)
            _paint_dot(img, 40.0, 60.0, r=3.0)  # a red LED on a shelf, always on
            return img.astype(np.uint8)

    painted = replace(cap, frames=Painted(cap.frames))
    assert len(find_dot_candidates(painted.frames.rgb(int(gt["v1_sync_frame"])))) >= 1  # the LED is a candidate
    ev = detect_laser_event(painted)
    assert ev is not None and ev.frame == int(gt["v1_sync_frame"])


def test_manual_frames_override_detection(sessions):
    caps, gt = _views(sessions[SEEDS[0]])
    events = sync_views(caps, {"v1": 7, "v2": None})
    assert events["v1"] == SyncEvent(7, 1.0, None, 0, "manual")
    assert events["v2"].method == "auto" and events["v2"].frame == int(gt["v2_sync_frame"])
    with pytest.raises(InputError, match="outside the capture"):
        sync_views(caps, {"v1": caps["v1"].num_frames, "v2": 3})


def test_sync_json_round_trip(sessions):
    caps, _ = _views(sessions[SEEDS[0]])
    events = sync_views(caps, {"v1": 4})
    back = sync_events_from_json(json.loads(json.dumps(sync_events_to_json(events))))
    assert back == events
    with pytest.raises(InputError, match="malformed"):
        sync_events_from_json({"version": 1, "views": {"v1": {"frame": 3}}}, "sync.json")


def test_contact_sheet(sessions, tmp_path):
    caps, gt = _views(sessions[SEEDS[0]])
    cap = caps["v1"]
    ev = detect_laser_event(cap)
    path = write_contact_sheet(cap, ev, tmp_path / "sheets" / "v1.png", window=4)
    assert [p.name for p in path.parent.iterdir()] == ["v1.png"]  # no temporary left behind
    with Image.open(path) as im:
        assert im.size == contact_sheet_size(cap, window=4) == (4 * 320, 2 * 240)
        sheet = np.asarray(im.convert("RGB")).astype(int)
    x, y = (int(round(c)) for c in ev.dot_xy_before)

    def redness(tile_col, tile_row):
        patch = sheet[tile_row * 240 + y - 2: tile_row * 240 + y + 3, tile_col * 320 + x - 2: tile_col * 320 + x + 3]
        return (patch[..., 0] - np.maximum(patch[..., 1], patch[..., 2])).max()

    assert redness(3, 0) > 100  # frame event-1 (top right): the dot is there
    assert redness(0, 1) < 60  # the event frame (bottom left): gone
    assert tuple(sheet[240 + 120, 1]) == (0, 255, 0)  # the event tile's green border


# --------------------------------------------------------------------------- sync then slice


def test_synced_and_sliced_views_show_the_same_instant(sessions):
    caps, gt = _views(sessions[SEEDS[1]])
    maps = slice_views(caps, sync_views(caps, {}))
    # Ground truth: raw frame i of view v shows motion frame motion_start[v] + i.
    motion = {v: int(gt[f"{v}_motion_start"]) + maps[v].raw_frames for v in VIEWS}
    np.testing.assert_array_equal(motion["v1"], motion["v2"])
    assert motion["v1"][0] == int(gt["event_motion_frame"])
    assert not any(m.dropped.any() for m in maps.values())


def test_dot_is_examined_among_many_warm_texture_spots():
    # A floor under warm light: hundreds of small texture spots saturate red and stand out in red
    # more than the laser core on its bright wall; only the core's red excess sets it apart.
    rng = np.random.default_rng(7)
    img = np.empty((240, 320, 3))
    img[:] = (200, 150, 140)  # warm wall
    img[120:] = (60, 45, 40)  # dark floor
    for y, x in zip(rng.integers(124, 236, 400), rng.integers(2, 316, 400)):
        img[y:y + 2, x:x + 2] = (255, 220, 205)  # saturated-red speckles of the floor's texture
    _paint_dot(img, 160.0, 60.0, r=2.0)
    img = np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
    c = find_dot_candidates(img, SyncConfig())
    assert len(c) >= 1 and np.min(np.hypot(c.xy[:, 0] - 160, c.xy[:, 1] - 60)) < 3
    # Examining only the spots that stand out most in red (the old ranking) loses the dot.
    old = find_dot_candidates(img, SyncConfig(max_excess_candidates=0))
    assert len(old) == 0 or np.min(np.hypot(old.xy[:, 0] - 160, old.xy[:, 1] - 60)) > 3


def test_small_drop_loses_to_the_laser_switch_off():
    # The laser shines on a faint reddish mark (so its spot does not go out completely); later a
    # small glint with a pinkish rim on the grey wall goes out completely (the performer's shadow).
    # By contrast (relative drop) the glint wins; the laser's drop of red is far larger and wins.
    rng = np.random.default_rng(8)
    base = _wall(rng, 240, 320)
    frames = []
    for f in range(60):
        img = base.copy()
        img[128:133, 218:223] = (165, 135, 125)  # faint reddish mark under the dot
        if f < 20:
            _paint_dot(img, 220.0, 130.0, r=3.0)
            img[129:132, 219:222] = (255, 235, 230)  # over-exposed white core
        if f < 45:
            img[59:64, 79:84] = (215, 150, 145)  # the glint's pinkish rim
            img[60:63, 80:83] = (250, 236, 232)  # and its white core
        img += rng.normal(0, 2.0, img.shape)
        frames.append(np.clip(img, 0, 255).astype(np.uint8))
    ev = detect_laser_event(_capture(frames))
    assert ev is not None and ev.frame == 20, ev
    old = detect_laser_event(_capture(frames), SyncConfig(rival_drop_weight=0.0))
    assert old is not None and old.frame == 45, old  # by contrast alone the glint won
