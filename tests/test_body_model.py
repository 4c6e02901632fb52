"""BodyModel: SMPL semantics, skinning, COCO-17 mapping, frame changes and the file loaders."""

from __future__ import annotations

import os
import pickle
import sys
import types

import numpy as np
import pytest
import scipy.sparse
import torch
from scipy.spatial.transform import Rotation

from embodmocap.body.joints import coco17_matrix, smpl_to_coco17, subtree
from embodmocap.body.model import BodyModel, load_body_model, params_for_world_frame
from embodmocap.body.pkl import load_model_arrays
from embodmocap.body.testmodel import make_test_model, write_test_model
from embodmocap.errors import InputError
from embodmocap.geometry.transforms import make_T
from embodmocap.types import COCO17_NAMES, SmplParams


@pytest.fixture(scope="module")
def body() -> BodyModel:
    return load_body_model(None)


def _random_params(T: int, seed: int, scale: float = 0.3) -> SmplParams:
    rng = np.random.default_rng(seed)
    return SmplParams(
        betas=rng.normal(0, 1, 10), global_orient=rng.normal(0, 1.0, (T, 3)),
        body_pose=rng.normal(0, scale, (T, 69)), transl=rng.normal(0, 1.0, (T, 3)),
    )


def _f64(body: BodyModel, p: SmplParams):
    return body.from_params(p, dtype=torch.float64)


def _reference_rigid(body: BodyModel, betas, go, transl):
    """SMPL's root semantics written out: rotate the shaped rest body about J_0, then translate."""
    v_rest = body.v_template + body.arrays["shapedirs"] @ betas
    p = body.pelvis_offset(betas)
    return (v_rest - p) @ Rotation.from_rotvec(go).as_matrix().T + p + transl


def test_rest_pose_is_template(body):
    out = body.forward(np.zeros(10), np.zeros((1, 3)), np.zeros((1, 69)), dtype=torch.float64)
    np.testing.assert_allclose(out.vertices[0].numpy(), body.v_template, atol=1e-12)
    J = body.arrays["J_regressor"] @ body.v_template
    np.testing.assert_allclose(out.joints[0].numpy(), J, atol=1e-12)
    np.testing.assert_allclose(body.rest_joints(), J, atol=1e-12)
    assert out.vertices.dtype == torch.float64
    assert body.forward(np.zeros(10), np.zeros((1, 3)), np.zeros((1, 69))).vertices.dtype == torch.float32


def test_betas_change_height_monotonically(body):
    heights = []
    for b0 in np.linspace(-2, 2, 5):
        betas = np.zeros(10)
        betas[0] = b0
        v = body.forward(betas, np.zeros((1, 3)), np.zeros((1, 69)), dtype=torch.float64).vertices[0].numpy()
        heights.append(np.ptp(v[:, 1]))
    assert np.all(np.diff(heights) > 0.03)


@pytest.mark.parametrize("joint", [18, 4, 12])
def test_joint_rotation_moves_only_its_subtree(body, joint):
    pose = np.zeros((1, 69))
    pose[0, 3 * (joint - 1): 3 * joint] = [0.3, -0.8, 0.5]
    rest = body.forward(np.zeros(10), np.zeros((1, 3)), np.zeros((1, 69)), dtype=torch.float64)
    posed = body.forward(np.zeros(10), np.zeros((1, 3)), pose, dtype=torch.float64)
    moved = np.linalg.norm((posed.vertices - rest.vertices)[0].numpy(), axis=1)
    sub = subtree(joint)
    w_sub = body.lbs_weights[:, sub].sum(axis=1)
    assert np.all(moved[w_sub == 0] < 1e-12)
    assert np.all(moved[w_sub > 0.05] > 1e-4)
    jmoved = np.linalg.norm((posed.joints - rest.joints)[0].numpy(), axis=1)
    assert np.all(jmoved[[j for j in range(24) if j not in sub[1:]]] < 1e-12)  # incl. the joint itself
    assert np.all(jmoved[sub[1:]] > 1e-3)


