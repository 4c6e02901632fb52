"""Video files: probe, random-access reading and atomic streaming writing (PyAV).

Frames are (H, W, 3) uint8 **RGB**. Frame ``i`` is the i-th frame in presentation order. The
reader keeps one decoder open and decodes forward, so sequential access costs one decode per frame;
it seeks (to the key frame before the target) only when asked for an earlier frame or one far ahead
with a key frame in between.

Rotation metadata (a display matrix, as iPhones write for portrait recordings) is *not* applied:
frames come out as stored in the file. :attr:`VideoInfo.rotation_deg` reports it so a capture
reader can decide what to do.
"""

from __future__ import annotations

import logging
import os
import tempfile
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from embodmocap.errors import InputError
from embodmocap.io.atomic import default_file_mode

log = logging.getLogger(__name__)

#: Jumping ahead by more than this many frames seeks instead of decoding through the gap (when a
#: key frame lies in the gap: a seek lands on the key frame before the target, and without one
#: there it would decode again the frames already passed).
_SEEK_AHEAD_FRAMES = 48


@dataclass(frozen=True)
class VideoInfo:
    """What a video file holds, read from its packets (no frame decoded).

    Attributes:
        num_frames: number of video frames (packets of the first video stream).
        fps: average frame rate, frames per second.
        width: frame width in pixels as stored (rotation metadata not applied).
        height: frame height in pixels as stored.
        codec: decoder name, e.g. ``"h264"`` or ``"hevc"``.
        timestamps_s: (num_frames,) presentation time of every frame, seconds from the stream
            start, increasing.
        rotation_deg: display rotation from the file's display matrix, degrees counter-clockwise
            as PyAV reports it (0, 90, -90, 180); iPhone portrait videos usually say -90 (turn the
            stored frame 90 degrees clockwise to view it upright). 0 if none.
    """

    num_frames: int
    fps: float
    width: int
    height: int
    codec: str
    timestamps_s: NDArray[np.float64]
    rotation_deg: int = 0


def _open(path: Path):
    import av

    if not path.is_file():
        raise InputError(path, "video file not found", "check the capture folder is complete")
    try:
        container = av.open(str(path))
    except av.error.FFmpegError as err:
        raise InputError(path, f"unreadable video ({err.__class__.__name__}: {err})",
                         "the file is truncated or not a video; copy it again from the phone") from err
    if not container.streams.video:
        container.close()
        raise InputError(path, "file holds no video stream", "give the capture's RGB video")
    return container


