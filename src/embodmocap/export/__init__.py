"""Exports of the fitted motion for downstream tools: AMASS npz, BVH, glTF, MimicKit, CSV.

``export_sequence(session, seq, to)`` reads a sequence's Stage IV outputs and writes one format;
the writers underneath take in-memory :class:`~embodmocap.types.SmplParams` (world, Z up) and a
:class:`~embodmocap.body.model.BodyModel`. Every file is written atomically. Formats are described
in ``docs/formats.md`` (section "Exports").
"""

# Each name is imported from its module on first use, so importing one module of the package (its
# settings, for the command line) does not load every writer's dependencies.
_WHERE = {
    "read_amass": "embodmocap.io.amass", "write_amass": "embodmocap.io.amass", "bvh_text": "bvh", "write_bvh": "bvh",
    "joints_csv_header": "csv_joints", "write_joints_csv": "csv_joints", "glb_document": "gltf", "write_glb": "gltf",
    "HeightMap": "mimickit", "egocentric_heightmap": "embodmocap.geometry.heightmap", "mimickit_frames": "mimickit",
    "read_heightmap": "embodmocap.io.heightmap_file", "read_mimickit_motion": "mimickit", "scene_heightmap": "mimickit",
    "write_heightmap": "mimickit", "write_mimickit": "mimickit", "write_mimickit_motion": "mimickit",
    "trc_text": "trc", "write_trc": "trc", "smplx_arrays": "smplx_npz", "write_smplx": "smplx_npz",
    "FORMATS": "run", "export_sequence": "run", "ExportConfig": "config",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name in _WHERE:
        import importlib

        mod = _WHERE[name] if "." in _WHERE[name] else f"embodmocap.export.{_WHERE[name]}"
        return getattr(importlib.import_module(mod), name)
    raise AttributeError(f"module 'embodmocap.export' has no attribute {name!r}")
