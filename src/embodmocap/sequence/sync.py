"""Automatic laser-dot sync: find the frame where the dot on the wall disappears, in each view.

In a session someone shines a laser pointer on a wall both phones film, then switches it off. The
first frame of a view *without* the dot is that view's sync (event) frame. The paper has a person
read it off; here it is found automatically and a person only confirms it on a contact sheet.

How the detector works, reading each frame once, in order, at full resolution (up to
``max_width``): a real dot is a 2-3 px over-exposed core with a 5-10 px red halo, on any wall.

1. **Candidates** (:func:`find_dot_candidates`): near-saturated red pixels that stand out from
   their local background (top-hats of red and of red excess ``r - max(g, b)``) form small spots;
   each spot is compared with a ring around it (robust statistics: median and upper percentiles,
   so a textured or red wall is its own reference). A dot has a red rim confined to the spot and
   either an over-exposed white core or a core far redder than the ring: specular highlights and
   lamps have no red rim, the bright parts of red clothes and posters have as red pixels just
   outside, red paint is not brighter than its surroundings.
2. **Tracks**: the image's global motion between frames (phase correlation on a small grey copy)
   predicts where a dot, fixed on the wall, moves while the phone moves; candidates are linked to
   that prediction within a small residual gate (or to a constant-velocity guess in the next
   frame). A track may miss up to ``absent_frames - 1`` frames and continue: a dot hidden for a
   moment by the performer's arm and seen again at a consistent position is the same dot.
   Hysteresis: a track the candidate test misses in the next frame goes on where its spot still
   stands out nearly as strongly as when detected (``follow_strength``), so it ends where the dot
   really goes out, not where the strict test first fails.
3. **Events**: a track seen for at least ``min_seen_frames`` that then stays gone for
   ``absent_frames`` frames, whose place stays inside the image (a dot that leaves the field of
   view has not been switched off), ends with an event at the frame after its last sighting.
4. **Confidence**: how strongly the spot stood out just before versus how strongly its place
   (moved with the image) stands out just after (clean switch-off), whether the wall around the
   spot looks the same after (an occluder changes it), how long and how steadily the dot was seen.
   The best-scoring track wins.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Literal, Mapping

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.atomic import atomic_path
from embodmocap.sequence.laser_dots import (  # noqa: F401 (re-exported: SyncConfig is the sync's settings)
    DotCandidates, SyncConfig, _radius, _spot_centre, find_dot_candidates, spot_strength,
)
from embodmocap.types import Capture

log = logging.getLogger(__name__)

SYNC_JSON_VERSION = 1


# --------------------------------------------------------------------------- config and result


@dataclass(frozen=True)
class SyncEvent:
    """The sync event of one view.

    Attributes:
        frame: first raw frame of the capture *without* the dot (0-based video frame index).
        confidence: in [0, 1]; 1 for manual frames.
        dot_xy_before: (x, y) full-resolution pixel position of the dot in the last frame it was
            seen (OpenCV pixel centres), or None (manual frames).
        frames_seen: frames in which the dot was seen before the event (0 for manual frames).
        method: ``"auto"`` (detected) or ``"manual"`` (given in the manifest).
    """

    frame: int
    confidence: float
    dot_xy_before: tuple[float, float] | None = None
    frames_seen: int = 0
    method: Literal["auto", "manual"] = "auto"


# --------------------------------------------------------------------------- tracking


@dataclass
class _Track:
    """A dot followed across frames (mutable while the frames are read)."""

    frames: list[int] = field(default_factory=list)
    xy: list[NDArray] = field(default_factory=list)
    diameter: list[float] = field(default_factory=list)
    strength: list[float] = field(default_factory=list)
    ring: list[NDArray] = field(default_factory=list)
    after_strength: list[float] = field(default_factory=list)
    after_xy: list[NDArray] = field(default_factory=list)
    after_ring: NDArray | None = None
    detected: list[float] = field(default_factory=list)  # strengths of candidate-test sightings

    def predict(self, frame: int, motion: "_ImageMotion") -> tuple[NDArray | None, NDArray]:
        """Two guesses of the position at ``frame``: rigid with the image (the last position
        moved by the image's global motion since; None where that motion is unknown), and
        constant velocity. A dot on a wall moves with the wall; the second guess covers the
        frames where the global motion is off (strong motion blur, a large occluder)."""
        last = self.frames[-1]
        rigid = self.xy[-1] + motion.shift(last, frame) if motion.known(last, frame) else None
        p = self.xy[-1]
        if len(self.frames) >= 2:
            v = (self.xy[-1] - self.xy[-2]) / (self.frames[-1] - self.frames[-2])
            p = p + v * (frame - last)
        return rigid, p

    def add(self, frame: int, cands: DotCandidates, k: int) -> None:
        self.follow(frame, cands.xy[k], float(cands.diameter[k]), float(cands.strength[k]), cands.ring_rgb[k])
        self.detected.append(float(cands.strength[k]))

    def follow(self, frame: int, xy: NDArray, diameter: float, strength: float, ring: NDArray) -> None:
        """A sighting at ``frame``: a candidate, or (hysteresis) the spot still as strong."""
        self.frames.append(frame)
        self.xy.append(np.asarray(xy, np.float64))
        self.diameter.append(diameter)
        self.strength.append(strength)
        self.ring.append(ring)
        self.after_strength.clear()  # it was only hidden: what follows its new last sighting counts
        self.after_xy.clear()
        self.after_ring = None


class _ImageMotion:
    """The image's global translation between consecutive frames (phase correlation on a small
    grey copy), accumulated so the shift between any two frames read is a subtraction."""

    def __init__(self, cfg: SyncConfig) -> None:
        self.cfg = cfg
        self.cum: list[NDArray] = []  # cumulative shift (x, y) in analysed pixels, per frame
        self.bad: list[int] = []  # cumulative count of frames whose shift is unknown
        self._prev = None
        self._win = None

    def add(self, img: NDArray[np.uint8]) -> None:
        import cv2

        H, W = img.shape[:2]
        mw = min(W, self.cfg.motion_width)
        mh = max(8, int(round(H * mw / W)))
        g = cv2.resize(cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY), (mw, mh),
                       interpolation=cv2.INTER_AREA).astype(np.float32)
        shift, ok = np.zeros(2), False
        if self._prev is not None and self._prev.shape == g.shape:
            if self._win is None or self._win.shape != g.shape:
                self._win = cv2.createHanningWindow((mw, mh), cv2.CV_32F)
            (dx, dy), resp = cv2.phaseCorrelate(self._prev, g, self._win)
            if resp >= self.cfg.min_motion_response:
                shift, ok = np.array([dx, dy]) * (W / mw), True
        first = not self.cum
        self.cum.append(shift if first else self.cum[-1] + shift)
        self.bad.append(0 if first else self.bad[-1] + (0 if ok else 1))
        self._prev = g

    def known(self, a: int, b: int) -> bool:
        return self.bad[b] == self.bad[a]

    def shift(self, a: int, b: int) -> NDArray:
        return self.cum[b] - self.cum[a]


def _greedy_pairs(dist: NDArray, ok: NDArray) -> list[tuple[int, int]]:
    """Closest-first matching of a (tracks, candidates) distance matrix where ``ok`` allows it."""
    pairs, used_t, used_c = [], set(), set()
    for flat in np.argsort(dist, axis=None):
        ti, ci = (int(v) for v in np.unravel_index(flat, dist.shape))
        if ok[ti, ci] and ti not in used_t and ci not in used_c:
            pairs.append((ti, ci))
            used_t.add(ti)
            used_c.add(ci)
    return pairs


def _downscale(rgb: NDArray[np.uint8], max_width: int) -> tuple[NDArray[np.uint8], float]:
    """Area-averaged downscale to at most ``max_width`` wide; returns (image, scale <= 1)."""
    import cv2

    H, W = rgb.shape[:2]
    if W <= max_width:
        return rgb, 1.0
    s = max_width / W
    return cv2.resize(rgb, (max_width, max(1, int(round(H * s)))), interpolation=cv2.INTER_AREA), s


def _track_dots(frames: Iterable[NDArray[np.uint8]], cfg: SyncConfig) -> tuple[list[_Track], int, tuple[int, int]]:
    """Read frames in order and follow every dot candidate.

    Returns ``(tracks, frames read, analysed (W, H))``; tracks are in analysed-image pixels.
    """
    active: list[_Track] = []
    done: list[_Track] = []
    motion = _ImageMotion(cfg)
    n_read, size = 0, (0, 0)
    for f, rgb in enumerate(frames):
        img, _ = _downscale(np.asarray(rgb), cfg.max_width)
        H, W = img.shape[:2]
        size, n_read = (W, H), f + 1
        motion.add(img)
        # Tracks unseen for absent_frames frames are finished; the rest may still be matched.
        still = [t for t in active if f - t.frames[-1] < cfg.absent_frames + 1]
        done += [t for t in active if f - t.frames[-1] >= cfg.absent_frames + 1]
        active = still
        cands = find_dot_candidates(img, cfg)
        preds = [t.predict(f, motion) for t in active]
        if active and len(cands):
            gap = np.array([f - t.frames[-1] for t in active], dtype=np.float64)
            # Rigid with the image: only a small residual (parallax, the hand holding the pointer),
            # growing slowly with the frames missed. Constant velocity: the wide gate, next frame only.
            g_rigid = cfg.max_residual_frac * W * (1 + 0.25 * (gap - 1))
            cv = np.stack([p for _, p in preds])
            d = np.linalg.norm(cv[:, None, :] - cands.xy[None, :, :], axis=2) / (cfg.max_step_frac * W)
            d[gap > 1] = np.inf
            for ti, (rigid, _) in enumerate(preds):
                if rigid is not None:
                    d[ti] = np.minimum(d[ti], np.linalg.norm(cands.xy - rigid, axis=1) / g_rigid[ti])
            pairs = _greedy_pairs(d, d <= 1.0)
        else:
            pairs = []
        matched_t = {ti for ti, _ in pairs}
        for ti, ci in pairs:
            active[ti].add(f, cands, ci)
        # Unmatched tracks: measure what their spot looks like now, while this frame is at hand.
        for ti, t in enumerate(active):
            if ti in matched_t:
                continue
            p = preds[ti][0] if preds[ti][0] is not None else preds[ti][1]
            s, ring = spot_strength(img, p, _radius(t.diameter[-1]) + 1.0)
            if f - t.frames[-1] == 1 and s >= cfg.follow_strength * float(np.median(t.detected[-5:])) > 0:
                # Still there, only missed by the candidate test (hysteresis): follow it.
                q = _spot_centre(img, p, _radius(t.diameter[-1]) + 1.0, cfg)
                t.follow(f, q, t.diameter[-1], s, ring)
                continue
            t.after_strength.append(s)
            t.after_xy.append(p)
            if t.after_ring is None:
                t.after_ring = ring
        matched_c = {ci for _, ci in pairs}
        for ci in range(len(cands)):
            if ci not in matched_c:
                t = _Track()
                t.add(f, cands, ci)
                active.append(t)
    return done + active, n_read, size


def _score(t: _Track, cfg: SyncConfig, size: tuple[int, int], n_read: int, last_allowed: int) -> float | None:
    """Confidence that track ``t`` ends with the laser being switched off; None if it cannot."""
    W, H = size
    last = t.frames[-1]
    if len(t.frames) < cfg.min_seen_frames or last + 1 > last_allowed:
        return None
    if last + cfg.absent_frames >= n_read or len(t.after_strength) < cfg.absent_frames:
        return None  # not seen to stay gone (the frames ran out)
    m = cfg.border_frac * W
    for x, y in [t.xy[-1], *t.after_xy[: cfg.gone_in_view_frames]]:
        if x < m or y < m or x > W - 1 - m or y > H - 1 - m:
            return None  # it left the field of view (or would have, moving with the image)
    before = float(np.median(t.strength[-3:]))
    after = max(t.after_strength[: cfg.absent_frames])
    contrast = float(np.clip((before - after) / max(before, 1.0), 0.0, 1.0))
    ring_before = np.mean(t.ring[-2:], axis=0)
    change = float(np.abs(t.after_ring - ring_before).mean()) if t.after_ring is not None else np.inf
    background = float(np.clip(1.0 - change / cfg.background_change, 0.0, 1.0)) if np.isfinite(change) else 0.0
    support = min(1.0, len(t.frames) / (2.0 * cfg.min_seen_frames))
    # A laser dot is seen in (nearly) every frame it is on; a spot that flickers in and out of the
    # detector is something else (texture at the detection limit).
    density = len(t.frames) / (t.frames[-1] - t.frames[0] + 1)
    steady = min(1.0, density / cfg.min_seen_fraction)
    return contrast * background * (0.5 + 0.5 * support) * steady


def _drop(t: _Track, cfg: SyncConfig) -> float:
    """How much the spot's strength fell at its last sighting (the measure :func:`_score`'s
    contrast divides by the strength before)."""
    return float(np.median(t.strength[-3:])) - max(t.after_strength[: cfg.absent_frames])


def _weigh_drops(scored: list[tuple[float, _Track]], cfg: SyncConfig) -> list[tuple[float, _Track]]:
    """Scale the event candidates' scores by their strength drop relative to the largest drop among
    them (``rival_drop_weight``). Every score is relative (a dim reddish speck covered by a passing
    hand goes fully out, contrast 1); switching a laser off is the largest drop of red in the view.
    A view with one candidate keeps its score, so whether an event is reported at all is unchanged."""
    w = cfg.rival_drop_weight
    events = [(s, t) for s, t in scored if s >= cfg.min_confidence]
    if w <= 0 or len(events) < 2:
        return scored
    top = max(_drop(t, cfg) for _, t in events)
    if top <= 0:
        return scored
    return [(s * (1.0 - w + w * float(np.clip(_drop(t, cfg) / top, 0.0, 1.0))), t) for s, t in scored]


def detect_laser_candidates_in_frames(
    frames: Iterable[NDArray[np.uint8]], cfg: SyncConfig = SyncConfig(), max_event_frame: int | None = None,
) -> list[SyncEvent]:
    """Every plausible laser-dot event in a stream of (H, W, 3) uint8 RGB frames (frame 0 first).

    Args:
        frames: the frames in order; each is read once.
        cfg: detector settings.
        max_event_frame: the event frame must be <= this (None: anywhere with enough frames after).

    Returns:
        The events scoring at least ``cfg.min_confidence``, best first (at most
        ``cfg.max_events``); empty when none qualifies. A view may show several disappearances (a
        dot swept off the part of the wall a phone films and back, a red speck covered by a hand):
        the sync chooses among them with the other view's events and the geometry
        (:mod:`embodmocap.sequence.sync_record`).
    """
    tracks, n_read, size = _track_dots(frames, cfg)
    if n_read == 0:
        return []
    last_allowed = n_read if max_event_frame is None else max_event_frame
    scored = [(s, t) for t in tracks if (s := _score(t, cfg, size, n_read, last_allowed)) is not None]
    scored = _weigh_drops(scored, cfg)
    scored.sort(key=lambda st: -st[0])
    if not scored or scored[0][0] < cfg.min_confidence:
        log.info("no laser-dot event: %d dot tracks, best score %s", len(tracks),
                 f"{scored[0][0]:.2f}" if scored else "none")
        return []
    return [SyncEvent(frame=t.frames[-1] + 1, confidence=round(s, 4), dot_xy_before=tuple(t.xy[-1]),
                      frames_seen=len(t.frames), method="auto")
            for s, t in scored[: max(1, cfg.max_events)] if s >= cfg.min_confidence]


def detect_laser_event_in_frames(
    frames: Iterable[NDArray[np.uint8]], cfg: SyncConfig = SyncConfig(), max_event_frame: int | None = None,
) -> SyncEvent | None:
    """The best of :func:`detect_laser_candidates_in_frames` (None if there is none); a warning
    when the runner-up scores alike."""
    found = detect_laser_candidates_in_frames(frames, cfg, max_event_frame)
    if not found:
        return None
    _warn_rival(found, cfg)
    return found[0]


def _warn_rival(found: list[SyncEvent], cfg: SyncConfig, where: str = "") -> None:
    if len(found) > 1 and found[1].confidence >= cfg.rival_ratio * found[0].confidence:
        log.warning("%stwo laser-dot disappearances score alike (frames %d: %.2f and %d: %.2f); the other view's event "
                    "and the geometric sync decide, check the contact sheet", where, found[0].frame,
                    found[0].confidence, found[1].frame, found[1].confidence)


def _search_frames(capture: Capture, cfg: SyncConfig) -> int:
    """Number of leading frames within ``cfg.search_s`` of the capture's first frame."""
    ts = np.asarray(capture.timestamps_s)
    if len(ts) >= capture.num_frames and capture.num_frames > 0:
        return int(np.count_nonzero(ts[: capture.num_frames] - ts[0] < cfg.search_s))
    return min(capture.num_frames, int(math.ceil(cfg.search_s * capture.fps)))


