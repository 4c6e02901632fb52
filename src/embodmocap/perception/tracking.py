"""Keep the performer's identity: track every detected person, then pick the performer.

A view's detector gives, per frame, any number of people (bystanders, reflections, false
detections, the performer split in two). :func:`track_people` links them frame to frame into
tracks; :func:`select_performer` (one view) or :func:`select_performer_two_views` picks the
performer's track; :func:`performer_keypoints` turns it into per-frame arrays.

Association, frame by frame (the loop over frames is inherent; each frame is vectorised):

1. every live track predicts where its person is now: the last observation moved by the track's
   velocity (an exponential average of its box-centre motion) times the frames since it was seen;
2. similarity of track and detection = ``iou_weight * IoU(predicted box, box)`` + ``(1 -
   iou_weight) * OKS`` where OKS is the mean over joints confident in both of ``exp(-d^2 / (2 s^2))``,
   ``s = oks_sigma * sqrt(box area)``, widened by ``gap_growth`` per missed frame so a person coming
   back from an occlusion is still recognised;
3. one-to-one assignment maximising the total similarity (Hungarian,
   :func:`scipy.optimize.linear_sum_assignment`); pairs below ``min_similarity`` are not linked;
4. unmatched detections start new tracks; a track unseen for more than ``max_gap`` frames ends.

Why this keeps the identity when a second person crosses in front of the performer: the crossing
person has their own track, whose prediction (moving with them) fits their detections better than
the performer's (which stays with the performer), and the joint assignment gives each detection to
one track only; while the performer is hidden their track waits (up to ``max_gap`` frames) rather
than taking the only person left in view, because that person is already claimed by their own track.

Conventions: keypoints are COCO-17 ``(x, y, confidence)`` px; boxes ``(x1, y1, x2, y2)`` px;
"frame" here means the position in the list given (the caller maps it to raw frame numbers).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from embodmocap.perception.config import TrackingConfig  # noqa: F401 (defined with the settings)
from embodmocap.perception.precomputed import box_iou, boxes_from_keypoints

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SelectionWeights:
    """How the performer's track is scored; each term is in [0, 1]."""

    length: float = 1.0
    """Weight of the fraction of frames the track is seen in (longest track)."""
    centrality: float = 0.5
    """Weight of how close its box centre stays to the image centre (1 = always centred)."""
    size: float = 0.5
    """Weight of its median box area relative to the largest track's (largest person)."""
    cross_view: float = 2.0
    """Two views: weight of the overlap (IoU) of the two tracks' sequence instants. At 2 a pair
    seen at exactly the same instants outweighs one view's whole single-view score (max 2 with the
    defaults): both operators film the performer, so being seen together is the strongest cue."""


@dataclass(frozen=True)
class Track:
    """One person followed through a view.

    Attributes:
        track_id: number of the track, in order of creation.
        frames: (L,) increasing frame positions (indices into the list given to ``track_people``).
        detections: (L,) index of the person in that frame's (N_t, 17, 3) array.
        keypoints: (L, 17, 3) the person's keypoints in those frames.
        boxes: (L, 4) boxes of the confident keypoints (enlarged), px.
    """

    track_id: int
    frames: NDArray[np.int64]
    detections: NDArray[np.int64]
    keypoints: NDArray[np.float64]
    boxes: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.frames)


@dataclass
class _Live:
    """A track being built (mutable, internal)."""

    track_id: int
    frames: list[int] = field(default_factory=list)
    detections: list[int] = field(default_factory=list)
    keypoints: list[NDArray] = field(default_factory=list)
    boxes: list[NDArray] = field(default_factory=list)
    velocity: NDArray = field(default_factory=lambda: np.zeros(2))
    memory: NDArray = field(default_factory=lambda: np.zeros((17, 3)))
    """(17, 3) each joint as last seen confidently (so a partial detection does not erase the rest)."""
    memory_frame: NDArray = field(default_factory=lambda: np.full(17, -1))
    """(17,) frame at which each memory joint was seen."""

    def freeze(self) -> Track:
        return Track(self.track_id, np.asarray(self.frames, dtype=np.int64),
                     np.asarray(self.detections, dtype=np.int64),
                     np.stack(self.keypoints), np.stack(self.boxes))


