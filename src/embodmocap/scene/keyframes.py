"""Key frames of the scene capture: chosen by camera motion, without blurry frames or tracking jumps.

Three steps, each a small function:

1. :func:`detect_jumps` marks trajectory rows whose pose cannot be trusted: non-finite or
   non-rigid poses, and every row outside the largest run of mutually consistent poses once the
   trajectory is cut at speed spikes (a relocalisation moves the whole rest of the trajectory, so
   mixing both sides would fuse two copies of every wall).
2. :func:`motion_keyframes` walks the trusted rows and takes a new key frame once the camera centre
   is ``keyframe_step_m`` from the last key frame's centre, or has turned ``keyframe_step_deg``.
3. :func:`drop_blurriest` takes the motion key frames in consecutive groups of ``blur_window`` and
   drops the one with the lowest sharpness (:func:`blur_scores`) in every full group, as the
   paper's release does (``blur_filter_range`` 4).

:func:`choose_keyframes` runs all three on a capture; :func:`select_keyframes` does 2-3 given the
jump mask and the sharpness of the candidates.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.geometry.transforms import is_rigid, rotation_angle
from embodmocap.scene.config import SceneConfig
from embodmocap.types import Capture, CameraTrajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class KeyframeSelection:
    """The chosen key frames and why the others were left out.

    Attributes:
        frame_ids: (K,) int64 video frame indices of the key frames, increasing.
        rows: (K,) int64 rows of those frames in the capture's trajectory.
        dropped_blurry: (B,) int64 frame indices of motion key frames dropped as blurriest in
            their group.
        excluded_jumps: (J,) int64 frame indices whose poses were excluded (tracking jumps,
            non-finite or non-rigid poses).
        sharpness: (K,) float64 sharpness (variance of the Laplacian) of each key frame, NaN when
            it was not measured.
    """

    frame_ids: NDArray[np.int64]
    rows: NDArray[np.int64]
    dropped_blurry: NDArray[np.int64]
    excluded_jumps: NDArray[np.int64]
    sharpness: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.frame_ids)

    def reasons(self) -> dict[int, str]:
        """Frame index -> ``"blurry"`` or ``"tracking jump"`` for every frame left out on purpose."""
        out = {int(f): "tracking jump" for f in self.excluded_jumps}
        out.update({int(f): "blurry" for f in self.dropped_blurry})
        return out


# ------------------------------------------------------------------------------------------------
# Sharpness


def sharpness(rgb: NDArray[np.uint8], long_side_px: int = 320) -> float:
    """Variance of the Laplacian of a grey, downscaled copy of an (H, W, 3) uint8 image.

    Higher is sharper. Shrinking first (area averaging) makes the score cheap and stops sensor
    noise from dominating it; the same size must be used for every frame compared.
    """
    import cv2

    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    h, w = grey.shape
    s = long_side_px / max(h, w)
    if s < 1:
        grey = cv2.resize(grey, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_32F).var())


def blur_scores(capture: Capture, frame_ids: Sequence[int], long_side_px: int = 320,
                keep: dict[int, NDArray[np.uint8]] | None = None) -> NDArray[np.float64]:
    """(N,) sharpness of the given frames (higher = sharper), in the order given.

    Each frame is read once, in increasing frame order, so a video decoder only ever runs forward.
    ``keep``, when given, receives every frame read (frame index -> RGB), for a later step that
    needs some of the same frames (the sparse model's key frames) without decoding them again.
    """
    ids = np.asarray(frame_ids, dtype=np.int64)
    out = np.full(len(ids), np.nan)
    for i in np.argsort(ids, kind="stable"):
        rgb = capture.frames.rgb(int(ids[i]))
        out[i] = sharpness(rgb, long_side_px)
        if keep is not None:
            keep[int(ids[i])] = rgb
    return out


# ------------------------------------------------------------------------------------------------
# Tracking jumps


def _step_sizes(T: NDArray) -> tuple[NDArray, NDArray]:
    """Translation (metres) and rotation (degrees) of each consecutive step of (N, 4, 4) poses."""
    dist = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    R_rel = np.swapaxes(T[:-1, :3, :3], -1, -2) @ T[1:, :3, :3]
    return dist, np.degrees(rotation_angle(R_rel))


def _is_jump(dist: NDArray, ang: NDArray, dt: NDArray, cfg: SceneConfig, local_m: NDArray | None) -> NDArray[np.bool_]:
    """Which steps (dist m, ang deg over dt s) are jumps; ``local_m`` = typical step nearby (or None)."""
    jump = (dist / dt > cfg.jump_speed_mps) | (ang / dt > cfg.jump_rate_dps)
    if local_m is not None:
        jump |= (dist > cfg.jump_min_step_m) & (dist > cfg.jump_ratio * local_m)
    return jump


def _local_median(x: NDArray, half: int) -> NDArray:
    """Median of each element's neighbours within ``half`` on each side, the element excluded."""
    n = len(x)
    if n < 2:
        return np.full(n, np.inf)
    pad = np.pad(x, half, mode="constant", constant_values=np.nan)
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * half + 1).copy()  # (n, 2h+1)
    win[:, half] = np.nan  # the step under test must not vouch for itself
    return np.nanmedian(win, axis=1)


