"""Make the pictures of docs/recording.md from a synthetic studio session (ground truth known).

    .venv/bin/python scripts/make_recording_figures.py --out docs/images                # makes its sessions
    .venv/bin/python scripts/make_recording_figures.py GOOD BAD --out docs/images       # or uses yours

Without sessions it synthesises two under --work (a normal take, `embodmocap synth --seed 1 --seconds
8 --laser.mode realistic`, and one built to fail `check`: no laser, phones 20 deg apart, phone 2
turned away at the end) and runs Stage I on each (`embodmocap scene`, which `check` needs): about
25 minutes on two cores. Pictures written (each under 200 KB):

- recording_scan.png: top view of the studio room with the scene scan's path, where its view hits
  the floor, and the scan camera's pitch over time;
- recording_phones.png: top view of the performance (performer's path, the two phones, the angle
  between them at a few instants, the laser dot and both phones' sight lines to it) and a side view
  of how far a phone must be to keep the whole body in frame;
- recording_laser.jpg: the studio's rendered frames of both phones just before and at the laser
  switch-off, with the dot magnified, and what the sync detector found;
- recording_check.png: what `embodmocap check` prints on the two sessions (run here).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

PORTRAIT_VFOV_DEG = 67.0
"""Field of view along an iPhone main camera's long side (vertical when held upright), degrees."""
PHONE_HEIGHT_M = 1.45
"""Height at which the operators hold the phones (the studio's 1.35-1.55 m)."""


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "embodmocap.cli", *args], capture_output=True, text=True)


GOOD_TAKE = ("--seed", "1", "--seconds", "8", "--laser.mode", "realistic")
"""`embodmocap synth` options of the session the pictures show (a normal take)."""
BAD_TAKE = ("--seed", "1", "--seconds", "8", "--laser.mode", "none", "--view-separation-deg", "20",
            "--view2-away-fraction", "0.5")
"""... and of a take built to fail `check`: no laser, phones 20 deg apart, phone 2 turned away at the end."""


def make_session(work: Path, name: str, options: tuple[str, ...]) -> Path:
    """A studio session with Stage I done (what `check` needs), made once under ``work``."""
    session = work / name
    if not (session / "session.toml").is_file():
        out = _run("synth", str(session), *options)
        if out.returncode:
            raise SystemExit(out.stderr)
    out = _run("scene", str(session))
    if out.returncode:
        raise SystemExit(out.stderr)
    return session


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"font.size": 9, "axes.titlesize": 10, "axes.titleweight": "bold"})
    return plt


def _truth(session: Path) -> tuple[dict, dict, dict, np.ndarray]:
    """(ground_truth.json, scene device npz, sequence npz, room (2, 2) xy min/max) of a studio session."""
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.mesh_file import read_mesh_ply

    gt = SessionLayout(session).ground_truth
    info = json.loads(gt.info.read_text())
    scene = dict(np.load(gt.scene_device(info["scene"])))
    seq = dict(np.load(gt.sequence(info["sequence"])))
    v, _, _ = read_mesh_ply(gt.scene_mesh(info["scene"]))
    floor = v[v[:, 2] < 0.05]
    room = np.stack([floor[:, :2].min(axis=0), floor[:, :2].max(axis=0)])
    return info, scene, seq, room


def _draw_room(ax, info: dict, room: np.ndarray) -> None:
    """Walls and furniture footprints, top view (x right, y up, metres)."""
    from matplotlib.patches import Polygon, Rectangle

    (x0, y0), (x1, y1) = room
    ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, lw=2.5, ec="#333333"))
    for name, f in info["furniture"].items():
        c, yaw = np.asarray(f["centre_xy"]), f["yaw"]
        hx, hy = f["size"][0] / 2, f["size"][1] / 2
        R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
        corners = (R @ np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]]).T).T + c
        ax.add_patch(Polygon(corners, closed=True, fc="#d9d4c7", ec="#8c8470", lw=1))
        ax.text(*c, name.replace("_", " "), ha="center", va="center", fontsize=7, color="#5a5345")
    ax.set_aspect("equal")
    ax.set_xlim(x0 - 0.3, x1 + 0.3)
    ax.set_ylim(y0 - 0.3, y1 + 0.3)
    ax.set_xticks([])
    ax.set_yticks([])