def track_people(
    per_frame_keypoints: Sequence[NDArray], image_size: tuple[int, int], cfg: TrackingConfig = TrackingConfig()
) -> list[Track]:
    """Link the people of consecutive frames into tracks.

    Args:
        per_frame_keypoints: per frame, (N_t, 17, 3) keypoints of every detected person.
        image_size: ``(W, H)`` px (boxes are clipped to it).
        cfg: association settings.

    Returns:
        Every track, in order of creation (``track_id`` 0, 1, ...). A detection belongs to at most
        one track; people with fewer than ``cfg.min_keypoints`` confident points are in none.
    """
    live: list[_Live] = []
    done: list[_Live] = []
    next_id = 0
    for t, people in enumerate(per_frame_keypoints):
        people = np.asarray(people, dtype=np.float64).reshape(-1, 17, 3)
        usable = np.flatnonzero((people[..., 2] >= cfg.conf_thr).sum(-1) >= max(cfg.min_keypoints, 2))
        kps = people[usable]
        boxes = boxes_from_keypoints(kps, cfg.conf_thr, cfg.box_scale, image_size)
        # Tracks unseen for too long end before matching.
        still = [tr for tr in live if t - tr.frames[-1] <= cfg.max_gap + 1]
        done += [tr for tr in live if t - tr.frames[-1] > cfg.max_gap + 1]
        live = still
        matched_det: set[int] = set()
        if live and len(kps):
            sim = _similarity(live, t, kps, boxes, cfg)
            rows, cols = linear_sum_assignment(-sim)
            for r, c in zip(rows, cols):
                if sim[r, c] >= cfg.min_similarity:
                    _extend(live[r], t, int(usable[c]), kps[c], boxes[c], cfg)
                    matched_det.add(int(c))
        for c in range(len(kps)):
            if c not in matched_det:
                tr = _Live(next_id)
                next_id += 1
                _extend(tr, t, int(usable[c]), kps[c], boxes[c], cfg)
                live.append(tr)
    tracks = sorted((tr.freeze() for tr in done + live), key=lambda tr: tr.track_id)
    log.debug("%d frames: %d tracks (lengths %s)", len(per_frame_keypoints), len(tracks), [len(t) for t in tracks])
    return tracks


def _extend(tr: _Live, t: int, det: int, kp: NDArray, box: NDArray, cfg: TrackingConfig) -> None:
    """Append an observation; update the track's velocity (px per frame) and joint memory."""
    seen = kp[:, 2] >= cfg.conf_thr
    common = seen & (tr.memory[:, 2] >= cfg.conf_thr)
    if common.sum() >= 2:
        # Median joint motion, not box-centre motion: a partial detection (legs only) moves the
        # box centre a lot while the person hardly moved.
        step = np.median((kp[common, :2] - tr.memory[common, :2]) / (t - tr.memory_frame[common, None]), axis=0)
        a = cfg.velocity_smoothing if len(tr.frames) > 1 else 1.0
        tr.velocity = a * step + (1 - a) * tr.velocity
    tr.memory[seen] = kp[seen]
    tr.memory_frame[seen] = t
    tr.memory[t - tr.memory_frame > cfg.max_gap, 2] = 0.0
    tr.frames.append(t)
    tr.detections.append(det)
    tr.keypoints.append(kp)
    tr.boxes.append(box)


def _centre(box: NDArray) -> NDArray:
    return 0.5 * (box[..., :2] + box[..., 2:4])


def _similarity(live: list[_Live], t: int, kps: NDArray, boxes: NDArray, cfg: TrackingConfig) -> NDArray:
    """(M, N) similarity of M live tracks (predicted to frame ``t``) and N detections."""
    gap = np.array([t - tr.frames[-1] for tr in live], dtype=np.float64)  # (M,) >= 1
    pred_kp = np.stack([tr.memory for tr in live])  # (M, 17, 3), a copy
    since = t - np.stack([tr.memory_frame for tr in live])  # (M, 17) frames since each joint was seen
    vel = np.stack([tr.velocity for tr in live])  # (M, 2)
    pred_kp[..., :2] += vel[:, None, :] * since[..., None]
    pred_box = boxes_from_keypoints(pred_kp, cfg.conf_thr, cfg.box_scale)  # (M, 4)
    iou = box_iou(pred_box, boxes)
    # OKS: joints confident in both; distance scale from the track's size, grown with the gap.
    area = np.prod(pred_box[:, 2:] - pred_box[:, :2], axis=-1).clip(1.0, None)
    s = cfg.oks_sigma * np.sqrt(area) * (1 + cfg.gap_growth * (gap - 1))  # (M,)
    both = (pred_kp[:, None, :, 2] >= cfg.conf_thr) & (kps[None, :, :, 2] >= cfg.conf_thr)  # (M, N, 17)
    d2 = np.sum((pred_kp[:, None, :, :2] - kps[None, :, :, :2]) ** 2, axis=-1)
    per_joint = np.exp(-d2 / (2 * s[:, None, None] ** 2))
    n = both.sum(-1)
    oks = np.where(n >= 2, np.where(both, per_joint, 0).sum(-1) / np.maximum(n, 1), 0.0)
    sim = cfg.iou_weight * iou + (1 - cfg.iou_weight) * oks
    age = np.array([min(len(tr.frames), cfg.age_frames) for tr in live]) / max(cfg.age_frames, 1)
    # The bonus only breaks near-ties: it never lifts a pair over the linking threshold.
    return np.where(sim >= cfg.min_similarity, sim + cfg.age_bonus * age[:, None], sim)


# ------------------------------------------------------------------------------------------------
# Picking the performer


