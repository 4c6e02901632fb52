"""Who does what when in one `embodmocap run`: a per-step timeline with each process's CPU.

Runs every stage of a session (``pipeline.run_session``, as ``embodmocap run`` does) in a child
process on a fresh copy of the session's inputs, and meanwhile samples every ``--every`` seconds the
CPU time (user + system) and resident memory of the child and of every process below it (the
workers of ``--workers 2``), and the whole machine's busy time (``/proc/stat``: what the other
users of a shared box took). The child logs each step's end with its duration and its process id
(the workers' log records keep their own time and process), so each step gets an interval on one
process and the CPU that process spent in it.

Printed: the steps in order of their start (process, start, end, wall, CPU, CPU / wall), the jobs
of the scheduler, a strip per process in ``--bin`` second bins (the CPU it used per bin, 0-9 for
0-100 % of a core, ``.`` below 5 %), the core-seconds the run left idle on ``--cores`` cores and how
busy the machine was meanwhile. ``--json`` keeps the raw samples and records.

    cp -al /work/sessions/indoor_60s OUT/in
    env -u OMP_NUM_THREADS PYTHONPATH=src python benchmarks/run_timeline.py OUT/in --work OUT/t --workers 0
    ... --src /work/base-src/src     # the baseline code (its sequential run)
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

from _child import _tree, communicate_sampling

_CODE = r"""
import inspect, logging, sys, time
log_path, session, workers = sys.argv[1], sys.argv[2], int(sys.argv[3])
h = logging.FileHandler(log_path, encoding="utf-8")
h.setFormatter(logging.Formatter("%(created).3f\t%(process)d\t%(name)s\t%(message)s"))
pkg = logging.getLogger("embodmocap")
pkg.addHandler(h); pkg.setLevel(logging.INFO)
from embodmocap.pipeline import PipelineConfig, run_session
kw = {"workers": workers} if "workers" in inspect.signature(run_session).parameters else {}
say = logging.getLogger("embodmocap.timeline").info
say("run start")
res = run_session(PipelineConfig(), session, on_progress=say, **kw)
say("run end ok=%s" % res.ok)
sys.exit(0 if res.ok else 1)
"""

STEP = re.compile(r"^(?P<label>(scene|sequence) \S+): (?P<step>\S+) done in (?P<s>[0-9.]+) s")
JOB = re.compile(r"^(?P<target>(scene|sequence) \S+): (?P<stage>\w+) (\.\.\.|done in (?P<s>[0-9.]+) s)")


def _ticks(pid: int) -> tuple[int, int, str] | None:
    """(utime + stime ticks, RSS kB, command name) of a live process."""
    try:
        stat = open(f"/proc/{pid}/stat").read()
        rest = stat[stat.rindex(")") + 2:].split()
        rss = int(rest[21]) * os.sysconf("SC_PAGE_SIZE") // 1024
        cmd = open(f"/proc/{pid}/cmdline", "rb").read().replace(b"\0", b" ").decode(errors="replace")
        return int(rest[11]) + int(rest[12]), rss, cmd
    except (OSError, ValueError, IndexError):
        return None


def _machine() -> tuple[int, int]:
    """(busy, total) jiffies of the whole machine."""
    f = [int(x) for x in open("/proc/stat").readline().split()[1:]]
    idle = f[3] + f[4]
    return sum(f[:8]) - idle, sum(f[:8])


def record(session: Path, src: str | None, workers: int, log_path: Path, every: float) -> dict:
    env = dict(os.environ)
    if src:
        env["PYTHONPATH"] = src
    log_path.unlink(missing_ok=True)
    samples = []
    t0 = time.time()
    proc = subprocess.Popen([sys.executable, "-c", _CODE, str(log_path), str(session), str(workers)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    def sample() -> None:
        t = time.time() - t0
        procs = {}
        for p in _tree(proc.pid):
            got = _ticks(p)
            if got is not None:
                procs[p] = got
        samples.append({"t": t, "machine": _machine(), "procs": {p: v[:2] for p, v in procs.items()},
                        "cmd": {p: v[2][:200] for p, v in procs.items()}})

    out, _ = communicate_sampling(proc, sample, every)
    wall = time.time() - t0
    recs = []
    for line in log_path.read_text(encoding="utf-8").splitlines():
        parts = line.split("\t", 3)
        if len(parts) == 4:
            try:
                recs.append({"t": float(parts[0]) - t0, "pid": int(parts[1]), "name": parts[2], "msg": parts[3]})
            except ValueError:
                pass
    return {"wall_s": wall, "rc": proc.returncode, "tail": out[-3000:], "samples": samples, "records": recs,
            "root": proc.pid, "hz": os.sysconf("SC_CLK_TCK"), "load_start": None}


def _cpu_at(samples, pid: int, t: float, hz: int) -> float:
    """Cumulative CPU seconds of ``pid`` at time ``t`` (linear between samples; its last sample after it ended)."""
    prev = None
    for s in samples:
        v = s["procs"].get(pid)
        if v is None:
            continue
        if s["t"] >= t:
            if prev is None:
                return v[0] / hz
            (t1, c1) = prev
            return (c1 + (v[0] / hz - c1) * (t - t1) / max(1e-9, s["t"] - t1))
        prev = (s["t"], v[0] / hz)
    return prev[1] if prev else 0.0


def _role(cmd: str, pid: int, root: int) -> str:
    if pid == root:
        return "main"
    if "resource_tracker" in cmd:
        return "tracker"
    if "spawn_main" in cmd:
        return "worker"
    return cmd.split()[0].rsplit("/", 1)[-1] if cmd else "?"


def report(data: dict, cores: int, bin_s: float) -> None:
    samples, recs, hz, root = data["samples"], data["records"], data["hz"], data["root"]
    for s in samples:  # JSON round trip turns pid keys into strings
        s["procs"] = {int(k): v for k, v in s["procs"].items()}
        s["cmd"] = {int(k): v for k, v in s.get("cmd", {}).items()}
    cmds = {}
    for s in samples:  # a process's first command line (an ended, unreaped one shows none)
        for p, c in s["cmd"].items():
            if c and p not in cmds:
                cmds[p] = c
        for p in s["procs"]:
            cmds.setdefault(p, "")
    roles, n = {}, 0
    for pid in sorted(cmds, key=lambda p: min(s["t"] for s in samples if p in s["procs"])):
        r = _role(cmds[pid], pid, root)
        if r == "worker":
            n += 1
            r = f"worker{n}"
        roles[pid] = r
    cpu_end = {p: max(s["procs"][p][0] for s in samples if p in s["procs"]) / hz for p in roles}
    wall = data["wall_s"]
    print(f"wall {wall:.1f} s; CPU of the processes (last samples) {sum(cpu_end.values()):.1f} s: "
          + ", ".join(f"{roles[p]} {c:.1f}" for p, c in cpu_end.items()))
    print("\n| start s | end s | process | step | wall s | CPU s | CPU / wall |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for r in recs:
        m = STEP.match(r["msg"])
        if not m:
            continue
        end, dur = r["t"], float(m["s"])
        c = _cpu_at(samples, r["pid"], end, hz) - _cpu_at(samples, r["pid"], end - dur, hz)
        rows.append((end - dur, end, roles.get(r["pid"], str(r["pid"])), f"{m['label']} {m['step']}", dur, c))
    for a, b, who, what, dur, c in sorted(rows):
        print(f"| {a:.1f} | {b:.1f} | {who} | {what} | {dur:.1f} | {c:.1f} | {c / max(dur, 1e-9):.2f} |")
    # The chain after Stage I and II (registration, the rest of Stage III, Stage IV) of each sequence:
    # its wall from the register job's start to the motion job's end, and the seconds between its
    # steps where none of them ran (job start-up: imports, upstream checks; a job waiting for a worker).
    for r in recs:
        m = JOB.match(r["msg"])
        if not (m and m["stage"] == "register" and m["s"] is None):
            continue
        target, t_reg = m["target"], r["t"]
        ends = [x["t"] for x in recs if (j := JOB.match(x["msg"])) and j["target"] == target
                and j["stage"] == "motion" and j["s"] is not None]
        chain = sorted((a, b) for a, b, _, what, *_ in rows if what.startswith(target + " ") and a >= t_reg - 0.05
                       and what.split()[-1] not in ("scene", "sequence", "register", "calibrate", "motion"))
        if not ends or not chain:
            continue
        gaps, cur = [], t_reg
        for a, b in chain:
            if a > cur:
                gaps.append((cur, a))
            cur = max(cur, b)
        if ends[0] > cur:
            gaps.append((cur, ends[0]))
        print(f"\nchain of {target}: register job start {t_reg:.1f} s -> motion done {ends[0]:.1f} s: "
              f"{ends[0] - t_reg:.1f} s, of which {sum(b - a for a, b in gaps):.1f} s between its steps ("
              + ", ".join(f"{a:.1f}-{b:.1f}" for a, b in gaps if b - a >= 0.05) + ")")
    print("\n| time s | job line |")
    print("|---|---|")
    for r in recs:
        if JOB.match(r["msg"]) or r["name"] == "embodmocap.timeline":
            print(f"| {r['t']:.1f} | {r['msg']} |")
    # CPU per bin per process, and the machine.
    nb = int(wall // bin_s) + 1
    print(f"\nCPU per {bin_s:g} s bin (0-9: tenths of a core, '.' < 5 %, ' ' not alive); machine = every process on the box")
    for p in roles:
        line = ""
        for b in range(nb):
            alive = any(p in s["procs"] and b * bin_s <= s["t"] < (b + 1) * bin_s for s in samples)
            if not alive:
                line += " "
                continue
            c = (_cpu_at(samples, p, (b + 1) * bin_s, hz) - _cpu_at(samples, p, b * bin_s, hz)) / bin_s
            line += "." if c < 0.05 else str(min(9, int(c * 10 + 0.5)))
        print(f"{roles[p]:>9} |{line}|")
    mline, busy_other = "", 0.0
    ours_total = 0.0
    for b in range(nb):
        ss = [s for s in samples if b * bin_s <= s["t"] < (b + 1) * bin_s]
        if len(ss) < 2:
            mline += " "
            continue
        (b0, t0), (b1, t1) = ss[0]["machine"], ss[-1]["machine"]
        ncpu = os.cpu_count() or cores
        frac = (b1 - b0) / max(1, t1 - t0) * ncpu  # cores busy on the machine
        mline += str(min(9, int(frac / cores * 10 + 0.5)))
        ours = sum(_cpu_at(samples, p, ss[-1]["t"], hz) - _cpu_at(samples, p, ss[0]["t"], hz) for p in roles)
        dt = ss[-1]["t"] - ss[0]["t"]
        ours_total += ours
        busy_other += max(0.0, frac * dt - ours)
    print(f"{'machine':>9} |{mline}| (tenths of {cores} cores)")
    peak = max(samples, key=lambda s: sum(v[1] for v in s["procs"].values()))
    own = {p: max((s["procs"][p][1] for s in samples if p in s["procs"]), default=0) // 1024 for p in roles}
    print(f"\npeak of the processes' RSS sum: {sum(v[1] for v in peak['procs'].values()) // 1024} MB at {peak['t']:.0f} s ("
          + ", ".join(f"{roles.get(p, p)} {v[1] // 1024}" for p, v in peak["procs"].items())
          + "); each process's own peak: " + ", ".join(f"{roles[p]} {m}" for p, m in own.items()))
    ours = sum(cpu_end.values())
    print(f"\nidle core-seconds of the run on {cores} cores: {cores * wall - ours:.1f} of {cores * wall:.1f} "
          f"({100 * (1 - ours / (cores * wall)):.0f} %); other processes on the machine meanwhile: {busy_other:.1f} core-s "
          f"(mean {busy_other / wall:.2f} cores)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("inputs", type=Path, help="a session's inputs (copied; stage outputs in it are left out)")
    ap.add_argument("--work", type=Path, required=True, help="folder for the copy, the log and the JSON")
    ap.add_argument("--src", default=None, help="src folder of the code to run (default: this checkout's)")
    ap.add_argument("--workers", type=int, default=0, help="run_session's workers (0: its default)")
    ap.add_argument("--every", type=float, default=0.25, help="sampling period, s")
    ap.add_argument("--bin", type=float, default=2.0, help="seconds per character of the strips")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--report", type=Path, default=None, help="only print the report of a saved JSON")
    args = ap.parse_args()
    if args.report:
        report(json.loads(args.report.read_text()), args.cores, args.bin)
        return
    src = args.src or str(Path(__file__).resolve().parents[1] / "src")
    args.work.mkdir(parents=True, exist_ok=True)
    sess = args.work / "session"
    if sess.exists():
        shutil.rmtree(sess)
    # Hard links (every stage writes by rename, so the inputs are never written through them).
    subprocess.run(["cp", "-al", str(args.inputs), str(sess)], check=True)
    for old in ("scenes", "sequences", "evaluation.json"):
        if (sess / old).is_dir():
            shutil.rmtree(sess / old)
        elif (sess / old).exists():
            (sess / old).unlink()
    load0 = os.getloadavg()
    data = record(sess, src, args.workers, args.work / "run.log", args.every)
    data["load_start"], data["load_end"], data["src"], data["workers"] = load0, os.getloadavg(), src, args.workers
    (args.work / "timeline.json").write_text(json.dumps(data))
    print(f"src {src}, workers {args.workers}, load average at start {load0}, at the end {data['load_end']}, rc {data['rc']}")
    if data["rc"] != 0:
        print(data["tail"])
    report(data, args.cores, args.bin)


if __name__ == "__main__":
    main()
