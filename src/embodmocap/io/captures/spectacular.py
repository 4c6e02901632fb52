"""Spectacular AI recordings (the paper's released data format): read and write.

Folder layout (see docs/formats.md)::

    data.jsonl          one JSON object per line: frame lines {"frames": [...], "number": n, "time": t},
                        IMU lines {"sensor": {"type": "accelerometer"|"gyroscope", "values": [...]}, "time": t}
    data.mov            RGB video (frame i <-> data.jsonl frame number i); the Spectacular Rec iOS
                        app (the paper's data) writes data.mov, the SDK's recorder data.mp4 or data.mkv
    frames2/%08d.png    uint16 depth in millimetres, one per frame number
    calibration.json    cameras[0]: focalLengthX/Y, principalPointX/Y, imageWidth/imageHeight, model, ...
    metadata.json       platform etc.
    cameras_sai.jsonl   smoothed per-frame poses ("sai-cli smooth" output): time, position{x,y,z},
                        orientation{w,x,y,z}; camera-to-world, OpenCV camera, Z-up world
    transforms.json     (scene recordings) Nerfstudio key frames, OpenGL camera-to-world, Z-up world

Poses are matched to frames by nearest time (a quarter of a frame interval tolerance), never by
exact float equality. Portrait recordings are detected from the data: when the video frames have
the calibration's width and height swapped, intrinsics, poses and depth maps are turned to match the
video frames (direction from the video's display rotation; clockwise, like ``transpose=1``, if none).
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.geometry.transforms import gl_to_cv_cam, make_T, quat_to_matrix, matrix_to_quat
from embodmocap.io.atomic import write_json, write_text
from embodmocap.io.captures.common import (
    CaptureScan, LazyFrames, LazyVideo, Problem, capture_from_scan, depth_file_problems,
    intrinsics_problems, pose_problems, probe_app_video, quarter_turns_for, rotate_camera_poses, rotate_intrinsics,
    write_png,
)
from embodmocap.io.video import VideoWriter
from embodmocap.types import Capture, CameraTrajectory, ImuSamples, Intrinsics

log = logging.getLogger(__name__)

FORMAT = "spectacular"
POSE_FILE = "cameras_sai.jsonl"
#: The RGB video's name: the Spectacular Rec app's first, then the SDK recorder's.
VIDEO_NAMES = ("data.mov", "data.mp4", "data.mkv")
#: A pose matches a frame when their times differ by less than this fraction of a frame interval.
TIME_TOLERANCE_FRAMES = 0.25


def is_spectacular(path: Path) -> bool:
    """True if ``path`` looks like a Spectacular AI recording (data.jsonl + calibration.json)."""
    return path.is_dir() and (path / "data.jsonl").exists() and (path / "calibration.json").exists()


def read_spectacular(path: str | Path) -> Capture:
    """Read a Spectacular AI recording (with its ``cameras_sai.jsonl`` poses) into a Capture.

    Raises:
        InputError: on the first problem found, naming the file and what to do.
    """
    return capture_from_scan(scan_spectacular(path))


def scan_spectacular(path: str | Path, thorough: bool = False) -> CaptureScan:
    """Read everything but the frames, collecting every problem instead of stopping."""
    root = Path(path)
    problems: list[Problem] = []
    if not root.is_dir():
        return CaptureScan(root, FORMAT, problems=(Problem(root, "recording folder not found"),))

    video = next((root / n for n in VIDEO_NAMES if (root / n).is_file()), root / VIDEO_NAMES[0])
    info, problems = probe_app_video(
        video, "a Spectacular AI recording holds its RGB video as data.mov (Spectacular Rec app) or data.mp4 / "
               "data.mkv (SDK recorder)", "copy the whole recording folder (unzip the app's recording_*.zip)")
    num_frames = info.num_frames if info else 0
    fps = info.fps if info else 0.0

    frame_times = np.zeros(0)
    imu = ImuSamples.empty()
    try:
        frame_numbers, frame_times_all, imu = read_data_jsonl(root / "data.jsonl")
        frame_times = np.full(max(num_frames, int(frame_numbers.max(initial=-1)) + 1), np.nan)
        frame_times[frame_numbers] = frame_times_all
        frame_times = frame_times[:num_frames] if num_frames else frame_times
        if num_frames and np.isnan(frame_times).any():
            n_missing = int(np.isnan(frame_times).sum())
            problems.append(Problem(root / "data.jsonl", f"{n_missing} of {num_frames} video frames have no "
                                    "frame line", "the recording is incomplete; copy it again"))
    except InputError as err:
        problems.append(Problem(root / "data.jsonl", err.problem, err.fix))

    K = None
    k_turns = 0
    calib = root / "calibration.json"
    try:
        K_cal = read_calibration(calib)
        if info is not None:
            turns = quarter_turns_for((info.width, info.height), (K_cal.width, K_cal.height), info.rotation_deg)
            if turns is None:
                problems.append(Problem(calib, f"calibration is for {K_cal.width}x{K_cal.height} but the video is "
                                        f"{info.width}x{info.height}", "use the recording's own calibration.json"))
            else:
                k_turns = turns
                if k_turns:
                    log.info("%s: portrait video (%dx%d, calibration %dx%d); turning intrinsics, poses and "
                             "depth by %d quarter turns", root, info.width, info.height, K_cal.width,
                             K_cal.height, k_turns)
                K = rotate_intrinsics(K_cal, k_turns).scaled(info.width, info.height)
                problems += intrinsics_problems(calib, K)
    except InputError as err:
        problems.append(Problem(calib, err.problem, err.fix))

    trajectory = None
    pose_path = root / POSE_FILE
    try:
        t_pose, T = read_pose_jsonl(pose_path)
        if len(frame_times) and fps > 0:
            frames, rows = match_times(frame_times, t_pose, TIME_TOLERANCE_FRAMES / fps)
            if len(rows) < len(t_pose):
                log.info("%s: %d of %d poses match no frame time", pose_path, len(t_pose) - len(rows), len(t_pose))
            T_frames = rotate_camera_poses(T[rows], k_turns)
            problems += pose_problems(pose_path, T_frames, fps, num_frames)
            trajectory = CameraTrajectory(frame_times[frames], frames, T_frames)
    except InputError as err:
        problems.append(Problem(pose_path, err.problem, err.fix))

    depth_paths = [root / "frames2" / f"{i:08d}.png" for i in range(num_frames)]
    dprob, raw_depth_size = depth_file_problems(
        depth_paths, None, "uint16", thorough, "a Spectacular AI recording holds one frames2/NNNNNNNN.png (uint16 mm) "
                                               "per video frame")
    problems += dprob
    depth_size = None
    if raw_depth_size is not None:
        depth_size = raw_depth_size if k_turns % 2 == 0 else raw_depth_size[::-1]

    def make_frames() -> LazyFrames:
        return LazyFrames(num_frames, LazyVideo(video), lambda i: root / "frames2" / f"{i:08d}.png", None,
                          raw_depth_size, rot90=k_turns)

    timestamps = frame_times if len(frame_times) == num_frames and not np.isnan(frame_times).any() else (
        info.timestamps_s if info else np.zeros(0))
    return CaptureScan(
        path=root, format=FORMAT, variant=_variant(root, video, k_turns), num_frames=num_frames, fps=fps, rgb_intrinsics=K, depth_size=depth_size,
        timestamps_s=timestamps, trajectory=trajectory, imu=imu, make_frames=make_frames,
        problems=tuple(problems),
    )


def _variant(root: Path, video: Path, k_turns: int) -> str:
    """The recording in words: the recorder named in ``metadata.json`` (when it says), which
    recorder the video's name comes from, orientation, and whether the key frames of
    ``sai-cli process`` are there."""
    head = "Spectacular AI recording"
    try:
        meta = json.loads((root / "metadata.json").read_text())
        if isinstance(meta, dict):
            who = " ".join(str(meta[k]) for k in ("platform", "device_model", "software", "version", "sdkVersion")
                           if meta.get(k))
            head += f" ({who})" if who else ""
    except (OSError, ValueError):
        pass
    recorder = "Spectacular Rec app" if video.name == "data.mov" else "SDK recorder"
    parts = [head, f"{video.name} ({recorder})", "portrait video" if k_turns else "landscape video",
             f"poses from {POSE_FILE}"]
    if (root / "transforms.json").is_file():
        parts.append("with sai-cli process key frames (transforms.json)")
    return ", ".join(parts)


# --------------------------------------------------------------------------- file parsers


def _json_lines(path: Path) -> list[dict]:
    if not path.is_file():
        raise InputError(path, f"{path.name} not found", "copy the complete recording")
    out = []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError as err:
            raise InputError(path, f"line {n} is not JSON ({err.msg})", "the file is truncated or edited") from err
    return out


def read_data_jsonl(path: Path) -> tuple[NDArray[np.int64], NDArray[np.float64], ImuSamples]:
    """(frame numbers, frame times in s, IMU) from ``data.jsonl``.

    Gyroscope samples are interpolated to the accelerometer times so that both share one clock
    axis (the two sensors report separately).
    """
    records = _json_lines(path)
    frames = [(r["number"], r["time"]) for r in records if "frames" in r and "number" in r and "time" in r]
    if not frames:
        raise InputError(path, "no frame lines ({\"frames\": ..., \"number\": n, \"time\": t})",
                         "this is not a Spectacular AI recording or it is empty")
    numbers = np.array([f[0] for f in frames], dtype=np.int64)
    times = np.array([f[1] for f in frames], dtype=np.float64)
    sensors: dict[str, list] = {"accelerometer": [], "gyroscope": []}
    for r in records:
        s = r.get("sensor")
        if isinstance(s, dict) and s.get("type") in sensors and "time" in r:
            sensors[s["type"]].append([r["time"], *s["values"][:3]])
    acc = np.array(sensors["accelerometer"], dtype=np.float64).reshape(-1, 4)
    gyr = np.array(sensors["gyroscope"], dtype=np.float64).reshape(-1, 4)
    imu = ImuSamples.empty()
    if len(acc) and len(gyr):
        acc = acc[np.argsort(acc[:, 0], kind="stable")]
        gyr = gyr[np.argsort(gyr[:, 0], kind="stable")]
        g = np.stack([np.interp(acc[:, 0], gyr[:, 0], gyr[:, 1 + k]) for k in range(3)], axis=1)
        imu = ImuSamples(acc[:, 0], acc[:, 1:], g)
    return numbers, times, imu


def read_calibration(path: Path) -> Intrinsics:
    """Intrinsics of ``cameras[0]`` of ``calibration.json`` at its imageWidth x imageHeight."""
    if not path.is_file():
        raise InputError(path, "calibration.json not found", "copy the complete recording")
    try:
        cam = json.loads(path.read_text())["cameras"][0]
        K = Intrinsics(float(cam["focalLengthX"]), float(cam.get("focalLengthY", cam["focalLengthX"])),
                       float(cam["principalPointX"]), float(cam["principalPointY"]),
                       int(cam["imageWidth"]), int(cam["imageHeight"]))
    except (json.JSONDecodeError, KeyError, IndexError, TypeError, ValueError) as err:
        raise InputError(path, f"malformed calibration ({err.__class__.__name__}: {err})",
                         "expected cameras[0] with focalLengthX/Y, principalPointX/Y, imageWidth/Height") from err
    coeffs = cam.get("distortionCoefficients") or []
    if cam.get("model", "pinhole") != "pinhole" and any(abs(c) > 1e-9 for c in coeffs):
        log.warning("%s: camera model %s with distortion is treated as pinhole", path, cam.get("model"))
    return K


def read_pose_jsonl(path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(times (N,), T_world_cam (N, 4, 4)) from a smoothed-pose JSONL, sorted by time."""
    records = _json_lines(path)
    if not records:
        raise InputError(path, "no poses", "run 'sai-cli smooth' on the recording")
    try:
        t = np.array([r["time"] for r in records], dtype=np.float64)
        p = np.array([[r["position"][k] for k in "xyz"] for r in records], dtype=np.float64)
        q = np.array([[r["orientation"][k] for k in "xyzw"] for r in records], dtype=np.float64)
    except (KeyError, TypeError) as err:
        raise InputError(path, f"pose line lacks {err}", "expected time, position{x,y,z}, orientation{w,x,y,z}") from err
    order = np.argsort(t, kind="stable")
    R = quat_to_matrix(q, invalid="nan")
    return t[order], make_T(R, p)[order]


