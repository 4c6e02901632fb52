"""Every rotation conversion of the package, on SciPy's ``Rotation`` (and torch where autograd needs it).

The package's ONE quaternion order is **scalar last, (x, y, z, w)**, as SciPy and the capture apps'
CSVs store it. Formats that store (w, x, y, z) (MuJoCo's ``qpos``/``xquat``, mjlab's tracking npz,
``qpos.npz``'s ``root_quat_wxyz``, viser) are converted where the data crosses into or out of them,
with :func:`wxyz_to_xyzw` / :func:`xyzw_to_wxyz`; a name holding (w, x, y, z) says ``wxyz``.

Other conventions: rotation vectors (axis-angle) are (..., 3) in radians, matrices (..., 3, 3) act
on column vectors (``p' = R @ p``), and :func:`quat_mul` is the Hamilton product (``a * b`` applies
``b`` first). Every function takes any leading batch shape (SciPy sees them flattened) and returns
float64 arrays of the matching shape.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

if TYPE_CHECKING:
    import torch

F = NDArray[np.floating]

#: The package's quaternion component order.
QUAT_ORDER = "xyzw"


def _convert(x: F, kind: str, out_tail: tuple[int, ...], as_out) -> F:
    """SciPy's ``Rotation`` from (..., 3) rotation vectors, (..., 4) quaternions or (..., 3, 3)
    matrices (``kind``), converted by ``as_out`` (e.g. ``Rotation.as_matrix``), in the input's batch
    shape; empty input gives an empty output."""
    x = np.asarray(x, dtype=np.float64)
    batch = x.shape[:-2] if kind == "matrix" else x.shape[:-1]
    if x.size == 0:
        return np.zeros(batch + out_tail)
    flat = x.reshape((-1,) + x.shape[len(batch):])
    r = {"matrix": Rotation.from_matrix, "quat": Rotation.from_quat, "rotvec": Rotation.from_rotvec}[kind](flat)
    return np.asarray(as_out(r)).reshape(batch + out_tail)


# ------------------------------------------------------------------------------- component order


def wxyz_to_xyzw(q: F) -> F:
    """(..., 4) quaternions stored (w, x, y, z) -> the package's (x, y, z, w)."""
    return np.asarray(q)[..., [1, 2, 3, 0]]


def xyzw_to_wxyz(q: F) -> F:
    """(..., 4) quaternions (x, y, z, w) -> (w, x, y, z) for a format that wants the scalar first."""
    return np.asarray(q)[..., [3, 0, 1, 2]]


def canonical_quat(q: F) -> F:
    """(..., 4) quaternions (x, y, z, w) with the sign chosen so that w >= 0 (same rotations)."""
    q = np.asarray(q, dtype=np.float64)
    return np.where(q[..., 3:4] < 0, -q, q)


# ------------------------------------------------------------------------------- conversions


def quat_to_matrix(q: F, invalid: Literal["raise", "nan"] = "raise") -> F:
    """Quaternions (..., 4) (x, y, z, w) -> rotation matrices (..., 3, 3).

    The quaternion is normalised first, so slightly non-unit input (as CSVs store) is fine. A zero
    or non-finite quaternion raises ``ValueError``, or gives a NaN matrix with ``invalid="nan"``
    (pose files whose missing rows must stay visible as NaN).
    """
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1)
    ok = np.isfinite(n) & (n > 1e-9)
    if invalid == "raise" and not np.all(ok):
        raise ValueError("zero-length or non-finite quaternion")
    out = np.full(q.shape[:-1] + (3, 3), np.nan)
    if np.any(ok):
        out[ok] = Rotation.from_quat(q[ok].reshape(-1, 4)).as_matrix()
    return out


