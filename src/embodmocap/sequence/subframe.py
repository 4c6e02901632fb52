"""Sub-frame sync for Stage IV: view 2's observations at view 1's instants.

After slicing, view 2's sequence frame ``k`` is taken ``residual_s`` (``sync.json``'s
``chosen.residual_s``, a fraction of a frame after a laser sync, up to seconds after a slicing
without laser) away from view 1's frame ``k``. :func:`synced_views` resamples view 2's 2D
keypoints (linearly) and world cameras (slerp + linear, :mod:`embodmocap.geometry.interpolate`)
at view 1's frame times plus that offset, so both views observe the same instant. Where view 2
has no frames at those instants (the ends, after a large offset) its keypoints get confidence 0
and Stage IV relies on view 1 there.
"""

from __future__ import annotations

import json
import logging
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.interpolate import interp_keypoints, interp_poses
from embodmocap.io.layout import VIEWS, SequenceLayout
from embodmocap.io.stage_files import read_cameras, read_final_sync

log = logging.getLogger(__name__)


def frame_times(cams: Mapping[str, NDArray], fps: float | None = None) -> NDArray[np.float64]:
    """(T,) each sequence frame's time on its view's own clock, seconds after the slicing event.

    Stage II writes ``frame_times_s`` into ``cameras.npz``; older files only have the sequence
    times (``timestamps_s``), which equal the frame times for a view without dropped frames.
    """
    for key in ("frame_times_s", "timestamps_s"):
        if key in cams:
            return np.asarray(cams[key], dtype=np.float64)
    n = len(cams["T_world_cam"])
    return np.arange(n) / float(fps or 30.0)


def resample_view(kp: NDArray, T_world_cam: NDArray, times_s: NDArray, query_s: NDArray) -> tuple[NDArray, NDArray]:
    """A view's keypoints (T2, J, 3) and cameras (T2, 4, 4), sampled at ``times_s`` (T2,),
    evaluated at ``query_s`` (T,). Repeated times (a dropped frame sliced twice) keep their first
    sample. Returns ``(keypoints (T, J, 3), T_world_cam (T, 4, 4))``; keypoint confidence is 0 at
    queries outside the samples' span."""
    times_s = np.asarray(times_s, dtype=np.float64)
    keep = np.concatenate([[True], np.diff(times_s) > 0])
    keep &= np.maximum.accumulate(times_s) == times_s  # strictly increasing subsequence
    t, kp, T = times_s[keep], np.asarray(kp, float)[keep], np.asarray(T_world_cam, float)[keep]
    return interp_keypoints(kp, t, query_s), interp_poses(T, t, query_s)[0]


def synced_views(out: SequenceLayout, cams: Mapping[str, Mapping], kps: Mapping[str, NDArray]) -> tuple[dict, dict]:
    """Both views' cameras and keypoints on view 1's instants (Stage IV's input).

    Args:
        out: the sequence's layout (``sync.json``, ``<view>/cameras.npz`` frame times).
        cams: view -> mapping with ``K``, ``T_world_cam`` (T, 4, 4) ... (``cameras_world.npz``).
        kps: view -> (T, J, 3) keypoints.

    Returns:
        ``(cams, kps)``: view 1 unchanged; view 2 resampled to view 1's length. Identity (view 2's
        own arrays) when the residual offset is 0 and the frame times agree, or when there is no
        sync record (sequences synced by older versions), or with one view (nothing to sync).
    """
    cams = {v: dict(cams[v].items()) for v in VIEWS if v in cams}
    kps = dict(kps)
    if len(cams) == 1 or not (out.final_sync.is_file() or out.sync.is_file()):
        return cams, kps
    v1, v2 = VIEWS
    off = read_final_sync(out).residual_s
    t1, t2 = (frame_times(read_cameras(out.view(v).cameras, "cameras")) if out.view(v).cameras.is_file() else
              frame_times(cams[v]) for v in VIEWS)
    t1, t2 = t1[: len(kps[v1])], t2[: len(kps[v2])]
    query = t1 + off
    if off == 0.0 and len(t1) == len(t2) and np.allclose(t1, t2, atol=1e-4):
        return cams, kps
    kp2, T2 = resample_view(kps[v2], np.asarray(cams[v2]["T_world_cam"])[: len(t2)], t2, query)
    lost = int((kp2[..., 2].max(axis=1) == 0).sum() - (kps[v2][..., 2].max(axis=1) == 0).sum())
    log.info("sub-frame sync: view %s resampled at view %s's instants %+.2f ms (%.3f frames at the median "
             "frame step)%s", v2, v1, 1e3 * off, off / float(np.median(np.diff(t1))) if len(t1) > 1 else 0.0,
             f"; {lost} frames without view {v2}" if lost > 0 else "")
    kps[v2] = kp2
    cams[v2]["T_world_cam"] = T2
    return cams, kps
