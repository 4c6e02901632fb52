"""One processed session read for Stage IV re-fits in memory (shared by the re-fit benchmarks)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass
class Stage4Session:
    """What a re-fit of a session's Stage IV needs: its first sequence's name, the body model, the
    truth, the benchmark's reading context, both views' cameras and keypoints on view 1's instants
    (as Stage IV: the sub-frame sync), the frame count and the keypoint layout."""

    seq: str
    gender: str | None
    model: object
    truth: object
    ctx: object
    cams: dict
    kps: dict
    T: int
    layout: str


def stage4_session(path: str | Path) -> Stage4Session:
    from embodmocap.body.model import load_body_model
    from embodmocap.evaluate.benchmark import _Context
    from embodmocap.evaluate.session import sequence_truth
    from embodmocap.io.layout import VIEWS, SessionLayout
    from embodmocap.io.manifest import load_manifest
    from embodmocap.io.stage_files import read_cameras, read_keypoints2d
    from embodmocap.motion.stage import keypoint_layout
    from embodmocap.sequence.subframe import synced_views

    lay = SessionLayout(Path(path))
    man = load_manifest(lay.manifest)
    seq = next(iter(man.sequences))
    scene = man.sequences[seq].scene
    model = load_body_model(man.body_model)
    ctx = _Context(lay, seq, scene, model)
    sl = ctx.sl
    # As Stage IV: view 2 resampled at view 1's instants (sub-frame sync).
    cams, kps = synced_views(sl, {v: read_cameras(sl.view(v).cameras_world) for v in VIEWS},
                             {v: read_keypoints2d(sl.view(v).keypoints).keypoints for v in VIEWS})
    return Stage4Session(seq, man.gender, model, sequence_truth(lay, scene, seq), ctx, cams, kps,
                         min(len(kps[v]) for v in VIEWS), keypoint_layout(sl, seq))