def matrix_to_quat(R: F) -> F:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) (x, y, z, w) with w >= 0."""
    return canonical_quat(_convert(R, "matrix", (4,), Rotation.as_quat))


def rotvec_to_matrix(v: F) -> F:
    """Rotation vectors (..., 3) (axis times angle, radians) -> matrices (..., 3, 3)."""
    return _convert(v, "rotvec", (3, 3), Rotation.as_matrix)


def matrix_to_rotvec(R: F) -> F:
    """Rotation matrices (..., 3, 3) -> rotation vectors (..., 3), angle in [0, pi]."""
    return _convert(R, "matrix", (3,), Rotation.as_rotvec)


def rotvec_to_quat(v: F) -> F:
    """Rotation vectors (..., 3) -> quaternions (..., 4) (x, y, z, w), w >= 0."""
    return canonical_quat(_convert(v, "rotvec", (4,), Rotation.as_quat))


def quat_to_rotvec(q: F) -> F:
    """Quaternions (..., 4) (x, y, z, w) -> rotation vectors (..., 3) of the shorter turn (angle in [0, pi])."""
    return _convert(q, "quat", (3,), Rotation.as_rotvec)


# ------------------------------------------------------------------------------- algebra


def quat_mul(a: F, b: F) -> F:
    """Hamilton products ``a * b`` of quaternions (..., 4) (x, y, z, w), broadcast; ``b`` applies first.

    Plain algebra rather than SciPy's composition: no normalisation, so a zero quaternion (MuJoCo's
    data before its first forward pass) multiplies to zero instead of raising, and non-unit input
    scales the product. The product's sign is not canonicalised (use :func:`canonical_quat`).
    """
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    va, wa, vb, wb = a[..., :3], a[..., 3:], b[..., :3], b[..., 3:]
    return np.concatenate([wa * vb + wb * va + np.cross(va, vb),
                           wa * wb - (va * vb).sum(-1, keepdims=True)], axis=-1)


def quat_conj(q: F) -> F:
    """Conjugates (..., 4) of quaternions (x, y, z, w): the inverse rotations of unit quaternions."""
    return np.asarray(q, dtype=np.float64) * np.array([-1.0, -1.0, -1.0, 1.0])


def slerp(q0: F, q1: F, w: F) -> F:
    """Spherical linear interpolation between quaternion pairs (..., 4) (x, y, z, w) by weights (...).

    ``q0 * exp(w * log(q0^-1 q1))`` on the shorter arc (the double cover is handled: ``q1`` and
    ``-q1`` give the same rotations); ``w = 0`` gives ``q0``'s rotation, ``w = 1`` ``q1``'s. Returns
    unit quaternions (..., 4); their sign is not canonicalised.
    """
    q0, q1 = np.asarray(q0, dtype=np.float64), np.asarray(q1, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)
    shape = np.broadcast_shapes(q0.shape[:-1], q1.shape[:-1], w.shape)
    if int(np.prod(shape)) == 0:
        return np.zeros(shape + (4,))
    r0 = Rotation.from_quat(np.broadcast_to(q0, shape + (4,)).reshape(-1, 4))
    r1 = Rotation.from_quat(np.broadcast_to(q1, shape + (4,)).reshape(-1, 4))
    step = (r0.inv() * r1).as_rotvec() * np.broadcast_to(w, shape).reshape(-1, 1)
    return (r0 * Rotation.from_rotvec(step)).as_quat().reshape(shape + (4,))


def rotvec_between(a: F, b: F) -> F:
    """Rotation vectors (..., 3) of the smallest rotations taking directions ``a`` (..., 3) onto ``b``.

    Opposite directions get a half turn about an axis perpendicular to ``a``; zero-length input
    gives a zero rotation."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True).clip(min=1e-12)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True).clip(min=1e-12)
    ax = np.cross(a, b)
    s = np.linalg.norm(ax, axis=-1)
    ang = np.arctan2(s, (a * b).sum(-1))
    perp = np.cross(a, np.where(np.abs(a[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]))
    ax = np.where((s < 1e-9)[..., None], perp, ax)
    return ax / np.linalg.norm(ax, axis=-1, keepdims=True).clip(min=1e-12) * ang[..., None]


def smooth_rotvecs(v: F, sigma: float) -> F:
    """Rotation vectors (T, ..., 3) smoothed along axis 0 by a Gaussian of ``sigma`` samples.

    Each series' quaternions are put on one hemisphere sample by sample (``q`` and ``-q`` are the
    same rotation; a sign flip between neighbours would average to nonsense), filtered component by
    component (the ends repeated) and normalised: for neighbours a few degrees apart this is the
    weighted rotation mean to second order. ``sigma`` <= 0 or fewer than 2 samples: ``v`` as given.
    """
    from scipy.ndimage import gaussian_filter1d

    v = np.array(v, dtype=np.float64)  # a writable copy (SciPy refuses read-only buffers)
    if sigma <= 0 or v.shape[0] < 2:
        return v
    q = rotvec_to_quat(v)
    # Running product of the signs: each sample on the hemisphere of the one before it.
    flip = np.where((q[1:] * q[:-1]).sum(-1) < 0, -1.0, 1.0)
    q = q * np.concatenate([np.ones_like(flip[:1]), np.cumprod(flip, axis=0)], 0)[..., None]
    q = gaussian_filter1d(q, sigma, axis=0, mode="nearest")
    return quat_to_rotvec(q / np.linalg.norm(q, axis=-1, keepdims=True).clip(min=1e-12))


# ------------------------------------------------------------------------------- torch (autograd)


def rotvec_to_matrix_torch(r: "torch.Tensor") -> "torch.Tensor":
    """Rodrigues in torch for autograd: (..., 3) rotation vectors -> (..., 3, 3), smooth at zero.

    ``R = I + a [r]x + b [r]x^2`` with ``a = sin t / t`` and ``b = (1 - cos t) / t^2``; ``t`` is
    ``|r|`` padded by 1e-12 under the square root so the gradient at r = 0 is finite. Agrees with
    :func:`rotvec_to_matrix` to rounding (tests/test_rotations.py).
    """
    import torch

    t2 = (r * r).sum(-1)
    t = torch.sqrt(t2 + 1e-12)
    a = torch.sin(t) / t
    b = (1.0 - torch.cos(t)) / (t2 + 1e-12)
    c = 1.0 - b * t2
    # The nine entries from per-rotation scalars ([r]x^2 = r r^T - |r|^2 I written out): ops on
    # (...,) tensors instead of broadcasts over (..., 3, 3), a third of the time forward and back
    # (SMPLify evaluates this for every joint of every frame at each step).
    x, y, z = r.unbind(-1)
    bx, by = b * x, b * y
    ax, ay, az = a * x, a * y, a * z
    bxy, bxz, byz = bx * y, bx * z, by * z
    return torch.stack([c + bx * x, bxy - az, bxz + ay,
                        bxy + az, c + by * y, byz - ax,
                        bxz - ay, byz + ax, c + b * z * z], -1).reshape(r.shape[:-1] + (3, 3))
