"""embodmocap: metric, gravity-aligned 4D human-scene capture from two handheld iPhones."""

import logging
import os

# OpenMP threads (Open3D, torch) spin-wait by default; on a busy 2-core machine that made a small
# TSDF integration ~30x slower (measured: 10 s vs 0.3 s for 30 frames). The policy is read when
# the OpenMP runtime loads, so it is set here, before anything imports open3d; setdefault keeps a
# user's own choice.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"

#: The package logger; modules use ``logging.getLogger(__name__)`` under it, never the root logger.
logger = logging.getLogger("embodmocap")
logger.addHandler(logging.NullHandler())


def __getattr__(name: str):
    # ``embodmocap.run`` / ``embodmocap.load`` (the notebook API, :mod:`embodmocap.api`) are
    # imported on first use, so ``import embodmocap`` stays light for the command line.
    if name in ("run", "load"):
        from embodmocap import api

        return getattr(api, name)
    raise AttributeError(f"module 'embodmocap' has no attribute {name!r}")
