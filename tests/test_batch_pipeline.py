"""`embodmocap batch` end to end on real synthetic sessions (slow: every stage runs).

A dataset of two sessions made from one synthetic capture: ``good`` (its raw inputs as they are)
and ``broken`` (its scene capture lost its poses file). Two local workers; the worker running
``good``'s Stage III is killed in the middle of it. Checked: the killed task is retried and the
outputs equal those of `embodmocap run` on the same capture alone; ``broken`` fails alone with its
cause in the catalog; a second batch redoes nothing; the catalog's rows match the sessions' files;
SequenceDataset windows match smpl_world.npz, also through DataLoader workers.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from embodmocap.batch.config import BatchConfig
from embodmocap.batch.local_pool import LocalPool
from embodmocap.batch.run import run_batch
from embodmocap.io.layout import SessionLayout
from embodmocap.pipeline import PipelineConfig, run_session
from embodmocap.synth.config import SynthConfig

pytestmark = pytest.mark.slow

SYNTH = SynthConfig(seed=0, seconds=3.0, scene_seconds=10.0)
RAW = ("captures", "perception", "ground_truth", "body_model.npz", "session.toml")


def _raw_copy(src: Path, dst: Path) -> Path:
    dst.mkdir(parents=True)
    for name in RAW:
        (shutil.copytree if (src / name).is_dir() else shutil.copy2)(src / name, dst / name)
    return dst


def _arrays(session: Path) -> dict[str, np.ndarray]:
    from embodmocap.io.mesh_file import read_mesh_ply
    from embodmocap.io.smpl_file import read_smpl_npz
    from embodmocap.io.stage_files import read_cameras, read_world_joints

    lay = SessionLayout(session)
    sl = lay.sequence(SYNTH.sequence_name)
    params, frames = read_smpl_npz(sl.smpl_world)
    out = {"poses": params.poses, "trans": params.transl, "betas": params.betas, "frames": frames,
           "joints": read_world_joints(sl.joints_world).joints,
           "mesh": read_mesh_ply(lay.scene(SYNTH.scene_name).mesh_simplified)[0]}
    for v in ("v1", "v2"):
        out[v] = read_cameras(sl.view(v).cameras_final).T_world_cam
    return out


def _steps(session: Path) -> dict[str, dict]:
    lay = SessionLayout(session)
    sl = lay.sequence(SYNTH.sequence_name)
    return {m.name: json.loads(m.read_text())["steps"] for m in
            (lay.scene(SYNTH.scene_name).manifest, sl.manifest, sl.calibrate_manifest, sl.motion_manifest)}


@pytest.fixture(scope="module")
def processed(tmp_path_factory):
    from embodmocap.synth.studio import synthesize

    root = tmp_path_factory.mktemp("batch")
    ref = root / "ref"
    synthesize(SYNTH, ref)
    assert run_session(PipelineConfig(), ref).ok
    ds = root / "ds"
    _raw_copy(ref, ds / "good")
    _raw_copy(ref, ds / "broken")
    (ds / "broken" / "captures" / SYNTH.scene_name / "odometry.csv").unlink()
    pool = LocalPool(2, PipelineConfig())
    killed: list[str] = []

    def killer():  # kill good's Stage III two seconds into it
        key, deadline, seen = "good/calibrate/seq0", time.time() + 3600, None
        while time.time() < deadline and not killed:
            pid = pool.worker_pids().get(key)
            if pid and seen is None:
                seen = time.time()
            if pid and seen and time.time() - seen > 2.0:
                os.kill(pid, signal.SIGKILL)
                killed.append(key)
            time.sleep(0.05)

    th = threading.Thread(target=killer, daemon=True)
    th.start()
    first = run_batch(ds, BatchConfig(retries=1, evaluate=True), PipelineConfig(), executor=pool, say=lambda m: None)
    killed.append("done")
    th.join()
    return {"ref": ref, "ds": ds, "first": first, "killed": killed}


def test_outputs_equal_run_alone_even_after_a_killed_worker(processed):
    st = processed["first"].states
    assert processed["killed"][0] == "good/calibrate/seq0"
    cal = st["good/calibrate/seq0"]
    assert cal.status == "ok" and cal.attempts == 2 and cal.causes[0].startswith("worker process died (killed by signal 9)")
    assert all(st[f"good/{s}"].status == "ok" for s in ("scene/scene0", "sequence/seq0", "motion/seq0", "evaluate/good"))
    ref, got = _arrays(processed["ref"]), _arrays(processed["ds"] / "good")
    for k in ref:
        np.testing.assert_array_equal(got[k], ref[k], err_msg=k)
    # Same inputs and settings: every step's fingerprint is the one `run` recorded (Stage III's
    # geosync step fingerprints the refined offsets, not calibration.json, whose solver timings
    # differ between any two runs).
    ref_steps, got_steps = _steps(processed["ref"]), _steps(processed["ds"] / "good")
    for m in ref_steps:
        got = {k: s["fingerprint"] for k, s in got_steps[m].items()}
        assert got == {k: s["fingerprint"] for k, s in ref_steps[m].items()}, m


def test_broken_session_fails_alone_and_a_second_batch_redoes_nothing(processed):
    ds = processed["ds"]
    st = processed["first"].states
    assert st["broken/scene/scene0"].status == "failed" and "odometry.csv" in st["broken/scene/scene0"].error
    assert st["broken/motion/seq0"].status == "blocked" and st["broken/evaluate/broken"].status == "blocked"
    before = _steps(ds / "good")
    again = run_batch(ds, BatchConfig(retries=0, executor="local", workers=2), PipelineConfig(), say=lambda m: None)
    assert {k: s.status for k, s in again.states.items() if k.startswith("good/")} == {
        "good/scene/scene0": "current", "good/sequence/seq0": "current", "good/calibrate/seq0": "current",
        "good/motion/seq0": "current"}
    after = _steps(ds / "good")
    for m in before:
        assert {k: s["finished"] for k, s in after[m].items()} == {k: s["finished"] for k, s in before[m].items()}
    db = sqlite3.connect(ds / "catalog.sqlite")
    row = db.execute("SELECT status, failed_stage, error FROM sequences WHERE session='broken'").fetchone()
    assert row[:2] == ("failed", "scene") and "odometry.csv" in row[2]
    assert db.execute("SELECT status FROM sequences WHERE session='good'").fetchone() == ("done",)


def test_catalog_rows_match_the_sessions_files(processed):
    from embodmocap.catalog.db import rebuild
    from embodmocap.io.smpl_file import read_smpl_npz, read_smpl_valid
    from embodmocap.io.stage_files import read_cameras, sequence_fps

    ds = processed["ds"]
    ev = json.loads(SessionLayout(ds / "good").evaluation.read_text())  # written by the batch's evaluate task
    db = sqlite3.connect(ds / "catalog.sqlite")
    assert db.execute("SELECT COUNT(*) FROM metrics WHERE session='good'").fetchone()[0] > 0  # updated by the batch
    db.close()
    rebuild(ds)
    db = sqlite3.connect(ds / "catalog.sqlite")
    sl = SessionLayout(ds / "good").sequence(SYNTH.sequence_name)
    params, frames = read_smpl_npz(sl.smpl_world)
    n_cams = read_cameras(sl.view("v1").cameras).num_frames
    fps = sequence_fps(sl.root)
    row = db.execute("SELECT frames, fps, duration_s, motion_frames, valid_frames FROM sequences WHERE session='good'").fetchone()
    assert row[:2] == (n_cams, fps) and row[3] == len(params) == len(frames)
    assert row[4] == int(read_smpl_valid(sl.smpl_world).sum()) and row[2] == pytest.approx(len(params) / fps, abs=1e-3)
    cal = json.loads(sl.calibrate_manifest.read_text())
    for v in ("v1", "v2"):
        reg = db.execute("SELECT registered_fraction FROM views WHERE session='good' AND view=?", (v,)).fetchone()[0]
        assert reg == cal["figures"][f"{v}_registered_fraction"]
    seconds = db.execute("SELECT seconds FROM stages WHERE session='good' AND stage='motion'").fetchone()[0]
    mot = json.loads(sl.motion_manifest.read_text())
    assert seconds == pytest.approx(sum(s["seconds"] for s in mot["steps"].values()), abs=1e-3)
    metrics = dict(db.execute("SELECT key, value FROM metrics WHERE session='good'").fetchall())
    assert metrics["w_mpjpe_mm"] == pytest.approx(ev["sequences"][SYNTH.sequence_name]["w_mpjpe_mm"])


def test_sequence_dataset_windows_match_smpl_world(processed):
    import torch

    from embodmocap.data import SequenceDataset

    ds_root = processed["ds"]
    sl = SessionLayout(ds_root / "good").sequence(SYNTH.sequence_name)
    raw = np.load(sl.smpl_world)  # an independent reader of the file the dataset must reproduce
    ds = SequenceDataset(ds_root, window=16, stride=8, require_valid=False, camera_view="v1")
    T = len(raw["poses"])
    assert len(ds) == (T - 16) // 8 + 1 and {r.session for r in ds.sequences} == {"good"}
    for i in (0, len(ds) - 1):
        item = ds[i]
        s = ds.index[i][1]
        np.testing.assert_allclose(item["poses"].numpy(), raw["poses"][s:s + 16], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(item["trans"].numpy(), raw["trans"][s:s + 16], rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(item["frames"].numpy(), raw["frames"][s:s + 16])
        # Camera-space joints map back onto the world joints with the view's final cameras.
        T_cw = item["T_cam_world"].double().numpy()
        back = np.einsum("tij,tkj->tki", np.linalg.inv(T_cw)[:, :3, :3], item["joints_cam"].double().numpy()) \
            + np.linalg.inv(T_cw)[:, None, :3, 3]
        np.testing.assert_allclose(back, item["joints"].numpy(), atol=1e-4)
        assert item["height_map"].shape == (32, 32) and item["contacts"].shape == (16, 4)
    # Filters: no sequence of another scene, none above an impossible error threshold.
    assert len(SequenceDataset(ds_root, window=16, scenes=("elsewhere",))) == 0
    assert len(SequenceDataset(ds_root, window=16, max_metrics={"w_mpjpe_mm": 0.0})) == 0
    # DataLoader workers give the same windows.
    loader = torch.utils.data.DataLoader(ds, batch_size=2, num_workers=2, shuffle=False)
    first = next(iter(loader))
    np.testing.assert_array_equal(first["poses"][1].numpy(), ds[1]["poses"].numpy())


@pytest.mark.parametrize("executor", ["local", "ray"])
def test_ctrl_c_stops_cleanly_and_the_next_batch_resumes(tmp_path, executor, monkeypatch):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) during Stage II: status
    130, the stage records `interrupted`, the catalog the interrupted attempt; the next batch
    finishes the stage."""
    import subprocess
    import sys

    if executor == "ray":
        pytest.importorskip("ray")
        monkeypatch.setenv("RAY_AUTH_MODE", "disabled")

    from embodmocap.synth.studio import synthesize

    synthesize(SynthConfig(seed=2, seconds=3.0, scene_seconds=0.5, width=320, height=240, depth_width=64,
                           depth_height=48), tmp_path / "ds" / "a")
    ds = tmp_path / "ds"
    m = SessionLayout(ds / "a").sequence(SYNTH.sequence_name).manifest
    cmd = [sys.executable, "-m", "embodmocap.cli", "batch", str(ds), "--executor", executor, "--workers", "1",
           "--only", "sequence", "--ray-object-store-gb", "0.2"]
    # The child starts with SIGINT at its default (a test run started in the background inherits it
    # ignored, and an ignored SIGINT stays ignored in Python and in every process it starts).
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 600
    while not (m.is_file() and json.loads(m.read_text())["steps"]) and time.time() < deadline and p.poll() is None:
        time.sleep(0.05)  # interrupt once the stage has finished its first step
    os.killpg(p.pid, signal.SIGINT)
    out, _ = p.communicate(timeout=300)
    if executor == "ray" and "discovered a bug in Ray" in out:
        # Ray 2.60's core worker aborts the driver when a task completes while its cancel is in
        # flight ("Tried to complete task that was not pending"; seen once in 6 runs here). Not
        # ours to catch (a C++ check failure); the batch's Ctrl-C with Ray is then not clean.
        pytest.xfail("Ray aborted the batch on a cancel racing the task's end (Ray's own check failure)")
    assert p.returncode == 130, out
    assert "run the same command again to resume" in out
    status = json.loads(m.read_text())["status"]
    db = sqlite3.connect(ds / "catalog.sqlite")
    last = db.execute("SELECT status FROM attempts WHERE stage='sequence'").fetchall()[-1][0]
    if executor == "ray" and status == "ok":
        # Ray's cancel is asynchronous: a task in its last second can finish before the
        # KeyboardInterrupt reaches it (seen in 2 of 4 runs here). Then the catalog must say so
        # too: nothing is recorded as interrupted that was not.
        assert last == "ok"
    else:
        assert status == "interrupted" and last == "interrupted", (status, last)
    done_steps = json.loads(m.read_text())["steps"]
    res = run_batch(ds, BatchConfig(only=("sequence",), executor="local", workers=1), PipelineConfig(), say=lambda m: None)
    # The rerun finishes the stage (or, if the task had finished, finds it up to date).
    assert res.states["a/sequence/seq0"].status == ("current" if status == "ok" else "ok")
    assert json.loads(m.read_text())["status"] == "ok"
    after = json.loads(m.read_text())["steps"]
    for step, rec in done_steps.items():
        assert after[step]["finished"] == rec["finished"], step  # finished steps were not redone
