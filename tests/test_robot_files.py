"""The files of `embodmocap robot retarget` on a tiny synthetic session, read back independently."""

from __future__ import annotations

import csv
import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip("mink")
mujoco = pytest.importorskip("mujoco")

from embodmocap.cli import main  # noqa: E402
from embodmocap.robot.config import RetargetConfig  # noqa: E402
from embodmocap.robot.stage import retarget_sequence  # noqa: E402
from stage4_session import make_stage4_session  # noqa: E402
from test_robot import MJLAB_G1_JOINTS  # noqa: E402


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("robot") / "session"
    make_stage4_session(root)
    return root


@pytest.fixture(scope="module")
def out(session) -> Path:
    return retarget_sequence(session)


@pytest.fixture(scope="module")
def mj_model(out):
    from embodmocap.robot.g1 import G1
    from embodmocap.robot.model import resolve_mjcf

    return mujoco.MjModel.from_xml_path(str(resolve_mjcf(G1)))


def test_outputs_exist_where_the_issue_says(session, out):
    assert out == session / "sequences" / "seq0" / "robot" / "g1"
    for name in ("qpos.npz", "motion.csv", "motion.npz", "motion_gmr.pkl", "scene.obj", "scene.xml", "robot_report.json"):
        assert (out / name).is_file(), name
    assert not (out / "qpos_partial.npz").exists()


def test_csv_has_exactly_the_columns_csv_to_npz_reads(out):
    with np.load(out / "qpos.npz") as z:
        root_pos, quat, joints, names = z["root_pos"], z["root_quat_wxyz"], z["joint_pos"], list(z["joint_names"])
        fps = float(z["fps"])
    assert fps == 10.0
    rows = [[float(x) for x in r] for r in csv.reader((out / "motion.csv").open())]
    data = np.array(rows)
    assert data.shape == (len(root_pos), 7 + 29)  # no header line: np.loadtxt reads every line
    np.testing.assert_allclose(data[:, :3], root_pos, atol=1e-8)
    np.testing.assert_allclose(data[:, 3:7], quat[:, [1, 2, 3, 0]], atol=1e-8)  # x y z w
    order = [names.index(j) for j in MJLAB_G1_JOINTS]
    np.testing.assert_allclose(data[:, 7:], joints[:, order], atol=1e-8)
    np.testing.assert_allclose(np.linalg.norm(quat, axis=1), 1.0, atol=1e-12)


def test_tracking_npz_round_trips_through_mujoco_forward_kinematics(out, mj_model):
    with np.load(out / "motion.npz") as z:
        a = {k: z[k] for k in z.files}
    with np.load(out / "qpos.npz") as z:
        T, fps = len(z["root_pos"]), float(z["fps"])
    N = len(np.arange(0.0, (T - 1) / fps, 1 / 50.0))  # csv_to_npz's frames at its default 50 fps
    assert a["fps"].tolist() == [50.0]
    B = mj_model.nbody - 1
    assert a["joint_pos"].shape == (N, 29) and a["joint_vel"].shape == (N, 29)
    for k in ("body_pos_w", "body_lin_vel_w", "body_ang_vel_w"):
        assert a[k].shape == (N, B, 3), k
    assert a["body_quat_w"].shape == (N, B, 4)
    np.testing.assert_allclose(np.linalg.norm(a["body_quat_w"], axis=-1), 1.0, atol=1e-9)
    d = mujoco.MjData(mj_model)
    for t in range(N):
        d.qpos[:3] = a["body_pos_w"][t, 0]
        d.qpos[3:7] = a["body_quat_w"][t, 0]
        d.qpos[7:] = a["joint_pos"][t]
        mujoco.mj_kinematics(mj_model, d)
        np.testing.assert_allclose(d.xpos[1:], a["body_pos_w"][t], atol=1e-6)
        dots = np.abs(np.sum(d.xquat[1:] * a["body_quat_w"][t], axis=-1))
        np.testing.assert_allclose(dots, 1.0, atol=1e-6)
    # Body velocities agree with finite differences of the poses (the 10 fps motion is interpolated
    # linearly to 50 fps, so they differ only at the kinks between input frames).
    fd = np.gradient(a["body_pos_w"], 1 / 50.0, axis=0)
    assert np.median(np.abs(fd[2:-2] - a["body_lin_vel_w"][2:-2])) < 1e-3
    R = Rotation.from_quat(a["body_quat_w"][..., [1, 2, 3, 0]].reshape(-1, 4)).as_matrix().reshape(N, B, 3, 3)
    rel = np.einsum("tbij,tbkj->tbik", R[2:], R[:-2]).reshape(-1, 3, 3)
    w = Rotation.from_matrix(rel).as_rotvec().reshape(N - 2, B, 3) / (2 / 50.0)
    assert np.median(np.abs(w - a["body_ang_vel_w"][1:-1])) < 1e-3
    np.testing.assert_allclose(a["body_lin_vel_w"][:, 0], np.gradient(a["body_pos_w"][:, 0], 1 / 50.0, axis=0), atol=1e-9)
    np.testing.assert_allclose(a["joint_vel"], np.gradient(a["joint_pos"], 1 / 50.0, axis=0), atol=1e-9)


