"""Pieces every capture reader shares: depth images, problem lists, pose checks, lazy frames.

Each format module *scans* a capture into a :class:`CaptureScan` that records every problem it
finds (so ``embodmocap inspect`` can list them all at once); its ``read_*`` function then raises the
first problem as one :class:`~embodmocap.errors.InputError`, or builds the
:class:`~embodmocap.types.Capture`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.geometry.transforms import is_rigid, rotation_angle
from embodmocap.io.atomic import atomic_path
from embodmocap.types import Capture, CameraTrajectory, FrameSource, ImuSamples, Intrinsics

log = logging.getLogger(__name__)

#: Standard gravity, m/s^2 (accelerometers that report in g are scaled by it).
GRAVITY = 9.80665
#: A camera step larger than this between consecutive frames at 30 fps is a pose jump.
JUMP_M_AT_30FPS = 0.5
#: A camera rotation larger than this (degrees) between consecutive frames at 30 fps is a jump.
JUMP_DEG_AT_30FPS = 30.0


# --------------------------------------------------------------------------- problems


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a capture: the file, what is wrong, and what to do about it."""

    path: Path
    problem: str
    fix: str = ""

    def error(self) -> InputError:
        return InputError(self.path, self.problem, self.fix)

    def __str__(self) -> str:
        return str(self.error())


@dataclass(frozen=True)
class CaptureScan:
    """Everything a reader learnt about a capture, problems included.

    Fields are ``None`` where the file they come from could not be read.

    Attributes:
        path: the capture folder (or file).
        format: ``"strayscanner"``, ``"spectacular"`` or ``"record3d"``.
        variant: which version of the app's export was recognised, in words (e.g. "Stray Scanner,
            15-column odometry.csv with per-frame intrinsics"), for ``inspect`` and the logs.
        num_frames: RGB frames (video frames or images); 0 if unknown.
        fps: nominal frame rate; 0 if unknown.
        rgb_intrinsics: intrinsics at the RGB size the frames are returned in.
        depth_size: (width, height) of the depth maps as returned.
        timestamps_s: (num_frames,) per-frame time in seconds (empty if unknown).
        trajectory: poses in the package convention (Z-up world, OpenCV camera), or None.
        imu: IMU samples (possibly empty).
        make_frames: builds the lazy frame source (only called when there is no problem).
        problems: everything found wrong, in the order found; the first one is what a reader raises.
    """

    path: Path
    format: str
    variant: str = ""
    num_frames: int = 0
    fps: float = 0.0
    rgb_intrinsics: Intrinsics | None = None
    depth_size: tuple[int, int] | None = None
    timestamps_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    trajectory: CameraTrajectory | None = None
    imu: ImuSamples = field(default_factory=ImuSamples.empty)
    make_frames: Callable[[], FrameSource] | None = None
    problems: tuple[Problem, ...] = ()


def capture_from_scan(scan: CaptureScan) -> Capture:
    """The :class:`Capture` of a clean scan; raises the scan's first problem otherwise."""
    if scan.problems:
        for extra in scan.problems[1:]:
            log.debug("also wrong: %s", extra)
        raise scan.problems[0].error()
    assert scan.rgb_intrinsics is not None and scan.depth_size is not None and scan.trajectory is not None
    assert scan.make_frames is not None
    return Capture(
        path=scan.path, format=scan.format, num_frames=scan.num_frames, fps=scan.fps,
        rgb_intrinsics=scan.rgb_intrinsics,
        depth_intrinsics=scan.rgb_intrinsics.scaled(*scan.depth_size),
        trajectory=scan.trajectory, frames=scan.make_frames(), imu=scan.imu,
        timestamps_s=scan.timestamps_s,
    )


# --------------------------------------------------------------------------- depth images