def detect_laser_candidates(capture: Capture, cfg: SyncConfig = SyncConfig()) -> list[SyncEvent]:
    """Every plausible laser-dot event in the first ``cfg.search_s`` seconds of ``capture``, best
    first (:func:`detect_laser_candidates_in_frames`).

    Frames are read once, in increasing order (cheap for video captures), and downscaled to at
    most ``cfg.max_width`` wide. ``dot_xy_before`` is returned in full-resolution pixels.
    """
    n_search = _search_frames(capture, cfg)
    n_read = min(capture.num_frames, n_search + cfg.absent_frames + 1)
    found = detect_laser_candidates_in_frames((capture.frames.rgb(i) for i in range(n_read)), cfg,
                                              max_event_frame=n_search - 1)
    W = capture.rgb_intrinsics.width
    s = min(1.0, cfg.max_width / W) if W > 0 else 1.0
    out = []
    for ev in found:
        # Back to full-resolution pixels (pixel centres at integers in both images).
        x, y = ((c + 0.5) / s - 0.5 for c in ev.dot_xy_before)
        out.append(SyncEvent(ev.frame, ev.confidence, (float(x), float(y)), ev.frames_seen, ev.method))
    if out:
        log.info("%s: laser dot gone at frame %d (seen %d frames, confidence %.2f)%s", capture.path, out[0].frame,
                 out[0].frames_seen, out[0].confidence,
                 "; other candidates: " + ", ".join(f"{e.frame} ({e.confidence:.2f})" for e in out[1:]) if len(out) > 1 else "")
        _warn_rival(out, cfg, f"{capture.path}: ")
    return out


