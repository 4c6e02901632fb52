"""Fixtures: the studio's synthetic room filmed once, written in every app version's export layout.

Each writer here follows the app's documented layout (shared/reference/capture-formats.md and
docs/formats.md) on its own, with its own convention matrices, so a reader that mistakes a
convention disagrees with the truth. The walk is rendered with the studio's renderer and LiDAR
model; its poses live in a gravity-aligned "ARKit" world of known yaw and offset against the
room (floor at z = 0), so the floor of anything fused from a reader's output must be horizontal.

Conventions written (``A`` = ARKit world, Y up; ``W`` = the room's Z-up frame):
- ``M_A_W`` maps Z-up coordinates to ARKit's: x_A = x_W, y_A = z_W, z_A = -y_W;
- Stray Scanner: position = camera centre in A, quaternion = rotation of the OpenCV camera in A;
- Record3D: [qx, qy, qz, qw, tx, ty, tz] of the ARKit (OpenGL: x right, y up, z back) camera in A;
  older apps: relative to the first camera, with ``initPose`` the first camera in A;
- Spectacular AI: ``cameras_sai.jsonl`` positions and orientations of the OpenCV camera in the
  Z-up VIO world.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from embodmocap.io.video import VideoWriter
from embodmocap.types import Intrinsics

M_A_W = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
GL_FROM_CV = np.diag([1.0, -1.0, -1.0])
#: The capture's VIO world against the room: a yaw and an offset (gravity-aligned).
VIO_YAW = 0.8
VIO_OFFSET = np.array([1.1, -0.6, 0.25])


@dataclass
class Walk:
    """A rendered walk: truth poses in the capture's VIO world (Z up), frames, times."""

    K: Intrinsics
    """RGB intrinsics at the rendered size."""
    T_vio_cam: np.ndarray
    """(N, 4, 4) camera-to-VIO-world, OpenCV camera, Z up (the truth a reader must give back)."""
    rgb: list
    depth_mm: list
    conf: list
    times: np.ndarray
    fps: float
    floor_z_vio: float
    """Height of the room's floor in the VIO world."""


def _T_vio_scene(tilt_deg: float = 0.0) -> np.ndarray:
    c, s = np.cos(VIO_YAW), np.sin(VIO_YAW)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    T[:3, 3] = VIO_OFFSET
    if tilt_deg:
        a = np.deg2rad(tilt_deg)
        R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
        T[:3, :3] = R @ T[:3, :3]
    return T


def render_walk(width: int, height: int, depth_wh: tuple[int, int], seconds: float, fps: float, *,
                portrait: bool = False, seed: int = 3, tilt_deg: float = 0.0) -> Walk:
    """Render the studio's indoor room along its scene walk (``portrait``: the phone held upright,
    frames ``height`` x ``width`` turned). ``tilt_deg`` tilts the VIO world (a capture whose
    gravity is wrong)."""
    from embodmocap.synth import lidar, trajectory
    from embodmocap.synth.render import Renderer
    from embodmocap.synth.scene import build_scene

    rng = np.random.default_rng(seed)
    built = build_scene("indoor", np.random.default_rng([seed, 1]))
    T_scene_cam = trajectory.scene_walk(built.spec, seconds, fps, np.random.default_rng([seed, 5]))
    fx = (width / 2) / np.tan(np.deg2rad(63.0) / 2)
    K = Intrinsics(fx, fx, (width - 1) / 2, (height - 1) / 2, width, height)
    dw, dh = depth_wh
    if portrait:
        # Upright phone: the camera turns +90 deg about its optical axis (image x = old y).
        K = Intrinsics(fx, fx, (height - 1) / 2, (width - 1) / 2, height, width)
        dw, dh = dh, dw
        Rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
        T_scene_cam = T_scene_cam.copy()
        T_scene_cam[:, :3, :3] = T_scene_cam[:, :3, :3] @ Rz
    Kd = K.scaled(dw, dh)
    renderer = Renderer(built)
    rgb, depth, conf = [], [], []
    for T in T_scene_cam:
        r = renderer.render(K, T, None, False, Kd)
        d, c = lidar.simulate_lidar(r.depth_lr_m, rng)
        rgb.append(r.rgb)
        depth.append(d)
        conf.append(c)
    T_vio_scene = _T_vio_scene(tilt_deg)
    T_vio_cam = T_vio_scene @ T_scene_cam
    times = 500.0 + np.arange(len(T_scene_cam)) / fps
    return Walk(K, T_vio_cam, rgb, depth, conf, times, fps, float(T_vio_scene[2, 3]))


