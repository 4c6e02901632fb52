"""A generated body model in the SMPL file layout, so the demo and every test run without a licence.

The body is built from 20 closed capsules (torso pieces, neck, head, and per side: collar, upper
arm, forearm, hand, thigh, shin, foot) whose end rings sit exactly on a designed 24-joint SMPL
skeleton. It lives in SMPL's canonical frame: Y up, facing +Z, its left on +X, metres, T-pose,
pelvis joint about 0.22 m below the origin (as in SMPL's own template), about 1.70 m tall.

What makes it usable in place of SMPL:

- ``J_regressor`` averages the vertices of the end rings that meet at each joint; a ring's
  vertices are evenly spaced around the capsule axis, so the average is exactly the joint and
  ``J_regressor @ v_template`` reproduces the designed skeleton (also after any shape change that
  keeps rings centred, e.g. girth).
- ``weights`` (LBS) give each capsule to the joint that rotates it and blend smoothly into the
  neighbouring joint over a few centimetres around each joint (50/50 on the shared end rings), so
  skinning has no seams.
- ``shapedirs`` are hand-designed directions: 0 overall size (height), 1 girth, 2 leg length,
  3 arm length, 4 shoulder width, 5 torso length, 6 head size, 7 hip width, 8 belly, 9 chest
  depth; further components (num_betas > 10) are small smooth random fields.
- ``posedirs`` (pose correctives) are zero, with SMPL's shape (V, 3, 207).

The file format is written up in ``docs/formats.md``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.body.joints import FACE_KEYPOINT_NAMES, SMPL_JOINT_NAMES, SMPL_PARENTS
from embodmocap.io.atomic import write_npz

log = logging.getLogger(__name__)

#: Version of the generated model's design; bump when the geometry changes.
TEST_MODEL_VERSION = 1

_X, _Y, _Z = np.eye(3)


@dataclass(frozen=True)
class _Part:
    """One capsule of the body and how it is skinned.

    The capsule's straight part runs from ``a`` to ``b`` with elliptic cross-sections ``ra`` at a
    and ``rb`` at b (half-axes along the local x = ``width`` direction and local y = axis x x);
    half-ellipsoid caps of height ``cap_a`` / ``cap_b`` close the ends. ``owner`` is the joint
    whose rotation moves it; near ``a`` it blends into ``parent_blend``, near ``b`` into
    ``child_blend``.
    """

    name: str
    a: NDArray
    b: NDArray
    ra: tuple[float, float]
    rb: tuple[float, float]
    cap_a: float
    cap_b: float
    width: NDArray
    owner: int
    parent_blend: int | None
    child_blend: int | None
    joint_a: int | None
    joint_b: int | None
    n_lon: int = 20
    n_hemi: int = 5
    axis: NDArray | None = None
    blend_origin: NDArray | None = None


def _design_skeleton(rng: np.random.Generator) -> NDArray[np.float64]:
    """(24, 3) rest joints of a symmetric adult in SMPL's canonical frame, lightly varied by rng."""
    left = {  # left-side joints (x > 0) and the midline; the right side mirrors x
        0: (0.0, -0.22, 0.02), 1: (0.07, -0.31, 0.01), 3: (0.0, -0.11, 0.0),
        4: (0.10, -0.69, 0.015), 6: (0.0, 0.02, 0.025), 7: (0.085, -1.075, -0.02),
        9: (0.0, 0.08, 0.03), 10: (0.11, -1.115, 0.10), 12: (0.0, 0.29, -0.01),
        13: (0.075, 0.20, -0.005), 15: (0.0, 0.37, 0.04), 16: (0.17, 0.23, -0.015),
        18: (0.43, 0.215, -0.035), 20: (0.67, 0.22, -0.035), 22: (0.75, 0.21, -0.045),
    }
    J = np.zeros((24, 3))
    for j, p in left.items():
        J[j] = p
    mirror = {2: 1, 5: 4, 8: 7, 11: 10, 14: 13, 17: 16, 19: 18, 21: 20, 23: 22}
    # Proportions vary by a few per cent per seed (legs below the hips, arms beyond the
    # shoulders); the hip joint height and the shoulders stay, so the figure stays plausible.
    leg, arm = 1.0 + 0.02 * np.clip(rng.standard_normal(2), -2.0, 2.0)
    legs = [4, 7, 10]
    J[legs, 1] = J[1, 1] + (J[legs, 1] - J[1, 1]) * leg
    arms = [18, 20, 22]
    J[arms, 0] = J[16, 0] + (J[arms, 0] - J[16, 0]) * arm
    for r, l in mirror.items():
        J[r] = J[l] * (-1.0, 1.0, 1.0)
    return J


