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


