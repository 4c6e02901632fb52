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
from embodmocap.types import Capture

log = logging.getLogger(__name__)

SYNC_JSON_VERSION = 1


# --------------------------------------------------------------------------- config and result


@dataclass(frozen=True)
class SyncConfig:
    """Settings of the laser-dot detector. Pixel values are 0-255 RGB; sizes in analysed pixels."""

    min_peak_red: int = 215
    """Red value a dot's pixels must reach: a laser dot saturates red."""
    min_tophat_red: int = 20
    """...and by which they must exceed their local background (white top-hat of the red channel
    over ``background_px``): the dot is a small spot brighter than what surrounds it."""
    min_peak_red_redcore: int = 185
    """Red value pixels of a red (not white) core must reach: video's half-resolution chroma
    pulls a small pure-red core down to ~200."""
    min_tophat_redness: int = 60
    """...and by which their red excess ``r - max(g, b)`` must exceed its local background
    (top-hat): a red core on a bright wall is not brighter in red, but much redder."""
    background_px: int = 31
    """Size of the square structuring element of the top-hats (larger than any dot), pixels at
    640 wide (scaled with the analysed width)."""
    min_rim_redness: float = 30.0
    """Red excess the rim of a dot with a red (not white) core needs (80th percentile over the spot and the 2 px around it, less a
    white centre) above the ring's 90th percentile: the red rim, confined to a small spot. A
    specular highlight or a lamp has no red rim; the bright part of a red shirt or poster has as
    red pixels just outside it."""
    min_rim_redness_white: float = 10.0
    """The same for a spot with an over-exposed white core, above the ring's 75th percentile: a
    white spot with a red rim. A specular highlight's rim is as neutral as (or, on a red wall,
    less red than) the wall."""
    min_core_whitening: float = 50.0
    """``min(g, b)`` of the brightest core pixel above the ring's median for an over-exposed
    (white) core."""
    min_core_white_margin: float = 20.0
    """...and by which it must exceed the ring's 95th percentile of ``min(g, b)``: an over-exposed
    core is whiter than anything around it."""
    min_core_redness_gain: float = 110.0
    """Without a white core: red excess of the reddest pixel above the ring's median. A bright fold
    of a red shirt is only a little redder than the shirt; a red laser core on any wall is far
    redder than the wall."""
    min_peak_redness: int = 140
    """Without a white core: red excess the reddest pixel itself must reach."""
    rim_px: float = 3.0
    """Width of the rim around the saturated spot where the red halo is looked for, pixels."""
    diameter_frac: tuple[float, float] = (0.0, 0.05)
    """Smallest and largest equivalent diameter (``2 sqrt(area / pi)``) of the saturated spot, as
    fractions of the analysed image width."""
    max_extent_frac: float = 0.07
    """Largest bounding-box side of the saturated spot (a motion-blurred dot is a short streak),
    as a fraction of the analysed image width."""
    min_spot_redness: int = 15
    """Red excess some pixel of a spot or the 2 px around it must reach to be examined at all."""
    max_candidates: int = 48
    """At most this many spots per frame are examined (those standing out most first)."""
    max_excess_candidates: int = 16
    """...plus at most this many of the spots standing out most in red excess (``r - max(g, b)``),
    when not among those already: under warm light hundreds of texture spots saturate red."""
    min_seen_frames: int = 5
    """Frames the dot must be seen (gaps allowed) before it disappears for the event to count."""
    min_seen_fraction: float = 0.6
    """Share of the frames from a track's first to its last sighting in which it must be seen
    for full confidence (scaled down below): a dot is seen in nearly every frame it is on,
    brief occlusions aside."""
    follow_strength: float = 0.75
    """Hysteresis: a track seen in the previous frame that the candidate test misses now goes on
    where its spot, at the predicted position, still stands out (:func:`spot_strength`) by at least
    this fraction of the median strength of its last detections. The candidate test starts tracks;
    a dot already found only has to stay (nearly) as strong: a pointer that is on shines steadily
    (0.9-1.1 of its strength in the benchmark's dots), while the place of a dot switched off keeps
    at most about half of it (a white-and-red wall edge). The thin red rim of a large over-exposed core
    (5-6 px core, halo 1 px wider) is diluted by video's half-resolution chroma and passes the
    rim test only in some frames, and an event is the first frame the spot is really gone, not
    the first frame the strict test fails."""
    absent_frames: int = 8
    """Frames the dot must stay gone after the event; a dot that comes back within this many
    frames at a consistent position was only hidden, not switched off."""
    max_step_frac: float = 0.06
    """Largest distance of the dot from its constant-velocity prediction in the next frame (camera
    shake and panning), as a fraction of the image width. After missed frames only the prediction
    by the image's global motion is used (``max_residual_frac``)."""
    max_residual_frac: float = 0.02
    """Largest motion of the dot relative to the image's global motion between consecutive frames
    (the dot is rigid with the wall), as a fraction of the image width; grows by a quarter per
    frame missed."""
    motion_width: int = 160
    """Frames are reduced to this width to measure the image's global motion (phase correlation)."""
    min_motion_response: float = 0.05
    """Phase-correlation peak below which a frame's global motion counts as unknown."""
    border_frac: float = 0.02
    """A track whose last position is within this fraction of the width from the image border
    left the field of view; it is not an event."""
    gone_in_view_frames: int = 3
    """The spot must be seen gone for this many frames at positions inside the image (its
    position moved with the image): a spot whose place leaves the view was not switched off."""
    background_change: float = 50.0
    """Mean RGB change of the ring around the dot, from the last frame with it to the first
    without, at which the confidence drops to 0 (something moved in front of the dot)."""
    rival_drop_weight: float = 0.5
    """When several disappearances score at least ``min_confidence``, each score is multiplied by
    ``1 - w + w * drop / largest drop`` (drop: strength before less after): a dim reddish speck
    that a passing hand covers goes out as completely as a laser, but by far less. 0 = off."""
    min_confidence: float = 0.4
    """Events scoring below this are not reported (the caller then asks for a manual frame). A
    bare foot's pink-white highlight walking out of a real lab video scored 0.38; switch-offs of
    the benchmark's realistic dots score 0.51-0.93, of its easy dots 0.70-0.89."""
    search_s: float = 10.0
    """Only events in the first this many seconds of a capture are searched (the laser is
    switched off near the start of a recording)."""
    max_width: int = 1920
    """Frames wider than this are downscaled (area averaging) to this width before analysis. A
    real dot is 2-3 px across: analyse at full resolution whenever possible."""


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


