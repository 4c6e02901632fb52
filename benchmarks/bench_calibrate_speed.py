"""Stage III speed before/after on one session, in one run (issue 13).

Runs Stages I and II once (this checkout) if needed, then Stage III from scratch (``--force``) in a
child process with this checkout, then with another checkout's ``src`` (``--old-src``, e.g. the
code before issue 13) on the same session right after, and reports both wall times and their
ratio, with the registration step times from the stage manifest. ``--workers`` also times this
checkout's Stage III with registration on one thread, for the thread pool's speed-up (measured
as is, on whatever load the machine has: the load average is printed with it).

    .venv/bin/python benchmarks/bench_calibrate_speed.py --session /work/bench/13/seq60/indoor_0 \\
        --old-src /work/bench/13/old/src --workers
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

_CODE = """
import json, resource, sys, time
from embodmocap.calibrate import stage
from embodmocap.calibrate.register import RegisterConfig
cfg = stage.CalibrateConfig()
if len(sys.argv) > 2:
    cfg = stage.CalibrateConfig(register=RegisterConfig(workers=int(sys.argv[2])))
t0 = time.perf_counter()
stage.run(cfg, sys.argv[1], force=True)
print(json.dumps({"wall_s": time.perf_counter() - t0, "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024}))
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


def stage3(session: Path, src: str, workers: int | None = None, snap: dict | None = None) -> dict:
    if snap:
        _restore(snap)
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
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", type=Path, required=True)
    ap.add_argument("--old-src", required=True, help="src folder of the checkout to compare with")
    ap.add_argument("--workers", action="store_true", help="also time this checkout with 1 registration thread")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--old-first", action="store_true",
                    help="time the other checkout first (a second run in the other order shows how much the order and "
                         "the machine's changing load move the ratio)")
    args = ap.parse_args()
    from embodmocap.io.layout import SessionLayout

    new_src = str(Path(__file__).resolve().parents[1] / "src")
    lay = SessionLayout(args.session)
    cli = "import sys; from embodmocap.cli import main; sys.exit(main(sys.argv[1:]))"
    if not (lay.scene("scene0").sfm_dir / "sparse").is_dir():
        subprocess.run([sys.executable, "-c", cli, "scene", str(args.session)], check=True,
                       env=dict(os.environ, PYTHONPATH=new_src))
    if not lay.sequence("seq0").view("v1").cameras.is_file():
        subprocess.run([sys.executable, "-c", cli, "sequence", str(args.session)], check=True,
                       env=dict(os.environ, PYTHONPATH=new_src))
    snap = _snapshot(args.session)
    rows = {}
    for name in (("old", "new") if args.old_first else ("new", "old")):
        rows[name] = stage3(args.session, new_src if name == "new" else args.old_src, snap=snap)
        print(name, json.dumps(rows[name]), flush=True)
    if args.workers:
        rows["new_1_thread"] = stage3(args.session, new_src, workers=1, snap=snap)
        print("new_1_thread", json.dumps(rows["new_1_thread"]), flush=True)
    _restore(snap)
    rows["ratio_new_over_old"] = rows["new"]["wall_s"] / rows["old"]["wall_s"]
    print(f"Stage III new/old wall time: {rows['ratio_new_over_old']:.3f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
