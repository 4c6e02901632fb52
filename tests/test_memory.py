"""release_freed_memory: freed heap memory really leaves the process (glibc), measured in /proc."""

import sys

import numpy as np
import pytest

from embodmocap.memory import _glibc, release_freed_memory


def _rss_anon_mb() -> float:
    for line in open("/proc/self/status"):
        if line.startswith("RssAnon:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no RssAnon in /proc/self/status")


@pytest.mark.skipif(not sys.platform.startswith("linux") or _glibc() is None, reason="needs glibc's malloc_trim")
def test_freed_heap_memory_returns_to_the_system():
    # 300 MB in 64 KiB blocks (under malloc's mmap threshold: they live in the heap, as a stage's
    # many mid-sized temporaries do); the last one stays alive so the heap's top cannot shrink by itself.
    blocks = [np.ones(8192) for _ in range(4800)]
    keep = np.ones(8192)
    before_free = _rss_anon_mb()
    del blocks
    held = _rss_anon_mb()
    assert before_free - held < 100, "glibc returned the blocks by itself: the test shows nothing here"
    assert release_freed_memory() is True
    after = _rss_anon_mb()
    assert held - after > 250, f"resident {held:.0f} MB before the release, {after:.0f} MB after"
    assert keep.sum() == 8192  # what is alive is untouched


def test_without_malloc_trim_it_still_collects(monkeypatch):
    import embodmocap.memory as memory

    monkeypatch.setattr(memory, "_libc", False)  # a C library without malloc_trim (macOS, musl)
    assert release_freed_memory() is False



_FREE_8MB_BLOCKS = """
import sys, numpy as np
from embodmocap.memory import map_large_blocks
def rss():
    return next(int(l.split()[1]) / 1024 for l in open("/proc/self/status") if l.startswith("RssAnon:"))
if sys.argv[1] == "map":
    map_large_blocks(4 << 20)
first = np.ones(2 << 20); del first  # a 16 MB free: glibc's own threshold rises past 8 MB
big = [np.ones(1 << 20) for _ in range(40)]  # 40 blocks of 8 MB
keep = np.ones(8192)  # a heap block after them, as in a stage
held = rss(); del big
print(held - rss())  # MB back to the system at the free, no trim
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or _glibc() is None, reason="needs glibc's mallopt")
def test_large_blocks_leave_the_process_when_freed():
    import os
    import subprocess
    from pathlib import Path

    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1] / "src")}

    def released(mode: str) -> float:  # a fresh process each: malloc's state is process-wide
        out = subprocess.run([sys.executable, "-c", _FREE_8MB_BLOCKS, mode], env=env, capture_output=True, text=True,
                             check=True)
        return float(out.stdout.strip())

    assert released("map") > 250
    assert released("default") < 100  # glibc's default keeps them: what map_large_blocks changes
