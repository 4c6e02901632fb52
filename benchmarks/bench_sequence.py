"""Benchmark Stage II (`embodmocap sequence`) with the precomputed backends.

For each length: synthesise a session (scene capture minimal), run the stage from scratch in a
child process (peak RSS of that process), and report per-view throughput of the observation steps
(keypoints + tracking, masks, depth, body prior; frames/s per view, from the stage manifest's step
timings) and, separately, the sync step (laser-dot detection decodes every frame of both videos).
Memory should not grow with the sequence length.

Target (issue 4): at least 300 frames/s per view with the precomputed backend; memory flat.

    .venv/bin/python benchmarks/bench_sequence.py --seconds 10 30 --out /tmp/bench_seq
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from _child import run_cli


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, nargs="+", default=[10.0, 30.0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("bench_out/sequence"))
    args = ap.parse_args()
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    rows = []
    for sec in args.seconds:
        session = args.out / f"seq_{int(sec)}s"
        if not (session / "ground_truth" / "ground_truth.json").is_file():
            synthesize(SynthConfig(seed=args.seed, seconds=sec, scene_seconds=1.0), session)
        wall, rss = run_cli("sequence", str(session), "--force")
        man = json.loads((session / "sequences" / "seq0" / "manifest.json").read_text())
        st = {k: v["seconds"] for k, v in man["steps"].items()}
        T = man["figures"]["frames"]
        per_view = {v: st["keypoints"] / 2 + st[f"masks_{v}"] + st[f"depth_{v}"] + st.get(f"body_prior_{v}", 0.0)
                    for v in ("v1", "v2")}
        row = {"seconds": sec, "frames": T, "wall_s": round(wall, 1), "peak_rss_mb": rss, "sync_s": st["sync"],
               **{f"{v}_fps": round(T / t, 1) for v, t in per_view.items()}, "steps_s": st}
        rows.append(row)
        print(json.dumps(row), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_sequence.json").write_text(json.dumps(rows, indent=2))
    print("\n| sequence (s) | frames | v1 frames/s | v2 frames/s | sync step (s) | stage wall (s) | peak RSS (MB) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['seconds']} | {r['frames']} | {r['v1_fps']} | {r['v2_fps']} | {r['sync_s']} | {r['wall_s']} | {r['peak_rss_mb']} |")


if __name__ == "__main__":
    main()
