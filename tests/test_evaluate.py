"""`embodmocap evaluate` and `report` on a session whose outputs are its own ground truth.

With the true body, cameras, offsets and sync frames fed back as the prediction, every error
against ground truth is zero and the quality metrics are perfect (up to the renderer's pixel edge).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from embodmocap.evaluate.session import EvaluateConfig, evaluate_session, sequence_truth
from embodmocap.io.layout import VIEWS, SessionLayout
from stage4_session import SYNTH, make_stage4_session


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("evaluate") / "session"
    facts = make_stage4_session(root, stage1_world=True)
    return root, facts


def test_truth_fed_back_gives_zero_errors(session):
    root, facts = session
    result = evaluate_session(root, EvaluateConfig(frames_per_view=5))
    assert json.loads(SessionLayout(root).evaluation.read_text()) == result
    assert set(result) >= {"scene", "sequences"} and result["ground_truth"] is True
    m = result["sequences"][SYNTH.sequence_name]
    for key in ("w_mpjpe_mm", "wa_mpjpe_mm", "w_mpjpe_mm_c500", "wa_mpjpe_mm_c1000", "pa_mpjpe_mm"):
        assert m[key] == pytest.approx(0.0, abs=1e-3), key
    assert m["rte_pct"] == pytest.approx(0.0, abs=1e-3)
    for v in VIEWS:
        assert m[f"{v}_view_translation_err_cm"] == pytest.approx(0.0, abs=1e-6)
        assert m[f"{v}_view_yaw_err_deg"] == pytest.approx(0.0, abs=1e-4)
        assert m[f"{v}_sync_err_frames"] == 0
    # Quality metrics: the true joints project onto the true 2D keypoints.
    assert m["reproj_err_px"] < 1e-6
    assert m["frames"] == facts["T"] and m["jitter"] > 0


def test_truth_is_in_stage1_world(session):
    root, facts = session
    truth = sequence_truth(SessionLayout(root), SYNTH.scene_name, SYNTH.sequence_name)
    joints = np.load(SessionLayout(root).sequence(SYNTH.sequence_name).joints_world)["joints"]
    assert truth.valid.all()
    np.testing.assert_allclose(truth.joints, joints, atol=1e-9)


def test_errors_grow_with_a_known_offset(session, tmp_path):
    """The whole motion shifted by 10 cm: the chunk-aligned metrics undo it, the reprojection does not."""
    import shutil

    from embodmocap.body.model import load_body_model
    from embodmocap.io.smpl_file import read_smpl_npz, write_smpl_npz

    root, _ = session
    copy = tmp_path / "s"
    shutil.copytree(root, copy)
    path = SessionLayout(copy).sequence(SYNTH.sequence_name).smpl_world
    params, frames = read_smpl_npz(path)
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.0, 0.0]
    write_smpl_npz(path, load_body_model(None).params_for_world_frame(params, T), frames)
    m = evaluate_session(copy, EvaluateConfig(frames_per_view=3))["sequences"][SYNTH.sequence_name]
    # W-MPJPE aligns each chunk on its first frames and WA-MPJPE the whole chunk: both undo a
    # constant shift; PA-MPJPE too. The reprojection error sees it.
    assert m["w_mpjpe_mm"] == pytest.approx(0.0, abs=1e-3)
    assert m["wa_mpjpe_mm"] == pytest.approx(0.0, abs=1e-3)
    assert m["reproj_err_px"] > 5.0


def test_missing_motion_is_reported(tmp_path):
    from embodmocap.synth.studio import synthesize

    synthesize(SYNTH, tmp_path / "s")
    result = evaluate_session(tmp_path / "s")
    assert "embodmocap run" in result["sequences"][SYNTH.sequence_name]["missing"]


def test_a_failed_stage_is_not_evaluated(session, tmp_path):
    """Outputs left behind by a Stage IV run that failed are reported, never evaluated."""
    import shutil

    from embodmocap.io.stage_manifest import StageManifest

    root, _ = session
    copy = tmp_path / "s"
    shutil.copytree(root, copy)
    sl = SessionLayout(copy).sequence(SYNTH.sequence_name)
    sm = StageManifest(sl.motion_manifest, "motion", {}, root=copy)
    sm.finish("failed", RuntimeError("fit diverged"))
    m = evaluate_session(copy, EvaluateConfig(frames_per_view=3))["sequences"][SYNTH.sequence_name]
    assert set(m) == {"missing"} and "motion stage failed" in m["missing"] and "embodmocap motion" in m["missing"]


def test_subframe_sync_error_against_the_phones_true_phase(session, tmp_path):
    """The truth-fed session is sliced at the true sync frames of frame-aligned phones: a final
    sync.json applying no residual has no error; one applying a quarter frame is a quarter off."""
    import shutil

    from embodmocap.evaluate.session import subframe_sync_err_frames
    from embodmocap.io.atomic import write_json

    root, _ = session
    copy = tmp_path / "s"
    shutil.copytree(root, copy)
    lay = SessionLayout(copy)
    sl = lay.sequence(SYNTH.sequence_name)
    assert subframe_sync_err_frames(lay, SYNTH.sequence_name) is None  # version 1: no sub-frame offset
    rec = json.loads(sl.sync.read_text())
    for frames in (0.0, 0.25, -0.4):
        rec.update(version=2, chosen={"final": True, "residual_s": frames / SYNTH.fps})
        write_json(sl.final_sync, rec)  # Stage III's final record
        assert subframe_sync_err_frames(lay, SYNTH.sequence_name) == pytest.approx(frames, abs=1e-4)


def test_report_is_self_contained(session):
    import re

    from embodmocap.evaluate.report import write_report

    root, _ = session
    html_path, md_path = write_report(root)
    html = html_path.read_text()
    # Every picture is embedded; nothing is fetched from elsewhere.
    assert not re.search(r"""src=["'](?!data:)""", html)
    assert html.count("data:image/png;base64,") >= 4  # floor plan, errors, two overlay strips
    for text in ("w_mpjpe_mm", "Top-down view", "fitted body over the RGB frames"):
        assert text in html
    md = md_path.read_text()
    for name in re.findall(r"\]\(([^)]+\.png)\)", md):
        assert (md_path.parent / name).is_file()
