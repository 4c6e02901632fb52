"""Slice the synchronised views to one common timeline, through timestamps.

Each view's clock is re-based so that its sync event (the timestamp of its event frame) is t = 0.
The sequence runs from 0 to the earliest end over the views, at one frame rate (default: the lowest
view frame rate). Every sequence time maps, per view, to the raw frame nearest in time, so views at
different frame rates and views with dropped frames line up by their timestamps, never by counting
frames. A sequence time whose nearest raw frame is more than half that view's frame period away
falls in a gap (a dropped frame) and is flagged, not hidden.
"""

from __future__ import annotations

import logging
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.stage_files import FrameMap
from embodmocap.sequence.sync import SyncEvent
from embodmocap.types import Capture

log = logging.getLogger(__name__)

def _view_clock(cap: Capture) -> NDArray[np.float64]:
    """(num_frames,) frame times in seconds; nominal ``i / fps`` when the capture has none."""
    ts = np.asarray(cap.timestamps_s, dtype=np.float64)
    if len(ts) == cap.num_frames and cap.num_frames > 0:
        return ts
    if cap.fps <= 0:
        raise InputError(cap.path, "capture has neither frame timestamps nor a frame rate", "re-export the capture")
    log.warning("%s: no per-frame timestamps, using frame index / %.3g fps", cap.path, cap.fps)
    return np.arange(cap.num_frames) / cap.fps


def _frame_period(t: NDArray[np.float64], fps: float) -> float:
    """A view's frame period: median step of its timestamps (robust to drops), else 1 / fps."""
    steps = np.diff(t)
    steps = steps[steps > 0]
    return float(np.median(steps)) if len(steps) else 1.0 / fps


def _nearest(t_raw: NDArray[np.float64], t: NDArray[np.float64]) -> NDArray[np.int64]:
    """Index of the nearest element of increasing ``t_raw`` for every ``t`` (ties: earlier)."""
    hi = np.clip(np.searchsorted(t_raw, t), 1, len(t_raw) - 1)
    lo = hi - 1
    return np.where(np.abs(t_raw[hi] - t) < np.abs(t - t_raw[lo]), hi, lo).astype(np.int64)


def slice_views(
    captures: Mapping[str, Capture], events: Mapping[str, SyncEvent], fps: float | None = None,
    min_overlap_s: float = 1.0,
) -> dict[str, FrameMap]:
    """Map a common sequence timeline to each view's raw frames.

    Args:
        captures: view name -> capture (its ``timestamps_s`` give the frame times).
        events: view name -> sync event (``frame`` = raw frame at sequence time 0).
        fps: sequence frame rate; default the lowest view frame rate (from its timestamps).
        min_overlap_s: shortest common span after the event that is accepted, seconds.

    Returns:
        view name -> :class:`FrameMap`, all of the same length T.

    Raises:
        InputError: an event frame outside its capture, or a common span shorter than
            ``min_overlap_s`` (the message gives every view's span).
    """
    clocks, periods, ends, event_t = {}, {}, {}, {}
    for view, cap in captures.items():
        if view not in events:
            raise InputError(cap.path, f"view {view} has no sync event", "sync every view before slicing")
        e = events[view].frame
        if not 0 <= e < cap.num_frames:
            raise InputError(cap.path, f"sync frame {e} of view {view} is outside the capture's {cap.num_frames} frames",
                             "fix sync_frame in session.toml")
        t = _view_clock(cap)
        if np.any(np.diff(t) <= 0):
            raise InputError(cap.path, "frame timestamps do not increase", "re-export the capture")
        clocks[view] = t - t[e]
        event_t[view] = float(t[e])
        periods[view] = _frame_period(t, cap.fps)
        ends[view] = float(clocks[view][-1])
    if not clocks:
        raise ValueError("no views to slice")
    span = min(ends.values())
    if span < min_overlap_s:
        detail = ", ".join(f"{v} records {ends[v]:.2f} s after its sync frame {events[v].frame} "
                           f"(of {captures[v].num_frames} frames)" for v in clocks)
        short = min(ends, key=ends.get)
        raise InputError(captures[short].path,
                         f"views do not overlap after sync: common span {span:.2f} s < {min_overlap_s:g} s ({detail})",
                         "check the sync frames (sync_frame in session.toml) and that both views film the same take")
    rate = float(fps) if fps is not None else min(
        (c.fps if c.fps > 0 else 1.0 / periods[v]) for v, c in captures.items())
    # Sequence frames at k / rate up to the common end (a small tolerance keeps a frame that lands
    # on the end exactly despite floating point).
    T = int(np.floor(span * rate + 1e-6)) + 1
    seq_t = np.arange(T) / rate
    out = {}
    for view, t in clocks.items():
        idx = _nearest(t, seq_t)
        dt = np.abs(t[idx] - seq_t)
        dropped = dt > 0.5 * periods[view] + 1e-6
        if dropped.any():
            log.warning("view %s: %d of %d sequence frames fall on dropped raw frames (largest gap %.1f ms)",
                        view, int(dropped.sum()), T, 1e3 * dt.max())
        out[view] = FrameMap(seq_t, idx, dt, dropped, events[view].frame, event_t[view], rate)
    return out