@dataclass(frozen=True)
class DotCandidates:
    """Dot candidates of one frame, in pixels of the analysed (possibly downscaled) image.

    Attributes:
        xy: (N, 2) centroids (x, y) of the saturated spots.
        diameter: (N,) equivalent diameters ``2 sqrt(area / pi)`` of the saturated spots.
        peak_redness: (N,) largest red excess ``r - max(g, b)`` in the spot and its rim.
        ring_rgb: (N, 3) mean RGB of the ring around the spot (outside the halo).
        strength: (N,) how much the spot stands out from that ring (:func:`spot_strength`).
        white: (N,) ``min(g, b)`` of the core above the ring's median (> 0: over-exposed core).
    """

    xy: NDArray[np.float64]
    diameter: NDArray[np.float64]
    peak_redness: NDArray[np.float64]
    ring_rgb: NDArray[np.float64]
    strength: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    white: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        return len(self.xy)


# --------------------------------------------------------------------------- per-frame candidates


def _channels(img: NDArray[np.uint8]) -> tuple[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.uint8]]:
    """Red, red excess ``max(0, r - max(g, b))`` and ``min(g, b)`` of an (H, W, 3) uint8 image."""
    import cv2

    r = np.ascontiguousarray(img[..., 0])
    g, b = img[..., 1], img[..., 2]
    return r, cv2.subtract(r, np.maximum(g, b)), np.minimum(g, b)


