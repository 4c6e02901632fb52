"""Slicing synced views to a common timeline through timestamps: different frame rates, dropped
frames, clock jitter, non-overlapping views, and the frame-map JSON round trip."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.io.stage_files import FrameMap, read_frame_map, write_frame_map
from embodmocap.sequence.slicing import slice_views
from embodmocap.sequence.sync import SyncEvent
from embodmocap.types import CameraTrajectory, Capture, Intrinsics


class NoFrames:
    """Slicing only reads timestamps; any pixel access is a bug."""

    def __init__(self, n: int) -> None:
        self.n = n

    def __len__(self) -> int:
        return self.n

    def rgb(self, index):
        raise AssertionError("slicing must not read frames")

    depth_m = confidence = rgb


def _cap(ts: np.ndarray, fps: float, name: str) -> Capture:
    n = len(ts)
    K = Intrinsics(500.0, 500.0, 319.5, 239.5, 640, 480)
    traj = CameraTrajectory(ts, np.arange(n), np.tile(np.eye(4), (n, 1, 1)))
    return Capture(Path(f"captures/{name}"), "strayscanner", n, fps, K, K.scaled(256, 192), traj, NoFrames(n),
                   timestamps_s=ts)


def _ev(frame: int) -> SyncEvent:
    return SyncEvent(frame, 1.0, None, 0, "manual")


def test_30_and_60_fps_views_map_by_time():
    v1 = _cap(100.0 + np.arange(90) / 30, 30.0, "v1")
    v2 = _cap(731.25 + np.arange(200) / 60, 60.0, "v2")
    maps = slice_views({"v1": v1, "v2": v2}, {"v1": _ev(10), "v2": _ev(33)})
    # Common span: v1 has (89 - 10) / 30 = 2.633 s after its event, v2 (199 - 33) / 60 = 2.767 s.
    T = 80
    assert len(maps["v1"]) == len(maps["v2"]) == T
    np.testing.assert_allclose(maps["v1"].seq_times_s, np.arange(T) / 30)
    np.testing.assert_array_equal(maps["v1"].raw_frames, 10 + np.arange(T))
    np.testing.assert_array_equal(maps["v2"].raw_frames, 33 + 2 * np.arange(T))
    assert maps["v1"].fps == maps["v2"].fps == 30.0
    assert maps["v2"].event_frame == 33 and maps["v2"].event_time_s == pytest.approx(731.25 + 33 / 60)
    for m in maps.values():
        assert m.dt_s.max() < 1e-9 and not m.dropped.any()


def test_explicit_fps_resamples_the_faster_view():
    v1 = _cap(np.arange(120) / 60, 60.0, "v1")
    v2 = _cap(5.0 + np.arange(120) / 60, 60.0, "v2")
    maps = slice_views({"v1": v1, "v2": v2}, {"v1": _ev(0), "v2": _ev(20)}, fps=15.0)
    assert len(maps["v1"]) == int((99 / 60) * 15) + 1
    np.testing.assert_array_equal(maps["v1"].raw_frames, 4 * np.arange(len(maps["v1"])))
    np.testing.assert_array_equal(maps["v2"].raw_frames, 20 + 4 * np.arange(len(maps["v2"])))


def test_dropped_frames_are_mapped_by_time_and_flagged():
    nominal = np.arange(100) / 30
    keep = np.ones(100, bool)
    keep[[40, 41, 70]] = False  # the phone dropped three frames
    v1 = _cap(10.0 + nominal, 30.0, "v1")
    v2 = _cap(20.0 + nominal[keep], 30.0, "v2")
    maps = slice_views({"v1": v1, "v2": v2}, {"v1": _ev(5), "v2": _ev(5)})
    m = maps["v2"]
    seq_t = m.seq_times_s
    # For every sequence time, v2's raw frame is the one whose timestamp is nearest.
    raw_t = v2.timestamps_s - v2.timestamps_s[5]
    expect = np.abs(raw_t[None, :] - seq_t[:, None]).argmin(axis=1)
    np.testing.assert_array_equal(m.raw_frames, expect)
    # Counting frames would be wrong after the drop: sequence frame 50 is nominal frame 55,
    # which is raw frame 53 of v2 (two dropped before it).
    assert m.raw_frames[50] == 53 and maps["v1"].raw_frames[50] == 55
    # The three missing instants are flagged (nominal frames 40, 41, 70 = sequence frames 35, 36, 65).
    np.testing.assert_array_equal(np.nonzero(m.dropped)[0], [35, 36, 65])
    assert m.num_dropped == 3 and m.dt_s[m.dropped].min() == pytest.approx(1 / 30)
    assert not maps["v1"].dropped.any()


def test_clock_jitter_still_maps_to_the_right_frames():
    rng = np.random.default_rng(0)
    ts = np.arange(150) / 30 + rng.uniform(-0.004, 0.004, 150)
    maps = slice_views({"v1": _cap(ts, 30.0, "v1"), "v2": _cap(3 + np.arange(150) / 30, 30.0, "v2")},
                       {"v1": _ev(12), "v2": _ev(0)})
    np.testing.assert_array_equal(maps["v1"].raw_frames, 12 + np.arange(len(maps["v1"])))
    assert not maps["v1"].dropped.any() and maps["v1"].dt_s.max() < 0.009


def test_views_that_do_not_overlap_after_sync():
    v1 = _cap(np.arange(60) / 30, 30.0, "v1")
    v2 = _cap(np.arange(300) / 30, 30.0, "v2")
    with pytest.raises(InputError) as err:
        slice_views({"v1": v1, "v2": v2}, {"v1": _ev(45), "v2": _ev(10)})
    msg = str(err.value)
    assert msg.startswith("captures/v1:")
    assert "common span 0.47 s < 1 s" in msg and "v1 records 0.47 s after its sync frame 45" in msg
    assert "v2 records 9.63 s" in msg and "sync_frame" in msg
    # Accepted when the caller allows shorter overlaps.
    assert len(slice_views({"v1": v1, "v2": v2}, {"v1": _ev(45), "v2": _ev(10)}, min_overlap_s=0.4)["v1"]) == 15


def test_bad_event_frames_and_timestamps():
    v1 = _cap(np.arange(60) / 30, 30.0, "v1")
    with pytest.raises(InputError, match="sync frame 60 of view v1 is outside"):
        slice_views({"v1": v1}, {"v1": _ev(60)})
    with pytest.raises(InputError, match="has no sync event"):
        slice_views({"v1": v1}, {})
    ts = np.arange(60) / 30
    ts[30] = ts[29]
    with pytest.raises(InputError, match="timestamps do not increase"):
        slice_views({"v1": _cap(ts, 30.0, "v1")}, {"v1": _ev(0)})


def test_frame_map_json_round_trip(tmp_path):
    nominal = np.arange(80) / 30
    maps = slice_views({"v1": _cap(np.delete(nominal, [20]), 30.0, "v1"), "v2": _cap(nominal, 30.0, "v2")},
                       {"v1": _ev(3), "v2": _ev(1)})
    fm = maps["v1"]
    path = tmp_path / "frame_map.json"
    write_frame_map(path, fm)
    back = read_frame_map(path)
    for k in ("seq_times_s", "raw_frames", "dt_s", "dropped"):
        np.testing.assert_array_equal(getattr(back, k), getattr(fm, k))
        assert getattr(back, k).dtype == getattr(fm, k).dtype
    assert (back.event_frame, back.event_time_s, back.fps) == (fm.event_frame, fm.event_time_s, fm.fps)
    assert back.num_dropped == 1
    bad = json.loads(path.read_text())
    bad["num_frames"] = 3
    path.write_text(json.dumps(bad))
    with pytest.raises(InputError, match="num_frames = 3"):
        read_frame_map(path)
    path.write_text(json.dumps({"version": 2}))
    with pytest.raises(InputError, match="version 2"):
        read_frame_map(path)
    del bad["raw_frames"]
    path.write_text(json.dumps(bad))
    with pytest.raises(InputError, match="malformed"):
        read_frame_map(path)


def test_frame_map_arrays_are_read_only():
    fm = FrameMap(np.zeros(3), np.arange(3), np.zeros(3), np.zeros(3, bool))
    with pytest.raises(ValueError):
        fm.raw_frames[0] = 5
