"""Stray Scanner captures (iOS app): read and write.

Folder layout (see docs/formats.md)::

    rgb.mp4                 RGB video (size and rate read from the file)
    depth/000000.png        uint16 depth in millimetres, LiDAR resolution (typically 256x192)
    confidence/000000.png   uint8 confidence 0/1/2 (optional folder)
    camera_matrix.csv       3x3 intrinsics of the RGB stream
    odometry.csv            timestamp, frame, x, y, z, qx, qy, qz, qw   (oldest apps: x..qw only;
                            newer apps add fx, fy, cx, cy, distortion_center_x, distortion_center_y:
                            per-frame intrinsics, the distortion fields empty)
    imu.csv                 timestamp, a_x, a_y, a_z, alpha_x, alpha_y, alpha_z (optional)

The odometry pose maps **OpenCV camera axes** into ARKit's **Y-up** world (the app multiplies
ARKit's camera rotation by a 180-degree turn about x before writing). It is converted once here:
``T_world_cam = T_zup_yup @ T_yup_cam``.

Intrinsics: the per-frame ``fx, fy, cx, cy`` of a 15-column ``odometry.csv`` when present (their
median over the capture: ARKit refines them by fractions of a pixel), else ``camera_matrix.csv``;
either is rescaled to the video's size when it was written for another one
(:func:`~embodmocap.io.captures.common.intrinsics_for_image`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.geometry.transforms import T_zup_from_yup, invert_T, make_T, matrix_to_quat, quat_to_matrix
from embodmocap.io.atomic import write_text
from embodmocap.io.captures.common import (
    CaptureScan, LazyFrames, LazyVideo, Problem, accel_to_mps2, capture_from_scan,
    depth_file_problems, intrinsics_for_image, intrinsics_problems, pose_problems, probe_app_video, write_png,
)
from embodmocap.io.video import VideoWriter
from embodmocap.types import Capture, CameraTrajectory, ImuSamples, Intrinsics

log = logging.getLogger(__name__)

FORMAT = "strayscanner"
POSE_COLUMNS = ("x", "y", "z", "qx", "qy", "qz", "qw")
INTRINSIC_COLUMNS = ("fx", "fy", "cx", "cy")
#: Per-frame intrinsics that differ from their median by more than this (relative) are reported:
#: ARKit refines them by fractions of a pixel, a larger spread means a change of camera or zoom.
INTRINSICS_SPREAD_REL = 0.02
#: What the app writes, for messages about a missing or truncated part.
APP_WRITES_DEPTH = "Stray Scanner writes one depth/NNNNNN.png (uint16 mm) per video frame"
IMU_COLUMNS = ("timestamp", "a_x", "a_y", "a_z", "alpha_x", "alpha_y", "alpha_z")


def is_strayscanner(path: Path) -> bool:
    """True if ``path`` looks like a Stray Scanner folder: rgb.mp4 with odometry.csv or depth/, or
    (an export missing its video, reported by the scan) odometry.csv with depth/ or camera_matrix.csv."""
    if not path.is_dir():
        return False
    odo, depth = (path / "odometry.csv").is_file(), (path / "depth").is_dir()
    if (path / "rgb.mp4").exists():
        return odo or depth
    return odo and (depth or (path / "camera_matrix.csv").is_file())


@dataclass(frozen=True)
class Odometry:
    """The parsed ``odometry.csv``.

    Attributes:
        timestamps_s: (N,) app clock in seconds, or None (oldest header-less files).
        frame_ids: (N,) video frame of each row.
        T_world_cam: (N, 4, 4) poses in the package convention (NaN rows where a pose is missing).
        intrinsics: (N, 4) per-frame fx, fy, cx, cy (NaN where empty), or None without those columns.
        columns: number of columns (7, 9 or 15 in the app versions known).
    """

    timestamps_s: NDArray[np.float64] | None
    frame_ids: NDArray[np.int64]
    T_world_cam: NDArray[np.float64]
    intrinsics: NDArray[np.float64] | None
    columns: int

    @property
    def variant(self) -> str:
        if self.intrinsics is not None:
            return f"Stray Scanner, {self.columns}-column odometry.csv with per-frame intrinsics (newer app)"
        if self.timestamps_s is None:
            return "Stray Scanner, header-less odometry.csv (oldest app)"
        return f"Stray Scanner, {self.columns}-column odometry.csv (older app)"


def read_strayscanner(path: str | Path) -> Capture:
    """Read a Stray Scanner folder into a :class:`Capture` (frames are read lazily).

    Raises:
        InputError: on the first problem found (missing or truncated file, bad rows, NaN or
            jumping poses, missing depth maps, ...), naming the file and what to do.
    """
    return capture_from_scan(scan_strayscanner(path))


def scan_strayscanner(path: str | Path, thorough: bool = False) -> CaptureScan:
    """Read everything but the frames, collecting every problem instead of stopping.

    ``thorough`` also reads the header of every depth/confidence PNG (slower) instead of the first.
    """
    root = Path(path)
    problems: list[Problem] = []
    if not root.is_dir():
        return CaptureScan(root, FORMAT, problems=(Problem(root, "capture folder not found"),))

    video = root / "rgb.mp4"
    info, problems = probe_app_video(video, "a Stray Scanner export holds its RGB video as rgb.mp4 beside "
                                            "odometry.csv and depth/",
                                     "copy the whole folder the app exported, rgb.mp4 included")
    num_frames = info.num_frames if info else 0
    fps = info.fps if info else 0.0

    trajectory = None
    variant = "Stray Scanner"
    odometry = None
    timestamps = info.timestamps_s if info else np.zeros(0)
    odo = root / "odometry.csv"
    try:
        odometry = read_odometry(odo)
        variant = odometry.variant
        t_odo, frames, T = odometry.timestamps_s, odometry.frame_ids, odometry.T_world_cam
        problems += pose_problems(odo, T, fps, num_frames)
        keep = frames < num_frames if num_frames else np.ones(len(frames), bool)
        if t_odo is None:
            t_odo = timestamps[frames[keep]] if num_frames else frames[keep] / 30.0
        else:
            t_odo = t_odo[keep]
            if num_frames and np.array_equal(np.sort(frames[keep]), np.arange(num_frames)):
                # The app's clock (shared with imu.csv) is better than the video's own pts.
                timestamps = np.empty(num_frames)
                timestamps[frames[keep]] = t_odo
        trajectory = CameraTrajectory(t_odo, frames[keep], T[keep])
    except InputError as err:
        problems.append(Problem(odo, err.problem, err.fix))

    K, k_note, k_problems = _intrinsics(root, info, odometry)
    problems += k_problems
    if k_note:
        variant += f"; {k_note}"

    depth_paths = [root / "depth" / f"{i:06d}.png" for i in range(num_frames)]
    if not (root / "depth").is_dir() and num_frames:
        problems.append(Problem(root / "depth", f"missing: {APP_WRITES_DEPTH}",
                                "copy the whole folder the app exported, depth/ included"))
        depth_size = None
    else:
        dprob, depth_size = depth_file_problems(depth_paths, None, "uint16", thorough, APP_WRITES_DEPTH)
        problems += dprob
    has_conf = (root / "confidence").is_dir()
    if has_conf:
        conf_paths = [root / "confidence" / f"{i:06d}.png" for i in range(num_frames)]
        cprob, _ = depth_file_problems(conf_paths, depth_size, "uint8", thorough,
                                       "Stray Scanner writes one confidence/NNNNNN.png per depth map")
        problems += cprob

    imu = ImuSamples.empty()
    if (root / "imu.csv").exists():
        try:
            imu = read_imu_csv(root / "imu.csv")
        except InputError as err:
            problems.append(Problem(root / "imu.csv", err.problem, err.fix))

    def make_frames() -> LazyFrames:
        return LazyFrames(
            num_frames, LazyVideo(video), lambda i: root / "depth" / f"{i:06d}.png",
            (lambda i: root / "confidence" / f"{i:06d}.png") if has_conf else None, depth_size,
        )

    return CaptureScan(
        path=root, format=FORMAT, variant=variant, num_frames=num_frames, fps=fps, rgb_intrinsics=K,
        depth_size=depth_size, timestamps_s=timestamps, trajectory=trajectory, imu=imu,
        make_frames=make_frames, problems=tuple(problems),
    )


def _intrinsics(root: Path, info, odometry: Odometry | None) -> tuple[Intrinsics | None, str, list[Problem]]:
    """(video intrinsics, a note on where they came from, problems): the per-frame intrinsics of
    ``odometry.csv`` when it has them (their median), else ``camera_matrix.csv``; rescaled when
    written for another size than the video's."""
    problems: list[Problem] = []
    per_frame = None
    if odometry is not None and odometry.intrinsics is not None:
        ok = np.all(np.isfinite(odometry.intrinsics), axis=1)
        if ok.any():
            per_frame = odometry.intrinsics[ok]
    K3, source = None, root / "camera_matrix.csv"
    if per_frame is not None:
        fx, fy, cx, cy = np.median(per_frame, axis=0)
        K3, source = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), root / "odometry.csv"
        spread = np.abs(per_frame / np.array([fx, fy, cx, cy]) - 1).max()
        if spread > INTRINSICS_SPREAD_REL:
            log.warning("%s: per-frame intrinsics vary by up to %.1f %% of their median; using the median",
                        source, 100 * spread)
    try:
        K_file = read_camera_matrix(root / "camera_matrix.csv")
        K3 = K_file if K3 is None else K3
    except InputError as err:
        if K3 is None:
            problems.append(Problem(root / "camera_matrix.csv", err.problem, err.fix))
    if K3 is None or info is None:
        return None, "", problems
    K, other = intrinsics_for_image(K3, info.width, info.height)
    note = f"intrinsics ({source.name}) for {other[0]}x{other[1]}, rescaled to the {info.width}x{info.height} video" \
        if other else ""
    if other:
        log.info("%s: %s", root, note)
    problems += intrinsics_problems(source, K)
    return K, note, problems


