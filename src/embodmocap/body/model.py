"""The body model adapter: SMPL skinning (via ``smplx``) behind one small, batched API.

Parameter semantics are exactly SMPL's, because world-space parameters and every export depend
on them. For betas ``b``, the shaped rest pose has joints ``J(b)`` (``J_regressor`` applied to the
shaped template). A frame's vertices are

    v = R(global_orient) @ (v_posed - J_0(b)) + J_0(b) + transl

i.e. the whole posed body is rotated **about the rest pelvis joint J_0(b)**, then translated.
``transl`` is therefore *not* the pelvis position: the pelvis lands at ``J_0(b) + transl``.
:meth:`BodyModel.pelvis_offset` gives ``J_0(b)``; :func:`params_for_world_frame` uses it to move
parameters rigidly into another frame.

Frames: parameters live in whatever frame the caller says (SMPL's canonical frame is Y up, facing
+Z, left on +X; world-space params in this package are in the Z-up world).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
from numpy.typing import NDArray

from embodmocap.body.joints import (
    FACE_KEYPOINT_NAMES, SMPL_FACE_VERTEX_IDS, SMPL_JOINT_NAMES, smpl_to_coco17,
)
from embodmocap.body.pkl import check_model_arrays, load_model_arrays
from embodmocap.errors import InputError
from embodmocap.geometry.transforms import is_rigid
from embodmocap.types import SmplParams

log = logging.getLogger(__name__)

TensorLike = Any  # numpy array, torch tensor or nested sequence


@dataclass(frozen=True)
class BodyOutput:
    """Posed bodies for T frames (torch tensors, differentiable w.r.t. the parameters).

    Attributes:
        vertices: (T, V, 3) mesh vertices, metres, in the parameters' frame.
        joints: (T, 24, 3) SMPL joints in SMPL order (:data:`SMPL_JOINT_NAMES`).
        coco17: (T, 17, 3) COCO-17 keypoints (see :mod:`embodmocap.body.joints`).
    """

    vertices: torch.Tensor
    joints: torch.Tensor
    coco17: torch.Tensor


def _smpl_class(num_shape: int) -> type:
    """An ``smplx.SMPL`` that keeps all ``num_shape`` shape components of the file.

    smplx keeps at most 10 components (and prints a warning) when a file has fewer than its
    ``SHAPE_SPACE_DIM`` (300); setting that to the file's own count keeps them all, silently.
    """
    import smplx

    return type("SMPLAllBetas", (smplx.SMPL,), {"SHAPE_SPACE_DIM": int(num_shape)})


def _guess_gender(arrays: Mapping[str, np.ndarray], source: str) -> str:
    if "gender" in arrays:
        return str(arrays["gender"])
    name = Path(source).name.lower()
    for pattern, gender in ((r"female|_f_", "female"), (r"(?<!fe)male|_m_", "male"), (r"neutral", "neutral")):
        if re.search(pattern, name):
            return gender
    return "unknown"


class BodyModel:
    """An SMPL-layout body model: skinning, joints, COCO-17 keypoints, frame changes.

    Build it with :func:`load_body_model`. Attributes are read-only numpy arrays; skinning
    modules are created per (dtype, device) on first use.
    """

    def __init__(self, arrays: Mapping[str, np.ndarray], source: str = "<arrays>") -> None:
        arrays = check_model_arrays(dict(arrays), None if source.startswith("<") else source)
        self.source = source
        self.gender = _guess_gender(arrays, source)
        self._arrays = arrays
        V = arrays["v_template"].shape[0]
        if "vertex_ids" in arrays:
            ids = dict(zip(map(str, arrays["vertex_id_names"]), map(int, arrays["vertex_ids"])))
        elif V == 6890:  # the official SMPL / SMPL-H topology
            ids = dict(SMPL_FACE_VERTEX_IDS)
        else:
            ids = {}
        missing = [n for n in FACE_KEYPOINT_NAMES if n not in ids]
        if missing:
            raise InputError(
                None if source.startswith("<") else source,
                f"no vertex ids for face keypoints {missing} on this {V}-vertex mesh",
                "add vertex_ids and vertex_id_names arrays to the model file",
            )
        self.vertex_ids: dict[str, int] = {n: ids[n] for n in FACE_KEYPOINT_NAMES}
        self.joint_names: tuple[str, ...] = SMPL_JOINT_NAMES
        self.faces: NDArray[np.int64] = self._readonly(arrays["f"])
        self.parents: NDArray[np.int64] = self._readonly(arrays["kintree_table"][0])
        self.v_template: NDArray[np.float64] = self._readonly(arrays["v_template"])
        self.lbs_weights: NDArray[np.float64] = self._readonly(arrays["weights"])
        # Rest joints are linear in betas: J(b) = J_regressor @ (v_template + shapedirs @ b).
        Jr = arrays["J_regressor"]
        self._J_template = Jr @ arrays["v_template"]  # (24, 3)
        self._J_shapedirs = np.einsum("jv,vcb->jcb", Jr, arrays["shapedirs"])  # (24, 3, B)
        self._modules: dict[tuple[torch.dtype, str], torch.nn.Module] = {}

    @staticmethod
    def _readonly(a: np.ndarray) -> np.ndarray:
        a = np.array(a, copy=True)
        a.setflags(write=False)
        return a

    def __repr__(self) -> str:
        return (
            f"BodyModel(source={self.source!r}, vertices={self.num_vertices}, "
            f"betas={self.num_betas}, gender={self.gender!r})"
        )

    @property
    def num_betas(self) -> int:
        """Number of shape coefficients the model uses."""
        return int(self._arrays["shapedirs"].shape[-1])

    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def arrays(self) -> dict[str, np.ndarray]:
        """Copies of the model's arrays in the SMPL file layout (e.g. to write the model out)."""
        return {k: np.array(v, copy=True) for k, v in self._arrays.items()}

    # ---------------------------------------------------------------- skinning

    def _module(self, dtype: torch.dtype, device: torch.device) -> torch.nn.Module:
        key = (dtype, str(device))
        if key not in self._modules:
            import smplx

            a = self._arrays
            smpl = _smpl_class(self.num_betas)(
                model_path="",
                data_struct=smplx.utils.Struct(**a),
                num_betas=self.num_betas,
                create_betas=False, create_global_orient=False, create_body_pose=False,
                create_transl=False,
                dtype=dtype,
                gender=self.gender,
                vertex_ids=self.vertex_ids,
                use_hands=False, use_feet_keypoints=False,  # only the 5 face vertices are needed
            )
            # smplx passes model arrays through float32 on the way in; put them back at full
            # precision so float64 results are exact (same layouts as smplx builds them).
            exact = {
                "v_template": a["v_template"], "shapedirs": a["shapedirs"], "J_regressor": a["J_regressor"],
                "lbs_weights": a["weights"], "posedirs": a["posedirs"].reshape(-1, a["posedirs"].shape[-1]).T,
            }
            for name, value in exact.items():
                getattr(smpl, name).copy_(torch.as_tensor(np.ascontiguousarray(value), dtype=dtype))
            self._modules[key] = smpl.to(device).eval()
        return self._modules[key]

    def forward(
        self,
        betas: TensorLike,
        global_orient: TensorLike,
        body_pose: TensorLike,
        transl: TensorLike | None = None,
        *,
        dtype: torch.dtype | None = None,
        device: str | torch.device | None = None,
    ) -> BodyOutput:
        """Pose the body for T frames.

        Args:
            betas: (B,) or (1, B) shared by all frames, or (T, B) per frame; B <= num_betas
                (missing trailing coefficients are zero).
            global_orient: (T, 3) axis-angle root rotation (about the rest pelvis joint).
            body_pose: (T, 69) or (T, 23, 3) axis-angle rotations of joints 1..23.
            transl: (T, 3) SMPL translation, metres; None = zero.
            dtype: float32 or float64; default: the dtype of the first torch tensor given, else
                float32.
            device: default: the device of the first torch tensor given, else CPU.

        Torch inputs keep their autograd graph; numpy inputs are converted.
        """
        tensors = [x for x in (betas, global_orient, body_pose, transl) if isinstance(x, torch.Tensor)]
        if dtype is None:
            dtype = tensors[0].dtype if tensors and tensors[0].is_floating_point() else torch.float32
        if device is None:
            device = tensors[0].device if tensors else torch.device("cpu")
        device = torch.device(device)
        conv = lambda x: (x.to(dtype=dtype, device=device) if isinstance(x, torch.Tensor)  # noqa: E731
                          else torch.as_tensor(np.array(x, dtype=np.float64), dtype=dtype, device=device))

        go = conv(global_orient).reshape(-1, 3)
        T = go.shape[0]
        pose = conv(body_pose).reshape(T, 69) if T else conv(body_pose).reshape(0, 69)
        tr = conv(transl).reshape(T, 3) if transl is not None else torch.zeros(T, 3, dtype=dtype, device=device)
        b = conv(betas)
        b = b.reshape(1, -1) if b.ndim == 1 else b
        if b.shape[-1] > self.num_betas:
            raise ValueError(f"got {b.shape[-1]} betas, the model has {self.num_betas}")
        if b.shape[0] not in (1, T):
            raise ValueError(f"betas must be (B,), (1, B) or (T={T}, B); got {tuple(b.shape)}")
        b = torch.nn.functional.pad(b, (0, self.num_betas - b.shape[-1]))
        if T == 0:
            V = self.num_vertices
            z = lambda n: torch.zeros(0, n, 3, dtype=dtype, device=device)  # noqa: E731
            return BodyOutput(z(V), z(24), z(17))

        out = self._module(dtype, device)(betas=b, global_orient=go, body_pose=pose, transl=tr)
        joints = out.joints[:, :24]
        return BodyOutput(out.vertices, joints, smpl_to_coco17(joints, out.vertices, self.vertex_ids))

    __call__ = forward

    def from_params(
        self, params: SmplParams, *, dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu"
    ) -> BodyOutput:
        """Pose the body for every frame of ``params`` (its betas shared by all frames)."""
        return self.forward(params.betas, params.global_orient, params.body_pose, params.transl, dtype=dtype, device=device)

    def joints_from_params(self, params: SmplParams, *, dtype: torch.dtype = torch.float64,
                           device: str | torch.device = "cpu") -> torch.Tensor:
        """(T, 24, 3) the posed joints of every frame of ``params``: :meth:`from_params`'s
        ``joints``, bit for bit, without skinning the mesh (joints do not depend on the pose blend
        shapes; the shaped rest joints, one set for the sequence, are regressed once)."""
        from smplx.lbs import batch_rigid_transform, batch_rodrigues, blend_shapes, vertices2joints

        device = torch.device(device)
        smpl = self._module(dtype, device)
        conv = lambda x: torch.as_tensor(np.array(x, dtype=np.float64), dtype=dtype, device=device)  # noqa: E731
        T = len(params)
        if T == 0:
            return torch.zeros(0, 24, 3, dtype=dtype, device=device)
        pose = torch.cat([conv(params.global_orient).reshape(T, 3), conv(params.body_pose).reshape(T, 69)], 1)
        b = conv(params.betas).reshape(1, -1)
        b = torch.nn.functional.pad(b, (0, self.num_betas - b.shape[-1]))
        # smplx regresses the rest joints once per frame from identical rows (T of them): whole
        # blocks of 64 rows give every row the bits of the first (SIMD vectors, BLAS tiles), the
        # T % 64 rows after them the bits of a batch's tail. 64 rows and that tail reproduce both.
        tail = T % 64 if T > 64 else 0
        n = min(T, 64) + tail
        J = vertices2joints(smpl.J_regressor, smpl.v_template + blend_shapes(b.expand(max(n, 1), -1), smpl.shapedirs))
        J = J if n == T else torch.cat([J[:1].expand(T - tail, -1, -1), J[n - tail:]])
        rot = batch_rodrigues(pose.reshape(-1, 3)).reshape(T, -1, 3, 3)
        joints, _ = batch_rigid_transform(rot, J, smpl.parents, dtype=dtype)
        return joints + conv(params.transl).reshape(T, 3).unsqueeze(1)

    # ---------------------------------------------------------------- rest shape

    def _betas_np(self, betas: TensorLike | None) -> NDArray[np.float64]:
        b = np.zeros(self.num_betas) if betas is None else np.asarray(betas, dtype=np.float64)
        if b.shape[-1] > self.num_betas:
            raise ValueError(f"got {b.shape[-1]} betas, the model has {self.num_betas}")
        pad = [(0, 0)] * (b.ndim - 1) + [(0, self.num_betas - b.shape[-1])]
        return np.pad(b, pad)

    def rest_joints(self, betas: TensorLike | None = None) -> NDArray[np.float64]:
        """(..., 24, 3) joints of the shaped rest pose (zero pose, zero transl) for betas (..., B)."""
        b = self._betas_np(betas)
        return self._J_template + np.einsum("jcb,...b->...jc", self._J_shapedirs, b)

    def pelvis_offset(self, betas: TensorLike | None = None) -> NDArray[np.float64]:
        """(..., 3) rest-pose pelvis position ``J_0(betas)``: the pivot of ``global_orient``.

        With zero ``transl`` the posed pelvis is here whatever the pose; in general it is at
        ``pelvis_offset(betas) + transl``.
        """
        return self.rest_joints(betas)[..., 0, :]

    def params_for_world_frame(self, params: SmplParams, T_new_old: NDArray) -> SmplParams:
        """Re-express ``params`` in another frame; see :func:`params_for_world_frame`."""
        return params_for_world_frame(params, T_new_old, self)