def scan_figure(session: Path, out: Path) -> None:
    plt = _plt()
    info, scene, seq, room = _truth(session)
    T = scene["T_scene_cam"]
    fps = float(info["config"]["fps"])
    pos, fwd = T[:, :3, 3], T[:, :3, 2]  # OpenCV: the camera looks along its +z axis
    t = np.arange(len(T)) / fps
    pitch = np.degrees(np.arcsin(np.clip(-fwd[:, 2], -1, 1)))  # degrees below the horizon
    seen = _floor_seen(T[::3], info["config"], room)
    walk = seq["joints_smpl24"][:, 0, :2]

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 4.6), gridspec_kw={"width_ratios": [1.35, 1]})
    _draw_room(ax, info, room)
    (x0, y0), (x1, y1) = room
    ax.imshow(np.ma.masked_equal(seen, 0).T, origin="lower", extent=(x0, x1, y0, y1), cmap="Blues", vmin=0,
              vmax=1.3 * seen.max(), alpha=0.6, zorder=0)
    ax.plot(walk[:, 0], walk[:, 1], "--", color="#34495e", lw=2.2, zorder=5, label="the performer's path (later)")
    ax.fill_between([], [], color="#6baed6", alpha=0.6, label="floor in view (within 3.5 m)")
    sc = ax.scatter(pos[:, 0], pos[:, 1], c=t, cmap="viridis", s=6, zorder=3)
    step = max(1, int(fps))
    ax.quiver(pos[::step, 0], pos[::step, 1], fwd[::step, 0], fwd[::step, 1], color="#c0392b", scale=14,
              width=0.004, zorder=4, label="view direction (every 1 s)")
    ax.plot(*pos[0, :2], "o", ms=9, mfc="none", mec="k", zorder=5)
    ax.annotate("start", pos[0, :2], xytext=(6, 6), textcoords="offset points", fontsize=8)
    fig.colorbar(sc, ax=ax, fraction=0.04, pad=0.02, label="time (s)")
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, -0.2), ncol=2, frameon=False, fontsize=8)
    ax.set_title(f"Scene scan from above ({t[-1]:.0f} s, one slow loop)")

    ax2.plot(t, pitch, color="#2c3e50")
    ax2.axhspan(15, 40, color="#27ae60", alpha=0.12)
    ax2.text(t[-1] * 0.02, 37, "looking down at the floor", fontsize=8, color="#1e8449", va="top")
    ax2.axhspan(-5, 15, color="#2980b9", alpha=0.08)
    ax2.text(t[-1] * 0.02, 12, "looking across the room", fontsize=8, color="#1f618d", va="top")
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("camera pitch below the horizon (deg)")
    ax2.set_ylim(-5, 45)
    ax2.set_title("Tilt of the scanning phone")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=90, bbox_inches="tight")
    plt.close(fig)


