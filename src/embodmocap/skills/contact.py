"""Scene surfaces and body-surface contacts over time.

Surfaces: the scene mesh's height map (highest surface per cell below a cap, so no ceiling) split
into connected pieces of similar height: the floor is the most common height, every other piece
higher than ``surface_min_height_m`` and larger than ``surface_min_area_m2`` is a surface (seat,
bed, table top, box top ...). Contacts: a body vertex touches the surface of the height-map cell
under it when it is at most ``contact_above_m`` above it or ``contact_below_m`` inside it; a body
part (pelvis, back, front, hands, feet) touches the surface most of its touching vertices touch,
if they are at least ``min_part_vertices``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from embodmocap.skills.boxes import Box, surface_box
from embodmocap.skills.config import SkillsConfig

#: Body parts whose contacts the clip finder reads.
PARTS: tuple[str, ...] = ("pelvis", "back", "front", "left_hand", "right_hand", "left_foot", "right_foot")

#: SMPL joints whose skinning region makes each part (vertices whose largest weight is one of them).
_PART_JOINTS = {"pelvis": (0, 1, 2), "back": (3, 6, 9, 13, 14), "front": (3, 6, 9), "left_hand": (20, 22),
                "right_hand": (21, 23)}

#: Label of "no surface" in the per-frame contact arrays; -1 is the floor.
NONE, FLOOR = -2, -1


@dataclass(frozen=True)
class Surfaces:
    """Horizontal surfaces of a scene mesh (world Z up, metres).

    Attributes:
        labels: (H, W) int, the surface of each height-map cell (index into ``boxes``), FLOOR or NONE.
        heights: (H, W) float, the height-map heights.
        origin: (2,) world (x, y) of the corner of cell [0, 0]; cell [i, j] covers
            ``x in [origin_x + j * cell_m, +cell_m)``, ``y in [origin_y + i * cell_m, +cell_m)``.
        cell_m: cell size.
        floor_z: floor height.
        boxes: per surface, its oriented bounding box (floor to top).
        areas: (S,) area of each surface, square metres.
    """

    labels: NDArray[np.int64]
    heights: NDArray[np.float64]
    origin: NDArray[np.float64]
    cell_m: float
    floor_z: float
    boxes: list[Box]
    areas: NDArray[np.float64]

    def lookup(self, points: NDArray) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Surface label and height under points (..., 3) (the cell holding their x, y); NONE and
        NaN outside the map."""
        p = np.asarray(points, dtype=np.float64)
        H, W = self.labels.shape
        j = np.floor((p[..., 0] - self.origin[0]) / self.cell_m).astype(np.int64)
        i = np.floor((p[..., 1] - self.origin[1]) / self.cell_m).astype(np.int64)
        inside = (i >= 0) & (i < H) & (j >= 0) & (j < W)
        i, j = np.clip(i, 0, H - 1), np.clip(j, 0, W - 1)
        return np.where(inside, self.labels[i, j], NONE), np.where(inside, self.heights[i, j], np.nan)


