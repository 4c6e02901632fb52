"""``embodmocap inspect``: summarise a capture and list every problem in it at once.

The readers stop at the first fatal problem; this module runs the same scans in thorough mode
(every depth header read) and reports them all, plus figures a user wants before processing:
duration, sizes, intrinsics, pose path length and timestamp gaps.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from embodmocap.errors import InputError
from embodmocap.io.captures import scan_capture
from embodmocap.types import Intrinsics

#: A gap between consecutive frame timestamps larger than this many frame intervals is reported.
GAP_FRAMES = 1.5


@dataclass(frozen=True)
class CaptureReport:
    """What ``inspect`` found in one capture.

    Attributes:
        path: the capture inspected.
        format: detected format, or None when none matched.
        variant: the app version's export recognised, in words (e.g. "Record3D .r3d file, older
            metadata (poses relative to the first camera, put in ARKit's world with initPose; ...)").
        num_frames: RGB frames (0 when the video/images could not be read).
        duration_s: num_frames / fps.
        fps: nominal frame rate.
        rgb_size: (width, height) of the RGB frames as returned, or None.
        depth_size: (width, height) of the depth maps as returned, or None.
        intrinsics: RGB intrinsics, or None.
        pose_count: number of poses matched to frames.
        path_length_m: distance travelled by the camera centre over finite poses, metres.
        timestamp_gaps: (frame, gap seconds) for each frame whose time follows the previous frame's
            by more than 1.5 frame intervals.
        problems: one line per problem, each naming the file and what is wrong.
    """

    path: Path
    format: str | None
    variant: str = ""
    num_frames: int = 0
    duration_s: float = 0.0
    fps: float = 0.0
    rgb_size: tuple[int, int] | None = None
    depth_size: tuple[int, int] | None = None
    intrinsics: Intrinsics | None = None
    pose_count: int = 0
    path_length_m: float = 0.0
    timestamp_gaps: list[tuple[int, float]] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def check_capture(path: str | Path) -> CaptureReport:
    """Inspect a capture without stopping at the first problem."""
    path = Path(path)
    try:
        scan = scan_capture(path, thorough=True)
    except InputError as err:
        return CaptureReport(path, None, problems=[str(err)])
    K = scan.rgb_intrinsics
    gaps: list[tuple[int, float]] = []
    if scan.fps > 0 and len(scan.timestamps_s) > 1:
        dt = np.diff(scan.timestamps_s)
        rows = np.nonzero(dt > GAP_FRAMES / scan.fps)[0]
        gaps = [(int(i + 1), float(dt[i])) for i in rows]
    pose_count, length = 0, 0.0
    if scan.trajectory is not None and len(scan.trajectory):
        pose_count = len(scan.trajectory)
        c = scan.trajectory.centres
        c = c[np.all(np.isfinite(c), axis=1)]
        length = float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum()) if len(c) > 1 else 0.0
    return CaptureReport(
        path=path, format=scan.format, variant=scan.variant, num_frames=scan.num_frames,
        duration_s=scan.num_frames / scan.fps if scan.fps > 0 else 0.0, fps=scan.fps,
        rgb_size=(K.width, K.height) if K is not None else None, depth_size=scan.depth_size, intrinsics=K,
        pose_count=pose_count, path_length_m=length, timestamp_gaps=gaps,
        problems=[str(p) for p in scan.problems],
    )


def format_report(report: CaptureReport) -> str:
    """A few human-readable lines summarising a :class:`CaptureReport`."""
    r = report
    size = lambda s: f"{s[0]}x{s[1]}" if s else "?"  # noqa: E731 - tiny local formatter
    lines = [
        f"capture   {r.path}",
        f"format    {r.format or 'unknown'}",
        *([f"version   {r.variant}"] if r.variant else []),
        f"frames    {r.num_frames} at {r.fps:.2f} fps ({r.duration_s:.1f} s)",
        f"rgb       {size(r.rgb_size)}   depth {size(r.depth_size)}",
    ]
    if r.intrinsics is not None:
        K = r.intrinsics
        lines.append(f"K         fx {K.fx:.2f}  fy {K.fy:.2f}  cx {K.cx:.2f}  cy {K.cy:.2f}")
    lines.append(f"poses     {r.pose_count}, camera path {r.path_length_m:.2f} m")
    if r.timestamp_gaps:
        shown = ", ".join(f"frame {i} (+{g * 1000:.0f} ms)" for i, g in r.timestamp_gaps[:5])
        more = f" and {len(r.timestamp_gaps) - 5} more" if len(r.timestamp_gaps) > 5 else ""
        lines.append(f"gaps      {len(r.timestamp_gaps)}: {shown}{more}")
    if r.problems:
        lines.append(f"problems  {len(r.problems)}:")
        lines += [f"  - {p}" for p in r.problems]
    else:
        lines.append("problems  none")
    return "\n".join(lines)