def read_depth_image(path: str | Path) -> NDArray[np.float32]:
    """Read one depth map as (h, w) float32 metres, 0 where invalid.

    Accepts uint16 PNG in millimetres (Stray Scanner, Spectacular AI ``frames2/``) and float32
    TIFF in metres (iPhone depth apps). Non-finite and negative values become 0.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "depth image not found", "check the capture folder is complete")
    if path.suffix.lower() in (".tif", ".tiff"):
        import tifffile

        try:
            d = tifffile.imread(path)
        except Exception as err:  # noqa: BLE001 - tifffile raises many kinds on bad files
            raise InputError(path, f"unreadable TIFF ({err})", "copy the file again") from err
        if d.ndim == 3 and d.shape[-1] == 1:
            d = d[..., 0]
        if d.ndim != 2 or not np.issubdtype(d.dtype, np.floating):
            raise InputError(path, f"depth TIFF must be one float channel in metres, got {d.shape} {d.dtype}")
        d = d.astype(np.float32)
    else:
        d = _png_millimetres(path)
        d = d.astype(np.float32) / 1000.0
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d


def read_depth_png_mm(path: str | Path) -> NDArray[np.uint16] | None:
    """One depth map as stored, (h, w) uint16 millimetres (0 = invalid), when it is a PNG; None for
    a TIFF (float metres). The same numbers as :func:`read_depth_image` (metres x 1000, rounded),
    without the float round trip."""
    path = Path(path)
    if path.suffix.lower() in (".tif", ".tiff"):
        return None
    if not path.is_file():
        raise InputError(path, "depth image not found", "check the capture folder is complete")
    return _png_millimetres(path)


def _png_millimetres(path: Path) -> NDArray[np.uint16]:
    d = read_png(path)
    if d.ndim != 2 or d.dtype != np.uint16:
        raise InputError(path, f"depth PNG must be single-channel uint16 millimetres, got {d.shape} {d.dtype}",
                         "write depth as 16-bit PNG in mm")
    return d


def read_png(path: Path) -> NDArray:
    """Read a PNG unchanged (bit depth and channels as stored)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(path, "unreadable or missing image", "check the capture folder is complete")
    return img


def write_png(path: Path, img: NDArray) -> None:
    """Write a uint8/uint16 single-channel PNG atomically."""
    import cv2

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(img)):
            raise OSError(f"{path}: could not write PNG")


def png_size_and_dtype(path: Path) -> tuple[tuple[int, int], str]:
    """((width, height), dtype name) of a PNG from its header, without decoding the pixels."""
    from PIL import Image

    with Image.open(path) as im:
        dtype = {"I;16": "uint16", "I;16B": "uint16", "I;16L": "uint16", "I": "int32", "L": "uint8",
                 "P": "uint8", "1": "bool"}.get(im.mode, f"{im.mode} (multi-channel)")
        return im.size, dtype


def depth_to_rgb_scale(rgb_size: tuple[int, int], depth_size: tuple[int, int]) -> tuple[float, float]:
    """(sx, sy): how many RGB pixels one depth pixel spans, per axis; sizes are (width, height).

    The usual iPhone pair 1920x1440 / 256x192 gives (7.5, 7.5).
    """
    return rgb_size[0] / depth_size[0], rgb_size[1] / depth_size[1]


