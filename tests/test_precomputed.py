"""The ``precomputed`` perception backends: real OpenPose output, what the synthetic studio writes,
COCO keypoint files, masks, depth, body priors, missing frames, and reading speed and memory."""

from __future__ import annotations

import json
import logging
import time
import tracemalloc
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from embodmocap.errors import InputError
from embodmocap.io.body_prior import BodyPriorSeq, write_body_prior
from embodmocap.io.captures import open_capture
from embodmocap.io.manifest import load_manifest
from embodmocap.io.openpose import read_openpose_raw, write_openpose_json
from embodmocap.perception.precomputed import (
    PrecomputedBodyPrior, PrecomputedDepth, PrecomputedDetector, PrecomputedKeypoints, PrecomputedMasks,
    box_iou, boxes_from_keypoints,
)
from embodmocap.perception.roles import BodyPriorEstimator, KeypointEstimator, MaskSegmenter, PersonDetector
from embodmocap.perception.tracking import select_performer, track_people
from embodmocap.synth.config import SynthConfig
from embodmocap.synth.studio import synthesize
from embodmocap.types import COCO17_NAMES

POSE2SIM = Path("/work/shared/data/pose2sim_demo/pose")
REAL_SIZE = (1088, 1920)  # (W, H) of the Pose2Sim demo videos (portrait)
SMALL = dict(seconds=1.5, scene_seconds=2.0, width=160, height=120, depth_width=64, depth_height=48)
J = {n: i for i, n in enumerate(COCO17_NAMES)}


def _coco_person(cx=300.0, cy=200.0, s=1.0, conf=0.9) -> np.ndarray:
    """(17, 3) COCO-17 points of a standing person facing the camera."""
    off = np.array([(0, -150), (6, -156), (-6, -156), (12, -152), (-12, -152), (30, -110), (-30, -110),
                    (35, -55), (-35, -55), (38, -5), (-38, -5), (18, 0), (-18, 0), (18, 80), (-18, 80),
                    (18, 160), (-18, 160)], dtype=np.float64)
    return np.c_[np.array([cx, cy]) + s * off, np.full(17, conf)]


# ------------------------------------------------------------------------------------------------
# Real detector output: four Pose2Sim cameras, BODY_25B


@pytest.mark.skipif(not POSE2SIM.is_dir(), reason="real Pose2Sim demo data not available")
def test_real_four_cameras_through_the_backend():
    coverage = {}
    for cam in sorted(POSE2SIM.glob("cam*_json")):
        kp = PrecomputedKeypoints(cam)
        people = kp.read(range(0, 110))
        # Two of the cameras see the subject in profile (one eye never detected): the layout must
        # still be recognised on every camera.
        assert kp.layout == "BODY_25B", cam.name
        coverage[cam.name] = (kp.frames.tolist(), kp.missing_frames)
        assert all(len(p) >= 1 for p in people[:100]) and all(len(p) == 0 for p in people[100:])
        # Boxes from keypoints contain every confident point, and the detector scores them.
        for p in people[:100:7]:
            boxes = boxes_from_keypoints(p, conf_thr=0.3, scale=1.2)
            ok = p[..., 2] >= 0.3
            for b, q, m in zip(boxes, p, ok):
                if m.sum() >= 2:
                    xy = q[m, :2]
                    assert np.all((xy >= b[:2]) & (xy <= b[2:])), (cam.name, b, xy)
        dets = PrecomputedDetector(kp).detect([np.zeros((4, 4, 3), np.uint8)] * 3, [0, 50, 105])
        assert dets[2].shape == (0, 5) and len(dets[0]) >= 1
        assert np.all((dets[0][:, 4] > 0.3) & (dets[0][:, 4] <= 1)) and np.all(dets[0][:, :4] <= 3)  # clipped to 4x4
        # The performer (one track over all 100 frames) has a standing person's anatomy in COCO order.
        perf = select_performer(track_people(people[:100], REAL_SIZE), 100, REAL_SIZE)
        assert len(perf) == 100, cam.name
        y, c = perf.keypoints[..., 1], perf.keypoints[..., 2] > 0.3
        mid = lambda a, b: 0.5 * (y[:, J[a]] + y[:, J[b]])  # noqa: E731
        chain = (mid("left_shoulder", "right_shoulder") < mid("left_hip", "right_hip")) \
            & (mid("left_hip", "right_hip") < mid("left_knee", "right_knee")) \
            & (mid("left_knee", "right_knee") < mid("left_ankle", "right_ankle"))
        ok = np.all(c[:, [J[n] for n in ("left_shoulder", "right_shoulder", "left_hip", "right_hip",
                                          "left_knee", "right_knee", "left_ankle", "right_ankle")]], axis=1)
        assert ok.sum() > 80 and chain[ok].mean() > 0.95, (cam.name, chain[ok].mean())
        # The head (nose and ears) is above the shoulders.
        head = np.where(c[:, :5], y[:, :5], np.inf).min(axis=1)
        seen = np.isfinite(head)
        assert seen.sum() > 80 and np.mean(head[seen] < mid("left_shoulder", "right_shoulder")[seen]) > 0.95
    # All four cameras agree on the frames covered and on the missing frames.
    assert len(coverage) == 4
    assert all(v == (list(range(100)), list(range(100, 110))) for v in coverage.values()), coverage


