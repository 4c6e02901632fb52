"""Where the real test data lives: ``../shared/data`` beside the repository (as in CI), or the
workplace's ``/work/shared/data`` when the repository is a clone elsewhere."""

from __future__ import annotations

from pathlib import Path


def shared_data(name: str) -> Path:
    """The folder ``name`` of the shared real data (it may not exist: tests skip then)."""
    beside = Path(__file__).resolve().parents[2] / "shared" / "data" / name
    return beside if beside.is_dir() else Path("/work/shared/data") / name
