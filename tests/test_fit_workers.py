"""Stage IV's windows fitted by two forked worker processes give exactly the answer of one
process, near the studio truth (issue 30); a failing worker is one clear error."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from embodmocap.motion import smplify as S
from embodmocap.motion.fit_workers import can_fork, run_pieces

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_smplify_batch import _noisy_problem  # noqa: E402

pytestmark = pytest.mark.skipif(not can_fork(), reason="worker processes are forked")


def test_two_worker_processes_fit_the_windows_as_one_process_does():
    body, _, coco, init, views, kp3d = _noisy_problem(4.0, 2)
    T = len(coco)
    fits = {}
    for workers in (1, 2):
        cfg = S.SmplifyConfig(device="cpu", window_frames=40, overlap_frames=10, shape_frames=30,
                              phase1_iterations=30, phase2_iterations=120, workers=workers)
        res = S.fit_world_smpl(body, kp3d, np.ones((T, 17)), views, init, None, cfg)
        assert len(res.windows) >= 3
        fits[workers] = res.params
    for k in ("betas", "global_orient", "body_pose", "transl"):
        np.testing.assert_array_equal(getattr(fits[1], k), getattr(fits[2], k))
    fitted = body.from_params(fits[2], dtype=torch.float64).coco17.numpy()
    start = body.from_params(init, dtype=torch.float64).coco17.numpy()
    err, err0 = (np.linalg.norm(x - coco, axis=-1).mean() for x in (fitted, start))
    assert err < 0.04 and err < 0.5 * err0, (err, err0)


def _pid() -> int:
    return os.getpid()


def _fail() -> None:
    raise ValueError("no such window")


def test_pieces_run_in_other_processes_and_a_failure_is_reported():
    pids = run_pieces([_pid, _pid, _pid], workers=2)
    assert pids[0] == os.getpid() and pids[1] != os.getpid() and pids[2] != os.getpid()
    assert run_pieces([_pid, _pid], workers=1) == [os.getpid()] * 2
    with pytest.raises(RuntimeError, match="no such window"):
        run_pieces([_pid, _fail], workers=2)


def _pieces_in_a_daemon(conn) -> None:
    conn.send((os.getpid(), run_pieces([_pid, _pid], workers=2)))


def test_pieces_fork_from_a_daemonic_process_like_a_run_worker():
    """``embodmocap run --workers`` runs stages in daemonic processes, where ``multiprocessing``
    refuses children: the workers are forked all the same."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_pieces_in_a_daemon, args=(child,), daemon=True)
    proc.start()
    me, pids = parent.recv()
    proc.join()
    assert pids[0] == me and pids[1] not in (me, os.getpid())
