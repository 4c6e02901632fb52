"""Fault injection on a small synthetic session (slow): every fault gives one line naming the file
and what to do (never a traceback), leaves nothing half-written behind, and a rerun finishes with
the same outputs as an uninterrupted run. The table in docs/reliability.md lists these cases.
"""

from __future__ import annotations

import json
import random
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

from embodmocap.io.layout import SessionLayout

from fault_session import (RUN_OPTIONS, STAGE_OPTIONS, STAGES, SYNTH, cli, differences, popen, remove_outputs,
                           snapshot, stale_temps)

pytestmark = pytest.mark.slow

SEQ = SYNTH.sequence_name


def _one_line_error(res: subprocess.CompletedProcess, *needles: str) -> str:
    """The run's error line, after checking it is a single line without a traceback."""
    assert "Traceback" not in res.stdout, res.stdout
    errors = [line for line in res.stdout.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1, res.stdout
    for n in needles:
        assert n in errors[0], errors[0]
    print(f"status {res.returncode}: {errors[0]}")  # shown with -rA: the outcomes in docs/reliability.md
    return errors[0]


def _copy(src: Path, dst: Path, how: str = "-a") -> Path:
    subprocess.run(["cp", how, str(src), str(dst)], check=True)
    return dst


def _manifests(root: Path) -> dict[str, dict]:
    """Every stage manifest's step records (fingerprints, outputs, finish times)."""
    return {p.relative_to(root).as_posix(): json.loads(p.read_text())["steps"]
            for p in sorted(Path(root).rglob("*manifest.json"))}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    from embodmocap.synth.studio import synthesize

    root = tmp_path_factory.mktemp("faults") / "inputs"
    synthesize(SYNTH, root)
    return root


@pytest.fixture(scope="module")
def reference(inputs) -> tuple[Path, dict, dict]:
    """An uninterrupted `embodmocap run`: (session, output snapshot, seconds per stage)."""
    ref = _copy(inputs, inputs.parent / "reference")
    res = cli("run", str(ref), *RUN_OPTIONS)
    assert res.returncode == 0, res.stdout
    seconds = {m.group(2): float(m.group(3)) for m in re.finditer(r"^\s+(scene \S+|sequence \S+)\s+(\w+)\s+ok\s+([\d.]+) s",
                                                                   res.stdout, re.M)}
    assert set(seconds) == set(STAGES), res.stdout
    return ref, snapshot(ref), seconds


@pytest.mark.parametrize("stage", STAGES)
def test_kill_9_at_a_random_point_then_rerun_gives_the_same_outputs(reference, tmp_path, stage):
    ref, outputs, seconds = reference
    work = _copy(ref, tmp_path / "s")
    remove_outputs(work, STAGES[STAGES.index(stage):])
    delay = random.Random(f"kill-{stage}").uniform(0.1, 0.9) * seconds[stage]
    proc = popen("run", str(work), *RUN_OPTIONS)
    for line in proc.stdout:  # wait until the stage starts
        if f": {stage} ..." in line:
            break
    time.sleep(delay)
    proc.kill()  # SIGKILL: no clean-up code runs
    proc.wait()
    res = cli("run", str(work), *RUN_OPTIONS)
    assert res.returncode == 0, res.stdout
    assert differences(outputs, snapshot(work)) == [], f"killed {delay:.1f} s into {stage}"
    assert stale_temps(work) == []
    print(f"killed {delay:.1f} s into {stage} (of {seconds[stage]:.1f} s); the rerun's outputs equal the reference's")


def test_sigint_is_one_line_and_status_130(inputs, tmp_path):
    work = _copy(inputs, tmp_path / "s")
    proc = popen("scene", str(work), *STAGE_OPTIONS["scene"])
    deadline = time.time() + 300
    man = SessionLayout(work).scene(SYNTH.scene_name).manifest
    while not man.is_file() and time.time() < deadline:
        time.sleep(0.2)
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=300)
    assert proc.returncode == 130, out
    assert "interrupted: run the same command again to resume" in out and "Traceback" not in out
    assert json.loads(man.read_text())["status"] == "interrupted"
    print(f"status {proc.returncode}: {out.strip().splitlines()[-1]}")


