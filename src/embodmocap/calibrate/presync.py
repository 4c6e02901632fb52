"""Stage III's sub-frame sync before the refinement, and the cross-view track on one clock.

Two phones never film in phase: view 2's frame ``k`` is taken a fraction of a frame off view 1's
frame ``k`` (after the slicing), so the performer has moved between the two observations. The
refinement's cross-view track term pairs the two views' back-projected keypoints of the same
sequence frame; with a phase it pulls view 2's cameras by the performer's motion over that
fraction, i.e. towards "in phase", and the geometric sync measured afterwards on those cameras sees
part of the phase gone (2026-12-05-s10-syncphase: -0.126 frame measured for -0.341 on the refined
cameras, -0.275 on the registration-only ones).

So, before the refinement (:func:`presync_residual`): the geometric sync and the choice of source
(:func:`embodmocap.calibrate.final_sync.geometric_sync`) run on the registration-only cameras, and
their ``residual_s`` (what Stage IV would apply) puts view 2's track points on view 1's clock
(:func:`track_pairs_on_clock`): each view-2 joint, back-projected with depth at the two frames that
bracket view 1's instant, is interpolated linearly in view 2's VIO world (where the offsets being
refined act rigidly, so interpolating there commutes with them) and expressed in the camera of view
2's frame ``k`` again, so that the pair still indexes both views' cameras by one frame. Step 4 then
measures the sync again on the refined cameras (the final check, what is applied).
"""

from __future__ import annotations

import logging
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from embodmocap.calibrate.inputs import ViewInputs
from embodmocap.errors import InputError
from embodmocap.io.layout import VIEWS

log = logging.getLogger(__name__)


def presync_residual(cfg, record: dict, views: Mapping[str, ViewInputs], T_world_vio: Mapping[str, NDArray],
                     fps: float, label: str = "", subframe_sync: bool = True,
                     sync_force: bool = False) -> tuple[float, dict]:
    """View 2's time offset (seconds, on top of the slicing) the final choice would apply with the
    given (registration-only) offsets, and a record of it for ``calibration.json``.

    Runs without the laser same-dot check (it reads the videos; step 4 runs it): a choice that
    needs it, or that raises (nothing usable), gives 0 here and step 4 decides as before. A residual
    beyond ``cfg.presync_max_frames`` (a choice of another integer offset than the slicing's) is
    not applied either: the track pairs are sequence-frame pairs, meaningful near the slicing only.

    Args:
        cfg: the :class:`~embodmocap.calibrate.config.CalibrateConfig`; record: Stage II's ``sync.json``;
        views: the views' Stage II data; T_world_vio: view -> (4, 4) registration-only offset;
        fps: the sequence frame rate; label: the sequence (log lines); subframe_sync, sync_force:
        the sequence's session.toml keys.
    """
    from embodmocap.calibrate.final_sync import geometric_sync

    try:
        geo = geometric_sync(cfg, record, views, T_world_vio, fps, None, f"{label} (registration cameras)",
                             None, subframe_sync, sync_force)
    except InputError as err:  # step 4 raises it again (or decides otherwise on the refined cameras)
        return 0.0, {"applied": False, "residual_frames": 0.0, "reason": f"no choice: {err}"}
    ch = geo.record["chosen"]
    res = float(ch["residual_s"])
    info = {"source": ch["source"], "residual_frames": round(res * fps, 4),
            "geometric_offset_frames": geo.figures["geometric_offset_frames"],
            "geometric_std_frames": None if geo.geometric is None or not geo.geometric.found
            else round(float(geo.geometric.std_frames), 4)}
    if abs(res * fps) > cfg.presync_max_frames:
        return 0.0, {**info, "applied": False, "reason": f"beyond {cfg.presync_max_frames:g} frame of the slicing"}
    return res, {**info, "applied": res != 0.0}


