"""Stage IV's windows fitted by two worker processes give exactly the answer of one process, near
the studio truth (issue 30); a worker is a fresh interpreter, not a fork; a failing worker is one
clear error."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from embodmocap.motion import smplify as S
from embodmocap.motion import fit_workers
from embodmocap.motion.fit_workers import prestarted, run_pieces, start_workers

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_smplify_batch import _noisy_problem  # noqa: E402

def test_two_worker_processes_fit_the_windows_as_one_process_does(caplog):
    """Also with the second core lent by `embodmocap run`'s scheduler (``parallel.lend_cores``):
    ``workers`` 1, two processes, the same answer."""
    from embodmocap.motion.config import MotionConfig
    from embodmocap.parallel import lend_cores, usable_cores
    from embodmocap.schedule import FIT_PRELOAD, fit_helpers

    body, _, coco, init, views, kp3d = _noisy_problem(4.0, 2)
    T = len(coco)
    fits = {}
    for workers, lent in ((1, 1), (2, 1), (1, 2)):
        cfg = S.SmplifyConfig(device="cpu", window_frames=40, overlap_frames=10, shape_frames=30,
                              phase1_iterations=30, phase2_iterations=120, workers=workers)
        caplog.clear()
        with lend_cores(lent), caplog.at_level("DEBUG", logger="embodmocap.motion.smplify"):
            if lent == 1:
                res = S.fit_world_smpl(body, kp3d, np.ones((T, 17)), views, init, None, cfg)
            else:  # as a job of `embodmocap run` does it: the worker started as the stage begins, then taken
                n = fit_helpers(MotionConfig(smplify=cfg))
                assert n == min(2, usable_cores()) - 1
                with prestarted(n, FIT_PRELOAD, cfg.threads):
                    ahead = [p for _, w in fit_workers._AHEAD for p in w.procs]
                    res = S.fit_world_smpl(body, kp3d, np.ones((T, 17)), views, init, None, cfg)
                    assert not fit_workers._AHEAD  # taken by the fit, not left to be stopped
                assert len(ahead) == n and all(p.poll() is not None for p in ahead)
        assert len(res.windows) >= 3
        batches = 1 if (workers, lent) == (1, 1) else min(2, usable_cores())
        assert f"fitted in {batches} batch(es)" in caplog.text
        fits[workers, lent] = res.params
    for k in ("betas", "global_orient", "body_pose", "transl"):
        np.testing.assert_array_equal(getattr(fits[1, 1], k), getattr(fits[2, 1], k))
        np.testing.assert_array_equal(getattr(fits[1, 1], k), getattr(fits[1, 2], k))
    fits[2] = fits[2, 1]
    fitted = body.from_params(fits[2], dtype=torch.float64).coco17.numpy()
    start = body.from_params(init, dtype=torch.float64).coco17.numpy()
    err, err0 = (np.linalg.norm(x - coco, axis=-1).mean() for x in (fitted, start))
    assert err < 0.04 and err < 0.5 * err0, (err, err0)


def test_pieces_run_in_other_processes_and_a_failure_is_reported():
    # Module-level functions travel by name: os.getpid and int (which fails on this text).
    pids = run_pieces(os.getpid, [(), (), ()], workers=3)
    assert pids[0] == os.getpid() and len({*pids}) == 3
    assert run_pieces(os.getpid, [(), ()], workers=1) == [os.getpid()] * 2
    with start_workers(1) as pool:  # fewer workers than pieces: the rest run here
        assert run_pieces(os.getpid, [(), (), ()], pool).count(os.getpid()) == 2
    with pytest.raises(RuntimeError, match="no such window"):
        run_pieces(int, [("1",), ("no such window",)], workers=2)
    with pytest.raises(RuntimeError, match="without a result"):  # a worker that dies mid-job
        run_pieces(eval, [("1",), ("__import__('os')._exit(3)",)], workers=2)


def test_prestarted_workers_are_taken_by_a_matching_request_else_stopped():
    with prestarted(2, ("json",), 1):
        first = list(fit_workers._AHEAD[0][1].procs)
        with start_workers(1, ("json",), 2) as other:  # other threads: not these
            assert not {*other.procs} & {*first}
        with start_workers(1, ("json",), 1) as pool:  # taken; the one beyond the request stopped
            assert pool.procs == first[:1] and first[1].poll() is not None
            assert run_pieces(os.getpid, [(), ()], pool)[1] == first[0].pid
        assert not fit_workers._AHEAD
    with prestarted(1, ("json",), 1):
        left = fit_workers._AHEAD[0][1].procs[0]
        with start_workers(1, ("csv",), 1) as pool:
            assert pool.procs[0] is not left
    assert left.poll() is not None and not fit_workers._AHEAD  # never taken: stopped at the end
    with prestarted(1, ("json",), 1):  # one that died before it was taken is replaced
        dead = fit_workers._AHEAD[0][1].procs[0]
        dead.kill()
        dead.wait()
        with start_workers(1, ("json",), 1) as pool:
            fresh = pool.procs[0]
            assert fresh is not dead and run_pieces(os.getpid, [(), ()], pool)[1] == fresh.pid


def test_a_worker_is_a_fresh_interpreter_not_a_fork():
    """Session 10's forked workers deadlocked on a PyAV slice-thread lock held by the parent: a
    worker must not inherit this process's modules (their locks and threads) at all."""
    pytest.importorskip("av")  # loaded here (with its threads' locks once it decodes), absent there
    probe = "'av' in __import__('sys').modules"
    assert run_pieces(eval, [(probe,), (probe,)], workers=2) == [True, False]


def _pieces_in_a_daemon(conn) -> None:
    conn.send((os.getpid(), run_pieces(os.getpid, [(), ()], workers=2)))


def test_pieces_run_from_a_daemonic_process_like_a_run_worker():
    """``embodmocap run --workers`` runs stages in daemonic processes, where ``multiprocessing``
    refuses children: the workers start all the same."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_pieces_in_a_daemon, args=(child,), daemon=True)
    proc.start()
    me, pids = parent.recv()
    proc.join()
    assert pids[0] == me and pids[1] not in (me, os.getpid())