def find_surfaces(vertices: NDArray, faces: NDArray, floor_hint_z: float, cfg: SkillsConfig = SkillsConfig()) -> Surfaces:
    """The horizontal surfaces of a scene mesh (see the module docstring).

    Args:
        vertices: (N, 3) scene mesh vertices, faces: (F, 3) triangles, world Z up, metres.
        floor_hint_z: a height near the floor (e.g. the body's lowest point over the motion): the
            cap is ``cap_above_floor_m`` above it.
        cfg: settings.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from embodmocap.geometry.heightmap import scene_heightmap

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    cap = floor_hint_z + cfg.cap_above_floor_m
    keep = v[f, 2].max(axis=1) < cap  # faces entirely below the cap (no ceiling, no wall tops)
    if not keep.any():
        raise ValueError("no scene surface below the cap")
    hm = scene_heightmap(v, f[keep], cell_m=cfg.cell_m)
    h = np.asarray(hm.heights, dtype=np.float64)
    H, W = h.shape
    finite = np.isfinite(h)
    # Floor: the most common height (1 cm bins) among the cells near the hint.
    near = finite & (np.abs(h - floor_hint_z) < 0.3)
    pool = h[near] if near.any() else h[finite]
    bins = np.round(pool / 0.01).astype(np.int64)
    vals, counts = np.unique(bins, return_counts=True)
    floor_z = float(np.median(pool[bins == vals[np.argmax(counts)]]))
    labels = np.full((H, W), NONE, dtype=np.int64)
    labels[finite & (h < floor_z + cfg.surface_min_height_m)] = FLOOR
    cand = finite & (h >= floor_z + cfg.surface_min_height_m)
    # Connected pieces of similar height: 4-neighbour edges between candidate cells.
    idx = np.full((H, W), -1, dtype=np.int64)
    idx[cand] = np.arange(int(cand.sum()))
    rows, cols = [], []
    for a, b in (((slice(None), slice(0, -1)), (slice(None), slice(1, None))),
                 ((slice(0, -1), slice(None)), (slice(1, None), slice(None)))):
        ok = cand[a] & cand[b] & (np.abs(np.where(cand[a], h[a], 0) - np.where(cand[b], h[b], 0)) < cfg.surface_step_m)
        rows.append(idx[a][ok])
        cols.append(idx[b][ok])
    n = int(cand.sum())
    boxes, areas = [], []
    if n:
        r, c = np.concatenate(rows), np.concatenate(cols)
        graph = coo_matrix((np.ones(len(r)), (r, c)), shape=(n, n))
        _, comp = connected_components(graph, directed=False)
        ii, jj = np.nonzero(cand)
        min_cells = cfg.surface_min_area_m2 / cfg.cell_m**2
        for k in np.unique(comp):
            sel = comp == k
            if sel.sum() < min_cells:
                continue
            ci, cj = ii[sel], jj[sel]
            xy = np.stack([hm.origin[0] + (cj + 0.5) * cfg.cell_m, hm.origin[1] + (ci + 0.5) * cfg.cell_m], axis=1)
            top = float(np.median(h[ci, cj]))
            labels[ci, cj] = len(boxes)
            boxes.append(surface_box(xy, cfg.cell_m, top, floor_z))
            areas.append(sel.sum() * cfg.cell_m**2)
    return Surfaces(labels, h, np.asarray(hm.origin, dtype=np.float64), float(cfg.cell_m), floor_z, boxes,
                    np.asarray(areas, dtype=np.float64))


def part_vertex_ids(body, betas: NDArray | None = None) -> dict[str, NDArray[np.int64]]:
    """Vertex ids of each part in :data:`PARTS`: pelvis (buttocks and hips), back and front (the
    torso behind / in front of its joints), hands, feet (:func:`~embodmocap.body.vertex_sets.foot_vertex_ids`).
    Found from the model's skinning weights and its own rest pose (Y up, facing +Z)."""
    from embodmocap.body.vertex_sets import foot_vertex_ids

    out = body.forward(np.zeros(body.num_betas) if betas is None else betas, np.zeros((1, 3)), np.zeros((1, 69)))
    v = out.vertices[0].detach().cpu().numpy().astype(np.float64)
    j = out.joints[0].detach().cpu().numpy().astype(np.float64)
    owner = np.argmax(np.asarray(body.lbs_weights), axis=1)
    behind = v[:, 2] < j[owner, 2]
    ids = {}
    for name, joints in _PART_JOINTS.items():
        sel = np.isin(owner, joints)
        if name == "back":
            sel &= behind
        elif name == "front":
            sel &= ~behind
        ids[name] = np.nonzero(sel)[0]
    ids["left_foot"], ids["right_foot"] = foot_vertex_ids(body, betas)
    return ids