def _parts(J: NDArray[np.float64]) -> list[_Part]:
    """The capsules of the body for rest joints ``J`` (24, 3)."""
    head_c = J[15] + (0.0, 0.08, 0.005)
    parts = [
        _Part("pelvis", J[0], J[3], (0.155, 0.11), (0.14, 0.10), 0.12, 0.05, _X, 0, None, 3, 0, 3),
        _Part("abdomen", J[3], J[6], (0.14, 0.10), (0.15, 0.105), 0.05, 0.05, _X, 3, 0, 6, 3, 6),
        _Part("lower_chest", J[6], J[9], (0.15, 0.105), (0.155, 0.11), 0.04, 0.04, _X, 6, 3, 9, 6, 9),
        _Part("upper_chest", J[9], J[12], (0.155, 0.11), (0.12, 0.08), 0.04, 0.045, _X, 9, 6, 12, 9, 12),
        _Part("neck", J[12], J[15], (0.055, 0.055), (0.05, 0.05), 0.03, 0.03, _X, 12, 9, 15, 12, 15),
        _Part("head", head_c, head_c, (0.078, 0.098), (0.078, 0.098), 0.105, 0.105, _X, 15, 12, None,
              None, None, n_lon=24, n_hemi=8, axis=_Y, blend_origin=J[15]),
    ]
    for side, (col, sho, elb, wri, hnd, hip, kne, ank, ft) in (
        ("left", (13, 16, 18, 20, 22, 1, 4, 7, 10)),
        ("right", (14, 17, 19, 21, 23, 2, 5, 8, 11)),
    ):
        heel = np.array([J[ank, 0], J[ft, 1], J[ank, 2] - 0.04])
        parts += [
            _Part(f"{side}_collar", J[col], J[sho], (0.06, 0.06), (0.06, 0.06), 0.03, 0.03, _Z, col, 9, sho, col, sho),
            _Part(f"{side}_upper_arm", J[sho], J[elb], (0.05, 0.052), (0.04, 0.042), 0.04, 0.035, _Z, sho, col, elb, sho, elb),
            _Part(f"{side}_forearm", J[elb], J[wri], (0.04, 0.042), (0.032, 0.026), 0.035, 0.025, _Z, elb, sho, wri, elb, wri),
            _Part(f"{side}_hand", J[wri], J[hnd], (0.038, 0.02), (0.045, 0.017), 0.015, 0.09, _Z, wri, elb, hnd, wri, hnd),
            _Part(f"{side}_thigh", J[hip], J[kne], (0.085, 0.085), (0.055, 0.055), 0.06, 0.04, _X, hip, 0, kne, hip, kne),
            _Part(f"{side}_shin", J[kne], J[ank], (0.055, 0.055), (0.04, 0.04), 0.04, 0.04, _X, kne, hip, ank, kne, ank),
            _Part(f"{side}_foot", heel, J[ft], (0.04, 0.035), (0.045, 0.03), 0.035, 0.07, _X, ank, None, ft, None, ft),
        ]
    return parts


