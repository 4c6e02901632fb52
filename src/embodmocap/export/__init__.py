"""Exports of the fitted motion for downstream tools: AMASS npz, BVH, glTF, MimicKit, CSV.

``export_sequence(session, seq, to)`` reads a sequence's Stage IV outputs and writes one format;
the writers underneath take in-memory :class:`~embodmocap.types.SmplParams` (world, Z up) and a
:class:`~embodmocap.body.model.BodyModel`. Every file is written atomically. Formats are described
in ``docs/formats.md`` (section "Exports").
"""

from embodmocap.export.amass import read_amass, write_amass
from embodmocap.export.bvh import bvh_text, write_bvh
from embodmocap.export.csv_joints import joints_csv_header, write_joints_csv
from embodmocap.export.gltf import glb_document, write_glb
from embodmocap.export.mimickit import (
    HeightMap, egocentric_heightmap, mimickit_frames, read_heightmap, read_mimickit_motion, scene_heightmap,
    write_heightmap, write_mimickit, write_mimickit_motion,
)
from embodmocap.export.run import FORMATS, ExportConfig, export_sequence

__all__ = [
    "FORMATS", "ExportConfig", "HeightMap", "bvh_text", "egocentric_heightmap", "export_sequence", "glb_document",
    "joints_csv_header", "mimickit_frames", "read_amass", "read_heightmap", "read_mimickit_motion", "scene_heightmap",
    "write_amass", "write_bvh", "write_glb", "write_heightmap", "write_joints_csv", "write_mimickit",
    "write_mimickit_motion",
]