def match_times(frame_times: NDArray, pose_times: NDArray, tol_s: float) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Match each pose time to the nearest frame time within ``tol_s``.

    Returns (frame indices, pose rows), sorted by frame, one pose per frame (the closest).
    ``frame_times`` may hold NaN for frames without a time; they never match.
    """
    valid = np.nonzero(np.isfinite(frame_times))[0]
    ft = frame_times[valid]
    order = np.argsort(ft)
    ft_sorted = ft[order]
    pos = np.clip(np.searchsorted(ft_sorted, pose_times), 1, max(len(ft_sorted) - 1, 1))
    left = ft_sorted[pos - 1]
    right = ft_sorted[np.minimum(pos, len(ft_sorted) - 1)]
    take_left = np.abs(pose_times - left) <= np.abs(pose_times - right)
    nearest = np.where(take_left, pos - 1, np.minimum(pos, len(ft_sorted) - 1))
    err = np.abs(pose_times - ft_sorted[nearest])
    rows = np.nonzero(err <= tol_s)[0]
    frames = valid[order[nearest[rows]]]
    # One pose per frame: sort by (frame, error) and keep the first of each frame.
    key = np.lexsort((err[rows], frames))
    frames, rows = frames[key], rows[key]
    first = np.ones(len(frames), bool)
    first[1:] = frames[1:] != frames[:-1]
    return frames[first].astype(np.int64), rows[first].astype(np.int64)


# --------------------------------------------------------------------------- transforms.json


_FRAME_NUMBER = re.compile(r"(\d+)(?!.*\d)")


def read_transforms_json(path: str | Path) -> tuple[Intrinsics, NDArray[np.int64], NDArray[np.float64]]:
    """Key frames of a Nerfstudio ``transforms.json`` in time order.

    Returns (intrinsics at w x h, frame numbers parsed from ``file_path`` (N,),
    T_world_cam (N, 4, 4) with OpenCV camera axes). The file stores OpenGL camera-to-world matrices
    and lists train frames before val frames, so rows are sorted by frame number here.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "transforms.json not found", "run 'sai-cli process' on the scene recording")
    try:
        d = json.loads(path.read_text())
        K = Intrinsics(float(d["fl_x"]), float(d.get("fl_y", d["fl_x"])), float(d["cx"]), float(d["cy"]),
                       int(d["w"]), int(d["h"]))
        names = [f["file_path"] for f in d["frames"]]
        T_gl = np.array([f["transform_matrix"] for f in d["frames"]], dtype=np.float64).reshape(-1, 4, 4)
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise InputError(path, f"malformed transforms.json ({err.__class__.__name__}: {err})",
                         "expected fl_x, cx, cy, w, h and frames[] with file_path and transform_matrix") from err
    numbers = []
    for name in names:
        m = _FRAME_NUMBER.search(Path(name).stem)
        if m is None:
            raise InputError(path, f"no frame number in file_path {name!r}", "expected names like frame_00012.jpg")
        numbers.append(int(m.group(1)))
    numbers = np.array(numbers, dtype=np.int64)
    order = np.argsort(numbers, kind="stable")
    return K, numbers[order], gl_to_cv_cam(T_gl[order])


