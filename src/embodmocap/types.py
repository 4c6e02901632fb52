"""Typed, frozen data shared by the stages in memory (cameras, keypoints, SMPL parameters, captures).

The files one stage hands to the next are read and written by :mod:`embodmocap.io.stage_files`.

Shapes use ``T`` frames, ``J`` joints, ``N`` points, ``H x W`` image sizes. World: Z up, metres.
Cameras: OpenCV axes. ``T_world_cam`` maps camera points into the world (camera-to-world).

Arrays inside frozen dataclasses are made read-only at construction, so a stage cannot change what
another stage handed it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Protocol, Sequence

import numpy as np
from numpy.typing import NDArray

#: COCO-17 keypoint order used everywhere in the package.
COCO17_NAMES: tuple[str, ...] = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_hip", "right_hip",
    "left_knee", "right_knee", "left_ankle", "right_ankle",
)


def _frozen_array(x, dtype=np.float64) -> NDArray:
    a = np.array(x, dtype=dtype, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of one image stream, in pixels of that stream.

    Pixel centres sit at integer coordinates (OpenCV convention): the top-left pixel's centre is
    (0, 0), so the image spans [-0.5, W-0.5] x [-0.5, H-0.5].
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> NDArray[np.float64]:
        """The 3x3 calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_K(cls, K, width: int, height: int) -> "Intrinsics":
        K = np.asarray(K, dtype=np.float64)
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height))

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """The same camera seen at another resolution (e.g. RGB 1920x1440 -> depth 256x192).

        Uses the pixel-centre convention: ``c' = (c + 0.5) * s - 0.5``.
        """
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5,
            int(width), int(height),
        )


@dataclass(frozen=True)
class CameraTrajectory:
    """Per-frame camera poses of one capture.

    Attributes:
        timestamps_s: (T,) capture timestamps in seconds (the app's clock), increasing.
        frame_ids: (T,) index of each pose's frame in the capture's video.
        T_world_cam: (T, 4, 4) camera-to-world, Z-up metric world, OpenCV camera axes.
    """

    timestamps_s: NDArray[np.float64]
    frame_ids: NDArray[np.int64]
    T_world_cam: NDArray[np.float64]

    def __post_init__(self) -> None:
        object.__setattr__(self, "timestamps_s", _frozen_array(self.timestamps_s))
        object.__setattr__(self, "frame_ids", _frozen_array(self.frame_ids, np.int64))
        object.__setattr__(self, "T_world_cam", _frozen_array(self.T_world_cam))
        n = len(self.timestamps_s)
        if self.frame_ids.shape != (n,) or self.T_world_cam.shape != (n, 4, 4):
            raise ValueError(
                f"trajectory shapes disagree: timestamps {self.timestamps_s.shape}, "
                f"frame_ids {self.frame_ids.shape}, T_world_cam {self.T_world_cam.shape}"
            )

    def __len__(self) -> int:
        return len(self.timestamps_s)

    @property
    def centres(self) -> NDArray[np.float64]:
        """(T, 3) camera centres in the world."""
        return self.T_world_cam[:, :3, 3]

    def path_length_m(self) -> float:
        """Total distance travelled by the camera centre, metres."""
        if len(self) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.centres, axis=0), axis=1).sum())


@dataclass(frozen=True)
class RGBDFrame:
    """One frame of a capture, at full resolution.

    Attributes:
        index: frame number in the capture's video (0-based).
        timestamp_s: capture time in seconds.
        rgb: (H, W, 3) uint8, RGB order.
        depth_m: (h, w) float32 metres, 0 where invalid; its own (usually lower) resolution.
        confidence: (h, w) uint8 0 low / 1 medium / 2 high, or None if the capture has none.
        T_world_cam: (4, 4) camera-to-world pose of this frame, or None if not tracked.
    """

    index: int
    timestamp_s: float
    rgb: NDArray[np.uint8]
    depth_m: NDArray[np.float32]
    confidence: NDArray[np.uint8] | None
    T_world_cam: NDArray[np.float64] | None


class FrameSource(Protocol):
    """Random access to a capture's frames, read lazily from disk (never all in memory)."""

    def __len__(self) -> int: ...

    def rgb(self, index: int) -> NDArray[np.uint8]:
        """(H, W, 3) uint8 RGB image of frame ``index``."""
        ...

    def depth_m(self, index: int) -> NDArray[np.float32]:
        """(h, w) float32 depth in metres of frame ``index``; 0 = invalid."""
        ...

    def confidence(self, index: int) -> NDArray[np.uint8] | None:
        """(h, w) uint8 confidence of frame ``index`` (0/1/2), or None."""
        ...


@dataclass(frozen=True)
class ImuSamples:
    """IMU samples of a capture (may be empty).

    Attributes:
        timestamps_s: (N,) seconds, same clock as the frames.
        accel_mps2: (N, 3) accelerometer in m/s^2 (converted from g where the app wrote g).
        gyro_radps: (N, 3) gyroscope in rad/s.
    """

    timestamps_s: NDArray[np.float64]
    accel_mps2: NDArray[np.float64]
    gyro_radps: NDArray[np.float64]

    def __post_init__(self) -> None:
        for name in ("timestamps_s", "accel_mps2", "gyro_radps"):
            object.__setattr__(self, name, _frozen_array(getattr(self, name)))

    @classmethod
    def empty(cls) -> "ImuSamples":
        return cls(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)))


