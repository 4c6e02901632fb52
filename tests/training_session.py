"""A synthetic session with every file the training export reads, written from the studio's truth.

:func:`make_stage4_session` writes Stages II-IV from the ground truth (the fit is the true body,
the cameras the true cameras); this adds what it leaves out and the training export needs:
Stage II's ``depth.npy`` (the capture's own LiDAR depth of each sequence frame, as Stage II's
``lidar`` depth writes it), ``masks.npy`` (the studio's person masks, bit-packed) and
``frame_map.json``. Used by the training export and FrameDataset tests and by
``benchmarks/bench_frame_dataset.py``. Not a test module.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from embodmocap.io.atomic import write_json
from embodmocap.io.captures import open_capture
from embodmocap.io.frame_stack import depth_mm, pack_mask, write_stack
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.manifest import load_manifest
from embodmocap.io.stage_files import read_cameras
from embodmocap.perception.precomputed import PrecomputedMasks
from embodmocap.io.stage_files import FRAME_MAP_VERSION
from embodmocap.synth.config import SynthConfig
from stage4_session import SYNTH, make_stage4_session


def make_training_session(root: Path, cfg: SynthConfig = SYNTH) -> dict:
    """Synthesise ``root`` (Stage IV from the truth, Stage I's world) and add Stage II's depth,
    masks and frame maps. Returns :func:`make_stage4_session`'s dict."""
    info = make_stage4_session(root, cfg, stage1_world=True)
    add_stage2_frames(root)
    return info


def add_stage2_frames(root: Path) -> None:
    """Write ``depth.npy``, ``masks.npy`` and ``frame_map.json`` of every view of every sequence
    from the raw captures and the precomputed masks the session's manifest names."""
    lay = SessionLayout(root)
    manifest = load_manifest(lay.manifest)
    for entry in manifest.sequences.values():
        sl = lay.sequence(entry.name)
        for v in VIEWS:
            vl = sl.view(v)
            cams = read_cameras(vl.cameras, "cameras")
            raw = np.asarray(cams.raw_frames, np.int64)
            T, W, H = len(raw), int(cams.width), int(cams.height)
            cap = open_capture(entry.views[v].capture)
            first = cap.frames.depth_m(int(raw[0]))
            with write_stack(vl.depth, (T,) + first.shape, np.uint16) as stack:
                for t, r in enumerate(raw):
                    d = np.nan_to_num(np.asarray(cap.frames.depth_m(int(r)), np.float32), nan=0.0)
                    c = cap.frames.confidence(int(r))
                    stack[t] = depth_mm(np.where(c >= 1, d, 0.0) if c is not None else d)
            masks = PrecomputedMasks(entry.views[v].masks)
            with write_stack(vl.masks, (T, H, (W + 7) // 8), np.uint8) as stack:
                for t, r in enumerate(raw):
                    stack[t] = pack_mask(masks.mask(int(r), (W, H)))
            fps = float(cams.fps) if cams.fps is not None else 1.0 / float(np.median(np.diff(cams.timestamps_s)))
            write_json(vl.frame_map, {"version": FRAME_MAP_VERSION, "fps": fps, "event_frame": int(raw[0]),
                                      "event_time_s": 0.0, "num_frames": T, "seq_times_s": (np.arange(T) / fps).tolist(),
                                      "raw_frames": raw.tolist(), "dt_s": [0.0] * T, "dropped": [False] * T})


@pytest.fixture(scope="session")
def training_export(tmp_path_factory) -> dict:
    """A tiny finished session (1 s at 10 fps, 320x240) and its training export, made once per
    test process: ``session``, ``out`` (the export folder), ``info`` (:func:`make_training_session`).
    Read only: tests that change something work on a copy."""
    from embodmocap.export.training import export_training

    session = tmp_path_factory.mktemp("training") / "session"
    info = make_training_session(session)
    out = export_training(session, out=session.parent / "export")
    return {"session": session, "out": out, "info": info}
