"""The same inputs and settings give the same outputs: Stage I twice and Stage III twice on one small
synthetic session, compared file by file (bitwise; ``.npz`` by their arrays, JSON without timings).

Slow: Stage I, II and III each run about twice.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from embodmocap.calibrate import stage as stage3
from embodmocap.calibrate.register import RegisterConfig
from embodmocap.scene import stage as stage1
from embodmocap.scene.config import SceneConfig
from embodmocap.scene.sfm import SfmConfig, sparse_points
from embodmocap.sequence import stage as stage2
from embodmocap.sequence.config import SequenceConfig
from embodmocap.synth.studio import synthesize

from fault_session import SYNTH, differences, snapshot

pytestmark = pytest.mark.slow

SCENE = SceneConfig(voxel_m_indoor=0.02, sfm=SfmConfig(max_images=60))
CALIB = stage3.CalibrateConfig(register=RegisterConfig(num_frames=24), chamfer_frames=10)


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("determinism") / "s"
    synthesize(SYNTH, root)
    return root


def test_stage1_twice_is_bitwise_identical(session):
    stage1.run(SCENE, session)
    first = snapshot(session, ("scenes",))
    points = len(sparse_points(session / "scenes" / SYNTH.scene_name / "sfm")[0])
    again = stage1.run(SCENE, session, force=True)
    assert not again.skipped
    assert differences(first, snapshot(session, ("scenes",))) == []
    assert again.figures["sfm_points"] == points > 1000


def test_stage3_twice_is_identical(session):
    if not (session / "scenes" / SYNTH.scene_name / "sfm").is_dir():
        stage1.run(SCENE, session)
    stage2.run(SequenceConfig(), session)
    stage3.run(CALIB, session)
    first = snapshot(session, ("sequences",))
    again = stage3.run(CALIB, session, force=True)
    assert not again.skipped
    assert differences(first, snapshot(session, ("sequences",))) == []


def test_stage3_same_answer_on_lent_cores(session):
    """Stage III splits the refinement's and the geometric sync's work over the cores
    ``embodmocap run`` lends it (parallel.lent_cores): the split must not change a bit."""
    from embodmocap.parallel import lend_cores

    if not (session / "scenes" / SYNTH.scene_name / "sfm").is_dir():
        stage1.run(SCENE, session)
    stage2.run(SequenceConfig(), session)
    with lend_cores(1):
        stage3.run(CALIB, session, force=True)
    one = snapshot(session, ("sequences",))
    with lend_cores(2):
        again = stage3.run(CALIB, session, force=True)
    assert not again.skipped
    assert differences(one, snapshot(session, ("sequences",))) == []
