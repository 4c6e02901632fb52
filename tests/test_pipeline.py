"""`embodmocap run` end to end (slow: every stage on real synthetic captures).

A session with two sequences, one of whose captures is broken: the broken sequence fails alone with
a clear message naming the file while the other goes through every stage; a run interrupted after
Stage I resumes without redoing it; evaluate and report work on the result.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from embodmocap.io.layout import SessionLayout
from embodmocap.io.manifest import load_manifest, write_manifest
from embodmocap.synth.config import SynthConfig

pytestmark = pytest.mark.slow

SYNTH = SynthConfig(seed=0, seconds=3.0, scene_seconds=15.0)


def _two_sequence_session(root: Path) -> Path:
    """The synthetic session plus a copy of its sequence whose v2 capture lost its poses."""
    from embodmocap.synth.studio import synthesize

    synthesize(SYNTH, root)
    lay = SessionLayout(root)
    m = load_manifest(lay.manifest)
    seq = m.sequences[SYNTH.sequence_name]
    shutil.copytree(lay.captures_dir / SYNTH.sequence_name, lay.captures_dir / "broken")
    broken_v2 = lay.view_capture("broken", "v2")
    for name in ("odometry.csv", "data.jsonl"):
        if (broken_v2 / name).exists():
            (broken_v2 / name).write_text("this is not a pose file\n")
    views = {v: dataclasses.replace(e, capture=lay.view_capture("broken", v)) for v, e in seq.views.items()}
    broken = dataclasses.replace(seq, name="broken", views=views)
    write_manifest(dataclasses.replace(m, sequences={**m.sequences, "broken": broken}))
    return root


def _embodmocap(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "embodmocap.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, **kw)


def test_run_isolates_failures_and_resumes(tmp_path):
    root = _two_sequence_session(tmp_path / "s")
    lay = SessionLayout(root)
    # Interrupt the first run in the middle of Stage I (after its mesh step and one more).
    proc = _embodmocap("run", str(root))
    deadline = time.time() + 900
    while not lay.scene(SYNTH.scene_name).manifest.is_file() or "mesh" not in lay.scene(SYNTH.scene_name).manifest.read_text():
        assert proc.poll() is None and time.time() < deadline, proc.stdout.read() if proc.poll() is not None else "timeout"
        time.sleep(1.0)
    scene_steps = json.loads(lay.scene(SYNTH.scene_name).manifest.read_text())["steps"]
    while len(json.loads(lay.scene(SYNTH.scene_name).manifest.read_text())["steps"]) == len(scene_steps) and proc.poll() is None:
        time.sleep(0.5)  # let one more Stage I step land before interrupting
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=120)
    done_before = json.loads(lay.scene(SYNTH.scene_name).manifest.read_text())["steps"]

    proc = _embodmocap("run", str(root))
    out, _ = proc.communicate(timeout=1800)
    assert proc.returncode == 1, out  # one sequence failed
    # Stage I steps finished before the interruption were not redone.
    after = json.loads(lay.scene(SYNTH.scene_name).manifest.read_text())["steps"]
    for step, rec in done_before.items():
        assert after[step]["finished"] == rec["finished"], step
    # The good sequence went through every stage; the broken one failed alone, naming its file.
    assert lay.sequence(SYNTH.sequence_name).smpl_world.is_file()
    assert not lay.sequence("broken").smpl_world.is_file()
    failed = [line for line in out.splitlines() if "broken" in line and "failed" in line.lower()]
    assert failed and "v2" in " ".join(failed), out

    from embodmocap.evaluate.report import write_report
    from embodmocap.evaluate.session import evaluate_session

    ev = evaluate_session(root)
    assert ev["sequences"][SYNTH.sequence_name]["w_mpjpe_mm"] < 100.0
    assert "missing" in ev["sequences"]["broken"]
    html, _ = write_report(root)
    assert "w_mpjpe_mm" in html.read_text()