def detect_laser_event(capture: Capture, cfg: SyncConfig = SyncConfig()) -> SyncEvent | None:
    """The best of :func:`detect_laser_candidates` (None when there is none)."""
    found = detect_laser_candidates(capture, cfg)
    return found[0] if found else None


# --------------------------------------------------------------------------- both views


def sync_views(
    captures: Mapping[str, Capture], manual: Mapping[str, int | None] | None = None,
    cfg: SyncConfig = SyncConfig(), seq: str = "<seq>",
) -> dict[str, SyncEvent]:
    """The sync event of every view: the manifest's frame where given, else detected.

    Args:
        captures: view name -> capture.
        manual: view name -> ``sync_frame`` from the manifest (None or missing: detect).
        cfg: detector settings.
        seq: sequence name, only used in error messages.

    Raises:
        InputError: a manual frame outside the capture, or no event found in a view (the message
            says how to give the frame by hand).
    """
    manual = manual or {}
    events: dict[str, SyncEvent] = {}
    for view, cap in captures.items():
        frame = manual.get(view)
        where = f"[sequences.{seq}.views.{view}] in session.toml"
        if frame is not None:
            if not 0 <= int(frame) < cap.num_frames:
                raise InputError(cap.path, f"sync_frame = {frame} of view {view} is outside the capture's "
                                 f"{cap.num_frames} frames", f"give a frame in 0..{cap.num_frames - 1} under {where}")
            events[view] = SyncEvent(int(frame), 1.0, None, 0, "manual")
            continue
        ev = detect_laser_event(cap, cfg)
        if ev is None:
            raise InputError(
                cap.path, f"no laser-dot sync event found in the first {cfg.search_s:g} s of view {view}",
                f"find the first frame without the laser dot in the video and set sync_frame = N under {where}",
            )
        events[view] = ev
    return events


