"""The ``colmap`` scene model and the feet's metric scale cue of ``embodmocap mono``.

Fast: the feet cue recovers a known scale from synthetic cameras, a floor and walking feet (exact,
and within 2 % with a regressor's depth noise); the scale-free floor plane; pose interpolation;
a chunk the scene model fails on splits the result into segments with warnings.
Slow (real SfM through pycolmap on a studio session): camera centres of a chunk up to a similarity;
a chunk of blank frames fails SfM and starts a new segment, never a silent jump."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from embodmocap.evaluate.metrics import umeyama
from embodmocap.mono.colmap_scene import interpolate_poses
from embodmocap.mono.config import FeetScaleConfig, StitchConfig
from embodmocap.mono.feet import feet_scale, stitched_floor
from embodmocap.mono.files import ChunkPrediction, plan_chunks
from embodmocap.mono.stitch import stitch


def _look_at(c: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Rigid OpenCV camera-to-world pose at ``c`` looking at ``target`` (Z-up world, camera upright)."""
    z = target - c
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = c
    return T


def _walk(T: int = 240, fps: float = 30.0, seed: int = 0):
    """A metric Z-up world: a walker's feet (alternating 0.5 s stance / swing, on z = 0 in
    stance) filmed by a camera 1.4 m high circling them. Returns camera poses (T, 4, 4), camera-
    space foot vertices (T, 2, k, 3) and the stance flags (T, 2)."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) / fps
    body = np.stack([0.6 * t, 0.1 * np.sin(t), np.zeros(T)], 1)
    cams = []
    for i in range(T):
        a = 0.4 * t[i]
        c = body[i] + [2.5 * np.cos(a), 2.5 * np.sin(a), 1.4]
        cams.append(_look_at(c, body[i] + [0, 0, 0.9]))
    cams = np.array(cams)
    sole = rng.normal(scale=[0.08, 0.04, 0.0], size=(12, 3)) + [0.05, 0, 0]  # a flat sole around the ankle
    feet_w = np.zeros((T, 2, 12, 3))
    stance = np.zeros((T, 2), bool)
    for f, side in enumerate((0.12, -0.12)):
        u = t / 0.5 + f
        k, frac = np.floor(u), u - np.floor(u)
        phase = k % 2 == 0  # each foot: 0.5 s planted on the floor, 0.5 s swinging forward
        stance[:, f] = phase
        lift = np.where(phase, 0.0, 0.12 * np.sin(np.pi * frac))
        x = np.where(phase, 0.3 * k, 0.3 * (k - 1) + 0.6 * frac) - 0.3 * f  # planted: still
        anchor = np.stack([x, body[:, 1] + side, np.zeros(T)], 1)
        feet_w[:, f] = anchor[:, None] + sole[None] + lift[:, None, None] * np.array([0, 0, 1.0]) \
            + np.array([0, 0, 0.02])[None, None] * (np.arange(12) % 3 == 0)[None, :, None]  # toes/heel edge a bit up
        feet_w[:, f, :, 2] -= feet_w[:, f, :, 2].min(axis=1, keepdims=True) * phase[:, None]  # stance: lowest at z = 0
    R, c = cams[:, :3, :3], cams[:, :3, 3]
    feet_cam = np.einsum("tji,tfkj->tfki", R, feet_w - c[:, None, None])
    return cams, feet_cam, stance


def _stitched(cams: np.ndarray, s_true: float, seed: int = 1):
    """The same cameras in a stitched frame: an unknown rotation, translation and scale 1/s_true."""
    rng = np.random.default_rng(seed)
    Rg = Rotation.random(random_state=seed).as_matrix()
    tg = rng.normal(size=3)
    out = cams.copy()
    out[:, :3, :3] = Rg @ cams[:, :3, :3]
    out[:, :3, 3] = (cams[:, :3, 3] @ Rg.T) / s_true + tg
    n = Rg @ np.array([0.0, 0.0, 1.0])
    d = -n @ tg  # z = 0 maps to n . x + d = 0 (the plane passes through tg)
    return out, (n, d)


def test_feet_recover_a_known_scale_exactly():
    cams, feet_cam, stance = _walk()
    T_st, plane = _stitched(cams, s_true=3.7)
    fs = feet_scale(feet_cam, T_st, np.ones(len(cams), bool), plane, 30.0, FeetScaleConfig())
    assert fs["frames"] >= 0.5 * len(cams)
    assert abs(fs["scale"] - 3.7) / 3.7 < 1e-9
    # every voting frame has a foot in stance (the swing foot's frames are not chosen)
    assert np.all(stance[fs["contact"]].any(axis=1))


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_feet_scale_error_is_the_regressors_own_depth_error(seed):
    """Each frame's body moved along its rays by a correlated 10 % depth error (the realistic
    prior's): the scale's error is that depth error's median over the voting frames (the cue adds
    nothing of its own), and the spread in the manifest shows the per-frame error."""
    cams, feet_cam, _ = _walk(T=600, seed=2)
    rng = np.random.default_rng(seed)
    k = np.exp(-np.arange(-30, 31) ** 2 / (2 * 7.5 ** 2))
    err = np.convolve(rng.normal(size=len(cams) + 60), k / np.sqrt((k ** 2).sum()), "valid")[:len(cams)] * 0.10
    noisy = feet_cam * (1 + err)[:, None, None, None]
    T_st, plane = _stitched(cams, s_true=0.25)
    fs = feet_scale(noisy, T_st, np.ones(len(cams), bool), plane, 30.0, FeetScaleConfig())
    assert fs["frames"] >= 60
    assert abs((fs["scale"] / 0.25 - 1) - np.median(err[fs["contact"]])) < 0.003
    assert 0.02 < fs["mad_rel"] < 0.2 and fs["p10"] < fs["scale"] < fs["p90"]


def test_feet_scale_needs_contact_frames():
    cams, feet_cam, _ = _walk(T=60)
    T_st, plane = _stitched(cams, s_true=1.0)
    fs = feet_scale(feet_cam, T_st, np.zeros(60, bool), plane, 30.0, FeetScaleConfig())  # no body estimate
    assert np.isnan(fs["scale"]) and fs["frames"] == 0


def test_stitched_floor_is_scale_free():
    rng = np.random.default_rng(0)
    cams, _, _ = _walk(T=60)
    floor = np.c_[rng.uniform(-3, 5, 2000), rng.uniform(-3, 3, 2000), rng.normal(0, 0.003, 2000)]
    wall = np.c_[rng.uniform(-3, 5, 800), np.full(800, 4.0), rng.uniform(0, 2.5, 800)]
    P = np.concatenate([floor, wall])
    for s in (0.01, 1.0, 50.0):
        T_st, (n, d) = _stitched(cams, s_true=s)
        Rg = T_st[0, :3, :3] @ cams[0, :3, :3].T
        tg = T_st[0, :3, 3] - Rg @ cams[0, :3, 3] / s
        got = stitched_floor((P @ Rg.T) / s + tg, T_st, 0.01)
        assert got is not None
        assert np.degrees(np.arccos(min(1.0, got[0] @ n))) < 0.5
        assert abs(got[1] - d) * s < 0.02  # within 2 cm once metric


def test_interpolate_poses_slerps_and_holds_the_ends():
    A, B = np.eye(4), np.eye(4)
    B[:3, :3] = Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix()
    B[:3, 3] = [2, 0, 0]
    out = interpolate_poses(np.array([10, 20]), np.stack([A, B]), np.array([5, 15, 25]))
    np.testing.assert_allclose(out[0], A)
    np.testing.assert_allclose(out[2], B)
    np.testing.assert_allclose(Rotation.from_matrix(out[1, :3, :3]).as_rotvec(), [0, 0, np.pi / 4], atol=1e-12)
    np.testing.assert_allclose(out[1, :3, 3], [1, 0, 0])


class _SyntheticSfm:
    """A scene model over a known world (points seen by known cameras, each chunk in a random
    similarity) whose chunks listed in ``fail`` come back failed, as the colmap model returns them."""

    name = "synthetic"

    def __init__(self, cams: np.ndarray, fail: set[int]) -> None:
        self.cams, self.fail = cams, fail
        rng = np.random.default_rng(0)
        self.depth = rng.uniform(1.5, 4.0, size=(12, 16))

    def predict(self, frames):
        N = len(frames)
        K = np.array([[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]])
        u, v = np.meshgrid(np.arange(16), np.arange(12))
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
        pts = np.repeat((rays * self.depth[..., None])[None], N, 0).astype(np.float32)
        if int(frames[0]) in self.fail:
            return ChunkPrediction(frames, np.tile(np.eye(4), (N, 1, 1)), pts * 0, np.zeros(pts.shape[:3], np.float32),
                                   failure="SfM registered 1 of 8 images")
        rng = np.random.default_rng(int(frames[0]))
        s, R, t = rng.uniform(0.5, 2), Rotation.random(random_state=int(frames[0])).as_matrix(), rng.normal(size=3)
        T = self.cams[frames].copy()
        T[:, :3, :3] = R @ T[:, :3, :3]
        T[:, :3, 3] = s * T[:, :3, 3] @ R.T + t
        return ChunkPrediction(frames, T, pts * s, np.ones(pts.shape[:3], np.float32))


def test_a_failed_chunk_splits_the_result_into_segments_with_warnings():
    cams, _, _ = _walk(T=100)
    plan = plan_chunks(100, 24, 8)  # starts 0, 16, 32, 48, 64, 80
    res = stitch(_SyntheticSfm(cams, fail={32}), plan, StitchConfig())
    # chunk 32 failed: it is a segment of its own, and chunk 48 (overlapping only it) starts another
    # (a chunk places the frames after its predecessor's: chunk 32..55 places 40..55)
    assert res.segment[:40].max() == 0 and np.all(res.segment[40:56] == 1) and np.all(res.segment[56:] == 2)
    assert res.failed[40:56].all() and not res.failed[:40].any() and not res.failed[56:].any()
    assert len(res.warnings) == 2
    assert "failed on it: SfM registered 1 of 8 images" in res.warnings[0] and "previous chunk failed" in res.warnings[1]
    assert [c.segment for c in res.chunks] == [0, 0, 1, 2, 2, 2]
    # within each good segment the path is right up to a similarity (no jump inside a segment)
    for g in (0, 2):
        fr = np.flatnonzero(res.segment == g)
        P, G = res.T_stitch_cam[fr, :3, 3], cams[fr, :3, 3]
        s, R, t = umeyama(P, G)
        assert np.abs(s * P @ R.T + t - G).max() < 1e-6


# --------------------------------------------------------------------------- real SfM (slow)

@pytest.fixture(scope="module")
def studio(tmp_path_factory) -> Path:
    from embodmocap.sequence import stage as sequence_stage
    from embodmocap.sequence.config import SequenceConfig
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    root = tmp_path_factory.mktemp("mono_colmap") / "s"
    synthesize(SynthConfig(seed=0, seconds=9.0, scene_seconds=1.0, width=320, height=240, depth_width=64, depth_height=48),
               root)
    sequence_stage.run(SequenceConfig(), root)
    return root


def _scene_model(root: Path, blank: set[int] = frozenset()):
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.manifest import load_manifest
    from embodmocap.io.stage_files import read_cameras
    from embodmocap.mono.config import MonoConfig
    from embodmocap.mono.stage import _colmap_scene

    lay = SessionLayout(root)
    seq = next(iter(load_manifest(lay.manifest).sequences))
    cams = read_cameras(lay.sequence(seq).view("v1").cameras)
    scene = _colmap_scene(MonoConfig(), lay, seq, "v1", cams)
    if blank:
        read = scene.read_rgb
        scene.read_rgb = lambda f: np.full_like(read(f), 128) if f in blank else read(f)
    return scene, lay, seq


def _truth_centres(lay, seq):
    from embodmocap.evaluate.session import sequence_truth
    from embodmocap.io.manifest import load_manifest

    scene = load_manifest(lay.manifest).sequences[seq].scene
    return sequence_truth(lay, scene, seq).T_world_cam["v1"][:, :3, 3]


@pytest.mark.slow
def test_colmap_chunk_recovers_camera_centres_up_to_a_similarity(studio):
    """SfM on 64 frames (6 s into the take, every 4th frame registered, the rest interpolated):
    the registered centres match the truth after a similarity within 2 % of the chunk's path, the
    person has no points (masked out of SIFT)."""
    scene, lay, seq = _scene_model(studio)
    frames = np.arange(180, 244)
    pred = scene.predict(frames)
    assert pred.failure == "", pred.failure
    reg = pred.registered
    assert reg.sum() >= 12
    G = _truth_centres(lay, seq)[frames]
    P = pred.T_world_cam[:, :3, 3]
    s, R, t = umeyama(P[reg], G[reg])
    err = np.linalg.norm(s * P @ R.T + t - G, axis=1)
    L = np.linalg.norm(np.diff(G, axis=0), axis=1).sum()
    assert err[reg].max() < 0.02 * L, (err[reg].max(), L)
    assert err[4:-4].max() < 0.05 * L  # interpolated frames inside the registered range
    assert (pred.conf[reg] > 0).sum(axis=(1, 2)).min() > 50  # sparse maps have points


@pytest.mark.slow
def test_colmap_failure_on_blank_frames_starts_a_segment(studio):
    """Frames 48..95 blank (a covered lens): SfM fails on the chunks inside them; the stitched
    result has segments and one warning per break, and the good segments' paths stay right."""
    scene, lay, seq = _scene_model(studio, blank=set(range(48, 96)))
    plan = plan_chunks(160, 64, 16)  # 0..63, 48..111, 96..159
    res = stitch(scene, plan, StitchConfig())
    assert res.chunks[1].segment != res.chunks[0].segment and res.warnings
    assert "failed" in res.warnings[0]
    assert res.failed[64:112].all() and not res.failed[:48].any()
    G = _truth_centres(lay, seq)
    for g in np.unique(res.segment[~res.failed]):
        fr = np.flatnonzero((res.segment == g) & ~res.failed)
        # frames between registered ones (not the blank ones, nor the chunk ends: they hold a pose)
        fr = fr[(fr >= 4) & (fr <= 156) & ((fr < 44) | (fr >= 100))]
        s, R, t = umeyama(res.T_stitch_cam[fr, :3, 3], G[fr])
        err = np.linalg.norm(s * res.T_stitch_cam[fr, :3, 3] @ R.T + t - G[fr], axis=1)
        assert err.max() < 0.05, err.max()