@dataclass(frozen=True)
class Capture:
    """One RGB-D + pose recording, whatever app wrote it, in the package's conventions.

    Attributes:
        path: the capture folder (or file) it was read from.
        format: ``"strayscanner"``, ``"spectacular"`` or ``"record3d"``.
        num_frames: number of RGB video frames.
        fps: nominal frame rate (frames per second) read from the data.
        rgb_intrinsics: intrinsics at RGB resolution (size read from the video).
        depth_intrinsics: the same camera at depth-map resolution.
        trajectory: per-frame poses (T_world_cam); may cover a subset of frames.
        frames: lazy random access to RGB, depth and confidence.
        imu: IMU samples (possibly empty).
        timestamps_s: (num_frames,) time of every video frame, seconds.
    """

    path: Path
    format: str
    num_frames: int
    fps: float
    rgb_intrinsics: Intrinsics
    depth_intrinsics: Intrinsics
    trajectory: CameraTrajectory
    frames: FrameSource = field(repr=False, compare=False)
    imu: ImuSamples = field(default_factory=ImuSamples.empty, repr=False)
    timestamps_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0), repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "timestamps_s", _frozen_array(self.timestamps_s))

    @property
    def duration_s(self) -> float:
        return self.num_frames / self.fps if self.fps > 0 else 0.0

    def frame(self, index: int) -> RGBDFrame:
        """Read frame ``index`` (RGB, depth, confidence and its pose if tracked)."""
        if not 0 <= index < self.num_frames:
            raise IndexError(f"frame {index} outside 0..{self.num_frames - 1} of {self.path}")
        hit = np.nonzero(self.trajectory.frame_ids == index)[0]
        pose = self.trajectory.T_world_cam[hit[0]] if len(hit) else None
        t = float(self.timestamps_s[index]) if len(self.timestamps_s) > index else index / self.fps
        return RGBDFrame(
            index, t, self.frames.rgb(index), self.frames.depth_m(index),
            self.frames.confidence(index), pose,
        )

    def iter_frames(self, indices: Sequence[int] | None = None) -> Iterator[RGBDFrame]:
        """Yield frames one at a time (memory stays flat)."""
        for i in range(self.num_frames) if indices is None else indices:
            yield self.frame(int(i))


@dataclass(frozen=True)
class Keypoints2D:
    """2D keypoints of one view in COCO-17 order (:data:`COCO17_NAMES`).

    Attributes:
        data: (T, 17, 3) float: pixel x, pixel y, confidence in [0, 1]; confidence 0 = missing.
        frame_ids: (T,) frame index of each row.
    """

    data: NDArray[np.float64]
    frame_ids: NDArray[np.int64]

    def __post_init__(self) -> None:
        object.__setattr__(self, "data", _frozen_array(self.data))
        object.__setattr__(self, "frame_ids", _frozen_array(self.frame_ids, np.int64))
        if self.data.ndim != 3 or self.data.shape[1:] != (17, 3):
            raise ValueError(f"keypoints must be (T, 17, 3), got {self.data.shape}")
        if self.frame_ids.shape != (len(self.data),):
            raise ValueError("frame_ids must have one entry per keypoint row")

    @property
    def xy(self) -> NDArray[np.float64]:
        """(T, 17, 2) pixel coordinates."""
        return self.data[..., :2]

    @property
    def conf(self) -> NDArray[np.float64]:
        """(T, 17) confidences."""
        return self.data[..., 2]


@dataclass(frozen=True)
class PngMasks:
    """Person masks stored one PNG per frame (non-zero = person); read lazily.

    Attributes:
        paths: one path per frame, in frame order; a missing file means "no mask for this frame".
    """

    paths: tuple[Path, ...]

    def __len__(self) -> int:
        return len(self.paths)

    def mask(self, index: int) -> NDArray[np.bool_]:
        from PIL import Image

        with Image.open(self.paths[index]) as im:
            return np.asarray(im.convert("L")) > 127


@dataclass(frozen=True)
class SmplParams:
    """SMPL parameters of a sequence (axis-angle rotations).

    Attributes:
        betas: (B,) shape coefficients, one set for the whole sequence (B = 10 by default).
        global_orient: (T, 3) root rotation, axis-angle, in the frame the params live in
            (world for world-space params, camera for camera-space priors).
        body_pose: (T, 69) 23 body joints x axis-angle, SMPL joint order 1..23.
        transl: (T, 3) SMPL ``transl`` parameter in metres (not the pelvis position).
        fps: frame rate of the motion.
        gender: ``"neutral"``, ``"male"`` or ``"female"``.
    """

    betas: NDArray[np.float64]
    global_orient: NDArray[np.float64]
    body_pose: NDArray[np.float64]
    transl: NDArray[np.float64]
    fps: float = 30.0
    gender: str = "neutral"

    def __post_init__(self) -> None:
        for name in ("betas", "global_orient", "body_pose", "transl"):
            object.__setattr__(self, name, _frozen_array(getattr(self, name)))
        T = len(self.global_orient)
        if self.global_orient.shape != (T, 3) or self.body_pose.shape != (T, 69) or self.transl.shape != (T, 3):
            raise ValueError(
                "SMPL params must be global_orient (T,3), body_pose (T,69), transl (T,3); got "
                f"{self.global_orient.shape}, {self.body_pose.shape}, {self.transl.shape}"
            )
        if self.betas.ndim != 1:
            raise ValueError(f"betas must be (B,), got {self.betas.shape}")

    def __len__(self) -> int:
        return len(self.global_orient)

    @property
    def poses(self) -> NDArray[np.float64]:
        """(T, 72) global_orient and body_pose concatenated (AMASS ``poses`` layout)."""
        return np.concatenate([self.global_orient, self.body_pose], axis=1)