@dataclass(frozen=True)
class Contacts:
    """Per frame and body part, the surface touched (index into ``Surfaces.boxes``, FLOOR or NONE),
    and a few per-frame body measures the heuristics read.

    Attributes:
        part: part name -> (T,) int label.
        foot_gap: (T, 2) lowest vertex of the (left, right) foot above the floor, metres.
        pelvis: (T, 3) pelvis joint; neck: (T, 3) neck joint; ankles: (T, 2, 3); hips: (T, 2, 3)
            the (left, right) hip joints; hands: (T, 2, 3) the (left, right) hand joints (SMPL 22,
            23: the palm, where a supporting hand bears).
        posture: (T, 22, 3) joints 0..21 relative to the pelvis in the heading frame (rotated
            about +Z so that the hips' forward direction is +x): what changes when the body
            changes its posture, not when it walks off or turns.
    """

    part: dict[str, NDArray[np.int64]]
    foot_gap: NDArray[np.float64]
    pelvis: NDArray[np.float64]
    neck: NDArray[np.float64]
    ankles: NDArray[np.float64]
    hips: NDArray[np.float64]
    posture: NDArray[np.float64]
    hands: NDArray[np.float64]

    def posture_speed(self, fps: float, smooth_s: float = 0.0) -> NDArray[np.float64]:
        """(T,) mean speed of the joints in :attr:`posture`, m/s (central differences of the
        positions averaged over ``smooth_s`` seconds)."""
        from scipy.ndimage import uniform_filter1d

        if len(self.posture) < 2:
            return np.zeros(len(self.posture))
        win = max(int(round(smooth_s * fps)), 1)
        p = uniform_filter1d(self.posture, win, axis=0, mode="nearest") if win > 1 else self.posture
        return np.linalg.norm(np.gradient(p, axis=0), axis=-1).mean(axis=1) * fps


def body_contacts(params, body, surfaces: Surfaces, part_ids: dict[str, NDArray], cfg: SkillsConfig = SkillsConfig()) -> Contacts:
    """Pose the body frame by frame (chunks of ``chunk_frames``) and find each part's contact."""
    import torch

    T = len(params)
    labels = {p: np.full(T, NONE, dtype=np.int64) for p in PARTS}
    foot_gap = np.zeros((T, 2))
    pelvis, neck = np.zeros((T, 3)), np.zeros((T, 3))
    ankles, hips, hands = np.zeros((T, 2, 3)), np.zeros((T, 2, 3)), np.zeros((T, 2, 3))
    posture = np.zeros((T, 22, 3))
    S = len(surfaces.boxes)
    for s in range(0, T, cfg.chunk_frames):
        sl = slice(s, min(s + cfg.chunk_frames, T))
        with torch.no_grad():
            out = body.forward(params.betas, params.global_orient[sl], params.body_pose[sl], params.transl[sl])
        v = out.vertices.cpu().numpy().astype(np.float64)
        j = out.joints.cpu().numpy().astype(np.float64)
        pelvis[sl], neck[sl] = j[:, 0], j[:, 12]
        ankles[sl], hips[sl], hands[sl] = j[:, [7, 8]], j[:, [1, 2]], j[:, [22, 23]]
        left = j[:, 1, :2] - j[:, 2, :2]
        yaw = np.arctan2(-left[:, 0], left[:, 1])  # forward = left hip direction turned by -90 deg
        cy, sy = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        rel = j[:, :22] - j[:, :1]
        posture[sl] = np.stack([cy * rel[..., 0] + sy * rel[..., 1], -sy * rel[..., 0] + cy * rel[..., 1], rel[..., 2]], -1)
        for k, name in enumerate(("left_foot", "right_foot")):
            foot_gap[sl, k] = v[:, part_ids[name], 2].min(axis=1) - surfaces.floor_z
        for name in PARTS:
            pv = v[:, part_ids[name]]
            lab, hgt = surfaces.lookup(pv)
            dz = pv[..., 2] - np.where(lab == FLOOR, surfaces.floor_z, hgt)
            touch = (lab != NONE) & (dz < cfg.contact_above_m) & (dz > -cfg.contact_below_m)
            # Count touching vertices per surface (floor in the last column).
            col = np.where(lab == FLOOR, S, lab)
            counts = np.zeros((len(v), S + 1), dtype=np.int64)
            rr = np.broadcast_to(np.arange(len(v))[:, None], col.shape)
            np.add.at(counts, (rr[touch], col[touch]), 1)
            best = np.argmax(counts, axis=1)
            ok = counts[np.arange(len(v)), best] >= cfg.min_part_vertices
            labels[name][sl] = np.where(ok, np.where(best == S, FLOOR, best), NONE)
    return Contacts(labels, foot_gap, pelvis, neck, ankles, hips, posture, hands)
