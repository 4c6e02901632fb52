"""A sequence's view captures in every app layout a scene capture may have: Stage II gives the
same sync, slices, cameras, keypoints, masks and depth as from the studio's Stray Scanner views.

The studio writes its views as Stray Scanner exports; each test rewrites them with the project's
writers in another app's layout (Record3D ``.r3d`` zip and its unzipped folder, Record3D's
"EXR + JPG" export, Spectacular AI app and SDK recordings, the oldest header-less Stray Scanner
export), two phones with different apps per session, points ``session.toml`` at them and runs
Stage II. What may differ is what the format's compression changes: JPEG or H.264 colour (the
laser event must still land on the same frame), depth quantised to millimetres, and depth kept
where the format has no confidence map to filter it by.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from embodmocap.errors import EmbodMocapError
from embodmocap.io.captures import SpectacularWriter, StrayScannerWriter, open_capture, scan_capture, write_record3d
from embodmocap.io.frame_stack import read_depth_m, read_mask
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.manifest import load_manifest, write_manifest
from embodmocap.sequence import stage
from embodmocap.sequence.config import SequenceConfig
from embodmocap.synth.config import SynthConfig
from embodmocap.synth.studio import synthesize
from embodmocap.types import Capture

SYNTH = SynthConfig(seed=11, seconds=2.5, scene_seconds=1.0, width=320, height=240, depth_width=128, depth_height=96)
CFG = SequenceConfig()


# ------------------------------------------------------------------------------------------------
# writing a capture in another app's layout


def _frames(cap: Capture):
    n = cap.num_frames
    return ((cap.frames.rgb(i), cap.frames.depth_m(i), cap.frames.confidence(i)) for i in range(n))


def _stream(cap: Capture, writer) -> None:
    """Every frame of ``cap`` into a frame-by-frame writer (depth as the apps' uint16 millimetres)."""
    for i, (rgb, d, c) in enumerate(_frames(cap)):
        writer.add_frame(rgb, np.round(d * 1000).astype(np.uint16), c, cap.frame(i).T_world_cam, cap.timestamps_s[i])


def _record3d(cap: Capture, out: Path) -> Path:
    rgb, depth, conf = zip(*_frames(cap))
    return write_record3d(out, rgb, depth, cap.trajectory.T_world_cam, cap.rgb_intrinsics, cap.fps,
                          confidence=conf, timestamps_s=cap.timestamps_s)


def _record3d_exr(cap: Capture, out: Path) -> Path:
    """Record3D's "EXR + JPG" export: the unzipped export's metadata and JPEGs, depth as EXR metres."""
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    import cv2

    tmp = _record3d(cap, out.with_name(out.name + "_r3d"))
    (out / "rgb").mkdir(parents=True)
    (out / "depth").mkdir()
    shutil.move(tmp / "metadata", out / "metadata.json")
    for i in range(cap.num_frames):
        shutil.move(tmp / "rgbd" / f"{i}.jpg", out / "rgb" / f"{i}.jpg")
        assert cv2.imwrite(str(out / "depth" / f"{i}.exr"), cap.frames.depth_m(i).astype(np.float32))
    shutil.rmtree(tmp)
    return out


def _spectacular(cap: Capture, out: Path, sdk: bool = False) -> Path:
    """A Spectacular Rec app recording, or (``sdk``) the SDK recorder's: data.mp4 + vio_config.yaml."""
    with SpectacularWriter(out, cap.rgb_intrinsics, cap.fps) as w:
        _stream(cap, w)
    if sdk:
        (out / "data.mov").rename(out / "data.mp4")
        (out / "metadata.json").unlink()
        (out / "vio_config.yaml").write_text("useSlam: true\n")
    return out


def _stray_oldest(cap: Capture, out: Path) -> Path:
    """The oldest Stray Scanner export: header-less 7-column odometry.csv (no times)."""
    with StrayScannerWriter(out, cap.rgb_intrinsics, cap.fps, header=False) as w:
        _stream(cap, w)
    return out


#: layout name -> (writer, file name of the capture, keeps LiDAR confidence, depth quantum in
#: metres, words of the app version the reader must recognise)
LAYOUTS = {
    "r3d_zip": (_record3d, "{v}.r3d", True, 1e-6, "Record3D .r3d file"),
    "r3d_folder": (_record3d, "{v}_r3d", True, 1e-6, "unzipped"),
    "r3d_exr": (_record3d_exr, "{v}_exr", False, 1e-6, "EXR + JPG"),
    "spectacular": (_spectacular, "{v}_sai", False, 5e-4, "Spectacular Rec app"),
    "spectacular_sdk": (lambda c, o: _spectacular(c, o, sdk=True), "{v}_sai_sdk", False, 5e-4, "SDK recorder"),
    "stray_oldest": (_stray_oldest, "{v}_stray7", True, 5e-4, "header-less"),
}


# ------------------------------------------------------------------------------------------------
# fixtures


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("views") / "s"
    synthesize(SYNTH, out)
    return out


@pytest.fixture(scope="module")
def stray(session) -> stage.SequenceOutputs:
    """Stage II on the studio's own (Stray Scanner) views: what every other layout must give."""
    return stage.run(CFG, session)


def _session_with(session: Path, tmp_path: Path, layouts: dict[str, str]) -> Path:
    """A copy of the studio session whose views are rewritten in ``layouts`` (view -> layout)."""
    work = tmp_path / "s"
    shutil.copytree(session, work, ignore=shutil.ignore_patterns("sequences"))
    lay = SessionLayout(work)
    m = load_manifest(lay.manifest)
    seq = m.sequences["seq0"]
    views = {}
    for v, e in seq.views.items():
        write, name, *_, version = LAYOUTS[layouts[v]]
        path = write(open_capture(e.capture), work / "captures" / "apps" / name.format(v=v))
        assert version in scan_capture(path).variant  # the layout meant, not another
        shutil.rmtree(e.capture)  # nothing falls back on the Stray export
        views[v] = replace(e, capture=path)
    write_manifest(replace(m, sequences={**m.sequences, "seq0": replace(seq, views=views)}), lay.manifest)
    return work


def _assert_same_outputs(stray: stage.SequenceOutputs, got: stage.SequenceOutputs, layouts: dict[str, str]) -> None:
    f0, f1 = stray.figures, got.figures
    assert f1["frames"] == f0["frames"] and f1["sync_slicing"] == f0["sync_slicing"] == "laser"
    T = f0["frames"]
    for v in VIEWS:
        _, _, has_conf, quantum, _ = LAYOUTS[layouts[v]]
        assert f1[f"{v}_sync_frame"] == f0[f"{v}_sync_frame"], layouts[v]
        a, b = stray.layout.view(v), got.layout.view(v)
        assert json.loads(b.frame_map.read_text())["raw_frames"] == json.loads(a.frame_map.read_text())["raw_frames"]
        ca, cb = np.load(a.cameras), np.load(b.cameras)
        np.testing.assert_allclose(cb["T_world_cam"], ca["T_world_cam"], atol=1e-5)
        np.testing.assert_allclose(cb["K"], ca["K"], atol=1e-6)
        np.testing.assert_allclose(cb["K_depth"], ca["K_depth"], atol=1e-6)
        np.testing.assert_allclose(cb["timestamps_s"], ca["timestamps_s"], atol=1e-6)
        np.testing.assert_allclose(cb["frame_times_s"], ca["frame_times_s"], atol=1e-4)
        # Keypoints and masks come from the session's precomputed files of the same raw frames.
        np.testing.assert_array_equal(np.load(b.keypoints)["keypoints"], np.load(a.keypoints)["keypoints"])
        width = int(ca["width"])
        for t in range(0, T, 7):
            np.testing.assert_array_equal(read_mask(b.masks, t, width), read_mask(a.masks, t, width))
            da, db = read_depth_m(a.depth, t), read_depth_m(b.depth, t)
            both = (da > 0) & (db > 0)
            np.testing.assert_allclose(db[both], da[both], atol=quantum + 1e-6)
            if has_conf:  # the same LiDAR confidence filter: the same pixels kept
                np.testing.assert_array_equal(db > 0, da > 0)
            else:  # no confidence map in the format: depth edges dropped in its place (geometry.depth_edges)
                assert ((db > 0) == (da > 0)).mean() >= 0.85  # mostly the pixels the confidence keeps (beyond 3.5-4.5 m it is range, not edges)


# ------------------------------------------------------------------------------------------------
# tests


@pytest.mark.parametrize("layouts", [
    {"v1": "r3d_zip", "v2": "spectacular"},
    pytest.param({"v1": "r3d_folder", "v2": "r3d_exr"}, marks=pytest.mark.slow),
    pytest.param({"v1": "spectacular_sdk", "v2": "stray_oldest"}, marks=pytest.mark.slow),
], ids=lambda d: "+".join(d.values()))
def test_views_in_any_app_layout_give_the_stray_outputs(session, stray, tmp_path, layouts):
    work = _session_with(session, tmp_path, layouts)
    got = stage.run(CFG, work)
    _assert_same_outputs(stray, got, layouts)
    again = stage.run(CFG, work)  # a rerun resumes: the fingerprints of a .r3d file hold
    assert "sync" in again.skipped and "keypoints" in again.skipped


def test_a_view_capture_that_is_a_video_file_says_what_a_capture_is(session, tmp_path):
    work = tmp_path / "s"
    shutil.copytree(session, work, ignore=shutil.ignore_patterns("sequences"))
    lay = SessionLayout(work)
    m = load_manifest(lay.manifest)
    seq = m.sequences["seq0"]
    video = seq.views["v2"].capture / "rgb.mp4"
    write_manifest(replace(m, sequences={"seq0": replace(seq, views={**seq.views, "v2": replace(
        seq.views["v2"], capture=video)})}), lay.manifest)
    with pytest.raises(EmbodMocapError) as err:
        stage.run(CFG, work)
    msg = str(err.value)
    assert "sequences.seq0.views.v2.capture" in msg and "rgb.mp4 is a file, not a capture" in msg
    assert ".r3d" in msg and "folder the phone app exported" in msg


@pytest.mark.parametrize("layout, folder, fix", [
    ("stray_oldest", "depth", "depth/ included"),
    ("spectacular", "frames2", "frames2"),
    ("r3d_exr", "depth", "export"),
])
def test_a_view_capture_without_depth_is_one_clear_error(session, tmp_path, layout, folder, fix):
    """An export copied without its depth cannot serve as a view (Stage II needs the performer's
    depth): one error naming the depth files, the problem and what to do, before anything is written."""
    work = _session_with(session, tmp_path, {"v1": layout, "v2": "r3d_zip"})
    capture = load_manifest(SessionLayout(work).manifest).sequences["seq0"].views["v1"].capture
    shutil.rmtree(capture / folder)
    with pytest.raises(EmbodMocapError) as err:
        stage.run(CFG, work)
    msg = str(err.value)
    assert str(capture / folder) in msg and "missing" in msg and fix in msg, msg
    assert not (SessionLayout(work).root / "sequences" / "seq0" / "sync.json").exists()
