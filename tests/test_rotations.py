"""The rotation module against SciPy's Rotation/Slerp (and MuJoCo's own conversion where installed)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from embodmocap.geometry import rotations as rot

RNG = np.random.default_rng(7)


def _quats(*shape: int) -> np.ndarray:
    """Random non-unit quaternions (x, y, z, w) of any batch shape."""
    return RNG.normal(size=shape + (4,)) * RNG.uniform(0.5, 2.0, size=shape + (1,))


def test_conversions_match_scipy_on_any_batch_shape():
    q = _quats(3, 5)
    R = rot.quat_to_matrix(q)
    assert R.shape == (3, 5, 3, 3)
    np.testing.assert_allclose(R, Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(3, 5, 3, 3), atol=1e-14)
    qb = rot.matrix_to_quat(R)
    assert qb.shape == (3, 5, 4) and np.all(qb[..., 3] >= 0)
    np.testing.assert_allclose(np.abs(np.sum(qb * q / np.linalg.norm(q, axis=-1, keepdims=True), -1)), 1.0, atol=1e-12)
    v = rot.quat_to_rotvec(q)
    np.testing.assert_allclose(v, Rotation.from_quat(q.reshape(-1, 4)).as_rotvec().reshape(3, 5, 3), atol=1e-14)
    assert np.all(np.linalg.norm(v, axis=-1) <= np.pi + 1e-12)  # the shorter turn
    np.testing.assert_allclose(rot.rotvec_to_matrix(v), R, atol=1e-12)
    np.testing.assert_allclose(rot.matrix_to_rotvec(R), v, atol=1e-10)
    np.testing.assert_allclose(rot.quat_to_matrix(rot.rotvec_to_quat(v)), R, atol=1e-12)
    assert rot.quat_to_matrix(q[0, 0]).shape == (3, 3) and rot.rotvec_to_matrix(np.zeros((0, 3))).shape == (0, 3, 3)


def test_bad_quaternions_raise_or_become_nan():
    with pytest.raises(ValueError, match="zero-length"):
        rot.quat_to_matrix(np.zeros(4))
    q = np.array([[0.0, 0, 0, 1], [0, 0, 0, 0], [np.nan, 0, 0, 1]])
    R = rot.quat_to_matrix(q, invalid="nan")
    np.testing.assert_allclose(R[0], np.eye(3))
    assert np.all(np.isnan(R[1:]))


def test_product_conjugate_and_component_order():
    a, b = _quats(6), _quats(6)
    ab = rot.quat_mul(a, b)
    ref = Rotation.from_quat(a) * Rotation.from_quat(b)
    np.testing.assert_allclose(rot.quat_to_matrix(ab), ref.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(rot.quat_to_matrix(rot.quat_conj(a)), Rotation.from_quat(a).inv().as_matrix(), atol=1e-12)
    assert np.allclose(rot.quat_mul(a[0], b).shape, (6, 4))  # broadcast
    w = rot.xyzw_to_wxyz(a)
    np.testing.assert_array_equal(w[:, 0], a[:, 3])
    np.testing.assert_array_equal(rot.wxyz_to_xyzw(w), a)
    assert np.all(rot.canonical_quat(-np.abs(a))[:, 3] >= 0)


def test_wxyz_conversion_agrees_with_mujoco():
    mujoco = pytest.importorskip("mujoco")
    R = Rotation.from_quat(_quats(4)).as_matrix()
    for Ri in R:
        q = np.zeros(4)
        mujoco.mju_mat2Quat(q, Ri.ravel())
        ours = rot.xyzw_to_wxyz(rot.matrix_to_quat(Ri))
        assert np.allclose(ours, q, atol=1e-12) or np.allclose(ours, -q, atol=1e-12)


def test_slerp_matches_scipy_and_takes_the_shorter_arc():
    q0, q1 = _quats(20), _quats(20)
    w = RNG.uniform(0, 1, 20)
    out = rot.slerp(q0, q1, w)
    for k in range(20):
        ref = Slerp([0.0, 1.0], Rotation.from_quat(np.stack([q0[k], q1[k]])))([w[k]])
        np.testing.assert_allclose(rot.quat_to_matrix(out[k]), ref.as_matrix()[0], atol=1e-10)
    # the double cover: -q1 is the same rotation, so the same path
    np.testing.assert_allclose(rot.quat_to_matrix(rot.slerp(q0, -q1, w)), rot.quat_to_matrix(out), atol=1e-10)
    np.testing.assert_allclose(rot.quat_to_matrix(rot.slerp(q0, q1, 0.0)), rot.quat_to_matrix(q0), atol=1e-12)
    np.testing.assert_allclose(rot.quat_to_matrix(rot.slerp(q0, q1, 1.0)), rot.quat_to_matrix(q1), atol=1e-10)


def test_rotvec_between_is_the_smallest_turn_onto_b():
    a, b = RNG.normal(size=(50, 3)), RNG.normal(size=(50, 3))
    b[0] = -a[0] * 3.0  # opposite
    b[1] = a[1] * 2.0  # same direction
    v = rot.rotvec_between(a, b)
    ua, ub = a / np.linalg.norm(a, axis=1, keepdims=True), b / np.linalg.norm(b, axis=1, keepdims=True)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", rot.rotvec_to_matrix(v), ua), ub, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), np.arccos(np.clip((ua * ub).sum(1), -1, 1)), atol=1e-7)


def test_torch_rodrigues_matches_scipy_and_has_a_finite_gradient_at_zero():
    torch = pytest.importorskip("torch")
    v = RNG.normal(size=(10, 3)) * 1.5
    v[0] = 0.0
    R = rot.rotvec_to_matrix_torch(torch.tensor(v, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(R, Rotation.from_rotvec(v).as_matrix(), atol=1e-10)
    r = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    rot.rotvec_to_matrix_torch(r).sum().backward()
    assert torch.isfinite(r.grad).all()


def test_no_rotation_conversion_is_written_outside_the_rotation_module():
    """The figure of issue 32: 0 hand-written quaternion/rotation conversions (formulas or component
    shuffles) in the package outside geometry/rotations.py. SciPy calls at the call sites are fine."""
    src = Path(rot.__file__).parents[1]
    patterns = [r"\[1, 2, 3, 0\]", r"\[3, 0, 1, 2\]", r"\[4, 5, 6, 3\]", r"1 - 2 \* \(\w \* \w \+ \w \* \w\)",
                r"np\.cross\(v1, ", r"def \w*(quat|rodrigues|axis_angle)\w*\(", r"sin\(\(1\.0 - w\) \* theta\)"]
    hits = []
    for path in sorted(src.rglob("*.py")):
        if path.name == "rotations.py" and path.parent.name == "geometry":
            continue
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if any(re.search(p, line) for p in patterns):
                hits.append(f"{path.relative_to(src)}:{n}: {line.strip()}")
    assert hits == []


def test_smooth_rotvecs_keeps_a_steady_turn_and_removes_jitter_across_the_double_cover():
    """A turn at a constant rate (past a half turn, where rotation vectors jump and quaternion signs
    flip) comes back unchanged inside the series; a jitter of a few degrees on it shrinks by the
    filter's noise gain; several series (a (T, J, 3) batch) are filtered alike."""
    T = 60
    ang = np.linspace(0.0, 1.6 * np.pi, T)  # a steady turn well past pi about a tilted axis
    axis = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    steady = ang[:, None] * axis
    out = rot.smooth_rotvecs(steady, 1.0)
    d = (Rotation.from_rotvec(out[5:-5]).inv() * Rotation.from_rotvec(steady[5:-5])).magnitude()
    assert d.max() < 1e-3  # a steady turn: the symmetric kernel leaves it (second-order error only)
    rng = np.random.default_rng(0)
    noise = Rotation.from_rotvec(rng.normal(size=(T, 2, 3)) * np.radians(3.0))
    base = Rotation.from_rotvec(np.repeat(steady[:, None], 2, 1).reshape(-1, 3))
    noisy = (base * Rotation.from_rotvec(noise.as_rotvec().reshape(-1, 3))).as_rotvec().reshape(T, 2, 3)
    sm = rot.smooth_rotvecs(noisy, 1.0)
    err = lambda v: (Rotation.from_rotvec(v[5:-5].reshape(-1, 3)).inv() * base[10:-10]).magnitude()  # noqa: E731
    assert np.sqrt(np.mean(err(sm) ** 2)) < 0.6 * np.sqrt(np.mean(err(noisy) ** 2))
    np.testing.assert_allclose(rot.smooth_rotvecs(noisy, 0.0), noisy)
