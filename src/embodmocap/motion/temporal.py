"""Temporal consistency of each view's 2D keypoints: runs of a joint that jump away from its own
trajectory and back are a detector's guesses, not the joint.

A detector's blunders on a limb come in runs: a hidden joint guessed at a wrong place for 5-20
frames, a left/right confusion the swap check could not undo (the other view does not see the
limb), a single-frame outlier. With two views such a guess triangulates along the other view's
ray with little reprojection error, and at the start of a sequence (or after a gap) nothing in
the past contradicts it. The trajectory of the joint *relative to the body* in the same view does:
it jumps when the guess starts and when it ends, and the frames on either side agree with each
other, not with the run between. So, per view and joint:

1. the joint's position relative to the view's torso centre, in units of the torso's size (robust
   to the person walking towards or away from the camera and to the camera moving);
2. cut into segments at jumps (a step between detected frames larger than ``jump`` torso lengths,
   plus ``jump_per_frame`` for every frame of a gap) and at long gaps;
3. a segment of at most ``max_run`` frames bounded by a jump on at least one side and by a jump or
   the end of the run of detections on the other, is a guess: when it has neighbours on both sides
   the neighbours must agree with each other better than with the segment (the body returned to
   where it was); at the start or the end of the detections (no past, or no future, to compare
   with) it is judged against the longer segment after (before) it.

The flagged detections get confidence 0 in that view only: the other view, the 3D keypoints'
neighbours and the fit's smoothness carry the joint there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

#: COCO-17 indices checked (elbows, wrists, knees, ankles): the limb ends a detector guesses.
LIMB_JOINTS: tuple[int, ...] = (7, 8, 9, 10, 13, 14, 15, 16)
#: COCO-17 torso points (shoulders, hips) whose centre and size the trajectories are relative to.
TORSO: tuple[int, ...] = (5, 6, 11, 12)


@dataclass(frozen=True)
class TemporalConfig:
    """How runs of a view's 2D keypoints that leave their own trajectory are found."""

    enabled: bool = True
    """Find and drop such runs (False: keep every detection)."""
    min_conf: float = 0.1
    """Detections below this confidence are treated as missing."""
    jump: float = 0.35
    """A step between consecutive frames larger than this (torso lengths, relative to the torso
    centre) cuts the trajectory. A torso length is ~0.5 m: 0.35 is ~17 cm in one frame at 30 fps,
    faster than a wrist moves relative to the body in everyday motion; a wrong guess of a hidden
    joint jumps 8-20 % of the height (0.3-0.7 torso lengths), an outlier further."""
    jump_per_frame: float = 0.12
    """Added to ``jump`` for every missing frame between two detections."""
    max_gap: int = 10
    """Detections more than this many frames apart belong to different runs (nothing to compare)."""
    torso_conf: float = 0.3
    """Torso points below this confidence do not place the torso centre (a hidden hip's guess
    jitters several times more than a seen one)."""
    max_run: int = 30
    """Longest segment (frames) between jumps that can be judged a wrong guess; a longer one is
    taken as the limb's real motion."""
    flag_min_conf: float = 0.3
    """Only detections at least this confident are dropped (the weaker ones still shape the
    trajectories; below the triangulation's threshold they only enter the fit's 2D term, weighted
    by their confidence)."""
    min_reference: int = 0
    """At the start (end) of a run of detections, the segment after (before) a jump judges the one
    before (after) it only when it is longer than this many frames (and than that one)."""
    middle: bool = False
    """Also judge segments with neighbours on both sides (not only those at the start or the end
    of a run of detections). Off by default: in the middle of a run the fit's robust terms and
    the neighbouring frames already write a guess off, and on the hard studio sessions this rule
    dropped several good detections for each wrong one: W-MPJPE worse on 3 of the first 4 of the
    ten sessions (seed 2: W 77 -> 97 mm, PA 29 -> 57 mm; issue 11, third pass)."""
    confirm_frames: int = 1
    """At the start (end) of a run of detections, the jump that cuts the first (last) segment off
    must hold for this many of the longer segment's frames next to it: the segment is judged a
    guess only when none of them (the allowance for their distance in frames added) lies within
    ``jump`` of its nearest frame. One wayward detection right after a run's correct first frames
    otherwise cut them off and had them dropped (studio seed 3, outdoor: view 1's left wrist in
    the first 6 frames after the person came into view, confidence 0.74-0.93 and 2-9 px from the
    truth, dropped because frame 39 strayed 0.39 torso lengths and came back; the fit's wrist
    16-27 cm off there). 1 (default): the single step decides. 3 was measured on the five studio
    sessions of 2026-12-04 (session 8) and not kept: it kept seed 3's correct start, but also
    outdoor seed 1's wrong leg labels at a run's start (legs crossing: the wrong label lies
    within a jump of the next frames), W-MPJPE c100 26.8 -> 38.5 mm there."""


