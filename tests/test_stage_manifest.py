"""Resumable steps: fingerprints, skipping, and redoing what changed."""

import json
import os

from embodmocap.io.stage_manifest import StageManifest, fingerprint, path_fingerprint


def test_fingerprint_changes_with_inputs(tmp_path):
    f = tmp_path / "a.txt"
    f.write_text("one")
    fp1 = fingerprint({"voxel": 0.01}, path_fingerprint(f))
    assert fp1 == fingerprint({"voxel": 0.01}, path_fingerprint(f))
    assert fp1 != fingerprint({"voxel": 0.02}, path_fingerprint(f))
    f.write_text("three")  # new size and mtime
    assert fp1 != fingerprint({"voxel": 0.01}, path_fingerprint(f))
    d = tmp_path / "d"
    d.mkdir()
    (d / "x").write_text("1")
    before = path_fingerprint(d)
    (d / "y").write_text("2")
    assert path_fingerprint(d) != before


def test_folder_fingerprint_lists_what_it_reads(tmp_path):
    """A folder's fingerprint: every file below it by relative path, size and content digest;
    hidden names left out, a link to a file followed, a link to a folder not entered, a dangling
    link ignored; the same digest as the file alone, and the same list for a moved copy."""
    d = tmp_path / "cap"
    (d / "depth").mkdir(parents=True)
    (d / ".tmp").mkdir()
    (d / "depth" / "000001.png").write_bytes(b"a" * 10)
    (d / "rgb.mp4").write_bytes(b"video")
    (d / ".partial").write_text("x")
    (d / ".tmp" / "q").write_text("y")
    other = tmp_path / "other"
    other.mkdir()
    (other / "w").write_text("zz")
    os.symlink(other, d / "linked_folder")
    os.symlink("rgb.mp4", d / "linked_file")
    os.symlink(tmp_path / "nowhere", d / "dangling")
    fp = path_fingerprint(d)
    assert [(r, n) for r, n, _ in fp] == [("depth/000001.png", 10), ("linked_file", 5), ("rgb.mp4", 5)]
    assert fp[1][2] == fp[2][2] == path_fingerprint(d / "rgb.mp4")[2]
    assert fp[0][2] != fp[2][2]
    moved = tmp_path / "moved"
    os.rename(d, moved)
    assert path_fingerprint(moved) == fp


def test_steps_are_skipped_until_outputs_or_fingerprints_change(tmp_path):
    man = tmp_path / "manifest.json"
    out = tmp_path / "mesh.ply"
    sm = StageManifest(man, "scene", {"a": 1})
    assert not sm.is_current("mesh", "fp1")
    out.write_text("mesh")
    sm.record("mesh", "fp1", [out], 1.5, {"faces": 10})
    # A new run (new process) reads the manifest back.
    sm2 = StageManifest(man, "scene", {"a": 1})
    assert sm2.is_current("mesh", "fp1")
    assert not sm2.is_current("mesh", "fp2")
    assert sm2.figures() == {"faces": 10}
    data = json.loads(man.read_text())
    assert data["steps"]["mesh"]["outputs"] == ["mesh.ply"] and data["config"] == {"a": 1}
    os.remove(out)
    assert not StageManifest(man, "scene", {"a": 1}).is_current("mesh", "fp1")


def test_corrupt_or_foreign_manifest_means_redo(tmp_path):
    man = tmp_path / "manifest.json"
    man.write_text("{not json")
    assert not StageManifest(man, "scene", {}).is_current("x", "fp")
    man.write_text(json.dumps({"version": 1, "stage": "other", "steps": {"x": {"fingerprint": "fp", "outputs": []}}}))
    assert not StageManifest(man, "scene", {}).is_current("x", "fp")




def test_folder_fingerprint_lists_every_regular_file_below_it(tmp_path):
    """What a folder's fingerprint holds, entry by entry: the relative path (``/``-separated), size
    and digest of every regular file at any depth, sorted; hidden files and folders left out; a
    link to a file counts as that file, a dangling link and what a linked folder holds do not."""
    from embodmocap.io.stage_manifest import file_digest

    d = tmp_path / "cap"
    (d / "depth" / "deeper").mkdir(parents=True)
    (d / ".tmp").mkdir()
    (d / "b.csv").write_text("1,2\n")
    (d / "depth" / "000001.png").write_bytes(b"\x89PNG one")
    (d / "depth" / "deeper" / "z.bin").write_bytes(os.urandom(100))
    (d / ".hidden").write_text("x")
    (d / ".tmp" / "a.txt").write_text("x")
    (d / "linked.csv").symlink_to(d / "b.csv")
    (d / "dangling").symlink_to(d / "nowhere")
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "c.txt").write_text("c")
    (d / "dirlink").symlink_to(tmp_path / "elsewhere")
    expected = sorted([rel, (d / rel).stat().st_size, file_digest(d / rel)]
                      for rel in ("b.csv", "depth/000001.png", "depth/deeper/z.bin", "linked.csv"))
    assert path_fingerprint(d) == expected
    assert path_fingerprint(str(d) + "/") == expected  # however the folder is named