@dataclass(frozen=True)
class _Mesh:
    """A capsule's mesh with what skinning, shape and the regressor need per vertex."""

    verts: NDArray  # (N, 3)
    faces: NDArray  # (M, 3) int, outward normals (counter-clockwise seen from outside)
    axial: NDArray  # (N,) coordinate along the axis from a, metres
    radial: NDArray  # (N, 3) offset of each vertex from its axis point
    ring_a: NDArray  # ids of the equator ring centred on a
    ring_b: NDArray  # ids of the equator ring centred on b


def _capsule(p: _Part) -> _Mesh:
    """Tessellate one capsule: rings ordered from the a-pole to the b-pole."""
    ab = p.b - p.a
    L = float(np.linalg.norm(ab))
    d = ab / L if L > 1e-9 else np.asarray(p.axis, dtype=np.float64)
    x = p.width - (p.width @ d) * d
    x = x / np.linalg.norm(x)
    y = np.cross(d, x)  # (x, y, d) is right-handed
    alpha = np.arange(p.n_hemi) * (np.pi / 2) / p.n_hemi  # latitude of ring k (0 = equator)
    # (axial position, half-axis x, half-axis y) of each ring, from the a-side to the b-side.
    rings_a = [(-p.cap_a * np.sin(t), p.ra[0] * np.cos(t), p.ra[1] * np.cos(t)) for t in alpha[::-1]]
    first_b = 0 if L > 1e-9 else 1  # an ellipsoid (L = 0) shares its equator ring
    rings_b = [(L + p.cap_b * np.sin(t), p.rb[0] * np.cos(t), p.rb[1] * np.cos(t)) for t in alpha[first_b:]]
    rings = np.array(rings_a + rings_b)  # (R, 3)
    n, R = p.n_lon, len(rings)
    theta = 2 * np.pi * np.arange(n) / n
    ring_local = (
        rings[:, None, 1:2] * np.cos(theta)[None, :, None] * x
        + rings[:, None, 2:3] * np.sin(theta)[None, :, None] * y
        + rings[:, None, 0:1] * d
    ).reshape(-1, 3)
    poles = np.array([-p.cap_a * d, (L + p.cap_b) * d])
    verts = p.a + np.concatenate([ring_local, poles])
    axial = np.concatenate([np.repeat(rings[:, 0], n), [-p.cap_a, L + p.cap_b]])
    radial = verts - (p.a + axial[:, None] * d)

    idx = np.arange(R * n).reshape(R, n)
    nxt = np.roll(idx, -1, axis=1)
    quads_lo, quads_lo_next = idx[:-1], nxt[:-1]
    quads_hi, quads_hi_next = idx[1:], nxt[1:]
    tri1 = np.stack([quads_lo, quads_lo_next, quads_hi_next], -1).reshape(-1, 3)
    tri2 = np.stack([quads_lo, quads_hi_next, quads_hi], -1).reshape(-1, 3)
    pole_a, pole_b = R * n, R * n + 1
    fan_a = np.stack([np.full(n, pole_a), nxt[0], idx[0]], -1)
    fan_b = np.stack([np.full(n, pole_b), idx[-1], nxt[-1]], -1)
    faces = np.concatenate([tri1, tri2, fan_a, fan_b])
    eq_a = p.n_hemi - 1
    eq_b = eq_a + (1 if L > 1e-9 else 0)
    return _Mesh(verts, faces, axial, radial, idx[eq_a], idx[eq_b])


