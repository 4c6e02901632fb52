"""Reliability building blocks: content fingerprints that survive copies and moves, session-relative
manifest paths, stage status and upstream checks, stale temporary files, bounded JSON, one-line
file-system errors."""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from embodmocap.errors import InputError, os_error_line
from embodmocap.io import stage_manifest as smod
from embodmocap.io.atomic import atomic_dir, atomic_path, remove_stale_temps, temp_prefix, write_json
from embodmocap.io.jsonfile import json_depth, read_json
from embodmocap.io.stage_manifest import (MANIFEST_VERSION, StageManifest, Upstream, file_digest, fingerprint,
                                          path_fingerprint, require_upstream, tracked_stage)


def _tree(root: Path) -> Path:
    (root / "sub").mkdir(parents=True)
    (root / "a.txt").write_text("alpha")
    (root / "sub" / "b.bin").write_bytes(os.urandom(3000))
    (root / ".hidden.part-1-x").write_text("temporary")  # hidden: not part of the fingerprint
    return root


def test_fingerprints_follow_content_not_mtimes_or_places(tmp_path):
    src = _tree(tmp_path / "src")
    fp = path_fingerprint(src)
    # cp -a (mtimes kept), cp -r (new mtimes), a move and a symlink: the same fingerprint.
    subprocess.run(["cp", "-a", str(src), str(tmp_path / "copy_a")], check=True)
    subprocess.run(["cp", "-r", str(src), str(tmp_path / "copy_r")], check=True)
    os.utime(tmp_path / "copy_r" / "a.txt", (1, 1))
    shutil.move(str(tmp_path / "copy_a"), str(tmp_path / "moved"))
    (tmp_path / "link").symlink_to(tmp_path / "moved")
    for other in ("copy_r", "moved", "link"):
        assert path_fingerprint(tmp_path / other) == fp, other
    # Any change of content (same size) is seen.
    (tmp_path / "moved" / "a.txt").write_text("alphA")
    assert path_fingerprint(tmp_path / "moved") != fp
    # A missing path carries its name only, never where it was looked for.
    assert path_fingerprint(tmp_path / "nowhere" / "x.npz") == ["x.npz", None]


def test_large_files_are_sampled_at_both_ends_and_inside(tmp_path, monkeypatch):
    monkeypatch.setattr(smod, "SMALL_FILE_BYTES", 1 << 16)
    monkeypatch.setattr(smod, "EDGE_BYTES", 1 << 12)
    monkeypatch.setattr(smod, "SAMPLE_BYTES", 1 << 10)
    big = tmp_path / "video.mp4"
    data = bytearray(os.urandom(1 << 20))
    big.write_bytes(data)
    d0 = file_digest(big)
    step = (len(data) - 2 * smod.EDGE_BYTES - smod.SAMPLE_BYTES) / (smod.SAMPLE_BLOCKS + 1)
    block = smod.EDGE_BYTES + int(step * 8) + 10  # inside the 8th sampled block
    for where in (0, len(data) - 1, block):  # first MiB, last MiB, a sampled block
        changed = bytearray(data)
        changed[where] ^= 0xFF
        p = tmp_path / f"v{where}.mp4"
        p.write_bytes(changed)
        assert file_digest(p) != d0, where
    shutil.copy(big, tmp_path / "copy.mp4")
    assert file_digest(tmp_path / "copy.mp4") == d0


def test_manifest_paths_are_relative_to_its_folder_whatever_the_cwd(tmp_path, monkeypatch):
    session = tmp_path / "session"
    out = session / "sequences" / "seq0"
    out.mkdir(parents=True)
    (out / "sync.json").write_text("{}")
    monkeypatch.chdir(tmp_path)
    # Outputs named relative to the current directory (as `embodmocap sequence session` does).
    sm = StageManifest(Path("session/sequences/seq0/manifest.json"), "sequence", {}, root=Path("session"))
    sm.record("sync", "fp", [Path("session/sequences/seq0/sync.json")], 0.1)
    data = json.loads((out / "manifest.json").read_text())
    assert data["steps"]["sync"]["outputs"] == ["sync.json"]
    assert data["version"] == MANIFEST_VERSION
    # Another cwd, a relative path from elsewhere, a moved copy (cp -r: new mtimes), a symlink.
    monkeypatch.chdir(out)
    assert StageManifest(Path("manifest.json"), "sequence", {}).is_current("sync", "fp")
    subprocess.run(["cp", "-r", str(session), str(tmp_path / "copy")], check=True)
    (tmp_path / "via").symlink_to(tmp_path / "copy")
    for root in (tmp_path / "copy", tmp_path / "via"):
        monkeypatch.chdir(root / "sequences")
        assert StageManifest(Path("seq0/manifest.json"), "sequence", {}).is_current("sync", "fp"), root
    # An output whose content changed, or that is gone, redoes the step.
    (tmp_path / "copy" / "sequences" / "seq0" / "sync.json").write_text("{ }")
    assert not StageManifest(tmp_path / "copy/sequences/seq0/manifest.json", "sequence", {}).is_current("sync", "fp")