def detect_jumps(trajectory: CameraTrajectory, fps: float, cfg: SceneConfig = SceneConfig()) -> NDArray[np.bool_]:
    """(T,) bool: rows of the trajectory whose pose must not be used.

    A row is bad when its pose is non-finite or not a rotation, or when it lies outside the largest
    group of mutually consistent rows. Consistency: the trajectory of good poses is cut wherever a
    step is faster than ``jump_speed_mps`` / ``jump_rate_dps`` or much longer than its neighbours'
    (``jump_ratio``); each piece then joins the first earlier group whose last pose it continues
    smoothly (so a glitch of a few frames that comes back is removed alone), or starts a new group.
    """
    T = np.asarray(trajectory.T_world_cam, dtype=np.float64)
    n = len(T)
    bad = ~is_rigid(T, atol=1e-3)
    good = np.flatnonzero(~bad)
    if len(good) < 2:
        return bad
    Tg = T[good]
    fids = np.asarray(trajectory.frame_ids, dtype=np.float64)[good]
    dt = np.maximum(np.diff(fids), 1.0) / fps
    dist, ang = _step_sizes(Tg)
    cut = _is_jump(dist, ang, dt, cfg, _local_median(dist, cfg.jump_neighbours))

    # Pieces between cuts: [starts[k], ends[k]) in Tg rows. Few pieces, so a plain loop is clear.
    starts = np.concatenate([[0], np.flatnonzero(cut) + 1])
    ends = np.concatenate([starts[1:], [len(Tg)]])
    groups: list[list[int]] = []  # piece indices per group
    typical = float(np.median(dist)) if len(dist) else 0.0
    for k, (s, _) in enumerate(zip(starts, ends)):
        for g in groups:
            last = ends[g[-1]] - 1
            gap_T = Tg[[last, s]]
            d, a = _step_sizes(gap_T)
            gap_dt = np.array([max(fids[s] - fids[last], 1.0) / fps])
            # Over a gap the camera may have moved more, so compare with the speed limits only,
            # plus the ratio test against the capture's typical step scaled by the gap length.
            scaled = np.array([typical * gap_dt[0] * fps])
            if not _is_jump(d, a, gap_dt, cfg, scaled)[0]:
                g.append(k)
                break
        else:
            groups.append([k])
    sizes = [sum(ends[k] - starts[k] for k in g) for g in groups]
    keep = groups[int(np.argmax(sizes))]
    keep_rows = np.concatenate([np.arange(starts[k], ends[k]) for k in keep])
    inconsistent = np.ones(len(Tg), dtype=bool)
    inconsistent[keep_rows] = False
    bad[good[inconsistent]] = True
    return bad


# ------------------------------------------------------------------------------------------------
# Selection


def motion_keyframes(trajectory: CameraTrajectory, cfg: SceneConfig, indoor: bool,
                     excluded: NDArray[np.bool_] | None = None) -> NDArray[np.int64]:
    """(K,) trajectory rows chosen by camera motion (the first usable row is always one).

    A row becomes a key frame once its camera centre is at least ``keyframe_step_m(indoor)``
    (straight line) from the last key frame's centre, or its rotation differs from the last key
    frame's by at least ``keyframe_step_deg``. Rows marked in ``excluded`` are skipped.
    """
    T = np.asarray(trajectory.T_world_cam, dtype=np.float64)
    rows = np.arange(len(T)) if excluded is None else np.flatnonzero(~np.asarray(excluded, bool))
    return _motion_gate(T, rows, cfg.keyframe_step_m(indoor), cfg.keyframe_step_deg)


def _motion_gate(T: NDArray, rows: NDArray[np.int64], step_m: float, step_deg: float) -> NDArray[np.int64]:
    """The subset of ``rows`` (increasing) where the camera of ``T`` (N, 4, 4) has moved
    ``step_m`` or turned ``step_deg`` since the last row taken; the first row is always taken."""
    if len(rows) == 0:
        return np.zeros(0, dtype=np.int64)
    cos_step = np.cos(np.radians(step_deg))
    C, R = T[rows, :3, 3], T[rows, :3, :3]
    chosen = [0]
    # Greedy and sequential by nature (each choice depends on the previous key frame); the loop
    # body is O(1), so even a 10-minute capture takes milliseconds.
    for i in range(1, len(rows)):
        k = chosen[-1]
        moved = np.sum((C[i] - C[k]) ** 2) >= step_m**2
        # cos of the relative angle = (trace(R_k^T R_i) - 1) / 2, without forming the product.
        turned = (np.sum(R[k] * R[i]) - 1.0) / 2.0 <= cos_step
        if moved or turned:
            chosen.append(i)
    return rows[np.asarray(chosen, dtype=np.int64)]


