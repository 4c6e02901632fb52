"""Stage IV's windows fitted in one batch (``torch.func.vmap``) follow the same steps as each window
fitted alone: every window's loss and Adam state are its own (issue 30)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from embodmocap.body.model import load_body_model
from embodmocap.motion import smplify as S

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_smplify import BETAS, FPS, _perturbed, _views  # noqa: E402
from embodmocap.synth.motion import script_motion  # noqa: E402
from embodmocap.synth.scene import build_scene  # noqa: E402


def _noisy_problem(seconds: float, motion_seed: int):
    """(body model, true params, true COCO-17 (T, 17, 3), perturbed start, two views with 2 px noise,
    3D keypoints with 2 cm noise) of the studio's scripted motion."""
    body = load_body_model(None)
    spec = build_scene("indoor", np.random.default_rng(0)).spec
    params = script_motion(spec, body, BETAS, seconds, FPS, np.random.default_rng(motion_seed)).params
    coco = body.from_params(params, dtype=torch.float64).coco17.numpy()
    kp3d = coco + np.random.default_rng(3).normal(size=coco.shape) * 0.02
    return body, params, coco, _perturbed(params), _views(coco, noise_px=2.0), kp3d


def test_batched_windows_equal_windows_one_by_one():
    body, params, coco, init, views, kp3d = _noisy_problem(3.0, 0)
    T = len(coco)
    # Few iterations (the equality does not depend on them), every term on: prior, edges, both views.
    cfg = S.SmplifyConfig(device="cpu", window_frames=40, overlap_frames=10, phase1_iterations=8, phase2_iterations=12,
                          gnc_factor=2.0)
    prior = params.body_pose + np.random.default_rng(4).normal(size=params.body_pose.shape) * 0.05
    body_k = S.KeypointBody(body, torch.float64, "cpu")
    data = S._to_data(kp3d, np.ones((T, 17)), views, prior, cfg, torch.float64, "cpu")
    tt = lambda x: torch.as_tensor(np.array(x, dtype=np.float64))  # noqa: E731
    start = S._State(tt(init.betas), tt(init.global_orient), tt(init.body_pose), tt(init.transl))
    ranges = S.window_ranges(T, cfg.window_frames, cfg.overlap_frames)
    assert len(ranges) >= 3
    names = [v.name for v in views]
    alone = [S._fit_window(body_k, data.slice(slice(s, e)), S._State(start.betas, start.go[s:e], start.pose[s:e],
                                                                      start.transl[s:e]), cfg, names, False, True, {})
             for s, e in ranges]
    idx = torch.as_tensor(np.stack([np.arange(s, e) for s, e in ranges]))
    batch = S._fit_window(body_k, data.slice(idx), S._State(start.betas, start.go[idx], start.pose[idx], start.transl[idx]),
                          cfg, names, False, True, {}, batched=True)
    for k, st in enumerate(alone):
        for a, b in ((st.go, batch.go[k]), (st.pose, batch.pose[k]), (st.transl, batch.transl[k])):
            assert torch.allclose(a, b, atol=1e-9, rtol=0), float((a - b).abs().max())
        # and the fit moved: the comparison is not between two copies of the start
        assert float((st.pose - start.pose[ranges[k][0]:ranges[k][1]]).abs().max()) > 1e-3