def _packet_pts(container, stream, path: Path) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Sorted presentation timestamps of every packet of ``stream`` (demux only, no decode), and
    the sorted frame indices (presentation order) of its key frames."""
    import av

    pts, key = [], []
    try:
        for packet in container.demux(stream):
            if packet.size == 0:  # the flush packet at the end
                continue
            pts.append(packet.pts if packet.pts is not None else packet.dts)
            key.append(bool(packet.is_keyframe))
    except av.error.FFmpegError as err:
        raise InputError(path, f"video is truncated or corrupt after {len(pts)} frames ({err})",
                         "copy the file again from the phone") from err
    if any(p is None for p in pts):
        # Streams without timestamps: fall back to the packet order.
        return np.arange(len(pts), dtype=np.int64), np.flatnonzero(key).astype(np.int64)
    order = np.argsort(np.asarray(pts, dtype=np.int64), kind="stable")
    return np.asarray(pts, dtype=np.int64)[order], np.flatnonzero(np.asarray(key, dtype=bool)[order]).astype(np.int64)


def _first_frame_rotation(container, stream, path: Path) -> int:
    """Display rotation (degrees counter-clockwise, as PyAV reports it) of the first frame.

    Decoding one frame also proves the stream is decodable at all.
    """
    import av

    try:
        container.seek(0, stream=stream)
        frame = next(container.decode(stream))
    except (av.error.FFmpegError, StopIteration) as err:
        raise InputError(path, f"cannot decode the first video frame ({err})",
                         "the file is corrupt; copy it again from the phone") from err
    return int(round(getattr(frame, "rotation", 0) or 0))


def probe_video(path: str | Path) -> VideoInfo:
    """Read a video's size, frame count, frame rate and per-frame timestamps.

    Raises:
        InputError: the file is missing, not a video, truncated or has no frames.
    """
    return _probe(Path(path))[0]


def _probe(path: Path) -> tuple[VideoInfo, NDArray[np.int64], NDArray[np.int64]]:
    """:func:`probe_video` plus the sorted raw packet timestamps (stream time base) and the frame
    indices of the key frames."""
    container = _open(path)
    try:
        stream = container.streams.video[0]
        tb = stream.time_base
        pts, keys = _packet_pts(container, stream, path)
        if len(pts) == 0:
            raise InputError(path, "video has no frames", "record the capture again")
        declared = stream.frames
        if declared and declared > len(pts):
            raise InputError(path, f"video is truncated: header says {declared} frames, "
                             f"found {len(pts)}", "copy the file again from the phone")
        start = stream.start_time if stream.start_time is not None else int(pts[0])
        t = (pts - start).astype(np.float64) * float(tb) if tb is not None else np.arange(len(pts)) / 30.0
        rate = stream.average_rate or stream.guessed_rate
        if rate:
            fps = float(rate)
        elif len(t) > 1 and t[-1] > t[0]:
            fps = (len(t) - 1) / (t[-1] - t[0])
        else:
            fps = 30.0
        info = VideoInfo(
            num_frames=len(pts), fps=fps, width=stream.codec_context.width,
            height=stream.codec_context.height, codec=stream.codec_context.name,
            timestamps_s=t, rotation_deg=_first_frame_rotation(container, stream, path),
        )
        return info, pts, keys
    finally:
        container.close()


class VideoReader:
    """Random access to a video's frames as (H, W, 3) uint8 RGB.

    Cheap for forward sequential reads (the decoder stays open); a read of an earlier frame, or of
    one far ahead with a key frame in between, seeks to the key frame before it. Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.info, self._pts, self._keys = _probe(self.path)
        self._container = _open(self.path)
        self._stream = self._container.streams.video[0]
        self._stream.thread_type = "AUTO"
        # Map presentation timestamp -> frame index, to identify decoded frames after a seek.
        self._index_of_pts = {int(p): i for i, p in enumerate(self._pts)}
        self._frames = None  # decoding iterator
        self._next = 0  # index the iterator yields next
        self._last: tuple[int, NDArray[np.uint8]] | None = None

    def __len__(self) -> int:
        return self.info.num_frames

    def __enter__(self) -> "VideoReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._container is not None:
            self._container.close()
            self._container = None

    def read(self, index: int) -> NDArray[np.uint8]:
        """Frame ``index`` (0-based, presentation order) as (H, W, 3) uint8 RGB."""
        index = int(index)
        if not 0 <= index < len(self):
            raise IndexError(f"frame {index} outside 0..{len(self) - 1} of {self.path}")
        if self._last is not None and self._last[0] == index:
            return self._last[1]
        if self._container is None:
            raise ValueError(f"{self.path}: reader is closed")
        if self._frames is None or index < self._next or (index > self._next + _SEEK_AHEAD_FRAMES
                                                            and self._key_at_or_before(index) > self._next):
            self._seek(index)
        return self._decode_until(index)

    def _key_at_or_before(self, index: int) -> int:
        """The last key frame at or before ``index`` (``index`` itself when the demuxer flagged none)."""
        k = int(np.searchsorted(self._keys, index, side="right")) - 1
        return int(self._keys[k]) if k >= 0 else index

    def _seek(self, index: int) -> None:
        # backward=True lands on the key frame at or before the target; decoding then runs forward.
        self._container.seek(int(self._pts[index]), backward=True, any_frame=False, stream=self._stream)
        self._frames = self._container.decode(self._stream)
        self._next = -1  # unknown until the first decoded frame tells its pts

    def _decode_until(self, index: int) -> NDArray[np.uint8]:
        import av

        try:
            for frame in self._frames:
                i = self._index_of_pts.get(frame.pts, self._next) if frame.pts is not None else self._next
                self._next = i + 1
                if i < index:
                    continue
                rgb = frame.to_ndarray(format="rgb24")
                self._last = (i, rgb)
                if i == index:
                    return rgb
                break  # overshot: the seek landed after the target (should not happen)
        except av.error.FFmpegError as err:
            raise InputError(self.path, f"cannot decode frame {index} ({err})",
                             "the video is corrupt; copy it again from the phone") from err
        self._frames = None
        raise InputError(self.path, f"frame {index} could not be decoded (video ends early)",
                         "the video is truncated; copy it again from the phone")