def write_transforms_json(path: str | Path, intrinsics: Intrinsics, T_world_cam: NDArray) -> None:
    """Write key frames (in time order, OpenCV camera-to-world) as SAI's ``transforms.json`` does.

    Frame i (0-based, time order) is named ``./images/frame_{i+1:05d}.jpg``; frames with
    ``(i + 3) % 7 == 0`` are "val" and are listed after all "train" frames, as the tool does.
    """
    T_gl = gl_to_cv_cam(np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4))
    idx = np.arange(len(T_gl))
    is_val = (idx + 3) % 7 == 0
    order = np.concatenate([idx[~is_val], idx[is_val]])
    K = intrinsics
    frames = [{
        "file_path": f"./images/frame_{i + 1:05d}.jpg",
        "depth_file_path": f"./images/depth_{i + 1:05d}.png",
        "transform_matrix": T_gl[i].tolist(),
    } for i in order]
    write_json(path, {
        "fl_x": K.fx, "fl_y": K.fy, "cx": K.cx, "cy": K.cy, "w": K.width, "h": K.height,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "aabb_scale": 16, "orientation_override": "none",
        "auto_scale_poses_override": False, "ply_file_path": "./sparse_pc.ply", "frames": frames,
    })


# --------------------------------------------------------------------------- writer


