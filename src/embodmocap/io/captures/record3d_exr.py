"""Record3D's "EXR + JPG" export: a folder of numbered images beside the app's metadata.

Layout (see docs/formats.md)::

    metadata.json   the same JSON as a .r3d's metadata (K, w, h, dw, dh, fps, poses,
                    frameTimestamps, cameraType, ...), see :mod:`embodmocap.io.captures.record3d`
    rgb/N.jpg       RGB frame N (e.g. 1440x1920), N = 0, 1, ... with gaps where the app dropped frames
    depth/N.exr     float depth in metres (e.g. 192x256), one per rgb/N.jpg

The frames present become the capture's frames 0..n-1 in order of N. ``poses`` and
``frameTimestamps`` are indexed by N when they have an entry for every N up to the largest (the
app kept the dropped frames' poses), or by position when they have exactly one entry per file;
without ``frameTimestamps`` a frame's time is ``N / fps``, so dropped frames show as gaps.

EXR files are decoded with OpenCV's OpenEXR codec, which OpenCV only enables when
``OPENCV_IO_ENABLE_OPENEXR`` is set before its first EXR use; it is set here.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.captures.common import CaptureScan, LazyFrames, Problem, intrinsics_problems, pose_problems
from embodmocap.io.captures.record3d_meta import FORMAT, parse_metadata, world_poses
from embodmocap.types import CameraTrajectory, Intrinsics

log = logging.getLogger(__name__)

_NUMBERED = re.compile(r"^(\d+)$")
VARIANT = "Record3D EXR + JPG export"
APP_WRITES = "Record3D's EXR + JPG export writes depth/N.exr (float metres) beside every rgb/N.jpg"


def read_exr_depth(path: Path) -> NDArray[np.float32]:
    """One depth EXR as (h, w) float32 metres, 0 where invalid; one clear error when it does not decode."""
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    import cv2

    if not path.is_file():
        raise InputError(path, f"missing; {APP_WRITES}", "export the recording again")
    try:
        d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    except cv2.error as err:
        raise InputError(path, f"EXR does not decode ({str(err).strip().splitlines()[-1]})",
                         "export the recording again (or set OPENCV_IO_ENABLE_OPENEXR=1 before anything "
                         "imports cv2)") from err
    if d is None:
        raise InputError(path, "EXR does not decode (truncated or not an EXR file)", "export the recording again")
    if d.ndim == 3:
        d = d[..., 2] if d.shape[-1] >= 3 else d[..., 0]  # OpenCV gives BGR(A): the R channel
    d = np.asarray(d, dtype=np.float32).copy()
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d


def _jpeg(path: Path) -> NDArray[np.uint8]:
    import cv2

    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise InputError(path, "unreadable JPEG", "export the recording again")
    return np.ascontiguousarray(bgr[..., ::-1])


def _numbers(folder: Path, suffix: str) -> list[int]:
    if not folder.is_dir():
        return []
    return sorted(int(p.stem) for p in folder.glob(f"*{suffix}") if _NUMBERED.match(p.stem))


def _by_number(values: NDArray, numbers: list[int]) -> NDArray | None:
    """Rows of ``values`` for the files ``numbers``: indexed by N when there is an entry for every N,
    by position when there is one entry per file; None when neither holds."""
    if len(values) > numbers[-1]:
        return values[numbers]
    if len(values) == len(numbers):
        return values
    return None


def scan_record3d_exr(path: str | Path, thorough: bool = False) -> CaptureScan:
    """Read everything but the frames of an EXR + JPG export, collecting every problem."""
    root = Path(path)
    meta_path = root / "metadata.json"
    if not meta_path.is_file():
        return CaptureScan(root, FORMAT, variant=VARIANT, problems=(Problem(
            meta_path, "missing: Record3D's EXR + JPG export writes metadata.json beside rgb/ and depth/",
            "copy the whole folder the app exported"),))
    try:
        meta = parse_metadata(meta_path.read_bytes(), meta_path)
    except InputError as err:
        return CaptureScan(root, FORMAT, variant=VARIANT, problems=(Problem(err.path, err.problem, err.fix),))
    problems: list[Problem] = []
    numbers = _numbers(root / "rgb", ".jpg")
    if not numbers:
        return CaptureScan(root, FORMAT, variant=VARIANT, problems=(Problem(
            root / "rgb", "no frames: the app writes rgb/N.jpg", "export the recording again"),))
    num_frames = len(numbers)
    dropped = numbers[-1] + 1 - num_frames
    variant = f"{VARIANT} ({num_frames} frames" + (f", {dropped} dropped by the app)" if dropped else ")")

    first = _jpeg(root / "rgb" / f"{numbers[0]}.jpg")
    rgb_size = (first.shape[1], first.shape[0])
    K = Intrinsics.from_K(meta.K3, meta.w, meta.h)
    if rgb_size != (meta.w, meta.h):
        log.info("%s: JPEG frames are %dx%d, metadata says %dx%d; scaling K", root, *rgb_size, meta.w, meta.h)
        K = K.scaled(*rgb_size)
    problems += intrinsics_problems(meta_path, K)

    have_depth = set(_numbers(root / "depth", ".exr"))
    missing = [n for n in numbers if n not in have_depth]
    if missing:
        problems.append(Problem(root / "depth" / f"{missing[0]}.exr",
                                f"missing ({len(missing)} of {num_frames} depth frames missing; {APP_WRITES})",
                                "export the recording again"))
    depth_size = meta.depth_size
    for n in [n for n in numbers if n in have_depth][: None if thorough else 1]:
        try:
            d = read_exr_depth(root / "depth" / f"{n}.exr")
        except InputError as err:
            problems.append(Problem(err.path, err.problem, err.fix))
            continue
        got = (d.shape[1], d.shape[0])
        if depth_size is None:
            depth_size = got
        elif got != depth_size:
            problems.append(Problem(root / "depth" / f"{n}.exr", f"depth is {got[0]}x{got[1]}, metadata says "
                                    f"{depth_size[0]}x{depth_size[1]}", "export the recording again"))

    T_all, pose_note, pose_probs = world_poses(meta, meta_path)
    problems += pose_probs
    T = _by_number(T_all, numbers)
    if T is None:
        problems.append(Problem(meta_path, f"{len(T_all)} poses fit neither the {num_frames} frames nor their "
                                f"numbers 0..{numbers[-1]}", "export the recording again"))
        T = np.full((0, 4, 4), np.nan)
    stamps = meta.frame_timestamps
    times = _by_number(stamps, numbers) if stamps is not None else None
    if times is None:
        times = np.asarray(numbers, dtype=np.float64) / meta.fps
    problems += pose_problems(meta_path, T, meta.fps * num_frames / (numbers[-1] + 1), num_frames)
    n_pose = min(len(T), num_frames)
    trajectory = CameraTrajectory(times[:n_pose], np.arange(n_pose), T[:n_pose])
    variant += f" ({pose_note})"

    def make_frames() -> LazyFrames:
        assert depth_size is not None
        return LazyFrames(num_frames, lambda i: _jpeg(root / "rgb" / f"{numbers[i]}.jpg"),
                          lambda i: root / "depth" / f"{numbers[i]}.exr", None, depth_size,
                          read_depth=lambda i: read_exr_depth(root / "depth" / f"{numbers[i]}.exr"))

    return CaptureScan(
        path=root, format=FORMAT, variant=variant, num_frames=num_frames, fps=meta.fps, rgb_intrinsics=K,
        depth_size=depth_size, timestamps_s=times, trajectory=trajectory, make_frames=make_frames,
        problems=tuple(problems),
    )
