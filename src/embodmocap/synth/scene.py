"""The synthetic studio's static scene: a furnished room or a fenced yard built from boxes.

Every solid is a closed box (12 triangles, outward normals, counter-clockwise seen from outside), so
ray casting against the mesh is exact and the ground-truth mesh is watertight piece by piece. The
scene frame is Z up, metres, with the floor at z = 0 and the floor rectangle centred on the origin.

Furniture stands against the walls facing into the room (yaw a multiple of 90 degrees), without
overlap and with free floor in front of it, so the centre of the room stays free for the performer
(:attr:`SceneSpec.walk_area_min_xy` .. ``walk_area_max_xy``) and the camera operators.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from embodmocap.io.atomic import atomic_path
from embodmocap.synth.spec import Furniture, SceneSpec
from embodmocap.synth.texture import Material

log = logging.getLogger(__name__)

# Unit-cube corners: bit 0 -> x, bit 1 -> y, bit 2 -> z (0 = -0.5, 1 = +0.5).
_CORNERS = np.array([[(k >> 0) & 1, (k >> 1) & 1, (k >> 2) & 1] for k in range(8)], dtype=np.float64) - 0.5
# Two triangles per side, counter-clockwise seen from outside (outward normals by the right-hand rule).
_BOX_FACES = np.array(
    [
        [0, 4, 6], [0, 6, 2],  # -x
        [1, 3, 7], [1, 7, 5],  # +x
        [0, 1, 5], [0, 5, 4],  # -y
        [2, 6, 7], [2, 7, 3],  # +y
        [0, 2, 3], [0, 3, 1],  # -z
        [4, 5, 7], [4, 7, 6],  # +z
    ],
    dtype=np.int32,
)

WALL_THICKNESS_M = 0.2
"""Thickness of room walls, floor and ceiling slabs (outdoor fences are thinner)."""


def box_mesh(centres: NDArray, sizes: NDArray, yaws: NDArray | None = None) -> tuple[NDArray, NDArray]:
    """Triangle meshes of B boxes, vectorised.

    Args:
        centres: (B, 3) box centres, metres.
        sizes: (B, 3) full extents along the box's local x, y, z.
        yaws: (B,) rotation about +Z in radians (None = 0).

    Returns:
        vertices (8B, 3) float64 and faces (12B, 3) int32; box ``b`` owns vertices ``8b..8b+7`` and
        faces ``12b..12b+11``; every face's normal (right-hand rule) points out of its box.
    """
    centres = np.atleast_2d(np.asarray(centres, dtype=np.float64))
    sizes = np.atleast_2d(np.asarray(sizes, dtype=np.float64))
    B = len(centres)
    yaws = np.zeros(B) if yaws is None else np.broadcast_to(np.asarray(yaws, dtype=np.float64), (B,))
    c, s = np.cos(yaws), np.sin(yaws)
    local = _CORNERS[None] * sizes[:, None, :]  # (B, 8, 3)
    x = c[:, None] * local[..., 0] - s[:, None] * local[..., 1]
    y = s[:, None] * local[..., 0] + c[:, None] * local[..., 1]
    verts = np.stack([x, y, local[..., 2]], axis=-1) + centres[:, None, :]
    faces = (_BOX_FACES[None] + 8 * np.arange(B, dtype=np.int32)[:, None, None]).reshape(-1, 3)
    return verts.reshape(-1, 3), faces.astype(np.int32)


@dataclass(frozen=True)
class BuiltScene:
    """The static scene: its spec plus the triangle mesh the renderer casts rays against.

    Attributes:
        spec: the furniture and extents the performer's motion reads.
        vertices: (N, 3) float64, scene frame (Z up, metres, floor at z = 0).
        faces: (M, 3) int32 triangles, outward normals.
        face_material: (M,) int32 index into ``materials`` of each triangle.
        materials: texture parameters, one per material id.
        face_part: (M,) int32 index into ``part_names`` of each triangle (which solid it belongs to).
        part_names: name of each solid (``"floor"``, ``"wall_-x"``, ``"chair"`` ...).
    """

    spec: SceneSpec
    vertices: NDArray[np.float64]
    faces: NDArray[np.int32]
    face_material: NDArray[np.int32]
    materials: tuple[Material, ...]
    face_part: NDArray[np.int32] = field(default_factory=lambda: np.zeros(0, np.int32))
    part_names: tuple[str, ...] = ()

    def material_id(self, name: str) -> int:
        """Index of the material called ``name``."""
        return [m.name for m in self.materials].index(name)


# ------------------------------------------------------------------------------------------------
# Materials


def _materials(preset: str, rng: np.random.Generator, room: str = "standard") -> tuple[Material, ...]:
    """The palette: colours jittered per scene, so two seeds look different. ``room`` =
    ``"low_texture"`` makes walls and ceiling nearly plain paint; ``"repetitive"`` gives the walls
    a wallpaper pattern that repeats every two cells (many places look alike)."""

    def jit(rgb, amount=0.06):
        return tuple(np.clip(np.asarray(rgb) + rng.uniform(-amount, amount, 3), 0.02, 0.98).round(4).tolist())

    seed = int(rng.integers(1, 2**31 - 1))
    mats = [
        # name, base, alt, cell (m, x/y/z in the texture's rotated frame), blob (m), contrast, grout (m), grout rgb
        ("floor", jit([0.55, 0.42, 0.30]), jit([0.70, 0.58, 0.42]), (0.30, 0.30, 0.30), 0.05, 0.35, 0.006, (0.2, 0.17, 0.15)),
        ("wall", jit([0.78, 0.76, 0.70]), jit([0.62, 0.66, 0.70]), (0.22, 0.22, 0.22), 0.05, 0.40, 0.0, (0.0, 0.0, 0.0)),
        ("ceiling", jit([0.85, 0.85, 0.82]), jit([0.72, 0.72, 0.70]), (0.35, 0.35, 0.35), 0.07, 0.30, 0.0, (0.0, 0.0, 0.0)),
        ("wood", jit([0.45, 0.28, 0.15]), jit([0.62, 0.42, 0.24]), (0.10, 0.10, 0.60), 0.03, 0.35, 0.003, (0.18, 0.1, 0.05)),
        ("fabric", jit([0.25, 0.35, 0.55]), jit([0.45, 0.30, 0.35]), (0.15, 0.15, 0.15), 0.025, 0.45, 0.0, (0.0, 0.0, 0.0)),
        ("linen", jit([0.80, 0.78, 0.72]), jit([0.55, 0.65, 0.55]), (0.20, 0.20, 0.20), 0.03, 0.40, 0.004, (0.3, 0.3, 0.35)),
        ("box", jit([0.70, 0.55, 0.30]), jit([0.35, 0.50, 0.35]), (0.12, 0.12, 0.12), 0.025, 0.50, 0.003, (0.15, 0.12, 0.1)),
        ("poster", jit([0.85, 0.20, 0.15], 0.1), jit([0.10, 0.30, 0.75], 0.1), (0.07, 0.07, 0.07), 0.02, 0.60, 0.004, (0.05, 0.05, 0.05)),
        ("poster2", jit([0.95, 0.85, 0.20], 0.05), jit([0.10, 0.55, 0.25], 0.1), (0.10, 0.10, 0.10), 0.02, 0.60, 0.0, (0.0, 0.0, 0.0)),
        ("shelf", jit([0.30, 0.22, 0.18]), jit([0.75, 0.70, 0.55]), (0.06, 0.06, 0.25), 0.02, 0.50, 0.002, (0.1, 0.08, 0.05)),
    ]
    if preset == "outdoor":
        mats[0] = ("floor", jit([0.30, 0.45, 0.20]), jit([0.50, 0.48, 0.35]), (0.40, 0.40, 0.40), 0.04, 0.45, 0.0, (0.0, 0.0, 0.0))
        mats[1] = ("wall", jit([0.55, 0.40, 0.28]), jit([0.68, 0.55, 0.40]), (0.12, 0.12, 0.90), 0.04, 0.35, 0.004, (0.15, 0.1, 0.06))
    period = {}
    if room == "low_texture":
        # Plain paint: a barely visible mottle (real painted walls give SIFT almost nothing).
        wall_rgb = jit([0.80, 0.79, 0.75], 0.03)
        mats[1] = ("wall", wall_rgb, tuple(np.clip(np.asarray(wall_rgb) - 0.025, 0, 1).round(4).tolist()),
                   (0.40, 0.40, 0.40), 0.25, 0.04, 0.0, (0.0, 0.0, 0.0))
        mats[2] = ("ceiling", (0.88, 0.88, 0.86), (0.86, 0.86, 0.84), (0.5, 0.5, 0.5), 0.3, 0.03, 0.0, (0.0, 0.0, 0.0))
    elif room == "repetitive":
        mats[1] = ("wall", jit([0.75, 0.72, 0.62]), jit([0.45, 0.52, 0.62]), (0.16, 0.16, 0.16), 0.08, 0.35, 0.004,
                   (0.25, 0.22, 0.2))
        period[1] = 2
    return tuple(
        Material(n, b, a, c, bl, co, g, grgb, seed + 7919 * i, period.get(i, 0))
        for i, (n, b, a, c, bl, co, g, grgb) in enumerate(mats)
    )


# ------------------------------------------------------------------------------------------------
# Furniture: parts as boxes in the piece's local frame (x = front, y = along the wall, z = up).


def _legs(depth: float, width: float, height: float, t: float = 0.045) -> list[tuple]:
    """Four legs (centre, size) under a top of ``depth`` x ``width`` at ``height``."""
    out = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            out.append(((sx * (depth / 2 - t / 2), sy * (width / 2 - t / 2), height / 2), (t, t, height)))
    return out


def _piece_parts(name: str, size: NDArray, top_z: float, preset: str) -> list[tuple[tuple, tuple, str]]:
    """The boxes (local centre, size, material) of one piece of furniture."""
    d, w, h = size
    if name == "chair":
        seat_t, back_t = 0.05, 0.05
        parts = [(c, s, "wood") for c, s in _legs(d, w, top_z - seat_t)]
        parts.append(((0.0, 0.0, top_z - seat_t / 2), (d, w, seat_t), "wood" if preset == "outdoor" else "fabric"))
        parts.append(((-d / 2 + back_t / 2, 0.0, (top_z + h) / 2), (back_t, w, h - top_z), "wood"))
        return parts
    if name == "table":
        top_t = 0.04
        parts = [(c, s, "wood") for c, s in _legs(d, w, top_z - top_t)]
        parts.append(((0.0, 0.0, top_z - top_t / 2), (d, w, top_t), "wood"))
        return parts
    if name == "sofa":
        back_t, arm_w = 0.2, 0.16
        return [
            ((back_t / 2, 0.0, top_z / 2), (d - back_t, w - 2 * arm_w, top_z), "fabric"),
            ((-d / 2 + back_t / 2, 0.0, h / 2), (back_t, w, h), "fabric"),
            ((back_t / 2, -w / 2 + arm_w / 2, 0.3), (d - back_t, arm_w, 0.6), "fabric"),
            ((back_t / 2, w / 2 - arm_w / 2, 0.3), (d - back_t, arm_w, 0.6), "fabric"),
        ]
    if name == "bed":
        head_t = 0.08
        return [
            ((0.0, head_t / 2, top_z / 2), (d, w - head_t, top_z), "linen"),
            ((0.0, -w / 2 + head_t / 2, h / 2), (d, head_t, h), "wood"),
        ]
    if name == "box":
        return [((0.0, 0.0, h / 2), (d, w, h), "box")]
    if name == "shelf":
        parts = [((0.0, 0.0, h / 2), (d * 0.8, w, h), "shelf")]
        for z in np.linspace(0.35, h - 0.1, 4):  # shelf boards sticking out: corners for the texture
            parts.append(((0.0, 0.0, float(z)), (d, w, 0.03), "wood"))
        return parts
    raise ValueError(f"unknown furniture kind {name!r}")


def _draw_pieces(preset: str, rng: np.random.Generator) -> list[tuple[str, NDArray, float, float]]:
    """(name, size (3,), top_z, front clearance) of the pieces to place, biggest first."""
    u = rng.uniform
    outdoor = preset == "outdoor"
    big = "sofa" if rng.random() < 0.5 else "bed"
    pieces = []
    if big == "sofa":
        seat = u(0.40, 0.45)
        pieces.append(("sofa", np.array([u(0.85, 0.95), u(1.8, 2.2), u(0.80, 0.90)]), seat, 0.8))
    else:
        top = u(0.48, 0.55)
        pieces.append(("bed", np.array([u(1.4, 1.6), u(1.95, 2.1), u(0.95, 1.05)]), top, 0.8))
    seat = u(0.43, 0.47)
    chair_w = u(1.2, 1.5) if outdoor else u(0.45, 0.5)
    pieces.append(("chair", np.array([u(0.45, 0.5), chair_w, u(0.85, 0.95)]), seat, 0.8))
    top = u(0.72, 0.78)
    pieces.append(("table", np.array([u(0.7, 0.9), u(1.0, 1.4), top]), top, 0.6))
    hb = u(0.2, 0.3)
    pieces.append(("box", np.array([u(0.5, 0.6), u(0.55, 0.7), hb]), hb, 0.8))
    if not outdoor:
        hs = u(1.6, 2.0)
        pieces.append(("shelf", np.array([0.32, u(0.8, 1.2), hs]), hs, 0.3))
    return pieces


# Wall sides: inward normal and the yaw that makes a piece face into the room.
_SIDE_NORMAL = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])  # on -x, +x, -y, +y walls
_SIDE_YAW = np.array([0.0, np.pi, np.pi / 2, -np.pi / 2])


def _footprint(centre: NDArray, d: float, w: float, side: int) -> NDArray:
    """(2, 2) [min_xy, max_xy] of a piece standing against wall ``side`` (yaw multiple of 90 deg)."""
    half = np.array([d, w]) / 2 if side < 2 else np.array([w, d]) / 2
    return np.stack([centre - half, centre + half])


def _overlap(a: NDArray, b: NDArray) -> bool:
    return bool(np.all(a[0] < b[1]) and np.all(b[0] < a[1]))


def _place(pieces, lo: NDArray, hi: NDArray, rng: np.random.Generator, min_walk: NDArray):
    """Place pieces against the walls without overlap; returns (furniture, sides, walk lo, hi) or None."""
    placed: dict[str, Furniture] = {}
    zones: list[NDArray] = []  # footprint grown by the free floor the piece needs in front
    sides: dict[str, int] = {}
    band = np.zeros(4)  # how far furniture reaches into the room from each wall
    for name, size, top_z, clear in pieces:
        d, w = size[0], size[1]
        for _ in range(200):
            side = int(rng.integers(4))
            gap = rng.uniform(0.03, 0.12) if name != "box" else rng.uniform(0.15, 0.5)
            along_axis = 1 if side < 2 else 0
            normal_axis = 1 - along_axis
            span_lo, span_hi = lo[along_axis] + w / 2 + 0.05, hi[along_axis] - w / 2 - 0.05
            if span_lo >= span_hi:
                continue
            centre = np.zeros(2)
            centre[along_axis] = rng.uniform(span_lo, span_hi)
            wall = lo[normal_axis] if side in (0, 2) else hi[normal_axis]
            centre[normal_axis] = wall + _SIDE_NORMAL[side][normal_axis] * (gap + d / 2)
            fp = _footprint(centre, d, w, side)
            zone = fp.copy()
            grow = _SIDE_NORMAL[side] * clear
            zone[0] = np.minimum(zone[0], zone[0] + grow) - 0.08
            zone[1] = np.maximum(zone[1], zone[1] + grow) + 0.08
            if any(_overlap(fp, z) or _overlap(zone, z) for z in zones):
                continue
            zones.append(zone)
            sides[name] = side
            band[side] = max(band[side], gap + d + 0.35)
            placed[name] = Furniture(name, centre, float(_SIDE_YAW[side]), size.copy(), float(top_z))
            break
        else:
            return None
    band = np.maximum(band, 0.6)
    walk_lo = lo + np.array([band[0], band[2]])
    walk_hi = hi - np.array([band[1], band[3]])
    if np.any(walk_hi - walk_lo < min_walk):
        return None
    return placed, sides, walk_lo, walk_hi


def _laser_spot(lo, hi, furniture, sides, rng) -> tuple[NDArray, NDArray, int, float]:
    """A point on a wall at 1.2-1.6 m, away from tall furniture; returns (dot, normal, side, along)."""
    for _ in range(500):
        side = int(rng.integers(4))
        along_axis = 1 if side < 2 else 0
        normal_axis = 1 - along_axis
        a = rng.uniform(lo[along_axis] + 0.6, hi[along_axis] - 0.6)
        blocked = False
        for name, f in furniture.items():
            if sides[name] == side and f.size[2] > 1.1:
                if abs(a - f.centre_xy[along_axis]) < f.size[1] / 2 + 0.35:
                    blocked = True
        if blocked:
            continue
        dot = np.zeros(3)
        dot[along_axis] = a
        dot[normal_axis] = lo[normal_axis] if side in (0, 2) else hi[normal_axis]
        dot[2] = rng.uniform(1.2, 1.6)
        normal = np.zeros(3)
        normal[:2] = _SIDE_NORMAL[side]
        return dot, normal, side, a
    raise RuntimeError("no free wall spot for the laser dot")


def _pictures(lo, hi, furniture, sides, laser_side, laser_along, wall_h, rng, count):
    """Flat boxes on the walls (posters), away from the laser dot and tall furniture."""
    out = []
    for _ in range(count * 30):
        if len(out) >= count:
            break
        side = int(rng.integers(4))
        along_axis = 1 if side < 2 else 0
        normal_axis = 1 - along_axis
        pw, ph = rng.uniform(0.4, 1.0), rng.uniform(0.3, 0.7)
        a = rng.uniform(lo[along_axis] + pw / 2 + 0.2, hi[along_axis] - pw / 2 - 0.2)
        zc = rng.uniform(1.3 + ph / 2 - 0.2, min(wall_h - 0.25 - ph / 2, 2.1))
        if side == laser_side and abs(a - laser_along) < pw / 2 + 0.3:
            continue
        if any(sides[n] == side and f.size[2] > 1.1 and abs(a - f.centre_xy[along_axis]) < (f.size[1] + pw) / 2 + 0.1
               for n, f in furniture.items()):
            continue
        if any(o[0] == side and abs(a - o[1]) < (pw + o[2]) / 2 + 0.1 for o in out):
            continue
        out.append((side, a, pw, ph, zc))
    boxes = []
    for side, a, pw, ph, zc in out:
        along_axis = 1 if side < 2 else 0
        normal_axis = 1 - along_axis
        c = np.zeros(3)
        size = np.zeros(3)
        c[along_axis], size[along_axis] = a, pw
        wall = lo[normal_axis] if side in (0, 2) else hi[normal_axis]
        c[normal_axis], size[normal_axis] = wall + _SIDE_NORMAL[side][normal_axis] * 0.0125, 0.025
        c[2], size[2] = zc, ph
        boxes.append((c, size, 0.0, "poster" if rng.random() < 0.5 else "poster2", "picture"))
    return boxes


def _shell(preset: str, lo: NDArray, hi: NDArray, wall_h: float) -> list[tuple]:
    """Floor, walls (or fence with posts) and ceiling: (centre, size, yaw, material, part)."""
    t = WALL_THICKNESS_M if preset == "indoor" else 0.1
    L = hi - lo
    mid = (hi + lo) / 2
    out = [((mid[0], mid[1], -0.1), (L[0] + 2 * t, L[1] + 2 * t, 0.2), 0.0, "floor", "floor")]
    out += [
        ((lo[0] - t / 2, mid[1], wall_h / 2), (t, L[1] + 2 * t, wall_h), 0.0, "wall", "wall_-x"),
        ((hi[0] + t / 2, mid[1], wall_h / 2), (t, L[1] + 2 * t, wall_h), 0.0, "wall", "wall_+x"),
        ((mid[0], lo[1] - t / 2, wall_h / 2), (L[0], t, wall_h), 0.0, "wall", "wall_-y"),
        ((mid[0], hi[1] + t / 2, wall_h / 2), (L[0], t, wall_h), 0.0, "wall", "wall_+y"),
    ]
    if preset == "indoor":
        out.append(((mid[0], mid[1], wall_h + 0.1), (L[0] + 2 * t, L[1] + 2 * t, 0.2), 0.0, "ceiling", "ceiling"))
    else:
        # Fence posts every ~2 m along each side: relief and corners for feature matching.
        for axis in (0, 1):
            n = max(2, int(np.ceil(L[axis] / 2.0)))
            for a in np.linspace(lo[axis] + 0.3, hi[axis] - 0.3, n):
                for wall in (lo[1 - axis], hi[1 - axis]):
                    c = np.zeros(3)
                    c[axis] = a
                    c[1 - axis] = wall + (0.05 if wall == lo[1 - axis] else -0.05)
                    c[2] = (wall_h + 0.1) / 2
                    out.append((tuple(c), (0.1, 0.1, wall_h + 0.1), 0.0, "wood", "post"))
    return out


#: Indoor room presets (:func:`build_scene`'s ``room``).
ROOMS = ("standard", "large", "high_ceiling", "low_texture", "repetitive")


def build_scene(preset: Literal["indoor", "outdoor"], rng: np.random.Generator, room: str = "standard") -> BuiltScene:
    """Build a random furnished room (``"indoor"``) or fenced yard (``"outdoor"``).

    Indoor: 4.5-7 x 4-6 m, walls 2.6-3 m, ceiling, pictures and a shelf. Outdoor: 8-12 m square-ish
    yard with a 1.8-2.2 m fence and posts, no ceiling. Both hold a chair (a bench outdoors), a
    table, a box to step on and a sofa or a bed, placed against the walls without overlap.

    ``room`` (indoor only) picks a harder studio: ``"large"`` an 8 x 6 m room (far walls beyond a
    3.5 m depth cut), ``"high_ceiling"`` a 4-4.6 m ceiling, ``"low_texture"`` plain painted walls
    and ceiling with a single picture, ``"repetitive"`` walls with a repeating wallpaper. The
    ``"standard"`` room draws exactly what it always drew (same seed, same scene).
    """
    if preset not in ("indoor", "outdoor"):
        raise ValueError(f"preset must be 'indoor' or 'outdoor', not {preset!r}")
    if room not in ROOMS or (room != "standard" and preset != "indoor"):
        raise ValueError(f"room must be one of {ROOMS} (non-standard rooms are indoor only), not {room!r}")
    materials = _materials(preset, rng, room)
    for _ in range(100):
        if preset == "indoor":
            L = np.array([rng.uniform(4.5, 7.0), rng.uniform(4.0, 6.0)])
            wall_h = float(rng.uniform(2.6, 3.0))
            min_walk = np.array([1.8, 1.8])
            if room == "large":
                L = np.array([8.0, 6.0]) + rng.uniform(-0.15, 0.15, 2)
            elif room == "high_ceiling":
                wall_h = float(rng.uniform(4.0, 4.6))
        else:
            L = rng.uniform(8.0, 12.0, 2)
            wall_h = float(rng.uniform(1.8, 2.2))
            min_walk = np.array([3.0, 3.0])
        lo, hi = -L / 2, L / 2
        res = _place(_draw_pieces(preset, rng), lo, hi, rng, min_walk)
        if res is not None:
            break
    else:  # pragma: no cover - the ranges above always leave room in practice
        raise RuntimeError("could not place the furniture")
    furniture, sides, walk_lo, walk_hi = res
    if preset == "outdoor":
        # Keep the performer's area compact so the operators (1.5-4 m away) stay near textured fences.
        centre = (walk_lo + walk_hi) / 2
        half = np.minimum((walk_hi - walk_lo) / 2, 2.5)
        walk_lo, walk_hi = centre - half, centre + half
    dot, normal, laser_side, laser_along = _laser_spot(lo, hi, furniture, sides, rng)

    solids = _shell(preset, lo, hi, wall_h)
    for name, f in furniture.items():
        c, s = np.cos(f.yaw), np.sin(f.yaw)
        for pc, ps, mat in _piece_parts(name, f.size, f.top_z, preset):
            wx = f.centre_xy[0] + c * pc[0] - s * pc[1]
            wy = f.centre_xy[1] + s * pc[0] + c * pc[1]
            solids.append(((wx, wy, pc[2]), ps, f.yaw, mat, name))
    if preset == "indoor":
        n_pics = int(rng.integers(3, 6)) if room != "low_texture" else 1
        solids += _pictures(lo, hi, furniture, sides, laser_side, laser_along, wall_h, rng, n_pics)

    names = [m.name for m in materials]
    part_names = tuple(dict.fromkeys(s[4] for s in solids))
    verts, faces = box_mesh(
        np.array([s[0] for s in solids], dtype=np.float64),
        np.array([s[1] for s in solids], dtype=np.float64),
        np.array([s[2] for s in solids], dtype=np.float64),
    )
    face_material = np.repeat(np.array([names.index(s[3]) for s in solids], dtype=np.int32), 12)
    face_part = np.repeat(np.array([part_names.index(s[4]) for s in solids], dtype=np.int32), 12)
    spec = SceneSpec(
        preset=preset,
        floor_min_xy=lo,
        floor_max_xy=hi,
        wall_height=wall_h,
        furniture=furniture,
        laser_dot=dot,
        laser_normal=normal,
        walk_area_min_xy=walk_lo,
        walk_area_max_xy=walk_hi,
        extras={"wall_thickness_m": WALL_THICKNESS_M if preset == "indoor" else 0.1,
                "ceiling": 1.0 if preset == "indoor" else 0.0},
    )
    log.debug("built %s scene %.1f x %.1f m, %d triangles", preset, L[0], L[1], len(faces))
    return BuiltScene(spec, verts, faces, face_material, materials, face_part, part_names)


def scene_mesh_trimesh(built: BuiltScene):
    """The static scene as a ``trimesh.Trimesh`` (scene frame, metres), unmerged boxes."""
    import trimesh

    return trimesh.Trimesh(vertices=built.vertices, faces=built.faces, process=False)


def write_scene_ply(built: BuiltScene, path: str | Path) -> Path:
    """Write the ground-truth scene mesh as a binary PLY (scene frame, Z up, metres), atomically.

    Faces carry no colour; the file holds ``vertex`` (x, y, z float) and ``face`` (vertex_indices).
    """
    path = Path(path)
    mesh = scene_mesh_trimesh(built)
    with atomic_path(path, suffix=".ply") as tmp:
        tmp.write_bytes(mesh.export(file_type="ply", encoding="binary"))
    return path
