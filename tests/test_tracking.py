"""Performer identity: people crossing, occlusions, spurious detections, two views, real data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from embodmocap.perception.precomputed import PrecomputedKeypoints
from embodmocap.perception.tracking import (
    SelectionWeights, TrackingConfig, performer_keypoints, select_performer, select_performer_two_views,
    track_people,
)

SIZE = (1000, 700)  # (W, H)
POSE2SIM = Path("/work/shared/data/pose2sim_demo/pose")

# COCO-17 offsets of a standing person facing the camera, px at scale 1 (origin: between the hips).
_OFF = np.array([(0, -150), (6, -156), (-6, -156), (12, -152), (-12, -152), (30, -110), (-30, -110),
                 (35, -55), (-35, -55), (38, -5), (-38, -5), (18, 0), (-18, 0), (18, 80), (-18, 80),
                 (18, 160), (-18, 160)], dtype=np.float64)


def _person(cx, cy, s, rng, conf=0.9):
    """(17, 3) keypoints with 2 px noise."""
    return np.c_[np.array([cx, cy]) + s * _OFF + rng.normal(0, 2, (17, 2)), np.full(17, conf)]


def _frames(people_per_frame, rng):
    """Shuffle each frame's people (identity must not come from the order); return the keypoint
    arrays and, per frame, the label of each row."""
    kps, labels = [], []
    for people in people_per_frame:
        order = rng.permutation(len(people))
        kps.append(np.stack([people[i][1] for i in order]) if people else np.zeros((0, 17, 3)))
        labels.append([people[i][0] for i in order])
    return kps, labels


def _labels_of(track, labels):
    return {labels[f][d] for f, d in zip(track.frames, track.detections)}


def test_person_crossing_in_front_keeps_the_identity():
    rng = np.random.default_rng(0)
    T, frames = 90, []
    hidden = 0
    for t in range(T):
        px, cx = 420 + 2.0 * t, 1060 - 16.0 * t  # performer walks right, crosser runs left in front
        people = []
        dx = cx - px
        if abs(dx) >= 60:
            perf = _person(px, 330, 1.0, rng)
            if abs(dx) < 130:  # partly hidden: the side nearer the crosser is not detected
                side = np.sign(dx) * _OFF[:, 0] > 0
                perf[side, 2] = 0.0
            people.append(("performer", perf))
        else:
            hidden += 1
        if -80 < cx < SIZE[0] + 80:
            people.append(("crosser", _person(cx, 380, 1.35, rng)))
        frames.append(people)
    kps, labels = _frames(frames, rng)
    assert hidden >= 6  # the performer really disappears behind the crosser
    # Picking the largest person per frame (no tracking) would take the crosser in many frames.
    area = [np.ptp(k[..., 0], axis=-1) * np.ptp(k[..., 1], axis=-1) for k in kps]
    naive = [lab[int(np.argmax(a))] for lab, a in zip(labels, area) if len(lab)]
    assert naive.count("crosser") > 20
    tracks = track_people(kps, SIZE)
    for tr in tracks:
        assert len(_labels_of(tr, labels)) == 1, "a track mixes two people"
    perf = select_performer(tracks, T, SIZE)
    assert _labels_of(perf, labels) == {"performer"}
    assert len(perf) == T - hidden  # every frame the performer is seen, in one track
    k, boxes = performer_keypoints(perf, T)
    seen = np.array([any(lab == "performer" for lab in f) for f in labels])
    assert np.all(k[~seen] == 0) and np.all(np.isnan(boxes[~seen]))
    assert np.all(np.isfinite(boxes[seen]))


def test_occlusion_of_ten_frames_and_spurious_detections():
    rng = np.random.default_rng(1)
    T, frames = 80, []
    for t in range(T):
        people = []
        if not 40 <= t < 50:  # occluded for 10 frames while walking on
            people.append(("performer", _person(350 + 3.0 * t, 330, 1.0, rng)))
        people.append(("bystander", _person(80, 300, 0.6, rng)))  # at the edge, all along
        if t in (20, 21):  # a spurious detection, big and central, two frames
            people.append(("ghost", _person(520, 360, 1.6, rng, conf=0.5)))
        if t == 30:  # too few confident points to be anyone
            p = _person(600, 300, 1.0, rng)
            p[2:, 2] = 0.05
            people.append(("fragment", p))
        frames.append(people)
    kps, labels = _frames(frames, rng)
    tracks = track_people(kps, SIZE, TrackingConfig(max_gap=15))
    assert sorted(len(tr) for tr in tracks) == [2, 70, 80]  # the fragment is in no track
    perf = select_performer(tracks, T, SIZE)
    assert _labels_of(perf, labels) == {"performer"} and len(perf) == 70
    k, boxes = performer_keypoints(perf, T)
    assert np.all(k[40:50] == 0) and np.all(np.isnan(boxes[40:50]))
    assert np.all(k[50:, :, 2] > 0)
    # A gap longer than max_gap ends the track: the same data with max_gap 5 splits the performer.
    short = track_people(kps, SIZE, TrackingConfig(max_gap=5))
    perf_parts = [tr for tr in short if _labels_of(tr, labels) == {"performer"}]
    assert sorted(len(tr) for tr in perf_parts) == [30, 40]
    # The bystander wins when size and centrality are ignored and only length counts.
    only_length = select_performer(tracks, T, SIZE, SelectionWeights(length=1, centrality=0, size=0))
    assert _labels_of(only_length, labels) == {"bystander"}


def test_two_views_prefer_tracks_seen_at_the_same_instants():
    rng = np.random.default_rng(2)
    S, off = 100, 5  # sequence instants; view 2 started 5 frames earlier than view 1
    v1, v2 = [], []
    for k in range(S):
        a = [("bystander", _person(500, 360, 1.15, rng))]  # central, large, always in view 1
        if k < 55:  # the performer walks out of both views at instant 55
            a.append(("performer", _person(300 - k, 340, 1.0, rng)))
        v1.append(a)
    for f in range(S + off):
        k = f - off
        b = [("other", _person(900, 300, 0.5, rng))] if k >= 30 else []  # small, at the edge, late
        if 0 <= k < 55:
            b.append(("performer", _person(480 + k, 350, 1.2, rng)))
        v2.append(b)
    k1, l1 = _frames(v1, rng)
    k2, l2 = _frames(v2, rng)
    t1, t2 = track_people(k1, SIZE), track_people(k2, SIZE)
    # One view alone picks the bystander (always there, central, larger) ...
    assert _labels_of(select_performer(t1, S, SIZE), l1) == {"bystander"}
    # ... both views together pick the performer, seen at the same instants in both.
    p1, p2 = select_performer_two_views(t1, t2, np.arange(S), np.arange(S) + off, SIZE, SIZE)
    assert _labels_of(p1, l1) == {"performer"} and _labels_of(p2, l2) == {"performer"}
    # Without the cross-view term the answer is the single-view one (the term does the work).
    q1, _ = select_performer_two_views(t1, t2, np.arange(S), np.arange(S) + off, SIZE, SIZE,
                                       weights=SelectionWeights(cross_view=0.0))
    assert _labels_of(q1, l1) == {"bystander"}
    # A view with no one: the other is chosen alone.
    n1, n2 = select_performer_two_views([], t2, np.arange(S), np.arange(S) + off, SIZE, SIZE)
    assert n1 is None and _labels_of(n2, l2) == {"performer"}
    with pytest.raises(ValueError, match="differ in length"):
        select_performer_two_views(t1, t2, np.arange(S), np.arange(S - 1), SIZE, SIZE)


def test_empty_input():
    assert track_people([np.zeros((0, 17, 3))] * 5, SIZE) == []
    assert select_performer([], 5, SIZE) is None
    k, b = performer_keypoints(None, 5)
    assert k.shape == (5, 17, 3) and not k.any() and b.shape == (5, 4) and np.isnan(b).all()


@pytest.mark.skipif(not POSE2SIM.is_dir(), reason="real Pose2Sim demo data not available")
def test_real_cameras_with_a_bystander_and_a_split_detection():
    # cam01 and cam02 see a second, static person at the image edge; in cam01 frame 37 the subject
    # is detected in two pieces (upper body, legs). The subject stays one track in every camera.
    W, H = 1088, 1920
    for cam in ("cam01_json", "cam02_json"):
        kps = PrecomputedKeypoints(POSE2SIM / cam).read(range(100))
        assert max(len(k) for k in kps) >= 2
        tracks = track_people(kps, (W, H))
        perf = select_performer(tracks, 100, (W, H))
        assert len(perf) == 100
        cx = 0.5 * (perf.boxes[:, 0] + perf.boxes[:, 2])
        assert np.all(np.abs(cx - W / 2) < 0.3 * W)  # the central subject, not the edge bystander
        # No frame of the subject's track lies in the bystander's region (identity kept).
        others = [tr for tr in tracks if tr is not perf and len(tr) > 50]
        assert others and all(np.median(np.abs(0.5 * (o.boxes[:, 0] + o.boxes[:, 2]) - W / 2)) > 0.2 * W for o in others)
