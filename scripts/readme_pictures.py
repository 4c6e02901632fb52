"""Make the README's pictures from a processed session (e.g. the demo's): the web viewer in headless
Chromium, one frame of the side-by-side overlay video, and the CSV export drawn over the floor plan.

    .venv/bin/python scripts/readme_pictures.py demo_out --out docs/images
"""

from __future__ import annotations

import argparse
import csv
import socket
import tempfile
import time
from pathlib import Path

import numpy as np


def viewer_picture(session: Path, seq: str, out: Path) -> None:
    from embodmocap.viz.browser import HeadlessChromium
    from embodmocap.viz.viewer import ViewerConfig, serve

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    handle = serve(session, seq, ViewerConfig(port=port))
    try:
        handle.set_frame(handle.num_frames // 2)
        # (Chromium's helper processes may still write to the profile while it is removed.)
        with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as tmp, HeadlessChromium(handle.url, Path(tmp), (1280, 800)) as page:
            deadline = time.monotonic() + 60
            while not handle.server.get_clients() and time.monotonic() < deadline:
                time.sleep(0.1)
            time.sleep(12.0)  # software WebGL: let the scene and images arrive and draw
            import cv2

            cv2.imwrite(str(out), cv2.cvtColor(page.screenshot(), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])
    finally:
        handle.stop()


def render_picture(session: Path, seq: str, out: Path) -> None:
    import cv2

    from embodmocap.io.video import VideoReader
    from embodmocap.viz.render import RenderConfig, render_sequence

    paths = render_sequence(session, seq, RenderConfig(progress=False))
    side = [p for p in paths if "side_by_side" in p.name][0]
    with VideoReader(side) as reader:
        frame = reader.read(len(reader) // 2)
    cv2.imwrite(str(out), cv2.cvtColor(np.asarray(frame), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])


def export_picture(session: Path, seq: str, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from embodmocap.evaluate.mesh_metrics import sample_surface
    from embodmocap.export import export_sequence
    from embodmocap.io.layout import SessionLayout
    from embodmocap.scene.mesh import read_mesh_ply

    path = export_sequence(session, seq, "csv")
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    data = np.array(rows[1:], dtype=float)  # rows[0] is the header
    joints = data[:, 2:].reshape(len(data), -1, 3)
    lay = SessionLayout(session)
    scene = next(iter(lay.root.joinpath("scenes").iterdir())).name
    v, f, _ = read_mesh_ply(lay.scene(scene).mesh_raw)
    p = sample_surface(v, f, 60000)
    p = p[p[:, 2] < np.percentile(p[:, 2], 2) + 1.8]
    fig = plt.figure(figsize=(8, 6))
    ax = fig.add_subplot(projection="3d")
    ax.scatter(p[:, 0], p[:, 1], p[:, 2], s=0.2, c=p[:, 2], cmap="Greys", alpha=0.25)
    from embodmocap.body.joints import SMPL_PARENTS

    for t in np.linspace(0, len(joints) - 1, 8).astype(int):
        for j, parent in enumerate(SMPL_PARENTS):
            if parent >= 0:
                seg = joints[t, [parent, j]]
                ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], color=plt.cm.viridis(t / max(len(joints) - 1, 1)), lw=1.5)
    ax.set_title(f"{path.name}: {len(joints)} frames x {joints.shape[1]} joints, 8 frames shown")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    c = joints[:, 0].mean(axis=0)
    ax.set_xlim(c[0] - 2, c[0] + 2)
    ax.set_ylim(c[1] - 2, c[1] + 2)
    ax.set_zlim(0, 2.5)
    fig.savefig(out, dpi=90, bbox_inches="tight")
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("session", type=Path)
    ap.add_argument("--seq", default="seq0")
    ap.add_argument("--out", type=Path, default=Path("docs/images"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    viewer_picture(args.session, args.seq, args.out / "viewer.jpg")
    print("viewer done", flush=True)
    render_picture(args.session, args.seq, args.out / "render.jpg")
    export_picture(args.session, args.seq, args.out / "export_csv.png")
    print(f"pictures in {args.out}")


if __name__ == "__main__":
    main()