def track_pairs_on_clock(views: Mapping[str, ViewInputs], frames: NDArray, residual_s: float, fps: float,
                         source, max_depth_m: float = 6.0):
    """The cross-view track pairs of sequence frames ``frames`` (view 1's), with view 2's points at
    view 1's instants: view 2 sampled ``residual_s`` later on its own clock (Stage IV's convention,
    :mod:`embodmocap.sequence.subframe`).

    Args:
        views: both views' Stage II data (cameras with ``frame_times_s``, keypoints, depth).
        frames: (F,) view 1's sequence frames to use.
        residual_s: view 2's time minus view 1's for one instant, on top of the slicing, seconds.
        fps: the sequence frame rate (frame times of files without them).
        source: the :class:`~embodmocap.calibrate.losses.KeypointCorrespondences` settings (joints,
            confidence threshold, joint depth behind the surface), applied to both views.

    Returns:
        :class:`~embodmocap.calibrate.losses.TrackPairs` (view 2's points in its frame-``f`` camera),
        or None when no pair has depth in both views.
    """
    from embodmocap.calibrate import losses as L
    from embodmocap.geometry.interpolate import bracket
    from embodmocap.geometry.transforms import apply_T, invert_T
    from embodmocap.sequence.subframe import frame_times

    v1, v2 = VIEWS
    c1, c2 = views[v1].cameras, views[v2].cameras
    kp1 = np.asarray(views[v1].keypoints, dtype=np.float64)
    kp2 = np.asarray(views[v2].keypoints, dtype=np.float64)
    T2 = np.asarray(c2["T_world_cam"], dtype=np.float64)
    n2 = min(len(kp2), len(T2))
    j = np.asarray(source.joints, dtype=np.int64)
    behind = np.asarray(source.depth_behind_surface_m, dtype=np.float64)[j]
    frames = np.asarray(frames, dtype=np.int64)
    frames = frames[frames < min(len(kp1), n2)]  # view 2's frame f holds the pair's camera
    t1 = frame_times(c1, fps)[frames]
    t2 = frame_times(c2, fps)[:n2]
    # View 2's samples: a strictly increasing time subsequence (a dropped frame sliced twice keeps its first).
    keep = np.concatenate([[True], np.diff(t2) > 0]) & (np.maximum.accumulate(t2) == t2)
    idx = np.nonzero(keep)[0]
    i0, w, inside = bracket(t2[idx], t1 + residual_s)
    k0 = idx[i0]
    k1 = idx[np.minimum(i0 + 1, len(idx) - 1)]
    # A query on a sample (w 0 or 1) needs that sample only.
    w = np.where(w < 1e-9, 0.0, np.where(w > 1 - 1e-9, 1.0, w))
    k0 = np.where(w == 1.0, k1, k0)
    w = np.where(w == 1.0, 0.0, w)
    a = kp1[frames][:, j]  # (F, J, 3)
    b0, b1 = kp2[k0][:, j], kp2[k1][:, j]
    both = w[:, None] > 0
    conf2 = np.where(both, np.minimum(b0[..., 2], b1[..., 2]), b0[..., 2])
    conf = np.minimum(a[..., 2], conf2)
    ok = ((conf > source.min_confidence) & inside[:, None] & np.isfinite(a).all(-1) & np.isfinite(b0).all(-1)
          & (~both | np.isfinite(b1).all(-1)))
    fi, ji = np.nonzero(ok)
    if len(fi) == 0:
        return None
    size = lambda c: (int(c["width"]), int(c["height"]))  # noqa: E731
    da = L.sample_depth(views[v1].depth_m, frames[fi], a[fi, ji, :2], size(c1))
    d0 = L.sample_depth(views[v2].depth_m, k0[fi], b0[fi, ji, :2], size(c2))
    two = both[fi, 0]
    d1 = np.zeros(len(fi))
    if two.any():
        d1[two] = L.sample_depth(views[v2].depth_m, k1[fi][two], b1[fi, ji, :2][two], size(c2))
    good = lambda d: (d > 0) & (d < max_depth_m)  # noqa: E731
    valid = good(da) & good(d0) & (~two | good(d1))
    fi, ji, two, da, d0, d1 = fi[valid], ji[valid], two[valid], da[valid], d0[valid], d1[valid]
    if len(fi) == 0:
        return None
    pa = L.backproject(a[fi, ji, :2], da, c1["K"], behind[ji])

    def vio(k, xy, d):  # view 2's frame-k pixels with depth -> its VIO world
        p = L.backproject(xy, d, c2["K"], behind[ji])
        return apply_T(T2[k], p[:, None])[:, 0]

    y = vio(k0[fi], b0[fi, ji, :2], d0)
    if two.any():
        y1 = vio(k1[fi], b1[fi, ji, :2], d1)
        ww = w[fi][:, None]
        y = np.where(two[:, None], (1.0 - ww) * y + ww * y1, y)
    f = frames[fi]
    # Back into view 2's frame-f camera: the refinement indexes both views' cameras by one frame.
    pb = apply_T(invert_T(T2[f]), y[:, None])[:, 0]
    log.debug("track pairs on view %s's clock (view %s %+.3f frames): %d pairs", v1, v2, residual_s * fps, len(f))
    return L.make_track_pairs(VIEWS, f, pa, pb, conf[fi, ji])