def sync_events_to_json(events: Mapping[str, SyncEvent]) -> dict:
    """JSON-ready dict of the events of a sequence (the stage's ``sync.json``)."""
    return {"version": SYNC_JSON_VERSION, "views": {
        v: {"frame": e.frame, "confidence": e.confidence,
            "dot_xy_before": None if e.dot_xy_before is None else list(e.dot_xy_before),
            "frames_seen": e.frames_seen, "method": e.method}
        for v, e in events.items()}}


def sync_events_from_json(obj: dict, path: str | Path | None = None) -> dict[str, SyncEvent]:
    """Inverse of :func:`sync_events_to_json`; ``path`` names the file in errors."""
    fix = "delete the file to redo the sync"
    if not isinstance(obj, dict) or obj.get("version") != SYNC_JSON_VERSION or not isinstance(obj.get("views"), dict):
        raise InputError(path, f"not a version-{SYNC_JSON_VERSION} sync file", fix)
    out = {}
    try:
        for v, d in obj["views"].items():
            xy = d.get("dot_xy_before")
            if d["method"] not in ("auto", "manual"):
                raise ValueError(f"unknown method {d['method']!r}")
            out[v] = SyncEvent(int(d["frame"]), float(d["confidence"]),
                               None if xy is None else (float(xy[0]), float(xy[1])),
                               int(d["frames_seen"]), d["method"])
    except (KeyError, TypeError, ValueError, IndexError) as err:
        raise InputError(path, f"malformed sync entry: {err}", fix) from err
    return out