def test_old_manifest_version_redoes_its_steps(tmp_path):
    man = tmp_path / "manifest.json"
    (tmp_path / "mesh.ply").write_text("x")
    man.write_text(json.dumps({"version": 1, "stage": "scene", "steps": {"mesh": {"fingerprint": "fp", "outputs": ["mesh.ply"]}},
                               "figures": {}}))
    # An upstream check does not refuse a stage written by an older version (nothing to judge by) ...
    require_upstream(Upstream(man, "scene", "embodmocap scene S"))
    # ... and the stage itself redoes the step.
    assert not StageManifest(man, "scene", {}).is_current("mesh", "fp")


def _stage_dir(tmp_path: Path) -> tuple[Path, Path, Path]:
    session = tmp_path / "s"
    (session / "inputs").mkdir(parents=True)
    inp = session / "inputs" / "keypoints.json"
    inp.write_text('{"people": []}')
    return session, inp, session / "stage" / "manifest.json"


def test_stage_status_and_upstream_checks(tmp_path):
    session, inp, man = _stage_dir(tmp_path)
    out = man.parent / "result.npz"

    @tracked_stage
    def stage(fail: bool = False) -> None:
        sm = StageManifest(man, "sequence", {}, inputs=[inp], root=session)
        if not sm.is_current("work", "fp"):
            out.parent.mkdir(exist_ok=True)
            out.write_bytes(b"result")
            sm.record("work", "fp", [out], 0.0)
        if fail:
            raise InputError(inp, "bad keypoints", "re-export")

    up = Upstream(man, "sequence", "embodmocap sequence S")
    require_upstream(up)  # no manifest yet: nothing to refuse
    stage()
    data = json.loads(man.read_text())
    assert data["status"] == "ok" and list(data["inputs"]) == ["../inputs/keypoints.json"]
    require_upstream(up)

    with pytest.raises(InputError):
        stage(fail=True)
    with pytest.raises(InputError, match=r"sequence stage failed in its last run \(.*bad keypoints.*run `embodmocap sequence S` first"):
        require_upstream(up)

    stage()
    inp.write_text('{"people": [ ]}')  # the input changed after the stage ran
    with pytest.raises(InputError, match="out of date: its input .*keypoints.json changed"):
        require_upstream(up)
    stage()
    require_upstream(up)
    out.write_bytes(b"tampered")  # an output changed after the stage wrote it
    with pytest.raises(InputError, match="result.npz changed since it was written"):
        require_upstream(up)

    # A run that never finished (killed) leaves "running".
    data = json.loads(man.read_text())
    data["status"] = "running"
    man.write_text(json.dumps(data))
    with pytest.raises(InputError, match="did not finish"):
        require_upstream(up)


def test_interrupted_stage_is_marked(tmp_path):
    session, inp, man = _stage_dir(tmp_path)

    @tracked_stage
    def stage() -> None:
        StageManifest(man, "motion", {}, root=session)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        stage()
    assert json.loads(man.read_text())["status"] == "interrupted"


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_stale_temporary_files_of_dead_writers_are_removed(tmp_path):
    dead = _dead_pid()
    (tmp_path / "sub").mkdir()
    stale_file = tmp_path / "sub" / f".mesh_raw.ply.part-{dead}-abc123.ply"
    stale_dir = tmp_path / f".sfm.part-{dead}-k2j3h4"
    legacy_dir = tmp_path / ".sfm.a1b2c3d4"  # what an earlier version left behind on kill -9
    live = tmp_path / f"{temp_prefix(tmp_path / 'x.json')}zzz.json"  # this (running) process's
    keep = tmp_path / ".gitignore"
    stale_file.write_text("half")
    for d in (stale_dir, legacy_dir):
        (d / "images").mkdir(parents=True)
    live.write_text("in progress")
    keep.write_text("*")
    removed = remove_stale_temps(tmp_path)
    assert set(removed) == {stale_file, stale_dir, legacy_dir}
    assert live.exists() and keep.exists()


def test_atomic_writers_leave_nothing_on_failure(tmp_path):
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "a.npz") as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError
    with pytest.raises(RuntimeError):
        with atomic_dir(tmp_path / "sfm") as tmp:
            (tmp / "x").write_text("half")
            raise RuntimeError
    assert list(tmp_path.iterdir()) == []