def temporal_outliers(kp: NDArray, cfg: TemporalConfig = TemporalConfig()) -> NDArray[np.bool_]:
    """(T, V, J) True where a view's 2D keypoint lies in a run that jumps off its trajectory.

    Args:
        kp: (T, V, J, 3) COCO-17-ordered pixels and confidence of every view (J = 17).
        cfg: thresholds.
    """
    kp = np.asarray(kp, dtype=np.float64)
    T, V, J = kp.shape[:3]
    out = np.zeros((T, V, J), dtype=bool)
    if not cfg.enabled or T < 3:
        return out
    for v in range(V):
        rel = _torso_relative(kp[:, v], cfg.torso_conf)
        if rel is None:
            continue
        for j in LIMB_JOINTS:
            seen = (kp[:, v, j, 2] >= cfg.min_conf) & np.isfinite(rel[:, j]).all(-1)
            out[:, v, j] = _guessed_runs(rel[:, j], seen, cfg) & (kp[:, v, j, 2] >= cfg.flag_min_conf)
    return out


def _torso_relative(kp: NDArray, min_conf: float, partial: bool = False, partial_frames: int | None = None
                    ) -> NDArray | None:
    """(T, J, 2) points minus the torso centre, over the torso's size (NaN where the centre is
    unknown); None when no frame has the whole torso. ``partial``: a frame before the first whole
    torso (after the last) that sees both shoulders or both hips takes its centre from them
    (:func:`_partial_centres`) instead of holding the first (last) whole torso's; with
    ``partial_frames``, only within that many frames of it."""
    T = len(kp)
    torso = kp[:, list(TORSO)]
    full = (torso[..., 2] >= min_conf).all(-1)
    if full.sum() < 2:
        return None
    t = np.arange(T)
    centre = torso[..., :2].mean(1)
    shoulders, hips = torso[:, :2, :2].mean(1), torso[:, 2:, :2].mean(1)
    size = np.linalg.norm(shoulders - hips, axis=-1)
    # Interpolate the centre over frames without the whole torso (it moves smoothly); the size
    # through a running median of the sequence (a person's size in the image changes slowly).
    # The centre through a short running median (its own points jitter), the size through a long
    # one (a person's size in the image changes slowly). The centre's window stays centred: near
    # the first (last) frame of a run of torsos it shrinks on both sides, since a window cut on
    # one side is the median of the frames after (before) the frame, up to 1.5 frames of image
    # motion off (issue 29: outdoor seed 5, the person entering view 1 at 40 px a frame, the
    # first frame's correct wrist and elbow 0.5 torso lengths from the next frames, dropped as a
    # guess, the fitted hand 11 cm off).
    c = np.stack([np.interp(t, t[full], _centred_median(np.where(full, centre[:, k], np.nan), 3)[full])
                  for k in range(2)], -1)
    s = np.interp(t, t[full], _running_median(np.where(full, size, np.nan), 15)[full])
    s = np.maximum(s, 1.0)
    if partial:
        c = _partial_centres(torso, full, c, min_conf, partial_frames)
    return (kp[..., :2] - c[:, None]) / s[:, None, None]


