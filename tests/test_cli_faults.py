"""One-line errors from the command line for file-system faults: a session folder that cannot be
written is refused by every writing command before any work starts (read-only mount, permission
denied), and `inspect` lists every problem of a session at once."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from embodmocap.cli import main

WRITING = [["scene"], ["sequence"], ["calibrate"], ["motion"], ["run"], ["evaluate"], ["report"],
           ["export", "--to", "csv"], ["render"]]

# Runs every writing command in-process on SESSION and prints (status, stderr) of each as JSON.
_SCRIPT = """
import contextlib, io, json, sys
from embodmocap.cli import main
out = []
for cmd in json.loads(sys.argv[2]):
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = main([cmd[0], sys.argv[1], *cmd[1:]])
    out.append([rc, err.getvalue()])
print(json.dumps(out))
"""


def _session(parent: Path) -> Path:
    root = parent / "session"
    root.mkdir()
    (root / "session.toml").write_text('version = 1\n[scenes.scene0]\ncapture = "captures/scene0"\n')
    (root / "sequences" / "seq0").mkdir(parents=True)
    return root


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}


def _run_all(session: Path, prefix: list[str]) -> list[tuple[int, str]]:
    res = subprocess.run([*prefix, sys.executable, "-c", _SCRIPT, str(session), json.dumps(WRITING)],
                         capture_output=True, text=True, env=_env(), timeout=600)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout.strip().splitlines()[-1])


def _check(results, session: Path, reason: str) -> None:
    for cmd, (rc, err) in zip(WRITING, results):
        lines = [line for line in err.splitlines() if line.strip()]
        assert rc == 2 and len(lines) == 1, (cmd, err)
        assert lines[0].startswith(f"error: {session}") and "cannot be written" in lines[0] and reason in lines[0], (cmd, err)
        assert "copy the session to a folder you own" in lines[0]


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("unshare") is None, reason="read-only bind mount needs root or user namespaces")
def test_read_only_session_is_refused_by_every_writing_command(tmp_path):
    session = _session(tmp_path)
    script = f'mount --bind "{session}" "{session}" && mount -o remount,ro,bind "{session}" && exec "$@"'
    _check(_run_all(session, ["unshare", "-rm", "sh", "-c", script, "sh"]), session, "Read-only file system")
    assert not any(session.rglob(".*"))  # nothing written, not even a probe


def test_permission_denied_is_refused_by_every_writing_command():
    # A folder another user owns, read-only for us: as root, run as 'nobody' (root may write anywhere).
    base = Path(tempfile.mkdtemp(dir="/tmp"))
    try:
        os.chmod(base, 0o755)
        session = _session(base)
        if os.geteuid() == 0:
            if shutil.which("setpriv") is None:
                pytest.skip("running as root without setpriv")
            os.chmod(session / "sequences", 0o755)
            prefix = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]
        else:
            os.chmod(session, 0o555)
            prefix = []
        _check(_run_all(session, prefix), session, "Permission denied")
    finally:
        os.chmod(base / "session", 0o755) if (base / "session").exists() else None
        shutil.rmtree(base)


def test_debug_keeps_the_traceback(tmp_path, capsys):
    missing = tmp_path / "nowhere"
    assert main(["evaluate", str(missing)]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    with pytest.raises(Exception):
        main(["evaluate", str(missing), "--debug"])


def test_inspect_lists_every_session_problem_at_once(tmp_path):
    from embodmocap.check.inspect import inspect_path
    from embodmocap.io.layout import SessionLayout
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    cfg = SynthConfig(seconds=1.0, scene_seconds=1.0, fps=10, width=160, height=120, depth_width=64, depth_height=48)
    root = tmp_path / "s"
    synthesize(cfg, root)
    text, problems = inspect_path(root)
    assert problems == [], text
    lay = SessionLayout(root)
    empty = lay.perception(cfg.sequence_name, "v1").keypoints_json(3)
    empty.write_bytes(b"")
    nested = lay.perception(cfg.sequence_name, "v2").keypoints_json(4)
    nested.write_text("[" * 50_000 + "]" * 50_000)
    mask = lay.perception(cfg.sequence_name, "v2").mask_png(2)
    mask.write_bytes(b"GIF89a not a png")
    toml = lay.manifest
    toml.write_text(toml.read_text().replace('body_model = "body_model.npz"', 'body_model = "/etc/passwd"'))
    text, problems = inspect_path(root)
    joined = "\n".join(problems)
    assert len(problems) == 4, text
    for needle in (f"{empty}: keypoint file is empty", f"{nested}: keypoint file is nested 50000 levels deep",
                   f"{mask}: not a PNG or JPEG image", "/etc/passwd: unknown body model file type"):
        assert needle in joined, text


needs_tiny_disk = pytest.mark.skipif(
    shutil.which("unshare") is None or subprocess.run(["unshare", "-rm", "true"], capture_output=True).returncode != 0,
    reason="needs user + mount namespaces (unshare -rm) for a small file system")


def _on_tiny_disk(folder, code: str) -> tuple[subprocess.CompletedProcess, list[str]]:
    """Run Python ``code`` (argv[1] = ``folder``) with a 1 MiB tmpfs mounted on ``folder``; returns
    the process and its output lines, the last ones being what was left on that disk."""
    script = f'mount -t tmpfs -o size=1m tmpfs "{folder}" && "$@"; rc=$?; ls -A "{folder}"; exit $rc'
    res = subprocess.run(["unshare", "-rm", "sh", "-c", script, "sh", sys.executable, "-c", code, str(folder)],
                         capture_output=True, text=True, env=_env(), timeout=300)
    return res, res.stdout.splitlines()


@needs_tiny_disk
def test_full_disk_under_a_memory_mapped_stack_is_an_error_not_sigbus(tmp_path):
    # Stage II writes masks and depth through memory maps; on a full disk that used to be SIGBUS.
    code = ("import numpy as np, sys\n"
            "from embodmocap.io.frame_stack import write_stack\n"
            "try:\n"
            "    with write_stack(sys.argv[1] + '/depth.npy', (64, 192, 256), np.uint16) as s:\n"
            "        s[:] = 1\n"
            "except OSError as e:\n"
            "    print('OSError', e.errno, e.filename); sys.exit(2)\n")
    res, lines = _on_tiny_disk(tmp_path, code)
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)  # -7 would be SIGBUS
    first, *left = lines
    assert first == f"OSError 28 {tmp_path}/depth.npy" and left == []  # no partial file left


@needs_tiny_disk
def test_sfm_refuses_to_start_on_a_disk_too_small(tmp_path):
    # COLMAP aborts the whole process (SIGABRT, a C++ stack trace) when its database meets a full
    # disk, so SfM checks the free space first.
    pytest.importorskip("pycolmap")
    code = ("import numpy as np, sys\n"
            "from embodmocap.errors import InputError\n"
            "from embodmocap.scene.sfm import build_sparse_model\n"
            "from embodmocap.types import Intrinsics\n"
            "K = Intrinsics(500.0, 500.0, 319.5, 239.5, 640, 480)\n"
            "rgb = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)\n"
            "T = np.stack([np.eye(4)] * 2); T[1, 0, 3] = 0.1\n"
            "try:\n"
            "    build_sparse_model([('a', rgb), ('b', rgb)], K, T, sys.argv[1] + '/sfm')\n"
            "except InputError as e:\n"
            "    print(e); sys.exit(2)\n")
    res, lines = _on_tiny_disk(tmp_path, code)
    assert res.returncode == 2, (res.returncode, res.stdout, res.stderr)
    first, *left = lines
    assert first.startswith(f"{tmp_path}: only 1 MiB free on its disk; the sparse model of 2 key frames needs up to")
    assert "free some disk space" in first and left == []
