"""`embodmocap benchmark` scores the frames Stage IV flagged unplaceable as `evaluate` does.

Found on the outdoor studio seed (2026-12-02): view 1 sees nobody in the first 32 frames, Stage IV
flags them ``valid = False``, and the keypoints-only fit holds the body there turned 61-69 degrees
about Z from the truth. The benchmark scored every frame as if valid (``invalid_frames`` 0), so
W-MPJPE's two-frame alignment of the first chunk was fitted on those frames: 150 mm instead of the
35 mm ``evaluate`` reports. These tests check the flagged frames are left out, counted, and kept
beside (``w_mpjpe_mm_incl_invalid``), and that every capture method is scored on the same frames.
"""

from __future__ import annotations

import numpy as np

from embodmocap.evaluate.benchmark import same_frames, tables_markdown
from embodmocap.evaluate.session import SequenceTruth, motion_errors


def _rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _walk(T: int, rng) -> np.ndarray:
    """(T, 24, 3) a rigid joint cloud walking 3 m along x while turning 90 degrees."""
    body = rng.normal(scale=[0.15, 0.15, 0.45], size=(24, 3)) + [0.0, 0.0, 0.9]
    body[0] = [0.0, 0.0, 0.9]
    out = np.empty((T, 24, 3))
    for t in range(T):
        pelvis = np.array([3.0 * t / T, 0.3 * np.sin(t / 20), 0.9])
        out[t] = (body - body[0]) @ _rot_z(90.0 * t / T).T + pelvis
    return out


def test_same_frames_marks_the_dual_fits_flagged_frames():
    frames = np.arange(2, 12)  # the dual fit's sequence frames
    valid = np.ones(10, dtype=bool)
    valid[[0, 1, 9]] = False  # frames 2, 3 and 11
    got = same_frames(frames, valid, 11)  # a method with frames 0..10 (11 is beyond it)
    want = np.ones(11, dtype=bool)
    want[[2, 3]] = False
    np.testing.assert_array_equal(got, want)


def test_flagged_start_frames_turned_away_do_not_set_the_alignment():
    rng = np.random.default_rng(0)
    T, bad = 172, 32
    gt = _walk(T, rng)
    truth = SequenceTruth(joints=gt, T_world_vio={}, T_world_cam={}, sync_frame={}, valid=np.ones(T, dtype=bool))
    pred = gt + rng.normal(scale=0.01, size=gt.shape)
    # The outdoor case: the unplaceable start held turned 65 degrees about the pelvis.
    pelvis = pred[:bad, :1]
    pred[:bad] = (pred[:bad] - pelvis) @ _rot_z(65.0).T + pelvis
    valid = np.ones(T, dtype=bool)
    valid[:bad] = False
    frames = np.arange(T)
    scored = motion_errors(pred, frames, truth, same_frames(frames, valid, T))
    assert scored["invalid_frames"] == bad and scored["evaluated_frames"] == T - bad
    assert scored["w_mpjpe_mm"] < 40.0, scored
    # Kept beside, never hidden: with the flagged frames the chunk turns with them.
    assert scored["w_mpjpe_mm_incl_invalid"] > 3 * scored["w_mpjpe_mm"], scored
    blind = motion_errors(pred, frames, truth)  # what the benchmark reported before
    assert blind["invalid_frames"] == 0 and blind["w_mpjpe_mm"] == scored["w_mpjpe_mm_incl_invalid"]


def test_world_error_is_the_unaligned_error_the_chunk_alignment_hides():
    """A body placed 20 cm off everywhere has W-MPJPE ~0 (each chunk re-anchored on its first two
    frames) but world_mpjpe_mm 200; two noisy anchor frames move W-MPJPE, not the world error."""
    from embodmocap.evaluate.benchmark import scored

    rng = np.random.default_rng(1)
    T = 172
    gt = _walk(T, rng)
    truth = SequenceTruth(joints=gt, T_world_vio={}, T_world_cam={}, sync_frame={}, valid=np.ones(T, dtype=bool))
    frames = np.arange(T)
    shifted = scored(gt + [0.2, 0.0, 0.0], frames, truth)
    assert shifted["w_mpjpe_mm_c1000"] < 1.0 and abs(shifted["world_mpjpe_mm"] - 200.0) < 1e-6, shifted
    # 1 cm noise on every frame; then 4 cm more on the two anchor frames only.
    noisy = gt + rng.normal(scale=0.01, size=gt.shape)
    anchors = noisy.copy()
    anchors[:2] += rng.normal(scale=0.04, size=anchors[:2].shape)
    a, b = scored(noisy, frames, truth), scored(anchors, frames, truth)
    assert b["w_mpjpe_mm_c1000"] > 2 * a["w_mpjpe_mm_c1000"], (a, b)
    assert abs(b["world_mpjpe_mm"] - a["world_mpjpe_mm"]) < 2.0, (a, b)
    # Flagged frames are left out of it as from the other figures.
    valid = np.ones(T, dtype=bool)
    valid[:10] = False
    far = gt.copy()
    far[:10] += 1.0
    assert scored(far, frames, truth, valid)["world_mpjpe_mm"] < 1e-6


def test_tables_show_flagged_frames():
    row = {"w_mpjpe_mm": 30.0, "wa_mpjpe_mm": 15.0, "w_mpjpe_mm_c500": 40.0, "wa_mpjpe_mm_c500": 15.0,
           "w_mpjpe_mm_c1000": 40.0, "wa_mpjpe_mm_c1000": 15.0, "rte_pct": 0.3}
    flagged = {**row, "invalid_frames": 32, "w_mpjpe_mm_incl_invalid": 150.0}
    rows = [{"seed": 1, "preset": "outdoor", "perception": "clean",
             "methods": {m: row for m in ("monocular", "single_v1", "single_v2")} | {"dual": flagged},
             "methods_no_prior": {"dual": flagged}}]
    md = tables_markdown(rows)
    assert "invalid_frames | w_mpjpe_mm_incl_invalid | world_mpjpe_mm |" in md
    line = next(x for x in md.splitlines() if x.startswith("| dual | none | clean"))
    assert line.rstrip(" |").endswith("32.00 | 150.00 | nan"), line
    # A row without flags (older results) counts 0 frames and its own W-MPJPE (and had no
    # unaligned world error).
    line = next(x for x in md.splitlines() if x.startswith("| monocular |"))
    assert line.rstrip(" |").endswith("0.00 | 30.00 | nan"), line


def test_tables_are_written_after_every_session(tmp_path):
    """A long benchmark stopped early keeps the rows it finished: benchmark.json and .md hold
    every session done so far when the next one starts (a failed seed is a row too)."""
    import json
    import logging

    from embodmocap.evaluate.benchmark import BenchmarkConfig, run_benchmark

    seen: list[int] = []

    class AtEachSession(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if record.getMessage().startswith("benchmark seed"):
                seen.append(len(json.loads((tmp_path / "benchmark.json").read_text())["rows"]))

    handler = AtEachSession(logging.INFO)
    logger = logging.getLogger("embodmocap.evaluate.benchmark")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        # seconds = 0 is refused by the studio at once, so each seed fails fast with a clear error.
        result = run_benchmark(tmp_path, BenchmarkConfig(seeds=3, seconds=0.0, ablation=False))
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    assert seen == [1, 2, 3]
    assert [r["seed"] for r in result["rows"]] == [0, 1, 2]
    assert all("seconds and scene_seconds must be > 0" in r["error"] for r in result["rows"])
    assert "Seeds: 0 of 3 succeeded" in (tmp_path / "benchmark.md").read_text()
