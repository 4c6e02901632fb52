"""Stage II's decisions as a pure function: who the performer is in each view.

:func:`solve_performer` takes every person's keypoints per sliced frame of the views (arrays, no
paths), links them into tracks, picks the performer's track consistently across the views and
returns the performer's per-frame keypoints and boxes with the figures the stage reports. The
stage's ``run`` (:mod:`embodmocap.sequence.stage`) reads the inputs through the perception
backends, checks the result against its thresholds with errors naming the files, and writes it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from embodmocap.io.layout import VIEWS
from embodmocap.perception.tracking import (
    TrackingConfig, performer_keypoints, select_performer, select_performer_two_views, track_people,
)


@dataclass(frozen=True)
class PerformerView:
    """The performer in one view.

    Attributes:
        keypoints: (T, 17, 3) pixels and confidence, zeros where not seen.
        boxes: (T, 4) x1, y1, x2, y2 pixels, NaN where not seen.
        seen: (T,) bool.
        track_id: the performer's track (-1 = nobody found).
        tracks: number of tracks in the view.
        seen_fraction: share of frames with the performer.
        longest_gap_s: longest run of frames without the performer, seconds.
    """

    keypoints: NDArray[np.float64]
    boxes: NDArray[np.float64]
    seen: NDArray[np.bool_]
    track_id: int
    tracks: int
    seen_fraction: float
    longest_gap_s: float

    def figures(self, view: str) -> dict:
        conf = self.keypoints[..., 2][self.seen]
        return {
            f"{view}_frames_with_person": int(self.seen.sum()),
            f"{view}_mean_keypoint_confidence": round(float(conf.mean()) if conf.size else 0.0, 4),
            f"{view}_longest_gap_s": round(self.longest_gap_s, 2),
            f"{view}_tracks": self.tracks,
        }


def solve_performer(people: Mapping[str, Sequence[NDArray]], sizes: Mapping[str, tuple[int, int]],
                    fps: Mapping[str, float], cfg: TrackingConfig = TrackingConfig()) -> dict[str, PerformerView]:
    """The performer's keypoints in every view (one or two).

    Args:
        people: view -> per sliced frame, (N_t, 17, 3) keypoints of every person (T frames, the
            same T in every view); two views are chosen jointly (seen at the same instants), one
            view alone.
        sizes: view -> image ``(W, H)`` pixels.
        fps: view -> frame rate (for the gap length).
        cfg: tracking settings.

    Returns:
        view -> :class:`PerformerView`, for the views of ``people``.
    """
    views = [v for v in VIEWS if v in people]
    tracks = {v: track_people(people[v], sizes[v], cfg) for v in views}
    T = len(people[views[0]])
    frames = np.arange(T)
    if len(views) == 1:
        best = (select_performer(tracks[views[0]], T, sizes[views[0]]),)
    else:
        best = select_performer_two_views(tracks[views[0]], tracks[views[1]], frames, frames, sizes[views[0]],
                                          sizes[views[1]], T, T)
    out = {}
    for v, track in zip(views, best):
        kp, boxes = performer_keypoints(track, T)
        seen = kp[..., 2].max(axis=1) > 0
        out[v] = PerformerView(kp, boxes, seen, int(track.track_id) if track else -1, len(tracks[v]),
                               float(seen.mean()) if T else 0.0, longest_run(~seen) / fps[v])
    return out


def longest_run(mask: NDArray) -> int:
    """Length of the longest run of True values of a (T,) bool array."""
    if not mask.any():
        return 0
    padded = np.concatenate([[0], mask.astype(np.int8), [0]])
    d = np.diff(padded)
    return int((np.nonzero(d == -1)[0] - np.nonzero(d == 1)[0]).max())