def test_global_orient_rotates_about_rest_pelvis(body):
    betas = np.linspace(-1, 1, 10)
    transl = np.array([[0.3, -0.2, 1.5]])
    go = np.array([[0.0, np.pi / 2, 0.0]])  # 90 degrees about Y
    out = body.forward(betas, go, np.zeros((1, 69)), transl, dtype=torch.float64)
    pelvis = body.pelvis_offset(betas)
    np.testing.assert_allclose(out.joints[0, 0].numpy(), pelvis + transl[0], atol=1e-12)
    np.testing.assert_allclose(out.vertices[0].numpy(), _reference_rigid(body, betas, go[0], transl[0]), atol=1e-10)
    assert not np.allclose(pelvis, body.pelvis_offset(np.zeros(10)))  # the pivot depends on betas


def test_params_for_world_frame_equals_rigid_motion(body):
    params = _random_params(4, seed=1)
    R = Rotation.from_rotvec([0.4, -1.1, 2.0]).as_matrix()
    T_new_old = make_T(R, [1.0, -2.0, 0.5])
    moved = params_for_world_frame(params, T_new_old, body)
    before, after = _f64(body, params), _f64(body, moved)
    expected = before.vertices.numpy() @ R.T + T_new_old[:3, 3]
    # 1e-7 m: smplx's axis-angle conversion adds 1e-8 to the rotation vector (its guard against a
    # zero angle), so two rotation vectors of one rotation give matrices equal to ~1e-8.
    np.testing.assert_allclose(after.vertices.numpy(), expected, atol=1e-7)
    np.testing.assert_allclose(after.joints.numpy(), before.joints.numpy() @ R.T + T_new_old[:3, 3], atol=1e-7)
    np.testing.assert_array_equal(moved.body_pose, params.body_pose)
    # The method agrees, and going back gives the original parameters.
    back = body.params_for_world_frame(moved, np.linalg.inv(T_new_old))
    np.testing.assert_allclose(_f64(body, back).vertices.numpy(), before.vertices.numpy(), atol=1e-7)
    with pytest.raises(ValueError):
        params_for_world_frame(params, np.diag([2.0, 1.0, 1.0, 1.0]), body)


def test_coco17_left_right_and_hips(body):
    out = body.forward(np.zeros(10), np.zeros((1, 3)), np.zeros((1, 69)), dtype=torch.float64)
    coco, J = out.coco17[0].numpy(), out.joints[0].numpy()
    for k, name in enumerate(COCO17_NAMES):
        if name.startswith("left"):
            assert coco[k, 0] > 0.02, name  # SMPL faces +Z, its left is +X
        elif name.startswith("right"):
            assert coco[k, 0] < -0.02, name
    idx = {n: i for i, n in enumerate(COCO17_NAMES)}
    np.testing.assert_allclose(coco[idx["left_shoulder"]], J[16])
    np.testing.assert_allclose(coco[idx["right_ankle"]], J[8])
    np.testing.assert_allclose(coco[idx["nose"]], out.vertices[0, body.vertex_ids["nose"]].numpy())
    # COCO hips sit lower and further out than SMPL's hip joints, above the knees.
    for name, hip, knee in (("left_hip", 1, 4), ("right_hip", 2, 5)):
        p = coco[idx[name]]
        assert J[knee, 1] < p[1] < J[hip, 1] - 0.03 and abs(p[0]) > abs(J[hip, 0])
    # The numpy path agrees with the torch path; rows are affine (sum to one).
    np.testing.assert_allclose(smpl_to_coco17(J, out.vertices[0].numpy(), body.vertex_ids), coco, atol=1e-12)
    np.testing.assert_allclose(coco17_matrix().sum(axis=1), 1.0)


