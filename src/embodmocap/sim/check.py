"""Physical plausibility of a fitted motion against its scene (``embodmocap sim check``).

Per frame, from the posed SMPL mesh (every ``vertex_stride``-th vertex) and the scene mesh:

==========================  ==============================================================  =====
figure                      definition                                                      unit
==========================  ==============================================================  =====
penetration                 deepest body vertex inside the scene: ``max(0, -min_v sd(v))``,  cm
                            ``sd`` the signed distance to the closest scene triangle (its
                            normal gives the side: scene meshes are oriented outwards)
floating                    lowest body point above the support under it: ``min_v`` of the   cm
                            straight-down gap from each vertex to the scene, 0 on frames
                            that penetrate (a frame in flight counts as floating); null
                            where no vertex has any surface below it (a hole in the scan,
                            counted in ``unsupported_frames``)
foot skating                MotionVAE's measure (the paper's *jitter*): per foot, the         cm
                            horizontal displacement of its ankle and toe joints to the
                            next frame, weighted ``2 - 2^(h/H)`` where its lowest point is
                            ``h < H`` above the support (0 above ``H``), mean of the feet
contact per body part       a part touches when one of its vertices is within                0/1
                            ``contact_m`` of the scene (or inside it)
residual root force/torque  the part of the root wrench that MuJoCo inverse dynamics needs   N/kg,
                            which no contact force can supply: ``min |b - A f|`` over         N m/kg
                            forces ``f`` in friction pyramids at the touching vertices
                            (non-negative least squares), ``b`` the free joint's
                            generalized force, per kg of body mass
==========================  ==============================================================  =====

Vertices whose closest surface is more than ``max_depth_m`` (0.3 m) "inside" are not counted as
penetrating or touching: a scanned mesh has holes, and there the closest surface is a far one
whose normal says nothing. A scan sees each surface from one side only (no seat has an underside
in it), so a vertex behind its closest face penetrates only when the body went through a seen
surface to get there (:func:`entered_through_surface`); feet tucked under a seat lie on the sheet's
unseen side and read as outside (``SimCheckConfig.through_surface``). These decisions are taken on
the simplified scene mesh (Stage I's ``mesh_simplified.ply``, smooth enough for the side votes);
how deep a vertex found inside is, is then measured on the full-resolution mesh it was made from
(``mesh_raw.ply``, its faces near the vertex only, :func:`detail_signed_distance`), since the
clustering moves the surface by up to a cell (``SimCheckConfig.full_resolution_depth``).
The summary gives the max and mean over frames of each figure and the fraction of frames in
contact per part. Contact and the residual use the fitted mesh; the inverse dynamics use the
MuJoCo model of :mod:`embodmocap.sim.model` (masses from its geoms).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.body.humanoid import HUMANOID_TO_SMPL
from embodmocap.io.stage_manifest import tracked_stage
from embodmocap.sim.config import HumanoidConfig, SimCheckConfig
from embodmocap.sim.session import SIM_FORMAT_VERSION, SimSequence, body_vertices, load_sequence

log = logging.getLogger(__name__)

#: Body parts for the contact figures: part -> SMPL joints whose skinned vertices belong to it.
BODY_PARTS: dict[str, tuple[int, ...]] = {
    "left_foot": (7, 10), "right_foot": (8, 11),
    "left_leg": (1, 4), "right_leg": (2, 5),
    "pelvis": (0,), "torso": (3, 6, 9, 13, 14),
    "head": (12, 15),
    "left_arm": (16, 18), "right_arm": (17, 19),
    "left_hand": (20, 22), "right_hand": (21, 23),
}
#: SMPL joints of each foot used for the skating figure (ankle, toe).
FEET: tuple[tuple[int, int], ...] = ((7, 10), (8, 11))


class SceneQuery:
    """Signed distance and downward gap of points to a triangle mesh (open3d ray casting).

    The side of a triangle that is solid comes from its normal (scene meshes are oriented
    outwards), but not from that one triangle alone: with ``side_radius_m > 0`` the closest
    triangle's normal is voted over the surface sheet around it (:meth:`face_side`), so a patch of
    a few triangles facing the wrong way does not turn the air above a floor into solid; and a
    point behind a face that is not a wall is inside only with surface above it within
    ``enclosed_m`` (a solid has a top; air above a turned-over floor or beside the rim of a hole
    in a scanned floor has none).
    """

    #: Cell edge (metres) of the area-weighted normal sums the side vote reads.
    CELL_M = 0.03

    def __init__(self, vertices: NDArray, faces: NDArray, side_radius_m: float = 0.3, side_sheet_m: float = 0.01,
                 enclosed_m: float = np.inf) -> None:
        import open3d as o3d

        self._o3d = o3d
        v = np.asarray(vertices, np.float64).reshape(-1, 3)
        f = np.asarray(faces, np.int64).reshape(-1, 3)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
        tri = v[f]  # (F, 3, 3)
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self._area = 0.5 * np.linalg.norm(cross, axis=1)  # (F,)
        self._normal = cross / np.maximum(2.0 * self._area, 1e-12)[:, None]  # (F, 3) unit (0 if degenerate)
        self._centroid = tri.mean(axis=1)  # (F, 3)
        self.side_radius_m = float(side_radius_m)
        self.side_sheet_m = float(side_sheet_m)
        self.enclosed_m = float(enclosed_m)
        self._side = np.zeros(len(f), dtype=np.int8)  # +1 / -1 once voted, 0 = not yet
        self._cells = None

    def _cell_sums(self):
        """Per occupied ``CELL_M`` cell: area-weighted centroid (C, 3), area-weighted normal sum
        (C, 3) and a KD-tree over the centroids (built once, on first use)."""
        from scipy.spatial import cKDTree

        key = np.floor(self._centroid / self.CELL_M).astype(np.int64)
        _, cell = np.unique(key, axis=0, return_inverse=True)
        cell = cell.reshape(-1)
        a = self._area
        area = np.bincount(cell, weights=a)
        cen = np.stack([np.bincount(cell, weights=a * self._centroid[:, k]) for k in range(3)], 1)
        cen /= np.maximum(area, 1e-18)[:, None]
        nsum = np.stack([np.bincount(cell, weights=a * self._normal[:, k]) for k in range(3)], 1)
        self._cells = (cen, nsum, cKDTree(cen))
        return self._cells

    def face_side(self, face_ids: NDArray) -> NDArray[np.int8]:
        """(N,) +1 where a face's normal agrees with its sheet, -1 where the sheet says the face
        is turned over.

        The vote: the area-weighted normals of the surface within ``side_radius_m`` of the face's
        centroid and within ``side_sheet_m`` of its plane (the same sheet: not the far face of a
        table top, not a wall meeting the floor), projected on the face's normal and summed; a
        negative sum means most of that sheet faces the other way. Each face is voted once.
        """
        ids = np.asarray(face_ids, np.int64).reshape(-1)
        if self.side_radius_m <= 0 or len(ids) == 0:
            return np.ones(len(ids), dtype=np.int8)
        todo = np.unique(ids[self._side[ids] == 0])
        if len(todo):
            cen, nsum, tree = self._cells if self._cells is not None else self._cell_sums()
            c, n = self._centroid[todo], self._normal[todo]
            vote = np.zeros(len(todo))
            for s in range(0, len(todo), 4096):  # chunks keep the pair lists small
                e = min(s + 4096, len(todo))
                hits = tree.query_ball_point(c[s:e], self.side_radius_m)
                counts = np.fromiter((len(h) for h in hits), dtype=np.int64, count=len(hits))
                if counts.sum() == 0:
                    continue
                q = np.repeat(np.arange(s, e), counts)
                k = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits])
                on_sheet = np.abs(np.einsum("pc,pc->p", cen[k] - c[q], n[q])) < self.side_sheet_m
                q, k = q[on_sheet], k[on_sheet]
                vote[s:e] += np.bincount(q - s, weights=np.einsum("pc,pc->p", nsum[k], n[q]), minlength=e - s)
            self._side[todo] = np.where(vote < 0, -1, 1)
        return self._side[ids]

    def signed_distance(self, points: NDArray) -> tuple[NDArray, NDArray]:
        """(N,) signed distance (negative inside) and (N, 3) outward normal of the closest triangle
        (turned over where its sheet says so, :meth:`face_side`)."""
        p = np.asarray(points, np.float32).reshape(-1, 3)
        r = self.scene.compute_closest_points(self._o3d.core.Tensor(p))
        ids = r["primitive_ids"].numpy().astype(np.int64)
        n = (self._normal[ids] * self.face_side(ids)[:, None]).astype(np.float32)
        diff = p - r["points"].numpy()
        dist = np.linalg.norm(diff, axis=1)
        # The distance to the closest point (the projection on the normal alone would call a point
        # far beside a surface close to it), negative when the point is behind its triangle. Inside
        # a solid the closest point lies inside a face, straight behind it; a closest point on an
        # edge or corner (diff far from the normal, e.g. a hand above a table's edge whose closest
        # triangle is the table's side) means outside, whatever the side of that triangle.
        inside = np.einsum("nc,nc->n", diff, n) < -0.5 * dist
        # Behind a face that is not a wall is inside a solid with a top: under a floor or a seat
        # (the face itself is the top), above a table top's underside (its upper face is). So the
        # point must have surface above it within ``enclosed_m``. Air above a scanned floor whose
        # faces there are turned over has none, nor has a foot beside the curled rim of a hole in
        # the scanned floor: this holds whatever the faces' sheet says. Walls (|n_z| < 0.2) keep
        # the closest face's word: their tops are rarely scanned. A scan's open ceiling is the
        # exception: a head pushed into it is not found.
        check = np.flatnonzero(inside & (np.abs(n[:, 2]) > 0.2))
        if len(check) and np.isfinite(self.enclosed_m):
            inside[check] = self.up_gap(p[check]) < self.enclosed_m
        return np.where(inside, -dist, dist), n

    def exits(self, inner: NDArray, outer: NDArray) -> tuple[NDArray[np.bool_], NDArray]:
        """(N,) whether the segment from ``inner`` (N, 3) to ``outer`` (N, 3) leaves through the
        seen side of a face: its first surface lies on the segment and faces the way it goes
        (the face's voted normal, :meth:`face_side`, points toward ``outer``); and (N, 3) that
        face's voted normal (0 where none is crossed)."""
        p0 = np.asarray(inner, np.float32).reshape(-1, 3)
        d = np.asarray(outer, np.float32).reshape(-1, 3) - p0
        out, normal = np.zeros(len(p0), dtype=bool), np.zeros((len(p0), 3))
        if len(p0) == 0:
            return out, normal
        r = self.scene.cast_rays(self._o3d.core.Tensor(np.concatenate([p0, d], axis=1)))
        t = r["t_hit"].numpy()  # in units of |d|: <= 1 is on the segment
        hit = np.flatnonzero(t <= 1.0)
        if len(hit):
            ids = r["primitive_ids"].numpy()[hit].astype(np.int64)
            n = self._normal[ids] * self.face_side(ids)[:, None]
            out[hit] = np.einsum("nc,nc->n", n, d[hit]) > 0
            normal[hit] = np.where(out[hit, None], n, 0.0)
        return out, normal

    def up_gap(self, points: NDArray) -> NDArray:
        """(N,) distance straight up to the first surface (inf where none)."""
        p = np.asarray(points, np.float32).reshape(-1, 3)
        rays = np.concatenate([p, np.tile(np.float32([0, 0, 1]), (len(p), 1))], axis=1)
        return self.scene.cast_rays(self._o3d.core.Tensor(rays))["t_hit"].numpy()

    def down_gap(self, points: NDArray) -> NDArray:
        """(N,) distance straight down to the first surface (inf where none)."""
        p = np.asarray(points, np.float32).reshape(-1, 3)
        rays = np.concatenate([p, np.tile(np.float32([0, 0, -1]), (len(p), 1))], axis=1)
        return self.scene.cast_rays(self._o3d.core.Tensor(rays))["t_hit"].numpy()


#: A penetrating vertex's full-resolution depth is read from the detail mesh's faces within its
#: simplified depth plus this (metres): the simplified surface lies within about a clustering cell
#: (5 cm, its diagonal 8.7 cm) of the surface it was made from.
DETAIL_REACH_M = 0.1


def detail_signed_distance(vertices: NDArray, faces: NDArray, points: NDArray, reach_m: NDArray,
                           side_radius_m: float = 0.3, side_sheet_m: float = 0.01) -> NDArray[np.float64]:
    """(N,) signed distance (negative inside) of ``points`` (N, 3) to a full-resolution mesh
    (``vertices`` (M, 3), ``faces`` (F, 3)), read from its faces near the points only; NaN where it
    has no surface within ``reach_m`` (N,) of the point.

    The rule of :meth:`SceneQuery.signed_distance` on those faces: the closest face's side voted
    over its own sheet of the full mesh (``side_radius_m``, ``side_sheet_m``: a scanned mesh at full
    resolution has single faces turned over in its noise), inside = the closest point lying inside
    a face, straight behind it. (Not the simplified mesh's normal there: near a small feature, the
    side of a spike of the scan, the simplified surface faces another way than the face beside
    the point, and turning the face to agree with it reads the outside of the feature as inside.)"""
    from scipy.spatial import cKDTree

    p = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.full(len(p), np.nan)
    reach = np.broadcast_to(np.asarray(reach_m, np.float64), (len(p),))
    v, f = np.asarray(vertices, np.float64).reshape(-1, 3), np.asarray(faces, np.int64).reshape(-1, 3)
    if len(p) == 0 or len(f) == 0:
        return out
    # The faces with a vertex within reach (+ an edge length's margin, + the side vote's radius)
    # of some point, from a box around the points first.
    r = float(reach.max()) + 0.05 + max(float(side_radius_m), 0.0)
    box = np.flatnonzero(np.all((v >= p.min(axis=0) - r) & (v <= p.max(axis=0) + r), axis=1))
    seeds = np.unique(np.round(p / 0.01).astype(np.int64), axis=0) * 0.01  # the points to 1 cm
    d, _ = cKDTree(seeds).query(v[box], distance_upper_bound=r + 0.01)
    near_v = np.zeros(len(v), dtype=bool)
    near_v[box[np.isfinite(d)]] = True
    sel = f[near_v[f].any(axis=1)]
    if len(sel) == 0:
        return out
    used, local = np.unique(sel, return_inverse=True)
    sd, _ = SceneQuery(v[used], local.reshape(-1, 3), side_radius_m, side_sheet_m).signed_distance(p)
    ok = np.abs(sd) <= reach
    out[ok] = sd[ok]
    return out


def mesh_edges(faces: NDArray) -> NDArray[np.int64]:
    """(M, 2) the unique undirected edges (low index first) of a triangle mesh's faces (F, 3)."""
    f = np.asarray(faces, np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0)


def entered_through_surface(query: SceneQuery, verts: NDArray, sd: NDArray, normals: NDArray, near: NDArray,
                            edges: NDArray, same_sheet_cos: float = 0.5, chunk: int = 256) -> NDArray[np.bool_]:
    """(T, V) which body vertices behind a scene face got there through a seen surface.

    A scan sees a surface from one side only: the top of a seat, not its underside; the top of a
    table, not the space under it. Behind such a sheet the mesh says nothing, so "behind the
    closest face" does not mean "inside a solid": a calf under a chair seat is behind the seat's
    top. What the scan does tell is that a body cannot reach the far side of a seen surface without
    passing through it or round its edge. So a connected patch of body vertices behind the scene
    (``sd < 0`` and ``near``, connected by body mesh ``edges`` whose ends are behind the same
    sheet: their closest faces' normals within 60 degrees) penetrates only when one of its edges to
    the outside (``sd >= 0``) crosses a face from behind (:meth:`SceneQuery.exits`): a foot through
    the floor, a seat pushed into, a hand in a table top. A patch that meets the outside only round
    an edge (a calf under a seat, thighs under a table top) lies on the unseen side of an open
    sheet: outside. Of a patch that went through, only the vertices behind the sheet it crossed
    (closest face's normal within 60 degrees of a crossed face's) penetrate: splitting patches by
    sheet and this keep a small true crossing (a thigh through a seat's rounded front edge) from
    lending its "inside" to vertices behind another face next to it.

    Args:
        query: the scene; verts: (T, V, 3) body vertices; sd: (T, V) their signed distances;
        normals: (T, V, 3) outward normals of their closest faces; near: (T, V) vertices not deeper
        than the hole cut-off; edges: (M, 2) body mesh edges; same_sheet_cos: two behind vertices
        are behind the same sheet when their normals' dot product exceeds this; chunk: frames per
        connected-components graph (memory).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    behind = (sd < 0) & near
    outside = sd >= 0
    a, b = edges[:, 0], edges[:, 1]
    entered = np.zeros_like(behind)
    for s in range(0, len(sd), chunk):
        bh, out, v = behind[s:s + chunk], outside[s:s + chunk], verts[s:s + chunk]
        n, V = bh.shape
        if not bh.any():
            continue
        ab, ba = bh[:, a] & out[:, b], bh[:, b] & out[:, a]
        t, e = np.nonzero(ab | ba)  # edges from behind to outside
        inner = np.where(ab[t, e], a[e], b[e])
        outer = np.where(ab[t, e], b[e], a[e])
        crossed, cross_n = query.exits(v[t, inner], v[t, outer])
        if not crossed.any():
            continue
        nv = normals[s:s + chunk]
        same = np.einsum("tmc,tmc->tm", nv[:, a], nv[:, b]) > same_sheet_cos
        t2, e2 = np.nonzero(bh[:, a] & bh[:, b] & same)  # edges within the behind patches
        g = coo_matrix((np.ones(len(e2), np.int8), (t2 * V + a[e2], t2 * V + b[e2])), shape=(n * V, n * V))
        _, label = connected_components(g, directed=False)
        # A patch penetrates the sheet it went through: its vertices behind that sheet (normal
        # within 60 degrees of a crossed face's), not those behind another one it borders (a
        # thigh through a seat's rounded front edge does not put the buttocks above the seat
        # behind a sliver of its top). Crossed normals per patch, deduplicated on a coarse grid.
        key = np.unique(np.column_stack([label[t[crossed] * V + inner[crossed]],
                                         np.round(cross_n[crossed] * 4).astype(np.int64)]), axis=0)
        cand = np.flatnonzero(bh.reshape(-1) & np.isin(label, key[:, 0]))
        lo = np.searchsorted(key[:, 0], label[cand], "left")
        cnt = np.searchsorted(key[:, 0], label[cand], "right") - lo
        vi = np.repeat(cand, cnt)
        ki = np.repeat(lo - np.cumsum(cnt) + cnt, cnt) + np.arange(cnt.sum())
        kn = key[ki, 1:] / np.linalg.norm(key[ki, 1:], axis=1, keepdims=True).clip(1e-9)
        ok = np.einsum("pc,pc->p", nv.reshape(-1, 3)[vi], kn) > same_sheet_cos
        flat = np.zeros(n * V, dtype=bool)
        flat[vi[ok]] = True
        entered[s:s + chunk] = flat.reshape(n, V)
    return entered


def _unseen_side(query: SceneQuery, verts_all: NDArray, sd: NDArray, normals: NDArray, stride: int,
                 body_faces: NDArray, max_depth_m: float) -> NDArray[np.bool_]:
    """(T, V) the strided vertices behind a scene face that did not get there through it
    (:func:`entered_through_surface`, on the full body mesh: a patch is connected through the
    vertices a stride skips, whose signed distances are then measured on the frames that need them)."""
    behind = (sd < 0) & (sd > -max_depth_m)
    frames = np.flatnonzero(behind.any(axis=1))
    if len(frames) == 0:
        return np.zeros_like(behind)
    v = verts_all[frames]
    if stride == 1:
        sd_f, n_f = sd[frames], normals[frames]
    else:
        sd_f, n_f = query.signed_distance(v.reshape(-1, 3))
        sd_f, n_f = sd_f.reshape(v.shape[:2]), n_f.reshape(v.shape)
    entered = entered_through_surface(query, v, sd_f, n_f, sd_f > -max_depth_m, mesh_edges(body_faces))[:, ::stride]
    out = np.zeros_like(behind)
    out[frames] = behind[frames] & ~entered
    return out


def _part_of_vertex(body_model) -> NDArray[np.int64]:
    owner = np.asarray(body_model.lbs_weights).argmax(axis=1)
    part = np.full(len(owner), -1)
    for k, joints in enumerate(BODY_PARTS.values()):
        part[np.isin(owner, joints)] = k
    return part


def foot_skating(foot_xy: NDArray, foot_h: NDArray, H: float) -> NDArray[np.float64]:
    """MotionVAE foot skating per frame (T,), metres (last frame 0).

    Args:
        foot_xy: (T, F, 2) horizontal foot positions; foot_h: (T, F) height of each foot's lowest
            point above the support; H: height threshold, metres.
    """
    disp = np.linalg.norm(np.diff(foot_xy, axis=0), axis=-1)  # (T-1, F)
    h = np.clip(foot_h[:-1], 0.0, None)
    w = np.where(h < H, 2.0 - np.power(2.0, h / H), 0.0)
    out = np.zeros(len(foot_xy))
    if len(disp):
        out[:-1] = (disp * w).mean(axis=1)
    return out


def residual_root_wrench(sq: SimSequence, contact_pts: list[NDArray], contact_normals: list[NDArray],
                         contact_bodies: list[NDArray], cfg: SimCheckConfig,
                         hcfg: HumanoidConfig = HumanoidConfig()) -> tuple[NDArray, NDArray, float]:
    """Residual root force and torque per kg (T,), (T,) and the model's mass (kg).

    ``contact_*[t]`` are frame t's touching points (K, 3), scene normals (K, 3) and MuJoCo body
    ids (K,). Velocities and accelerations are central differences of the reference qpos.
    """
    from scipy.optimize import nnls

    from embodmocap.sim.deps import mujoco as _mujoco
    from embodmocap.sim.model import performer_mjcf, reference_qpos

    mujoco = _mujoco()  # one clear line naming the extra when missing

    m = mujoco.MjModel.from_xml_string(performer_mjcf(sq.body_model, sq.params.betas, hcfg))
    d = mujoco.MjData(m)
    mass = float(m.body_subtreemass[1])
    q = reference_qpos(sq.params, sq.rest_joints)
    T, dt = len(q), 1.0 / sq.params.fps
    v_half = np.zeros((max(T - 1, 0), m.nv))
    for t in range(T - 1):
        mujoco.mj_differentiatePos(m, v_half[t], dt, q[t], q[t + 1])
    qvel = np.zeros((T, m.nv))
    qacc = np.zeros((T, m.nv))
    if T > 1:
        qvel[1:-1] = (v_half[1:] + v_half[:-1]) / 2
        qvel[0], qvel[-1] = v_half[0], v_half[-1]
        qacc[1:-1] = (v_half[1:] - v_half[:-1]) / dt
    ang = np.linspace(0, 2 * np.pi, 4, endpoint=False)
    force, torque = np.zeros(T), np.zeros(T)
    jacp = np.zeros((3, m.nv))
    for t in range(T):
        d.qpos[:], d.qvel[:], d.qacc[:] = q[t], qvel[t], qacc[t]
        mujoco.mj_inverse(m, d)
        b = d.qfrc_inverse[:6].copy()
        pts, nrm, bodies = contact_pts[t], contact_normals[t], contact_bodies[t]
        r = b
        if len(pts):
            J6 = np.empty((len(pts), 3, 6))
            for i, (p, body) in enumerate(zip(pts, bodies)):
                mujoco.mj_jac(m, d, jacp, None, p, int(body))
                J6[i] = jacp[:, :6]
            n = nrm / np.linalg.norm(nrm, axis=1, keepdims=True).clip(1e-12)
            ref = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
            t1 = np.cross(n, ref)
            t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
            t2 = np.cross(n, t1)
            # Friction pyramid edges (K, 4, 3), mapped to the free joint's generalized force (K*4, 6).
            E = n[:, None] + cfg.friction * (np.cos(ang)[None, :, None] * t1[:, None] + np.sin(ang)[None, :, None] * t2[:, None])
            A = np.einsum("kcs,kdc->kds", J6, E).reshape(-1, 6).T
            f, _ = nnls(A, b, maxiter=200)
            r = b - A @ f
        force[t], torque[t] = np.linalg.norm(r[:3]) / mass, np.linalg.norm(r[3:]) / mass
    return force, torque, mass


def plausibility(sq: SimSequence, cfg: SimCheckConfig = SimCheckConfig(), *, residual: bool = True) -> dict:
    """Per-frame and summary figures of :mod:`this module <embodmocap.sim.check>` for one sequence."""
    t0 = time.perf_counter()
    verts_all = body_vertices(sq.body_model, sq.params)
    stride = max(int(cfg.vertex_stride), 1)
    verts = verts_all[:, ::stride]
    part = _part_of_vertex(sq.body_model)[::stride]
    owner = np.asarray(sq.body_model.lbs_weights).argmax(axis=1)[::stride]
    T, V = verts.shape[:2]
    query = SceneQuery(sq.scene_vertices, sq.scene_faces, cfg.side_radius_m, cfg.side_sheet_m,
                       cfg.max_depth_m if cfg.side_radius_m > 0 else np.inf)
    sd, normals = query.signed_distance(verts.reshape(-1, 3))
    sd, normals = sd.reshape(T, V), normals.reshape(T, V, 3)
    gap = query.down_gap(verts.reshape(-1, 3)).reshape(T, V)
    near = sd > -cfg.max_depth_m  # farther inside than that: a hole in the scan, not a penetration
    unseen = np.zeros((T, V), dtype=bool)
    if cfg.through_surface:
        unseen = _unseen_side(query, verts_all, sd, normals, stride, sq.body_model.faces, cfg.max_depth_m)
        # On the unseen side of an open sheet: outside it, facing its far side.
        sd, normals = np.where(unseen, -sd, sd), np.where(unseen[..., None], -normals, normals)
    if cfg.full_resolution_depth and sq.detail_vertices is not None:
        # How deep the vertices the simplified mesh calls inside are, on the full mesh around them.
        cand = (sd < 0) & near
        if cand.any():
            sd_full = detail_signed_distance(sq.detail_vertices, sq.detail_faces, verts[cand], -sd[cand] + DETAIL_REACH_M,
                                             cfg.side_radius_m, cfg.side_sheet_m)
            ok = np.isfinite(sd_full)
            sd_c = sd[cand].astype(np.float64)
            sd_c[ok] = sd_full[ok]
            out_now = sd_c >= 0  # outside on the full mesh: its distance bounds the gap
            g = gap[cand]
            g[out_now] = np.minimum(g[out_now], sd_c[out_now])
            sd = sd.astype(np.float64)
            sd[cand], gap[cand] = sd_c, g
            near[cand] = sd_c > -cfg.max_depth_m  # deeper than that on the full mesh: a hole there
    gap = np.where((sd < 0) & near, 0.0, gap)  # inside a solid: no gap
    pen = np.clip(-np.where(near, sd, np.inf).min(axis=1), 0.0, None)
    import warnings

    with warnings.catch_warnings():  # an all-NaN row (no support under any vertex) is expected
        warnings.simplefilter("ignore", RuntimeWarning)
        lowest = np.nanmin(np.where(np.isfinite(gap), gap, np.nan), axis=1)  # NaN: no support below at all
    floating = np.where(pen > 0, 0.0, np.clip(lowest, 0.0, None))
    supported = np.isfinite(floating)
    touch = (sd < cfg.contact_m) & near
    contact = {name: (touch & (part == k)).any(axis=1) for k, name in enumerate(BODY_PARTS)}
    # Foot skating: each foot's joints horizontally, its lowest point's gap.
    import torch

    with torch.no_grad():
        joints = sq.body_model.from_params(sq.params, dtype=torch.float64).joints.numpy()
    foot_xy = np.stack([joints[:, list(f), :2].mean(axis=1) for f in FEET], axis=1)
    foot_h = np.stack([np.where(np.isfinite(g := np.where(np.isin(owner, f), gap, np.inf)), g, np.inf).min(axis=1)
                       for f in FEET], axis=1)
    skate = foot_skating(foot_xy, foot_h, cfg.skate_height_m)
    out_frames = {
        "penetration_cm": pen * 100, "floating_cm": floating * 100, "foot_skating_cm": skate * 100,
    }
    summary = {
        "frames": int(T), "fps": float(sq.params.fps),
        "penetration_max_cm": float(pen.max() * 100) if T else 0.0,
        "penetration_mean_cm": float(pen.mean() * 100) if T else 0.0,
        "floating_max_cm": float(floating[supported].max() * 100) if supported.any() else 0.0,
        "floating_mean_cm": float(floating[supported].mean() * 100) if supported.any() else 0.0,
        "unsupported_frames": int((~supported).sum()),
        "unseen_side_frames": int(unseen.any(axis=1).sum()),
        "foot_skating_mean_cm": float(skate[:-1].mean() * 100) if T > 1 else 0.0,
        "foot_skating_max_cm": float(skate.max() * 100) if T else 0.0,
        "contact_fraction": {k: float(v.mean()) if T else 0.0 for k, v in contact.items()},
    }
    if residual:
        h_of_smpl = {int(j): i + 1 for i, j in enumerate(HUMANOID_TO_SMPL)}  # MuJoCo body id (0 = world)
        rng = np.random.default_rng(0)
        pts, nrm, bod = [], [], []
        for t in range(T):
            idx = np.flatnonzero(touch[t])
            if len(idx) > cfg.max_contact_points:
                idx = np.sort(rng.choice(idx, cfg.max_contact_points, replace=False))
            pts.append(verts[t, idx].astype(np.float64))
            nrm.append(normals[t, idx].astype(np.float64))
            bod.append(np.array([h_of_smpl[int(o)] for o in owner[idx]], dtype=np.int64))
        force, torque, mass = residual_root_wrench(sq, pts, nrm, bod, cfg)
        out_frames["residual_force_n_per_kg"] = force
        out_frames["residual_torque_nm_per_kg"] = torque
        summary.update({
            "mass_kg": mass,
            "residual_force_n_per_kg_mean": float(force.mean()) if T else 0.0,
            "residual_force_n_per_kg_max": float(force.max()) if T else 0.0,
            "residual_torque_nm_per_kg_mean": float(torque.mean()) if T else 0.0,
            "residual_torque_nm_per_kg_max": float(torque.max()) if T else 0.0,
        })
    summary["seconds"] = time.perf_counter() - t0
    per_frame = {k: [None if not np.isfinite(x) else x for x in np.round(np.asarray(v, dtype=np.float64), 4).tolist()]
                 for k, v in out_frames.items()}
    per_frame["contact"] = {k: v.astype(int).tolist() for k, v in contact.items()}
    return {"summary": summary, "per_frame": per_frame}


def vertical_repair(sq: SimSequence, per_frame: dict, cfg: SimCheckConfig = SimCheckConfig()) -> NDArray[np.float64]:
    """(T,) vertical shift of each frame (metres) that puts the lowest body point on the support.

    The smallest smooth correction: ``min sum_t w_t (d_t - g_t)^2 + repair_smooth * sum_t (d_{t+1} -
    2 d_t + d_{t-1})^2`` with ``g_t = penetration_t - floating_t`` and ``w_t = 1`` where ``|g_t| <
    repair_max_m`` (else 0: a jump stays a jump). Penalising the second difference keeps a slow
    drift (a ramp) fully corrected while an abrupt change is spread over a few frames.
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    g = (np.asarray(per_frame["penetration_cm"]) - np.asarray(per_frame["floating_cm"])) / 100.0
    w = (np.abs(g) < cfg.repair_max_m).astype(np.float64)
    T = len(g)
    if T < 3:
        return w * g
    D2 = sp.diags([np.ones(T - 2), -2 * np.ones(T - 2), np.ones(T - 2)], [0, 1, 2], shape=(T - 2, T))
    A = sp.diags(w + 1e-9) + cfg.repair_smooth * (D2.T @ D2)
    return np.asarray(spsolve(A.tocsc(), w * g))


@tracked_stage
def sim_check(session: str | Path, seq: str | None = None, cfg: SimCheckConfig = SimCheckConfig(),
              repair: bool = False, *, force: bool = False) -> Path:
    """Run the check on a sequence of a session and write ``sequences/<seq>/sim/sim_check.json``.

    With ``repair``, also :func:`vertical_repair` the motion, check it again, write it to
    ``sequences/<seq>/sim/smpl_repaired.npz`` (AMASS-style, like ``smpl_world.npz``) and add
    ``repair`` (shift statistics, summary before and after) to the JSON.

    Resumable like the stages (``sim/manifest.json``): a rerun with the same motion, mesh, body
    model and settings redoes nothing; the check's run time goes to the manifest, not the JSON, so
    the same input gives the same bytes.
    """
    import dataclasses

    from embodmocap.io.atomic import write_json
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.stage_manifest import StageManifest, fingerprint, path_fingerprint

    sq = load_sequence(session, seq, detail=cfg.full_resolution_depth)
    path = SessionLayout(sq.session).sequence(sq.name).sim_check
    path.parent.mkdir(parents=True, exist_ok=True)
    sm = StageManifest(path.parent / "manifest.json", "sim", {"check": asdict(cfg), "repair": repair},
                       inputs=sq.inputs, root=sq.session)
    fp = fingerprint("sim_check", SIM_FORMAT_VERSION, asdict(cfg), repair, *[path_fingerprint(p) for p in sq.inputs])
    with sm.step("check", fp, force=force) as st:
        if not st.run:
            return path
        res = plausibility(sq, cfg)
        res["summary"].pop("seconds")  # wall time: recorded by the manifest
        doc = {"version": SIM_FORMAT_VERSION, "sequence": sq.name, "frames": np.asarray(sq.frames).tolist(),
               "config": asdict(cfg), **res}
        outputs = [path]
        if repair:
            from embodmocap.io.amass import write_amass

            shift = vertical_repair(sq, res["per_frame"], cfg)
            transl = np.array(sq.params.transl)
            transl[:, 2] += shift
            fixed = dataclasses.replace(sq.params, transl=transl)
            after = plausibility(sq.with_params(fixed), cfg)["summary"]
            after.pop("seconds")
            out = path.parent / "smpl_repaired.npz"
            write_amass(out, fixed, frames=np.asarray(sq.frames))
            outputs.append(out)
            doc["repair"] = {"file": out.name, "shift_max_cm": float(np.abs(shift).max() * 100) if len(shift) else 0.0,
                             "shift_mean_cm": float(np.abs(shift).mean() * 100) if len(shift) else 0.0,
                             "before": res["summary"], "after": after}
        write_json(path, doc)
        s = res["summary"]
        st.record(outputs, {k: s[k] for k in ("penetration_max_cm", "floating_max_cm", "foot_skating_mean_cm") if k in s})
    log.info("sim check %s: penetration max %.2f cm, floating max %.2f cm, skating %.2f cm/frame, residual %.2f N/kg",
             sq.name, s["penetration_max_cm"], s["floating_max_cm"], s["foot_skating_mean_cm"],
             s.get("residual_force_n_per_kg_mean", float("nan")))
    return path


def unsupported_note(summary: dict) -> str | None:
    """One plain sentence when some frames have no scene surface at all under the body (holes in
    the scanned mesh), else None: floating is not measured on those frames and penetration may be
    missed there, so the figures describe the other frames only."""
    n, total = int(summary.get("unsupported_frames", 0)), int(summary.get("frames", 0))
    if n == 0:
        return None
    return (f"{n} of {total} frames ({100.0 * n / max(total, 1):.0f} %) have no scene surface under the body "
            f"(a hole in the scene mesh, e.g. floor the scan never saw): floating is not measured on them and "
            f"penetration may be missed; the figures describe the other frames.")
