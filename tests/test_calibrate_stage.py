"""Stage III end to end on a small synthetic session: offsets against ground truth, resume, errors."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from embodmocap.calibrate import stage
from embodmocap.calibrate.register import RegisterConfig
from embodmocap.errors import InputError
from embodmocap.geometry.transforms import invert_T, rotation_angle
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.stage_files import read_final_sync
from embodmocap.scene import stage as scene_stage
from embodmocap.scene.config import SceneConfig
from embodmocap.scene.sfm import SfmConfig
from embodmocap.sequence import stage as seq_stage
from embodmocap.sequence.config import SequenceConfig
from embodmocap.synth.config import SynthConfig
from embodmocap.synth.studio import synthesize

CFG = stage.CalibrateConfig(register=RegisterConfig(num_frames=24), chamfer_frames=10)


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("calib") / "s"
    synthesize(SynthConfig(seed=5, seconds=2.0, scene_seconds=10.0), out)
    scene_stage.run(SceneConfig(voxel_m_indoor=0.02, sfm=SfmConfig(max_images=60, num_threads=1)), out)
    seq_stage.run(SequenceConfig(), out)
    # Stage II's sync record as Stage III finds it (Stage III writes its own final_sync.json).
    shutil.copy(SessionLayout(out).sequence("seq0").sync, out.parent / "sync_stage2.json")
    return out


@pytest.fixture(scope="module")
def done(session) -> stage.CalibrateOutputs:
    return stage.run(CFG, session)


def true_offsets(session: Path) -> dict[str, np.ndarray]:
    """T_world_vio of each view in Stage I's world (the scene capture's VIO world)."""
    gt = SessionLayout(session).ground_truth
    scene_vio = np.load(gt.scene_device("scene0"))["T_scene_vio"]
    seq = np.load(gt.sequence("seq0"))
    return {v: invert_T(scene_vio) @ seq[f"{v}_T_scene_vio"] for v in VIEWS}


def offset_error(T_est: np.ndarray, T_true: np.ndarray, probe: np.ndarray) -> tuple[float, float]:
    """(translation error at the view's own cameras in m, yaw error in degrees)."""
    p = np.c_[probe, np.ones(len(probe))]
    d = (p @ T_est.T)[:, :3] - (p @ T_true.T)[:, :3]
    return float(np.linalg.norm(d, axis=1).mean()), float(np.degrees(rotation_angle(T_est[:3, :3].T @ T_true[:3, :3])))


def test_offsets_match_ground_truth(session, done):
    truth = true_offsets(session)
    for v in VIEWS:
        cams = np.load(SessionLayout(session).sequence("seq0").view(v).cameras)
        centres = cams["T_world_cam"][:, :3, 3]
        t_err, yaw_err = offset_error(done.T_world_vio[v], truth[v], centres)
        # VIO drift alone is about 1 cm over a clip; 2 cm / 0.5 deg is the median target.
        assert t_err < 0.04 and yaw_err < 0.8, (v, t_err, yaw_err)
        reg_err = offset_error(np.asarray(done.report["views"][v]["T_world_vio_registration"]), truth[v], centres)
        assert reg_err[0] < 0.06
        world = np.load(SessionLayout(session).sequence("seq0").view(v).cameras_world)
        np.testing.assert_allclose(world["T_world_cam"], done.T_world_vio[v] @ cams["T_world_cam"], atol=1e-9)
    assert "refine" in done.report and done.report["refine"]["loss_after"] <= done.report["refine"]["loss_before"]


def test_second_run_skips_every_step(session, done):
    again = stage.run(CFG, session)
    assert set(again.skipped) == {"register_v1", "register_v2", "geosync", "refine"}


def test_missing_stage_outputs_say_which_stage_to_run(session, tmp_path):
    work = tmp_path / "s"
    shutil.copytree(session, work, ignore=shutil.ignore_patterns("scenes"))
    with pytest.raises(InputError, match="embodmocap scene"):
        stage.run(CFG, work)


def test_too_few_registered_frames_names_the_view_and_causes(session, tmp_path):
    work = tmp_path / "s"
    shutil.copytree(session, work)
    # Demand more inliers than any frame can have: nothing registers.
    cfg = replace(CFG, register=replace(CFG.register, min_inliers=100000))
    with pytest.raises(InputError) as err:
        stage.run(cfg, work)
    msg = str(err.value)
    assert "registered" in msg and "v1" in msg and "texture" in msg


def test_vio_check_is_reported_and_rejected_frames_stay_out_of_the_fit(session, done):
    for v in VIEWS:
        chk = done.report["views"][v]["vio_check"]
        assert set(chk) >= {"runs", "rejected_runs", "rejected_frames", "off_chain_frames"}
        reg_off = np.load(SessionLayout(session).sequence("seq0").view(v).registration)["off_chain"]
        assert chk["off_chain_frames"] == int(reg_off.sum())
        reg = np.load(SessionLayout(session).sequence("seq0").view(v).registration)
        assert reg["accepted"].shape == reg["t"].shape and chk["rejected_frames"] == int((~reg["accepted"]).sum())
        init = stage.YawOffset(*_offset_of(done.report["views"][v]["T_world_vio_registration"]))
        data = stage.build_view_data(CFG, SessionLayout(session), "seq0", v, init, reg)
        assert not np.isin(np.asarray(data.matches.frames), reg["t"][~reg["accepted"]]).any()
    assert (SessionLayout(session).scene("scene0").root / "register_index.npz").is_file()  # cached for the next sequence


def _offset_of(T):
    T = np.asarray(T)
    return float(np.arctan2(T[1, 0], T[0, 0])), T[:3, 3]


def test_view_that_disagrees_with_its_vio_is_one_clear_error_and_writes_nothing(session, tmp_path):
    work = tmp_path / "s"
    shutil.copytree(session, work)
    lay = SessionLayout(work)
    for v in VIEWS:  # drop Stage III outputs: nothing may appear
        for p in (lay.sequence("seq0").view(v).registration, lay.sequence("seq0").view(v).cameras_world):
            p.unlink(missing_ok=True)
    lay.sequence("seq0").calibration.unlink(missing_ok=True)
    # The VIO of v1 no longer belongs to its video (each frame turned about Z by a random angle and
    # moved by up to a metre): registrations, each fine on its own, disagree with the VIO motion
    # everywhere, as for a sequence filmed in another scene.
    from embodmocap.geometry.transforms import make_T, rot_z

    cams_path = lay.sequence("seq0").view("v1").cameras
    cams = dict(np.load(cams_path))
    rng = np.random.default_rng(0)
    n = len(cams["T_world_cam"])
    jumble = make_T(np.stack([rot_z(a) for a in rng.uniform(-np.pi, np.pi, n)]), rng.uniform(-1, 1, (n, 3)))
    cams["T_world_cam"] = jumble @ cams["T_world_cam"]
    np.savez(cams_path, **cams)
    # As if Stage II's outputs had been made by hand: no Stage II manifest (with it, Stage III
    # rightly refuses a Stage II output changed behind its back); Stage III's own checks apply.
    lay.sequence("seq0").manifest.unlink()
    with pytest.raises(InputError) as err:
        stage.run(CFG, work)
    msg = str(err.value)
    assert "v1" in msg and "disagree with its own VIO" in msg and "wrong scene" in msg and len(msg.splitlines()) == 1
    assert not lay.sequence("seq0").view("v1").registration.is_file()
    assert not lay.sequence("seq0").calibration.is_file()


def test_view_whose_registration_fails_is_placed_through_the_performer(session, tmp_path, monkeypatch):
    """v1's registrations scattered at random (as on plain walls under other light) while its VIO
    is right: v1 is placed through the performer v2 also films, checked on the scene mesh, and
    ends near the truth; v2 is untouched."""
    work = tmp_path / "s"
    shutil.copytree(session, work)
    from embodmocap.calibrate import solve

    real = solve.register_frames_of_view
    rng = np.random.default_rng(1)
    calls = []

    def broken(cfg, frames, K, index, T_vio, name, pool=None):
        reg = real(cfg, frames, K, index, T_vio, name, pool)
        calls.append(name[-2:])
        if not name.endswith("v1"):
            return reg
        from embodmocap.geometry.transforms import make_T, rot_z

        n = len(reg.t)
        scatter = make_T(np.stack([rot_z(a) for a in rng.uniform(-np.pi, np.pi, n)]), rng.uniform(-2, 2, (n, 3)))
        return replace(reg, T_world_cam=scatter @ reg.T_world_cam)

    monkeypatch.setattr(solve, "register_frames_of_view", broken)
    out = stage.run(CFG, work, force=True)
    truth = true_offsets(work)
    rep = out.report["views"]
    assert rep["v1"]["offset_fit"]["placement"] == "performer" and rep["v2"]["offset_fit"]["placement"] == "registration"
    reg = np.load(SessionLayout(work).sequence("seq0").view("v1").registration)
    assert not reg["accepted"].any() and reg["T_world_vio_performer"].shape == (4, 4)
    for v in VIEWS:
        centres = np.load(SessionLayout(work).sequence("seq0").view(v).cameras)["T_world_cam"][:, :3, 3]
        t_err, yaw_err = offset_error(out.T_world_vio[v], truth[v], centres)
        assert t_err < 0.06 and yaw_err < 1.0, (v, t_err, yaw_err)

    # The placement read the mesh, so its record's fingerprint has the mesh: a rerun skips it, the
    # registration alone (``embodmocap run``'s early pass) too, until the mesh changes; then v1 is
    # registered again and, as the placement needs the whole stage, left to it (v2 stays done).
    assert set(stage.run(CFG, work).skipped) == {"register_v1", "register_v2", "refine", "geosync"}
    calls.clear()
    assert stage.run(CFG, work, only_register=True) is None and calls == []
    lay = SessionLayout(work)
    before = json.loads(lay.sequence("seq0").calibrate_manifest.read_text())["steps"]
    mesh = lay.scene("scene0").mesh_raw
    mesh.write_bytes(mesh.read_bytes() + b"\n")  # other content, same mesh for the reader
    stage.run(CFG, work, only_register=True)
    after = json.loads(lay.sequence("seq0").calibrate_manifest.read_text())
    assert calls == ["v1"] and after["status"] == "partial"
    assert after["steps"] == before


def test_geometric_sync_after_registration(session, done):
    """final_sync.json is final and the geometric offset matches the truth (the studio's phones are
    frame-aligned here, and the laser frames are exact, so the residual is 0); Stage II's sync.json
    is left as Stage II wrote it (one writer per file)."""
    import json

    sl = SessionLayout(session).sequence("seq0")
    rec = json.loads(sl.final_sync.read_text())
    assert rec["version"] == 2 and rec["chosen"]["final"]
    assert json.loads(sl.sync.read_text()) == json.loads((session.parent / "sync_stage2.json").read_text())
    assert read_final_sync(sl).record == rec and read_final_sync(sl).residual_s == rec["chosen"]["residual_s"]
    geo = rec["sources"]["geometric"]
    # 2 s after the event the performer is still starting to move: the offset is right, but how
    # sure it is depends on the motion; the choice must follow that confidence.
    assert abs(geo["offset_frames"]) < 0.5, geo
    assert rec["agreement"]["agree"] and abs(rec["chosen"]["residual_frames"]) < 0.5
    assert rec["chosen"]["source"] == ("geometric" if geo["trusted"] else "laser")
    cw = np.load(SessionLayout(session).sequence("seq0").view("v2").cameras_world)
    assert float(cw["time_offset_s"]) == pytest.approx(rec["chosen"]["residual_s"])


def _plain_json(obj):
    """``obj`` as JSON would store it, without timings (they differ between any two runs)."""
    import json

    from embodmocap.io.atomic import _json_default

    def strip(o):
        if isinstance(o, dict):
            return {k: strip(x) for k, x in o.items() if k != "seconds"}
        return [strip(x) for x in o] if isinstance(o, list) else o

    return strip(json.loads(json.dumps(obj, default=_json_default)))


def test_solve_in_memory_gives_the_run_s_files(session, done, tmp_path):
    """Stage III's pure solve, on inputs read into memory from a copy of the session that is then
    deleted (so it can open no file), gives exactly what the run wrote."""
    import json

    from embodmocap.calibrate import solve
    from embodmocap.calibrate.register import load_or_build_scene_index
    from embodmocap.io.captures import open_capture
    from embodmocap.io.manifest import load_manifest
    from embodmocap.io.mesh_file import read_mesh_ply
    from embodmocap.io.stage_files import read_cameras, read_keypoints2d, read_registration, sequence_fps
    from embodmocap.sequence.laser_check import observe_laser_dots

    work = tmp_path / "s"
    shutil.copytree(session, work)
    lay = SessionLayout(work)
    entry = load_manifest(lay.manifest).sequence(None)
    sl = lay.sequence(entry.name)
    views = {}
    for v in VIEWS:
        cams = read_cameras(sl.view(v).cameras)
        depth, masks = np.load(sl.view(v).depth), np.load(sl.view(v).masks)
        cap = open_capture(entry.views[v].capture)
        rgb = [np.asarray(cap.frames.rgb(int(r))) for r in cams.raw_frames]
        w = int(cams.width)
        views[v] = solve.ViewInputs(
            cameras=cams, keypoints=read_keypoints2d(sl.view(v).keypoints).keypoints,
            depth_m=lambda t, d=depth: d[t].astype(np.float32) / 1000.0,
            mask=lambda t, m=masks, w=w: np.unpackbits(m[t], axis=-1, count=w).astype(bool), rgb=lambda t, r=rgb: r[t])
    scene = lay.scene(entry.scene)
    mv, mf, _ = read_mesh_ply(scene.mesh_raw)
    rec = json.loads((session.parent / "sync_stage2.json").read_text())
    inputs = solve.CalibrateInputs(
        sequence=entry.name, scene=entry.scene, views=views,
        index=load_or_build_scene_index(scene.sfm_dir, CFG.register, scene.root / "register_index.npz"),
        mesh_vertices=mv, mesh_faces=mf, sync_record=rec, fps=sequence_fps(sl),
        sources={v: entry.views[v].capture for v in VIEWS},
        contact_sheets={v: str(SessionLayout(session).sequence(entry.name).root / d["contact_sheet"])
                        for v, d in rec["sources"]["laser"]["views"].items() if d.get("contact_sheet")},
        laser_dots=observe_laser_dots(rec, {v: (lambda p=entry.views[v].capture: open_capture(p)) for v in VIEWS}))
    shutil.rmtree(work)  # nothing of the session is left to read
    res = solve.solve(CFG, inputs)

    files = SessionLayout(session).sequence(entry.name)
    for v in VIEWS:
        want = read_registration(files.view(v).registration)
        assert res.registrations[v].files == want.files
        for k in want.files:
            assert np.array_equal(res.registrations[v][k], want[k]), (v, k)
        cw = read_cameras(files.view(v).cameras_world)
        assert res.cameras_world[v].files == cw.files
        for k in cw.files:
            assert np.array_equal(res.cameras_world[v][k], cw[k]), (v, k)
        assert np.array_equal(res.T_world_vio[v], done.T_world_vio[v])
    assert _plain_json(res.report) == _plain_json(json.loads(files.calibration.read_text()))
    assert _plain_json(res.sync_record) == _plain_json(json.loads(files.final_sync.read_text()))


def test_presync_measures_on_the_registration_cameras(session, done, tmp_path):
    """``presync`` with ``sync_cameras = "registration"``: the sub-frame sync measured before the
    refinement is recorded in calibration.json, and step 4's measurement, on the same
    registration-only cameras, is the same one; the session is in phase (the truth's
    ``view_time_offset_frames`` is 0), so both are within half a frame of 0, and the refined view
    offsets stay within the default run's bounds of the truth (4 cm / 0.8 deg)."""
    from embodmocap.io.ground_truth import read_truth_info
    from embodmocap.io.stage_files import read_calibration

    work = tmp_path / "s"
    shutil.copytree(session, work)
    assert read_truth_info(SessionLayout(work).ground_truth.info)["view_time_offset_frames"]["v2"] == 0.0
    out = stage.run(replace(CFG, presync=True, sync_cameras="registration"), work)
    sl = SessionLayout(work).sequence("seq0")
    pre = read_calibration(sl.calibration).record["presync"]
    rec = json.loads(sl.final_sync.read_text())
    assert pre["geometric_offset_frames"] == pytest.approx(rec["sources"]["geometric"]["offset_frames"], abs=1e-4)
    assert abs(pre["residual_frames"]) < 0.5 and abs(rec["chosen"]["residual_frames"]) < 0.5
    assert pre["applied"] == (pre["residual_frames"] != 0.0)
    truth = true_offsets(work)
    for v in VIEWS:
        probe = np.load(sl.view(v).cameras)["T_world_cam"][:, :3, 3]
        cm, deg = offset_error(out.T_world_vio[v], truth[v], probe)
        assert cm < 0.04 and deg < 0.8, (v, cm, deg)


def test_whole_stage_beside_stage_one_s_last_steps_needs_its_mesh_step(session, done, tmp_path):
    """``scene_running`` (``embodmocap run`` starts Stage III after Stage I's ``mesh`` step, beside
    its ``floor`` and ``simplify``): a Stage I still running is accepted once its ``sfm`` and
    ``mesh`` steps are recorded, refused while its mesh is not done or changed since; without the
    flag a running Stage I is refused as before."""
    work = tmp_path / "s"
    shutil.copytree(session, work)
    scene_manifest = SessionLayout(work).scene("scene0").manifest
    data = json.loads(scene_manifest.read_text())
    running = dict(data, status="running")
    scene_manifest.write_text(json.dumps(running))
    with pytest.raises(InputError, match="did not finish its last run \\(running\\)"):
        stage.run(CFG, work)
    out = stage.run(CFG, work, scene_running=True)
    assert set(out.skipped) == {"register_v1", "register_v2", "refine", "geosync"}
    assert json.loads(SessionLayout(work).sequence("seq0").calibrate_manifest.read_text())["status"] == "ok"
    for v in VIEWS:
        np.testing.assert_array_equal(out.T_world_vio[v], done.T_world_vio[v])
    no_mesh = dict(running, steps={k: s for k, s in data["steps"].items() if k not in ("mesh", "floor", "simplify")})
    scene_manifest.write_text(json.dumps(no_mesh))
    with pytest.raises(InputError, match="its mesh step is not done"):
        stage.run(CFG, work, scene_running=True)
    scene_manifest.write_text(json.dumps(running))
    mesh = SessionLayout(work).scene("scene0").mesh_raw
    mesh.write_bytes(mesh.read_bytes() + b"\n")
    with pytest.raises(InputError, match="changed since it was written"):
        stage.run(CFG, work, scene_running=True)
