"""benchmarks/_child.py reports a child's own peak memory, not its parent's (session 6: Stage II's
"900 MB" was the peak of the benchmark process that had just synthesised the session; on Linux a
child's ru_maxrss starts from the parent's high-water mark)."""

from __future__ import annotations

import resource
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from _child import run_cli  # noqa: E402


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="Linux /proc needed")
def test_child_peak_is_its_own(tmp_path):
    _, small = run_cli("body", "make-test-model", str(tmp_path / "a.npz"))
    big = bytearray(400 << 20)
    big[::4096] = b"\x01" * len(big[::4096])  # touch every page: 400 MB resident in this process
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024 >= 400
    _, after = run_cli("body", "make-test-model", str(tmp_path / "b.npz"))
    del big
    assert after < 300 and abs(after - small) < 100, (small, after)