class SpectacularWriter:
    """Writes a Spectacular AI-style recording plus its smoothed poses (used by tests and the studio).

    Args:
        out_dir: recording folder to create.
        rgb_intrinsics: intrinsics of the sensor (landscape) image given to :meth:`add_frame`.
        fps: video frame rate.
        portrait: store the video turned 90 degrees clockwise (a portrait recording whose
            calibration stays landscape), to exercise the reader's portrait handling.
        crf: H.264 quality.

    Confidence maps are not part of the format and are dropped.
    """

    def __init__(self, out_dir: str | Path, rgb_intrinsics: Intrinsics, fps: float,
                 portrait: bool = False, crf: int = 18) -> None:
        self.root = Path(out_dir)
        (self.root / "frames2").mkdir(parents=True, exist_ok=True)
        self.K = rgb_intrinsics
        self.fps = fps
        self.portrait = portrait
        w, h = (rgb_intrinsics.height, rgb_intrinsics.width) if portrait else (rgb_intrinsics.width, rgb_intrinsics.height)
        self._video = VideoWriter(self.root / "data.mov", fps, w, h, crf=crf)
        self._lines: list[tuple[float, str]] = []
        self._poses: list[str] = []
        self._depth_size: tuple[int, int] | None = None
        self._n = 0

    def add_frame(self, rgb: NDArray[np.uint8], depth_mm: NDArray[np.uint16], confidence: NDArray[np.uint8] | None,
                  T_world_cam: NDArray[np.float64], timestamp_s: float) -> None:
        """Append one frame (sensor orientation): RGB (H, W, 3) uint8, depth (h, w) uint16 mm,
        confidence (ignored), camera-to-world pose (4, 4) in the package convention, time (s)."""
        self._video.write(np.ascontiguousarray(np.rot90(rgb, -1)) if self.portrait else rgb)
        depth_mm = np.asarray(depth_mm)
        if depth_mm.dtype != np.uint16:
            raise ValueError(f"depth must be uint16 millimetres, got {depth_mm.dtype}")
        self._depth_size = (depth_mm.shape[1], depth_mm.shape[0])
        write_png(self.root / "frames2" / f"{self._n:08d}.png", depth_mm)
        t = float(timestamp_s)
        frame = {"frames": [{"cameraInd": 0, "time": t}, {"cameraInd": 1, "time": t, "aligned": True,
                                                           "depthScale": 0.001}],
                 "number": self._n, "time": t}
        self._lines.append((t, json.dumps(frame)))
        T = np.asarray(T_world_cam, dtype=np.float64)
        q = matrix_to_quat(T[:3, :3])
        self._poses.append(json.dumps({
            "time": t, "position": dict(zip("xyz", map(float, T[:3, 3]))),
            "orientation": {"w": float(q[3]), "x": float(q[0]), "y": float(q[1]), "z": float(q[2])},
        }))
        self._n += 1

    def add_imu(self, timestamps_s: NDArray, accel_mps2: NDArray, gyro_radps: NDArray) -> None:
        """Append IMU samples: times (N,), accelerometer (N, 3) m/s^2, gyroscope (N, 3) rad/s."""
        for t, a, g in zip(np.asarray(timestamps_s, float), np.asarray(accel_mps2, float), np.asarray(gyro_radps, float)):
            self._lines.append((float(t), json.dumps({"sensor": {"type": "accelerometer", "values": a.tolist()}, "time": float(t)})))
            self._lines.append((float(t), json.dumps({"sensor": {"type": "gyroscope", "values": g.tolist()}, "time": float(t)})))

    def close(self) -> None:
        """Finish the video and write data.jsonl, calibration.json, metadata.json, cameras_sai.jsonl."""
        self._video.close()
        self._lines.sort(key=lambda x: x[0])
        write_text(self.root / "data.jsonl", "".join(line + "\n" for _, line in self._lines))
        write_text(self.root / POSE_FILE, "".join(line + "\n" for line in self._poses))
        K = self.K
        cams = [{"focalLengthX": K.fx, "focalLengthY": K.fy, "principalPointX": K.cx, "principalPointY": K.cy,
                 "imageWidth": K.width, "imageHeight": K.height, "model": "pinhole",
                 "distortionCoefficients": [0.0, 0.0, 0.0], "imuToCamera": np.eye(4).tolist()}]
        if self._depth_size is not None:
            Kd = K.scaled(*self._depth_size)
            cams.append({"focalLengthX": Kd.fx, "focalLengthY": Kd.fy, "principalPointX": Kd.cx,
                         "principalPointY": Kd.cy, "imageWidth": Kd.width, "imageHeight": Kd.height,
                         "model": "pinhole", "depthScale": 0.001, "aligned": True})
        write_json(self.root / "calibration.json", {"cameras": cams})
        write_json(self.root / "metadata.json", {"platform": "ios", "device_model": "synthetic",
                                                 "software": "embodmocap"})

    def __enter__(self) -> "SpectacularWriter":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.close()
        else:
            self._video.abort()
