"""Accuracy and throughput of the MediaPipe Pose backend on the real Pose2Sim demo videos.

For each of the four cameras (1080x1920 portrait, 60 fps, 100 frames) MediaPipe's COCO-17
keypoints are compared with the OpenPose BODY_25B keypoints shipped with the demo (another
detector, not ground truth; its coordinates are quantised to ~5 px steps). It prints:

- the frame offset between video frames and OpenPose file numbers that fits best, per camera;
- a Markdown table of the median pixel distance per COCO-17 joint and camera, over frames where
  both are confident (MediaPipe visibility >= 0.5, OpenPose score >= 0.3), at that offset;
- throughput (frames/s of the backend alone; decoding excluded) at the real resolution and on the
  same frames letterboxed to 640x480, in video (tracking) and static mode;
- everything again as one JSON document (also written to ``--json`` if given).

Not a test: run it by hand (about a minute on 2 cores).

    .venv/bin/python benchmarks/bench_mediapipe.py [--data ../shared/data/pose2sim_demo] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings
from pathlib import Path

os.environ.setdefault("GLOG_minloglevel", "2")  # MediaPipe's C++ logging, before it loads

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from embodmocap.io.openpose import read_keypoint_folder  # noqa: E402
from embodmocap.io.video import VideoReader  # noqa: E402
from embodmocap.perception.mediapipe_backend import MediaPipePose  # noqa: E402
from embodmocap.types import COCO17_NAMES  # noqa: E402

CAMS = ("cam01", "cam02", "cam03", "cam04")
MP_CONF, OP_CONF = 0.5, 0.3
OFFSETS = (-2, -1, 0, 1, 2)


def errors(mp_kp: np.ndarray, op_kp: np.ndarray) -> np.ndarray:
    """(T, 17) pixel distances, NaN where either detector is not confident."""
    d = np.linalg.norm(mp_kp[..., :2] - op_kp[..., :2], axis=-1)
    ok = (mp_kp[..., 2] >= MP_CONF) & (op_kp[..., 2] >= OP_CONF)
    return np.where(ok, d, np.nan)


def aligned(kp: np.ndarray, op: np.ndarray, s: int) -> tuple[np.ndarray, np.ndarray]:
    """Video frames v and OpenPose files v + s over the frames both exist."""
    n = len(kp)
    v = np.arange(max(0, -s), min(n, n - s))
    return kp[v], op[v + s]


def letterbox(frame: np.ndarray, W: int = 640, H: int = 480) -> tuple[np.ndarray, float, float]:
    """Scale ``frame`` to fit W x H, centred on black; returns it, the scale and the x offset."""
    h, w = frame.shape[:2]
    s = min(W / w, H / h)
    small = cv2.resize(frame, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
    out = np.zeros((H, W, 3), np.uint8)
    x0 = (W - small.shape[1]) // 2
    out[: small.shape[0], x0:x0 + small.shape[1]] = small
    return out, s, float(x0)


def run(frames, video_mode: bool) -> tuple[np.ndarray, float]:
    """(T, 17, 3) keypoints + masks for every frame, and frames/s (keypoints and masks)."""
    ids = list(range(len(frames)))
    with MediaPipePose(video_mode=video_mode) as pose:
        t0 = time.perf_counter()
        kp = np.concatenate(pose.estimate(frames, ids))
        pose.segment(frames, ids)  # served from the same run (cached), as Stage II would ask
        dt = time.perf_counter() - t0
    return kp, len(frames) / dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared/data/pose2sim_demo")
    ap.add_argument("--json", type=Path, default=None, help="also write the JSON summary here")
    args = ap.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN joints (e.g. an ear never seen)

    report: dict = {"cameras": {}, "joints": list(COCO17_NAMES)}
    for cam in CAMS:
        with VideoReader(args.data / "videos" / f"{cam}.mp4") as reader:
            frames = [reader.read(i) for i in range(len(reader))]
            res = f"{reader.info.width}x{reader.info.height}"
        op, missing = read_keypoint_folder(args.data / "pose" / f"{cam}_json", range(len(frames)), layout="BODY_25B")
        op = op.data
        kp_static, fps_static = run(frames, video_mode=False)
        kp_video, fps_video = run(frames, video_mode=True)
        small = [letterbox(f) for f in frames]
        kp_small, fps_small = run([s[0] for s in small], video_mode=True)
        _, s, x0 = small[0]
        kp_small[..., 0] = (kp_small[..., 0] - x0 + 0.5) / s - 0.5  # back to full-frame pixels
        kp_small[..., 1] = (kp_small[..., 1] + 0.5) / s - 0.5

        by_offset = {k: {o: float(np.nanmedian(errors(*aligned(kp, op, o)))) for o in OFFSETS}
                     for k, kp in (("static", kp_static), ("video", kp_video))}
        best = min(by_offset["static"], key=by_offset["static"].get)
        a, b = aligned(kp_static, op, best)
        err = errors(a, b)
        conf = b[..., 2] >= OP_CONF
        height = float(np.nanmedian(np.nanmax(np.where(conf, b[..., 1], np.nan), 1)
                                    - np.nanmin(np.where(conf, b[..., 1], np.nan), 1)))
        report["cameras"][cam] = {
            "resolution": res, "frames": len(frames), "openpose_missing": len(missing),
            "best_offset_static": best, "median_px_by_offset": by_offset,
            "median_px_per_joint": [None if np.isnan(v) else round(float(v), 1) for v in np.nanmedian(err, 0)],
            "pairs_per_joint": [int(v) for v in np.isfinite(err).sum(0)],
            "median_px_all": round(float(np.nanmedian(err)), 2),
            "median_px_video_mode": round(float(np.nanmedian(errors(*aligned(kp_video, op, best)))), 2),
            "median_px_640x480": round(float(np.nanmedian(errors(*aligned(kp_small, op, best)))), 2),
            "person_height_px": round(height, 1),
            "frames_with_person": int((kp_static[..., 2].max(-1) > 0).sum()),
            "fps_full_video_mode": round(fps_video, 1), "fps_full_static": round(fps_static, 1),
            "fps_640x480_video_mode": round(fps_small, 1),
        }
        print(f"{cam}: offset {best:+d} best (static medians {by_offset['static']}), "
              f"{fps_video:.1f} fps full res, {fps_small:.1f} fps 640x480", flush=True)

    cams = report["cameras"]
    print("\nMedian distance MediaPipe - OpenPose (px, static mode, video frame v vs file v + offset)\n")
    print("| joint | " + " | ".join(CAMS) + " |")
    print("|---|" + "---|" * len(CAMS))
    for j, name in enumerate(COCO17_NAMES):
        cells = [("-" if cams[c]["median_px_per_joint"][j] is None else f"{cams[c]['median_px_per_joint'][j]:.1f}")
                 + f" ({cams[c]['pairs_per_joint'][j]})" for c in CAMS]
        print(f"| {name} | " + " | ".join(cells) + " |")
    rows = [("all joints", "median_px_all"), ("all, video mode", "median_px_video_mode"),
            ("all, 640x480 input", "median_px_640x480"), ("person height px", "person_height_px"),
            ("best offset", "best_offset_static"), ("fps full res (video)", "fps_full_video_mode"),
            ("fps full res (static)", "fps_full_static"), ("fps 640x480 (video)", "fps_640x480_video_mode")]
    for label, key in rows:
        print(f"| {label} | " + " | ".join(str(cams[c][key]) for c in CAMS) + " |")
    print("\n(n) = frames where both detectors are confident.\n")
    text = json.dumps(report, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text)


if __name__ == "__main__":
    main()
