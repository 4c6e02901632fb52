"""``SequenceDataset``: windows of finished sequences for training motion models (PyTorch).

    ds = SequenceDataset("DATASET", window=60, stride=30, scenes=("scene0",),
                         max_metrics={"w_mpjpe_mm": 80.0}, camera_view="v1")
    loader = torch.utils.data.DataLoader(ds, batch_size=32, shuffle=True, num_workers=4)

The sequences come from the dataset's catalog (``DATASET/catalog.sqlite``; built when missing):
those whose every stage is done, filtered by scene, session, an SQL condition on the catalog's
``sequences`` table and thresholds on its metrics. Every file is read through the package's
typed readers (``io.smpl_file``, ``io.stage_files``, ``io.mesh_file``), each sequence once per
process (DataLoader workers each keep their own small cache; nothing unpicklable is held).

An item is a dict (``T`` = ``window`` frames):

=================== ================ =======================================================
key                 shape, dtype     meaning
=================== ================ =======================================================
``poses``           (T, 72) float32  SMPL axis-angle, world frame (global orient + 23 joints)
``trans``           (T, 3) float32   SMPL ``transl``, world metres
``betas``           (B,) float32     shape of the sequence
``joints``          (T, 24, 3) f32   SMPL joints, world metres (Z up)
``contacts``        (T, 4) bool      left/right ankle, left/right foot in contact
``height_map``      (K, K) float32   ground z around the root at the window's first frame
``height_map_xy``   (2,) float32     world x, y of the patch's centre (rows +y, columns +x)
``valid``           (T,) bool        frames Stage IV could place (see ``smpl_world.npz``)
``frames``          (T,) int64       sequence frames
``fps``             () float32       frames per second
``joints_cam``      (T, 24, 3) f32   with ``camera_view``: joints in that view's camera (OpenCV)
``T_cam_world``     (T, 4, 4) f32    with ``camera_view``: world-to-camera of that view
``session``, ``sequence``, ``scene`` str
=================== ================ =======================================================
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from embodmocap.data.terrain import CONTACT_JOINTS, HeightGrid, foot_contacts, height_grid, height_patch, sample_heights
from embodmocap.errors import InputError


@dataclass(frozen=True)
class SequenceRef:
    """A finished sequence the dataset draws windows from."""

    session: str
    sequence: str
    scene: str
    session_path: str
    frames: int


class SequenceDataset(Dataset):
    """Windows of ``window`` frames of finished sequences (see the module docstring).

    Args:
        dataset: a folder of session folders, one session folder, or a list file (as ``batch``).
        window: frames per item; ``stride``: frames between the starts of consecutive windows.
        scenes: keep only these scenes (names, or ``session/scene``); None = all.
        sessions: keep only these sessions; None = all.
        where: an SQL condition on the catalog's ``sequences`` table (e.g. ``"valid_frames >= 100"``).
        min_metrics, max_metrics: thresholds on the catalog's metrics (``evaluation.json`` keys,
            e.g. ``{"w_mpjpe_mm": 80.0}``); a sequence without the metric is left out.
        min_registered_fraction: both views at least this registered in Stage III.
        require_valid: leave out windows holding a frame Stage IV could not place.
        heightmap_size, heightmap_cell_m: the height map patch, cells and cell size.
        camera_view: ``"v1"`` or ``"v2"`` adds camera-space targets of that view.
        contact_height_m, contact_speed_m_s: the contact labels' thresholds.
    """

    def __init__(self, dataset: str | Path, window: int = 60, stride: int | None = None, *,
                 scenes: tuple[str, ...] | None = None, sessions: tuple[str, ...] | None = None,
                 where: str | None = None, min_metrics: dict[str, float] | None = None,
                 max_metrics: dict[str, float] | None = None, min_registered_fraction: float | None = None,
                 require_valid: bool = True, heightmap_size: int = 32, heightmap_cell_m: float = 0.1,
                 camera_view: str | None = None, contact_height_m: float = 0.08,
                 contact_speed_m_s: float = 0.4) -> None:
        from embodmocap.io.dataset import dataset_root
        from embodmocap.catalog.db import CATALOG_NAME, rebuild

        if window < 1:
            raise ValueError("window must be >= 1")
        if camera_view not in (None, "v1", "v2"):
            raise ValueError("camera_view must be None, 'v1' or 'v2'")
        self.window, self.stride = int(window), int(stride or window)
        self.require_valid = require_valid
        self.heightmap_size, self.heightmap_cell_m = int(heightmap_size), float(heightmap_cell_m)
        self.camera_view = camera_view
        self.contact_height_m, self.contact_speed_m_s = contact_height_m, contact_speed_m_s
        root = dataset_root(dataset)
        if not (root / CATALOG_NAME).is_file():
            rebuild(dataset)
        self.sequences = _select(root / CATALOG_NAME, scenes, sessions, where, min_metrics or {}, max_metrics or {},
                                 min_registered_fraction)
        self.index: list[tuple[int, int]] = []  # (sequence, first row)
        for i, ref in enumerate(self.sequences):
            valid = self._valid(ref) if require_valid else None
            for start in range(0, ref.frames - self.window + 1, self.stride):
                if valid is None or valid[start:start + self.window].all():
                    self.index.append((i, start))
        self._cache: dict[str, Any] = {}

    # DataLoader workers get a copy without the (possibly large) cache.
    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_cache"] = {}
        return state

    def __len__(self) -> int:
        return len(self.index)

    def _valid(self, ref: SequenceRef) -> np.ndarray:
        from embodmocap.io.layout import SessionLayout
        from embodmocap.io.smpl_file import read_smpl_valid

        return read_smpl_valid(SessionLayout(Path(ref.session_path)).sequence(ref.sequence).smpl_world)

    def _load(self, ref: SequenceRef) -> dict[str, Any]:
        key = f"{ref.session_path}|{ref.sequence}"
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        from embodmocap.io.layout import SessionLayout
        from embodmocap.io.smpl_file import read_smpl_npz, read_smpl_valid
        from embodmocap.io.stage_files import read_cameras, read_world_joints

        lay = SessionLayout(Path(ref.session_path))
        sl = lay.sequence(ref.sequence)
        params, frames = read_smpl_npz(sl.smpl_world)
        joints = read_world_joints(sl.joints_world)
        if not np.array_equal(joints.frames, frames):
            raise InputError(sl.joints_world, "its frames differ from smpl_world.npz's",
                             f"run `embodmocap motion {lay.root} --seq {ref.sequence} --force`")
        data: dict[str, Any] = {
            "poses": np.asarray(params.poses, np.float32), "trans": np.asarray(params.transl, np.float32),
            "betas": np.asarray(params.betas, np.float32), "joints": np.asarray(joints.joints, np.float32),
            "valid": read_smpl_valid(sl.smpl_world), "frames": frames, "fps": float(params.fps),
            "grid": self._grid(lay, ref.scene)}
        if self.camera_view is not None:
            cams = read_cameras(sl.view(self.camera_view).cameras_final)
            data["T_cam_world"] = np.linalg.inv(cams.T_world_cam[frames]).astype(np.float32)
        if len(self._cache) >= 8:
            self._cache.pop(next(iter(self._cache)))
        self._cache[key] = data
        return data

    def _grid(self, lay, scene: str) -> HeightGrid:
        key = f"grid|{lay.root}|{scene}"
        hit = self._cache.get(key)
        if hit is None:
            from embodmocap.io.mesh_file import read_mesh_ply

            v, f, _ = read_mesh_ply(lay.scene(scene).mesh_simplified)
            hit = self._cache[key] = height_grid(v, f, cell_m=self.heightmap_cell_m)
        return hit

    def __getitem__(self, i: int) -> dict[str, Any]:
        seq_i, start = self.index[i]
        ref = self.sequences[seq_i]
        d = self._load(ref)
        sl = slice(start, start + self.window)
        joints = d["joints"][sl]
        grid: HeightGrid = d["grid"]
        ground = sample_heights(grid, joints[:, CONTACT_JOINTS, :2])
        center = joints[0, 0, :2].astype(np.float64)  # the pelvis at the window's first frame
        item: dict[str, Any] = {
            "poses": torch.from_numpy(d["poses"][sl].copy()), "trans": torch.from_numpy(d["trans"][sl].copy()),
            "betas": torch.from_numpy(d["betas"].copy()), "joints": torch.from_numpy(joints.copy()),
            "contacts": torch.from_numpy(foot_contacts(joints, ground, d["fps"], self.contact_height_m,
                                                       self.contact_speed_m_s)),
            "height_map": torch.from_numpy(height_patch(grid, center, self.heightmap_size, self.heightmap_cell_m)),
            "height_map_xy": torch.from_numpy(center.astype(np.float32)),
            "valid": torch.from_numpy(d["valid"][sl].copy()), "frames": torch.from_numpy(d["frames"][sl].copy()),
            "fps": torch.tensor(d["fps"], dtype=torch.float32),
            "session": ref.session, "sequence": ref.sequence, "scene": ref.scene}
        if self.camera_view is not None:
            T = d["T_cam_world"][sl]
            cam = np.einsum("tij,tkj->tki", T[:, :3, :3], joints) + T[:, None, :3, 3]
            item["joints_cam"] = torch.from_numpy(cam.astype(np.float32))
            item["T_cam_world"] = torch.from_numpy(T.copy())
        return item


def _select(catalog: Path, scenes, sessions, where, min_metrics: dict, max_metrics: dict,
            min_registered_fraction) -> list[SequenceRef]:
    """The finished sequences of the catalog that pass every filter, in (session, sequence) order."""
    sql = ("SELECT q.session, q.sequence, q.scene, s.path, q.motion_frames FROM sequences q"
           " JOIN sessions s ON s.session = q.session WHERE q.status = 'done'")
    args: list[Any] = []
    if where:
        sql += f" AND ({where})"
    for key, value in min_metrics.items():
        sql += " AND EXISTS (SELECT 1 FROM metrics m WHERE m.session=q.session AND m.sequence=q.sequence AND m.key=? AND m.value >= ?)"
        args += [key, float(value)]
    for key, value in max_metrics.items():
        sql += " AND EXISTS (SELECT 1 FROM metrics m WHERE m.session=q.session AND m.sequence=q.sequence AND m.key=? AND m.value <= ?)"
        args += [key, float(value)]
    if min_registered_fraction is not None:
        sql += (" AND (SELECT MIN(COALESCE(v.registered_fraction, 0)) FROM views v WHERE v.session=q.session"
                " AND v.sequence=q.sequence) >= ?")
        args.append(float(min_registered_fraction))
    sql += " ORDER BY q.session, q.sequence"
    db = sqlite3.connect(f"file:{catalog}?mode=ro", uri=True)
    try:
        rows = db.execute(sql, args).fetchall()
    except sqlite3.Error as err:
        raise InputError(catalog, f"sequence filter failed: {err}", "check `where` against docs/formats.md") from None
    finally:
        db.close()
    out = []
    for session, seq, scene, path, frames in rows:
        if scenes is not None and scene not in scenes and f"{session}/{scene}" not in scenes:
            continue
        if sessions is not None and session not in sessions:
            continue
        out.append(SequenceRef(session, seq, scene, path, int(frames or 0)))
    return out
