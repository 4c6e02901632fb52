"""Stage III's cross-view track on one clock (:mod:`embodmocap.calibrate.presync`).

Two cameras film the moving point set of ``test_geosync``, view 2 a known fraction of a frame off
view 1; each view's depth maps hold the exact depth of the joints around their pixels. With view 2's
points taken at view 1's instants, both views' back-projections of one joint, put in the world by
the true cameras, coincide up to the linear interpolation of the motion over a frame (the swing's
acceleration, at most 15 m/s^2, times dt^2 / 8: under 2.1 mm); paired frame by frame they miss by
the motion over the phase (centimetres). Every expected number comes from the construction.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_geosync import FPS, K, cameras, joints, project

from embodmocap.calibrate import losses as L
from embodmocap.calibrate.presync import track_pairs_on_clock
from embodmocap.calibrate.solve import ViewInputs, track_pairs

W, H = 640, 480


def view(T: np.ndarray, X: np.ndarray) -> ViewInputs:
    """A view of the points X (N, J, 3) from cameras T (N, 4, 4): keypoints, and depth maps with
    each joint's depth in a 7 x 7 patch around its pixel (nearer joints painted last)."""
    n = len(T)
    xy = project(T, X)
    z = np.einsum("tji,tnj->tni", T[:, :3, :3], X - T[:, None, :3, 3])[..., 2]
    kp = np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], -1)

    def depth(t: int) -> np.ndarray:
        d = np.zeros((H, W), np.float32)
        for j in np.argsort(-z[t]):
            u, v = np.rint(xy[t, j]).astype(int)
            d[max(v - 3, 0):max(v + 4, 0), max(u - 3, 0):max(u + 4, 0)] = z[t, j]
        return d

    cams = {"K": K, "width": np.int64(W), "height": np.int64(H), "T_world_cam": T,
            "raw_frames": np.arange(n), "frame_times_s": np.arange(n) / FPS}
    return ViewInputs(cameras=cams, keypoints=kp, depth_m=depth)


def views(phase: float, n: int = 60):
    """View 2's frame k films the instant (k - phase) / fps: view 1's instant t is view 2's t + phase."""
    t = np.arange(n) / FPS
    t2 = t - phase / FPS
    return {"v1": view(cameras(t, 0.0), joints(t)), "v2": view(cameras(t2, np.pi / 2), joints(t2))}


def world_gap(pairs, vs) -> np.ndarray:
    """(N,) distance, metres, between the pairs' two points put in the world by the true cameras."""
    f = pairs.frames.numpy()
    out = []
    for v, p in (("v1", pairs.p_a.numpy()), ("v2", pairs.p_b.numpy())):
        T = vs[v].cameras["T_world_cam"][f]
        out.append(np.einsum("nij,nj->ni", T[:, :3, :3], p) + T[:, :3, 3])
    return np.linalg.norm(out[0] - out[1], axis=1)


SOURCE = L.KeypointCorrespondences(np.zeros((1, 17, 3)), np.zeros((1, 17, 3)), depth_behind_surface_m=(0.0,) * 17)


@pytest.mark.parametrize("phase", [0.4, -0.3])
def test_view_2_taken_at_view_1_s_instants_meets_view_1(phase):
    vs = views(phase)
    on_clock = track_pairs_on_clock(vs, np.arange(60), phase / FPS, FPS, SOURCE)
    gap = world_gap(on_clock, vs)
    assert len(gap) > 300
    # (a few joints hidden behind a nearer one's depth patch are outliers: the 90th percentile)
    assert np.median(gap) < 2e-3 and np.percentile(gap, 90) < 2.5e-3
    # Paired frame by frame (as without the sub-frame sync): off by the motion over the phase.
    frame_pairs = track_pairs_on_clock(vs, np.arange(60), 0.0, FPS, SOURCE)
    assert np.median(world_gap(frame_pairs, vs)) > 4 * np.median(gap)
    # A query beyond view 2's frames has no pair: view 2 starts later (phase > 0) or ends earlier.
    end = 59 if phase > 0 else 0
    assert end not in set(on_clock.frames.numpy().tolist())


def test_in_phase_the_pairs_are_the_frame_pairs():
    """Phase 0: the same pairs as the frame-paired track (``solve.track_pairs``), to rounding."""
    vs = views(0.0)
    a = track_pairs_on_clock(vs, np.arange(60), 0.0, FPS, L.KeypointCorrespondences(vs["v1"].keypoints, vs["v2"].keypoints))
    b = track_pairs(vs)
    assert np.array_equal(a.frames.numpy(), b.frames.numpy())
    assert np.allclose(a.p_a.numpy(), b.p_a.numpy(), atol=1e-12) and np.allclose(a.p_b.numpy(), b.p_b.numpy(), atol=1e-9)
    assert np.allclose(a.weight.numpy(), b.weight.numpy())
    # track_pairs with a residual goes through the clock, same frames subset rule.
    c = track_pairs(vs, 20, 0.25 / FPS, FPS)
    assert set(c.frames.numpy().tolist()) <= set(np.linspace(0, 59, 20).round().astype(int).tolist())


# --------------------------------------------------------------------------- a studio session


@pytest.fixture(scope="module")
def studio(tmp_path_factory):
    """A 3 s studio session whose view 2 films 0.4 frame later than view 1 (Stage II run; the
    offsets come from the truth, so Stage I is not needed)."""
    from embodmocap.sequence import stage as seq_stage
    from embodmocap.sequence.config import SequenceConfig
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    out = tmp_path_factory.mktemp("presync") / "s"
    synthesize(SynthConfig(seed=5, seconds=3.0, scene_seconds=4.0, phone_phase="fixed", phone_offset_frames=0.4), out)
    seq_stage.run(SequenceConfig(), out)
    return out


def test_studio_phase_view_2_on_view_1_s_clock(studio):
    """Stage II's real files (keypoints, depth, frame times): with the true offsets, both views'
    points of a joint come closest when view 2 is taken at view 1's instants, i.e. 0.4 frame
    earlier on its own clock (the studio's truth, ``view_time_offset_frames``): closer than frame by
    frame, and than the opposite sign. The gap left (about 4 cm) is the joints' depth behind the
    seen surface, which the keypoints' approximation leaves; the phase moves it by millimetres."""
    from embodmocap.calibrate import stage
    from embodmocap.evaluate.truth import sequence_truth
    from embodmocap.io.ground_truth import read_truth_info
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.stage_files import sequence_fps

    lay = SessionLayout(studio)
    sl = lay.sequence("seq0")
    phase = read_truth_info(lay.ground_truth.info)["view_time_offset_frames"]
    assert phase == {"v1": 0.0, "v2": 0.4}
    truth = sequence_truth(lay, "scene0", "seq0")
    vs = {v: stage.view_inputs(sl, v) for v in ("v1", "v2")}
    fps = sequence_fps(sl)
    world = {v: replace_cams(vs[v], truth.T_world_vio[v] @ vs[v].cameras["T_world_cam"]) for v in vs}
    gap = {r: float(np.median(world_gap(track_pairs(vs, 0, r / fps, fps), world))) for r in (-0.4, 0.0, 0.4)}
    assert gap[-0.4] < gap[0.0] - 2e-3 and gap[-0.4] < gap[0.4] - 2e-3, gap


def replace_cams(view: ViewInputs, T_world_cam: np.ndarray) -> ViewInputs:
    from dataclasses import replace

    return replace(view, cameras={"T_world_cam": T_world_cam})
