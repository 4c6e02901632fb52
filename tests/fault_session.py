"""Helpers of the slow reliability tests (fault injection, determinism): a small synthetic session,
the CLI in a subprocess, and a content snapshot of every output for comparing two runs.

Not a test module (no ``test_`` prefix); test modules import it.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

from embodmocap.io.stage_manifest import file_digest
from embodmocap.synth.config import SynthConfig

#: Small enough for every stage to run in about a minute on 2 cores, large enough for Stage III to
#: register (the calibrate stage test uses the same capture).
SYNTH = SynthConfig(seed=5, seconds=2.0, scene_seconds=10.0)

#: Stage settings of `embodmocap run` for that session (coarser TSDF, fewer frames to register).
RUN_OPTIONS = ("--scene.voxel-m-indoor", "0.02", "--scene.sfm.max-images", "60",
               "--calibrate.register.num-frames", "24", "--calibrate.chamfer-frames", "10")

#: The same settings for the single-stage commands.
STAGE_OPTIONS = {
    "scene": ("--voxel-m-indoor", "0.02", "--sfm.max-images", "60"),
    "sequence": (),
    "calibrate": ("--register.num-frames", "24", "--chamfer-frames", "10"),
    "motion": (),
}

#: Output files (relative to the session) of each stage, for deleting them to rerun a stage.
STAGE_OUTPUTS = {
    "scene": ("scenes",),
    "sequence": ("sequences",),
    "calibrate": ("sequences/seq0/calibrate_manifest.json", "sequences/seq0/calibration.json",
                  "sequences/seq0/v1/registration.npz", "sequences/seq0/v2/registration.npz",
                  "sequences/seq0/v1/cameras_world.npz", "sequences/seq0/v2/cameras_world.npz"),
    "motion": ("sequences/seq0/motion_manifest.json", "sequences/seq0/keypoints3d.npz", "sequences/seq0/smpl_fit.npz",
               "sequences/seq0/smpl_world.npz", "sequences/seq0/joints_world.npz",
               "sequences/seq0/v1/cameras_final.npz", "sequences/seq0/v2/cameras_final.npz"),
}
STAGES = ("scene", "sequence", "calibrate", "motion")


def env() -> dict:
    """The environment of a CLI subprocess: this checkout's package first, one OpenMP thread."""
    return {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p), "OMP_NUM_THREADS": "1"}


def cli(*args: str, cwd: Path | None = None, timeout: float = 1800, prefix: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    """Run ``embodmocap ARGS`` to the end; stdout and stderr together in ``.stdout``."""
    return subprocess.run([*prefix, sys.executable, "-m", "embodmocap.cli", *args], cwd=cwd, env=env(),
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=timeout)


def popen(*args: str) -> subprocess.Popen:
    # SIGINT back to its default in the child: a test run started in the background of a
    # non-interactive shell inherits SIGINT ignored, and Python then never raises KeyboardInterrupt.
    import signal

    return subprocess.Popen([sys.executable, "-m", "embodmocap.cli", *args], env=env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, bufsize=1,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def remove_outputs(root: Path, stages) -> None:
    import shutil

    for st in stages:
        for rel in STAGE_OUTPUTS[st]:
            p = root / rel
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()


def _plain_json(obj, root: str):
    """JSON content without timings, with the session's own path written as ``<session>``."""
    if isinstance(obj, dict):
        return {k: _plain_json(v, root) for k, v in obj.items() if "seconds" not in k and k not in ("finished", "ended")}
    if isinstance(obj, list):
        return [_plain_json(v, root) for v in obj]
    if isinstance(obj, str):
        # Paths into a session (e.g. keyframes.json's capture) as seen from the session: a copy
        # that was not rerun still names the folder it was copied from.
        m = re.match(r"^/.*?/((?:captures|perception|scenes|sequences)/.*)$", obj)
        return f"<session>/{m.group(1)}" if m else obj.replace(root, "<session>")
    return obj


def snapshot(root: Path, under: tuple[str, ...] = ("scenes", "sequences")) -> dict[str, object]:
    """Every output file's content, comparable across runs and session folders: arrays of ``.npz``
    files (their zip headers carry write times), JSON without timings, other files by content
    (SQLite change counters left out). Stage manifests are left out (they hold timings and dates)."""
    root = Path(root)
    out: dict[str, object] = {}
    for top in under:
        for p in sorted((root / top).rglob("*")):
            rel = p.relative_to(root).as_posix()
            if not p.is_file() or any(part.startswith(".") for part in p.relative_to(root).parts) or "manifest" in p.name:
                continue
            if p.suffix == ".npz":
                with np.load(p, allow_pickle=False) as z:
                    out[rel] = {k: (str(z[k].dtype), z[k].shape, hashlib.sha256(np.ascontiguousarray(z[k]).tobytes()).hexdigest())
                                for k in sorted(z.files)}
            elif p.suffix == ".json":
                out[rel] = _plain_json(json.loads(p.read_text()), str(root))
            else:
                out[rel] = file_digest(p)
    return out


def differences(a: dict, b: dict) -> list[str]:
    """Files that differ between two snapshots (names only, with the differing array keys)."""
    bad = []
    for k in sorted(set(a) | set(b)):
        if a.get(k) != b.get(k):
            if isinstance(a.get(k), dict) and isinstance(b.get(k), dict) and k.endswith(".npz"):
                keys = [x for x in set(a[k]) | set(b[k]) if a[k].get(x) != b[k].get(x)]
                bad.append(f"{k} {sorted(keys)}")
            else:
                bad.append(k)
    return bad


def stale_temps(root: Path) -> list[Path]:
    """Temporary files or folders left anywhere in the session."""
    return [p for p in Path(root).rglob("*") if p.name.startswith(".") and (".part-" in p.name or p.name.startswith(".sfm."))]
