"""The monocular pipeline (``embodmocap mono``) on a tiny studio session with Stage II done and the
studio's precomputed scene-model / human inputs: exact recovery on noise-free inputs, sane
figures on noisy ones, the vio ablation, gravity, segments, resuming and bad input."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.evaluate.metrics import umeyama
from embodmocap.geometry.similarity import similarity_parts
from embodmocap.io.layout import SessionLayout
from embodmocap.io.smpl_file import read_smpl_npz
from embodmocap.io.stage_files import read_cameras
from embodmocap.mono import stage
from embodmocap.mono.config import MonoConfig, ScaleConfig
from embodmocap.mono.files import plan_chunks, read_chunk, read_mono_cameras, read_points_ply, write_chunk
from embodmocap.synth.config import SynthConfig
from embodmocap.synth.mono_inputs import MonoInputConfig, write_mono_inputs

SYNTH = SynthConfig(seed=3, seconds=3.0, scene_seconds=1.0, width=320, height=240, depth_width=64, depth_height=48)
CHUNK, OVERLAP = 32, 8
# human_depth="model": the exact-recovery tests need the body as the (noise-free) model gives it; the
# studio's Stage II keypoints carry detector noise, so the keypoint refinement (the default) would
# move a noise-free body by their error (tests/test_mono_refine.py and the tests at the end cover it).
# cue="body": these tests check the body-depth cue's own summary (the default, combined, averages it
# with the feet's; test_combined_scale_cue covers that).
CFG = MonoConfig(scene_model="precomputed", chunk=CHUNK, overlap=OVERLAP, human_model="precomputed",
                 human_depth="model", scale=ScaleConfig(cue="body"))


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    from embodmocap.sequence import stage as sequence_stage
    from embodmocap.sequence.config import SequenceConfig
    from embodmocap.synth.studio import synthesize

    root = tmp_path_factory.mktemp("mono") / "s"
    synthesize(SYNTH, root)
    sequence_stage.run(SequenceConfig(), root)
    return root


def _copy(base: Path, dst: Path) -> Path:
    shutil.copytree(base, dst, symlinks=True)
    return dst


@pytest.fixture(scope="module")
def exact(base, tmp_path_factory):
    root = _copy(base, tmp_path_factory.mktemp("exact") / "s")
    truth = write_mono_inputs(root, cfg=MonoInputConfig(chunk=CHUNK, overlap=OVERLAP, noise=False), seed=1)
    return root, truth, stage.run(CFG, root)


@pytest.fixture(scope="module")
def noisy(base, tmp_path_factory):
    root = _copy(base, tmp_path_factory.mktemp("noisy") / "s")
    truth = write_mono_inputs(root, cfg=MonoInputConfig(chunk=CHUNK, overlap=OVERLAP), seed=2)
    return root, truth, stage.run(CFG, root)


def _centre_errors(out, truth):
    P = read_mono_cameras(out.layout.cameras_world)["T_world_cam"][:, :3, 3]
    G = truth["T_scene_cam"][:, :3, 3]
    s, _, _ = umeyama(P, G)
    _, R1, t1 = umeyama(P, G, with_scale=False)
    rigid = np.linalg.norm(P @ R1.T + t1 - G, axis=1)
    s2, R2, t2 = umeyama(P, G)
    sim = np.linalg.norm(s2 * P @ R2.T + t2 - G, axis=1)
    return float(s), rigid, sim, R1, float(np.linalg.norm(np.diff(G, axis=0), axis=1).sum())


def test_plan_chunks_cover_every_frame_with_the_overlap():
    assert plan_chunks(100, 32, 8) == [(0, 32), (24, 56), (48, 80), (72, 100)]
    assert plan_chunks(20, 32, 8) == [(0, 20)]
    assert plan_chunks(56, 32, 8) == [(0, 32), (24, 56)]


def test_noise_free_inputs_are_recovered_exactly(exact):
    root, truth, out = exact
    s, rigid, _, R1, path = _centre_errors(out, truth)
    assert abs(s - 1) < 1e-3  # metric scale within 0.1 %
    assert rigid.max() < 1e-3  # camera centres within 1 mm after one rigid motion
    # Z-up from the VIO: the world differs from the true (Z-up) scene frame by a yaw only.
    assert R1[2, 2] > np.cos(np.deg2rad(1.0))
    f = out.figures
    assert f["segments"] == 1 and f["warnings"] == [] and f["scale_from"] == "body"
    assert f["overlap_residual_rel_max"] < 1e-6
    # The chunk similarities found are the studio's: chunk k -> chunk 0 = G_0 G_k^-1.
    G = truth["chunk_similarity"]
    for rec, Gk in zip(f["chunks"], G):
        want = G[0] @ np.linalg.inv(Gk)
        assert np.allclose(np.asarray(rec["S"]), want, atol=1e-4 * max(1.0, np.abs(want).max()))
    m = f["metric_scale"]["0"]["scale"]
    assert abs(m * similarity_parts(G[0])[0] - 1) < 1e-3


def test_noise_free_body_lands_on_the_true_joints(exact):
    from embodmocap.evaluate.mono import mono_metrics

    root, truth, out = exact
    lay = SessionLayout(root)
    params, frames = read_smpl_npz(out.layout.smpl_world)
    assert len(params) == len(truth["T_scene_cam"]) and np.array_equal(frames, np.arange(len(params)))
    e = mono_metrics(lay, SYNTH.scene_name, SYNTH.sequence_name)
    assert e["v1_mono_reference"] == "ground truth"
    assert e["v1_mono_w_mpjpe_mm"] < 1.0 and e["v1_mono_wa_mpjpe_mm"] < 1.0
    assert e["v1_mono_camera_err_cm"] < 0.1 and e["v1_mono_scale_err_pct"] < 0.1 and e["v1_mono_rte_pct"] < 0.1
    assert e["v1_mono_segments"] == 1


def test_points_ply_holds_the_scene_in_the_world(exact):
    root, truth, out = exact
    P, C = read_points_ply(out.layout.points)
    assert len(P) > 1000 and C.shape == P.shape and C.std() > 5
    # The points are the true scene surface: moved with the cameras' rigid alignment they lie on
    # the true mesh (the studio's room: floor z = 0 and walls / furniture above it).
    from embodmocap.io.mesh_file import read_mesh_ply
    import trimesh

    _, R1, t1 = umeyama(read_mono_cameras(out.layout.cameras_world)["T_world_cam"][:, :3, 3],
                        truth["T_scene_cam"][:, :3, 3], with_scale=False)
    v, f, _ = read_mesh_ply(SessionLayout(root).ground_truth.scene_mesh(SYNTH.scene_name))
    d = np.abs(trimesh.proximity.signed_distance(trimesh.Trimesh(v, f, process=False), (P[:500] @ R1.T + t1)))
    assert np.median(d) < 0.01


def test_noisy_inputs_stitch_within_the_path_and_report_residuals(noisy):
    root, truth, out = noisy
    s, rigid, sim, _, path = _centre_errors(out, truth)
    f = out.figures
    assert f["segments"] == 1
    # Stitching alone (a similarity to the truth): within 2 % of the path length.
    assert sim.mean() < 0.02 * path
    # The metric scale from a realistic body prior (depth 10 % off, slowly drifting) over 3 s.
    assert abs(s - 1) < 0.15
    res = [c["residual_rel"] for c in f["chunks"] if c["aligned"]]
    assert all(0.001 < r < 0.1 for r in res)
    sc = f["metric_scale"]["0"]
    assert sc["samples"] >= 100 and sc["frames"] >= 20 and sc["p10"] <= sc["scale"] <= sc["p90"] and sc["mad_rel"] > 0


def test_combined_scale_cue(exact, noisy, tmp_path):
    """``--scale.cue combined``: both cues' summaries in the manifest, the scale their weighted mean
    by their own block standard errors; on noise-free inputs the body cue (zero spread) takes all
    the weight and the scale is exact."""
    from embodmocap.mono.scale import combine_cues

    cfg = replace(CFG, scale=replace(CFG.scale, cue="combined", block_s=0.5))  # 3 s: 6 blocks
    root, truth, _ = exact
    out = stage.run(cfg, _copy(root, tmp_path / "exact"), force=True)
    sc = out.figures["metric_scale"]["0"]
    assert sc["cue"] == "combined" and sc["weights"]["body"] > 0.999 and sc["body"]["se_rel"] < 1e-6
    s, *_ = _centre_errors(out, truth)
    assert abs(s - 1) < 1e-3
    root, truth, _ = noisy
    out = stage.run(cfg, _copy(root, tmp_path / "noisy"), force=True)
    sc = out.figures["metric_scale"]["0"]
    assert sc["cue"] == "combined" and {"body", "feet"} <= set(sc) and out.figures["segments"] == 1
    assert sc["body"]["frames"] >= 20 and sc["body"]["se_rel"] > 0
    used = {k: sc[k] for k in sc["weights"]}
    assert "body" in used and np.isclose(sum(sc["weights"].values()), 1.0, atol=1e-3)
    assert np.isclose(sc["scale"], combine_cues(used)["scale"], rtol=1e-5)
    lo, hi = min(c["scale"] for c in used.values()), max(c["scale"] for c in used.values())
    assert lo * (1 - 1e-5) <= sc["scale"] <= hi * (1 + 1e-5)
    assert abs(_centre_errors(out, truth)[0] - 1) < 0.15  # metric, as the body cue alone (3 s, 10 % prior)


def test_second_run_skips_and_force_redoes(exact):
    root, truth, out = exact
    before = read_mono_cameras(out.layout.cameras_world)["T_world_cam"]
    again = stage.run(CFG, root)
    assert set(again.skipped) == {"stitch", "body"}
    assert np.array_equal(read_mono_cameras(again.layout.cameras_world)["T_world_cam"], before)
    manifest = json.loads(out.layout.manifest.read_text())
    assert manifest["status"] == "ok" and set(manifest["steps"]) == {"stitch", "body"}


def test_vio_scene_model_reproduces_the_phone_poses(exact):
    root, truth, _ = exact
    out = stage.run(replace(CFG, scene_model="vio"), root, view="v1")
    mc = read_mono_cameras(out.layout.cameras_world)
    vio = read_cameras(SessionLayout(root).sequence(SYNTH.sequence_name).view("v1").cameras).T_world_cam
    assert np.allclose(mc["T_world_cam"], vio, atol=1e-6)
    assert out.figures["scale_from"] == "scene model (metric)"
    # the body's own scale estimate is still reported (LiDAR depth vs body: close to 1)
    assert abs(out.figures["metric_scale"]["0"]["scale"] - 1) < 0.05


def test_gravity_from_the_floor_plane(exact, tmp_path):
    root, truth, _ = exact
    out = stage.run(replace(CFG, gravity="plane"), root, force=True)
    assert out.figures["gravity"]["0"] == "plane"
    P = read_mono_cameras(out.layout.cameras_world)["T_world_cam"][:, :3, 3]
    G = truth["T_scene_cam"][:, :3, 3]
    _, R1, _ = umeyama(P, G, with_scale=False)
    assert R1[2, 2] > np.cos(np.deg2rad(1.0))  # Z up as the true scene frame's
    assert np.abs(P[:, 2] - G[:, 2]).max() < 0.02  # the floor is at z = 0 as in the truth
    stage.run(CFG, root)  # back to the default outputs for the other tests


def test_a_chunk_that_cannot_be_aligned_starts_a_segment(exact, tmp_path):
    root, truth, _ = exact
    work = _copy(root, tmp_path / "s")
    folder = SessionLayout(work).perception(SYNTH.sequence_name, "v1").mono_scene_dir
    path = folder / "chunk_000048.npz"
    c = read_chunk(path, np.arange(48, 80))
    rng = np.random.default_rng(0)
    write_chunk(path, c.frames, c.T_world_cam, rng.uniform(0.5, 5, size=c.local_points.shape), c.conf)
    out = stage.run(CFG, work, force=True)
    assert out.figures["segments"] >= 2
    assert any("could not be aligned" in w and "segment 1" in w for w in out.figures["warnings"])
    mc = read_mono_cameras(out.layout.cameras_world)
    seg = mc["segment"]
    assert seg[0] == 0 and seg[-1] >= 1 and np.all(np.diff(seg) >= 0)
    # The junk chunk's segment has no body samples: no metric scale, its frames not valid.
    assert any("no metric scale" in w for w in out.figures["warnings"]), out.figures["warnings"]
    from embodmocap.io.smpl_file import read_smpl_valid

    valid = read_smpl_valid(out.layout.smpl_world)
    assert np.array_equal(valid, np.isfinite(mc["metric_scale"])) and valid[:48].all() and not valid[56:72].any()


def test_bad_inputs_name_the_file(exact, tmp_path):
    root, truth, _ = exact
    work = _copy(root, tmp_path / "s")
    pl = SessionLayout(work).perception(SYNTH.sequence_name, "v1")
    with pytest.raises(InputError, match="rerun with the --chunk"):
        stage.run(replace(CFG, chunk=40), work, force=True)
    d = dict(np.load(pl.mono_human))
    d["frames"] = d["frames"] + 5  # rows beyond the video's frames
    np.savez(pl.mono_human, **d)
    with pytest.raises(InputError, match="mono_human.npz.*do not match the video"):
        stage.run(CFG, work, force=True)
    shutil.rmtree(pl.mono_scene_dir)
    with pytest.raises(InputError, match="mono_scene"):
        stage.run(CFG, work, force=True)


def test_cli_runs_mono(exact):
    from embodmocap.cli import main

    root, _, _ = exact
    assert main(["mono", str(root), "--chunk", str(CHUNK), "--overlap", str(OVERLAP), "--human-model", "precomputed", "--scene-model", "precomputed"]) == 0


def test_evaluate_adds_the_mono_keys(exact):
    from embodmocap.evaluate.session import evaluate_session

    root, _, _ = exact
    res = evaluate_session(root)["sequences"][SYNTH.sequence_name]
    assert "missing" in res  # no Stage IV here: the dual-view keys are missing, the mono ones are not
    for k in ("w_mpjpe_mm", "wa_mpjpe_mm", "rte_pct", "camera_err_cm", "scale_err_pct"):
        assert np.isfinite(res[f"v1_mono_{k}"])
    assert res["v1_mono_reference"] == "ground truth" and "v2_mono_w_mpjpe_mm" not in res


def test_keypoint_depth_refinement_on_the_studio(noisy, tmp_path):
    """``--human-depth keypoints`` (the default) on the noisy studio inputs: the refined body is
    closer to the truth (W-MPJPE: the prior's depth error dominates it) and the manifest says what
    the refinement did; the noise-free view's figures (human_depth model) are untouched by it."""
    from embodmocap.evaluate.mono import mono_metrics

    root, truth, out = noisy
    lay = SessionLayout(root)
    before = mono_metrics(lay, SYNTH.scene_name, SYNTH.sequence_name)
    assert out.figures["human_depth"]["source"] == "model"
    work = _copy(root, tmp_path / "kp")
    ref = stage.run(replace(CFG, human_depth="keypoints"), work)
    assert ref.skipped == ()  # another human_depth: both steps redone (fingerprints)
    st = ref.figures["human_depth"]
    T = len(truth["T_scene_cam"])
    assert st["source"] == "keypoints" and st["frames_refined"] >= 0.8 * T
    assert st["reproj_px_after_median"] < st["reproj_px_before_median"]
    assert 0.7 < st["depth_factor_p10"] <= st["depth_factor_median"] <= st["depth_factor_p90"] < 1.4
    after = mono_metrics(SessionLayout(work), SYNTH.scene_name, SYNTH.sequence_name)
    assert after["v1_mono_w_mpjpe_mm"] < 0.8 * before["v1_mono_w_mpjpe_mm"]
    params, _ = read_smpl_npz(ref.layout.smpl_world)
    assert np.array_equal(params.betas.shape, (10,))


def test_missing_keypoints_fall_back_to_the_model_depth_with_a_warning(noisy):
    """Without a keypoints file (``kp_path`` None: ``mono`` finds no ``<view>/keypoints2d.npz``;
    Stage II always writes one, so a session without it is refused by the upstream check before
    this) the camera-space body is the model's, with one warning."""
    from embodmocap.body.model import load_body_model
    from embodmocap.mono.roles import PrecomputedHuman

    root, truth, out = noisy
    lay = SessionLayout(root)
    cams = read_cameras(lay.sequence(SYNTH.sequence_name).view("v1").cameras)
    human = PrecomputedHuman(lay.perception(SYNTH.sequence_name, "v1").mono_human)
    T = cams.num_frames
    hum, st, warn = stage._camera_body(replace(CFG, human_depth="keypoints"), human, load_body_model(
        lay.root / "body_model.npz"), cams, None, T)
    assert len(warn) == 1 and "keypoints2d.npz is missing" in warn[0] and st["source"] == "model"
    ref = human.estimate(T)
    assert np.array_equal(hum.transl, ref.transl) and np.array_equal(hum.betas, ref.betas)


class _ChunksInMemory:
    """The precomputed scene model's chunks, read before the session is deleted."""

    name = "precomputed"

    def __init__(self, chunks: dict) -> None:
        self.chunks = chunks

    def predict(self, frames):
        return self.chunks[int(frames[0])]


def test_solve_gives_the_runs_files_from_inputs_held_in_memory(noisy, tmp_path):
    """``mono.solve`` on the view's inputs read into memory from a copy of the session, deleted
    before it runs (so it can read no file), gives the run's files array by array."""
    from embodmocap.body.model import load_body_model
    from embodmocap.io.captures import open_capture
    from embodmocap.io.manifest import load_manifest
    from embodmocap.mono import solve
    from embodmocap.mono.files import chunk_file_name, read_human_npz

    root, _, out = noisy
    work = _copy(root, tmp_path / "s")
    lay = SessionLayout(work)
    vl, pl = lay.sequence(out.name).view("v1"), lay.perception(out.name, "v1")
    cams = read_cameras(vl.cameras)
    T, W = cams.num_frames, int(cams.width)
    masks = np.unpackbits(np.load(vl.masks), axis=-1)[..., :W].astype(bool)
    capture = open_capture(load_manifest(lay.manifest).sequence(out.name).views["v1"].capture)
    rgb = {f: capture.frames.rgb(int(cams.raw_frames[f])) for f in range(T)}
    chunks = {s: read_chunk(pl.mono_scene_dir / chunk_file_name(s), np.arange(s, e)) for s, e in plan_chunks(T, CHUNK, OVERLAP)}
    human = read_human_npz(pl.mono_human, T)
    model = load_body_model(None)
    view = solve.MonoView(K=np.asarray(cams.K, np.float64), size=(W, int(cams.height)), T_vio=np.array(cams.T_world_cam),
                          tracked=~np.asarray(cams.untracked, bool), fps=float(cams.fps), mask=lambda f: masks[f],
                          rgb=lambda f: rgb[f])
    shutil.rmtree(work)

    hum, _ = solve.camera_body(CFG, human, model, None, "COCO17", view.K, view.rate)
    res = solve.stitch_view(CFG, _ChunksInMemory(chunks), hum, model, view)
    files = read_mono_cameras(out.layout.cameras_world)
    assert np.array_equal(res.T_world_cam, files["T_world_cam"])
    assert np.array_equal(res.segment, files["segment"])
    assert np.array_equal(res.metric_scale, files["metric_scale"], equal_nan=True)
    P, C = read_points_ply(out.layout.points)
    assert np.array_equal(np.asarray(res.points, np.float32), P) and np.array_equal(res.colours, C)
    assert json.dumps(res.figures["metric_scale"], sort_keys=True) == json.dumps(out.figures["metric_scale"], sort_keys=True)
    params, valid = solve.body_world(hum, res.T_world_cam, res.metric_scale, model, view.rate)
    want, _ = read_smpl_npz(out.layout.smpl_world)
    for k in ("transl", "global_orient", "body_pose"):
        got, ref = np.asarray(getattr(params, k)), np.asarray(getattr(want, k))
        assert np.array_equal(got.astype(ref.dtype), ref), k
