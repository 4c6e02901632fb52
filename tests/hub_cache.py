"""Put a saved model into a Hugging Face hub cache the way a download leaves it (for tests).

There is no network to the Hub in the tests, so the "first run" of a model given by hub id (the
download) is replaced by writing the same files a download writes:

    CACHE/models--ORG--NAME/
        blobs/<hash>                      file contents (sha256 for weights, git blob sha1 otherwise)
        snapshots/<commit>/<file>         relative symlinks to the blobs
        refs/main                         the commit the branch points at
        trees/<commit>.json               the repository's file listing (huggingface_hub >= 1.x)

The listing holds every file of the "repository", including ``extra_files`` that a filtered
download did not fetch (like the original training checkpoints of real model repositories), so an
offline look-up must ask for the same subset as the download did. ``huggingface_hub.scan_cache_dir``
reads the result back as a valid cached repository (the tests check that too).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path


def _git_blob_sha1(data: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


def place_in_hub_cache(model_dir: Path, repo_id: str, cache: Path, *, extra_files: dict[str, int] | None = None,
                       drop: tuple[str, ...] = ()) -> Path:
    """Copy the files of ``model_dir`` into ``cache`` as the snapshot of ``repo_id``; return the snapshot.

    ``extra_files``: name -> size of repository files listed in the tree but not downloaded.
    ``drop``: files of ``model_dir`` listed in the tree but left out of the snapshot (a partial download).
    """
    repo = cache / ("models--" + repo_id.replace("/", "--"))
    files = {p.name: p.read_bytes() for p in sorted(model_dir.iterdir()) if p.is_file()}
    listing: dict[str, dict] = {}
    for name, data in files.items():
        entry = {"size": len(data), "blob_id": _git_blob_sha1(data)}
        if name.endswith(".safetensors"):
            entry.update(lfs_sha256=hashlib.sha256(data).hexdigest(), lfs_size=len(data))
        listing[name] = entry
    for name, size in (extra_files or {}).items():
        listing[name] = {"size": size, "blob_id": hashlib.sha1(name.encode()).hexdigest(),
                         "lfs_sha256": hashlib.sha256(name.encode()).hexdigest(), "lfs_size": size}
    commit = hashlib.sha1(json.dumps(listing, sort_keys=True).encode()).hexdigest()
    snapshot = repo / "snapshots" / commit
    (repo / "blobs").mkdir(parents=True, exist_ok=True)
    snapshot.mkdir(parents=True, exist_ok=True)
    for name, data in files.items():
        if name in drop:
            continue
        blob = listing[name].get("lfs_sha256") or listing[name]["blob_id"]
        (repo / "blobs" / blob).write_bytes(data)
        os.symlink(os.path.join("..", "..", "blobs", blob), snapshot / name)
    (repo / "refs").mkdir(exist_ok=True)
    (repo / "refs" / "main").write_text(commit)
    (repo / "trees").mkdir(exist_ok=True)
    (repo / "trees" / f"{commit}.json").write_text(json.dumps({"format_version": 1, "files": listing}, indent=1))
    return snapshot
