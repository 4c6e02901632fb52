"""Stage II end to end on a small synthetic session: ground truth, overrides, resume, bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.manifest import load_manifest, write_manifest
from embodmocap.sequence import stage
from embodmocap.sequence.config import SequenceConfig
from embodmocap.synth.config import SynthConfig
from embodmocap.synth.studio import synthesize

SYNTH = SynthConfig(seed=11, seconds=2.5, scene_seconds=1.0, width=320, height=240, depth_width=128, depth_height=96)
CFG = SequenceConfig()


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("seq") / "s"
    synthesize(SYNTH, out)
    return out


@pytest.fixture(scope="module")
def done(session) -> stage.SequenceOutputs:
    return stage.run(CFG, session)


def _copy(session: Path, tmp_path: Path) -> Path:
    work = tmp_path / "s"
    shutil.copytree(session, work, ignore=shutil.ignore_patterns("sequences"))
    return work


def test_sync_and_slices_match_ground_truth(session, done):
    gt = np.load(SessionLayout(session).ground_truth.sequence("seq0"))
    T = done.figures["frames"]
    assert T > 30
    for v in VIEWS:
        assert done.figures[f"{v}_sync_frame"] == int(gt[f"{v}_sync_frame"])
        vl = done.layout.view(v)
        fm = json.loads(vl.frame_map.read_text())
        raw = np.asarray(fm["raw_frames"])
        assert raw[0] == int(gt[f"{v}_sync_frame"]) and len(raw) == T
        # Both views show the same motion frame at every sequence frame (they are synchronised).
        motion = raw + int(gt[f"{v}_motion_start"])
        if v == "v1":
            motion_v1 = motion
        else:
            np.testing.assert_array_equal(motion, motion_v1)
        cams = np.load(vl.cameras)
        np.testing.assert_allclose(cams["T_world_cam"], gt[f"{v}_T_vio_cam"][raw], atol=1e-4)
        assert cams["K"].shape == (3, 3) and int(cams["width"]) == SYNTH.width
        kp = np.load(vl.keypoints)
        assert kp["keypoints"].shape == (T, 17, 3) and kp["boxes"].shape == (T, 4)
        good = kp["keypoints"][..., 2] > 0.5
        err = np.linalg.norm(kp["keypoints"][..., :2] - gt[f"{v}_keypoints2d_gt"][raw], axis=-1)[good]
        assert np.median(err) < 4.0
        from embodmocap.io.frame_stack import depth_mm, read_depth_m, read_mask
        from embodmocap.types import PngMasks

        # Masks equal the precomputed PNGs of the same raw frames; depth equals the capture's
        # LiDAR depth where its confidence passes the filter.
        src = PngMasks(tuple(SessionLayout(session).perception("seq0", v).mask_png(int(r)) for r in raw))
        from embodmocap.io.captures import open_capture

        cap = open_capture(SessionLayout(session).view_capture("seq0", v))
        for t in (0, T // 2, T - 1):
            np.testing.assert_array_equal(read_mask(vl.masks, t, SYNTH.width), src.mask(t))
            d = cap.frames.depth_m(int(raw[t]))
            keep = cap.frames.confidence(int(raw[t])) >= CFG.min_depth_confidence
            np.testing.assert_allclose(read_depth_m(vl.depth, t), np.where(keep, d, 0), atol=5e-4)
            # To the millimetre what the metres filtered and rounded give (the integer path's promise).
            np.testing.assert_array_equal(np.load(vl.depth, mmap_mode="r")[t], depth_mm(np.where(keep, d, 0.0)))
        assert np.load(vl.masks).shape == (T, SYNTH.height, SYNTH.width // 8)
        assert np.load(vl.depth).shape == (T, SYNTH.depth_height, SYNTH.depth_width)
        from embodmocap.io.body_prior import read_body_prior

        assert len(read_body_prior(vl.body_prior).frame_ids) == T
    assert (done.layout.root / "sync_v1.png").is_file() and (done.layout.root / "sync_v2.png").is_file()


def test_second_run_skips_every_step(session, done):
    again = stage.run(CFG, session)
    assert "sync" in again.skipped and "keypoints" in again.skipped and "depth_v2" in again.skipped
    assert len(again.skipped) == 9


def test_manifest_sync_frames_override_detection(session, tmp_path):
    work = _copy(session, tmp_path)
    gt = json.loads(SessionLayout(work).ground_truth.info.read_text())["sync_frames"]
    m = load_manifest(work)
    from dataclasses import replace

    seq = m.sequences["seq0"]
    views = {v: replace(seq.views[v], sync_frame=gt[v] + 2) for v in VIEWS}
    m = replace(m, sequences={"seq0": replace(seq, views=views)})
    write_manifest(m, work / "session.toml")
    out = stage.run(CFG, work)
    sync = json.loads(out.layout.sync.read_text())
    for v in VIEWS:
        assert out.figures[f"{v}_sync_frame"] == gt[v] + 2
    assert "manual" in json.dumps(sync)


def test_missing_keypoint_files_are_counted(session, tmp_path):
    work = _copy(session, tmp_path)
    gt = json.loads(SessionLayout(work).ground_truth.info.read_text())["sync_frames"]
    folder = SessionLayout(work).perception("seq0", "v1").keypoints_dir
    for i in range(3):
        (folder / f"{gt['v1'] + 5 + i:06d}_keypoints.json").unlink()
    out = stage.run(CFG, work)
    assert out.figures["v1_frames_missing_keypoint_file"] == 3
    assert out.figures["v2_frames_missing_keypoint_file"] == 0


def test_view_without_the_performer_is_an_error(session, tmp_path):
    work = _copy(session, tmp_path)
    folder = SessionLayout(work).perception("seq0", "v2").keypoints_dir
    for f in folder.glob("*.json"):
        f.write_text(json.dumps({"version": 1.3, "people": []}))
    with pytest.raises(InputError) as err:
        stage.run(CFG, work)
    assert "v2" in str(err.value) and "performer" in str(err.value)


def test_views_that_do_not_overlap_after_sync(session, tmp_path):
    work = _copy(session, tmp_path)
    m = load_manifest(work)
    from dataclasses import replace

    from embodmocap.io.captures import open_capture

    seq = m.sequences["seq0"]
    n = open_capture(seq.views["v1"].capture).num_frames
    views = {"v1": replace(seq.views["v1"], sync_frame=n - 5), "v2": replace(seq.views["v2"], sync_frame=1)}
    write_manifest(replace(m, sequences={"seq0": replace(seq, views=views)}), work / "session.toml")
    with pytest.raises(InputError, match="overlap"):
        stage.run(CFG, work)


def test_sync_record_lists_laser_per_view_and_the_slicing(session, done):
    rec = json.loads(done.layout.sync.read_text())
    gt = json.loads(SessionLayout(session).ground_truth.info.read_text())["sync_frames"]
    assert rec["version"] == 2 and rec["slicing"]["source"] == "laser" and not rec["chosen"]["final"]
    for v in VIEWS:
        lz = rec["sources"]["laser"]["views"][v]
        assert lz["found"] and lz["frame"] == gt[v] and lz["contact_sheet"] == f"sync_{v}.png"
    # Same timestamps clock per capture: the laser offset is the event frames' time difference.
    cams = {v: np.load(done.layout.view(v).cameras) for v in VIEWS}
    assert np.allclose(cams["v1"]["frame_times_s"], cams["v1"]["timestamps_s"], atol=1e-5)
    assert rec["sources"]["laser"]["offset_s"] == pytest.approx(rec["views"]["v2"]["time_s"] - rec["views"]["v1"]["time_s"])


def test_without_a_laser_event_the_views_are_sliced_from_their_start(session, tmp_path):
    from dataclasses import replace

    from embodmocap.errors import InputError
    from embodmocap.sequence.sync import SyncConfig

    work = _copy(session, tmp_path)
    blind = replace(CFG, sync=SyncConfig(min_confidence=1.01))  # no event can pass: "no laser"
    out = stage.run(blind, work)
    rec = json.loads(out.layout.sync.read_text())
    assert rec["slicing"]["source"] == "start" and all(rec["views"][v]["frame"] == 0 for v in VIEWS)
    assert not any(rec["sources"]["laser"]["views"][v]["found"] for v in VIEWS)
    assert rec["sources"]["laser"]["offset_s"] is None and "geometrically" in rec["chosen"]["reason"]
    with pytest.raises(InputError, match="no laser-dot sync event"):
        stage.run(replace(blind, sync_without_laser="error"), _copy(session, tmp_path / "b"))


def test_manual_frame_outside_the_view_names_the_view_the_frame_and_the_laser_estimate(session, tmp_path):
    work = _copy(session, tmp_path)
    gt = json.loads(SessionLayout(work).ground_truth.info.read_text())["sync_frames"]
    m = load_manifest(work)
    from dataclasses import replace

    seq = m.sequences["seq0"]
    views = {"v1": replace(seq.views["v1"], sync_frame=gt["v1"]), "v2": replace(seq.views["v2"], sync_frame=100000)}
    write_manifest(replace(m, sequences={"seq0": replace(seq, views=views)}), work / "session.toml")
    with pytest.raises(InputError) as err:
        stage.run(CFG, work)
    msg = str(err.value)
    assert "sync_frame = 100000 of view v2 is outside" in msg and f"goes out at frame {gt['v2']}" in msg
    assert "[sequences.seq0.views.v2]" in msg and not SessionLayout(work).sequence("seq0").sync.exists()