def test_gmr_pickle_and_scene_mjcf(out, mj_model):
    with open(out / "motion_gmr.pkl", "rb") as f:
        g = pickle.load(f)
    assert set(g) == {"fps", "root_pos", "root_rot", "dof_pos", "local_body_pos", "link_body_list"}
    with np.load(out / "qpos.npz") as z:
        np.testing.assert_allclose(g["root_rot"], z["root_quat_wxyz"][:, [1, 2, 3, 0]])
        np.testing.assert_allclose(g["dof_pos"], z["joint_pos"])
    world = g["root_pos"][:, None] + np.einsum("tab,tnb->tna", Rotation.from_quat(g["root_rot"]).as_matrix(), g["local_body_pos"])
    d = mujoco.MjData(mj_model)
    d.qpos[:3], d.qpos[3:7], d.qpos[7:] = g["root_pos"][0], g["root_rot"][0, [3, 0, 1, 2]], g["dof_pos"][0]
    mujoco.mj_kinematics(mj_model, d)
    np.testing.assert_allclose(world[0], d.xpos[1:], atol=1e-9)
    assert g["link_body_list"][0] == "pelvis"

    scene = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    assert scene.nhfield == 1 and scene.nkey == 1 and scene.nmesh >= 1
    np.testing.assert_allclose(scene.key_qpos[0][:3], g["root_pos"][0], atol=1e-5)  # MJCF text: 6 digits
    # The scene's height field is under the robot's soles at the first frame: no foot deeper than
    # 1 cm in it, and lowering the robot by 3 cm makes it touch.
    hf = [i for i in range(scene.ngeom) if scene.geom_type[i] == mujoco.mjtGeom.mjGEOM_HFIELD]
    sd = mujoco.MjData(scene)

    def ground_contacts(dz):
        mujoco.mj_resetDataKeyframe(scene, sd, 0)
        sd.qpos[2] -= dz
        mujoco.mj_forward(scene, sd)
        return [sd.contact.dist[i] for i in range(sd.ncon) if set(sd.contact.geom[i]) & set(hf)]

    assert all(d > -0.011 for d in ground_contacts(0.0))
    assert len(ground_contacts(0.03)) > 0


def test_report_keys_and_figures(out):
    rep = json.loads((out / "robot_report.json").read_text())
    assert rep["joint_limit_violations"] == 0
    assert 0 < rep["keypoint_residual_mean_m"] <= rep["keypoint_residual_max_m"]
    assert rep["foot_penetration_max_m"] <= 0.01
    assert set(rep["joint_speed_peak_rad_s"]) == set(MJLAB_G1_JOINTS)
    assert rep["joint_speed_over_limit_joints"] == 0