def test_benchmark_tables_carry_the_monocular_rows():
    """`embodmocap benchmark`'s capture-methods table: mono_colmap / mono_vio rows beside the
    others, means over the sessions that have them (a failed mono run or an older result without
    them is left out of that row only), and the summary says whether dual view beats each."""
    from embodmocap.evaluate.benchmark import summary, tables_markdown

    def errs(w):
        return {"w_mpjpe_mm": w, "wa_mpjpe_mm": w / 2, "w_mpjpe_mm_c500": w, "wa_mpjpe_mm_c500": w / 2,
                "w_mpjpe_mm_c1000": w, "wa_mpjpe_mm_c1000": w / 2, "rte_pct": w / 100}

    base = {m: errs(100.0) for m in ("monocular", "single_v1", "single_v2")} | {"dual": errs(40.0)}
    rows = [{"seed": 0, "preset": "indoor", "perception": "hard", "methods": base | {"mono_colmap": errs(300.0),
                                                                                     "mono_vio": errs(200.0)}},
            {"seed": 1, "preset": "indoor", "perception": "hard", "methods": base | {"mono_colmap": errs(500.0),
                                                                                     "mono_vio": {"error": "x"}}},
            {"seed": 2, "preset": "indoor", "perception": "hard", "methods": dict(base)}]
    md = tables_markdown(rows)
    colmap = next(x for x in md.splitlines() if x.startswith("| mono_colmap |"))
    vio = next(x for x in md.splitlines() if x.startswith("| mono_vio |"))
    assert colmap.startswith("| mono_colmap | realistic | hard | 2 | 400.00 | 200.00 |"), colmap
    assert vio.startswith("| mono_vio | realistic | hard | 1 | 200.00 |"), vio
    text = summary({"rows": rows})
    assert "Dual view better than mono_colmap at every chunk size and in RTE (2 sessions): True" in text
