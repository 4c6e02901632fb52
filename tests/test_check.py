"""`embodmocap check` on small synthetic sessions, normal and "built to fail"."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from embodmocap.check.config import CheckConfig
from embodmocap.check.core import check_session, exit_status
from embodmocap.cli import main
from embodmocap.synth.config import SynthConfig
from embodmocap.synth.studio import synthesize

SMALL = dict(seconds=3.0, scene_seconds=0.5, width=320, height=240, depth_width=64, depth_height=48)


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("check")
    out = {}
    for name, kw in {"normal": {}, "away": {"view2_away_fraction": 0.6}}.items():
        out[name] = root / name
        synthesize(SynthConfig(seed=2, **SMALL, **kw), out[name])
    return out


def test_without_the_scene_the_check_says_what_it_could_not_check(sessions, capsys):
    rc = main(["check", str(sessions["normal"]), "--json"])
    rep = json.loads(capsys.readouterr().out)
    seq = rep["sequences"][0]
    assert rc == rep["exit_status"] == seq["exit_status"] == 1
    assert seq["verdict"] == "usable with warnings"
    assert any("not processed" in r for r in seq["reasons"])
    f = seq["figures"]
    assert all(f["sync"]["laser"][v]["found"] for v in ("v1", "v2"))
    assert f["both_seen_fraction"] > 0.6 and f["tracking_jumps"] == {"v1": 0, "v2": 0}


def test_without_keypoints_the_check_names_what_it_skipped_and_how_to_enable_it(sessions, tmp_path, capsys):
    """A session fresh from the phones (no keypoint folders, scene not processed): every check
    left out is listed with its reason and what to add or run; the rest is still checked."""
    from dataclasses import replace

    from embodmocap.io.manifest import load_manifest, write_manifest

    work = tmp_path / "s"
    shutil.copytree(sessions["normal"], work)
    m = load_manifest(work / "session.toml")
    seq = m.sequences["seq0"]
    views = {v: replace(e, keypoints=None) for v, e in seq.views.items()}
    write_manifest(replace(m, sequences={"seq0": replace(seq, views=views)}), work / "session.toml")
    rc = main(["check", str(work), "--json"])
    rep = json.loads(capsys.readouterr().out)["sequences"][0]
    assert rc == 1 and rep["verdict"] == "usable with warnings"
    by_reason = {x["reason"].split(" ")[0]: x for x in rep["skipped"]}
    kp, scene = by_reason["no"], by_reason["scene"]
    assert kp["checks"] == ["performer", "view angle", "geometric sync"]
    assert "v1, v2" in kp["reason"] and "[sequences.seq0.views.v1]" in kp["enable"] and "keypoints =" in kp["enable"]
    assert scene["checks"][0] == "registration" and f"embodmocap scene {work}" in scene["enable"]
    assert "seen_fraction" not in rep["figures"] and rep["figures"]["tracking_jumps"] == {"v1": 0, "v2": 0}
    assert main(["check", str(work)]) == 1
    text = capsys.readouterr().out
    assert "skipped: performer, view angle, geometric sync (no keypoint folder in session.toml for v1, v2); " \
           "to check them: add `keypoints" in text


def test_performer_out_of_one_view_is_a_reshoot(sessions):
    res = check_session(CheckConfig(), sessions["away"])
    assert exit_status(res) == 2 and res[0].verdict == "reshoot"
    assert any("both views only" in r for r in res[0].reasons)
    assert res[0].figures["seen_fraction"]["v2"] < 0.6 < res[0].figures["seen_fraction"]["v1"]


@pytest.mark.slow
def test_verdicts_with_the_scene(tmp_path):
    """Normal: usable; views 20 deg apart, view 2 in another room: reshoot (the scene's Stage I
    outputs are shared: every variant has seed 0's scene capture, byte for byte)."""
    from embodmocap.scene import stage as scene_stage
    from embodmocap.scene.config import SceneConfig
    from embodmocap.scene.sfm import SfmConfig

    base = dict(seed=0, seconds=4.0, scene_seconds=10.0)
    variants = {"normal": {}, "sep20": {"view_separation_deg": 20.0}, "scene": {"view2_other_scene": True}}
    for name, kw in variants.items():
        synthesize(SynthConfig(**base, **kw), tmp_path / name)
    scene_stage.run(SceneConfig(voxel_m_indoor=0.02, sfm=SfmConfig(max_images=60, num_threads=1)), tmp_path / "normal")
    for name in ("sep20", "scene"):
        shutil.copytree(tmp_path / "normal" / "scenes", tmp_path / name / "scenes")
    got = {n: check_session(CheckConfig(), tmp_path / n)[0] for n in variants}
    assert got["normal"].verdict != "reshoot", got["normal"].reasons
    assert got["normal"].figures["sync"]["geometric_confidence"] > 0.3
    assert abs(got["normal"].figures["sync"]["geometric_offset_frames"]) < 1.0
    assert 60 <= got["normal"].figures["angle_deg"]["median"] <= 120
    # Both views' laser sightings land on one place of the scene (the same-dot check passes).
    dot = got["normal"].figures["sync"]["laser_dot_check"]
    assert dot["same_dot"] is not False and dot["gap_m"] < 0.15, dot
    assert got["sep20"].verdict == "reshoot" and got["sep20"].figures["angle_deg"]["median"] < 40
    assert got["scene"].verdict == "reshoot"
    assert any("registers" in r and "v2" in r for r in got["scene"].reasons)
