"""Contact-marker alignment: recovering a known offset, translation-only fits, refusals, and
body/camera consistency, on the generated test body standing at a few places in the world."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from embodmocap.body.model import load_body_model
from embodmocap.errors import InputError
from embodmocap.geometry.transforms import R_ZUP_YUP, apply_T, invert_T, make_T, rot_z, rotation_angle
from embodmocap.motion.contact import (
    ContactConfig, align_to_contacts, apply_alignment, apply_alignment_to_cameras, contact_points,
)
from embodmocap.types import SmplParams

# Standing places (x, y, heading in degrees) of the 4 frames; contacts at frames 0 and 3 are
# about 4.3 m apart.
PLACES = np.array([[0.5, 1.0, 0.0], [1.5, 1.2, 60.0], [2.5, 0.2, 120.0], [3.0, -1.0, -90.0]])


@pytest.fixture(scope="module")
def model():
    return load_body_model(None)


@pytest.fixture(scope="module")
def standing(model) -> SmplParams:
    """The body standing (zero pose, arms out) on the floor z = 0 at PLACES."""
    T = len(PLACES)
    rng = np.random.default_rng(0)
    betas = 0.5 * rng.normal(size=10)
    go = (Rotation.from_matrix(rot_z(np.deg2rad(PLACES[:, 2]))) * Rotation.from_matrix(R_ZUP_YUP)).as_rotvec()
    pose = np.zeros((T, 69))
    rest = model.forward(betas, go, pose, np.zeros((T, 3)), dtype=torch.float64)
    v = rest.vertices.numpy()
    pelvis = rest.joints.numpy()[:, 0]
    transl = np.zeros((T, 3))
    transl[:, :2] = PLACES[:, :2] - pelvis[:, :2]
    transl[:, 2] = -v[..., 2].min(axis=1)
    return SmplParams(betas, go, pose, transl, fps=30.0)


def _vertices(model, params):
    return model.from_params(params, dtype=torch.float64).vertices.numpy()


def _markers(model, params, frames):
    return [(int(f), p) for f, p in zip(frames, contact_points(model, params, np.array(frames)))]


def test_contact_point_is_between_the_feet_on_the_floor(model, standing):
    p = contact_points(model, standing, np.arange(len(standing)))
    joints = model.from_params(standing, dtype=torch.float64).joints.numpy()
    ankles_mid = 0.5 * (joints[:, 7] + joints[:, 8])
    np.testing.assert_allclose(p[:, 2], 0.0, atol=1e-9)  # the feet were put on the floor
    # The soles' centre lies under the ankles (feet point forward a few cm).
    assert np.all(np.linalg.norm(p[:, :2] - ankles_mid[:, :2], axis=1) < 0.08)
    # Moving the body moves the contact point with it.
    moved = apply_alignment(model, standing, make_T(np.eye(3), [0.3, -0.2, 0.1]))
    np.testing.assert_allclose(contact_points(model, moved, np.arange(4)), p + [0.3, -0.2, 0.1], atol=1e-9)


def test_recovers_known_yaw_and_shift(model, standing):
    """Markers where the feet truly are; the motion off by 5 deg yaw and 20 cm."""
    contacts = _markers(model, standing, [0, 1, 3])
    T_off = make_T(rot_z(np.deg2rad(5.0)), [0.12, 0.16, 0.0])
    off = apply_alignment(model, standing, T_off)
    al = align_to_contacts(model, off, contacts)
    assert not al.refused and al.yaw_fitted, al.message
    residual = al.T @ T_off  # should be the identity
    assert np.linalg.norm(residual[:3, 3]) < 1e-3
    assert np.rad2deg(rotation_angle(residual[:3, :3])) < 0.01
    assert al.yaw_deg == pytest.approx(-5.0, abs=0.01)
    assert np.all(al.residuals_before_m > 0.15) and np.all(al.residuals_after_m < 1e-3)
    aligned = apply_alignment(model, off, al.T)
    assert np.abs(_vertices(model, aligned) - _vertices(model, standing)).max() < 1e-3


def test_one_contact_fixes_translation_only(model, standing):
    contacts = _markers(model, standing, [2])
    off = apply_alignment(model, standing, make_T(rot_z(np.deg2rad(3.0)), [0.1, -0.05, 0.0]))
    al = align_to_contacts(model, off, contacts)
    assert not al.refused and not al.yaw_fitted
    assert al.yaw_deg == 0.0
    np.testing.assert_allclose(al.T[:3, :3], np.eye(3), atol=1e-12)
    assert al.residuals_after_m[0] == pytest.approx(0.0, abs=1e-9)
    assert "yaw not fitted" in al.message
    # A pure shift is undone exactly.
    off2 = apply_alignment(model, standing, make_T(np.eye(3), [0.1, -0.05, 0.0]))
    al2 = align_to_contacts(model, off2, contacts)
    np.testing.assert_allclose(al2.T[:3, 3], [-0.1, 0.05, 0.0], atol=1e-9)
    # Two contacts on the same marker give no baseline either.
    al3 = align_to_contacts(model, off, contacts + contacts)
    assert not al3.yaw_fitted and al3.yaw_deg == 0.0


def test_inconsistent_contacts_are_refused_with_the_residual(model, standing):
    """The end marker placed 30 cm too far along the line between the markers: no rigid motion
    can stretch the distance, so both contacts stay 15 cm off."""
    (f0, m0), (f3, m3) = _markers(model, standing, [0, 3])
    u = (m3 - m0) / np.linalg.norm(m3 - m0)
    al = align_to_contacts(model, standing, [(f0, m0), (f3, m3 + 0.3 * u)])
    assert al.refused
    np.testing.assert_allclose(al.residuals_after_m, [0.15, 0.15], atol=1e-9)
    np.testing.assert_allclose(al.residuals_before_m, [0.0, 0.3], atol=1e-9)
    np.testing.assert_array_equal(al.T, np.eye(4))
    assert "0.150 m" in al.message and "frame" in al.message and "max_residual_m" in al.message
    # A looser threshold accepts the same fit.
    loose = ContactConfig(max_residual_m=0.2)
    assert not align_to_contacts(model, standing, [(f0, m0), (f3, m3 + 0.3 * u)], loose).refused


def test_implausibly_large_yaw_is_refused(model, standing):
    contacts = _markers(model, standing, [0, 3])
    off = apply_alignment(model, standing, make_T(rot_z(np.deg2rad(30.0)), np.zeros(3)))
    al = align_to_contacts(model, off, contacts)
    assert al.refused and "max_yaw_deg" in al.message
    assert al.yaw_deg == pytest.approx(-30.0, abs=1e-6)
    np.testing.assert_allclose(al.T_fit @ make_T(rot_z(np.deg2rad(30.0)), np.zeros(3)), np.eye(4), atol=1e-6)


def test_height_shift_only_with_fit_z(model, standing):
    contacts = _markers(model, standing, [0, 3])
    T_off = make_T(rot_z(np.deg2rad(2.0)), [0.05, 0.02, 0.04])
    off = apply_alignment(model, standing, T_off)
    flat = align_to_contacts(model, off, contacts)
    assert flat.T[2, 3] == 0.0
    np.testing.assert_allclose(flat.height_gap_m, [-0.04, -0.04], atol=1e-9)
    full = align_to_contacts(model, off, contacts, ContactConfig(fit_z=True))
    np.testing.assert_allclose(full.T @ T_off, np.eye(4), atol=1e-6)
    np.testing.assert_allclose(full.height_gap_m, 0.0, atol=1e-9)


def test_cameras_and_body_stay_consistent(model, standing):
    """A camera that saw the pelvis at pixel p sees the aligned pelvis at p through the aligned
    camera."""
    contacts = _markers(model, standing, [0, 3])
    off = apply_alignment(model, standing, make_T(rot_z(np.deg2rad(4.0)), [0.1, 0.15, 0.0]))
    al = align_to_contacts(model, off, contacts)
    assert not al.refused

    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    pelvis = model.from_params(off, dtype=torch.float64).joints.numpy()[:, 0]  # (T, 3)
    # One camera per frame, 3 m away along -x and 0.4 m up, looking along +x (OpenCV axes).
    R_wc = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    T_wc = make_T(np.broadcast_to(R_wc, (4, 3, 3)), pelvis + [-3.0, 0.2, 0.4])

    def pixels(T_world_cam, points):
        cam = apply_T(invert_T(T_world_cam), points[:, None])[:, 0]
        uv = cam @ K.T
        return uv[:, :2] / uv[:, 2:]

    before = pixels(T_wc, pelvis)
    aligned = apply_alignment(model, off, al.T)
    pelvis2 = model.from_params(aligned, dtype=torch.float64).joints.numpy()[:, 0]
    after = pixels(apply_alignment_to_cameras(T_wc, al.T), pelvis2)
    assert np.abs(pelvis2 - pelvis).max() > 0.1  # the body did move
    np.testing.assert_allclose(after, before, atol=1e-6)


def test_bad_contacts_raise_one_clear_error(model, standing):
    with pytest.raises(InputError, match="outside the sequence"):
        align_to_contacts(model, standing, [(9, np.zeros(3))])
    with pytest.raises(InputError, match="not 3 finite numbers"):
        align_to_contacts(model, standing, [(0, [1.0, 2.0])])
    with pytest.raises(InputError, match="no contacts"):
        align_to_contacts(model, standing, [])
    with pytest.raises(ValueError):
        apply_alignment_to_cameras(np.eye(4), 2 * np.eye(4))