def _floor_seen(T: np.ndarray, cfg: dict, room: np.ndarray, cell_m: float = 0.1, max_m: float = 3.5) -> np.ndarray:
    """(nx, ny) count of frames whose image sees each floor cell within ``max_m`` (occlusion by
    furniture ignored): rays through a grid of pixels of the studio camera, cut with z = 0."""
    from scipy.ndimage import binary_closing, binary_fill_holes

    w, h = int(cfg["width"]), int(cfg["height"])
    f = w / 2 / np.tan(np.radians(cfg["hfov_deg"]) / 2)
    u, v = np.meshgrid(np.linspace(0, w, 16), np.linspace(0, h, 12))
    rays_cam = np.stack([(u - w / 2) / f, (v - h / 2) / f, np.ones_like(u)], -1).reshape(-1, 3)
    (x0, y0), (x1, y1) = room
    nx, ny = int(np.ceil((x1 - x0) / cell_m)), int(np.ceil((y1 - y0) / cell_m))
    seen = np.zeros((nx, ny))
    for T_wc in T:
        d = rays_cam @ T_wc[:3, :3].T
        o = T_wc[:3, 3]
        down = d[:, 2] < -1e-3
        s = -o[2] / d[down, 2]
        p = o + d[down] * s[:, None]
        near = np.linalg.norm(p - o, axis=1) < max_m
        ix = ((p[near, 0] - x0) / cell_m).astype(int)
        iy = ((p[near, 1] - y0) / cell_m).astype(int)
        ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        frame = np.zeros_like(seen, dtype=bool)
        frame[ix[ok], iy[ok]] = True
        # Fill the frame's footprint between the sampled rays (a coarse grid leaves gaps).
        seen += binary_fill_holes(binary_closing(frame, np.ones((5, 5))))
    return seen


def _angle_at(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    u, w = a - p, b - p
    return float(np.degrees(np.arccos(np.clip(u @ w / (np.linalg.norm(u) * np.linalg.norm(w)), -1, 1))))


def phones_figure(session: Path, out: Path) -> None:
    plt = _plt()
    info, _, seq, room = _truth(session)
    pelvis = seq["joints_smpl24"][:, 0]  # (M, 3) motion frames
    start = {v: int(seq[f"{v}_motion_start"]) for v in ("v1", "v2")}
    cams = {v: seq[f"{v}_T_scene_cam"][:, :3, 3] for v in ("v1", "v2")}
    event = int(info["event_motion_frame"])
    dot = np.asarray(info["laser_dot"])
    colours = {"v1": "#2471a3", "v2": "#cb4335"}

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10.5, 4.8), gridspec_kw={"width_ratios": [1.3, 1]})
    _draw_room(ax, info, room)
    ax.plot(pelvis[:, 0], pelvis[:, 1], color="#555555", lw=2, label="performer")
    for v in ("v1", "v2"):
        ax.plot(cams[v][:, 0], cams[v][:, 1], color=colours[v], lw=1.2, alpha=0.8, label=f"phone {v[1]}")
    # The laser dot and both phones' sight lines to it at the switch-off.
    ax.plot(*dot[:2], marker="*", ms=14, color="#e74c3c", mec="k", zorder=6, label="laser dot (on a wall)")
    for v in ("v1", "v2"):
        c = cams[v][event - start[v]]
        ax.plot([c[0], dot[0]], [c[1], dot[1]], ":", color=colours[v], lw=1.2)
    # A few instants: both phones, lines to the performer, the angle between them.
    M = len(pelvis)
    for k, m in enumerate(np.linspace(event + 15, M - 10, 3).astype(int)):
        p = pelvis[m]
        ends = {v: cams[v][min(max(m - start[v], 0), len(cams[v]) - 1)] for v in ("v1", "v2")}
        for v, c in ends.items():
            ax.plot([c[0], p[0]], [c[1], p[1]], color=colours[v], lw=0.9, alpha=0.6)
            ax.plot(*c[:2], "s", ms=5, color=colours[v])
        ang = _angle_at(p[:2], ends["v1"][:2], ends["v2"][:2])
        dist = np.mean([np.linalg.norm(ends[v][:2] - p[:2]) for v in ends])
        ax.plot(*p[:2], "o", ms=6, color="#333333")
        ax.annotate(f"{ang:.0f} deg, {dist:.1f} m", p[:2], xytext=(6, -12 if k % 2 else 6),
                    textcoords="offset points", fontsize=8, weight="bold")
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, -0.16), ncol=4, frameon=False, fontsize=8)
    ax.set_title("Performance, top view: two phones 60-120 deg apart")

    _framing_panel(ax2)
    fig.tight_layout()
    fig.savefig(out, dpi=90, bbox_inches="tight")
    plt.close(fig)


