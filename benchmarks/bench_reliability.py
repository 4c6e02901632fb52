"""Reliability figures (issue 20): SfM repeatability and cost by thread count, and the cost of a
rerun that has nothing to redo on a copied session.

    OMP_NUM_THREADS=1 python benchmarks/bench_reliability.py SESSION [--runs 2] [--threads 1 -1] \
        [--run-options "--scene.voxel-m-indoor 0.02 ..."]

SESSION must have Stage I done (``embodmocap scene SESSION``): its key frames (``sfm/images``) and
their poses (``keyframes.json``) are the SfM input, built ``--runs`` times per thread count into a
temporary folder. Then the finished session is copied with ``cp -r`` (new mtimes) and
``embodmocap run`` (with the options the session was processed with) is timed on the copy
(every step must be skipped).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from embodmocap.io.captures import open_capture
from embodmocap.io.layout import SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.stage_manifest import fingerprint, path_fingerprint
from embodmocap.scene.sfm import SfmConfig, build_sparse_model


def sfm_runs(session: Path, threads: int, runs: int, work: Path) -> list[dict]:
    lay = SessionLayout(session)
    name = next(iter(load_manifest(lay.manifest).scenes))
    scene = lay.scene(name)
    kf = json.loads(scene.keyframes.read_text())
    cap = open_capture(load_manifest(lay.manifest).scenes[name].capture)
    images = scene.sfm_dir / "images"
    # The key frames SfM used (thinned by the stage to at most max_images), in name order.
    used = sorted(p.stem for p in images.iterdir())
    ids = [f"kf_{int(i):06d}" for i in kf["frame_ids"]]
    T = np.asarray(kf["T_world_cam"], dtype=np.float64).reshape(-1, 4, 4)[[ids.index(u) for u in used]]
    rows = []
    for r in range(runs):
        out = work / f"t{threads}_{r}"
        t0 = time.perf_counter()
        model = build_sparse_model(images, cap.rgb_intrinsics, T, out, SfmConfig(num_threads=threads))
        rows.append({"threads": threads, "run": r, "points": model.num_points,
                     "seconds": round(time.perf_counter() - t0, 1),
                     "model_sha": hashlib.sha256(b"".join(p.read_bytes() for p in sorted((out / "sparse").iterdir()))).hexdigest()[:12],
                     "database_fp": fingerprint(path_fingerprint(out / "database.db"))})
        print(rows[-1], flush=True)
    return rows


def noop_rerun(session: Path, work: Path, options: list[str]) -> dict:
    copy = work / "copy"
    subprocess.run(["cp", "-r", str(session), str(copy)], check=True)
    before = {p.as_posix(): json.loads(p.read_text())["steps"] for p in copy.rglob("*manifest.json")}
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "embodmocap.cli", "run", str(copy), *options], capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    after = {p.as_posix(): json.loads(p.read_text())["steps"] for p in copy.rglob("*manifest.json")}
    return {"rerun_status": proc.returncode, "rerun_seconds": round(seconds, 1), "steps_redone":
            sum(1 for k in before for s in before[k] if after.get(k, {}).get(s) != before[k][s])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("session", type=Path)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, -1])
    ap.add_argument("--no-rerun", action="store_true", help="skip the copied-session rerun")
    ap.add_argument("--run-options", default="", help="options of `embodmocap run` the session was processed with")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(dir=args.session.parent) as tmp:
        rows = [row for t in args.threads for row in sfm_runs(args.session, t, args.runs, Path(tmp))]
        for t in args.threads:
            mine = [r for r in rows if r["threads"] == t]
            same = len({(r["model_sha"], r["database_fp"]) for r in mine}) == 1
            print(f"threads {t:>2}: points {[r['points'] for r in mine]}, seconds {[r['seconds'] for r in mine]}, "
                  f"bitwise identical: {same}")
        if not args.no_rerun:
            print(noop_rerun(args.session, Path(tmp), args.run_options.split()))
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
