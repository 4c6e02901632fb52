"""Files of the monocular pipeline: the inputs users bring (per-chunk scene-model output, a
camera-space SMPL file) and the outputs of ``embodmocap mono`` (``docs/formats.md``, section
"Monocular pipeline"). Every reader raises one :class:`InputError` naming the file."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.atomic import write_npz
from embodmocap.io.npz_file import load_npz

#: Version of ``cameras_world.npz`` written by ``embodmocap mono``.
MONO_CAMERAS_VERSION = 1


def chunk_file_name(first: int) -> str:
    """Name of the precomputed scene-model file of the chunk starting at sequence frame ``first``."""
    return f"chunk_{first:06d}.npz"


def plan_chunks(T: int, chunk: int, overlap: int) -> list[tuple[int, int]]:
    """Chunks ``[start, end)`` of ``chunk`` frames over ``T`` frames, consecutive ones sharing
    ``overlap`` frames; the last one ends at ``T`` (and may be shorter)."""
    if T <= 0:
        return []
    step = chunk - overlap
    out, start = [], 0
    while True:
        end = min(start + chunk, T)
        out.append((start, end))
        if end >= T:
            return out
        start += step


@dataclass(frozen=True)
class ChunkPrediction:
    """What a scene/camera model gives for one chunk, in its own arbitrary scale and frame.

    Attributes:
        frames: (N,) sequence frames of the chunk.
        T_world_cam: (N, 4, 4) camera-to-chunk-world poses (rigid, OpenCV axes), chunk units.
        local_points: (N, H, W, 3) per-pixel points in each frame's camera frame, chunk units;
            the map covers the whole RGB image (pixel (i, j) of the map is RGB pixel
            ``((j + 0.5) W_rgb / W - 0.5, (i + 0.5) H_rgb / H - 0.5)``).
        conf: (N, H, W) confidence in [0, 1] (0 = no point).
        metric: the units are metres (the ``vio`` model): the body's scale is then only reported.
        failure: why the model could not reconstruct the chunk ("" when it did): the stitching
            starts a new segment there with a warning, and the chunk's frames get no metric scale.
        registered: (N,) bool, frames the model reconstructed itself (None: all); the others'
            poses are interpolated and their maps empty (the ``colmap`` model).
    """

    frames: NDArray[np.int64]
    T_world_cam: NDArray[np.float64]
    local_points: NDArray[np.float32]
    conf: NDArray[np.float32]
    metric: bool = False
    failure: str = ""
    registered: NDArray[np.bool_] | None = None

    def world_points(self, idx: NDArray | slice = slice(None), rows: NDArray | slice = slice(None),
                     cols: NDArray | slice = slice(None)) -> NDArray[np.float64]:
        """(n, h, w, 3) points of frames ``idx`` at pixel ``rows`` x ``cols`` in the chunk's world
        (only those pixels are transformed: full maps of a real model are large)."""
        T = self.T_world_cam[idx]
        p = self.local_points[idx][:, rows][:, :, cols].astype(np.float64)
        return np.einsum("nij,nhwj->nhwi", T[:, :3, :3], p) + T[:, None, None, :3, 3]


def read_chunk(path: Path, frames: NDArray[np.int64]) -> ChunkPrediction:
    """Read one precomputed chunk file (Pi3 layout) and check it covers ``frames``."""
    fix = "write one file per chunk with camera_poses (N,4,4), local_points (N,H,W,3), conf (N,H,W), frames (N,)"
    if not path.is_file():
        raise InputError(path, f"missing the scene model's output for frames {int(frames[0])}..{int(frames[-1])}",
                         f"{fix}, chunked as --chunk/--overlap say (see docs/formats.md, 'Monocular pipeline')")
    d = load_npz(path, what="scene-model chunk", fix=fix, required=("camera_poses", "local_points", "conf", "frames"))
    poses = np.asarray(d["camera_poses"], dtype=np.float64)
    pts = np.asarray(d["local_points"], dtype=np.float32)
    conf = np.asarray(d["conf"], dtype=np.float32)
    got = np.asarray(d["frames"]).astype(np.int64).reshape(-1)
    N = len(got)
    if poses.shape != (N, 4, 4) or pts.ndim != 4 or pts.shape[0] != N or pts.shape[-1] != 3 or conf.shape != pts.shape[:3]:
        raise InputError(path, f"shapes do not fit: camera_poses {poses.shape}, local_points {pts.shape}, conf {conf.shape}, "
                         f"frames ({N},)", fix)
    if not np.array_equal(got, frames):
        raise InputError(path, f"holds frames {got[:1].tolist()}..{got[-1:].tolist()} ({N}), the chunk needs "
                         f"{int(frames[0])}..{int(frames[-1])} ({len(frames)})",
                         "rerun with the --chunk/--overlap the files were made with, or re-chunk the files")
    if not np.all(np.isfinite(poses)):
        raise InputError(path, "camera_poses has non-finite values", fix)
    conf = np.where(np.isfinite(conf), conf, 0.0).astype(np.float32)
    if conf.size and (conf.min() < 0 or conf.max() > 1):
        conf = (1.0 / (1.0 + np.exp(-conf))).astype(np.float32)  # raw logits (Pi3's conf head): squash
    bad = ~np.all(np.isfinite(pts), axis=-1) | (pts[..., 2] <= 0)
    conf = np.where(bad, 0.0, conf).astype(np.float32)
    pts = np.where(bad[..., None], 0.0, pts).astype(np.float32)
    return ChunkPrediction(frames.astype(np.int64), poses, pts, conf)


def write_chunk(path: Path, frames: NDArray, camera_poses: NDArray, local_points: NDArray, conf: NDArray) -> Path:
    """Write a chunk file in the layout :func:`read_chunk` reads (atomic)."""
    write_npz(path, frames=np.asarray(frames, dtype=np.int64), camera_poses=np.asarray(camera_poses, dtype=np.float64),
              local_points=np.asarray(local_points, dtype=np.float32), conf=np.asarray(conf, dtype=np.float32))
    return Path(path)


@dataclass(frozen=True)
class HumanSeq:
    """Camera-space SMPL per sequence frame ``0..T-1`` (OpenCV camera axes, metres).

    Attributes:
        global_orient: (T, 3) axis-angle root rotation in the camera frame.
        body_pose: (T, 69) axis-angle of SMPL joints 1..23.
        betas: (T, B) per-frame shape.
        transl: (T, 3) SMPL ``transl`` in the camera frame (pelvis at ``J_0(betas) + transl``).
        valid: (T,) bool: the model gave the frame.
    """

    global_orient: NDArray[np.float64]
    body_pose: NDArray[np.float64]
    betas: NDArray[np.float64]
    transl: NDArray[np.float64]
    valid: NDArray[np.bool_]


def human_from_rows(path: Path, frames: NDArray, go: NDArray, pose: NDArray, betas: NDArray, transl: NDArray,
                    T: int, valid: NDArray | None = None) -> HumanSeq:
    """A :class:`HumanSeq` over ``0..T-1`` from rows at ``frames``; rows absent stay invalid. A
    frame outside the video (``< 0`` or ``>= T``) or given twice is one error naming ``path``."""
    frames = np.asarray(frames).astype(np.int64).reshape(-1)
    n = len(frames)
    if n and (frames.min() < 0 or frames.max() >= T or len(np.unique(frames)) != n):
        raise InputError(path, f"its frames ({int(frames.min())}..{int(frames.max())}, {n} rows) do not match the "
                         f"video's {T} sequence frames 0..{T - 1} (or repeat)",
                         "write one row per sequence frame of the view (Stage II's numbering)")
    B = betas.shape[-1]
    out = HumanSeq(np.zeros((T, 3)), np.zeros((T, 69)), np.zeros((T, B)), np.zeros((T, 3)), np.zeros(T, bool))
    out.global_orient[frames] = go
    out.body_pose[frames] = pose.reshape(n, 69)
    out.betas[frames] = betas if betas.ndim == 2 else betas[None]
    out.transl[frames] = transl
    ok = np.ones(n, bool) if valid is None else np.asarray(valid, dtype=bool)
    # A row of zeros is "no estimate" (Stage II fills missing prior rows so).
    ok &= np.any(pose.reshape(n, 69) != 0, axis=1) | np.any(transl != 0, axis=1)
    out.valid[frames] = ok
    return out


def read_human_npz(path: Path, T: int) -> HumanSeq:
    """Read a camera-space SMPL file (``mono_human.npz``: VIMO / TRAM / GVHMR output) for ``T`` frames."""
    fix = "keys frames (T,), global_orient (T,3), body_pose (T,69), betas (T,B) or (B,), transl (T,3), camera frame"
    d = load_npz(path, what="camera-space SMPL", fix=fix,
                 required=("frames", "global_orient", "body_pose", "betas", "transl"))
    frames = np.asarray(d["frames"]).reshape(-1)
    n = len(frames)
    go, pose = np.asarray(d["global_orient"], float), np.asarray(d["body_pose"], float)
    betas, transl = np.asarray(d["betas"], float), np.asarray(d["transl"], float)
    if go.shape != (n, 3) or pose.reshape(n, -1).shape != (n, 69) or transl.shape != (n, 3) \
            or not (betas.ndim == 1 or betas.shape[0] == n):
        raise InputError(path, f"shapes do not fit {n} frames: global_orient {go.shape}, body_pose {pose.shape}, "
                         f"betas {betas.shape}, transl {transl.shape}", fix)
    if not all(np.all(np.isfinite(a)) for a in (go, pose, betas, transl)):
        raise InputError(path, "non-finite values", fix)
    valid = np.asarray(d["valid"], bool) if "valid" in d else None
    return human_from_rows(path, frames, go, pose, np.broadcast_to(betas, (n, betas.shape[-1])) if betas.ndim == 1 else betas,
                           transl, T, valid)


def write_human_npz(path: Path, human: HumanSeq) -> Path:
    """Write a :class:`HumanSeq` in the layout :func:`read_human_npz` reads (valid rows only)."""
    f = np.flatnonzero(human.valid)
    write_npz(path, frames=f.astype(np.int64), global_orient=human.global_orient[f], body_pose=human.body_pose[f],
              betas=human.betas[f], transl=human.transl[f])
    return Path(path)


def write_mono_cameras(path: Path, T_world_cam: NDArray, K: NDArray, width: int, height: int, segment: NDArray,
                       metric_scale: NDArray, fps: float) -> Path:
    """``mono/<view>/cameras_world.npz`` (version 1, see docs/formats.md)."""
    write_npz(path, version=np.int64(MONO_CAMERAS_VERSION), T_world_cam=np.asarray(T_world_cam, np.float64),
              K=np.asarray(K, np.float64), width=np.int64(width), height=np.int64(height),
              frames=np.arange(len(T_world_cam), dtype=np.int64), segment=np.asarray(segment, np.int64),
              metric_scale=np.asarray(metric_scale, np.float64), fps=np.float64(fps))
    return Path(path)


def read_mono_cameras(path: Path) -> dict[str, NDArray]:
    """Read ``mono/<view>/cameras_world.npz`` (keys as written by :func:`write_mono_cameras`)."""
    d = load_npz(path, what="monocular cameras", fix="run `embodmocap mono SESSION` to write it",
                 required=("version", "T_world_cam", "K", "frames", "segment", "metric_scale"))
    if int(d["version"]) != MONO_CAMERAS_VERSION:
        raise InputError(path, f"version {int(d['version'])} is not known (this package reads {MONO_CAMERAS_VERSION})",
                         "run `embodmocap mono SESSION --force` to write it again")
    return {k: np.asarray(d[k]) for k in d}


def write_points_ply(path: Path, points: NDArray, colours: NDArray) -> Path:
    """Binary little-endian PLY point cloud (atomic): float32 x, y, z and uint8 red, green, blue."""
    from embodmocap.io.atomic import write_bytes

    p = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    c = np.asarray(colours, dtype=np.uint8).reshape(-1, 3)
    rec = np.empty(len(p), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    rec["x"], rec["y"], rec["z"] = p[:, 0], p[:, 1], p[:, 2]
    rec["r"], rec["g"], rec["b"] = c[:, 0], c[:, 1], c[:, 2]
    head = ("ply\nformat binary_little_endian 1.0\n"
            f"element vertex {len(p)}\nproperty float x\nproperty float y\nproperty float z\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    write_bytes(path, head.encode() + rec.tobytes())
    return Path(path)


def read_points_ply(path: Path) -> tuple[NDArray[np.float32], NDArray[np.uint8]]:
    """(N, 3) points and (N, 3) colours of a file written by :func:`write_points_ply`."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    n = int([ln for ln in data[:end].decode().splitlines() if ln.startswith("element vertex")][0].split()[-1])
    rec = np.frombuffer(data[end:], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")],
                        count=n)
    return np.stack([rec["x"], rec["y"], rec["z"]], 1), np.stack([rec["r"], rec["g"], rec["b"]], 1)