def track_scores(
    tracks: Sequence[Track], num_frames: int, image_size: tuple[int, int], weights: SelectionWeights = SelectionWeights()
) -> NDArray[np.float64]:
    """(K,) single-view performer score of each track: weighted length, centrality and size."""
    if not tracks:
        return np.zeros(0)
    W, H = image_size
    length = np.array([len(tr) for tr in tracks]) / max(num_frames, 1)
    half_diag = 0.5 * np.hypot(W, H)
    centrality = np.array([1.0 - np.mean(np.linalg.norm(_centre(tr.boxes) - [W / 2, H / 2], axis=-1)) / half_diag
                           for tr in tracks])
    area = np.array([np.median(np.prod(tr.boxes[:, 2:] - tr.boxes[:, :2], axis=-1)) for tr in tracks])
    size = area / max(area.max(), 1e-9)
    return weights.length * length + weights.centrality * centrality + weights.size * size


def select_performer(
    tracks: Sequence[Track], num_frames: int, image_size: tuple[int, int], weights: SelectionWeights = SelectionWeights()
) -> Track | None:
    """The performer's track in one view (highest :func:`track_scores`); None if there are no tracks."""
    if not tracks:
        return None
    scores = track_scores(tracks, num_frames, image_size, weights)
    best = int(np.argmax(scores))
    log.info("performer: track %d (%d of %d frames, score %.3f; %d tracks)",
             tracks[best].track_id, len(tracks[best]), num_frames, scores[best], len(tracks))
    return tracks[best]


def select_performer_two_views(
    tracks_v1: Sequence[Track], tracks_v2: Sequence[Track],
    frames_v1: Sequence[int] | NDArray, frames_v2: Sequence[int] | NDArray,
    image_size_v1: tuple[int, int], image_size_v2: tuple[int, int],
    num_frames_v1: int | None = None, num_frames_v2: int | None = None,
    weights: SelectionWeights = SelectionWeights(), candidates: int = 8,
) -> tuple[Track | None, Track | None]:
    """The performer's track in each view, preferring tracks seen at the same instants in both.

    Args:
        tracks_v1, tracks_v2: each view's tracks (from :func:`track_people`).
        frames_v1, frames_v2: (S,) aligned frame lists: sequence instant ``k`` is frame position
            ``frames_v1[k]`` in view 1 and ``frames_v2[k]`` in view 2 (after sync and slicing).
        image_size_v1, image_size_v2: ``(W, H)`` of each view.
        num_frames_v1, num_frames_v2: frames in each view's track input (default: max frame + 1
            of the aligned lists).
        weights: scoring weights; ``cross_view`` weighs the co-presence term.
        candidates: only the best this many tracks per view (single-view score) are paired.

    Returns:
        ``(track_v1, track_v2)`` maximising ``score_v1 + score_v2 + cross_view * co-presence``,
        where co-presence is the intersection over union of the sequence instants at which each
        track is seen. A view without tracks gives None (the other is then chosen alone).
    """
    f1 = np.asarray(frames_v1, dtype=np.int64).reshape(-1)
    f2 = np.asarray(frames_v2, dtype=np.int64).reshape(-1)
    if f1.shape != f2.shape:
        raise ValueError(f"aligned frame lists differ in length: {len(f1)} vs {len(f2)}")
    n1 = num_frames_v1 if num_frames_v1 is not None else int(f1.max(initial=-1)) + 1
    n2 = num_frames_v2 if num_frames_v2 is not None else int(f2.max(initial=-1)) + 1
    if not tracks_v1 or not tracks_v2:
        return (select_performer(tracks_v1, n1, image_size_v1, weights),
                select_performer(tracks_v2, n2, image_size_v2, weights))
    s1 = track_scores(tracks_v1, n1, image_size_v1, weights)
    s2 = track_scores(tracks_v2, n2, image_size_v2, weights)
    c1, c2 = np.argsort(-s1)[:candidates], np.argsort(-s2)[:candidates]
    p1 = np.stack([np.isin(f1, tracks_v1[i].frames) for i in c1])  # (K1, S) seen at instant k
    p2 = np.stack([np.isin(f2, tracks_v2[j].frames) for j in c2])  # (K2, S)
    inter = p1.astype(np.float64) @ p2.T.astype(np.float64)
    union = p1.sum(1)[:, None] + p2.sum(1)[None, :] - inter
    copresence = inter / np.maximum(union, 1)
    total = s1[c1][:, None] + s2[c2][None, :] + weights.cross_view * copresence
    a, b = np.unravel_index(int(np.argmax(total)), total.shape)
    t1, t2 = tracks_v1[c1[a]], tracks_v2[c2[b]]
    log.info("performer: v1 track %d, v2 track %d (co-presence %.2f)", t1.track_id, t2.track_id, copresence[a, b])
    return t1, t2


def performer_keypoints(track: Track | None, num_frames: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The performer's per-frame arrays from their track.

    Returns:
        ``(keypoints, boxes)``: (T, 17, 3) keypoints, zeros (confidence 0) where the performer is
        not seen; (T, 4) boxes, NaN where not seen. ``T = num_frames``.
    """
    kps = np.zeros((num_frames, 17, 3))
    boxes = np.full((num_frames, 4), np.nan)
    if track is not None and len(track):
        inside = track.frames < num_frames
        kps[track.frames[inside]] = track.keypoints[inside]
        boxes[track.frames[inside]] = track.boxes[inside]
    return kps, boxes
