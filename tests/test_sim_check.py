"""`embodmocap sim check`: plausibility figures recover constructed cases and are small on the
studio's ground-truth motion."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

pytest.importorskip("mujoco")

from embodmocap.sim.check import foot_skating, plausibility  # noqa: E402
from embodmocap.sim.config import SimCheckConfig  # noqa: E402
from embodmocap.sim.session import load_sequence  # noqa: E402
from sim_session import sim_session  # noqa: E402,F401


@pytest.fixture(scope="module")
def truth(sim_session):
    return load_sequence(sim_session)


def _shifted(sq, dz=0.0, dx_per_frame=0.0, static=False):
    p = sq.params
    if static:  # the first frame held for 20 frames
        idx = np.zeros(20, dtype=int)
        p = dataclasses.replace(p, global_orient=p.global_orient[idx], body_pose=p.body_pose[idx], transl=p.transl[idx])
    transl = np.array(p.transl)
    transl[:, 2] += dz
    transl[:, 0] += dx_per_frame * np.arange(len(transl))
    return sq.with_params(dataclasses.replace(p, transl=transl))


def test_truth_is_plausible(truth):
    s = plausibility(truth)["summary"]
    assert s["penetration_max_cm"] < 1.0 and s["floating_max_cm"] < 1.0
    assert s["contact_fraction"]["left_foot"] > 0.5 and s["contact_fraction"]["right_foot"] > 0.5
    assert s["contact_fraction"]["head"] == 0.0
    # Standing and turning on the floor: contact forces explain the motion.
    assert s["residual_force_n_per_kg_mean"] < 0.5


def test_pushed_into_the_floor_and_lifted_are_recovered(truth):
    base = plausibility(truth, residual=False)["per_frame"]
    pushed = plausibility(_shifted(truth, dz=-0.05), residual=False)
    assert abs(pushed["summary"]["penetration_max_cm"] - 5.0) < 0.5
    assert np.allclose(pushed["per_frame"]["penetration_cm"], 5.0 + np.array(base["penetration_cm"]), atol=0.5)
    assert pushed["summary"]["floating_max_cm"] == 0.0
    lifted = plausibility(_shifted(truth, dz=0.05))
    assert np.allclose(lifted["per_frame"]["floating_cm"], 5.0 + np.array(base["floating_cm"]), atol=0.5)
    assert lifted["summary"]["penetration_max_cm"] == 0.0
    assert sum(lifted["summary"]["contact_fraction"].values()) == 0.0
    # In the air nothing holds the body up: the residual is its weight, g per kg.
    assert abs(lifted["summary"]["residual_force_n_per_kg_mean"] - 9.81) < 0.5


def test_sliding_feet_are_recovered(truth):
    still = plausibility(_shifted(truth, static=True), residual=False)["summary"]
    assert still["foot_skating_mean_cm"] < 0.1
    sliding = plausibility(_shifted(truth, static=True, dx_per_frame=0.01), residual=False)["summary"]
    assert abs(sliding["foot_skating_mean_cm"] - 1.0) < 0.5


def test_foot_skating_weights_by_height():
    xy = np.zeros((3, 1, 2))
    xy[:, 0, 0] = [0.0, 0.02, 0.04]
    h = np.array([[0.0], [0.0125], [0.0]])
    H = 0.025
    out = foot_skating(xy, h, H)
    assert np.allclose(out, [0.02, 0.02 * (2 - 2 ** 0.5), 0.0])
    assert np.allclose(foot_skating(xy, np.full((3, 1), 0.03), H), 0.0)


def test_cli_sim_check_writes_the_json(sim_session):
    from embodmocap.cli import main

    assert main(["sim", "check", str(sim_session)]) == 0
    doc = json.loads((sim_session / "sequences" / "seq0" / "sim" / "sim_check.json").read_text())
    assert doc["version"] == 1 and len(doc["per_frame"]["penetration_cm"]) == len(doc["frames"])
    assert set(doc["per_frame"]["contact"]) == set(doc["summary"]["contact_fraction"])


def test_report_has_the_sim_check_section(sim_session):
    from embodmocap.evaluate.report import write_report
    from embodmocap.sim.check import sim_check

    sim_check(sim_session)
    _, md = write_report(sim_session)
    text = md.read_text()
    assert "Physical plausibility (sim check)" in text and "penetration_max_cm" in text


def test_repair_removes_penetration_and_floating(sim_session, tmp_path):
    import shutil

    from embodmocap.cli import main
    from embodmocap.io.amass import read_amass, write_amass

    work = tmp_path / "s"
    shutil.copytree(sim_session, work)
    smpl = work / "sequences" / "seq0" / "smpl_world.npz"
    params, frames = read_amass(smpl)
    transl = np.array(params.transl)
    transl[:, 2] += np.linspace(-0.04, 0.04, len(transl))  # drifting from 4 cm into the floor to 4 cm above
    write_amass(smpl, dataclasses.replace(params, transl=transl), frames=frames)
    assert main(["sim", "check", str(work), "--repair"]) == 0
    doc = json.loads((work / "sequences" / "seq0" / "sim" / "sim_check.json").read_text())
    rep = doc["repair"]
    assert rep["before"]["penetration_max_cm"] > 3.5 and rep["before"]["floating_max_cm"] > 3.5
    assert rep["after"]["penetration_max_cm"] < 1.5 and rep["after"]["floating_max_cm"] < 1.5
    assert 1.5 < rep["shift_mean_cm"] < 3.0 and rep["shift_max_cm"] < 5.0
    fixed, _ = read_amass(work / "sequences" / "seq0" / "sim" / rep["file"])
    assert np.allclose(fixed.body_pose, params.body_pose) and np.allclose(fixed.transl[:, :2], params.transl[:, :2])


def test_sim_check_without_a_fit_names_the_file_and_the_command(sim_session, tmp_path, capsys):
    import shutil

    from embodmocap.cli import main

    work = tmp_path / "nofit"
    shutil.copytree(sim_session, work)
    (work / "sequences" / "seq0" / "smpl_world.npz").unlink()
    assert main(["sim", "check", str(work)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "smpl_world.npz" in err and "embodmocap motion" in err


def test_rerun_and_a_copy_reached_by_a_relative_path_redo_nothing_and_keep_the_bytes(sim_session, tmp_path, monkeypatch,
                                                                                    caplog):
    import logging
    import shutil
    import subprocess

    from embodmocap.cli import main

    work = tmp_path / "s"
    shutil.copytree(sim_session, work, symlinks=True)
    assert main(["sim", "check", str(work)]) == 0
    out = work / "sequences" / "seq0" / "sim" / "sim_check.json"
    first = out.read_bytes()
    man = json.loads((out.parent / "manifest.json").read_text())
    assert man["status"] == "ok" and man["steps"]["check"]["seconds"] > 0
    assert "seconds" not in json.loads(first)["summary"]  # wall time lives in the manifest
    finished = man["steps"]["check"]["finished"]
    subprocess.run(["cp", "-a", str(work), str(tmp_path / "copy")], check=True)
    monkeypatch.chdir(tmp_path)
    for session in (str(work), "copy"):
        assert main(["sim", "check", session]) == 0
    copy_out = tmp_path / "copy" / "sequences" / "seq0" / "sim" / "sim_check.json"
    assert out.read_bytes() == first and copy_out.read_bytes() == first
    for root in (work, tmp_path / "copy"):
        m = json.loads((root / "sequences" / "seq0" / "sim" / "manifest.json").read_text())
        assert m["steps"]["check"]["finished"] == finished  # skipped, not redone
    # A fresh run on an untouched copy gives the same bytes; --force redoes it.
    fresh = tmp_path / "fresh"
    shutil.copytree(sim_session, fresh, symlinks=True)
    shutil.rmtree(fresh / "sequences" / "seq0" / "sim", ignore_errors=True)
    assert main(["sim", "check", str(fresh)]) == 0
    assert (fresh / "sequences" / "seq0" / "sim" / "sim_check.json").read_bytes() == first
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="embodmocap.io.stage_manifest"):
        assert main(["sim", "check", str(work), "--force"]) == 0
    assert "check done in" in caplog.text  # the step ran again


def test_frames_with_no_surface_under_them_are_counted_and_said_plainly(truth, sim_session, tmp_path, capsys):
    """A scene with nothing under the body (its mesh moved 100 m away): every frame is
    unsupported, floating is not measured, and the CLI and the report say so in words."""
    import shutil

    from embodmocap.evaluate.report import write_report
    from embodmocap.sim.check import unsupported_note

    far = dataclasses.replace(truth, scene_vertices=truth.scene_vertices + [100.0, 0.0, 0.0])
    s = plausibility(far, residual=False)["summary"]
    assert s["unsupported_frames"] == s["frames"] == len(truth.params)
    assert s["floating_max_cm"] == 0.0
    assert unsupported_note(s).startswith(f"{s['frames']} of {s['frames']} frames (100 %) have no scene surface")
    assert unsupported_note(plausibility(truth, residual=False)["summary"]) is None

    copy = tmp_path / "session"
    shutil.copytree(sim_session, copy)
    from embodmocap.cli import main

    assert main(["sim", "check", str(copy)]) == 0
    assert "no scene surface" not in capsys.readouterr().out  # the true scene supports every frame
    path = copy / "sequences" / "seq0" / "sim" / "sim_check.json"
    doc = json.loads(path.read_text())
    doc["summary"]["unsupported_frames"] = 3
    path.write_text(json.dumps(doc))
    _, md = write_report(copy)
    assert f"3 of {doc['summary']['frames']} frames" in md.read_text()


def _floor_with_flipped_footprints(sq, cell=0.05, margin=0.03):
    """A 4 m floor at z = 0 around the performer in 5 cm cells (a simplified scan's size), facing
    up except under the feet: every triangle within ``margin`` (horizontally) of a foot vertex in
    any frame faces down (a turned-over patch of ~30 x 15 cm per foot)."""
    from embodmocap.sim.check import BODY_PARTS, _part_of_vertex
    from embodmocap.sim.session import body_vertices

    verts = body_vertices(sq.body_model, sq.params)
    part = _part_of_vertex(sq.body_model)
    feet = np.isin(part, [list(BODY_PARTS).index("left_foot"), list(BODY_PARTS).index("right_foot")])
    foot_xy = verts[:, feet, :2].reshape(-1, 2)
    c = np.round(foot_xy.mean(axis=0) / cell) * cell
    n = int(round(4.0 / cell))
    x, y = np.meshgrid(c[0] - 2.0 + cell * np.arange(n + 1), c[1] - 2.0 + cell * np.arange(n + 1), indexing="ij")
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    f = np.concatenate([np.column_stack([a, a + n + 1, a + 1]), np.column_stack([a + 1, a + n + 1, a + n + 2])])
    from scipy.spatial import cKDTree

    centroid_xy = v[f].mean(axis=1)[:, :2]
    under = np.isfinite(cKDTree(foot_xy).query(centroid_xy, distance_upper_bound=margin)[0])
    f[under] = f[under][:, [0, 2, 1]]
    return v, f, under


def test_a_turned_over_floor_patch_under_the_feet_is_not_solid(truth):
    # A scanned floor with the triangles under the feet facing down: the closest triangle alone
    # says "behind the floor" for every sole vertex above it; the sheet around it says otherwise.
    v, f, under = _floor_with_flipped_footprints(truth)
    assert 20 < under.sum() < 0.05 * len(f)
    floor_truth = truth.__class__(truth.session, truth.name, truth.params, truth.frames, truth.body_model, v, f)
    base = plausibility(floor_truth, residual=False)["per_frame"]
    lifted = plausibility(_shifted(floor_truth, dz=0.05), residual=False)
    assert lifted["summary"]["penetration_max_cm"] == 0.0
    assert np.allclose(lifted["per_frame"]["floating_cm"], 5.0 + np.array(base["floating_cm"]), atol=0.5)
    pushed = plausibility(_shifted(floor_truth, dz=-0.05), residual=False)
    assert np.allclose(pushed["per_frame"]["penetration_cm"], 5.0 + np.array(base["penetration_cm"]), atol=0.5)
    # The closest triangle alone (side_radius_m = 0, the old rule) reads the lifted body as inside.
    alone = SimCheckConfig(side_radius_m=0.0, through_surface=False)
    assert plausibility(_shifted(floor_truth, dz=0.05), alone, residual=False)["summary"]["penetration_max_cm"] > 4.0
    # The entry rule alone reads it right: the feet never went through the floor to get there.
    entry = SimCheckConfig(side_radius_m=0.0)
    assert plausibility(_shifted(floor_truth, dz=0.05), entry, residual=False)["summary"]["penetration_max_cm"] == 0.0


def test_side_of_a_table_top_and_of_a_floor_turned_over_entirely():
    import trimesh

    from embodmocap.sim.check import SceneQuery

    top = trimesh.creation.box(extents=(1.0, 0.6, 0.04))  # closed, faces outwards
    top.apply_translation((0.0, 0.0, 0.72))
    n = 40
    x, y = np.meshgrid(np.linspace(-2, 2, n + 1), np.linspace(-2, 2, n + 1), indexing="ij")
    fv = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    ff = np.concatenate([np.column_stack([a, a + n + 1, a + 1]), np.column_stack([a + 1, a + n + 1, a + n + 2])])
    pts = np.array([[0.1, 0.1, 0.72],   # inside the top, 2 cm from its faces
                    [0.1, 0.1, 0.705],  # 5 mm above its underside (a knee pushed up into it)
                    [0.1, 0.1, 0.66],   # under it
                    [0.1, 0.1, 0.78],   # above it
                    [1.5, 1.5, 0.05],   # above the floor
                    [1.5, 1.5, -0.03]])  # below the floor
    for floor_faces, below_floor_inside in ((ff, True), (ff[:, [0, 2, 1]], False)):
        v = np.concatenate([top.vertices, fv])
        f = np.concatenate([top.faces, floor_faces + len(top.vertices)])
        sd, _ = SceneQuery(v, f, enclosed_m=0.3).signed_distance(pts)
        np.testing.assert_allclose(np.abs(sd), [0.02, 0.005, 0.04, 0.04, 0.05, 0.03], atol=1e-4)
        # The table top reads right either way; a floor turned over entirely (every face looking
        # down) is read as a ceiling with nothing above it: the air above it stays air (and a
        # foot below it is missed: the mesh says nothing is there).
        assert list(sd < 0) == [True, True, False, False, False, below_floor_inside]


def test_a_foot_beside_the_lip_of_a_hole_in_the_scanned_floor_is_not_inside():
    # A scanned floor (y > 0) ends at a hole (y < 0) in a lip rising 2 cm toward the hole, as TSDF
    # surfaces do at their edge. A foot at floor level 20 cm into the hole lies "behind" the tilted
    # lip by the closest-face test; nothing is above it, so it is not inside anything.
    from embodmocap.sim.check import SceneQuery

    n = 20
    x, y = np.meshgrid(np.linspace(-1, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    f = np.concatenate([np.column_stack([a, a + n + 1, a + 1]), np.column_stack([a + 1, a + n + 1, a + n + 2])])
    lip = np.array([[-1, 0, 0], [1, 0, 0], [1, -0.03, 0.0193], [-1, -0.03, 0.0193]], float)
    lf = np.array([[0, 2, 1], [0, 3, 2]]) + len(v)
    v, f = np.concatenate([v, lip]), np.concatenate([f, lf])
    assert (np.cross(*(lip[[2, 1]] - lip[0]))[1:] > 0).all()  # the lip faces up and out, into the hole
    pts = np.array([[0.0, -0.2, 0.0],     # beside the lip, over the hole
                    [0.0, 0.3, -0.03]])   # under the floor
    old, _ = SceneQuery(v, f, side_radius_m=0.0).signed_distance(pts)
    new, _ = SceneQuery(v, f, enclosed_m=0.3).signed_distance(pts)
    assert old[0] < -0.1 and new[0] > 0.1
    assert old[1] == pytest.approx(-0.03, abs=1e-4) and new[1] == pytest.approx(-0.03, abs=1e-4)