def params_for_world_frame(params: SmplParams, T_new_old: NDArray, model: BodyModel) -> SmplParams:
    """SMPL parameters describing the same bodies after the rigid change of frame ``T_new_old``.

    With ``R, t`` the rotation and translation of ``T_new_old`` (4, 4) and ``p = J_0(betas)`` the
    rest pelvis (:meth:`BodyModel.pelvis_offset`):

        global_orient' = R * global_orient        (rotation composition)
        transl'        = R (transl + p) + t - p

    so that every vertex ``v`` of the old frame becomes ``R v + t``. Betas and body pose do not
    change. Raises ValueError if ``T_new_old`` is not a rigid transform.
    """
    from scipy.spatial.transform import Rotation

    T = np.asarray(T_new_old, dtype=np.float64)
    if T.shape != (4, 4) or not bool(is_rigid(T)):
        raise ValueError(f"T_new_old must be a rigid 4x4 transform, got shape {T.shape}")
    R, t = T[:3, :3], T[:3, 3]
    p = model.pelvis_offset(params.betas)
    if len(params) == 0:
        return params
    go = (Rotation.from_matrix(R) * Rotation.from_rotvec(np.array(params.global_orient))).as_rotvec()
    transl = (params.transl + p) @ R.T + t - p
    return dataclasses.replace(params, global_orient=go, transl=transl)


@functools.lru_cache(maxsize=1)
def _test_model() -> BodyModel:
    from embodmocap.body.testmodel import make_test_model

    return BodyModel(make_test_model(), source="<generated test model>")


def load_body_model(path: str | Path | None) -> BodyModel:
    """Load a body model file (.pkl or .npz in the SMPL layout).

    ``None`` gives the generated test model (seed 0, 10 betas), built once per process and
    shared: treat it as read-only.
    """
    if path is None:
        return _test_model()
    path = Path(path)
    model = BodyModel(load_model_arrays(path), source=str(path))
    # Every stage loads the model: say so once per file and process, not once per stage.
    level = logging.DEBUG if str(path) in _ANNOUNCED else logging.INFO
    _ANNOUNCED.add(str(path))
    log.log(level, "loaded body model %s (%d vertices, %d betas)", path, model.num_vertices, model.num_betas)
    return model


#: Body model files already announced in the log by :func:`load_body_model`.
_ANNOUNCED: set[str] = set()