def _smoothstep(x: NDArray) -> NDArray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _part_weights(p: _Part, m: _Mesh) -> NDArray[np.float64]:
    """(N, 24) LBS weights of one capsule: owner joint, blended into neighbours near the ends."""
    if p.blend_origin is not None:  # the head blends by height above the head joint
        t = (m.verts - p.blend_origin) @ _Y
        L = np.inf
    else:
        t, L = m.axial, float(np.linalg.norm(p.b - p.a))
    hb = min(0.05, 0.5 * L)  # half-width of the blend band, metres
    w = np.zeros((len(t), 24))
    pw = _smoothstep((hb - t) / (2 * hb)) if p.parent_blend is not None else np.zeros_like(t)
    cw = _smoothstep((t - (L - hb)) / (2 * hb)) if p.child_blend is not None else np.zeros_like(t)
    w[:, p.owner] = np.clip(1.0 - pw - cw, 0.0, None)
    if p.parent_blend is not None:
        w[:, p.parent_blend] += pw
    if p.child_blend is not None:
        w[:, p.child_blend] += cw
    return w / w.sum(axis=1, keepdims=True)


def _shape_dirs(
    v: NDArray, radial: NDArray, part_of: NDArray, names: list[str], J: NDArray, num_betas: int,
    rng: np.random.Generator,
) -> NDArray[np.float64]:
    """(V, 3, num_betas) shape directions (per unit beta, metres); see the module docstring."""
    x, y, z = v[:, 0], v[:, 1], v[:, 2]

    def is_part(*keys: str) -> NDArray[np.bool_]:
        return np.isin(part_of, [i for i, n in enumerate(names) if any(k in n for k in keys)])

    dirs = np.zeros((len(v), 3, max(num_betas, 10)))
    dirs[:, :, 0] = 0.04 * (v - J[0])  # overall size: 4 % per unit about the pelvis
    girth = np.where(part_of == names.index("head"), 0.03, 0.15)
    dirs[:, :, 1] = girth[:, None] * radial  # thicker cross-sections, joints stay on the axes
    dirs[:, 1, 2] = 0.06 * np.minimum(0.0, y - J[1, 1])  # legs longer below the hip joints
    dirs[:, 0, 3] = 0.06 * np.sign(x) * np.maximum(0.0, np.abs(x) - J[16, 0])  # arms beyond shoulders
    upper = _smoothstep((y - 0.05) / 0.10)
    dirs[:, 0, 4] = 0.03 * np.sign(x) * _smoothstep(np.abs(x) / J[16, 0]) * upper  # shoulder width
    span = J[12, 1] - J[3, 1]
    dirs[:, 1, 5] = 0.04 * np.clip(y - J[3, 1], 0.0, span) / span  # torso longer, head rides up
    head = part_of == names.index("head")
    dirs[head, :, 6] = 0.08 * (v[head] - v[head].mean(axis=0))  # head size
    dirs[:, 0, 7] = 0.15 * x * (1.0 - _smoothstep((y - J[3, 1]) / 0.1))  # hips and legs apart
    belly = is_part("pelvis", "abdomen", "lower_chest")
    dirs[belly, 2, 8] = 0.3 * np.maximum(z[belly], 0.0)  # belly forward
    chest = is_part("upper_chest", "lower_chest")
    dirs[chest, 2, 9] = 0.2 * (z[chest] - J[9, 2])  # chest depth
    # Further components: small smooth random fields (about 5 mm per unit).
    for k in range(10, num_betas):
        w = rng.normal(0.0, 3.0, (3, 3))
        phase = rng.uniform(0.0, 2 * np.pi, 3)
        dirs[:, :, k] = 0.005 * np.sin(v @ w + phase)
    return dirs[:, :, :num_betas]


def _nearest(verts: NDArray, ids: NDArray, target: NDArray) -> int:
    return int(ids[np.argmin(np.linalg.norm(verts[ids] - target, axis=1))])