def _spot_features(img, red, white, mask, rim: int, ring: int, min_white: float, white_margin: float):
    """Features of one spot given as a uint8 ``mask`` over a window of ``img`` (window arrays).

    Returns ``(rim_redness, core_redness, core_white, peak_redness, ring_rgb)``: red excess of the
    spot and the 2 px around it less its white centre (80th percentile) above the ring's 90th
    percentile (75th for a white core, ``core_white >= min_white``); red excess of its reddest pixel and ``min(g, b)`` of its whitest pixel above the
    ring's medians; the reddest pixel's red excess; the ring's mean RGB.
    """
    import cv2

    # Distance of every window pixel to the spot (one transform gives every band).
    dist = cv2.distanceTransform((mask == 0).astype(np.uint8), cv2.DIST_L2, 3)
    near = dist <= 2  # the spot and the 2 px around it: the red rim
    ring_m = (dist > rim + 1) & (dist <= rim + 1 + ring)
    if not ring_m.any():
        return None
    bg_red = float(np.median(red[ring_m]))
    bg_white = float(np.median(white[ring_m]))
    core = mask.astype(bool)
    # An over-exposed core is whiter than anything around it: above the ring's median and, less a
    # margin, its 95th percentile (a lit edge next to a darker floor is not).
    whitest = float(white[core].max())
    core_white = whitest - bg_white
    if whitest - float(np.percentile(white[ring_m], 95)) < white_margin:
        core_white = min(core_white, 0.0)
    # The rim: the spot and its surroundings less an over-exposed (white) centre, which has no red
    # excess however red the light is.
    rim_m = near & ~(core & (white.astype(np.float32) >= bg_white + 0.5 * max(core_white, 0.0) + 25))
    vals = red[rim_m] if rim_m.any() else red[near]
    # The rim against the ring's *redder* pixels (90th percentile): the laser's red is confined to
    # a small spot, while the bright part of a red shirt or poster has as red pixels just outside.
    # For a white core the ring's 75th percentile: video's half-resolution chroma dilutes a thin
    # red rim, and a white spot is no bright part of red cloth.
    rim80 = float(np.percentile(vals, 80))
    ring75, ring90 = np.percentile(red[ring_m], [75, 90])
    rim_red = rim80 - float(ring75 if core_white >= min_white else ring90)
    return rim_red, float(vals.max()) - bg_red, core_white, float(vals.max()), img[ring_m].reshape(-1, 3).mean(0)


def spot_strength(img: NDArray[np.uint8], xy, radius: float, ring: int = 5) -> tuple[float, NDArray]:
    """How much a laser-like spot near ``xy`` stands out from its surroundings; and the ring's RGB.

    Within ``radius`` px of ``xy``: the largest red excess above the median red excess of a ring
    (``radius + 2 .. radius + 2 + ring`` px), plus half the largest ``min(g, b)`` above the ring's
    median (an over-exposed core). The same measure is taken where the dot was last seen and where
    it would be after the event, so their ratio says how cleanly it went out. ``(0, nan)`` outside
    the image.
    """
    H, W = img.shape[:2]
    R = int(math.ceil(radius)) + 2 + ring
    cx, cy = int(round(xy[0])), int(round(xy[1]))
    x0, x1, y0, y1 = max(0, cx - R), min(W, cx + R + 1), max(0, cy - R), min(H, cy + R + 1)
    if x0 >= x1 or y0 >= y1:
        return 0.0, np.full(3, np.nan)
    patch = img[y0:y1, x0:x1]
    _, red, white = _channels(patch)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    d = np.hypot(xx - xy[0], yy - xy[1])
    inside, ring_m = d <= radius, (d > radius + 2) & (d <= radius + 2 + ring)
    if not inside.any() or not ring_m.any():
        return 0.0, np.full(3, np.nan)
    s_red = float(red[inside].max()) - float(np.median(red[ring_m]))
    s_white = float(white[inside].max()) - float(np.median(white[ring_m]))
    return max(0.0, s_red) + 0.5 * max(0.0, s_white), patch[ring_m].reshape(-1, 3).mean(0)


