"""OpenPose / COCO keypoint files: layouts, auto-detection, folders, and real detector output."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.io.openpose import (
    COCO17_FROM, LAYOUT_SIZE, detect_layout, read_coco_keypoints, read_keypoint_folder,
    read_openpose_json, read_openpose_raw, write_openpose_json,
)
from embodmocap.types import COCO17_NAMES

REAL = Path("/work/shared/data/pose2sim_demo/pose/cam01_json")

# Each layout's point names (independent of the module's index tables, to check them).
NAMES = {
    "COCO18": ["nose", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder",
               "left_elbow", "left_wrist", "right_hip", "right_knee", "right_ankle", "left_hip",
               "left_knee", "left_ankle", "right_eye", "left_eye", "right_ear", "left_ear"],
    "BODY_25": ["nose", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder",
                "left_elbow", "left_wrist", "mid_hip", "right_hip", "right_knee", "right_ankle",
                "left_hip", "left_knee", "left_ankle", "right_eye", "left_eye", "right_ear",
                "left_ear", "left_big_toe", "left_small_toe", "left_heel", "right_big_toe",
                "right_small_toe", "right_heel"],
    "BODY_25B": list(COCO17_NAMES) + ["neck", "head_top", "left_big_toe", "left_small_toe",
                                      "left_heel", "right_big_toe", "right_small_toe", "right_heel"],
    "COCO17": list(COCO17_NAMES),
}


def _person(shift=(0.0, 0.0), scale=1.0) -> dict[str, np.ndarray]:
    """A standing person facing the camera (their left on the image's right), x, y px, conf."""
    p = {
        "nose": (0, 0), "left_eye": (6, -6), "right_eye": (-6, -6), "left_ear": (12, -2),
        "right_ear": (-12, -2), "left_shoulder": (30, 40), "right_shoulder": (-30, 40),
        "left_elbow": (35, 95), "right_elbow": (-35, 95), "left_wrist": (38, 145),
        "right_wrist": (-38, 145), "left_hip": (18, 150), "right_hip": (-18, 150),
        "left_knee": (18, 230), "right_knee": (-18, 230), "left_ankle": (18, 310),
        "right_ankle": (-18, 310), "neck": (0, 38), "mid_hip": (0, 150), "head_top": (0, -25),
        "left_big_toe": (22, 325), "left_small_toe": (28, 322), "left_heel": (16, 315),
        "right_big_toe": (-22, 325), "right_small_toe": (-28, 322), "right_heel": (-16, 315),
    }
    return {k: np.array([shift[0] + scale * x + 300, shift[1] + scale * y + 100, 0.9]) for k, (x, y) in p.items()}


def _as_layout(person: dict, layout: str) -> np.ndarray:
    return np.stack([person[n] for n in NAMES[layout]])


@pytest.mark.parametrize("layout", ["COCO17", "COCO18", "BODY_25", "BODY_25B"])
def test_round_trip_and_mapping_per_layout(tmp_path, layout):
    people = [_person(), _person(shift=(200, 30), scale=0.6)]
    raw = [_as_layout(p, layout) for p in people]
    assert raw[0].shape == (LAYOUT_SIZE[layout], 3)
    path = write_openpose_json(tmp_path / f"{layout}_000004_keypoints.json", raw)
    doc = json.loads(path.read_text())
    assert doc["version"] == 1.3 and doc["people"][0]["person_id"] == [-1]
    np.testing.assert_allclose(read_openpose_raw(path), np.stack(raw))
    expected = np.stack([np.stack([p[n] for n in COCO17_NAMES]) for p in people])
    for given in (layout, None):  # explicit, then detected from the anatomy
        np.testing.assert_allclose(read_openpose_json(path, given), expected)
    assert detect_layout([np.stack(raw)]) == layout


def test_index_tables_agree_with_names():
    for layout, idx in COCO17_FROM.items():
        assert [NAMES[layout][i] for i in idx] == list(COCO17_NAMES)


def test_folder_naming_missing_frames_and_pick(tmp_path):
    big, small = _person(), _person(shift=(250, 0), scale=0.5)
    write_openpose_json(tmp_path / "000000_keypoints.json", [_as_layout(small, "BODY_25"), _as_layout(big, "BODY_25")])
    write_openpose_json(tmp_path / "clip_000001_keypoints.json", [_as_layout(big, "BODY_25")])
    write_openpose_json(tmp_path / "cam02.0003.json", [])  # nobody detected
    (tmp_path / "notes.txt").write_text("ignored")
    kp, missing = read_keypoint_folder(tmp_path, [0, 1, 2, 3])
    assert missing == [2, 3]
    np.testing.assert_array_equal(kp.frame_ids, [0, 1, 2, 3])
    want = np.stack([big[n] for n in COCO17_NAMES])
    np.testing.assert_allclose(kp.data[0], want)  # the largest person was picked
    np.testing.assert_allclose(kp.data[1], want)
    assert np.all(kp.data[2:] == 0)
    first, _ = read_keypoint_folder(tmp_path, [0], pick="first")
    np.testing.assert_allclose(first.data[0], np.stack([small[n] for n in COCO17_NAMES]))
    # Two files naming one frame is an error.
    write_openpose_json(tmp_path / "x_000001_keypoints.json", [])
    with pytest.raises(InputError, match="frame 1"):
        read_keypoint_folder(tmp_path, [0, 1])


def test_bad_files(tmp_path):
    (tmp_path / "a.json").write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        read_openpose_json(tmp_path / "a.json")
    (tmp_path / "b.json").write_text(json.dumps({"people": [{"pose_keypoints_2d": [1, 2]}]}))
    with pytest.raises(InputError, match="triples"):
        read_openpose_json(tmp_path / "b.json")
    write_openpose_json(tmp_path / "c.json", [np.zeros((19, 3))])
    with pytest.raises(InputError, match="19 keypoints"):
        read_openpose_json(tmp_path / "c.json")
    write_openpose_json(tmp_path / "d.json", [_as_layout(_person(), "COCO18")])
    with pytest.raises(InputError, match="layout BODY_25"):
        read_openpose_json(tmp_path / "d.json", layout="BODY_25")
    with pytest.raises(InputError, match="not found"):
        read_keypoint_folder(tmp_path / "nope", [0])


def test_coco_keypoint_files(tmp_path):
    kp = np.stack([_person()[n] for n in COCO17_NAMES])
    ann = {"images": [{"id": 1}, {"id": 2}], "annotations": [
        {"image_id": 1, "category_id": 1, "keypoints": np.c_[kp[:, :2], np.r_[[2] * 16, [0]]].ravel().tolist()}]}
    (tmp_path / "ann.json").write_text(json.dumps(ann))
    got = read_coco_keypoints(tmp_path / "ann.json")
    assert got[1].shape == (1, 17, 3) and got[2].shape == (0, 17, 3)
    np.testing.assert_allclose(got[1][0, :, :2], kp[:, :2])
    np.testing.assert_array_equal(got[1][0, :, 2], [1] * 16 + [0])
    res = [{"image_id": "f7", "category_id": 1, "keypoints": kp.ravel().tolist(), "score": 0.8}] * 2
    (tmp_path / "res.json").write_text(json.dumps(res))
    got = read_coco_keypoints(tmp_path / "res.json")
    assert got["f7"].shape == (2, 17, 3)
    np.testing.assert_allclose(got["f7"][1], kp)
    (tmp_path / "bad.json").write_text(json.dumps([{"image_id": 1, "keypoints": [0] * 50}]))
    with pytest.raises(InputError, match="51"):
        read_coco_keypoints(tmp_path / "bad.json")


# ---------------------------------------------------------------- real detector output


def _anatomy(kp: np.ndarray) -> dict[str, float]:
    """Fractions of confident frames where the standing subject's anatomy holds."""
    c = kp[..., 2] > 0.3
    y, x = kp[..., 1], kp[..., 0]
    idx = {n: i for i, n in enumerate(COCO17_NAMES)}

    def frac(cond, *names):
        ok = np.all(c[:, [idx[n] for n in names]], axis=1)
        return float(cond[ok].mean()) if ok.any() else np.nan

    mid = lambda a, b: 0.5 * (y[:, idx[a]] + y[:, idx[b]])  # noqa: E731
    # (the subject balances and leans forward, so the nose is only required above the hips)
    order = ((y[:, idx["nose"]] < mid("left_hip", "right_hip"))
             & (mid("left_shoulder", "right_shoulder") < mid("left_hip", "right_hip"))
             & (mid("left_hip", "right_hip") < mid("left_knee", "right_knee"))
             & (mid("left_knee", "right_knee") < mid("left_ankle", "right_ankle")))
    # Torso points only: the balancing subject crosses their legs at times.
    side = np.sign(x[:, [idx["left_shoulder"], idx["left_hip"]]] - x[:, [idx["right_shoulder"], idx["right_hip"]]])
    height = np.abs(mid("left_ankle", "right_ankle") - y[:, idx["nose"]])
    eye = np.linalg.norm(kp[:, [idx["left_eye"], idx["right_eye"]], :2] - kp[:, [idx["nose"]], :2], axis=-1).max(1)
    return {
        "order": frac(order, "nose", "left_shoulder", "right_shoulder", "left_hip", "right_hip",
                      "left_knee", "right_knee", "left_ankle", "right_ankle"),
        # The left side is on the same image side for shoulders and hips ...
        "sides_agree": frac(np.all(side == side[:, :1], axis=1), "left_shoulder", "right_shoulder",
                            "left_hip", "right_hip"),
        # ... and on the same image side in (nearly) every frame (the subject does not turn round).
        "side_sign": float(np.mean(side[:, 0] == np.sign(np.median(side[:, 0])))),
        "eyes_near_nose": frac(eye < 0.1 * height, "nose", "left_eye", "right_eye", "left_ankle", "right_ankle"),
    }


@pytest.mark.skipif(not REAL.is_dir(), reason="real Pose2Sim demo data not available")
def test_real_body25b_detections():
    from embodmocap.io.openpose import keypoint_files

    raws = [read_openpose_raw(p) for p in keypoint_files(REAL).values()]
    assert detect_layout(raws, REAL) == "BODY_25B"
    kp, missing = read_keypoint_folder(REAL, np.arange(105))
    assert missing == [100, 101, 102, 103, 104]  # the demo has frames 0..99
    a = _anatomy(kp.data[:100])
    assert a["order"] > 0.95, a
    assert a["sides_agree"] > 0.95, a
    assert a["side_sign"] > 0.9, a
    assert a["eyes_near_nose"] > 0.9, a
    # The same files read with the wrong 25-point layout break the anatomy (the check can fail).
    wrong, _ = read_keypoint_folder(REAL, np.arange(100), layout="BODY_25")
    b = _anatomy(wrong.data)
    assert b["order"] < 0.5 or b["eyes_near_nose"] < 0.5, b


@pytest.mark.parametrize("cam", ["cam03", "cam04"])
def test_profile_cameras_detect_body25b_without_a_hint(cam):
    # These real cameras see the subject in profile: one eye is never confident, so the layout
    # must be told from the neck/hip midpoints.
    from embodmocap.io.openpose import detect_layout, keypoint_files, read_openpose_raw

    files = keypoint_files(f"/work/shared/data/pose2sim_demo/pose/{cam}_json")
    people = [read_openpose_raw(p) for p in list(files.values())[::5]]
    assert detect_layout(people) == "BODY_25B"
