"""Laser-dot candidates of one frame (step 1 of :mod:`embodmocap.sequence.sync`) and the sync's
settings, :class:`SyncConfig` (also importable from :mod:`embodmocap.sequence.sync`).

A real dot is a 2-3 px over-exposed core with a 5-10 px red halo, on any wall: near-saturated red
pixels that stand out from their local background form small spots, and each spot is compared with
a ring around it (robust statistics, so a textured or red wall is its own reference).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray


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
    max_events: int = 4
    """At most this many plausible events (scoring >= ``min_confidence``) are kept per view, best
    first; the sync chooses among them with the other view's events and the geometric sync."""
    rival_ratio: float = 0.8
    """A runner-up pair of events scoring at least this fraction of the best pair's score makes
    the laser ambiguous: the views are then sliced at the best pair but Stage III does not take
    their frames as simultaneous, and the geometric sync decides among the pairs."""
    search_s: float = 10.0
    """Only events in the first this many seconds of a capture are searched (the laser is
    switched off near the start of a recording)."""
    max_width: int = 1920
    """Frames wider than this are downscaled (area averaging) to this width before analysis. A
    real dot is 2-3 px across: analyse at full resolution whenever possible."""


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


def _channels_whole(img: NDArray[np.uint8]) -> tuple[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.uint8]]:
    """:func:`_channels` of a whole frame, the same arrays, through OpenCV's per-channel kernels
    (NumPy's on the interleaved channels cost several times more on a 640x480 frame)."""
    import cv2

    if img.ndim != 3 or img.shape[2] != 3 or not img.flags.c_contiguous:
        return _channels(img)
    r, g, b = cv2.split(img)
    return r, cv2.subtract(r, cv2.max(g, b)), cv2.min(g, b)


def _bounding_box(mask: NDArray[np.bool_]) -> tuple[int, int, int, int] | None:
    """``(y0, y1, x0, x1)``, ends exclusive, of the True pixels of a 2D mask; None when there are none."""
    rows = np.flatnonzero(mask.any(axis=1))
    if not len(rows):
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _seed_components(seed: NDArray[np.uint8], origin: tuple[int, int], shape: tuple[int, int]):
    """``cv2.connectedComponentsWithStats(full, connectivity=8)`` of a (H, W) image ``shape`` that is
    zero except for ``seed`` placed at ``origin`` (y, x): ``(n, labels, stats, centroids)`` in
    full-image pixels, or None when ``seed`` is empty. ``n``, ``labels`` and the components' rows
    (1..n-1) of ``stats`` and ``centroids`` are the very values the call on the whole image gives;
    row 0 (the background) describes the labelled box only.

    Labelling only the box around the seed pixels costs a fraction of the whole frame (a handful
    of seed pixels per frame): the box starts at even image coordinates, so OpenCV's 2x2-block
    scan meets the components in the same order and numbers them alike; statistics move by the
    offset, and each centroid is the sum of its pixels' coordinates over their count as OpenCV
    computes it (the sums are integers, recovered exactly from the box's centroids).
    """
    import cv2

    box = _bounding_box(seed)
    if box is None:
        return None
    H, W = shape
    y0, x0 = origin[0] + box[0], origin[1] + box[2]
    y0, x0 = y0 - y0 % 2, x0 - x0 % 2  # block-aligned
    y1, x1 = origin[0] + box[1], origin[1] + box[3]
    win = np.zeros((y1 - y0, x1 - x0), np.uint8)
    win[origin[0] + box[0] - y0:, origin[1] + box[2] - x0:] = seed[box[0]:box[1], box[2]:box[3]]
    n, lab, stats, cents = cv2.connectedComponentsWithStats(win, connectivity=8)
    labels = np.zeros((H, W), lab.dtype)
    labels[y0:y1, x0:x1] = lab
    stats = stats.copy()
    stats[1:, cv2.CC_STAT_LEFT] += x0
    stats[1:, cv2.CC_STAT_TOP] += y0
    area = stats[1:, cv2.CC_STAT_AREA].astype(np.float64)
    cents = cents.copy()
    cents[1:] = (np.round(cents[1:] * area[:, None]) + np.array([x0, y0], np.float64) * area[:, None]) / area[:, None]
    return n, labels, stats, cents


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
    r, red, white = _channels_whole(img)
    hot = r >= min(cfg.min_peak_red, cfg.min_peak_red_redcore)
    # Top-hats only over the rows and columns that hold hot pixels (plus the element's reach).
    box = _bounding_box(hot)
    if box is None:
        return empty
    k = max(15, int(round(cfg.background_px * W / 640)) | 1)
    ker = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
    by0, by1 = max(0, box[0] - k), min(H, box[1] + k)
    bx0, bx1 = max(0, box[2] - k), min(W, box[3] + k)
    sub = (slice(by0, by1), slice(bx0, bx1))
    rs = r[sub]
    c_red = cv2.morphologyEx(rs, cv2.MORPH_TOPHAT, ker).astype(np.int16) - cfg.min_tophat_red
    c_redness = cv2.morphologyEx(red[sub], cv2.MORPH_TOPHAT, ker).astype(np.int16) - cfg.min_tophat_redness
    c_red[rs < cfg.min_peak_red] = -1
    c_redness[rs < cfg.min_peak_red_redcore] = -1
    contrast = np.maximum(c_red, c_redness)
    found = _seed_components((contrast >= 0).astype(np.uint8), (by0, bx0), (H, W))
    if found is None:
        return empty
    n, labels, stats, cents = found
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
    # The spots lie inside the top-hat window: their boxes, moved into it, index its arrays.
    standout = np.array([contrast[y - by0:y - by0 + h, x - bx0:x - bx0 + w].max() for x, y, w, h in boxes],
                        dtype=np.float64).reshape(-1)
    order = np.argsort(-standout, kind="stable")
    first = ids[order][reddest[order] >= cfg.min_spot_redness][: cfg.max_candidates]
    # Plus the spots standing out most in red *excess*: a scene under warm light (a white balance
    # towards red, a terracotta floor) saturates red in hundreds of texture spots that all stand
    # out more in red than a small red laser core, which only its red excess sets apart; ranked by
    # red alone, the dot fell out of the examined spots.
    excess = np.array([c_redness[y - by0:y - by0 + h, x - bx0:x - bx0 + w].max() for x, y, w, h in boxes],
                      dtype=np.float64).reshape(-1)
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