def find_dot_candidates(rgb: NDArray[np.uint8], cfg: SyncConfig = SyncConfig()) -> DotCandidates:
    """Laser-dot-like spots in one (H, W, 3) uint8 RGB image, at its full resolution.

    A laser dot as a phone records it is a very small spot whose core saturates red (and, when
    over-exposed, green and blue too: a white core) with a red rim, on any wall. So:

    1. **seeds**: pixels with ``r >= min_peak_red`` that stand out from their local background
       (white top-hat over ``background_px``) in red, or with ``r >= min_peak_red_redcore`` that
       stand out in red excess;
    2. **spots**: 8-connected seeds, of a plausible size (``diameter_frac``, ``max_extent_frac``);
    3. each spot is compared with a ring around it (median, robust to texture): it needs a red rim
       confined to the spot (``min_rim_redness``: rejects specular highlights, lamps and the
       bright parts of red clothes and posters) and either an over-exposed
       white core (``min_core_whitening``) or a core far redder than the ring
       (``min_core_redness_gain`` and ``min_peak_redness``: rejects bright folds of red clothes
       and red paint on red walls).

    Coordinates and sizes are in pixels of ``rgb``.
    """
    import cv2

    img = np.asarray(rgb)
    H, W = img.shape[:2]
    empty = DotCandidates(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros(0))
    r, red, white = _channels(img)
    hot = r >= min(cfg.min_peak_red, cfg.min_peak_red_redcore)
    if not hot.any():
        return empty
    k = max(15, int(round(cfg.background_px * W / 640)) | 1)
    ker = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
    # Top-hats only over the rows and columns that hold hot pixels (plus the element's reach).
    ys, xs = np.nonzero(hot)
    by0, by1 = max(0, ys.min() - k), min(H, ys.max() + k + 1)
    bx0, bx1 = max(0, xs.min() - k), min(W, xs.max() + k + 1)
    sub = (slice(by0, by1), slice(bx0, bx1))
    rs = r[sub]
    c_red = cv2.morphologyEx(rs, cv2.MORPH_TOPHAT, ker).astype(np.int16) - cfg.min_tophat_red
    c_redness = cv2.morphologyEx(red[sub], cv2.MORPH_TOPHAT, ker).astype(np.int16) - cfg.min_tophat_redness
    c_red[rs < cfg.min_peak_red] = -1
    c_redness[rs < cfg.min_peak_red_redcore] = -1
    contrast = np.maximum(c_red, c_redness)
    seed = np.zeros((H, W), np.uint8)
    seed[sub] = (contrast >= 0).astype(np.uint8)
    n, labels, stats, cents = cv2.connectedComponentsWithStats(seed, connectivity=8)
    if n <= 1:
        return empty
    area = stats[1:, cv2.CC_STAT_AREA].astype(np.float64)
    diam = 2.0 * np.sqrt(area / np.pi)
    extent = np.maximum(stats[1:, cv2.CC_STAT_WIDTH], stats[1:, cv2.CC_STAT_HEIGHT])
    ok = (diam >= cfg.diameter_frac[0] * W) & (diam <= cfg.diameter_frac[1] * W) & (extent <= cfg.max_extent_frac * W)
    ids = np.nonzero(ok)[0] + 1
    # A cheap first look: some red excess on or right around the spot (a laser always has a red
    # rim); lamps, windows and white clothes in a bright scene have none. The spots that stand
    # out most from their background (top-hat) go first.
    boxes = stats[ids, :4]
    reddest = np.array([red[max(0, y - 2):y + h + 2, max(0, x - 2):x + w + 2].max() for x, y, w, h in boxes],
                       dtype=np.float64).reshape(-1)
    full = np.zeros((H, W), np.int16)
    full[sub] = contrast
    standout = np.array([full[y:y + h, x:x + w].max() for x, y, w, h in boxes], dtype=np.float64).reshape(-1)
    order = np.argsort(-standout, kind="stable")
    first = ids[order][reddest[order] >= cfg.min_spot_redness][: cfg.max_candidates]
    # Plus the spots standing out most in red *excess*: a scene under warm light (a white balance
    # towards red, a terracotta floor) saturates red in hundreds of texture spots that all stand
    # out more in red than a small red laser core, which only its red excess sets apart; ranked by
    # red alone, the dot fell out of the examined spots.
    full[sub] = c_redness
    excess = np.array([full[y:y + h, x:x + w].max() for x, y, w, h in boxes], dtype=np.float64).reshape(-1)
    order = np.argsort(-excess, kind="stable")
    keep = (excess[order] >= 0) & (reddest[order] >= cfg.min_spot_redness)
    extra = [i for i in ids[order][keep][: cfg.max_excess_candidates] if i not in set(first.tolist())]
    ids = np.concatenate([first, np.asarray(extra, dtype=first.dtype)])
    out = []
    for lab in ids:
        x, y, w, h = stats[lab, :4]
        rim = int(math.ceil(max(cfg.rim_px, 0.5 * max(w, h))))
        ring = max(4, int(max(w, h)))
        pad = rim + 2 + ring
        x0, x1, y0, y1 = max(0, x - pad), min(W, x + w + pad), max(0, y - pad), min(H, y + h + pad)
        win = (slice(y0, y1), slice(x0, x1))
        f = _spot_features(img[win], red[win], white[win], (labels[win] == lab).astype(np.uint8), rim, ring,
                           cfg.min_core_whitening, cfg.min_core_white_margin)
        if f is None:
            continue
        rim_red, core_red, core_white, peak_red, ring_rgb = f
        white_dot = core_white >= cfg.min_core_whitening and rim_red >= cfg.min_rim_redness_white
        red_dot = (core_red >= cfg.min_core_redness_gain and peak_red >= cfg.min_peak_redness
                   and rim_red >= cfg.min_rim_redness)
        is_dot = white_dot or red_dot
        if is_dot:
            s, _ = spot_strength(img, cents[lab], _radius(diam[lab - 1]))
            out.append((cents[lab], diam[lab - 1], peak_red, ring_rgb, s, core_white))
    if not out:
        return empty
    # One dot, one candidate: a textured wall or a motion streak can split a spot in two; keep the
    # strongest of spots whose rims overlap.
    out.sort(key=lambda c: -c[4])
    kept: list[tuple] = []
    for c in out:
        if all(np.hypot(*(c[0] - k[0])) > max(c[1], k[1]) + 2 * cfg.rim_px for k in kept):
            kept.append(c)
    xy, d, pr, rr, st, wh = zip(*kept)
    return DotCandidates(np.array(xy, np.float64), np.array(d, np.float64), np.array(pr, np.float64),
                         np.array(rr, np.float64), np.array(st, np.float64), np.array(wh, np.float64))


