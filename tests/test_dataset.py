"""Height maps and contact labels of `embodmocap.data` against scenes and motions with known answers
(windows of real processed sequences are checked against smpl_world.npz in test_batch_pipeline.py)."""

from __future__ import annotations

import numpy as np

from embodmocap.data.terrain import CONTACT_JOINTS, foot_contacts, height_grid, height_patch, sample_heights


def _quad(x0, x1, y0, y1, z):
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], float)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _room() -> tuple[np.ndarray, np.ndarray]:
    """A 4 x 3 m floor at z = 0.1, a table top at 0.75 over x in [1, 2], y in [1, 1.5], a ceiling at 2.6."""
    parts = [_quad(0, 4, 0, 3, 0.1), _quad(1, 2, 1, 1.5, 0.75), _quad(0, 4, 0, 3, 2.6)]
    vs, fs, n = [], [], 0
    for v, f in parts:
        vs.append(v)
        fs.append(f + n)
        n += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def test_height_grid_keeps_the_ground_and_drops_the_ceiling():
    v, f = _room()
    g = height_grid(v, f, cell_m=0.1)
    pts = np.array([[0.5, 0.5], [1.5, 1.25], [3.5, 2.5], [1.2, 1.4], [2.5, 1.25], [-5.0, -5.0]])
    np.testing.assert_allclose(sample_heights(g, pts), [0.1, 0.75, 0.1, 0.75, 0.1, 0.1], atol=1e-6)
    assert g.heights.max() <= 0.75 + 1e-6  # the ceiling (2.5 m above the floor) is not ground
    assert g.heights.shape == (31, 41)  # rows along y (3 m), columns along x (4 m)


def test_height_patch_rows_follow_y_and_columns_x():
    v, f = _room()
    g = height_grid(v, f, cell_m=0.1)
    p = height_patch(g, np.array([1.5, 1.25]), size=11, cell_m=0.1)  # 1 m square centred on the table
    assert p[5, 5] == np.float32(0.75)
    # Row i samples y = 1.25 + (i - 5) * 0.1 and column j x = 1.5 + (j - 5) * 0.1: the table (x 1..2,
    # y 1..1.5) covers rows 3..7 (y 1.05..1.45) and the inner columns 1..9 (x 1.1..1.9).
    np.testing.assert_allclose(p[:, 5], [0.1] * 3 + [0.75] * 5 + [0.1] * 3, atol=1e-6)
    np.testing.assert_allclose(p[5, 1:10], [0.75] * 9, atol=1e-6)
    np.testing.assert_allclose(p[0], [0.1] * 11, atol=1e-6)


def test_foot_contacts_need_low_and_slow_feet():
    T, fps = 30, 30.0
    joints = np.zeros((T, 24, 3))
    joints[:, :, 2] = 1.0
    ground = np.zeros((T, 4))
    feet = list(CONTACT_JOINTS)
    joints[:, feet[0], 2] = 0.05  # left ankle: low and still -> contact throughout
    joints[:, feet[1], 2] = 0.05  # right ankle: low but sliding at 1 m/s -> never
    joints[:, feet[1], 0] = np.arange(T) / fps
    joints[:, feet[2], 2] = 0.3  # left foot: still but 30 cm up -> never
    joints[:, feet[3], 2] = np.where(np.arange(T) < 15, 0.02, 0.5)  # right foot: lifts at frame 15
    ground[:, 3] = 0.0
    c = foot_contacts(joints, ground, fps)
    assert c.shape == (T, 4) and c[:, 0].all() and not c[:, 1].any() and not c[:, 2].any()
    assert c[:14, 3].all() and not c[15:, 3].any()
    # Raising the ground under the left foot to 0.25 m makes it touch.
    ground[:, 2] = 0.25
    assert foot_contacts(joints, ground, fps)[:, 2].all()
