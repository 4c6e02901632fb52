"""`embodmocap run` with two workers (embodmocap.schedule) against the sequential run.

A studio session with two sequences, one of whose captures is broken. With two workers: Ctrl-C while
Stage III's registration runs beside Stage I's mesh stops every worker, each stage recording
``interrupted``; the rerun resumes without redoing Stage I's finished
steps, the broken sequence fails alone, the good one goes through every stage. Its outputs are
then the same, array by array, as one sequential run's (``--workers 1``) on a copy of the session.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from embodmocap.io.layout import SessionLayout
from embodmocap.io.stage_manifest import MANIFEST_VERSION, StageManifest, Upstream, require_step, require_upstream
from embodmocap.errors import InputError

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


def _cli(*args: str) -> subprocess.Popen:
    # Ctrl-C as a terminal gives it, even where pytest runs as a background job (SIGINT ignored).
    return subprocess.Popen([sys.executable, "-m", "embodmocap.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _steps(path: Path) -> dict:
    return json.loads(path.read_text())["steps"] if path.is_file() else {}


@pytest.mark.slow
def test_two_workers_resume_isolate_failures_and_match_one(tmp_path):
    from _child import _tree
    from compare_sessions import IGNORED, _strip, compare
    from test_pipeline import SYNTH, _two_sequence_session

    from embodmocap.pipeline import PipelineConfig, run_session

    a = _two_sequence_session(tmp_path / "a")
    b = tmp_path / "b"
    shutil.copytree(a, b)
    lay = SessionLayout(a)
    scene = lay.scene(SYNTH.scene_name)

    calib = lay.sequence(SYNTH.sequence_name).calibrate_manifest
    proc = _cli("run", str(a), "--workers", "2")
    deadline = time.time() + 900
    while "sfm" not in _steps(scene.manifest) or not calib.is_file():  # the registration has started
        assert proc.poll() is None and time.time() < deadline, proc.stdout.read() if proc.poll() is not None else "timeout"
        time.sleep(0.5)
    time.sleep(2.0)
    workers = [p for p in _tree(proc.pid) if b"spawn_main" in Path(f"/proc/{p}/cmdline").read_bytes()]
    assert workers
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=180)
    assert proc.returncode == 130, out
    assert json.loads(calib.read_text())["status"] == "interrupted", out
    assert json.loads(scene.manifest.read_text())["status"] in ("interrupted", "ok"), out
    assert not [p for p in workers if Path(f"/proc/{p}").exists()], "a worker outlived the run"
    before = _steps(scene.manifest)

    proc = _cli("run", str(a), "--workers", "2")
    out, _ = proc.communicate(timeout=1800)
    assert proc.returncode == 1, out  # the broken sequence failed
    after = _steps(scene.manifest)
    for step, rec in before.items():
        assert after[step]["finished"] == rec["finished"], step  # not redone
    assert lay.sequence(SYNTH.sequence_name).smpl_world.is_file()
    failed = [line for line in out.splitlines() if "broken" in line and "failed" in line.lower()]
    assert failed and "v2" in " ".join(failed), out
    assert " register " in out and "all stages done" not in out

    res = run_session(PipelineConfig(), b, workers=1)
    assert [r.target for r in res.failed()] == ["sequence broken"]
    # The broken sequence's failure names its file, under each copy's own folder.
    broken = [json.loads((s / "sequences/broken/manifest.json").read_text()) for s in (a, b)]
    broken[0]["error"] = broken[0]["error"].replace(str(a), str(b))
    assert broken[0]["status"] == "failed" and _strip(broken[0], IGNORED) == _strip(broken[1], IGNORED)
    same, diffs = compare(a, b)
    assert same > 100 and diffs in ([], ["sequences/broken/manifest.json: JSON content differs"]), diffs


def test_partial_stage_is_not_accepted_downstream_but_its_steps_are(tmp_path):
    """A run that does only some steps by design ends ``partial``: a downstream stage refuses it,
    while :func:`require_step` accepts a step it recorded (and refuses one it did not, or whose
    output changed since)."""
    from embodmocap.io.stage_manifest import tracked_stage

    out = tmp_path / "sfm.txt"

    @tracked_stage
    def stage_part():
        sm = StageManifest(tmp_path / "manifest.json", "scene", {"a": 1}, root=tmp_path)
        sm.partial = True
        with sm.step("sfm", "fp1") as step:
            out.write_text("model")
            step.record([out])

    stage_part()
    data = json.loads((tmp_path / "manifest.json").read_text())
    assert data["version"] == MANIFEST_VERSION and data["status"] == "partial"
    up = Upstream(tmp_path / "manifest.json", "scene", "embodmocap scene X")
    with pytest.raises(InputError, match="did not finish its last run \\(partial\\)"):
        require_upstream(up)
    require_step(up, "sfm")
    with pytest.raises(InputError, match="mesh step is not done"):
        require_step(up, "mesh")
    out.write_text("another model")
    with pytest.raises(InputError, match="changed since it was written"):
        require_step(up, "sfm")


def test_a_job_is_lent_the_idle_cores_only_when_every_job_left_waits_for_it():
    """The scheduler lends a job every worker's core only where the other workers would idle until
    it ends: no other job runs and every job left needs it, directly or not (Stage III and IV of a
    session's last sequence); the stage reads the loan through ``parallel.lent_cores``."""
    from embodmocap import parallel
    from embodmocap.schedule import cores_for, plan_jobs

    jobs = plan_jobs(["s"], [("q1", "s"), ("q2", "s")])
    state = {j.key: "pending" for j in jobs}
    assert all(cores_for(j.key, jobs, state, 2) == 1 for j in jobs)  # Stage I and II side by side
    state.update({k: "ok" for k in state if not k.endswith("q2")})
    state["motion/q1"] = "running"
    assert cores_for("calibrate/q2", jobs, state, 2) == 1  # q1's fit runs on the other worker
    state["motion/q1"] = "ok"
    state["scene/s"] = "running"
    assert cores_for("sequence/q2", jobs, state, 2) == 1  # Stage I runs beside it
    state["scene/s"] = state["sequence/q2"] = state["register/q2"] = "ok"
    assert cores_for("calibrate/q2", jobs, state, 2) == 2  # only q2's motion is left, and it waits
    state["calibrate/q2"] = "ok"
    assert cores_for("motion/q2", jobs, state, 2) == 2
    assert cores_for("motion/q2", jobs, state, 1) == 1
    state["motion/q1"] = "pending"  # e.g. q1 failed to start: it does not wait for q2
    assert cores_for("motion/q2", jobs, state, 2) == 1

    assert parallel.lent_cores() == 1
    with parallel.lend_cores(2):
        assert parallel.lent_cores() == 2
    assert parallel.lent_cores() == 1


def test_a_worker_does_not_import_the_cli_again(monkeypatch):
    """``spawn`` would re-import the parent's main module (the CLI, with every command's config) in
    each worker; the pool starts its workers without it, and leaves ``__main__`` as it was."""
    import types
    from multiprocessing import spawn

    from embodmocap.schedule import _main_module_not_rerun

    main = sys.modules["__main__"]
    monkeypatch.setattr(main, "__spec__", types.SimpleNamespace(name="embodmocap.cli"), raising=False)
    assert spawn.get_preparation_data("w")["init_main_from_name"] == "embodmocap.cli"
    with _main_module_not_rerun():
        assert not {k for k in spawn.get_preparation_data("w") if k.startswith("init_main")}
    assert sys.modules["__main__"] is main