def test_windows_stopped_early_on_their_own_loss_fit_as_alone_and_near_the_full_fit(monkeypatch):
    """``phase2_stop_tol``: each window leaves the batch when its own loss stops falling, at its
    own step; a window in the batch then gets exactly what it gets fitted alone (so the answer
    does not depend on how the windows are shared between processes), and the early stop lands
    within a few millimetres of the full schedule's fit."""
    body, params, coco, init, views, kp3d = _noisy_problem(3.0, 0)
    T = len(coco)
    body_k = S.KeypointBody(body, torch.float64, "cpu")
    tt = lambda x: torch.as_tensor(np.array(x, dtype=np.float64))  # noqa: E731
    start = S._State(tt(init.betas), tt(init.global_orient), tt(init.body_pose), tt(init.transl))
    steps = []
    real = S._optimise_windows
    monkeypatch.setattr(S, "_optimise_windows", lambda *a: steps.append(real(*a)) or steps[-1])
    fits = {}
    for tol in (0.0, 2e-3):
        cfg = S.SmplifyConfig(device="cpu", window_frames=40, overlap_frames=10, phase1_iterations=20,
                              phase2_iterations=120, phase2_stop_tol=tol)
        data = S._to_data(kp3d, np.ones((T, 17)), views, None, cfg, torch.float64, "cpu")
        ranges = S.window_ranges(T, cfg.window_frames, cfg.overlap_frames)
        names = [v.name for v in views]
        idx = torch.as_tensor(np.stack([np.arange(s, e) for s, e in ranges]))
        steps.clear()
        fits[tol] = S._fit_window(body_k, data.slice(idx), S._State(start.betas, start.go[idx], start.pose[idx],
                                                                    start.transl[idx]), cfg, names, False, True, {},
                                  batched=True)
        if tol == 0:
            assert not steps  # the plain schedule
            continue
        batch_steps = steps[0]
        assert len(batch_steps) == len(ranges) >= 3 and max(batch_steps) < 120 and len(set(batch_steps)) > 1, batch_steps
        for k, (s, e) in enumerate(ranges):
            alone = S._fit_window(body_k, data.slice(slice(s, e)), S._State(start.betas, start.go[s:e], start.pose[s:e],
                                                                         start.transl[s:e]), cfg, names, False, True, {})
            assert steps[-1] == [batch_steps[k]]
            for a, b in ((alone.go, fits[tol].go[k]), (alone.pose, fits[tol].pose[k]), (alone.transl, fits[tol].transl[k])):
                assert torch.allclose(a, b, atol=1e-9, rtol=0), float((a - b).abs().max())
    for k, (s, e) in enumerate(ranges):
        state = [S._State(start.betas, fits[t].go[k], fits[t].pose[k], fits[t].transl[k]) for t in (0.0, 2e-3)]
        c_full, c_stop = (body_k(x.betas, x.go, x.pose, x.transl)[1].numpy() for x in state)
        gap = np.linalg.norm(c_stop - c_full, axis=-1)
        err = np.linalg.norm(c_stop - coco[s:e], axis=-1).mean()
        assert 0 < gap.max() < 0.005 and err < 0.03, (gap.max(), err)


def test_float32_fit_lands_where_the_float64_fit_does():
    """The fit's default dtype is float32 (issue 30: faster on the CPU): on a perturbed start with
    noisy keypoints it lands within a millimetre of the float64 fit, both near the truth, and
    its parameters leave as float64."""
    body, _, coco, init, views, kp3d = _noisy_problem(2.0, 1)
    T = len(coco)
    fits = {}
    for dtype in ("float32", "float64"):
        cfg = S.SmplifyConfig(device="cpu", dtype=dtype)
        res = S.fit_world_smpl(body, kp3d, np.ones((T, 17)), views, init, None, cfg)
        assert all(getattr(res.params, k).dtype == np.float64 for k in ("betas", "global_orient", "body_pose", "transl"))
        fits[dtype] = body.from_params(res.params, dtype=torch.float64).coco17.numpy()
    assert S.SmplifyConfig().dtype == "float32"
    gap = np.linalg.norm(fits["float32"] - fits["float64"], axis=-1)
    assert gap.max() < 1e-3, gap.max()
    err = np.linalg.norm(fits["float32"] - coco, axis=-1).mean()
    start = np.linalg.norm(body.from_params(init, dtype=torch.float64).coco17.numpy() - coco, axis=-1).mean()
    assert err < 0.03 and err < 0.5 * start, (err, start)