# --------------------------------------------------------------------------- contact sheet


def contact_sheet_size(capture: Capture, window: int = 4, tile_width: int = 320) -> tuple[int, int]:
    """(width, height) in pixels of the sheet :func:`write_contact_sheet` writes."""
    tw, th = _tile_size(capture, tile_width)
    return window * tw, 2 * th


def _tile_size(capture: Capture, tile_width: int) -> tuple[int, int]:
    W, H = capture.rgb_intrinsics.width, capture.rgb_intrinsics.height
    tw = min(W, tile_width)
    return tw, max(1, int(round(H * tw / W)))


def write_contact_sheet(capture: Capture, event: SyncEvent, path: str | Path, window: int = 4,
                        tile_width: int = 320) -> Path:
    """Write a PNG of the frames ``event - window .. event + window - 1`` to confirm a sync event.

    Layout: two rows of ``window`` tiles, the frames before the event on top and the event frame
    first on the bottom row (green border, "EVENT"); each tile is labelled with its raw frame
    number; the dot's last detected position is circled (yellow) on every tile, so the dot is seen
    inside the circle on top and gone below. Frames outside the capture are left dark grey. Tiles
    are ``tile_width`` wide (or the frame width if smaller); the sheet's size is
    :func:`contact_sheet_size`. Written atomically.
    """
    from PIL import Image, ImageDraw, ImageFont

    if window < 1:
        raise ValueError("window must be >= 1")
    tw, th = _tile_size(capture, tile_width)
    W = capture.rgb_intrinsics.width
    s = tw / W
    sheet = Image.new("RGB", (window * tw, 2 * th), (40, 40, 40))
    draw = ImageDraw.Draw(sheet)
    font = ImageFont.load_default(size=max(10, th // 12))
    for k, f in enumerate(range(event.frame - window, event.frame + window)):
        x0, y0 = (k % window) * tw, (k // window) * th
        if 0 <= f < capture.num_frames:
            tile = Image.fromarray(capture.frames.rgb(f)).resize((tw, th), Image.Resampling.BILINEAR)
            sheet.paste(tile, (x0, y0))
        if event.dot_xy_before is not None:
            cx, cy = ((c + 0.5) * s - 0.5 for c in event.dot_xy_before)
            rad = max(6.0, 0.04 * tw)
            draw.ellipse([x0 + cx - rad, y0 + cy - rad, x0 + cx + rad, y0 + cy + rad], outline=(255, 230, 0), width=2)
        label = f"#{f}" + ("  EVENT" if f == event.frame else "")
        box = draw.textbbox((x0 + 4, y0 + 3), label, font=font)
        draw.rectangle([box[0] - 2, box[1] - 2, box[2] + 2, box[3] + 2], fill=(0, 0, 0))
        draw.text((x0 + 4, y0 + 3), label, fill=(0, 255, 0) if f == event.frame else (255, 255, 255), font=font)
        if f == event.frame:
            draw.rectangle([x0, y0, x0 + tw - 1, y0 + th - 1], outline=(0, 255, 0), width=3)
    caption = f"{event.method} sync, confidence {event.confidence:.2f}"
    box = draw.textbbox((4, 2 * th - 4), caption, font=font, anchor="ld")
    draw.rectangle([box[0] - 2, box[1] - 2, box[2] + 2, box[3] + 2], fill=(0, 0, 0))
    draw.text((4, 2 * th - 4), caption, fill=(255, 255, 255), font=font, anchor="ld")
    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        sheet.save(tmp, format="PNG")
    return path
