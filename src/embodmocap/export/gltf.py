"""Binary glTF 2.0 (``.glb``) export: the scene mesh plus the body as an animated skinned mesh.

Written with numpy and the standard library only (no glTF package needed to write).

Conventions (documented in ``docs/formats.md``):

- **Y up** as glTF requires: every world point is turned with ``R_YUP_ZUP`` (``(x, y, z) ->
  (x, z, -y)``) from our Z-up world. The body's rest pose is SMPL's canonical frame, already Y up.
- **Body = skinned mesh**: the shaped rest mesh (betas applied, zero pose) with SMPL's LBS weights
  reduced to the 4 largest per vertex and renormalised; a 24-joint skin whose joints are nodes
  named after :data:`SMPL_JOINT_NAMES`, each translated from its parent by the rest bone; inverse
  bind matrices ``translate(-J_j(betas))``.
- **Animation** ``"motion"``: one rotation channel per joint (SMPL's local rotations; the root's is
  turned into the Y-up world) and a translation channel on the pelvis (its world position
  ``J_0 + transl``), all LINEAR, one key per frame at ``(frame - frames[0]) / fps`` seconds.
  Quaternions are (x, y, z, w), made sign-continuous over time so interpolation takes the short way.
- **No pose correctives**: glTF skinning is plain LBS, so SMPL's pose blend shapes are not in the
  file; the skinned vertices equal SMPL's with ``posedirs`` zeroed.
"""

from __future__ import annotations

import json
import logging
import struct
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from embodmocap.body.joints import SMPL_JOINT_NAMES
from embodmocap.export.bvh import R_YUP_ZUP
from embodmocap.io.atomic import write_bytes
from embodmocap.types import SmplParams

log = logging.getLogger(__name__)

#: Joints influencing each vertex in the file (glTF's JOINTS_0 / WEIGHTS_0 hold 4).
MAX_INFLUENCES = 4

_FLOAT, _UBYTE, _USHORT, _UINT = 5126, 5121, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_NUMPY = {_FLOAT: np.float32, _UBYTE: np.uint8, _USHORT: np.uint16, _UINT: np.uint32}
_TYPES = {1: "SCALAR", 3: "VEC3", 4: "VEC4", 16: "MAT4"}


