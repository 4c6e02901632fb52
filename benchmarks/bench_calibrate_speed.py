"""Stage III speed before/after on one or more sessions, in one run (issues 13, 30).

Runs Stages I and II once (this checkout) if needed, then Stage III from scratch (``--force``) in a
child process with this checkout, then with another checkout's ``src`` (``--old-src``, e.g. main)
on the same session right after (``--pairs 2``: then again in the other order), and reports both
wall times, CPU seconds (user + system of the child, all threads: the figure that holds on a shared
machine) and their ratios, with the registration step times from the stage manifest. Where the
session has the studio's ground truth, each run's accuracy is reported too: each view's
``T_world_vio`` against the truth at the view's camera centres (mean cm, yaw deg; as
``bench_calibrate.py``). The scene's registration index cache (``register_index.npz``) is kept
between runs (both codes build the same one; ``--cold-index`` deletes it before every run).
``--workers`` also times this checkout's Stage III with registration on one thread, for the thread
pool's speed-up (measured as is, on whatever load the machine has: the load average is printed).

    .venv/bin/python benchmarks/bench_calibrate_speed.py --session /work/bench/13/seq60/indoor_0 \\
        --old-src /work/bench/13/old/src --workers
    nice -n 5 .venv/bin/python benchmarks/bench_calibrate_speed.py --session S1 S2 S3 --old-src /work/base-src/src \\
        --pairs 2 --json /tmp/stage3.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

_CODE = """
import json, resource, sys, time
from embodmocap.calibrate import stage
from embodmocap.calibrate.register import RegisterConfig
cfg = stage.CalibrateConfig()
if len(sys.argv) > 2:
    cfg = stage.CalibrateConfig(register=RegisterConfig(workers=int(sys.argv[2])))
c0 = resource.getrusage(resource.RUSAGE_SELF)
t0 = time.perf_counter()
out = stage.run(cfg, sys.argv[1], force=True)
wall = time.perf_counter() - t0
c1 = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"wall_s": wall, "cpu_s": (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime),
                  "rss_mb": c1.ru_maxrss // 1024, "T_world_vio": {v: T.tolist() for v, T in out.T_world_vio.items()}}))
"""


def _snapshot(session: Path) -> dict[Path, bytes]:
    """Stage II's sync.json and manifest.json of the session's sequences: Stage III completes them
    (geometric sync), and the code before issue 13 writes its own version of sync.json, which this
    checkout's Stage III refuses; every run starts from the same Stage II files."""
    return {p: p.read_bytes() for p in sorted((session / "sequences").glob("*/*.json"))
            if p.name in ("sync.json", "manifest.json")}


def _restore(snap: dict[Path, bytes]) -> None:
    for p, b in snap.items():
        p.write_bytes(b)


def accuracy(session: Path, T_world_vio: dict) -> dict:
    """Per view: mean distance (cm) at the view's camera centres and yaw (deg) of ``T_world_vio``
    against the studio's truth; {} for a session without ground truth."""
    from bench_calibrate import errors

    from embodmocap.geometry.transforms import invert_T
    from embodmocap.io.layout import SessionLayout

    lay = SessionLayout(session)
    if not lay.ground_truth.sequence("seq0").is_file():
        return {}
    scene_vio = np.load(lay.ground_truth.scene_device("scene0"))["T_scene_vio"]
    seq = np.load(lay.ground_truth.sequence("seq0"))
    out = {}
    for v, T in T_world_vio.items():
        truth = invert_T(scene_vio) @ seq[f"{v}_T_scene_vio"]
        centres = np.load(lay.sequence("seq0").view(v).cameras)["T_world_cam"][:, :3, 3]
        cm, deg = errors(np.asarray(T), truth, centres)
        out[f"{v}_cm"], out[f"{v}_deg"] = round(100 * cm, 3), round(deg, 4)
    return out


