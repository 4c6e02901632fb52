"""Looking at a finished sequence: the web viewer (:mod:`.viewer`) and overlay videos (:mod:`.render`).

This module holds what both share: reading a sequence's Stage IV outputs into one frozen
:class:`SequenceData`, and :class:`BodyFrames`, which poses the body a chunk of frames at a time
(float32) so a long sequence never holds all ``T x V x 3`` vertices in memory.

Frames: ``SequenceData`` rows are the rows of ``smpl_world.npz``; ``frames[i]`` is the sequence
frame of row ``i``, and a view's camera of that row is ``cameras_final`` row ``frames[i]``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io import stage_files
from embodmocap.io.layout import SessionLayout
from embodmocap.io.smpl_file import read_smpl_npz
from embodmocap.types import Intrinsics, SmplParams

log = logging.getLogger(__name__)

__all__ = ["ViewCameras", "Keypoints3D", "SequenceData", "BodyFrames", "load_sequence", "read_cameras_final",
           "read_keypoints3d", "RUN_MOTION_FIRST"]

#: What to tell a user whose Stage IV outputs are missing (``{seq}`` is filled in).
RUN_MOTION_FIRST = "run `embodmocap motion SESSION --seq {seq}` first"


@dataclass(frozen=True)
class ViewCameras:
    """One view's final cameras (``<view>/cameras_final.npz``).

    Attributes:
        name: view name (``v1``, ``v2``).
        intrinsics: the RGB camera, pixels of the raw capture's frames.
        T_world_cam: (N, 4, 4) camera-to-world per sequence frame, OpenCV axes, scene world (Z up).
        raw_frames: (N,) raw capture frame shown at each sequence frame.
    """

    name: str
    intrinsics: Intrinsics
    T_world_cam: NDArray[np.float64]
    raw_frames: NDArray[np.int64]


@dataclass(frozen=True)
class Keypoints3D:
    """Triangulated COCO-17 keypoints (``keypoints3d.npz``).

    Attributes:
        points: (N, 17, 3) world metres, NaN where not triangulated.
        conf: (N, 17) confidence in [0, 1].
        filled: (N, 17) bool, True where a gap was filled by interpolation.
    """

    points: NDArray[np.float64]
    conf: NDArray[np.float64]
    filled: NDArray[np.bool_]


@dataclass(frozen=True)
class SequenceData:
    """Everything the viewer and the renderer show of one sequence.

    Attributes:
        name: sequence name.
        scene: the scene the sequence was captured in (manifest).
        params: world SMPL parameters, T rows (``smpl_world.npz``).
        frames: (T,) sequence frame of each row.
        views: view name -> final cameras.
        keypoints3d: triangulated keypoints indexed by sequence frame, or None when the file is absent.
        pelvis: (T, 3) pelvis path in the world, metres (``joints_world.npz`` joint 0, or posed body).
        body_model: the body model file named by the manifest (None = generated test model).
    """

    name: str
    scene: str
    params: SmplParams
    frames: NDArray[np.int64]
    views: dict[str, ViewCameras]
    keypoints3d: Keypoints3D | None
    pelvis: NDArray[np.float64]
    body_model: Path | None


def read_cameras_final(path: str | Path, view: str, seq: str = "NAME") -> ViewCameras:
    """Read ``<view>/cameras_final.npz`` (keys K (3,3), width, height, T_world_cam (N,4,4), raw_frames (N,))."""
    c = stage_files.read_cameras(path, "cameras_final")
    K = Intrinsics.from_K(c.K, int(c.width), int(c.height))
    return ViewCameras(view, K, np.asarray(c.T_world_cam, dtype=np.float64), np.asarray(c.raw_frames, dtype=np.int64))


def read_keypoints3d(path: str | Path, seq: str = "NAME") -> Keypoints3D:
    """Read ``keypoints3d.npz`` (keys points (N,17,3), conf (N,17), filled (N,17))."""
    k3 = stage_files.read_keypoints3d(path)
    pts = np.asarray(k3.points, dtype=np.float64)
    filled = k3.filled if k3.filled is not None else np.zeros(pts.shape[:2], bool)
    return Keypoints3D(pts, np.asarray(k3.conf, dtype=np.float64), np.asarray(filled, dtype=bool))


def load_sequence(session: str | Path, seq: str) -> SequenceData:
    """Read a sequence's Stage IV outputs (``smpl_world``, both ``cameras_final``, optional
    ``keypoints3d`` and ``joints_world``) and its manifest entry.

    Raises:
        InputError: a required file is missing or malformed (the message says to run the motion
            stage), the sequence is not in the manifest, or the cameras cover fewer frames than
            the motion.
    """
    from embodmocap.io.manifest import load_manifest

    lay = SessionLayout(Path(session))
    manifest = load_manifest(lay.manifest)
    if seq not in manifest.sequences:
        raise InputError(lay.manifest, f"no sequence named {seq!r} (have {sorted(manifest.sequences)})",
                         "pass one of the manifest's sequence names")
    out = lay.sequence(seq)
    params, frames = read_smpl_npz(out.smpl_world)
    views = {v: read_cameras_final(out.view(v).cameras_final, v, seq) for v in manifest.sequences[seq].view_names}
    for v, cams in views.items():
        if len(frames) and (frames.min() < 0 or frames.max() >= len(cams.T_world_cam)):
            raise InputError(out.view(v).cameras_final, f"{len(cams.T_world_cam)} camera rows, but the motion "
                             f"reaches sequence frame {int(frames.max())}", RUN_MOTION_FIRST.format(seq=seq))
    kp3d = read_keypoints3d(out.keypoints3d, seq) if out.keypoints3d.is_file() else None
    pelvis = _pelvis_path(out.joints_world, params, frames, manifest.body_model, seq)
    return SequenceData(seq, manifest.sequences[seq].scene, params, frames, views, kp3d, pelvis, manifest.body_model)


def _pelvis_path(path: Path, params: SmplParams, frames: NDArray, body_model: Path | None, seq: str) -> NDArray:
    """(T, 3) pelvis positions: from ``joints_world.npz`` when present, else posed from the params."""
    if path.is_file():
        joints = np.asarray(stage_files.read_world_joints(path).joints, dtype=np.float64)
        if joints.shape == (len(frames), 24, 3):
            return joints[:, 0]
        log.warning("%s: joints %s do not match %d motion rows; posing the body instead", path, joints.shape, len(frames))
    from embodmocap.body.model import load_body_model

    model = load_body_model(body_model)
    # The pelvis is the rest pelvis rotated about itself, then translated: J_0(b) + transl.
    return model.pelvis_offset(params.betas) + np.asarray(params.transl)


class BodyFrames:
    """Posed body vertices per row, computed ``chunk`` rows at a time and cached per chunk.

    Only the most recent ``keep`` chunks are held, so memory stays at
    ``keep * chunk * V * 3 * 4`` bytes whatever the sequence length (2 x 64 x 6890 vertices: 10 MB).
    """

    def __init__(self, model, params: SmplParams, chunk: int = 64, keep: int = 2) -> None:
        if chunk < 1 or keep < 1:
            raise ValueError(f"chunk and keep must be >= 1, got {chunk}, {keep}")
        self.model = model
        self.params = params
        self.chunk = int(chunk)
        self.keep = int(keep)
        self._cache: dict[int, NDArray[np.float32]] = {}

    def __len__(self) -> int:
        return len(self.params)

    @property
    def faces(self) -> NDArray[np.int64]:
        return np.asarray(self.model.faces)

    def vertices(self, row: int) -> NDArray[np.float32]:
        """(V, 3) float32 world vertices of row ``row``."""
        if not 0 <= row < len(self):
            raise IndexError(f"row {row} outside 0..{len(self) - 1}")
        c = row // self.chunk
        block = self._cache.get(c)
        if block is None:
            block = self._pose(c * self.chunk, min(len(self), (c + 1) * self.chunk))
            if len(self._cache) >= self.keep:
                self._cache.pop(next(iter(self._cache)))  # oldest first (dicts keep insertion order)
            self._cache[c] = block
        return block[row - c * self.chunk]

    def _pose(self, start: int, stop: int) -> NDArray[np.float32]:
        p = self.params
        import torch  # on first use: the viewer's and renderer's settings load without it

        with torch.no_grad():
            out = self.model.forward(p.betas, p.global_orient[start:stop], p.body_pose[start:stop],
                                     p.transl[start:stop], dtype=torch.float32)
        return out.vertices.numpy()