class _GlbBuffer:
    """Collects binary arrays (one bufferView each, 4-byte aligned) and their accessors."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array: NDArray, component: int, *, target: int | None = None,
            minmax: bool = False, normalized: bool = False) -> int:
        """Append ``array`` (N, k) or (N,) as one accessor; returns the accessor index."""
        a = np.ascontiguousarray(array, dtype=_NUMPY[component])
        width = 1 if a.ndim == 1 else int(np.prod(a.shape[1:]))
        self.data += b"\0" * (-len(self.data) % 4)
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": a.nbytes}
        if target is not None:
            view["target"] = target
        self.data += a.tobytes()
        self.views.append(view)
        acc = {"bufferView": len(self.views) - 1, "componentType": component, "count": int(a.shape[0]), "type": _TYPES[width]}
        if normalized:
            acc["normalized"] = True
        if minmax:
            flat = a.reshape(len(a), width)
            acc["min"] = flat.min(axis=0).tolist()
            acc["max"] = flat.max(axis=0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1


def _glb_bytes(doc: dict, binary: bytes) -> bytes:
    """Pack a glTF JSON document and its binary buffer into the GLB container."""
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    binary = bytes(binary) + b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return (
        struct.pack("<4sII", b"glTF", 2, total)
        + struct.pack("<I4s", len(js), b"JSON") + js
        + struct.pack("<I4s", len(binary), b"BIN\0") + binary
    )


def top_influences(weights: NDArray, k: int = MAX_INFLUENCES) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
    """The ``k`` largest LBS weights per vertex (V, J) -> joints (V, k), weights (V, k) summing to 1.

    Slots with zero weight point at joint 0 (glTF validators expect unused slots to be zero).
    """
    w = np.asarray(weights, dtype=np.float64)
    idx = np.argsort(-w, axis=1, kind="stable")[:, :k]
    top = np.take_along_axis(w, idx, axis=1)
    top = top / top.sum(axis=1, keepdims=True)
    idx = np.where(top > 0, idx, 0)
    return idx.astype(np.uint8), top.astype(np.float32)


def _continuous(q: NDArray) -> NDArray:
    """Flip quaternions (T, ..., 4) so consecutive keys have a non-negative dot product."""
    if len(q) < 2:
        return q
    dots = np.sum(q[1:] * q[:-1], axis=-1)
    signs = np.cumprod(np.where(dots < 0, -1.0, 1.0), axis=0)
    return np.concatenate([q[:1], q[1:] * signs[..., None]], axis=0)


def _body_arrays(params: SmplParams, model) -> dict[str, NDArray]:
    """Rest mesh, skin and animation arrays of the body, all in the Y-up glTF world."""
    import torch

    T = len(params)
    zero = np.zeros((1, 3))
    # Zero pose: no pose blend shapes, so this is the shaped template in SMPL's canonical frame
    # (Y up), the bind pose of the skin.
    rest = model.forward(params.betas, zero, np.zeros((1, 69)), zero, dtype=torch.float64)
    rest_v = rest.vertices[0].detach().cpu().numpy()  # (V, 3)
    rest_j = model.rest_joints(params.betas)  # (24, 3)
    R = Rotation.from_rotvec(params.poses.reshape(-1, 3)).as_matrix().reshape(T, 24, 3, 3)
    R[:, 0] = R_YUP_ZUP @ R[:, 0]
    quats = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat().reshape(T, 24, 4)  # (x, y, z, w)
    return {
        "rest_v": rest_v,
        "rest_j": rest_j,
        "quats": _continuous(quats),
        "root_t": (rest_j[0] + params.transl) @ R_YUP_ZUP.T,  # pelvis world position, Y up
    }


def glb_document(params: SmplParams, model, scene: tuple | None = None, *, frames: NDArray | None = None) -> bytes:
    """The GLB bytes of the body animation (+ the scene mesh when given).

    Args:
        params: world SMPL parameters (Z up), T >= 1 frames.
        model: :class:`embodmocap.body.model.BodyModel` (rest shape, weights, faces, parents).
        scene: ``(vertices (N, 3), faces (F, 3)[, colours (N, 3) in 0..1 or (0, 3)])`` in our
            Z-up world (e.g. from ``read_mesh_ply``), or None for the body alone.
        frames: (T,) sequence frames giving the key times; default ``0..T-1``.
    """
    T = len(params)
    if T == 0:
        raise ValueError("cannot export an empty motion")
    frames = np.arange(T) if frames is None else np.asarray(frames, dtype=np.int64)
    times = ((frames - frames[0]) / float(params.fps)).astype(np.float32)
    body = _body_arrays(params, model)
    buf = _GlbBuffer()
    nodes: list[dict] = []
    meshes: list[dict] = []
    materials = [
        {"name": "scene", "doubleSided": True, "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0, "roughnessFactor": 0.9}},
        {"name": "body", "pbrMetallicRoughness": {"baseColorFactor": [0.75, 0.6, 0.5, 1], "metallicFactor": 0.0, "roughnessFactor": 0.7}},
    ]
    roots: list[int] = []

    if scene is not None:
        v, f = np.asarray(scene[0], dtype=np.float64), np.asarray(scene[1], dtype=np.int64)
        attrs = {"POSITION": buf.add(v @ R_YUP_ZUP.T, _FLOAT, target=_ARRAY_BUFFER, minmax=True)}
        colours = np.asarray(scene[2]) if len(scene) > 2 and scene[2] is not None else np.zeros((0, 3))
        if len(colours) == len(v) and len(v):
            rgba = np.concatenate([np.clip(colours, 0, 1) * 255, np.full((len(v), 1), 255.0)], axis=1)
            # RGBA bytes: vertex attributes must be 4-byte aligned, which RGB bytes are not.
            attrs["COLOR_0"] = buf.add(np.round(rgba), _UBYTE, target=_ARRAY_BUFFER, normalized=True)
        idx = buf.add(f.reshape(-1), _UINT, target=_ELEMENT_ARRAY_BUFFER)
        meshes.append({"name": "scene", "primitives": [{"attributes": attrs, "indices": idx, "material": 0}]})
        nodes.append({"name": "scene", "mesh": len(meshes) - 1})
        roots.append(len(nodes) - 1)

    # Joint nodes: node index = first + SMPL joint index.
    parents = np.asarray(model.parents, dtype=np.int64)
    first = len(nodes)
    rest_j = body["rest_j"]
    for j, name in enumerate(SMPL_JOINT_NAMES):
        p = int(parents[j])
        offset = rest_j[j] - (rest_j[p] if p >= 0 else 0.0)
        nodes.append({"name": name, "translation": offset.tolist()})
    for j in range(24):
        kids = [first + c for c in range(24) if parents[c] == j]
        if kids:
            nodes[first + j]["children"] = kids
    root_joint = first + int(np.flatnonzero(parents < 0)[0])
    roots.append(root_joint)

    joints, weights = top_influences(model.lbs_weights)
    body_attrs = {
        "POSITION": buf.add(body["rest_v"], _FLOAT, target=_ARRAY_BUFFER, minmax=True),
        "JOINTS_0": buf.add(joints, _UBYTE, target=_ARRAY_BUFFER),
        "WEIGHTS_0": buf.add(weights, _FLOAT, target=_ARRAY_BUFFER),
    }
    body_idx = buf.add(np.asarray(model.faces, dtype=np.int64).reshape(-1), _UINT, target=_ELEMENT_ARRAY_BUFFER)
    meshes.append({"name": "body", "primitives": [{"attributes": body_attrs, "indices": body_idx, "material": 1}]})
    # Inverse bind matrices: at rest every joint frame is axis-aligned at J_j, so the inverse is a
    # pure translation. glTF stores matrices column-major.
    ibm = np.tile(np.eye(4), (24, 1, 1))
    ibm[:, :3, 3] = -rest_j
    ibm_acc = buf.add(ibm.transpose(0, 2, 1).reshape(24, 16), _FLOAT)
    skin = {"name": "smpl", "joints": list(range(first, first + 24)), "inverseBindMatrices": ibm_acc, "skeleton": root_joint}
    nodes.append({"name": "body", "mesh": len(meshes) - 1, "skin": 0})
    roots.append(len(nodes) - 1)

    t_acc = buf.add(times, _FLOAT, minmax=True)
    samplers = [{"input": t_acc, "output": buf.add(body["root_t"], _FLOAT), "interpolation": "LINEAR"}]
    channels = [{"sampler": 0, "target": {"node": root_joint, "path": "translation"}}]
    for j in range(24):
        samplers.append({"input": t_acc, "output": buf.add(body["quats"][:, j], _FLOAT), "interpolation": "LINEAR"})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": first + j, "path": "rotation"}})

    doc = {
        "asset": {"version": "2.0", "generator": "embodmocap export"},
        "extras": {"fps": float(params.fps), "gender": params.gender, "betas": np.asarray(params.betas).tolist(),
                   "first_frame": int(frames[0]), "up_axis": "Y", "units": "m"},
        "scene": 0,
        "scenes": [{"name": "embodmocap", "nodes": roots}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": materials,
        "skins": [skin],
        "animations": [{"name": "motion", "samplers": samplers, "channels": channels}],
        "accessors": buf.accessors,
        "bufferViews": buf.views,
        "buffers": [{"byteLength": len(buf.data) + (-len(buf.data) % 4)}],
    }
    return _glb_bytes(doc, bytes(buf.data))


def write_glb(path: str | Path, params: SmplParams, model, scene: tuple | None = None, *, frames: NDArray | None = None) -> Path:
    """Write :func:`glb_document` to ``path`` atomically; returns the path."""
    data = glb_document(params, model, scene, frames=frames)
    write_bytes(path, data)
    log.info("wrote glTF %s (%d frames, %.1f MB)", path, len(params), len(data) / 1e6)
    return Path(path)