def depth_file_problems(paths: Sequence[Path], size: tuple[int, int] | None, dtype: str,
                        thorough: bool, app_writes: str = "") -> tuple[list[Problem], tuple[int, int] | None]:
    """Missing, mis-sized or wrongly typed depth/confidence PNGs.

    Checks that every file exists; reads the header of the first one (or of all with
    ``thorough``). ``app_writes`` says what the app should have written (e.g. "Stray Scanner
    writes one depth/NNNNNN.png per video frame"), for the message about missing files. Returns
    the problems and the (width, height) of the first readable file.
    """
    problems: list[Problem] = []
    exists = np.array([p.is_file() for p in paths], dtype=bool)
    missing = np.nonzero(~exists)[0]
    if len(missing):
        first = paths[missing[0]]
        what = f"; {app_writes}" if app_writes else ""
        problems.append(Problem(first, f"missing ({len(missing)} of {len(paths)} files missing in "
                                       f"{first.parent.name}/, first at frame {missing[0]}{what})",
                                "copy the complete capture folder from the phone"))
    found = [p for p, e in zip(paths, exists) if e]
    for p in found if thorough else found[:1]:
        try:
            got_size, got_dtype = png_size_and_dtype(p)
        except Exception as err:  # noqa: BLE001 - PIL raises many kinds on bad files
            problems.append(Problem(p, f"unreadable image ({err})", "copy the file again"))
            continue
        if size is None:
            size = got_size
        if got_dtype != dtype:
            problems.append(Problem(p, f"expected {dtype} PNG, found {got_dtype}",
                                    "depth must be 16-bit mm, confidence 8-bit"))
        elif got_size != size:
            problems.append(Problem(p, f"image is {got_size[0]}x{got_size[1]}, others are {size[0]}x{size[1]}",
                                    "all depth maps of a capture must share one size"))
    return problems, size


# --------------------------------------------------------------------------- poses


def pose_problems(path: Path, T_world_cam: NDArray, fps: float, num_frames: int) -> list[Problem]:
    """Too few, non-finite, non-rigid or jumping poses (consecutive rows, thresholds scaled by fps).

    A jump is a step larger than :data:`JUMP_M_AT_30FPS` metres or :data:`JUMP_DEG_AT_30FPS`
    degrees between consecutive poses at 30 fps (scaled by 30/fps for other rates).
    """
    problems = []
    T = np.asarray(T_world_cam, dtype=np.float64).reshape(-1, 4, 4)
    if num_frames and len(T) < num_frames:
        problems.append(Problem(path, f"only {len(T)} poses for {num_frames} frames",
                                "the pose file is truncated; export the capture again"))
    finite = np.all(np.isfinite(T), axis=(1, 2))
    if not finite.all():
        bad = np.nonzero(~finite)[0]
        problems.append(Problem(path, f"{len(bad)} poses are NaN/inf (first at row {bad[0]})",
                                "the tracker lost the camera; re-record or trim the capture"))
    rigid = is_rigid(T, atol=1e-3)
    if (finite & ~rigid).any():
        bad = np.nonzero(finite & ~rigid)[0]
        problems.append(Problem(path, f"{len(bad)} poses are not rotations (first at row {bad[0]})",
                                "check the quaternion columns"))
    steps = jump_steps(T, fps)
    if len(steps):
        i, dist, ang = steps[0]
        problems.append(Problem(path, f"{len(steps)} pose jumps (first between rows {i} and {i + 1}: "
                                      f"{dist:.2f} m, {ang:.0f} deg)",
                                "tracking relocalised; re-record or trim the capture"))
    return problems


def jump_steps(T: NDArray, fps: float) -> list[tuple[int, float, float]]:
    """(row, step metres, step degrees) of every consecutive-pose jump among finite poses."""
    if len(T) < 2:
        return []
    scale = 30.0 / fps if fps > 0 else 1.0
    dist = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)
    R_rel = np.swapaxes(T[:-1, :3, :3], -1, -2) @ T[1:, :3, :3]
    ang = np.degrees(rotation_angle(np.nan_to_num(R_rel)))
    with np.errstate(invalid="ignore"):
        jump = (dist > JUMP_M_AT_30FPS * scale) | (ang > JUMP_DEG_AT_30FPS * scale)
    rows = np.nonzero(jump & np.isfinite(dist))[0]
    return [(int(i), float(dist[i]), float(ang[i])) for i in rows]