def _spot_centre(img: NDArray[np.uint8], xy, radius: float, cfg: SyncConfig) -> NDArray:
    """Centroid of the red-saturated pixels (``r >= min_peak_red_redcore``) within ``radius`` px of
    ``xy`` in an (H, W, 3) image; ``xy`` itself when there are none (keeps a followed track on the
    spot rather than on its prediction)."""
    H, W = img.shape[:2]
    R = int(math.ceil(radius))
    cx, cy = int(round(xy[0])), int(round(xy[1]))
    x0, x1, y0, y1 = max(0, cx - R), min(W, cx + R + 1), max(0, cy - R), min(H, cy + R + 1)
    if x0 >= x1 or y0 >= y1:
        return np.asarray(xy, np.float64)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    m = (img[y0:y1, x0:x1, 0] >= cfg.min_peak_red_redcore) & (np.hypot(xx - xy[0], yy - xy[1]) <= radius)
    if not m.any():
        return np.asarray(xy, np.float64)
    return np.array([xx[m].mean(), yy[m].mean()], np.float64)


def _radius(diameter: float) -> float:
    """Radius within which :func:`spot_strength` looks for a spot of this saturated diameter."""
    return max(2.0, 0.5 * float(diameter) + 1.0)


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


def detect_laser_event_in_frames(
    frames: Iterable[NDArray[np.uint8]], cfg: SyncConfig = SyncConfig(), max_event_frame: int | None = None,
) -> SyncEvent | None:
    """Find the laser-dot event in a stream of (H, W, 3) uint8 RGB frames (frame 0 first).

    Args:
        frames: the frames in order; each is read once.
        cfg: detector settings.
        max_event_frame: the event frame must be <= this (None: anywhere with enough frames after).

    Returns:
        The best event, or None if no track qualifies with confidence >= ``cfg.min_confidence``.
    """
    tracks, n_read, size = _track_dots(frames, cfg)
    if n_read == 0:
        return None
    last_allowed = n_read if max_event_frame is None else max_event_frame
    scored = [(s, t) for t in tracks if (s := _score(t, cfg, size, n_read, last_allowed)) is not None]
    scored = _weigh_drops(scored, cfg)
    scored.sort(key=lambda st: -st[0])
    if not scored or scored[0][0] < cfg.min_confidence:
        log.info("no laser-dot event: %d dot tracks, best score %s", len(tracks),
                 f"{scored[0][0]:.2f}" if scored else "none")
        return None
    conf, best = scored[0]
    if len(scored) > 1 and scored[1][0] > 0.8 * conf:
        log.warning("two laser-dot disappearances score alike (frames %d: %.2f and %d: %.2f); check the contact sheet",
                    best.frames[-1] + 1, conf, scored[1][1].frames[-1] + 1, scored[1][0])
    return SyncEvent(frame=best.frames[-1] + 1, confidence=round(conf, 4), dot_xy_before=tuple(best.xy[-1]),
                     frames_seen=len(best.frames), method="auto")


