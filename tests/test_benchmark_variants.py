"""`embodmocap benchmark`'s variant rows re-fit Stage IV through its solve functions: with every
term on, the benchmark's dual fit must be Stage IV's own, sub-frame sync included (found 2026-12-02,
session 6: the variants fitted view 2's keypoints at its own instants while Stage IV resamples them
at view 1's, so on a session with a 0.2-frame residual the "all terms" row and the "prior = none"
row were not the pipeline with one thing changed)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from embodmocap.io.atomic import write_json, write_npz
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.smpl_file import read_smpl_npz, read_smpl_suspect, read_smpl_valid
from embodmocap.motion import stage as stage4
from stage4_session import SYNTH, make_stage4_session

SEQ = SYNTH.sequence_name


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench_variants") / "s"
    make_stage4_session(root, stage1_world=True)
    sl = SessionLayout(root).sequence(SEQ)
    rng = np.random.default_rng(0)
    for v in VIEWS:  # detector-like keypoints, as tests/test_motion_stage.py makes them
        kp = dict(np.load(sl.view(v).keypoints))
        kp["keypoints"] = kp["keypoints"].copy()
        kp["keypoints"][..., :2] += rng.normal(0, 2.0, kp["keypoints"][..., :2].shape)
        kp["keypoints"][..., 2] = 0.5 + 0.5 * kp["keypoints"][..., 2]
        write_npz(sl.view(v).keypoints, **kp)
    return root


@pytest.mark.slow
def test_benchmark_dual_fit_is_stage_iv_s_fit(session, tmp_path, residual_frames=0.3):
    from embodmocap.body.model import load_body_model
    from embodmocap.evaluate.benchmark import _Context
    from embodmocap.io.manifest import load_manifest

    work = tmp_path / "s"
    shutil.copytree(session, work)
    lay = SessionLayout(work)
    sl = lay.sequence(SEQ)
    rec = json.loads(sl.sync.read_text())
    rec.update(version=2, chosen={"final": True, "residual_s": residual_frames / SYNTH.fps})
    write_json(sl.final_sync, rec)  # as Stage III writes it
    stage4.run(stage4.MotionConfig(), work, force=True)
    want, _ = read_smpl_npz(sl.smpl_fit)
    manifest = load_manifest(lay.manifest)
    ctx = _Context(lay, SEQ, manifest.sequences[SEQ].scene, load_body_model(manifest.body_model))
    got, valid, suspect = ctx.fit(cameras={v: ctx.cameras(v) for v in VIEWS}, flagged=True)
    for k in ("betas", "global_orient", "body_pose", "transl"):
        np.testing.assert_allclose(np.asarray(getattr(got, k)), np.asarray(getattr(want, k)), atol=1e-9, err_msg=k)
    np.testing.assert_array_equal(valid, read_smpl_valid(sl.smpl_fit))
    np.testing.assert_array_equal(suspect, read_smpl_suspect(sl.smpl_fit))