def make_test_model(seed: int = 0, num_betas: int = 10) -> dict[str, np.ndarray]:
    """Generate the body model for ``seed`` as a dict of arrays in the SMPL file layout.

    Keys: ``v_template`` (V, 3), ``f`` (F, 3) int64, ``J_regressor`` (24, V) dense,
    ``weights`` (V, 24), ``kintree_table`` (2, 24) int64 (row 0 parents, root -1; row 1 ids),
    ``shapedirs`` (V, 3, num_betas), ``posedirs`` (V, 3, 207) zeros, ``vertex_ids`` (5,) int64
    with ``vertex_id_names`` (5,) str (nose, reye, leye, rear, lear), ``joint_names`` (24,) str,
    ``part_ids`` (V,) int64 with ``part_names`` str, ``gender`` "neutral", ``generator`` str,
    ``version`` int, ``seed`` int. Deterministic per (seed, num_betas).
    """
    if num_betas < 1:
        raise ValueError(f"num_betas must be >= 1, got {num_betas}")
    rng = np.random.default_rng(seed)
    J = _design_skeleton(rng)
    parts = _parts(J)
    meshes = [_capsule(p) for p in parts]
    offsets = np.cumsum([0] + [len(m.verts) for m in meshes])
    v = np.concatenate([m.verts for m in meshes])
    f = np.concatenate([m.faces + o for m, o in zip(meshes, offsets)]).astype(np.int64)
    part_of = np.concatenate([np.full(len(m.verts), i) for i, m in enumerate(meshes)]).astype(np.int64)
    weights = np.concatenate([_part_weights(p, m) for p, m in zip(parts, meshes)])

    # Regressor: uniform weights over every end ring centred on the joint.
    J_regressor = np.zeros((24, len(v)))
    for p, m, o in zip(parts, meshes, offsets):
        for joint, ring in ((p.joint_a, m.ring_a), (p.joint_b, m.ring_b)):
            if joint is not None:
                J_regressor[joint, ring + o] = 1.0
    J_regressor /= J_regressor.sum(axis=1, keepdims=True)

    names = [p.name for p in parts]
    head_ids = np.nonzero(part_of == names.index("head"))[0]
    c = meshes[names.index("head")].verts.mean(axis=0)
    targets = {
        "nose": c + (0.0, -0.01, 0.1), "reye": c + (-0.032, 0.02, 0.085), "leye": c + (0.032, 0.02, 0.085),
        "rear": c + (-0.08, 0.0, 0.0), "lear": c + (0.08, 0.0, 0.0),
    }
    vertex_ids = np.array([_nearest(v, head_ids, targets[n]) for n in FACE_KEYPOINT_NAMES], dtype=np.int64)

    kintree = np.stack([np.array(SMPL_PARENTS), np.arange(24)]).astype(np.int64)
    return {
        "v_template": v,
        "f": f,
        "J_regressor": J_regressor,
        "weights": weights,
        "kintree_table": kintree,
        "shapedirs": _shape_dirs(v, np.concatenate([m.radial for m in meshes]), part_of, names, J, num_betas, rng),
        "posedirs": np.zeros((len(v), 3, 207)),
        "vertex_ids": vertex_ids,
        "vertex_id_names": np.array(FACE_KEYPOINT_NAMES),
        "joint_names": np.array(SMPL_JOINT_NAMES),
        "part_ids": part_of,
        "part_names": np.array(names),
        "gender": np.array("neutral"),
        "generator": np.array("embodmocap.body.testmodel"),
        "version": np.array(TEST_MODEL_VERSION, dtype=np.int64),
        "seed": np.array(seed, dtype=np.int64),
    }


def write_test_model(path: str | Path, seed: int = 0, num_betas: int = 10) -> Path:
    """Write the generated model to ``path`` (.npz, written atomically); returns the path."""
    path = Path(path)
    write_npz(path, **make_test_model(seed=seed, num_betas=num_betas))
    return path


def make_test_model_cli(out: Path, seed: int = 0) -> None:
    """CLI entry: write the generated model to ``out`` and log a one-line summary."""
    arrays = make_test_model(seed=seed)
    write_npz(Path(out), **arrays)
    v = arrays["v_template"]
    log.info(
        "wrote test body model %s: %d vertices, %d faces, %d betas, height %.3f m (seed %d)",
        out, len(v), len(arrays["f"]), arrays["shapedirs"].shape[-1], np.ptp(v[:, 1]), seed,
    )