def _partial_centres(torso: NDArray, full: NDArray, c: NDArray, min_conf: float, within: int | None = None
                     ) -> NDArray:
    """(T, 2) ``c`` with each frame before the first whole torso or after the last that sees both
    shoulders or both hips (``torso`` (T, 4, 3): shoulders, hips) centred on them: their middle
    plus the offset from that middle to the centre in the nearest frame with the whole torso. Where a person enters the view, the centre held from the
    first whole torso is a frame or more of image motion off (issue 29, hard outdoor studio seed
    1: the person enters view 1 at frame 32 with the hips seen and the shoulders not; measured
    against frame 33's centre, the legs' step 32 -> 33 cost about as much under either label
    state, so view 1's legs, exchanged in 33-36, stayed exchanged)."""
    seen = torso[..., 2] >= min_conf
    whole = np.flatnonzero(full)
    # Only before the first whole torso and after the last, where the centre is held (between
    # two whole torsos the interpolated one was better on the hard studio seeds: frames seeing a
    # shoulder and a hip, often one a guess, centred on them turned seed 3's arms and seed 5's).
    outside = (np.arange(len(torso)) < whole[0]) | (np.arange(len(torso)) > whole[-1])
    # A left-right pair (both shoulders or both hips): its middle stays on the body's midline
    # as the person turns; one side's shoulder and hip do not (seed 5's end, view 2 seeing the
    # left side only: centred on it, that view's correct legs were exchanged in nine frames).
    pairs = np.stack([seen[:, :2].all(-1), seen[:, 2:].all(-1)], -1)  # (T, 2): shoulders, hips
    part = outside & pairs.any(-1)
    if within is not None:
        # Near the whole torso only: the offset from a pair's middle to the torso centre is taken
        # from the nearest whole torso, and holds while the person is entering or leaving, not
        # over a long stretch in which the view sees one side (hard outdoor studio seed 3, random
        # phase: view 2 sees the whole torso in frames 1-19 only; 150 frames centred on frame
        # 19's offset exchanged its correct arm labels in frames 1-8).
        t = np.arange(len(torso))
        part &= (whole[0] - t <= within) & (t - whole[-1] <= within)
    if not part.any():
        return c
    out = c.copy()
    for t in np.flatnonzero(part):
        f = whole[np.argmin(np.abs(whole - t))]
        m = slice(0, 2) if pairs[t, 0] else slice(2, 4)
        out[t] = torso[t, m, :2].mean(0) + torso[f, :, :2].mean(0) - torso[f, m, :2].mean(0)
    return out


def _centred_median(x: NDArray, h: int) -> NDArray:
    """(T,) median of each frame's centred window of 2k+1 frames, k the largest up to ``h`` whose
    window has no missing (NaN) value (NaN where the frame's own is)."""
    out = np.array(x, dtype=np.float64, copy=True)
    for k in range(1, h + 1):
        pad = np.concatenate([np.full(k, np.nan), x, np.full(k, np.nan)])
        m = np.median(np.lib.stride_tricks.sliding_window_view(pad, 2 * k + 1), axis=-1)  # NaN if any is
        if not np.isfinite(m).any():
            break
        out = np.where(np.isfinite(m), m, out)  # a window with no hole at k has none at k - 1
    return out


