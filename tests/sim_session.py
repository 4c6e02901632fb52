"""Sessions for the sim tests: the tiny Stage IV session of :mod:`stage4_session` (the studio's
ground truth written as the fit), made once per test process. Not a test module."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from stage4_session import make_stage4_session


@pytest.fixture(scope="session")
def sim_session(tmp_path_factory) -> Path:
    """A finished tiny session (1 s at 10 fps, indoor studio room with furniture)."""
    root = tmp_path_factory.mktemp("sim") / "session"
    make_stage4_session(root)
    return root


def furniture(session: Path) -> dict:
    """The studio's furniture (centre_xy, yaw, size, top_z per piece) from the ground truth."""
    return json.loads((session / "ground_truth" / "ground_truth.json").read_text())["furniture"]