def stage3(session: Path, src: str, workers: int | None = None, snap: dict | None = None, cold_index: bool = False) -> dict:
    if snap:
        _restore(snap)
    if cold_index:
        (session / "scenes" / "scene0" / "register_index.npz").unlink(missing_ok=True)
    env = dict(os.environ, PYTHONPATH=src)
    args = [sys.executable, "-c", _CODE, str(session)] + ([str(workers)] if workers else [])
    t0 = time.perf_counter()
    proc = subprocess.run(args, check=True, capture_output=True, text=True, env=env)
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["process_wall_s"] = time.perf_counter() - t0
    man = json.loads((session / "sequences" / "seq0" / "calibrate_manifest.json").read_text()) \
        if (session / "sequences" / "seq0" / "calibrate_manifest.json").is_file() else {"steps": {}}
    out["steps"] = {k: v["seconds"] for k, v in man["steps"].items()}
    out["load_avg_1m"] = os.getloadavg()[0]
    out.update(accuracy(session, out.pop("T_world_vio")))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", type=Path, nargs="+", required=True)
    ap.add_argument("--old-src", required=True, help="src folder of the checkout to compare with")
    ap.add_argument("--workers", action="store_true", help="also time this checkout with 1 registration thread")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--old-first", action="store_true",
                    help="time the other checkout first (a second run in the other order shows how much the order and "
                         "the machine's changing load move the ratio)")
    ap.add_argument("--pairs", type=int, default=1, help="old/new pairs per session, the order alternating")
    ap.add_argument("--cold-index", action="store_true", help="delete the scene's registration index before every run")
    args = ap.parse_args()
    from embodmocap.io.layout import SessionLayout

    new_src = str(Path(__file__).resolve().parents[1] / "src")
    cli = "import sys; from embodmocap.cli import main; sys.exit(main(sys.argv[1:]))"
    print(f"load average at start: {os.getloadavg()}", flush=True)
    rows: dict = {"runs": []}
    for session in args.session:
        lay = SessionLayout(session)
        if not (lay.scene("scene0").sfm_dir / "sparse").is_dir():
            subprocess.run([sys.executable, "-c", cli, "scene", str(session)], check=True,
                           env=dict(os.environ, PYTHONPATH=new_src))
        if not lay.sequence("seq0").view("v1").cameras.is_file():
            subprocess.run([sys.executable, "-c", cli, "sequence", str(session)], check=True,
                           env=dict(os.environ, PYTHONPATH=new_src))
        snap = _snapshot(session)
        for p in range(args.pairs):
            first_old = args.old_first != (p % 2 == 1)
            for name in (("old", "new") if first_old else ("new", "old")):
                r = stage3(session, new_src if name == "new" else args.old_src, snap=snap, cold_index=args.cold_index)
                r.update(code=name, session=str(session), pair=p)
                rows["runs"].append(r)
                print(name, json.dumps(r), flush=True)
        if args.workers:
            r = stage3(session, new_src, workers=1, snap=snap, cold_index=args.cold_index)
            r.update(code="new_1_thread", session=str(session))
            rows["runs"].append(r)
            print("new_1_thread", json.dumps(r), flush=True)
        _restore(snap)
    runs = rows["runs"]
    tot = {c: {k: sum(r[k] for r in runs if r["code"] == c) for k in ("wall_s", "cpu_s")} for c in ("old", "new")}
    rows["ratio_new_over_old"] = tot["new"]["wall_s"] / tot["old"]["wall_s"]
    rows["cpu_ratio_new_over_old"] = tot["new"]["cpu_s"] / tot["old"]["cpu_s"]
    print(f"\nload average at the end: {os.getloadavg()}")
    print("| session | code | wall s | CPU s | register s (v1 + v2) | refine s | v1 cm | v2 cm | v1 deg | v2 deg | load 1 min |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in runs:
        st = r["steps"]
        print(f"| {Path(r['session']).name} | {r['code']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | "
              f"{st.get('register_v1', 0):.1f} + {st.get('register_v2', 0):.1f} | {st.get('refine', 0):.1f} | "
              + " | ".join(str(r.get(k, "-")) for k in ("v1_cm", "v2_cm", "v1_deg", "v2_deg")) + f" | {r['load_avg_1m']:.1f} |")
    print(f"Stage III new/old: wall {rows['ratio_new_over_old']:.3f} (sum {tot['new']['wall_s']:.1f} / {tot['old']['wall_s']:.1f} s), "
          f"CPU {rows['cpu_ratio_new_over_old']:.3f} (sum {tot['new']['cpu_s']:.1f} / {tot['old']['cpu_s']:.1f} s)")
    for c in ("old", "new"):
        cm = [r[f"{v}_cm"] for r in runs if r["code"] == c for v in ("v1", "v2") if f"{v}_cm" in r]
        deg = [r[f"{v}_deg"] for r in runs if r["code"] == c for v in ("v1", "v2") if f"{v}_deg" in r]
        if cm:
            print(f"{c}: median {np.median(cm):.3f} cm, p95 {np.percentile(cm, 95):.3f} cm; "
                  f"median {np.median(deg):.4f} deg, p95 {np.percentile(deg, 95):.4f} deg (over views and runs)")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
