"""Benchmark: Stage III's same-dot check of the laser events against the studio's ground truth.

For every session given whose Stage III is done (``sync.json`` version 2, ``calibration.json``),
the two views' laser sightings are put in the scene's world with the calibrated ``T_world_vio``
(:func:`embodmocap.sequence.laser_check.laser_dot_check`) and the gap is set against whether the
laser events were right (the ground truth's ``sync_frames``). The check must pass every right pair
and fail the wrong ones; the truth is only used to score it.

    PYTHONPATH=src .venv/bin/python benchmarks/bench_laser_check.py SESSION [SESSION ...] [--limit-m 0.15]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from embodmocap.io.captures import open_capture
from embodmocap.io.manifest import load_manifest
from embodmocap.sequence.laser_check import laser_dot_check


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sessions", nargs="+", type=Path)
    ap.add_argument("--limit-m", type=float, default=0.15)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    rows = []
    for root in args.sessions:
        man = load_manifest(root / "session.toml")
        gt = json.loads((root / "ground_truth" / "ground_truth.json").read_text())
        for seq in sorted(p for p in (root / "sequences").iterdir() if (p / "calibration.json").is_file()):
            rec = json.loads((seq / "sync.json").read_text())
            if rec.get("version") != 2:
                print(f"{root.name} {seq.name}: sync.json version {rec.get('version')}, skipped")
                continue
            cal = json.loads((seq / "calibration.json").read_text())
            T = {v: np.asarray(cal["views"][v]["T_world_vio"]) for v in rec["views"]}
            entry = man.sequence(seq.name)
            caps = {v: (lambda p=entry.views[v].capture: open_capture(p)) for v in rec["views"]}
            chk = laser_dot_check(rec, caps, T, args.limit_m)
            laser = rec["sources"]["laser"]["views"]
            right = {v: bool(laser[v].get("found")) and laser[v]["frame"] == gt["sync_frames"][v] for v in rec["views"]}
            row = {"session": root.name, "sequence": seq.name, "right": right,
                   "check": None if chk is None else chk.to_json()}
            rows.append(row)
            print(json.dumps(row), flush=True)
    judged = [r for r in rows if r["check"] is not None]
    ok_pairs = [r for r in judged if all(r["right"].values())]
    bad_pairs = [r for r in judged if not all(r["right"].values())]
    print(f"right pairs: {len(ok_pairs)}, rejected {sum(r['check']['same_dot'] is False for r in ok_pairs)}; "
          f"wrong pairs: {len(bad_pairs)}, rejected {sum(r['check']['same_dot'] is False for r in bad_pairs)}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