def _quat(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).as_quat()  # x, y, z, w


def _video(path: Path, frames: list, fps: float, size: tuple[int, int] | None = None) -> None:
    h, w = frames[0].shape[:2]
    if size is not None:
        w, h = size
    writer = VideoWriter(path, fps, w, h, crf=18)
    for f in frames:
        writer.write(f if size is None else cv2.resize(f, (w, h), interpolation=cv2.INTER_CUBIC))
    writer.close()


def _png(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), img)


# --------------------------------------------------------------------------- Stray Scanner


def write_stray(out: Path, walk: Walk, *, columns: int, video_size: tuple[int, int] | None = None,
                matrix_size: tuple[int, int] | None = None) -> Path:
    """A Stray Scanner export: ``columns`` 7 (oldest, no header), 9 or 15 (per-frame intrinsics,
    empty distortion fields, leading spaces). The video is ``video_size`` (default: the rendered
    size, upscaled otherwise); ``camera_matrix.csv`` is for ``matrix_size`` (default: the video's)."""
    out.mkdir(parents=True)
    K = walk.K
    vw, vh = video_size or (K.width, K.height)
    Kv = K.scaled(vw, vh)
    _video(out / "rgb.mp4", walk.rgb, walk.fps, (vw, vh) if (vw, vh) != (K.width, K.height) else None)
    for i, (d, c) in enumerate(zip(walk.depth_mm, walk.conf)):
        _png(out / "depth" / f"{i:06d}.png", d)
        _png(out / "confidence" / f"{i:06d}.png", c)
    Km = K.scaled(*(matrix_size or (vw, vh))).K
    (out / "camera_matrix.csv").write_text("".join(",".join(f"{v:.6f}" for v in row) + "\n" for row in Km))
    rows = []
    jitter = np.random.default_rng(0).normal(0, 0.002, (len(walk.times), 1))  # ARKit refines K a little
    for i, (T, t) in enumerate(zip(walk.T_vio_cam, walk.times)):
        p = M_A_W @ T[:3, 3]
        q = _quat(M_A_W @ T[:3, :3])
        pose = [f"{v:.9f}" for v in (*p, *q)]
        if columns == 7:
            rows.append(", ".join(pose))
        elif columns == 9:
            rows.append(", ".join([f"{t:.6f}", f"{i:06d}", *pose]))
        else:
            k = np.array([Kv.fx, Kv.fy, Kv.cx, Kv.cy]) * (1 + jitter[i])
            rows.append(", ".join([f"{t:.6f}", str(i), *pose, *(f"{v:.4f}" for v in k), "", ""]))
    header = {7: "", 9: "timestamp, frame, x, y, z, qx, qy, qz, qw\n",
              15: "timestamp, frame, x, y, z, qx, qy, qz, qw, fx, fy, cx, cy, distortion_center_x, "
                  "distortion_center_y\n"}[columns]
    (out / "odometry.csv").write_text(header + "".join(r + "\n" for r in rows))
    return out


# --------------------------------------------------------------------------- Record3D