# --------------------------------------------------------------------------- file parsers


def read_camera_matrix(path: Path) -> NDArray[np.float64]:
    """The 3x3 K of ``camera_matrix.csv`` (three comma-separated rows)."""
    if not path.is_file():
        raise InputError(path, "camera_matrix.csv not found", "export the capture again with intrinsics")
    try:
        K = np.loadtxt(path, delimiter=",", ndmin=2)
    except ValueError as err:
        raise InputError(path, f"malformed intrinsics ({err})", "expected three rows of three numbers") from err
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or abs(K[2, 2] - 1) > 1e-6:
        raise InputError(path, f"expected a 3x3 matrix with K[2,2] = 1, got shape {K.shape}",
                         "expected three rows of three numbers")
    return K


def _split_header(path: Path) -> tuple[list[str] | None, list[str]]:
    """(column names or None when the file has no header, data lines)."""
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    if not lines:
        raise InputError(path, "file is empty", "export the capture again")
    first = lines[0].split(",")[0].strip()
    try:
        float(first)
        return None, lines
    except ValueError:
        return [c.strip() for c in lines[0].split(",")], lines[1:]


def _parse_rows(path: Path, lines: list[str], ncols: int, optional: tuple[int, ...] = ()) -> NDArray[np.float64]:
    """Float rows of a CSV body; a wrong column count or non-number names the line.

    Fields may carry spaces. An empty field is NaN in the ``optional`` columns (the newer app
    leaves its distortion columns empty in every row) and an error elsewhere.
    """
    rows = [[c.strip() for c in ln.split(",")] for ln in lines]
    counts = np.array([len(r) for r in rows])
    bad = np.nonzero(counts != ncols)[0]
    if len(bad):
        raise InputError(path, f"row {bad[0] + 1} of the data has {counts[bad[0]]} columns, expected {ncols}",
                         "the file is truncated or edited; export the capture again")
    for j in optional:
        for r in rows:
            if r[j] == "":
                r[j] = "nan"
    try:
        return np.array(rows, dtype=np.float64).reshape(-1, ncols)
    except ValueError as err:
        row = next(i for i, r in enumerate(rows) if not all(_is_number(c) for c in r))
        raise InputError(path, f"non-numeric value in row {row + 1} of the data ({err})",
                         "the file is truncated or edited; export the capture again") from err


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def read_odometry(path: Path) -> Odometry:
    """Parse ``odometry.csv`` into an :class:`Odometry`.

    Accepts every form the app has written: the headered form (any column order, spaces after
    commas, zero-padded frame numbers), with or without the newer per-frame ``fx, fy, cx, cy,
    distortion_center_x, distortion_center_y`` columns (any column other than time, frame and pose
    may be empty), and the oldest header-less ``x, y, z, qx, qy, qz, qw`` form (frame = row
    number, no time). Poses come out in the package convention (Z-up world, OpenCV camera axes).
    """
    if not path.is_file():
        raise InputError(path, "odometry.csv not found", "export the capture again with poses")
    header, lines = _split_header(path)
    if header is None:
        header = list(POSE_COLUMNS)
    missing = [c for c in POSE_COLUMNS if c not in header]
    if missing:
        raise InputError(path, f"header lacks columns {missing} (has {header})",
                         "expected 'timestamp, frame, x, y, z, qx, qy, qz, qw'")
    required = set(POSE_COLUMNS) | {"timestamp", "frame"}
    data = _parse_rows(path, lines, len(header), tuple(i for i, c in enumerate(header) if c not in required))
    col = {name: data[:, i] for i, name in enumerate(header)}
    frames = col["frame"].astype(np.int64) if "frame" in col else np.arange(len(data), dtype=np.int64)
    intr = np.stack([col[c] for c in INTRINSIC_COLUMNS], axis=1) if all(c in col for c in INTRINSIC_COLUMNS) else None
    t = col.get("timestamp")
    xyz = np.stack([col["x"], col["y"], col["z"]], axis=1)
    quat = np.stack([col["qx"], col["qy"], col["qz"], col["qw"]], axis=1)
    # NaN or zero rows give NaN poses (pose checks report them).
    R = quat_to_matrix(quat, invalid="nan")
    T_yup_cam = make_T(R, xyz)
    return Odometry(t, frames, T_zup_from_yup() @ T_yup_cam, intr, len(header))