def accel_to_mps2(accel: NDArray, path: Path) -> NDArray[np.float64]:
    """Accelerometer samples (N, 3) in m/s^2, whether the app wrote g or m/s^2.

    At rest the magnitude is gravity, so the median norm tells the unit: ~1 means g, ~9.8 m/s^2.
    """
    accel = np.asarray(accel, dtype=np.float64).reshape(-1, 3)
    if len(accel) == 0:
        return accel
    m = float(np.median(np.linalg.norm(accel, axis=1)))
    if 0.5 < m < 2.0:
        log.debug("%s: accelerometer in g (median |a| = %.2f), converting to m/s^2", path, m)
        return accel * GRAVITY
    if not 5.0 < m < 15.0:
        log.warning("%s: accelerometer median magnitude %.2f is neither ~1 g nor ~9.8 m/s^2; "
                    "keeping it as m/s^2", path, m)
    return accel


# --------------------------------------------------------------------------- lazy frames


class LazyFrames:
    """A :class:`~embodmocap.types.FrameSource` reading RGB through a callable and depth from files.

    Attributes:
        num_frames: number of frames.
        read_rgb: index -> (H, W, 3) uint8 RGB.
        depth_path: index -> path of that frame's depth image (any :func:`read_depth_image` format)
        conf_path: index -> path of a uint8 confidence PNG, or None when the capture has none.
        depth_size: expected (width, height) of depth maps, checked on every read.
        rot90: quarter turns (``np.rot90`` sense, counter-clockwise) applied to depth and
            confidence so they match the RGB orientation (portrait recordings).
    """

    def __init__(self, num_frames: int, read_rgb: Callable[[int], NDArray[np.uint8]],
                 depth_path: Callable[[int], Path], conf_path: Callable[[int], Path] | None,
                 depth_size: tuple[int, int], rot90: int = 0,
                 read_depth: Callable[[int], NDArray[np.float32]] | None = None,
                 read_conf: Callable[[int], NDArray[np.uint8]] | None = None) -> None:
        self.num_frames = num_frames
        self._read_rgb = read_rgb
        self._depth_path = depth_path
        self._conf_path = conf_path
        self._depth_size = depth_size
        self._rot90 = rot90
        self._stored_mm = read_depth is None  # depth files read by read_depth_image (PNG in mm or TIFF)
        self._read_depth = read_depth or (lambda i: read_depth_image(self._depth_path(i)))
        self._read_conf = read_conf or (None if conf_path is None else self._conf_from_png)

    def __len__(self) -> int:
        return self.num_frames

    def _check(self, i: int) -> None:
        if not 0 <= i < self.num_frames:
            raise IndexError(f"frame {i} outside 0..{self.num_frames - 1}")

    def rgb(self, index: int) -> NDArray[np.uint8]:
        self._check(index)
        return self._read_rgb(index)

    def depth_m(self, index: int) -> NDArray[np.float32]:
        self._check(index)
        return self._oriented(index, self._read_depth(index))

    def depth_mm(self, index: int) -> NDArray[np.uint16] | None:
        """(h, w) uint16 depth in millimetres of frame ``index`` as the capture stores it (a 16-bit
        PNG), or None when it stores depth otherwise (float metres). Equal to
        :func:`embodmocap.io.frame_stack.depth_mm` of :meth:`depth_m`, read without converting to
        metres and back (Stage II's depth stack is millimetres)."""
        self._check(index)
        if not self._stored_mm:
            return None
        d = read_depth_png_mm(self._depth_path(index))
        return None if d is None else self._oriented(index, d)

    def _oriented(self, index: int, d: NDArray) -> NDArray:
        """A depth map read for frame ``index``, its size checked, turned to the RGB orientation."""
        w, h = self._depth_size
        if d.shape != (h, w):
            raise InputError(self._depth_path(index), f"depth map is {d.shape[1]}x{d.shape[0]}, expected {w}x{h}",
                             "all depth maps of a capture must share one size")
        return np.ascontiguousarray(np.rot90(d, self._rot90)) if self._rot90 else d

    def confidence(self, index: int) -> NDArray[np.uint8] | None:
        self._check(index)
        if self._read_conf is None:
            return None
        c = self._read_conf(index)
        if c is None:
            return None
        return np.ascontiguousarray(np.rot90(c, self._rot90)) if self._rot90 else c

    def _conf_from_png(self, i: int) -> NDArray[np.uint8] | None:
        p = self._conf_path(i)
        if not p.is_file():
            return None
        c = read_png(p)
        if c.dtype != np.uint8 or c.ndim != 2:
            raise InputError(p, f"confidence must be single-channel uint8, got {c.shape} {c.dtype}")
        return c


