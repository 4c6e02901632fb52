"""The scene height map file (``scene_heightmap.npz`` of the MimicKit export and the simulator's
cache): :class:`~embodmocap.geometry.heightmap.HeightMap` as npz."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from embodmocap.geometry.heightmap import HeightMap
from embodmocap.io.atomic import write_npz
from embodmocap.io.npz_file import load_npz

#: Version of the height map file.
HEIGHTMAP_VERSION = 1


def write_heightmap(path: str | Path, hm: HeightMap) -> Path:
    """Write ``heights`` (H, W) float32, ``origin`` (2,), ``cell_m`` (), ``version`` () as npz."""
    write_npz(path, heights=hm.heights, origin=hm.origin, cell_m=np.array(hm.cell_m), version=np.array(HEIGHTMAP_VERSION))
    return Path(path)


def read_heightmap(path: str | Path) -> HeightMap:
    """Read a height map npz written by :func:`write_heightmap`."""
    path = Path(path)
    z = load_npz(path, what="height map", fix="write it again with the mimickit export",
                 required=("heights", "origin", "cell_m"), versions=(HEIGHTMAP_VERSION,))
    return HeightMap(heights=z["heights"], origin=z["origin"], cell_m=float(z["cell_m"]))
