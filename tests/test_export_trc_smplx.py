"""The OpenSim .trc and SMPL-X npz exports, each read back by an independent reader: a .trc
parser written here from the format's description (checked against the .trc files Pose2Sim
writes), and numpy plus the ``smplx`` package's own joint names for the SMPL-X file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from embodmocap.body.joints import SMPL_JOINT_NAMES
from embodmocap.cli import main
from embodmocap.export import export_sequence, write_smplx, write_trc
from embodmocap.io.layout import SessionLayout
from test_export import FPS, R_YUP, _forward, model, params, session  # noqa: F401 - fixtures

POSE2SIM_TRC = sorted(Path("/work/shared/data/pose2sim_demo/pose-3d").glob("*.trc"))


def read_trc(path: Path) -> dict:
    """A .trc reader from the format's description: line 1 the path type, line 2 the header keys,
    line 3 their values, line 4 ``Frame#``, ``Time`` and each marker name over its 3 columns, line 5
    the ``X<n> Y<n> Z<n>`` labels, then one row per frame (blank lines skipped)."""
    lines = Path(path).read_text().split("\n")
    head = dict(zip(lines[1].rstrip("\r").split("\t"), lines[2].rstrip("\r").split("\t")))
    names_row = lines[3].rstrip("\r").split("\t")
    assert names_row[:2] == ["Frame#", "Time"]
    cells = names_row[2:]
    markers = [c for c in cells[::3]]
    assert all(c == "" for i, c in enumerate(cells) if i % 3), "each name must be followed by two empty fields"
    labels = lines[4].rstrip("\r").split("\t")
    rows = [ln.rstrip("\r").split("\t") for ln in lines[5:] if ln.strip()]
    data = np.array([[float(x) if x else np.nan for x in r] for r in rows])
    return {"line1": lines[0].split("\t"), "keys": lines[1].rstrip("\r").split("\t"), "head": head,
            "markers": markers, "labels": labels, "first_data_line": next(i for i in range(5, len(lines)) if lines[i].strip()),
            "frame": data[:, 0], "time": data[:, 1], "xyz": data[:, 2:].reshape(len(data), -1, 3)}


def test_trc_reads_back_y_up_with_the_header_pose2sim_writes(tmp_path, model, params):  # noqa: F811
    _, joints = _forward(model, params)
    frames = np.arange(40, 48)
    path = write_trc(tmp_path / "walk.trc", joints, FPS, frames)
    trc = read_trc(path)
    assert trc["line1"] == ["PathFileType", "4", "(X/Y/Z)", "walk.trc"]
    assert trc["markers"] == list(SMPL_JOINT_NAMES)
    assert trc["labels"][:2] == ["", ""] and trc["labels"][2:5] == ["X1", "Y1", "Z1"] and trc["labels"][-1] == "Z24"
    h = trc["head"]
    assert float(h["DataRate"]) == float(h["CameraRate"]) == FPS and h["Units"] == "m"
    assert int(h["NumFrames"]) == len(params) and int(h["NumMarkers"]) == 24 and int(h["OrigDataStartFrame"]) == 40
    np.testing.assert_array_equal(trc["frame"], np.arange(1, len(params) + 1))
    np.testing.assert_allclose(trc["time"], frames / FPS, atol=1e-6)
    # Y up: our world height (z) is the file's Y, and the whole change is one rotation.
    np.testing.assert_allclose(trc["xyz"][..., 1], joints[..., 2], atol=1e-6)
    np.testing.assert_allclose(trc["xyz"], joints @ R_YUP.T, atol=1e-6)
    assert np.linalg.det(R_YUP) == pytest.approx(1.0)


@pytest.mark.skipif(not POSE2SIM_TRC, reason="Pose2Sim demo data not in /work/shared/data")
def test_trc_header_matches_the_files_pose2sim_writes(tmp_path, model, params):  # noqa: F811
    _, joints = _forward(model, params)
    ours = read_trc(write_trc(tmp_path / "ours.trc", joints, FPS))
    for ref_path in POSE2SIM_TRC:
        ref = read_trc(ref_path)
        assert ours["line1"][0] == ref["line1"][0].split()[0] == "PathFileType"
        assert ours["keys"] == ref["keys"], ref_path.name
        assert ours["head"]["Units"] == ref["head"]["Units"] == "m"
        assert ours["labels"][:5] == ref["labels"][:5]
        assert ref["xyz"].shape[1] == int(ref["head"]["NumMarkers"])
        assert ours["xyz"].shape[1] == int(ours["head"]["NumMarkers"])
    # Pose2Sim's own files (the ones written by its triangulation) start their data right after the
    # labels line, as ours do; the header values line is numbers, then "m".
    first = read_trc(POSE2SIM_TRC[0])
    assert first["first_data_line"] == ours["first_data_line"] == 5
    # Their world is Y up too: the hips are the highest of the hip/knee/ankle markers on Y.
    names = first["markers"]
    y = np.nanmean(first["xyz"][..., 1], axis=0)
    assert y[names.index("RHip")] > y[names.index("RKnee")] > y[names.index("RAnkle")]
    ours_y = np.mean(ours["xyz"][..., 1], axis=0)
    assert ours_y[SMPL_JOINT_NAMES.index("right_hip")] > ours_y[SMPL_JOINT_NAMES.index("right_knee")] \
        > ours_y[SMPL_JOINT_NAMES.index("right_ankle")]


def test_smplx_npz_reads_back_with_numpy_and_smplx_joint_names(tmp_path, params):  # noqa: F811
    smplx = pytest.importorskip("smplx")
    from smplx.joint_names import JOINT_NAMES

    valid = np.ones(len(params), bool)
    valid[3] = False
    path = write_smplx(tmp_path / "m.npz", params, frames=np.arange(10, 18), valid=valid)
    data = np.load(path)
    T, nb, nh = len(params), smplx.SMPLX.NUM_BODY_JOINTS, smplx.SMPLX.NUM_HAND_JOINTS
    assert data["body_pose"].shape == (T, 3 * nb) and data["left_hand_pose"].shape == (T, 3 * nh)
    assert data["right_hand_pose"].shape == (T, 3 * nh) and data["jaw_pose"].shape == (T, 3)
    assert data["leye_pose"].shape == data["reye_pose"].shape == (T, 3)
    # SMPL-X's body joints 1..21 by name are SMPL's joints 1..21: the pose is copied joint by joint.
    smpl = params.poses.reshape(T, 24, 3)
    for j in range(1, nb + 1):
        k = SMPL_JOINT_NAMES.index(JOINT_NAMES[j])
        np.testing.assert_array_equal(data["body_pose"].reshape(T, nb, 3)[:, j - 1], smpl[:, k])
    np.testing.assert_array_equal(data["global_orient"], params.global_orient)
    for key in ("jaw_pose", "leye_pose", "reye_pose", "left_hand_pose", "right_hand_pose"):
        assert not data[key].any(), key
    np.testing.assert_array_equal(data["transl"], params.transl)
    np.testing.assert_array_equal(data["betas"], params.betas)
    assert int(data["num_betas"]) == len(params.betas)
    assert str(data["gender"]) == "neutral" and float(data["mocap_frame_rate"]) == FPS
    # AMASS's SMPL-X layout: root 3, body 63, jaw 3, eyes 6, hands 90.
    assert data["poses"].shape == (T, 165)
    np.testing.assert_array_equal(data["poses"][:, 3:66], data["body_pose"])
    assert not data["poses"][:, 66:].any()
    np.testing.assert_array_equal(data["valid"], valid)
    np.testing.assert_array_equal(data["frames"], np.arange(10, 18))


def test_cli_exports_trc_and_smplx_of_a_session(session, params):  # noqa: F811
    lay = SessionLayout(session)
    assert main(["export", str(session), "--to", "trc"]) == 0
    assert main(["export", str(session), "--to", "smplx"]) == 0
    trc = read_trc(lay.sequence("seq0").exports_dir / "seq0.trc")
    joints = np.load(lay.sequence("seq0").joints_world)["joints"]
    np.testing.assert_allclose(trc["xyz"], joints @ R_YUP.T, atol=1e-6)
    data = np.load(lay.sequence("seq0").exports_dir / "seq0_smplx.npz")
    np.testing.assert_allclose(data["body_pose"], params.body_pose[:, :63])
    assert data["valid"].all()  # the fixture's smpl_world has no valid key: every frame valid
    out = export_sequence(session, "seq0", "trc", session / "elsewhere" / "x.trc")
    assert out.is_file()


def test_smplx_and_trc_carry_the_suspect_flags(tmp_path, params, caplog):  # noqa: F811
    suspect = np.zeros(len(params), bool)
    suspect[[2, 5]] = True
    data = np.load(write_smplx(tmp_path / "m.npz", params, suspect=suspect))
    np.testing.assert_array_equal(data["suspect"], suspect)
    assert not np.load(write_smplx(tmp_path / "n.npz", params))["suspect"].any()  # not given: none suspect
    with pytest.raises(ValueError, match="suspect"):
        write_smplx(tmp_path / "bad.npz", params, suspect=suspect[:-1])
    joints = np.zeros((len(params), 24, 3))
    with caplog.at_level("WARNING"):
        write_trc(tmp_path / "w.trc", joints, FPS, suspect=suspect)
    assert "2 of 8 frames are suspect" in caplog.text