@pytest.mark.parametrize("how", ["cp -a", "cp -r", "mv", "symlink", "relative"])
def test_moved_or_copied_session_redoes_nothing(reference, tmp_path, how):
    ref, outputs, _ = reference
    before = _manifests(ref)
    if how in ("cp -a", "cp -r"):
        target = _copy(ref, tmp_path / "copy", how.split()[1])
    else:
        target = _copy(ref, tmp_path / "copy")
        if how == "mv":
            target = Path(shutil.move(str(target), str(tmp_path / "elsewhere")))
        elif how == "symlink":
            (tmp_path / "link").symlink_to(target)
            target = tmp_path / "link"
    arg = "copy" if how == "relative" else str(target)
    res = cli("run", arg, *RUN_OPTIONS, cwd=tmp_path)
    assert res.returncode == 0, res.stdout
    # No step ran again: every step record (fingerprint, outputs, finish time) is unchanged.
    assert _manifests(target) == before
    assert differences(outputs, snapshot(target)) == []
    print(f"{how}: no step redone")


def test_bad_keypoint_file_stops_downstream_stages_until_fixed(reference, tmp_path):
    ref, outputs, _ = reference
    work = _copy(ref, tmp_path / "s")
    kp = SessionLayout(work).perception(SEQ, "v1").keypoints_json(45)
    saved = kp.read_bytes()
    kp.write_bytes(b"")
    res = cli("sequence", str(work))
    _one_line_error(res, str(kp), "empty")
    assert res.returncode == 2
    # Stage IV does not run on the previous Stage II outputs: it names the stage to rerun.
    res = cli("motion", str(work))
    _one_line_error(res, "the sequence stage failed in its last run", f"embodmocap sequence {work} --seq {SEQ}")
    assert res.returncode == 2
    res = cli("inspect", str(work))
    assert res.returncode == 1 and str(kp) in res.stdout
    # Fixed: the run redoes only what depended on it and ends where the reference ended.
    kp.write_bytes(saved)
    res = cli("run", str(work), *RUN_OPTIONS)
    assert res.returncode == 0, res.stdout
    assert differences(outputs, snapshot(work)) == []


def test_out_of_date_upstream_is_named(reference, tmp_path):
    ref, _, _ = reference
    work = _copy(ref, tmp_path / "s")
    cams = SessionLayout(work).sequence(SEQ).view("v2").cameras_world
    cams.write_bytes(cams.read_bytes() + b"\0")  # Stage III's output changed behind its back
    res = cli("motion", str(work))
    _one_line_error(res, "calibrate stage's output", "cameras_world.npz changed", f"embodmocap calibrate {work} --seq {SEQ}")


@pytest.mark.parametrize("fault", ["nested", "huge"])
def test_hostile_keypoint_json_is_one_line(inputs, tmp_path, fault):
    work = _copy(inputs, tmp_path / "s")
    kp = SessionLayout(work).perception(SEQ, "v2").keypoints_json(45)
    if fault == "nested":
        kp.write_text("[" * 300_000 + "]" * 300_000)
        needles = ("nested 300000 levels deep",)
    else:
        with open(kp, "wb") as f:
            f.truncate(200 << 20)  # 200 MiB by its size (sparse): refused before reading
        needles = ("200.0 MiB", "limit")
    res = cli("sequence", str(work))
    _one_line_error(res, str(kp), *needles)
    insp = cli("inspect", str(work))
    assert insp.returncode == 1 and str(kp) in insp.stdout


def test_body_model_that_is_not_a_model(reference, tmp_path):
    ref, _, _ = reference
    work = _copy(ref, tmp_path / "s")
    toml = work / "session.toml"
    toml.write_text(re.sub(r'(?m)^body_model = .*$', 'body_model = "/etc/passwd"', toml.read_text()))
    assert "/etc/passwd" in toml.read_text()
    res = cli("motion", str(work), "--force")
    _one_line_error(res, "/etc/passwd", "body model")
    insp = cli("inspect", str(work))
    assert insp.returncode == 1 and "/etc/passwd" in insp.stdout


def _can_unshare() -> bool:
    return shutil.which("unshare") is not None and subprocess.run(
        ["unshare", "-rm", "true"], capture_output=True).returncode == 0


