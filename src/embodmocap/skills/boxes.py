"""Oriented bounding boxes of scene surfaces (the ``object`` of a skill clip)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from embodmocap.io.stage_json import CORNER_SIGNS  # noqa: F401 (skills.json's corner order, used below)


@dataclass(frozen=True)
class Box:
    """An upright oriented box, world Z up, metres.

    Attributes:
        center: (3,) centre.
        size: (3,) extents along the box axes (x, y horizontal; x the longer; z up).
        R_world_box: (3, 3) rotation, columns = box axes in the world (a yaw about +Z).
        top_z: height of the top (the surface the body uses).
    """

    center: NDArray[np.float64]
    size: NDArray[np.float64]
    R_world_box: NDArray[np.float64]
    top_z: float

    def corners(self) -> NDArray[np.float64]:
        """(8, 3) corners in :data:`CORNER_SIGNS` order."""
        return self.center + (CORNER_SIGNS * self.size / 2) @ self.R_world_box.T


def min_area_rectangle(xy: NDArray) -> tuple[NDArray, NDArray, float]:
    """Smallest-area rectangle around points ``xy`` (N, 2): ``(centre (2,), size (2,), yaw)``,
    size[0] >= size[1] along the axes (cos yaw, sin yaw) and (-sin yaw, cos yaw).

    The best rectangle has a side along an edge of the convex hull, so only those directions are
    tried (all at once, vectorised)."""
    p = np.asarray(xy, dtype=np.float64)
    if len(p) < 3:
        c = p.mean(axis=0) if len(p) else np.zeros(2)
        return c, np.zeros(2), 0.0
    try:
        from scipy.spatial import ConvexHull

        hull = p[ConvexHull(p).vertices]
    except Exception:  # degenerate (collinear) points: every point is on the hull
        hull = p
    e = np.diff(np.vstack([hull, hull[:1]]), axis=0)
    ang = np.unique(np.mod(np.arctan2(e[:, 1], e[:, 0]), np.pi / 2))
    c, s = np.cos(ang), np.sin(ang)
    u = hull @ np.stack([c, s])            # (H, A) along the first axis
    v = hull @ np.stack([-s, c])           # (H, A) along the second
    area = (u.max(0) - u.min(0)) * (v.max(0) - v.min(0))
    k = int(np.argmin(area))
    lu, lv = u[:, k].max() - u[:, k].min(), v[:, k].max() - v[:, k].min()
    mu, mv = (u[:, k].max() + u[:, k].min()) / 2, (v[:, k].max() + v[:, k].min()) / 2
    yaw = float(ang[k])
    centre = mu * np.array([c[k], s[k]]) + mv * np.array([-s[k], c[k]])
    if lv > lu:  # the first axis the longer one
        lu, lv, yaw = lv, lu, yaw + np.pi / 2
    yaw = float((yaw + np.pi / 2) % np.pi - np.pi / 2)  # a box axis is a line: yaw in [-90, 90) deg
    return centre, np.array([lu, lv]), yaw


def surface_box(cells_xy: NDArray, cell_m: float, top_z: float, floor_z: float) -> Box:
    """The box of a horizontal surface given by its height-map cell centres (N, 2): the footprint's
    minimal rectangle, from the floor up to the top.

    A cell holds the surface when any of its 3 x 3 sub-samples hits it, so the outermost cell
    centres lie on average a sixth of a cell inside the true edge: ``cell_m / 3`` is added to each
    extent."""
    centre, size, yaw = min_area_rectangle(cells_xy)
    size = size + cell_m / 3.0
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    h = max(top_z - floor_z, 0.0)
    return Box(np.array([centre[0], centre[1], floor_z + h / 2]), np.array([size[0], size[1], h]), R, float(top_z))
