"""The generated body model: layout, skeleton, surface, skinning weights and shape directions."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import trimesh

from embodmocap.body.joints import FACE_KEYPOINT_NAMES, SMPL_JOINT_NAMES, SMPL_PARENTS
from embodmocap.body.pkl import load_model_arrays
from embodmocap.body.testmodel import _design_skeleton, make_test_model, make_test_model_cli, write_test_model


@pytest.fixture(scope="module")
def model() -> dict[str, np.ndarray]:
    return make_test_model(seed=0)


def test_layout_matches_smpl_files(model):
    V = len(model["v_template"])
    assert 2000 <= V <= 8000
    assert model["f"].shape[1] == 3 and model["f"].dtype == np.int64
    assert model["f"].min() == 0 and model["f"].max() == V - 1  # every vertex used
    assert model["J_regressor"].shape == (24, V)
    assert model["weights"].shape == (V, 24)
    assert model["kintree_table"].shape == (2, 24)
    assert tuple(model["kintree_table"][0]) == SMPL_PARENTS
    assert model["shapedirs"].shape == (V, 3, 10)
    assert model["posedirs"].shape == (V, 3, 207)
    assert tuple(model["joint_names"]) == SMPL_JOINT_NAMES
    assert tuple(model["vertex_id_names"]) == FACE_KEYPOINT_NAMES
    assert make_test_model(num_betas=16)["shapedirs"].shape == (V, 3, 16)


def test_deterministic_per_seed(model):
    again = make_test_model(seed=0)
    for k in model:
        np.testing.assert_array_equal(model[k], again[k])
    other = make_test_model(seed=3)
    assert not np.allclose(other["v_template"], model["v_template"])


@pytest.mark.parametrize("seed", [0, 7])
def test_regressor_reproduces_designed_skeleton(seed):
    m = make_test_model(seed=seed)
    Jr = m["J_regressor"]
    assert np.all(Jr >= 0) and np.allclose(Jr.sum(axis=1), 1.0)
    designed = _design_skeleton(np.random.default_rng(seed))
    np.testing.assert_allclose(Jr @ m["v_template"], designed, atol=1e-12)


def test_canonical_frame_and_proportions(model):
    v = model["v_template"]
    J = model["J_regressor"] @ v
    height = np.ptp(v[:, 1])  # Y up
    assert 1.6 < height < 1.8
    assert np.linalg.norm(J[0]) < 0.3  # pelvis near the origin
    assert v[:, 1].argmax() in np.nonzero(model["part_ids"] == list(model["part_names"]).index("head"))[0]
    # Left on +X, mirror symmetric, facing +Z (nose ahead of the head joint, toes ahead of ankles).
    left = [i for i, n in enumerate(SMPL_JOINT_NAMES) if n.startswith("left")]
    assert np.all(J[left, 0] > 0)
    np.testing.assert_allclose(J[[i + 1 for i in left], 0], -J[left, 0], atol=1e-12)
    ids = dict(zip(model["vertex_id_names"], model["vertex_ids"]))
    assert v[ids["nose"], 2] > J[15, 2] + 0.05 and abs(v[ids["nose"], 0]) < 1e-9
    assert v[ids["leye"], 0] > 0 > v[ids["reye"], 0] and v[ids["lear"], 0] > 0 > v[ids["rear"], 0]
    assert J[10, 2] > J[7, 2] + 0.05
    # Limb lengths of an adult (metres).
    arm = np.linalg.norm(J[20] - J[16])
    leg = np.linalg.norm(J[7] - J[1])
    assert 0.45 < arm < 0.6 and 0.7 < leg < 0.9


def test_surface_closed_with_outward_normals(model):
    v, f, part = model["v_template"], model["f"], model["part_ids"]
    for i, name in enumerate(model["part_names"]):
        faces = f[np.all(part[f] == i, axis=1)]
        mesh = trimesh.Trimesh(v, faces, process=False)
        assert mesh.is_watertight and mesh.is_winding_consistent, name
        assert mesh.volume > 1e-4, name  # positive signed volume: normals point outward
    # A ray from in front of the chest hits a face whose normal points back at it.
    whole = trimesh.Trimesh(v, f, process=False)
    loc, _, tri = whole.ray.intersects_location([[0.0, 0.1, 2.0]], [[0.0, 0.0, -1.0]])
    first = tri[np.argmax(loc[:, 2])]
    assert whole.face_normals[first] @ [0.0, 0.0, -1.0] < -0.9


def test_weights_smooth_and_local(model):
    w = model["weights"]
    assert np.all(w >= 0) and np.allclose(w.sum(axis=1), 1.0)
    # Each vertex is influenced by at most two joints, and only by a joint and its parent.
    assert (w > 0).sum(axis=1).max() <= 2
    for j, k in zip(*np.nonzero(np.triu((w > 0).T.astype(int) @ (w > 0).astype(int), 1))):
        assert SMPL_PARENTS[k] == j or SMPL_PARENTS[j] == k, (j, k)
    # Blending: the elbow has vertices weighted half and half between shoulder and elbow.
    both = (w[:, 16] > 0.3) & (w[:, 18] > 0.3)
    assert both.sum() >= 20


def test_shape_directions(model):
    v, sd, Jr = model["v_template"], model["shapedirs"], model["J_regressor"]

    def shaped(k, amount):
        return v + sd[:, :, k] * amount

    heights = [np.ptp(shaped(0, b)[:, 1]) for b in (-2, -1, 0, 1, 2)]
    assert np.all(np.diff(heights) > 0.03)  # first component ~ height, several cm per unit
    # Girth: thigh cross-section grows, joints stay.
    thigh = model["part_ids"] == list(model["part_names"]).index("left_thigh")
    J = Jr @ v
    radius = lambda x: np.linalg.norm(x[thigh][:, [0, 2]] - J[1, [0, 2]], axis=1).mean()  # noqa: E731
    assert radius(shaped(1, 2)) > radius(v) * 1.15
    np.testing.assert_allclose(Jr @ shaped(1, 2), J, atol=1e-12)
    # Leg length: the ankles go down, the neck does not move.
    J_legs = Jr @ shaped(2, 2)
    assert J_legs[7, 1] < J[7, 1] - 0.05 and abs(J_legs[12, 1] - J[12, 1]) < 1e-12
    # Arm length: wrists go out.
    J_arms = Jr @ shaped(3, 2)
    assert J_arms[20, 0] > J[20, 0] + 0.03 and J_arms[21, 0] < J[21, 0] - 0.03


def test_write_and_cli_round_trip(tmp_path, model, caplog):
    p = write_test_model(tmp_path / "m.npz")
    loaded = load_model_arrays(p)
    for k in ("v_template", "f", "J_regressor", "weights", "shapedirs", "vertex_ids"):
        np.testing.assert_array_equal(loaded[k], model[k])
    with caplog.at_level(logging.INFO, logger="embodmocap.body.testmodel"):
        make_test_model_cli(tmp_path / "sub" / "cli.npz", seed=0)
    assert "cli.npz" in caplog.text and f"{len(model['v_template'])} vertices" in caplog.text
    assert not list((tmp_path / "sub").glob(".*"))  # no temporary left behind
    np.testing.assert_array_equal(load_model_arrays(tmp_path / "sub" / "cli.npz")["v_template"], model["v_template"])