def _framing_panel(ax) -> None:
    """Side view: a phone held upright at chest height and aimed so that feet and head are equally
    far from the frame's edges, at two distances; the field of view (67 deg along the long side)
    against a 1.75 m performer."""
    from matplotlib.patches import Rectangle

    half = np.radians(PORTRAIT_VFOV_DEG / 2)
    tall = 1.75
    for d, colour in ((1.0, "#c0392b"), (2.5, "#1e8449")):
        feet, head = np.arctan2(PHONE_HEIGHT_M, d), np.arctan2(tall - PHONE_HEIGHT_M, d)  # below / above
        aim = (feet - head) / 2  # tilt below the horizon
        need = np.degrees(feet + head)
        for sgn in (-1, 1):
            ang = -aim + sgn * half
            ax.plot([0, 4.2], [PHONE_HEIGHT_M, PHONE_HEIGHT_M + 4.2 * np.tan(ang)], color=colour, lw=1.2)
        lo = PHONE_HEIGHT_M + d * np.tan(-aim - half)
        hi = PHONE_HEIGHT_M + d * np.tan(-aim + half)
        ax.add_patch(Rectangle((d - 0.12, 0), 0.24, tall, fc=colour, alpha=0.25, ec=colour))
        ax.plot([d, d], [max(lo, 0), min(hi, tall)], color=colour, lw=5, alpha=0.8, solid_capstyle="butt")
        verdict = "feet and head cut" if need > PORTRAIT_VFOV_DEG else "whole body, room to move"
        far = d > 2
        label = f"{d:g} m: body spans {need:.0f} deg\n{verdict}"
        ax.text(d + (0.2 if far else 0.0), tall + (0.05 if far else 0.5), label, color=colour, fontsize=8,
                ha="left" if far else "center", va="bottom")
    ax.plot(0, PHONE_HEIGHT_M, marker="s", ms=8, color="#2c3e50")
    ax.text(-0.15, 0.75, f"phone,\nupright,\n{PORTRAIT_VFOV_DEG:.0f} deg\nview", fontsize=8, va="center")
    ax.axhline(0, color="#555555", lw=1.5)
    ax.axvspan(2.0, 3.5, color="#27ae60", alpha=0.07)
    ax.text(2.75, -0.3, "2-3.5 m: in frame,\nLiDAR in range", ha="center", va="center", fontsize=8, color="#1e8449")
    ax.set_xlim(-0.2, 4.2)
    ax.set_ylim(-0.5, 2.7)
    ax.set_aspect("equal")
    ax.set_xlabel("distance to the performer (m)")
    ax.set_ylabel("height (m)")
    ax.set_title("Side view: keep the whole body in frame")
    ax.grid(alpha=0.25)