class VideoWriter:
    """Streams RGB frames into an H.264 (yuv420p) video, written atomically.

    Frames go to a temporary file next to ``path``; :meth:`close` renames it into place, so an
    interrupted write never leaves a playable-looking partial file. The container is chosen from
    the suffix (``.mp4``, ``.mov``). Width and height must be even (yuv420p subsamples chroma by 2).
    """

    def __init__(self, path: str | Path, fps: float, width: int, height: int,
                 codec: str = "libx264", crf: int = 18) -> None:
        import av

        if width % 2 or height % 2:
            raise ValueError(f"{path}: yuv420p video needs even width and height, got {width}x{height}; "
                             "crop or pad the frames by one pixel")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.width, self.height = int(width), int(height)
        from embodmocap.io.atomic import temp_prefix

        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(self.path), suffix=self.path.suffix, dir=self.path.parent)
        os.close(fd)
        self._tmp = Path(tmp)
        self._container = av.open(str(self._tmp), mode="w")
        rate = Fraction(fps).limit_denominator(1001)
        self._stream = self._container.add_stream(codec, rate=rate)
        self._stream.width, self._stream.height = self.width, self.height
        self._stream.pix_fmt = "yuv420p"
        self._stream.codec_context.time_base = 1 / rate
        if codec in ("libx264", "libx265"):
            # Deterministic output matters (the studio promises identical files per seed). With
            # the lookahead presets (veryfast and slower) the same frames gave different bytes
            # from run to run on a loaded machine here; ultrafast (no lookahead, no mbtree, one
            # thread) did not. CRF 18 keeps the quality high; files are just larger.
            self._stream.options = {"crf": str(int(crf)), "preset": "ultrafast"}
            self._stream.codec_context.thread_count = 1
        self._count = 0

    def write(self, rgb: NDArray[np.uint8]) -> None:
        """Append one (height, width, 3) uint8 RGB frame."""
        import av

        rgb = np.asarray(rgb)
        if rgb.shape != (self.height, self.width, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"{self.path}: frame must be ({self.height}, {self.width}, 3) uint8, "
                             f"got {rgb.shape} {rgb.dtype}")
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        # Convert to the encoder's pixel format here, single-threaded: left to the encoder, the
        # conversion ran on several threads and the same frames gave different bytes between runs.
        frame = frame.reformat(format=self._stream.pix_fmt, threads=1)
        frame.pts = self._count
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self._count += 1

    def close(self) -> None:
        """Flush the encoder and move the finished file into place."""
        if self._container is None:
            return
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()
        self._container = None
        os.chmod(self._tmp, default_file_mode())
        os.replace(self._tmp, self.path)

    def abort(self) -> None:
        """Drop the partial file (nothing appears at ``path``)."""
        if self._container is not None:
            try:
                self._container.close()
            except Exception:  # noqa: BLE001 - the file is being discarded anyway
                pass
            self._container = None
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