def fusion_rows(capture: Capture, cfg: SceneConfig) -> NDArray[np.int64]:
    """(F,) trajectory rows to fuse into the mesh: every row with a trusted pose (no tracking
    jump, :func:`detect_jumps`) once the camera moved ``cfg.fuse_step_m`` or turned
    ``cfg.fuse_step_deg`` since the last one (many more than the SfM key frames; blur does not
    matter to depth). Frames with too little valid depth are dropped later, when read."""
    traj = capture.trajectory
    excluded = detect_jumps(traj, capture.fps, cfg)
    T = np.asarray(traj.T_world_cam, dtype=np.float64)
    return _motion_gate(T, np.flatnonzero(~excluded), cfg.fuse_step_m, cfg.fuse_step_deg)


def drop_blurriest(sharp: NDArray, window: int) -> NDArray[np.bool_]:
    """(K,) bool keep-mask: in each full group of ``window`` consecutive entries, the least sharp
    one is dropped (a trailing partial group is kept whole). NaN sharpness counts as sharpest."""
    sharp = np.asarray(sharp, dtype=np.float64)
    keep = np.ones(len(sharp), dtype=bool)
    if window <= 1:
        return keep
    full = len(sharp) // window * window
    groups = np.where(np.isnan(sharp[:full]), np.inf, sharp[:full]).reshape(-1, window)
    worst = np.argmin(groups, axis=1) + np.arange(len(groups)) * window
    keep[worst] = False
    return keep


def select_keyframes(trajectory: CameraTrajectory, blur: NDArray | None, cfg: SceneConfig, indoor: bool,
                     excluded: NDArray[np.bool_] | None = None, capture_path=None) -> KeyframeSelection:
    """Key frames by motion, minus the blurriest of each group, minus excluded rows.

    Args:
        trajectory: the capture's poses (T rows).
        blur: (T,) sharpness per trajectory row (only the motion key frames' entries are read; the
            rest may be NaN), or None to skip the blur filter.
        cfg: settings; ``indoor`` picks the translation step.
        excluded: (T,) bool rows not to use (from :func:`detect_jumps`), or None.
        capture_path: named in the error message.

    Raises:
        InputError: fewer than ``cfg.min_keyframes`` key frames remain.
    """
    n = len(trajectory)
    excluded = np.zeros(n, dtype=bool) if excluded is None else np.asarray(excluded, dtype=bool)
    if excluded.shape != (n,):
        raise ValueError(f"excluded must be ({n},), got {excluded.shape}")
    fids = np.asarray(trajectory.frame_ids, dtype=np.int64)
    if excluded.any():
        log.warning("%s: %d of %d frames excluded (tracking jumps or invalid poses)",
                    capture_path or "capture", int(excluded.sum()), n)
    rows = motion_keyframes(trajectory, cfg, indoor, excluded)
    sharp = np.full(len(rows), np.nan) if blur is None else np.asarray(blur, dtype=np.float64)[rows]
    keep = drop_blurriest(sharp, cfg.blur_window) if blur is not None else np.ones(len(rows), bool)
    sel = KeyframeSelection(
        frame_ids=fids[rows[keep]], rows=rows[keep], dropped_blurry=fids[rows[~keep]],
        excluded_jumps=fids[excluded], sharpness=sharp[keep],
    )
    log.info("%d key frames (%d blurry dropped, %d frames excluded)", len(sel), int((~keep).sum()), int(excluded.sum()))
    if len(sel) < cfg.min_keyframes:
        raise InputError(
            capture_path, f"only {len(sel)} usable key frames (need {cfg.min_keyframes}; "
            f"{int(excluded.sum())} of {n} frames excluded for tracking jumps)",
            "record the scene longer, walking around it slowly, or lower min_keyframes",
        )
    return sel


def choose_keyframes(capture: Capture, cfg: SceneConfig, indoor: bool,
                     keep: dict[int, NDArray[np.uint8]] | None = None) -> KeyframeSelection:
    """Key frames of a scene capture: jumps excluded, motion steps, blurriest of each group dropped.

    Only the motion key frames are decoded (once each) to measure their sharpness; ``keep``, when
    given, receives the chosen key frames' RGB (frame index -> (H, W, 3) uint8) from that decoding.
    """
    traj = capture.trajectory
    excluded = detect_jumps(traj, capture.fps, cfg)
    rows = motion_keyframes(traj, cfg, indoor, excluded)
    blur = np.full(len(traj), np.nan)
    if cfg.blur_window > 1 and len(rows):
        blur[rows] = blur_scores(capture, traj.frame_ids[rows], cfg.blur_long_side_px, keep)
    sel = select_keyframes(traj, blur, cfg, indoor, excluded, capture_path=capture.path)
    if keep is not None:  # only the chosen ones stay (the blurriest of each group are dropped)
        chosen = set(int(i) for i in sel.frame_ids)
        for i in [i for i in keep if i not in chosen]:
            del keep[i]
    return sel