def quarter_turns_for(video_size: tuple[int, int], calib_size: tuple[int, int], rotation_deg: int) -> int | None:
    """How the stored video relates to the calibrated sensor image, in CCW quarter turns.

    Returns 0 when the video frames have the calibration's orientation (same aspect), the number
    of counter-clockwise quarter turns (``np.rot90`` k) that takes a sensor image to a video frame
    when width and height are swapped, or None when the sizes do not match either way. The turn
    direction of a swapped video comes from its display rotation (-90 = clockwise, the iPhone
    portrait case) and defaults to clockwise (k = -1 = 3), the official pipeline's ``transpose=1``.
    """
    vw, vh = video_size
    cw, ch = calib_size
    same = abs(vw / vh - cw / ch) < 1e-3
    swapped = abs(vw / vh - ch / cw) < 1e-3
    if same and not (swapped and rotation_deg % 180):
        return 0
    if swapped:
        return 1 if rotation_deg % 360 == 90 else 3
    return None


def rotate_intrinsics(K: Intrinsics, k: int) -> Intrinsics:
    """Intrinsics of the image turned by ``k`` counter-clockwise quarter turns (``np.rot90`` sense).

    One counter-clockwise turn maps pixel (u, v) of a W x H image to (v, W-1-u).
    """
    k %= 4
    for _ in range(k):
        K = Intrinsics(K.fy, K.fx, K.cy, K.width - 1 - K.cx, K.height, K.width)
    return K


def rotate_camera_poses(T_world_cam: NDArray, k: int) -> NDArray[np.float64]:
    """Camera-to-world poses of the same camera whose image is turned ``k`` CCW quarter turns.

    A CCW turn maps pixel (u, v) to (v, W-1-u): the new camera x axis (increasing u') is the old
    +y and the new y axis is the old -x, i.e. the camera frame turns about its optical axis by
    +90 degrees (``R @ Rz(+90 deg)`` per turn). The camera centre does not move.
    """
    from embodmocap.geometry.transforms import rot_z

    T = np.array(T_world_cam, dtype=np.float64, copy=True)
    T[..., :3, :3] = T[..., :3, :3] @ rot_z(np.pi / 2 * (k % 4))
    return T


def probe_app_video(video: Path, missing: str, fix: str):
    """(the video's :class:`~embodmocap.io.video.VideoInfo` or None, problems): a missing video is
    one problem saying what the app writes (``missing``) and what to do (``fix``)."""
    from embodmocap.io.video import probe_video

    if not video.is_file():
        return None, [Problem(video, f"missing: {missing}", fix)]
    try:
        return probe_video(video), []
    except InputError as err:
        return None, [Problem(video, err.problem, err.fix)]


class LazyVideo:
    """Opens a :class:`~embodmocap.io.video.VideoReader` on first use (a Capture holds no decoder
    until a frame is read); ``rot90`` turns every frame by that many CCW quarter turns."""

    def __init__(self, path: Path, rot90: int = 0) -> None:
        self.path = path
        self.rot90 = rot90 % 4
        self._reader = None

    def __call__(self, index: int) -> NDArray[np.uint8]:
        from embodmocap.io.video import VideoReader

        if self._reader is None:
            self._reader = VideoReader(self.path)
        rgb = self._reader.read(index)
        return np.ascontiguousarray(np.rot90(rgb, self.rot90)) if self.rot90 else rgb

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None