def _search_frames(capture: Capture, cfg: SyncConfig) -> int:
    """Number of leading frames within ``cfg.search_s`` of the capture's first frame."""
    ts = np.asarray(capture.timestamps_s)
    if len(ts) >= capture.num_frames and capture.num_frames > 0:
        return int(np.count_nonzero(ts[: capture.num_frames] - ts[0] < cfg.search_s))
    return min(capture.num_frames, int(math.ceil(cfg.search_s * capture.fps)))


def detect_laser_event(capture: Capture, cfg: SyncConfig = SyncConfig()) -> SyncEvent | None:
    """Find the laser-dot event in the first ``cfg.search_s`` seconds of ``capture``.

    Frames are read once, in increasing order (cheap for video captures), and downscaled to at
    most ``cfg.max_width`` wide. ``dot_xy_before`` is returned in full-resolution pixels.
    """
    n_search = _search_frames(capture, cfg)
    n_read = min(capture.num_frames, n_search + cfg.absent_frames + 1)
    ev = detect_laser_event_in_frames((capture.frames.rgb(i) for i in range(n_read)), cfg,
                                      max_event_frame=n_search - 1)
    if ev is None or ev.dot_xy_before is None:
        return ev
    W = capture.rgb_intrinsics.width
    s = min(1.0, cfg.max_width / W) if W > 0 else 1.0
    # Back to full-resolution pixels (pixel centres at integers in both images).
    x, y = ((c + 0.5) / s - 0.5 for c in ev.dot_xy_before)
    ev = SyncEvent(ev.frame, ev.confidence, (float(x), float(y)), ev.frames_seen, ev.method)
    log.info("%s: laser dot gone at frame %d (seen %d frames, confidence %.2f)",
             capture.path, ev.frame, ev.frames_seen, ev.confidence)
    return ev


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
