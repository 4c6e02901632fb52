"""MediaPipe Pose backend on the real Pose2Sim demo videos, checked against their OpenPose keypoints.

The OpenPose (BODY_25B) files of ``pose2sim_demo`` are a second detector's output, not ground
truth; the bounds below are loose enough for two different detectors and tight enough to catch a
wrong joint mapping (a left/right swap moves a joint by a shoulder width, ~10 % of the height),
a wrong pixel scale or a wrong crop-to-frame transform.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from embodmocap.errors import MissingExtraError
from embodmocap.perception import roles
from embodmocap.perception.mediapipe_backend import (
    COCO17_FROM_BLAZEPOSE, MediaPipeConfig, MediaPipePose, _to_coco17,
)
from embodmocap.types import COCO17_NAMES
from shared_data import shared_data

DATA = shared_data("pose2sim_demo")

#: Video frame v of these files is best matched by OpenPose file number v - 1 (see the benchmark
#: and ``test_openpose_files_lag_the_video_by_one_frame``).
JSON_OFFSET = -1
FIRST, COUNT = 62, 30  # the stretch of cam04 (one person in view) where the performer moves most
MP_CONF, OP_CONF = 0.5, 0.3  # "confident" for MediaPipe visibility / OpenPose's coarse scores


def _frames(cam: str, ids):
    from embodmocap.io.video import VideoReader

    with VideoReader(DATA / "videos" / f"{cam}.mp4") as reader:
        return [reader.read(int(i)) for i in ids]


def _openpose(cam: str, json_ids):
    from embodmocap.io.openpose import read_keypoint_folder

    # layout given explicitly: the coarse (0.1-step) scores of some cameras leave too few
    # confident faces for read_keypoint_folder's automatic BODY_25 / BODY_25B decision.
    kp, missing = read_keypoint_folder(DATA / "pose" / f"{cam}_json", json_ids, layout="BODY_25B")
    assert not missing
    return kp.data


def _errors(mp_kp, op_kp):
    """(T, 17) pixel distances, NaN where either side is not confident."""
    d = np.linalg.norm(mp_kp[..., :2] - op_kp[..., :2], axis=-1)
    ok = (mp_kp[..., 2] >= MP_CONF) & (op_kp[..., 2] >= OP_CONF)
    return np.where(ok, d, np.nan)


@pytest.fixture(scope="module")
def cam04():
    pytest.importorskip("mediapipe")
    if not (DATA / "videos" / "cam04.mp4").is_file():
        pytest.skip("pose2sim_demo data not available")
    # one frame either side, for the frame-offset check
    ids = np.arange(FIRST - 1, FIRST + COUNT + 1)
    frames = _frames("cam04", ids)
    with MediaPipePose(video_mode=False) as static:
        kp_static = np.concatenate(static.estimate(frames, ids))
    return {"ids": ids, "frames": frames, "kp_static": kp_static,
            "op": _openpose("cam04", ids)}


# ---------------------------------------------------------------------------------------------
# no mediapipe needed
# ---------------------------------------------------------------------------------------------


def test_blazepose_to_coco17_mapping_by_name():
    # BlazePose's 33 landmark names, in index order (person's left = "left").
    blaze = ["nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
             "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right",
             "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist",
             "right_wrist", "left_pinky", "right_pinky", "left_index", "right_index", "left_thumb",
             "right_thumb", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle",
             "right_ankle", "left_heel", "right_heel", "left_foot_index", "right_foot_index"]
    assert [blaze[i] for i in COCO17_FROM_BLAZEPOSE] == list(COCO17_NAMES)
    lm = np.column_stack([np.arange(33.0), 100 + np.arange(33.0), np.linspace(0, 1, 33)])
    kp = _to_coco17(lm)
    assert kp.shape == (17, 3)
    np.testing.assert_array_equal(kp[1:, 0], np.array(COCO17_FROM_BLAZEPOSE[1:], float))
    assert np.all(kp[0] == 0)  # nose had visibility 0 -> the whole row reads "missing"


@pytest.mark.parametrize("complexity", [0, 2])
def test_model_complexity_other_than_1_refused(complexity):
    with pytest.raises(ValueError, match="model_complexity=1"):
        MediaPipePose(model_complexity=complexity)


def test_bad_settings_refused():
    with pytest.raises(ValueError, match="mask_threshold"):
        MediaPipePose(mask_threshold=1.5)
    with pytest.raises(ValueError, match="either config"):
        MediaPipePose(MediaPipeConfig(), video_mode=False)


def test_missing_mediapipe_gives_one_line_naming_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "mediapipe", None)  # makes `import mediapipe` fail
    pose = MediaPipePose()
    with pytest.raises(MissingExtraError, match=r"embodmocap\[mediapipe\]"):
        pose.detect([np.zeros((64, 64, 3), np.uint8)], [0])


# ---------------------------------------------------------------------------------------------
# real videos
# ---------------------------------------------------------------------------------------------


def test_implements_the_roles():
    pose = MediaPipePose()
    assert isinstance(pose, roles.KeypointEstimator)
    assert isinstance(pose, roles.PersonDetector)
    assert isinstance(pose, roles.MaskSegmenter)


def test_openpose_files_lag_the_video_by_one_frame(cam04):
    kp, op = cam04["kp_static"], cam04["op"]
    # video frame v against OpenPose file v + s (both arrays indexed by the same ids)
    n = len(kp)
    med = {s: np.nanmedian(_errors(kp[1:n - 1], op[1 + s:n - 1 + s])) for s in (-1, 0, 1)}
    assert min(med, key=med.get) == JSON_OFFSET, med


@pytest.mark.filterwarnings("ignore:All-NaN slice")
def test_keypoints_match_openpose_on_real_video(cam04):
    kp, op = cam04["kp_static"][1:-1], cam04["op"][1 + JSON_OFFSET:len(cam04["op"]) - 1 + JSON_OFFSET]
    assert kp.shape == (COUNT, 17, 3)
    err = _errors(kp, op)
    per_joint = np.nanmedian(err, axis=0)
    conf = op[..., 2] >= OP_CONF
    height = np.median(np.nanmax(np.where(conf, op[..., 1], np.nan), 1) - np.nanmin(np.where(conf, op[..., 1], np.nan), 1))
    assert height > 500  # the performer stands tall in these portrait frames
    # body joints seen by both in most frames
    for j in range(5, 17):
        assert np.isfinite(err[:, j]).mean() > 0.5, COCO17_NAMES[j]
    assert np.nanmedian(per_joint) < 0.05 * height, per_joint
    assert np.nanmax(per_joint[5:]) < 0.08 * height, per_joint  # no swapped or offset limb
    # a left/right swap would put every left joint nearer OpenPose's right one: it is not
    left, right = [5, 7, 9, 11, 13, 15], [6, 8, 10, 12, 14, 16]
    swapped = np.nanmedian(np.linalg.norm(kp[:, left, :2] - op[:, right, :2], axis=-1))
    assert swapped > 2 * np.nanmedian(err[:, left])


def test_video_mode_and_box_crops_agree_with_whole_image(cam04):
    ids, frames = cam04["ids"][1:11], cam04["frames"][1:11]
    ref = cam04["kp_static"][1:11]
    with MediaPipePose() as pose:
        boxes = pose.detect(frames, ids)
        video = np.concatenate(pose.estimate(frames, ids, boxes))  # reuses the whole-image run
    # reuse_iou > 1 forces a crop run for every box, exercising the crop -> frame mapping
    with MediaPipePose(reuse_iou=1.01) as cropper:
        crop = np.concatenate(cropper.estimate(frames, ids, [b[:, :4] for b in boxes]))
    for other in (video, crop):
        err = _errors(other, ref)
        assert np.nanmedian(err) < 12.0, np.nanmedian(err)
    for b, k in zip(boxes, ref):  # the detected box holds the confident keypoints
        assert b.shape == (1, 5) and 0 < b[0, 4] <= 1
        ok = k[:, 2] >= MP_CONF
        assert np.all((k[ok, 0] >= b[0, 0]) & (k[ok, 0] <= b[0, 2]) & (k[ok, 1] >= b[0, 1]) & (k[ok, 1] <= b[0, 3]))


def test_mask_covers_the_confident_keypoints(cam04):
    ids, frames = cam04["ids"][1:11:3], cam04["frames"][1:11:3]
    op = cam04["op"][1 + JSON_OFFSET:11 + JSON_OFFSET:3]
    with MediaPipePose(video_mode=False) as pose:
        boxes = np.concatenate(pose.detect(frames, ids))[:, :4]
        kps = np.concatenate(pose.estimate(frames, ids))
        masks = pose.segment(frames, ids, boxes)
        masks_nobox = pose.segment(frames, ids, None)
    H, W = frames[0].shape[:2]
    for mask, mask2, kp, o in zip(masks, masks_nobox, kps, op):
        assert mask.shape == (H, W) and mask.dtype == bool
        assert 0.02 < mask.mean() < 0.5
        assert np.array_equal(mask, mask2)  # the box only trims far-away pixels
        body = [5, 6, 11, 12, 13, 14]  # shoulders, hips, knees: inside the silhouette
        for pts in (kp[body][kp[body, 2] >= MP_CONF], o[body][o[body, 2] >= OP_CONF]):
            x = np.clip(np.round(pts[:, 0]).astype(int), 0, W - 1)
            y = np.clip(np.round(pts[:, 1]).astype(int), 0, H - 1)
            assert mask[y, x].mean() >= 0.8


def test_no_person_gives_empty_results():
    pytest.importorskip("mediapipe")
    black = [np.zeros((480, 640, 3), np.uint8)] * 2
    with MediaPipePose() as pose:
        assert [b.shape for b in pose.detect(black, [0, 1])] == [(0, 5), (0, 5)]
        assert [k.shape for k in pose.estimate(black, [0, 1])] == [(0, 17, 3)] * 2
        kp = pose.estimate(black, [0, 1], [np.array([[100.0, 100, 300, 400]]), np.zeros((0, 4))])
        assert kp[0].shape == (1, 17, 3) and np.all(kp[0] == 0) and kp[1].shape == (0, 17, 3)
        masks = pose.segment(black, [0, 1], np.array([[100.0, 100, 300, 400], [np.nan] * 4]))
        assert all(m.shape == (480, 640) and not m.any() for m in masks)


def test_sequence_stage_runs_with_the_mediapipe_backend(tmp_path):
    # MediaPipe for boxes, keypoints and masks through the whole stage on a synthetic session.
    from embodmocap.sequence import stage
    from embodmocap.sequence.config import SequenceConfig
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    session = tmp_path / "s"
    synthesize(SynthConfig(seed=2, seconds=1.5, scene_seconds=0.5, width=320, height=240,
                           depth_width=64, depth_height=48), session)
    cfg = SequenceConfig(detector="mediapipe", keypoints="mediapipe", masks="mediapipe", body_prior="none",
                         min_person_fraction=0.0)
    out = stage.run(cfg, session)
    T = out.figures["frames"]
    for v in ("v1", "v2"):
        kp = np.load(out.layout.view(v).keypoints)
        assert kp["keypoints"].shape == (T, 17, 3)
        assert np.load(out.layout.view(v).masks).shape[0] == T
