"""`embodmocap batch` end to end on real synthetic sessions (slow: every stage runs).

A dataset of two sessions made from one synthetic capture: ``good`` (its raw inputs as they are)
and ``broken`` (its scene capture lost its poses file). Two local workers; the worker running
``good``'s Stage III is killed in the middle of it. Checked: the killed task is retried and the
outputs equal those of `embodmocap run` on the same capture alone; ``broken`` fails alone with its
cause in the catalog; a second batch redoes nothing; the catalog's rows match the sessions' files;
SequenceDataset windows match smpl_world.npz, also through DataLoader workers.

With Ray: Ctrl-C in the middle of Stage III stops cleanly (as with the local pool) and the next
batch resumes; a Ray worker killed in the middle of Stage III is retried with nothing lost; `batch
--address` runs on a Ray head started by `ray start --head`.
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
from embodmocap.pipeline import PipelineConfig
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


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """Every process of this module computes with OMP_NUM_THREADS=1: `run`'s subprocess, the local
    pool's workers (they inherit it) and Ray's (the batch passes the driver's value on to its tasks,
    1 when unset). Results are bit-identical only at equal thread counts: BLAS sums in another
    order differ in the last bits (~1e-13 from Stage III's scene index on)."""
    before = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = "1"
    yield
    if before is None:
        os.environ.pop("OMP_NUM_THREADS", None)
    else:
        os.environ["OMP_NUM_THREADS"] = before


@pytest.fixture(scope="module")
def reference(tmp_path_factory, _one_thread) -> Path:
    """One synthetic session processed by `embodmocap run` alone (what every batch must reproduce),
    in a process of its own so that it starts with this module's thread count."""
    import subprocess
    import sys

    from embodmocap.synth.studio import synthesize

    ref = tmp_path_factory.mktemp("ref") / "ref"
    synthesize(SYNTH, ref)
    p = subprocess.run([sys.executable, "-m", "embodmocap.cli", "run", str(ref)], stdout=subprocess.PIPE,
                       stderr=subprocess.STDOUT, text=True, timeout=3600)
    assert p.returncode == 0, p.stdout
    return ref


@pytest.fixture(scope="module")
def processed(tmp_path_factory, reference):
    ref = reference
    root = tmp_path_factory.mktemp("batch")
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


def _session_pids(sid: int) -> list[int]:
    """Processes of the Unix session ``sid`` (everything a process started with
    ``start_new_session=True`` started in turn, Ray's processes included: Ray gives its processes
    their own process groups, never their own sessions)."""
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()
            if int(fields[3]) == sid and int(d.name) != sid:
                pids.append(int(d.name))
    return pids


def _gone(sid: int, timeout_s: float = 60.0) -> list[int]:
    """Wait until no process of session ``sid`` is left; return those still there after ``timeout_s``."""
    deadline = time.time() + timeout_s
    while (left := _session_pids(sid)) and time.time() < deadline:
        time.sleep(0.2)
    return left


@pytest.mark.parametrize("executor", ["local", "ray"])
def test_ctrl_c_stops_cleanly_and_the_next_batch_resumes(tmp_path, reference, executor):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) during Stage III, once its
    first view is registered (the second one takes ~20 s): status 130, the stage records
    `interrupted` with the first view's step kept, the catalog the interrupted attempt, no process
    of the batch (Ray's included) is left; the next batch finishes the stage without redoing the
    first view, and its registrations and cameras equal those of `embodmocap run`."""
    import subprocess
    import sys

    env = dict(os.environ)
    if executor == "ray":
        pytest.importorskip("ray")
        env["RAY_AUTH_MODE"] = "disabled"
    ds = tmp_path / "ds"
    shutil.copytree(reference, ds / "a", symlinks=True)  # Stages I-IV done, as `run` left them
    sl = SessionLayout(ds / "a").sequence(SYNTH.sequence_name)
    m = sl.calibrate_manifest
    m.unlink()  # Stage III has to run again from its first step ...
    for v in ("v1", "v2"):  # ... and write its outputs again
        sl.view(v).registration.unlink()
        sl.view(v).cameras_world.unlink()
    cmd = [sys.executable, "-m", "embodmocap.cli", "batch", str(ds), "--executor", executor, "--workers", "1",
           "--only", "calibrate", "--ray-object-store-gb", "0.2"]
    # The child starts with SIGINT at its default (a test run started in the background inherits it
    # ignored, and an ignored SIGINT stays ignored in Python and in every process it starts).
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
                         env=env, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 900

    def first_view_done() -> bool:
        try:
            return "register_v1" in json.loads(m.read_text())["steps"]
        except (OSError, ValueError):
            return False

    while not first_view_done() and time.time() < deadline and p.poll() is None:
        time.sleep(0.05)
    assert p.poll() is None, p.communicate()[0]
    os.killpg(p.pid, signal.SIGINT)
    out, _ = p.communicate(timeout=600)
    assert p.returncode == 130, out
    assert "run the same command again to resume" in out
    assert _gone(p.pid) == [], "processes of the batch left running"
    data = json.loads(m.read_text())
    assert data["status"] == "interrupted", out
    assert "register_v1" in data["steps"] and "register_v2" not in data["steps"]
    db = sqlite3.connect(ds / "catalog.sqlite")
    rows = db.execute("SELECT status, worker FROM attempts WHERE stage='calibrate'").fetchall()
    db.close()
    assert [r[0] for r in rows] == ["interrupted"]
    assert not rows[0][1].endswith(f":{p.pid}")  # the stage ran in a worker process, not in the driver
    done_steps = data["steps"]
    res = run_batch(ds, BatchConfig(only=("calibrate",), executor="local", workers=1), PipelineConfig(),
                    say=lambda m: None)
    assert res.states["a/calibrate/seq0"].status == "ok"
    after = json.loads(m.read_text())
    assert after["status"] == "ok" and "register_v2" in after["steps"]
    assert after["steps"]["register_v1"]["finished"] == done_steps["register_v1"]["finished"]  # not redone
    from embodmocap.io.stage_files import read_cameras

    ref = SessionLayout(reference).sequence(SYNTH.sequence_name)
    for v in ("v1", "v2"):
        np.testing.assert_array_equal(read_cameras(sl.view(v).cameras_world).T_world_cam,
                                      read_cameras(ref.view(v).cameras_world).T_world_cam)
        got, want = np.load(sl.view(v).registration), np.load(ref.view(v).registration)
        assert sorted(got.files) == sorted(want.files)
        for k in want.files:
            np.testing.assert_array_equal(got[k], want[k], err_msg=f"{v} {k}")


def _started_pid(log_file: Path, key: str) -> int | None:
    """The pid of the worker process running ``key``, from the task's log ("<key>: start on host:pid")."""
    try:
        lines = [ln for ln in log_file.read_text().splitlines() if f"{key}: start on " in ln]
    except OSError:
        return None
    return int(lines[-1].rsplit(":", 1)[1]) if lines else None


def test_ray_worker_killed_mid_task_is_retried_and_nothing_is_lost(tmp_path, reference, monkeypatch):
    """The Ray worker process running a session's Stage III is killed (SIGKILL) once the stage has
    registered its first view: Ray reports the worker's death, the batch records the attempt as
    failed with that cause and retries it; the retry resumes (the first view's step is not redone)
    and every output and step fingerprint equals `embodmocap run` alone."""
    ray = pytest.importorskip("ray")
    from embodmocap.batch.run import task_log_file
    from embodmocap.batch.plan import make_plan

    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    ds = tmp_path / "ds"
    _raw_copy(reference, ds / "good")
    key = "good/calibrate/seq0"
    log_file = task_log_file(ds, make_plan(ds).by_key()[key])
    m = SessionLayout(ds / "good").sequence(SYNTH.sequence_name).calibrate_manifest
    killed: list = []

    def killer():
        deadline = time.time() + 1800
        while time.time() < deadline and not killed:
            try:
                ready = "register_v1" in json.loads(m.read_text())["steps"]
            except (OSError, ValueError):
                ready = False
            pid = _started_pid(log_file, key) if ready else None
            if pid:
                killed.append((pid, json.loads(m.read_text())["steps"]["register_v1"]["finished"]))
                os.kill(pid, signal.SIGKILL)
            time.sleep(0.05)

    th = threading.Thread(target=killer, daemon=True)
    th.start()
    res = run_batch(ds, BatchConfig(executor="ray", workers=1, retries=1, ray_object_store_gb=0.2), PipelineConfig(),
                    say=lambda m: None)
    killed.append(None)
    th.join()
    assert not ray.is_initialized()
    pid, v1_finished = killed[0]
    assert pid != os.getpid()  # a Ray worker process, not this driver
    st = res.states
    cal = st[key]
    assert cal.status == "ok" and cal.attempts == 2, (cal, res.executor)
    assert cal.causes[0].startswith("worker process died while running the task (ray: "), cal.causes
    assert all(st[f"good/{s}"].status == "ok" for s in ("scene/scene0", "sequence/seq0", "motion/seq0"))
    assert json.loads(m.read_text())["steps"]["register_v1"]["finished"] == v1_finished  # resumed, not redone
    ref_arrays, got = _arrays(reference), _arrays(ds / "good")
    for k in ref_arrays:
        np.testing.assert_array_equal(got[k], ref_arrays[k], err_msg=k)
    ref_steps, got_steps = _steps(reference), _steps(ds / "good")
    for name in ref_steps:
        assert {k: s["fingerprint"] for k, s in got_steps[name].items()} == \
            {k: s["fingerprint"] for k, s in ref_steps[name].items()}, name
    db = sqlite3.connect(ds / "catalog.sqlite")
    rows = db.execute("SELECT attempt, status, error FROM attempts WHERE stage='calibrate' ORDER BY id").fetchall()
    assert [r[:2] for r in rows] == [(1, "failed"), (2, "ok")] and rows[0][2].startswith("worker process died")
    assert db.execute("SELECT status FROM sequences WHERE session='good'").fetchone() == ("done",)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def ray_head():
    """A Ray head started with `ray start --head` in its own temporary folder and Unix session, as a
    user starts a cluster's head node. Teardown ends exactly the processes of that session (`ray
    stop` cannot be told which instance: it stops every Ray process of the machine)."""
    import re
    import subprocess
    import sys
    import tempfile

    pytest.importorskip("ray")
    tmp = Path(tempfile.mkdtemp(prefix="emray-", dir="/tmp"))  # Ray's socket paths must stay short
    env = {**os.environ, "RAY_AUTH_MODE": "disabled"}
    port = _free_port()
    cmd = [str(Path(sys.executable).parent / "ray"), "start", "--head", f"--port={port}", "--num-cpus=2",
           "--disable-usage-stats", f"--temp-dir={tmp}"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                         start_new_session=True)
    try:
        out, _ = p.communicate(timeout=300)
        assert p.returncode == 0, out
        found = re.search(r"--address='([^']+)'", out)
        yield {"address": found.group(1) if found else f"127.0.0.1:{port}", "temp_dir": tmp, "env": env,
               "sid": p.pid, "out": out}
    finally:
        for sig in (signal.SIGTERM, signal.SIGKILL):
            for pid in _session_pids(p.pid):
                try:
                    os.kill(pid, sig)
                except ProcessLookupError:
                    pass
            if not _gone(p.pid, 30.0):
                break
        left = _session_pids(p.pid)
        shutil.rmtree(tmp, ignore_errors=True)
        assert left == [], f"Ray head processes left: {left}"


def test_batch_on_an_existing_cluster_with_address(tmp_path, reference, ray_head):
    """`embodmocap batch DATASET --address HOST:PORT` joins a running Ray head (started by `ray start
    --head`) instead of starting its own instance: every task runs in that cluster's worker
    processes, the outputs equal `embodmocap run`'s, the catalog says done."""
    import subprocess
    import sys

    ds = tmp_path / "ds"
    _raw_copy(reference, ds / "good")
    cmd = [sys.executable, "-m", "embodmocap.cli", "batch", str(ds), "--address", ray_head["address"]]
    p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ray_head["env"],
                       timeout=1800)
    assert p.returncode == 0, p.stdout
    assert "Connecting to existing Ray cluster" in p.stdout and "Started a local Ray instance" not in p.stdout
    assert "on ray (2 at once" in p.stdout, p.stdout  # capacity = the cluster's 2 CPUs
    ref_arrays, got = _arrays(reference), _arrays(ds / "good")
    for k in ref_arrays:
        np.testing.assert_array_equal(got[k], ref_arrays[k], err_msg=k)
    db = sqlite3.connect(ds / "catalog.sqlite")
    rows = db.execute("SELECT stage, status, worker FROM attempts ORDER BY id").fetchall()
    assert sorted(r[0] for r in rows) == ["calibrate", "motion", "scene", "sequence"]
    assert all(r[1] == "ok" for r in rows), rows
    assert db.execute("SELECT status, motion_frames FROM sequences WHERE session='good'").fetchone() == \
        ("done", len(got["poses"]))
    db.close()
    # Every task ran in a worker process of that head: Ray names each worker's log files after its pid.
    logs = [f.name for f in ray_head["temp_dir"].glob("session_*/logs/*worker*")]
    for stage, _, worker in rows:
        pid = worker.rsplit(":", 1)[1]
        assert any(n.endswith((f"-{pid}.out", f"-{pid}.err", f"_{pid}.log")) for n in logs), (stage, worker, logs)