def test_bounded_json_reader(tmp_path):
    fix = "re-export the keypoints"
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 200_000 + "]" * 200_000)
    with pytest.raises(InputError, match="nested 200000 levels deep"):
        read_json(deep, max_bytes=1 << 20, what="keypoint file", fix=fix)
    huge = tmp_path / "huge.json"
    with open(huge, "wb") as f:
        f.truncate(300 << 20)  # sparse: 300 MiB by stat, no disk used; must not be read
    with pytest.raises(InputError, match=r"huge.json: keypoint file is 300.0 MiB, over the 4.0 MiB limit"):
        read_json(huge, max_bytes=4 << 20, what="keypoint file", fix=fix)
    empty = tmp_path / "empty.json"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        read_json(empty, max_bytes=1 << 20)
    bad = tmp_path / "bad.json"
    bad.write_text('{"people": [1, 2')
    with pytest.raises(InputError, match="not valid JSON"):
        read_json(bad, max_bytes=1 << 20)
    # Brackets inside strings (escaped quotes too) do not count.
    text = json.dumps({"name": "[[[[\"{{{{" * 50, "people": [[1, 2, 3]]})
    assert json_depth(text.encode()) == 3
    ok = tmp_path / "ok.json"
    ok.write_text(text)
    assert read_json(ok, max_bytes=1 << 20)["people"] == [[1, 2, 3]]
    # At the limit, with no more opening brackets than the limit (measured or not): one level too
    # many is refused, the limit itself is read.
    (tmp_path / "four.json").write_text("[[{\"a\": [1]}]]")
    with pytest.raises(InputError, match="nested 4 levels deep"):
        read_json(tmp_path / "four.json", max_bytes=1 << 20, max_depth=3)
    assert read_json(tmp_path / "four.json", max_bytes=1 << 20, max_depth=4) == [[{"a": [1]}]]


def test_os_errors_read_as_one_line():
    line = os_error_line(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/data/s/mesh_raw.ply"))
    assert line.startswith("/data/s/mesh_raw.ply: no space left") and "run the same command again" in line
    line = os_error_line(PermissionError(errno.EACCES, "Permission denied", "/data/s/evaluation.json"))
    assert "permission denied" in line and "\n" not in line


def test_fingerprint_of_identical_trees_matches_across_processes(tmp_path):
    src = _tree(tmp_path / "t")
    here = fingerprint(path_fingerprint(src))
    code = ("import sys; from embodmocap.io.stage_manifest import fingerprint, path_fingerprint; "
            "print(fingerprint(path_fingerprint(sys.argv[1])))")
    there = subprocess.run([sys.executable, "-c", code, str(src)], capture_output=True, text=True, check=True,
                           env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}).stdout.strip()
    assert here == there
    write_json(tmp_path / "t" / "new.json", {"a": 1})
    assert fingerprint(path_fingerprint(src)) != here


def test_colmap_database_reads_do_not_change_its_fingerprint(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    import hashlib

    db = tmp_path / "database.db"
    with pycolmap.Database.open(db) as d:
        d.write_camera(pycolmap.Camera(model="PINHOLE", width=64, height=48, params=[50, 50, 32, 24]))
    copy = tmp_path / "copy.db"
    shutil.copy(db, copy)
    with pycolmap.Database.open(copy) as d:  # only reads, as Stage III does ...
        assert d.num_cameras() == 1
    # ... yet SQLite's change counters moved: the bytes differ, the content fingerprint does not.
    assert hashlib.sha256(db.read_bytes()).digest() != hashlib.sha256(copy.read_bytes()).digest()
    assert file_digest(copy) == file_digest(db)
    with pycolmap.Database.open(copy) as d:
        d.write_camera(pycolmap.Camera(model="PINHOLE", width=64, height=48, params=[60, 60, 32, 24]))
    assert file_digest(copy) != file_digest(db)


def test_write_errors_name_the_destination_not_the_temporary_file(tmp_path):
    dest = tmp_path / "mesh_raw.ply"
    with pytest.raises(OSError) as info:
        with atomic_path(dest):
            raise OSError(errno.ENOSPC, "No space left on device")  # as a failed write() raises it
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(dest)
    assert os_error_line(info.value).startswith(f"{dest}: no space left on the device")
    with pytest.raises(OSError) as info:
        with atomic_dir(tmp_path / "sfm") as tmp:
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp / "database.db"))
    assert info.value.filename == str(tmp_path / "sfm" / "database.db")
    with pytest.raises(OSError) as info:
        with atomic_dir(tmp_path / "sfm") as tmp:  # shutil.copyfile names the source first
            raise OSError(errno.ENOSPC, "No space left on device", "/data/kf_1.jpg", None, str(tmp / "images" / "kf_1.jpg"))
    assert info.value.filename == str(tmp_path / "sfm" / "images" / "kf_1.jpg")
    assert list(tmp_path.iterdir()) == []
