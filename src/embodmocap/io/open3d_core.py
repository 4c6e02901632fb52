"""Open3D without its machine-learning package: ``from embodmocap.io.open3d_core import open3d``.

``import open3d`` (0.19) ends with ``import open3d.ml``, which pulls in scikit-learn: more than
half of the import's CPU (2.2 s vs 0.95 s on a quiet core; 6.9 s vs ~2 s on the loaded 2-core
box) for a package no part of embodmocap uses. Importing this module first puts an empty
placeholder where ``open3d.ml`` would go, so Open3D's own ``import open3d.ml`` finds it and skips
the package; everything else of Open3D (geometry, pipelines, t, io) is untouched. When Open3D is
already imported (by anything), this changes nothing.
"""

from __future__ import annotations

import sys
import types

if "open3d" not in sys.modules:
    _ml = types.ModuleType("open3d.ml", "placeholder: Open3D-ML is not used by embodmocap (see embodmocap.io.open3d_core)")
    sys.modules.setdefault("open3d.ml", _ml)

import open3d  # noqa: E402

__all__ = ["open3d"]