@pytest.mark.skipif(not _can_unshare(), reason="needs user + mount namespaces (unshare -rm) for a small file system")
def test_disk_full_is_one_line_and_leaves_no_partial_file(inputs, tmp_path):
    work = _copy(inputs, tmp_path / "s")
    scenes = work / "scenes"
    scenes.mkdir()
    # A 1 MiB file system where Stage I writes: its key frames fit, its sparse model does not.
    script = (f'mount -t tmpfs -o size=1m tmpfs "{scenes}" && "$@"; rc=$?; '
              f'echo "left: $(ls -A "{scenes}/{SYNTH.scene_name}" | tr "\\n" " ")"; exit $rc')
    res = cli("scene", str(work), *STAGE_OPTIONS["scene"], prefix=("unshare", "-rm", "sh", "-c", script, "sh"))
    # The sparse model (Stage I's second step since its mesh is fused with the model's drift correction)
    # checks the free space before COLMAP starts.
    line = _one_line_error(res, "MiB free", "run the same command again")
    assert res.returncode == 2, res.stdout
    assert str(scenes) in line
    left = res.stdout.strip().splitlines()[-1]
    assert ".part-" not in left and "sfm" not in left and "keyframes.json" in left, left
    # With space again, the same command finishes.
    res = cli("scene", str(work), *STAGE_OPTIONS["scene"])
    assert res.returncode == 0, res.stdout


# Downstream commands: each reads the four stages' outputs and writes its own folder; each must
# resume after a SIGKILL anywhere and end with the bytes of an uninterrupted run (the guide's
# "resume anywhere" covers every command a user runs, not only the four stages).
DOWNSTREAM = {
    "mono": (("mono", "{s}", "--scene-model", "vio"), ("sequences/seq0/mono",)),
    "skills": (("skills", "{s}"), ("sequences/seq0/skills",)),
    "training_export": (("export", "{s}", "--to", "training", "--out", "{s}/training"), ("training",)),
    "robot": (("robot:retarget", "{s}"), ("sequences/seq0/robot",)),
    "sim_check": (("sim:check", "{s}"), ("sequences/seq0/sim",)),
}


def _records(root: Path) -> dict[str, object]:
    """The step records of every manifest under ``root`` (a stage manifest's ``steps``; another
    command's own manifest whole)."""
    out = {}
    for p in sorted(Path(root).rglob("*manifest*.json")):
        data = json.loads(p.read_text())
        out[p.relative_to(root).as_posix()] = data.get("steps", data) if isinstance(data, dict) else data
    return out


def _downstream_args(name: str, session: Path) -> list[str]:
    return [a.replace("{s}", str(session)) for a in DOWNSTREAM[name][0]]


@pytest.fixture(scope="module")
def downstream(reference, tmp_path_factory) -> tuple[Path, dict, dict]:
    """Every downstream command run to the end on a copy of the reference: (session, snapshot of
    the outputs under ``sequences`` and ``training``, seconds per command)."""
    ref, _, _ = reference
    done = _copy(ref, tmp_path_factory.mktemp("downstream") / "s")
    seconds = {}
    for name in DOWNSTREAM:
        t0 = time.monotonic()
        res = cli(*_downstream_args(name, done))
        assert res.returncode == 0, (name, res.stdout)
        seconds[name] = time.monotonic() - t0
    return done, snapshot(done, under=("sequences", "training")), seconds


@pytest.mark.parametrize("name", list(DOWNSTREAM))
def test_downstream_kill_9_then_rerun_gives_the_same_outputs(downstream, tmp_path, name):
    done, outputs, seconds = downstream
    work = _copy(done, tmp_path / "s")
    for rel in DOWNSTREAM[name][1]:
        shutil.rmtree(work / rel)
    proc = popen(*_downstream_args(name, work))
    first = proc.stdout.readline()  # the command is up (imports done, logging started)
    delay = random.Random(f"kill-{name}").uniform(0.1, 0.9) * seconds[name] * 0.5
    time.sleep(delay)
    proc.kill()
    proc.wait()
    res = cli(*_downstream_args(name, work))
    assert res.returncode == 0, res.stdout
    assert differences(outputs, snapshot(work, under=("sequences", "training"))) == [], f"killed {delay:.1f} s after {first!r}"
    assert stale_temps(work) == []
    # And once finished, the same command again redoes nothing: no output file is rewritten and
    # no step record changes (the stage manifest itself notes the run).
    mtimes = {p: p.stat().st_mtime_ns for rel in DOWNSTREAM[name][1] for p in (work / rel).rglob("*")
              if p.is_file() and "manifest" not in p.name}
    steps = {rel: _records(work / rel) for rel in DOWNSTREAM[name][1]}
    res = cli(*_downstream_args(name, work))
    assert res.returncode == 0, res.stdout
    assert {p: p.stat().st_mtime_ns for p in mtimes} == mtimes
    assert {rel: _records(work / rel) for rel in DOWNSTREAM[name][1]} == steps
    print(f"{name}: killed {delay:.1f} s in (of {seconds[name]:.1f} s); the rerun's outputs equal the reference's")