def _running_median(x: NDArray, h: int) -> NDArray:
    """(T,) centred running median over 2h+1 frames ignoring NaN (NaN where the window has none)."""
    import warnings

    pad = np.concatenate([np.full(h, np.nan), x, np.full(h, np.nan)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(np.lib.stride_tricks.sliding_window_view(pad, 2 * h + 1), axis=-1)


def _guessed_runs(r: NDArray, seen: NDArray, cfg: TemporalConfig) -> NDArray[np.bool_]:
    """(T,) frames of ``r`` (T, 2) (valid where ``seen``) in a short segment that jumped off.

    Shortest first: a one-frame outlier cuts the trajectory twice and would make the good frames
    between two of them look like a segment that jumped off; once it is removed they join their
    neighbours. So the shortest qualifying segments are flagged, the rest re-cut, until none is left.
    """
    flag = np.zeros(len(r), dtype=bool)
    seen = seen.copy()
    while True:
        found = _short_segments(r, seen, cfg)
        if not found:
            return flag
        shortest = min(s[-1] - s[0] for s in found)
        for s in found:
            if s[-1] - s[0] == shortest:
                flag[s] = True
                seen[s] = False


def _short_segments(r: NDArray, seen: NDArray, cfg: TemporalConfig) -> list[list[int]]:
    """The segments of the detected frames that :func:`_guessed_runs` would flag now."""
    idx = np.flatnonzero(seen)
    if len(idx) < 2:
        return []
    # Segments of detected frames: cut at long gaps (a "border") and at jumps.
    segs: list[list[int]] = [[int(idx[0])]]
    left_cut = ["border"]
    step = np.linalg.norm(r[idx[1:]] - r[idx[:-1]], axis=-1)
    gap = np.diff(idx)
    for k, b in enumerate(idx[1:]):
        if gap[k] > cfg.max_gap:
            segs.append([int(b)])
            left_cut.append("border")
        elif step[k] > cfg.jump + cfg.jump_per_frame * (gap[k] - 1):
            segs.append([int(b)])
            left_cut.append("jump")
        else:
            segs[-1].append(int(b))
    right_cut = left_cut[1:] + ["border"]
    n = len(segs)
    span = [s[-1] - s[0] + 1 for s in segs]
    found = []
    for k, s in enumerate(segs):
        lc, rc = left_cut[k], right_cut[k]
        if span[k] > cfg.max_run or "jump" not in (lc, rc):
            continue
        if lc == "jump" and rc == "jump":
            if not cfg.middle:
                continue
            # Both neighbours: they must agree with each other better than with the segment.
            a, b = segs[k - 1][-1], segs[k + 1][0]
            across = np.linalg.norm(r[b] - r[a]) - cfg.jump_per_frame * (b - a - 1)
            into = min(np.linalg.norm(r[s[0]] - r[a]), np.linalg.norm(r[s[-1]] - r[b]))
            if across < into and span[k] <= max(span[k - 1], span[k + 1]):
                found.append(s)
        elif lc == "jump":  # at the end of the detections: judged against the segment before
            if span[k - 1] > max(span[k], cfg.min_reference) and _jump_holds(r, s[0], segs[k - 1][::-1], cfg):
                found.append(s)
        elif (k + 1 < n and span[k + 1] > max(span[k], cfg.min_reference)
              and _jump_holds(r, s[-1], segs[k + 1], cfg)):
            # At the start of the detections (the sequence's, or after a gap): no past to compare
            # with, so the longer segment after it judges it (propagation backwards).
            found.append(s)
    return found


def _jump_holds(r: NDArray, edge: int, other: list[int], cfg: TemporalConfig) -> bool:
    """Whether frame ``edge`` of an edge segment is more than a jump from each of the first
    ``cfg.confirm_frames`` frames of ``other`` (the neighbouring segment, nearest frame first),
    allowing ``jump_per_frame`` for every frame between them."""
    near = np.asarray(other[:max(cfg.confirm_frames, 1)])
    d = np.linalg.norm(r[near] - r[edge], axis=-1) - cfg.jump_per_frame * (np.abs(near - edge) - 1)
    return bool((d > cfg.jump).all())


def drop_guessed_runs(kp: NDArray, cfg: TemporalConfig = TemporalConfig()) -> tuple[NDArray, NDArray[np.bool_]]:
    """``kp`` (T, V, J, 3) with the confidence of :func:`temporal_outliers`' detections set to 0
    (a new array; the input is not modified), and those (T, V, J) flags."""
    flags = temporal_outliers(kp, cfg)
    out = np.array(kp, dtype=np.float64, copy=True)
    out[..., 2] = np.where(flags, 0.0, out[..., 2])
    return out, flags