def test_rerun_skips_and_an_interrupted_run_resumes_to_the_same_motion(session, out, tmp_path, monkeypatch):
    import embodmocap.robot.retarget as rt

    with np.load(out / "qpos.npz") as z:
        full = z["root_pos"].copy(), z["joint_pos"].copy()
    assert main(["export", str(session), "--to", "robot"]) == 0  # same as `robot retarget`: all skipped
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["status"] == "ok" and set(manifest["steps"]) == {"retarget", "export", "report"}

    real = rt.track
    cfg = RetargetConfig(checkpoint_frames=5)

    def interrupted_track(*args, progress=None, **kw):
        def stop(t, q):
            progress(t, q)
            if t == 8:
                raise KeyboardInterrupt
        return real(*args, progress=stop, **kw)

    other = tmp_path / "g1"
    monkeypatch.setattr(rt, "track", interrupted_track)
    with pytest.raises(KeyboardInterrupt):
        retarget_sequence(session, config=cfg, out=other)
    assert (other / "qpos_partial.npz").is_file()
    with np.load(other / "qpos_partial.npz") as z:
        assert len(z["qpos"]) == 5
    assert json.loads((other / "manifest.json").read_text())["status"] == "interrupted"
    starts = []

    def watching_track(*args, start_frame=0, **kw):
        starts.append(start_frame)
        return real(*args, start_frame=start_frame, **kw)

    monkeypatch.setattr(rt, "track", watching_track)
    retarget_sequence(session, config=cfg, out=other)
    assert starts == [5]
    with np.load(other / "qpos.npz") as z:
        np.testing.assert_allclose(z["root_pos"], full[0], atol=1e-9)
        np.testing.assert_allclose(z["joint_pos"], full[1], atol=1e-9)
    shutil.rmtree(other)


def test_missing_motion_is_one_clear_error(tmp_path, session):
    from embodmocap.errors import InputError

    copy = tmp_path / "s"
    shutil.copytree(session, copy)
    (copy / "sequences" / "seq0" / "smpl_world.npz").unlink()
    with pytest.raises(InputError, match="smpl_world.npz: missing world SMPL motion.*embodmocap motion"):
        retarget_sequence(copy)


def test_html_report_has_a_robot_section(out, tmp_path):
    from embodmocap.evaluate.report import _Page, _robot_tables

    page = _Page(tmp_path, [], [])
    _robot_tables(page, out.parent)
    html = "".join(page.html_parts)
    rep = json.loads((out / "robot_report.json").read_text())
    assert "<h3>Robot g1</h3>" in html and "joint-limit violations" in html
    assert f"{rep['keypoint_residual_mean_m']:.4g}" in html


def test_viewer_shows_the_robot_layer(session, out):
    pytest.importorskip("viser")
    import socket

    from embodmocap.viz.viewer import ViewerConfig, serve

    def port():
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            return s.getsockname()[1]

    handle = serve(session, "seq0", ViewerConfig(port=port(), max_image_side=0, robot_offset_m=(1.0, 0.0, 0.0)))
    try:
        nodes = list(handle.nodes["robot"].values())
        assert len(nodes) == len(handle.robot.meshes) > 20  # the G1's visual meshes
        handle.set_frame(5)
        # The first mesh is the pelvis's: where MuJoCo puts its geom at row 5, 1 m to the side.
        with np.load(out / "qpos.npz") as z:
            root5 = z["root_pos"][5]
        assert np.linalg.norm(np.asarray(nodes[0].position) - (root5 + [1.0, 0, 0])) < 0.1
        np.testing.assert_allclose(nodes[0].position, handle.robot.pos[5, 0] + [1.0, 0, 0], atol=1e-6)
    finally:
        handle.stop()
    handle = serve(session, "seq0", ViewerConfig(port=port(), max_image_side=0, robot="none"))
    try:
        assert "robot" not in handle.nodes
    finally:
        handle.stop()


def test_cli_retargets_to_a_robot_given_by_a_toml_file(session, out, tmp_path):
    """A user's robot is a TOML file: here the G1 renamed, with its MJCF path written out in full."""
    from dataclasses import replace

    from embodmocap.robot.config import robot_config_to_toml
    from embodmocap.robot.g1 import G1
    from embodmocap.robot.model import resolve_mjcf

    toml = tmp_path / "my_robot.toml"
    toml.write_text(robot_config_to_toml(replace(G1, name="my_g1", mjcf=str(resolve_mjcf(G1)))))
    assert main(["robot", "retarget", str(session), "--seq", "seq0", "--robot-config", str(toml)]) == 0
    mine = session / "sequences" / "seq0" / "robot" / "my_g1"
    with np.load(mine / "qpos.npz") as a, np.load(out / "qpos.npz") as b:
        assert str(a["robot"]) == "my_g1"
        np.testing.assert_allclose(a["joint_pos"], b["joint_pos"], atol=1e-9)  # the same robot, the same motion
    assert main(["robot", "retarget", str(session), "--robot", "h1"]) == 2  # unknown built-in: one error line
    shutil.rmtree(mine)