@pytest.mark.skipif(not POSE2SIM.is_dir(), reason="real Pose2Sim demo data not available")
def test_real_wrong_layout_is_refused_or_breaks_anatomy():
    # COCO-18 has 18 points: the 25-point files are refused with the file named.
    kp = PrecomputedKeypoints(POSE2SIM / "cam01_json", layout="COCO18")
    with pytest.raises(InputError, match="cam01.0000.json.*25 keypoints"):
        kp.people(0)


# ------------------------------------------------------------------------------------------------
# What the synthetic studio writes


@pytest.fixture(scope="module")
def studio(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "s"
    synthesize(SynthConfig(seed=5, **SMALL), out)
    return out


def test_studio_keypoints_masks_prior_depth_read_back(studio):
    m = load_manifest(studio / "session.toml")
    for name, view in m.sequences["seq0"].views.items():
        cap = open_capture(view.capture)
        n = cap.num_frames
        kp = PrecomputedKeypoints(view.keypoints)
        assert kp.frames.tolist() == list(range(n))
        got = kp.read(range(n + 3))
        for f in range(n):
            raw = read_openpose_raw(view.keypoints / f"{f:06d}_keypoints.json")
            np.testing.assert_array_equal(got[f], raw.reshape(-1, 17, 3))  # COCO-17: identity map
        assert kp.layout == "COCO17" and kp.missing_frames == [n, n + 1, n + 2]
        assert sum(len(p) for p in got) > n // 2  # the performer is seen in most frames

        masks = PrecomputedMasks(view.masks)
        rgb = cap.frames.rgb(0)
        out = masks.segment([rgb, rgb, rgb], [0, n // 2, n + 5], np.full((3, 4), np.nan))
        for f, mk in zip([0, n // 2], out):
            want = np.asarray(Image.open(view.masks / f"{f:06d}.png").convert("L")) > 127
            assert mk.shape == rgb.shape[:2] and mk.dtype == bool
            np.testing.assert_array_equal(mk, want)
        assert not out[2].any() and masks.missing_frames == [n + 5]

        prior = PrecomputedBodyPrior(view.body_prior)
        seq = prior.estimate([], [2, 0, n + 1], None)
        np.testing.assert_array_equal(seq.frame_ids, [2, 0])
        row = int(np.flatnonzero(prior.prior.frame_ids == 2)[0])
        np.testing.assert_array_equal(seq.body_pose[0], prior.prior.body_pose[row])
        assert prior.missing_frames == [n + 1]

        # The capture's own depth folder (uint16 mm PNG) reads as the capture reader gives it.
        depth = PrecomputedDepth(view.capture / "depth")
        np.testing.assert_allclose(depth.depth(3), cap.frames.depth_m(3), atol=1e-6)


# ------------------------------------------------------------------------------------------------
# COCO keypoint files, OpenPose folders, matching boxes


def test_coco_results_and_annotations_by_frame_number(tmp_path):
    a, b = _coco_person(), _coco_person(cx=600, s=0.8, conf=0.7)
    results = [{"image_id": 12, "category_id": 1, "keypoints": a.ravel().tolist(), "score": 0.9},
               {"image_id": 12, "category_id": 1, "keypoints": b.ravel().tolist(), "score": 0.8},
               {"image_id": 13, "category_id": 1, "keypoints": b.ravel().tolist(), "score": 0.8}]
    (tmp_path / "res.json").write_text(json.dumps(results))
    kp = PrecomputedKeypoints(tmp_path / "res.json")
    assert kp.kind == "coco" and kp.frames.tolist() == [12, 13]
    np.testing.assert_allclose(kp.people(12), np.stack([a, b]))
    assert kp.people(14).shape == (0, 17, 3) and kp.missing_frames == [14]

    # Annotations: frames from the trailing digits of the file names (ids are arbitrary); a folder
    # with a single COCO file is read as that file.
    ann = {"images": [{"id": 901, "file_name": "clip/frame_000007.jpg"}, {"id": 902, "file_name": "frame_000008.jpg"}],
           "annotations": [{"image_id": 901, "category_id": 1, "keypoints": np.c_[a[:, :2], np.full(17, 2)].ravel().tolist()}]}
    folder = tmp_path / "ann"
    folder.mkdir()
    (folder / "person_keypoints.json").write_text(json.dumps(ann))
    kp = PrecomputedKeypoints(folder)
    assert kp.kind == "coco" and kp.frames.tolist() == [7, 8]
    np.testing.assert_allclose(kp.people(7)[0], np.c_[a[:, :2], np.ones(17)])
    assert kp.people(8).shape == (0, 17, 3) and kp.missing_frames == []  # image listed, nobody in it

    # Two images naming one frame, or an image with no number, are refused.
    ann["images"][1]["file_name"] = "other_000007.png"
    (tmp_path / "dup.json").write_text(json.dumps(ann))
    with pytest.raises(InputError, match="frame 7"):
        PrecomputedKeypoints(tmp_path / "dup.json")
    (tmp_path / "nonum.json").write_text(json.dumps([{"image_id": "abc", "keypoints": a.ravel().tolist()}]))
    with pytest.raises(InputError, match="no frame number"):
        PrecomputedKeypoints(tmp_path / "nonum.json")


def test_estimate_matches_given_boxes_and_protocols(tmp_path):
    a, b = _coco_person(), _coco_person(cx=700, s=0.8)
    write_openpose_json(tmp_path / "000003_keypoints.json", [a, b])
    kp = PrecomputedKeypoints(tmp_path)
    boxes = np.stack([boxes_from_keypoints(b), [0, 0, 10, 10], boxes_from_keypoints(a) + 5])
    out = kp.estimate([None], [3], [boxes])[0]
    np.testing.assert_allclose(out[0], b)
    assert np.all(out[1] == 0)  # nobody there
    np.testing.assert_allclose(out[2], a)
    assert kp.estimate([None], [4], [boxes])[0].shape == (3, 17, 3) and kp.missing_frames == [4]
    det = PrecomputedDetector(kp)
    assert isinstance(kp, KeypointEstimator) and isinstance(det, PersonDetector)
    assert isinstance(PrecomputedMasks(tmp_path), MaskSegmenter)
    # Boxes: scale about the centre, NaN with fewer than two confident points, IoU of equal boxes 1.
    bx = boxes_from_keypoints(a, scale=1.0)
    np.testing.assert_allclose(bx, [a[:, 0].min(), a[:, 1].min(), a[:, 0].max(), a[:, 1].max()])
    one = a.copy()
    one[1:, 2] = 0
    assert np.all(np.isnan(boxes_from_keypoints(one)))
    assert box_iou(bx[None], bx[None])[0, 0] == pytest.approx(1.0)


def _body25(person: np.ndarray, layout: str, profile: bool) -> np.ndarray:
    """A (25, 3) OpenPose person from COCO-17 points; ``profile`` hides the right eye and ear."""
    p = person.copy()
    if profile:
        p[[J["right_eye"], J["right_ear"]], 2] = 0
    neck = 0.5 * (p[J["left_shoulder"]] + p[J["right_shoulder"]])
    mid_hip = 0.5 * (p[J["left_hip"]] + p[J["right_hip"]])
    feet = [p[J["left_ankle"]] + [4, 15, 0]] * 3 + [p[J["right_ankle"]] + [-4, 15, 0]] * 3
    if layout == "BODY_25B":
        return np.vstack([p, neck, p[J["nose"]] - [0, 25, 0], *feet])
    order = [J[n] for n in ("nose",)] + [-1] + [J[n] for n in (
        "right_shoulder", "right_elbow", "right_wrist", "left_shoulder", "left_elbow", "left_wrist")] + [-2] \
        + [J[n] for n in ("right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle",
                          "right_eye", "left_eye", "right_ear", "left_ear")]
    rows = [neck if i == -1 else mid_hip if i == -2 else p[i] for i in order]
    return np.vstack(rows + feet)


@pytest.mark.parametrize("layout", ["BODY_25", "BODY_25B"])
def test_25_point_layout_of_profile_views(tmp_path, layout):
    for f in range(5):
        person = _coco_person(cx=300 + 10 * f)
        write_openpose_json(tmp_path / f"cam.{f:04d}.json", [_body25(person, layout, profile=True)])
    kp = PrecomputedKeypoints(tmp_path)
    got = kp.people(2)
    assert kp.layout == layout
    want = _coco_person(cx=320)
    want[[J["right_eye"], J["right_ear"]], 2] = 0
    np.testing.assert_allclose(got[0], want)


# ------------------------------------------------------------------------------------------------
# Masks, depth, body prior files


def test_masks_names_resize_missing_and_bad_files(tmp_path, caplog):
    m = np.zeros((60, 80), np.uint8)
    m[10:40, 20:50] = 200
    m[0, 0] = 100  # <= 127: background
    cv2.imwrite(str(tmp_path / "000002.png"), m)
    cv2.imwrite(str(tmp_path / "frame_0004.png"), m)
    cv2.imwrite(str(tmp_path / "clip_7.png"), np.dstack([m] * 3))  # RGB mask
    (tmp_path / "readme.txt").write_text("ignored")
    masks = PrecomputedMasks(tmp_path)
    assert masks.frames.tolist() == [2, 4, 7]
    for f in (2, 4, 7):
        np.testing.assert_array_equal(masks.mask(f, (80, 60)), m > 127)
    # A different RGB size: nearest-neighbour resize, warned once.
    with caplog.at_level(logging.WARNING, logger="embodmocap.perception.precomputed"):
        big = masks.segment([np.zeros((120, 160, 3), np.uint8)] * 2, [2, 4], None)
    np.testing.assert_array_equal(big[0], np.kron(m > 127, np.ones((2, 2), bool)))
    assert sum("resizing" in r.message for r in caplog.records) == 1
    # Missing frames are empty and counted once.
    assert not masks.mask(3, (80, 60)).any() and not masks.mask(3, (80, 60)).any()
    assert masks.missing_frames == [3]
    (tmp_path / "000009.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="000009.png"):
        PrecomputedMasks(tmp_path).mask(9)
    cv2.imwrite(str(tmp_path / "x_000002.png"), m)
    with pytest.raises(InputError, match="frame 2"):
        PrecomputedMasks(tmp_path)
    with pytest.raises(InputError, match="not found"):
        PrecomputedMasks(tmp_path / "nope")


def test_depth_png_npy_missing_and_bad(tmp_path):
    rng = np.random.default_rng(0)
    mm = rng.integers(0, 5000, (48, 64)).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "000000.png"), mm)
    metres = rng.uniform(0.2, 4, (48, 64)).astype(np.float32)
    metres[0, 0], metres[0, 1] = np.nan, -1
    np.save(tmp_path / "000001.npy", metres)
    depth = PrecomputedDepth(tmp_path)
    np.testing.assert_allclose(depth.depth(0), mm * 0.001, rtol=1e-6)
    d1 = depth.depth(1)
    assert d1[0, 0] == 0 and d1[0, 1] == 0
    np.testing.assert_array_equal(d1[1:], metres[1:])
    np.testing.assert_allclose(PrecomputedDepth(tmp_path, scale=0.0001).depth(0), mm * 0.0001, rtol=1e-6)
    gone = depth.read([5, 0])
    assert gone[0].shape == (48, 64) and not gone[0].any() and depth.missing_frames == [5]
    cv2.imwrite(str(tmp_path / "000002.png"), (mm // 100).astype(np.uint8))
    with pytest.raises(InputError, match="16-bit"):
        PrecomputedDepth(tmp_path).depth(2)  # the file index is built at construction


def test_body_prior_lookup_and_duplicates(tmp_path):
    rng = np.random.default_rng(1)
    ids = np.array([5, 0, 1, 2])
    prior = BodyPriorSeq(rng.normal(size=(4, 3)), rng.normal(size=(4, 69)), rng.normal(size=(4, 10)),
                         rng.normal(size=(4, 3)), ids)
    write_body_prior(tmp_path / "p.npz", prior)
    pb = PrecomputedBodyPrior(tmp_path / "p.npz")
    assert isinstance(pb, BodyPriorEstimator) and pb.frames.tolist() == [0, 1, 2, 5]
    seq, found = pb.take([0, 3, 5])
    np.testing.assert_array_equal(found, [True, False, True])
    np.testing.assert_array_equal(seq.frame_ids, [0, 3, 5])
    np.testing.assert_allclose(seq.transl_cam[[0, 2]], prior.transl_cam[[1, 0]])
    np.testing.assert_allclose(seq.betas[2], prior.betas[0])
    assert np.all(seq.body_pose[1] == 0) and pb.missing_frames == [3]
    est = pb.estimate([], [5, 9, 1])
    np.testing.assert_array_equal(est.frame_ids, [5, 1])
    np.testing.assert_allclose(est.global_orient_cam, prior.global_orient_cam[[0, 2]])
    assert pb.missing_frames == [3, 9]
    write_body_prior(tmp_path / "dup.npz", BodyPriorSeq(prior.global_orient_cam, prior.body_pose, prior.betas,
                                                        prior.transl_cam, [0, 1, 1, 2]))
    with pytest.raises(InputError, match="frame 1 appears twice"):
        PrecomputedBodyPrior(tmp_path / "dup.npz")


# ------------------------------------------------------------------------------------------------
# Speed and memory (figures printed, not asserted; memory asserted not to grow)


def _write_view(folder: Path, n: int, size=(960, 720)) -> None:
    W, H = size
    (folder / "kp").mkdir(parents=True)
    (folder / "mask").mkdir()
    m = np.zeros((H, W), np.uint8)
    m[200:600, 400:600] = 255
    for f in range(n):
        write_openpose_json(folder / "kp" / f"{f:06d}_keypoints.json", [_coco_person(cx=450 + f % 50)])
        cv2.imwrite(str(folder / "mask" / f"{f:06d}.png"), m)


def _read_all(folder: Path, n: int) -> float:
    kp, masks = PrecomputedKeypoints(folder / "kp"), PrecomputedMasks(folder / "mask")
    t0 = time.perf_counter()
    for start in range(0, n, 32):  # the stage reads in chunks
        ids = list(range(start, min(start + 32, n)))
        kp.read(ids)
        masks.segment([np.empty((720, 960, 3), np.uint8)] * len(ids), ids, None)
    return n / (time.perf_counter() - t0)


def test_throughput_and_memory_do_not_grow(tmp_path, capsys):
    _write_view(tmp_path / "short", 60)
    _write_view(tmp_path / "long", 240)
    _read_all(tmp_path / "short", 60)  # warm up (imports, file cache)
    peaks = {}
    for name, n in (("short", 60), ("long", 240)):
        tracemalloc.start()
        fps = _read_all(tmp_path / name, n)
        peaks[name] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        with capsys.disabled():
            print(f"\nprecomputed keypoints+masks 960x720, {n} frames: {fps:.0f} frames/s "
                  f"(peak traced memory {peaks[name] / 2**20:.1f} MiB)")
    # Four times the frames, (nearly) the same peak memory: nothing is cached per frame.
    assert peaks["long"] < 1.3 * peaks["short"] + 2**20, peaks
