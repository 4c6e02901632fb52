"""The scene as collision geometry: a MuJoCo heightfield of the support surfaces (coacd convex
pieces are not built: see docs/sim.md, Limits).

MuJoCo collides a ``mesh`` geom as its convex hull, so a room mesh given as one geom would be a
solid block. A heightfield is exact for everything a body can stand, sit or lie on, and cheap.

The height map is the shared support map (:func:`embodmocap.geometry.heightmap.support_heightmap`): the
mesh's highest surface per cell without the faces that lie entirely above a cap (``cap_z``: the performer's highest point plus
a margin), so ceilings and lamps do not hide the floor. A cell whose centre at the cap is inside a
solid (the first surface straight up from there faces up, i.e. it is the inside of a box's top,
as in a wall) is raised to the cap, so walls stay walls.

MuJoCo's heightfield samples sit on a regular grid: with ``nrow x ncol`` samples and half sizes
``(rx, ry)``, samples lie ``2 rx / (ncol - 1)`` and ``2 ry / (nrow - 1)`` apart around the geom's
position, the ``elevation`` attribute listing rows from +y to -y (checked against ``mj_ray`` in the
tests), and MuJoCo interpolates between samples (two triangles per cell). Here the samples are
the centres of the height-map cells.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.heightmap import HeightMap, sample_heightmap, support_heightmap  # noqa: F401 (re-exported)


def heightfield_mjcf(hm: HeightMap, name: str = "scene", base_m: float = 0.5) -> tuple[str, str]:
    """MJCF ``<hfield>`` asset and ``<geom>`` for a height map: (asset line, geom line).

    ``base_m`` is the thickness of the solid below the lowest sample (a body pushed below the lowest
    surface still meets the field).
    """
    h = np.asarray(hm.heights, dtype=np.float64)
    H, W = h.shape
    if H < 2 or W < 2:  # MuJoCo needs at least 2 x 2 samples
        h = np.pad(h, ((0, max(0, 2 - H)), (0, max(0, 2 - W))), mode="edge")
        H, W = h.shape
    zmin, zmax = float(h.min()), float(h.max())
    span = max(zmax - zmin, 1e-3)
    rx, ry = (W - 1) * hm.cell_m / 2, (H - 1) * hm.cell_m / 2
    cx, cy = hm.origin[0] + hm.cell_m / 2 + rx, hm.origin[1] + hm.cell_m / 2 + ry
    # The elevation attribute lists rows from +y down to -y (as an image is stored): flip ours.
    elev = " ".join(f"{x:.5f}" for x in ((h[::-1] - zmin) / span).ravel())
    asset = (f'    <hfield name="{name}" nrow="{H}" ncol="{W}" size="{rx:.6g} {ry:.6g} {span:.6g} {base_m:.6g}" '
             f'elevation="{elev}"/>')
    geom = (f'    <geom name="{name}" type="hfield" hfield="{name}" pos="{cx:.6g} {cy:.6g} {zmin:.6g}" '
            f'contype="0" conaffinity="1" material="scene"/>')
    return asset, geom