def intrinsics_problems(path: Path, K: Intrinsics) -> list[Problem]:
    """Intrinsics whose principal point lies far from the image centre of the size they claim.

    Phones put the principal point within a few percent of the centre; a point outside the middle
    half means the matrix belongs to another resolution or orientation.
    """
    off_x = abs(K.cx - (K.width - 1) / 2) / K.width
    off_y = abs(K.cy - (K.height - 1) / 2) / K.height
    if off_x > 0.25 or off_y > 0.25 or K.fx <= 0 or K.fy <= 0:
        return [Problem(path, f"intrinsics (fx {K.fx:.1f}, fy {K.fy:.1f}, cx {K.cx:.1f}, cy {K.cy:.1f}) "
                              f"do not fit the {K.width}x{K.height} video",
                        "the matrix is for another resolution or orientation; export it again")]
    return []


#: Image widths (4:3 sensor modes, landscape) that iPhone apps write intrinsics for; a matrix whose
#: principal point sits at the centre of one of these sizes (or its portrait turn) is taken to be
#: for that size.
KNOWN_WIDTHS_4_3 = (192, 256, 320, 480, 640, 720, 960, 1280, 1440, 1920, 2560, 2880, 3840, 4032, 4224)
#: Scale factors between the frames and the size an app wrote intrinsics for, tried besides
#: :data:`KNOWN_WIDTHS_4_3` (a video downscaled or a matrix kept at the sensor's full size).
SIMPLE_SCALES = (1 / 4, 1 / 3, 1 / 2, 2 / 3, 3 / 4, 4 / 3, 3 / 2, 2, 3, 4)
#: How far (relative) a principal point may sit from a candidate size's centre and still match it.
CENTRE_MATCH_REL = 0.06


def intrinsics_for_image(K3: NDArray, width: int, height: int) -> tuple[Intrinsics, tuple[int, int] | None]:
    """``K3`` as :class:`Intrinsics` of a ``width`` x ``height`` image, rescaled when it was given for
    another size of the same aspect.

    Apps write one intrinsic matrix, not always for the size of the stored frames (e.g. a
    960x720 matrix beside a 1920x1440 video). The principal point of a phone camera sits within a
    few percent of the image centre, so the size a matrix is for is found by the centre: among the
    frame size and the known 4:3 sizes of the frame's orientation, the one whose centre is
    nearest (relative) to (cx, cy), within :data:`CENTRE_MATCH_REL` (with :data:`SIMPLE_SCALES` of
    the frame size as further candidates). Returns (intrinsics at
    width x height, the other size it was rescaled from or None).
    """
    K3 = np.asarray(K3, dtype=np.float64).reshape(3, 3)
    own = Intrinsics.from_K(K3, width, height)
    portrait = height > width
    sizes = {(width, height)}
    if abs(width / height - (3 / 4 if portrait else 4 / 3)) < 1e-3:
        sizes |= {((w * 3 // 4, w) if portrait else (w, w * 3 // 4)) for w in KNOWN_WIDTHS_4_3}
    sizes |= {(round(width * f), round(height * f)) for f in SIMPLE_SCALES
              if abs(width * f - round(width * f)) < 1e-6 and abs(height * f - round(height * f)) < 1e-6}

    def off(size: tuple[int, int]) -> float:
        return max(abs(K3[0, 2] + 0.5 - size[0] / 2) / size[0], abs(K3[1, 2] + 0.5 - size[1] / 2) / size[1])

    best = min(sorted(sizes), key=off)
    if off((width, height)) <= CENTRE_MATCH_REL or best == (width, height) or off(best) > CENTRE_MATCH_REL or off(best) >= off((width, height)):
        return own, None
    return Intrinsics.from_K(K3, *best).scaled(width, height), best