def test_gradcheck_float64(body):
    torch.manual_seed(0)
    betas = (0.5 * torch.randn(10, dtype=torch.float64)).requires_grad_()
    go = (0.5 * torch.randn(2, 3, dtype=torch.float64)).requires_grad_()
    pose = (0.3 * torch.randn(2, 69, dtype=torch.float64)).requires_grad_()
    transl = torch.randn(2, 3, dtype=torch.float64).requires_grad_()

    def f(b, g, p, t):
        out = body.forward(b, g, p, t)
        return out.vertices, out.joints, out.coco17

    assert torch.autograd.gradcheck(f, (betas, go, pose, transl), fast_mode=True)
    # Exact (slow-mode) check on the joints only: few outputs, so it stays fast.
    assert torch.autograd.gradcheck(lambda b, g, p, t: body.forward(b, g, p, t).joints, (betas, go, pose, transl))


def test_batching_and_inputs(body):
    params = _random_params(3, seed=2)
    out = body.from_params(params)
    assert out.vertices.shape == (3, body.num_vertices, 3) and out.joints.shape == (3, 24, 3)
    assert out.coco17.shape == (3, 17, 3) and out.vertices.dtype == torch.float32
    # Per-frame betas equal shared betas when repeated; fewer betas are zero-padded.
    per_frame = body.forward(np.tile(params.betas, (3, 1)), params.global_orient, params.body_pose, params.transl)
    torch.testing.assert_close(per_frame.vertices, out.vertices)
    short = body.forward(params.betas[:4], params.global_orient, params.body_pose.reshape(3, 23, 3), params.transl,
                         dtype=torch.float64)
    padded = np.concatenate([params.betas[:4], np.zeros(6)])
    full = body.forward(padded, params.global_orient, params.body_pose, params.transl, dtype=torch.float64)
    torch.testing.assert_close(short.vertices, full.vertices)
    with pytest.raises(ValueError):
        body.forward(np.zeros(11), params.global_orient, params.body_pose)
    assert body.forward(np.zeros(10), np.zeros((0, 3)), np.zeros((0, 69))).vertices.shape == (0, body.num_vertices, 3)
    assert load_body_model(None) is body  # cached
    assert body.faces.shape[1] == 3 and len(body.parents) == 24 and body.joint_names[16] == "left_shoulder"



@pytest.mark.parametrize("T", [0, 1, 5, 63, 64, 65, 130, 301])
def test_joints_without_the_mesh_equal_the_skinned_bodys_bit_for_bit(body, T):
    # Stage IV's leg-side pass reads only the start's joints: the same bits as the whole body's,
    # whatever the number of frames (whole SIMD blocks and a tail), betas shorter than the model's too.
    params = _random_params(T, seed=T)
    params = SmplParams(betas=params.betas[:7], global_orient=params.global_orient, body_pose=params.body_pose,
                        transl=params.transl)
    joints = body.joints_from_params(params)
    assert joints.shape == (T, 24, 3) and joints.dtype == torch.float64
    assert torch.equal(joints, _f64(body, params).joints)
    # and not a constant: the joints move with the pose
    if T > 1:
        assert not torch.equal(joints[0], joints[1])


# ------------------------------------------------------------------------------------------ files


def _official_style_dict(model: dict) -> dict:
    """The test model arranged like an official SMPL pickle (uint32 root parent, sparse regressor)."""
    kintree = model["kintree_table"].astype(np.uint32)  # root parent becomes 2**32 - 1
    return {
        "v_template": model["v_template"], "f": model["f"].astype(np.uint32),
        "J_regressor": scipy.sparse.csc_matrix(model["J_regressor"]), "weights": model["weights"],
        "kintree_table": kintree, "posedirs": model["posedirs"], "bs_style": "lbs", "bs_type": "lrotmin",
        "vertex_ids": model["vertex_ids"], "vertex_id_names": model["vertex_id_names"],
    }