def laser_figure(session: Path, out: Path) -> None:
    plt = _plt()
    from embodmocap.io.captures import open_capture
    from embodmocap.io.layout import SessionLayout
    from embodmocap.io.manifest import load_manifest
    from embodmocap.sequence.sync import detect_laser_event

    info, _, seq, _ = _truth(session)
    entry = load_manifest(SessionLayout(session).manifest).sequence(info["sequence"])
    dot = np.append(np.asarray(info["laser_dot"], float), 1.0)
    fig, axes = plt.subplots(2, 2, figsize=(8.4, 7.0))
    for row, v in enumerate(("v1", "v2")):
        cap = open_capture(entry.views[v].capture)
        found = detect_laser_event(cap)
        true = int(info["sync_frames"][v])
        K = cap.rgb_intrinsics.K
        for col, frame in enumerate((true - 1, true)):
            ax = axes[row, col]
            rgb = np.asarray(cap.frames.rgb(frame))
            ax.imshow(rgb)
            T_cam_scene = np.linalg.inv(seq[f"{v}_T_scene_cam"][frame])
            pc = (T_cam_scene @ dot)[:3]
            u, w = (K @ pc)[:2] / pc[2]
            r = 18
            ax.add_patch(plt.Circle((u, w), r, fill=False, ec="yellow", lw=1.5))
            inset = ax.inset_axes([0.66, 0.62, 0.32, 0.36])
            y0, x0 = int(round(w)) - r, int(round(u)) - r
            crop = rgb[max(y0, 0):y0 + 2 * r, max(x0, 0):x0 + 2 * r]
            inset.imshow(crop, interpolation="nearest")
            inset.set_xticks([])
            inset.set_yticks([])
            for s in inset.spines.values():
                s.set_edgecolor("yellow")
                s.set_linewidth(1.5)
            ax.set_xticks([])
            ax.set_yticks([])
            state = "dot on (last frame with it)" if col == 0 else "dot off: the sync frame"
            ax.set_title(f"phone {v[1]}, frame {frame}: {state}", fontsize=9)
        got = f"frame {found.frame} (confidence {found.confidence:.2f})" if found else "nothing"
        axes[row, 1].text(0.5, -0.06, f"detector found {got}; truth frame {true}", transform=axes[row, 1].transAxes,
                          ha="center", va="top", fontsize=8)
    fig.tight_layout(h_pad=2.5)
    fig.savefig(out, dpi=80, pil_kwargs={"quality": 82})
    plt.close(fig)


def check_figure(sessions: list[Path], out: Path) -> str:
    """Run `embodmocap check` on each session, draw what it printed as a terminal; return the text."""
    plt = _plt()
    lines: list[str] = []
    for session in sessions:
        res = _run("check", str(session))
        lines += [f"$ embodmocap check {session.name}", *res.stdout.rstrip().splitlines(), f"$ echo $?   # exit status",
                  str(res.returncode), ""]
    lines = lines[:-1]
    text = "\n".join(lines)
    width = max(len(s) for s in lines)
    fig = plt.figure(figsize=(0.079 * width + 0.3, 0.19 * len(lines) + 0.3))
    fig.patch.set_facecolor("#1e1e1e")
    for i, line in enumerate(lines):
        colour = "#d4d4d4"
        if line.startswith("$"):
            colour = "#9cdcfe"
        elif "RESHOOT" in line or line.strip().startswith("- reshoot"):
            colour = "#f48771"
        elif "WARNINGS" in line or line.strip().startswith("- warning"):
            colour = "#dcdcaa"
        elif "USABLE" in line:
            colour = "#b5cea8"
        fig.text(0.015, 1 - (i + 0.9) / (len(lines) + 0.6), line, family="monospace", fontsize=9, color=colour,
                 va="baseline", parse_math=False)
    fig.savefig(out, dpi=100, facecolor=fig.get_facecolor())
    plt.close(fig)
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", nargs="*", type=Path,
                    help="studio sessions with Stage I done: a normal take (pictures + check), then any others "
                         "for the check picture (default: make the two of GOOD_TAKE and BAD_TAKE)")
    ap.add_argument("--out", type=Path, default=Path("docs/images"))
    ap.add_argument("--work", type=Path, default=Path("/tmp/recording_figures"), help="where sessions are made")
    args = ap.parse_args()
    sessions = args.sessions or [make_session(args.work, "studio", GOOD_TAKE),
                                 make_session(args.work, "badtake", BAD_TAKE)]
    args.out.mkdir(parents=True, exist_ok=True)
    scan_figure(sessions[0], args.out / "recording_scan.png")
    phones_figure(sessions[0], args.out / "recording_phones.png")
    laser_figure(sessions[0], args.out / "recording_laser.jpg")
    print(check_figure(sessions, args.out / "recording_check.png"))
    for p in sorted(args.out.glob("recording_*")):
        print(f"{p}: {p.stat().st_size / 1024:.0f} KB")


if __name__ == "__main__":
    main()