def _r3d_poses(walk: Walk) -> np.ndarray:
    """(N, 4, 4) ARKit camera-to-world (OpenGL camera) in the ARKit world."""
    T = np.tile(np.eye(4), (len(walk.T_vio_cam), 1, 1))
    T[:, :3, :3] = M_A_W @ walk.T_vio_cam[:, :3, :3] @ GL_FROM_CV
    T[:, :3, 3] = walk.T_vio_cam[:, :3, 3] @ M_A_W.T
    return T


def _seven(T: np.ndarray) -> list:
    return [*_quat(T[:3, :3]).tolist(), *T[:3, 3].tolist()]


def write_record3d(out: Path, walk: Walk, *, older: bool, zipped: bool) -> Path:
    """A Record3D ``.r3d`` (``zipped``) or unzipped export. ``older``: metadata with only w, h, K,
    fps, poses (relative to the first camera) and initPose; else with dw, dh, frameTimestamps and
    world poses."""
    import lzfse

    K = walk.K
    T = _r3d_poses(walk)
    files: dict[str, bytes] = {}
    for i, (im, d, c) in enumerate(zip(walk.rgb, walk.depth_mm, walk.conf)):
        files[f"rgbd/{i}.jpg"] = cv2.imencode(".jpg", im[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
        files[f"rgbd/{i}.depth"] = lzfse.compress((d.astype(np.float32) / 1000.0).tobytes())
        files[f"rgbd/{i}.conf"] = lzfse.compress(c.astype(np.uint8).tobytes())
    meta = {"w": K.width, "h": K.height, "K": K.K.T.reshape(-1).tolist(), "fps": walk.fps}
    if older:
        rel = np.linalg.inv(T[0]) @ T
        meta["poses"] = [_seven(x) for x in rel]
        meta["initPose"] = _seven(T[0])
    else:
        dh, dw = walk.depth_mm[0].shape
        meta.update({"dw": dw, "dh": dh, "poses": [_seven(x) for x in T], "frameTimestamps": walk.times.tolist(),
                     "cameraType": 1})
    files["metadata"] = json.dumps(meta).encode()
    if zipped:
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
            for name, data in files.items():
                z.writestr(name, data)
        out.write_bytes(buf.getvalue())
    else:
        for name, data in files.items():
            (out / name).parent.mkdir(parents=True, exist_ok=True)
            (out / name).write_bytes(data)
    return out


def write_record3d_exr(out: Path, walk: Walk, dropped: tuple[int, ...] = (3, 4, 9)) -> Path:
    """Record3D's EXR + JPG export: metadata.json, rgb/N.jpg, depth/N.exr, frames ``dropped`` by
    the app missing (their numbers skipped; metadata keeps every pose and time)."""
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    K = walk.K
    dh, dw = walk.depth_mm[0].shape
    (out / "rgb").mkdir(parents=True)
    (out / "depth").mkdir()
    for i, (im, d) in enumerate(zip(walk.rgb, walk.depth_mm)):
        if i in dropped:
            continue
        assert cv2.imwrite(str(out / "rgb" / f"{i}.jpg"), im[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
        assert cv2.imwrite(str(out / "depth" / f"{i}.exr"), d.astype(np.float32) / 1000.0)
    meta = {"w": K.width, "h": K.height, "dw": dw, "dh": dh, "K": K.K.T.reshape(-1).tolist(), "fps": walk.fps,
            "cameraType": 1, "poses": [_seven(x) for x in _r3d_poses(walk)],
            "frameTimestamps": walk.times.tolist()}
    (out / "metadata.json").write_text(json.dumps(meta))
    return out


# --------------------------------------------------------------------------- Spectacular AI


def write_spectacular(out: Path, walk: Walk, sdk: bool = False) -> Path:
    """A Spectacular AI recording with the smoothed poses of ``sai-cli smooth`` (cameras_sai.jsonl),
    landscape: the Spectacular Rec iOS app's (data.jsonl, data.mov, frames2/, calibration.json,
    metadata.json; the paper's data) or, ``sdk``, the SDK recorder's (data.mp4, vio_config.yaml)."""
    out.mkdir(parents=True)
    K = walk.K
    _video(out / ("data.mp4" if sdk else "data.mov"), walk.rgb, walk.fps)
    if sdk:
        (out / "vio_config.yaml").write_text("useSlam: true\n")
    lines, poses = [], []
    for i, (T, t, d) in enumerate(zip(walk.T_vio_cam, walk.times, walk.depth_mm)):
        _png(out / "frames2" / f"{i:08d}.png", d)
        lines.append({"frames": [{"cameraInd": 0, "time": t}, {"cameraInd": 1, "time": t}], "number": i, "time": t})
        lines.append({"sensor": {"type": "accelerometer", "values": [0.0, 0.0, 9.81]}, "time": t + 0.001})
        lines.append({"sensor": {"type": "gyroscope", "values": [0.0, 0.0, 0.0]}, "time": t + 0.002})
        q = _quat(T[:3, :3])
        poses.append({"time": t, "position": dict(zip("xyz", T[:3, 3].tolist())),
                      "orientation": {"w": q[3], "x": q[0], "y": q[1], "z": q[2]}})
    (out / "data.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    (out / "cameras_sai.jsonl").write_text("".join(json.dumps(x) + "\n" for x in poses))
    cam = {"focalLengthX": K.fx, "focalLengthY": K.fy, "principalPointX": K.cx, "principalPointY": K.cy,
           "imageWidth": K.width, "imageHeight": K.height, "model": "pinhole", "distortionCoefficients": [0, 0, 0],
           "imuToCamera": np.eye(4).tolist()}
    (out / "calibration.json").write_text(json.dumps({"cameras": [cam]}))
    if not sdk:
        (out / "metadata.json").write_text(json.dumps({"platform": "ios", "device_model": "iPhone14,3"}))
    return out


def write_variant(name: str, out: Path, walk: Walk, big_video: tuple[int, int] | None = None) -> Path:
    """Write the capture variant ``name`` (see :data:`VARIANTS`) of ``walk`` at ``out``."""
    K = walk.K
    if name == "stray7":
        return write_stray(out, walk, columns=7)
    if name == "stray9":  # camera_matrix.csv for twice the video's size
        return write_stray(out, walk, columns=9, matrix_size=(2 * K.width, 2 * K.height))
    if name == "stray15":
        return write_stray(out, walk, columns=15, video_size=big_video)
    if name == "r3d_exr":
        return write_record3d_exr(out, walk)
    if name.startswith("r3d_"):
        older, zipped = "old" in name, name.endswith("zip")
        return write_record3d(out.with_suffix(".r3d") if zipped else out, walk, older=older, zipped=zipped)
    if name in ("spectacular", "spectacular_sdk"):
        return write_spectacular(out, walk, sdk=name.endswith("sdk"))
    raise KeyError(name)


#: Every export variant: name -> (app version in words, portrait phone).
VARIANTS = {
    "stray7": ("Stray Scanner, oldest header-less odometry.csv", False),
    "stray9": ("Stray Scanner, 9-column odometry.csv, camera_matrix.csv for another size", False),
    "stray15": ("Stray Scanner, 15-column odometry.csv with per-frame intrinsics", False),
    "r3d_new_zip": ("Record3D .r3d, newer metadata", True),
    "r3d_new_dir": ("Record3D unzipped .r3d, newer metadata", True),
    "r3d_old_zip": ("Record3D .r3d, older metadata (initPose, no dw/dh, no frameTimestamps)", True),
    "r3d_old_dir": ("Record3D unzipped .r3d, older metadata", True),
    "r3d_exr": ("Record3D EXR + JPG export with dropped frames", True),
    "spectacular": ("Spectacular AI recording (Spectacular Rec app) with sai-cli smooth poses", False),
    "spectacular_sdk": ("Spectacular AI SDK recording (data.mp4) with sai-cli smooth poses", False),
}
