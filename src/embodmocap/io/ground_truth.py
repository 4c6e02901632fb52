"""Readers of a synthetic session's ground truth (``ground_truth/``, written by the studio).

The studio's files have no format version (they are written and read by the same package
version); these readers check that each file exists, is a readable npz and has the keys the
evaluation uses, through the one checked-npz helper.
"""

from __future__ import annotations

from pathlib import Path

from embodmocap.io.npz_file import NpzData, load_npz

_FIX = "the session's ground truth is damaged: synthesise the session again (`embodmocap synth`)"


def read_truth_sequence(path: str | Path) -> NpzData:
    """``ground_truth/seq_<seq>.npz``: world SMPL joints, per-view true cameras, VIO offsets, sync frames."""
    return load_npz(path, what="ground-truth sequence", fix=_FIX, required=("joints_smpl24",), versions=None)


def read_truth_scene_device(path: str | Path) -> NpzData:
    """``ground_truth/scene_<scene>_device.npz``: the scene capture's ``T_scene_vio`` and device poses."""
    return load_npz(path, what="ground-truth scene device", fix=_FIX, required=("T_scene_vio",), versions=None)


def read_truth_info(path: str | Path) -> dict:
    """``ground_truth/ground_truth.json``: seed, preset, sizes, per-scene and per-sequence facts."""
    from embodmocap.io.jsonfile import read_json

    return read_json(path, max_bytes=64 << 20, what="ground-truth info", fix=_FIX)