def read_imu_csv(path: Path) -> ImuSamples:
    """Parse ``imu.csv``; accelerometer converted to m/s^2 whatever unit the app used."""
    header, lines = _split_header(path)
    header = header or list(IMU_COLUMNS)
    missing = [c for c in IMU_COLUMNS if c not in header]
    if missing:
        raise InputError(path, f"header lacks columns {missing}", f"expected {', '.join(IMU_COLUMNS)}")
    if not lines:
        return ImuSamples.empty()
    data = _parse_rows(path, lines, len(header))
    c = {name: data[:, i] for i, name in enumerate(header)}
    accel = np.stack([c["a_x"], c["a_y"], c["a_z"]], axis=1)
    gyro = np.stack([c["alpha_x"], c["alpha_y"], c["alpha_z"]], axis=1)
    return ImuSamples(c["timestamp"], accel_to_mps2(accel, path), gyro)


# --------------------------------------------------------------------------- writer


class StrayScannerWriter:
    """Writes a capture the way the Stray Scanner app does (used by the synthetic studio).

    Frames stream to ``rgb.mp4`` and ``depth/``; the CSVs are written on :meth:`close`. Poses are
    given in the package convention and converted back to the app's, so reading the folder gives
    the same poses again.

    Args:
        out_dir: capture folder to create.
        rgb_intrinsics: intrinsics of the RGB frames (their size is the video size).
        fps: video frame rate.
        header: write the modern headered ``odometry.csv`` (False: the oldest header-less form).
        crf: H.264 quality (lower = better, 18 is visually lossless).
    """

    def __init__(self, out_dir: str | Path, rgb_intrinsics: Intrinsics, fps: float,
                 header: bool = True, crf: int = 18) -> None:
        self.root = Path(out_dir)
        (self.root / "depth").mkdir(parents=True, exist_ok=True)
        self.K = rgb_intrinsics
        self.fps = fps
        self.header = header
        self._video = VideoWriter(self.root / "rgb.mp4", fps, rgb_intrinsics.width, rgb_intrinsics.height, crf=crf)
        self._rows: list[NDArray[np.float64]] = []
        self._imu: list[tuple[NDArray, NDArray, NDArray]] = []
        self._n = 0

    def add_frame(self, rgb: NDArray[np.uint8], depth_mm: NDArray[np.uint16], confidence: NDArray[np.uint8] | None,
                  T_world_cam: NDArray[np.float64], timestamp_s: float) -> None:
        """Append one frame: RGB (H, W, 3) uint8, depth (h, w) uint16 mm, confidence (h, w) uint8
        or None, camera-to-world pose (4, 4) in the package convention, time in seconds."""
        if np.asarray(depth_mm).dtype != np.uint16:
            raise ValueError(f"depth must be uint16 millimetres, got {np.asarray(depth_mm).dtype}")
        self._video.write(rgb)
        write_png(self.root / "depth" / f"{self._n:06d}.png", depth_mm)
        if confidence is not None:
            write_png(self.root / "confidence" / f"{self._n:06d}.png", np.asarray(confidence, dtype=np.uint8))
        T_yup_cam = invert_T(T_zup_from_yup()) @ np.asarray(T_world_cam, dtype=np.float64)
        q = matrix_to_quat(T_yup_cam[:3, :3])
        self._rows.append(np.concatenate([[timestamp_s, self._n], T_yup_cam[:3, 3], q]))
        self._n += 1

    def add_imu(self, timestamps_s: NDArray, accel_mps2: NDArray, gyro_radps: NDArray) -> None:
        """Append IMU samples: times (N,), accelerometer (N, 3) m/s^2, gyroscope (N, 3) rad/s."""
        self._imu.append((np.asarray(timestamps_s, float).reshape(-1), np.asarray(accel_mps2, float).reshape(-1, 3),
                          np.asarray(gyro_radps, float).reshape(-1, 3)))

    def close(self) -> None:
        """Finish the video and write the CSVs."""
        self._video.close()
        K = self.K.K
        write_text(self.root / "camera_matrix.csv", "".join(f"{r[0]:.10g},{r[1]:.10g},{r[2]:.10g}\n" for r in K))
        rows = np.array(self._rows).reshape(-1, 9)
        if self.header:
            body = "".join(f"{r[0]:.6f}, {int(r[1]):06d}, " + ", ".join(f"{v:.10f}" for v in r[2:]) + "\n" for r in rows)
            write_text(self.root / "odometry.csv", "timestamp, frame, x, y, z, qx, qy, qz, qw\n" + body)
        else:
            write_text(self.root / "odometry.csv", "".join(", ".join(f"{v:.10f}" for v in r[2:]) + "\n" for r in rows))
        if self._imu:
            t = np.concatenate([x[0] for x in self._imu])
            a = np.concatenate([x[1] for x in self._imu])
            g = np.concatenate([x[2] for x in self._imu])
            body = "".join(", ".join(f"{v:.9f}" for v in row) + "\n" for row in np.column_stack([t, a, g]))
            write_text(self.root / "imu.csv", ", ".join(IMU_COLUMNS) + "\n" + body)

    def __enter__(self) -> "StrayScannerWriter":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.close()
        else:
            self._video.abort()