@pytest.mark.parametrize("protocol", [0, 2])
def test_pickle_with_chumpy_loads_without_chumpy(tmp_path, protocol):
    model = make_test_model()

    class Ch:  # stands for chumpy.ch.Ch when the pickle is written
        def __init__(self, x):
            self.x = x

        def __getstate__(self):
            return {"x": self.x, "_dirty_vars": set(), "dterms": ("x",)}

    class Expr:  # a chumpy expression: no plain array inside
        def __getstate__(self):
            return {"a": Ch(np.ones(3)), "b": 2.0}

    fake, fake_ch = types.ModuleType("chumpy"), types.ModuleType("chumpy.ch")
    for cls, mod in ((Ch, fake_ch), (Expr, fake_ch)):
        cls.__module__, cls.__qualname__ = mod.__name__, cls.__name__
        setattr(mod, cls.__name__, cls)
    fake.ch = fake_ch
    data = _official_style_dict(model)
    data["shapedirs"] = Ch(model["shapedirs"])
    data["J"] = Expr()
    sys.modules["chumpy"], sys.modules["chumpy.ch"] = fake, fake_ch
    try:
        blob = pickle.dumps(data, protocol=protocol)
    finally:
        del sys.modules["chumpy"], sys.modules["chumpy.ch"]
    assert b"chumpy" in blob and "chumpy" not in sys.modules
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    path.write_bytes(blob)

    arrays = load_model_arrays(path)
    np.testing.assert_array_equal(arrays["shapedirs"], model["shapedirs"])
    np.testing.assert_array_equal(arrays["J_regressor"], model["J_regressor"])
    assert arrays["kintree_table"][0, 0] == -1
    loaded = load_body_model(path)
    assert loaded.gender == "neutral"
    params = _random_params(2, seed=3)
    torch.testing.assert_close(_f64(loaded, params).vertices, _f64(load_body_model(None), params).vertices)


def test_npz_round_trip(tmp_path, body):
    path = write_test_model(tmp_path / "body_model.npz")
    loaded = load_body_model(path)
    params = _random_params(2, seed=4)
    torch.testing.assert_close(_f64(loaded, params).coco17, _f64(body, params).coco17)
    sixteen = load_body_model(write_test_model(tmp_path / "b16.npz", num_betas=16))
    assert sixteen.num_betas == 16  # smplx would keep only 10 of a file's <300 components


def _save(path, arrays):
    np.savez(path, **arrays)
    return path


def test_bad_files_raise_input_error(tmp_path):
    good = make_test_model()
    no_weights = {k: v for k, v in good.items() if k not in ("weights", "posedirs")}
    with pytest.raises(InputError, match=r"weights.*posedirs|posedirs.*weights") as err:
        load_body_model(_save(tmp_path / "missing.npz", no_weights))
    assert "missing.npz" in str(err.value)
    with pytest.raises(InputError, match="shapedirs"):
        load_body_model(_save(tmp_path / "shape.npz", {**good, "shapedirs": good["shapedirs"][:10]}))
    bad_tree = good["kintree_table"].copy()
    bad_tree[0, 5] = 3
    with pytest.raises(InputError, match="kintree_table"):
        load_body_model(_save(tmp_path / "tree.npz", {**good, "kintree_table": bad_tree}))
    with pytest.raises(InputError, match="faces"):
        load_body_model(_save(tmp_path / "faces.npz", {**good, "f": good["f"] + 10**6}))
    (tmp_path / "junk.pkl").write_bytes(b"not a pickle at all")
    with pytest.raises(InputError, match="junk.pkl"):
        load_body_model(tmp_path / "junk.pkl")
    (tmp_path / "list.pkl").write_bytes(pickle.dumps([1, 2, 3]))
    with pytest.raises(InputError, match="not a dict"):
        load_body_model(tmp_path / "list.pkl")
    with pytest.raises(InputError, match="not found"):
        load_body_model(tmp_path / "absent.npz")
    with pytest.raises(InputError, match="unknown body model file type"):
        load_body_model(tmp_path / "model.obj")
    other_topology = {k: v for k, v in good.items() if k not in ("vertex_ids", "vertex_id_names")}
    with pytest.raises(InputError, match="face keypoints"):
        load_body_model(_save(tmp_path / "noids.npz", other_topology))


def test_pickle_refuses_foreign_globals(tmp_path):
    class Evil:
        def __reduce__(self):
            return (os.system, ("echo should-not-run",))

    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"v_template": Evil()}))
    with pytest.raises(InputError, match="refusing to load"):
        load_body_model(path)
