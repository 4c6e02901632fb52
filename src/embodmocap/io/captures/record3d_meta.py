"""Record3D's metadata JSON, shared by both export forms (:mod:`embodmocap.io.captures.record3d`,
:mod:`embodmocap.io.captures.record3d_exr`, which is read through the first): its parse and the
camera poses it holds (format notes: the first module's docstring)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.geometry.rotations import quat_to_matrix
from embodmocap.geometry.transforms import T_zup_from_yup, gl_to_cv_cam, make_T
from embodmocap.io.captures.common import Problem

FORMAT = "record3d"
#: A first pose within this of the identity (rotation angle in radians, translation in metres)
#: marks poses relative to the first camera (older app versions).
IDENTITY_TOL = 1e-6


@dataclass(frozen=True)
class Record3dMetadata:
    """The export's ``metadata`` / ``metadata.json``, in every app version's form.

    Attributes:
        w, h: RGB size the intrinsics are for.
        K3: (3, 3) intrinsics at w x h.
        fps: frame rate.
        poses: (N, 7) [qx, qy, qz, qw, px, py, pz] ARKit camera-to-world (or relative to the first
            camera, see ``init_pose``).
        depth_size: (dw, dh), or None when the metadata does not say (older apps).
        frame_timestamps: (N,) seconds, or None (older apps).
        init_pose: (7,) the first camera in ARKit's world when present (older apps), else None.
    """

    w: int
    h: int
    K3: NDArray[np.float64]
    fps: float
    poses: NDArray[np.float64]
    depth_size: tuple[int, int] | None
    frame_timestamps: NDArray[np.float64] | None
    init_pose: NDArray[np.float64] | None


def parse_metadata(data: bytes, where: Path) -> Record3dMetadata:
    """Parse the metadata JSON; raises one :class:`InputError` naming what is malformed."""
    try:
        meta = json.loads(data)
        w, h = int(meta["w"]), int(meta["h"])
        fps = float(meta.get("fps", 0) or 0)
        K3 = np.asarray(meta["K"], dtype=np.float64).reshape(3, 3).T  # stored column-major
        poses = np.asarray(meta.get("poses", []), dtype=np.float64).reshape(-1, 7)
        dsize = (int(meta["dw"]), int(meta["dh"])) if "dw" in meta and "dh" in meta else None
        stamps = np.asarray(meta["frameTimestamps"], dtype=np.float64).reshape(-1) if "frameTimestamps" in meta else None
        init = np.asarray(meta["initPose"], dtype=np.float64).reshape(7) if meta.get("initPose") is not None else None
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, ValueError) as err:
        raise InputError(where, f"malformed metadata ({err.__class__.__name__}: {err})",
                         "expected JSON with K, w, h, fps and poses (Record3D writes it with every export)") from err
    if fps <= 0 and stamps is None:
        raise InputError(where, "metadata has neither fps nor frameTimestamps", "export the recording again")
    if fps <= 0:  # only frame times: the rate is their median step
        steps = np.diff(stamps) if stamps is not None else np.zeros(0)
        steps = steps[steps > 0]
        if not len(steps):
            raise InputError(where, "metadata has no fps and its frameTimestamps do not increase",
                             "export the recording again")
        fps = 1.0 / float(np.median(steps))
    return Record3dMetadata(w, h, K3, fps, poses, dsize, stamps, init)


def world_poses(meta: Record3dMetadata, where: Path) -> tuple[NDArray[np.float64], str, list[Problem]]:
    """(T_world_cam (N, 4, 4) in the package convention, a note on the pose form, problems).

    Poses relative to the first camera (``poses[0]`` the identity) are put in ARKit's world with
    ``initPose``; without one they are refused, since their world is not gravity-aligned.
    """
    T_pose = make_T(quat_to_matrix(meta.poses[:, :4], invalid="nan"), meta.poses[:, 4:])
    problems: list[Problem] = []
    note = "poses in ARKit's world"
    if len(T_pose) and _is_identity(T_pose[0]):
        if meta.init_pose is not None:
            T_init = make_T(quat_to_matrix(meta.init_pose[:4], invalid="nan"), meta.init_pose[4:])
            T_pose = T_init @ T_pose
            note = "poses relative to the first camera, put in ARKit's world with initPose"
        else:
            note = "poses relative to the first camera, no initPose"
            problems.append(Problem(where, "poses are relative to the first camera (poses[0] is the identity) and "
                                           "there is no initPose: the world would not be gravity-aligned",
                                    "export again with the app's metadata intact (older Record3D versions write "
                                    "initPose beside poses)"))
    return gl_to_cv_cam(T_zup_from_yup() @ T_pose), note, problems


def _is_identity(T: NDArray) -> bool:
    return bool(np.all(np.isfinite(T)) and np.abs(T[:3, :3] - np.eye(3)).max() < IDENTITY_TOL
                and np.abs(T[:3, 3]).max() < IDENTITY_TOL)


