"""Metrics (pure functions) and reports.

:mod:`.mesh_metrics`: scene-mesh accuracy and completeness against a ground-truth mesh.
"""

