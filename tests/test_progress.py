"""Progress on long steps (embodmocap.progress): a bar on a real terminal, one line per step when
stderr is not a terminal, nothing with -q; and `embodmocap -q run` keeps stdout empty."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from embodmocap import progress as P


@pytest.fixture
def not_quiet():
    old = P.set_quiet(False)
    yield
    P.set_quiet(old)


def test_without_a_terminal_each_step_is_one_log_line(caplog, capsys, not_quiet):
    caplog.set_level(logging.INFO, logger="embodmocap.progress")
    items = list(P.progress(range(250), "scene0: fusing", unit="frame"))
    assert items == list(range(250))  # the items pass through unchanged
    with P.step("sparse model: match"):
        pass
    assert [r.getMessage() for r in caplog.records] == ["scene0: fusing: 250 frames", "sparse model: match"]
    assert capsys.readouterr().err == ""  # no bar redraws where nobody watches
    P.set_quiet(True)
    caplog.clear()
    assert list(P.progress(iter([1, 2]), "x")) == [1, 2]
    with P.step("y"):
        pass
    assert caplog.records == []


def _on_a_terminal(code: str) -> str:
    """Run ``code`` in a child whose stderr is a real pseudo-terminal; what the terminal showed."""
    import fcntl
    import pty
    import struct
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))  # 24 rows, 120 columns
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    proc = subprocess.Popen([sys.executable, "-c", code], stderr=slave, stdout=subprocess.DEVNULL, env=env)
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 4096)
        except OSError:  # the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    proc.wait(timeout=60)
    os.close(master)
    assert proc.returncode == 0
    return b"".join(chunks).decode(errors="replace")


def test_on_a_terminal_a_bar_per_step_and_nothing_when_quiet():
    code = ("import time\nfrom embodmocap.progress import progress, step, set_quiet\n"
            "for _ in progress(range(40), 'view1: keypoints', unit='frame'): pass\n"
            "with step('sparse model: match'): time.sleep(1.2)\n")
    shown = _on_a_terminal(code)
    assert "view1: keypoints" in shown and "40/40" in shown and "100%" in shown
    assert "sparse model: match: 00:01" in shown  # the elapsed time ticks while the call runs
    quiet = _on_a_terminal("from embodmocap.progress import progress, set_quiet\nset_quiet(True)\n"
                           "for _ in progress(range(40), 'view1: keypoints'): pass\n")
    assert quiet == ""


def test_quiet_run_prints_nothing_on_stdout(tmp_path):
    root = tmp_path / "s"
    (root / "sequences" / "seq0").mkdir(parents=True)
    (root / "captures" / "scene0").mkdir(parents=True)
    (root / "captures" / "scene0" / "odometry.csv").write_text("")  # not a capture: Stage I fails
    (root / "session.toml").write_text('version = 1\n[scenes.scene0]\ncapture = "captures/scene0"\n')

    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "embodmocap.cli", *args, "run", str(root)],
                              capture_output=True, text=True, timeout=300)

    plain, quiet = run(), run("-q")
    assert plain.returncode == quiet.returncode == 1
    assert "scene scene0: scene ..." in plain.stdout and "1 stage(s) failed" in plain.stdout
    assert quiet.stdout == ""
    # the failure is still said, on stderr: the stage's line and what to do
    assert "scene scene0" in quiet.stderr and "not a capture of a known format" in quiet.stderr
    assert "1 stage(s) failed" in quiet.stderr
