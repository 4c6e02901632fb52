"""The perception registry (every backend follows its role's protocol, precomputed ones included),
Stage II's pure performer solve, and the stage manifest's step context manager."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from embodmocap.errors import InputError
from embodmocap.io.body_prior import BodyPriorSeq, write_body_prior
from embodmocap.io.manifest import ViewEntry
from embodmocap.io.openpose import write_openpose_json
from embodmocap.io.stage_manifest import StageManifest
from embodmocap.perception import registry
from embodmocap.perception.precomputed import PrecomputedDepth, PrecomputedKeypoints
from embodmocap.sequence.solve import longest_run, solve_performer

_OFF = np.array([(0, -150), (6, -156), (-6, -156), (12, -152), (-12, -152), (30, -110), (-30, -110),
                 (35, -55), (-35, -55), (38, -5), (-38, -5), (18, 0), (-18, 0), (18, 80), (-18, 80),
                 (18, 160), (-18, 160)], dtype=np.float64) * 0.5


def _person(cx, cy, conf=0.9):
    return np.c_[np.array([cx, cy]) + _OFF, np.full(17, conf)]


@pytest.fixture()
def view(tmp_path) -> ViewEntry:
    kp, masks, depth = tmp_path / "kp", tmp_path / "masks", tmp_path / "depth"
    for d in (kp, masks, depth):
        d.mkdir()
    for f in range(4):
        write_openpose_json(kp / f"{f:06d}_keypoints.json", _person(100 + 5 * f, 120)[None])
        m = np.zeros((240, 320), np.uint8)
        m[40:200, 60:160] = 255
        Image.fromarray(m).save(masks / f"{f:06d}.png")
        Image.fromarray(np.full((60, 80), 1500 + f, np.uint16)).save(depth / f"{f:06d}.png")
    prior = tmp_path / "prior.npz"
    write_body_prior(prior, BodyPriorSeq(np.zeros((4, 3)), np.ones((4, 69)) * 0.1, np.zeros((4, 10)),
                                         np.tile([0, 0, 3.0], (4, 1)), np.arange(4)))
    return ViewEntry(capture=tmp_path / "capture", keypoints=kp, masks=masks, depth=depth, body_prior=prior)


def test_every_precomputed_backend_follows_its_protocol_and_reads_the_files(view):
    rgb = [np.zeros((240, 320, 3), np.uint8)] * 2
    for role in registry.PROTOCOLS:
        backend = registry.make(role, "precomputed", view)
        assert isinstance(backend, registry.PROTOCOLS[role]), role
    boxes = registry.make("detector", "precomputed", view).detect(rgb, [0, 3])
    assert [b.shape for b in boxes] == [(1, 5), (1, 5)] and boxes[1][0, 0] > boxes[0][0, 0]  # the person moved right
    kps = registry.make("keypoints", "precomputed", view).estimate(rgb, [1], [boxes[0][:, :4]])
    np.testing.assert_allclose(kps[0][0], _person(105, 120), atol=1e-6)
    masks = registry.make("masks", "precomputed", view).segment(rgb, [0, 9], np.full((2, 4), np.nan))
    assert masks[0][100, 100] and not masks[0][10, 10] and not masks[1].any()  # frame 9 has no file
    depth = registry.make("depth", "precomputed", view).depth_maps(None, [2], None)
    np.testing.assert_allclose(depth[0], 1.502, atol=1e-6)
    prior = registry.make("body_prior", "precomputed", view).estimate(rgb, [3, 1], None)
    assert prior.frame_ids.tolist() == [3, 1]


def test_precomputed_depth_as_the_protocol_is_the_same_as_reading_it(view):
    src = PrecomputedDepth(view.depth)
    for a, b in zip(src.depth_maps(None, [0, 3], None), src.read([0, 3])):
        np.testing.assert_array_equal(a, b)


def test_missing_files_unknown_names_and_roles_are_clear(view, tmp_path):
    bare = ViewEntry(capture=tmp_path / "capture")
    with pytest.raises(InputError, match="capture: masks = precomputed but the view names no mask folder"):
        registry.make("masks", "precomputed", bare)
    with pytest.raises(InputError, match="detector = precomputed needs the view's keypoint folder"):
        registry.make("detector", "precomputed", bare)
    with pytest.raises(ValueError, match="no masks backend named 'magic'; masks backends: precomputed, sam2, mediapipe"):
        registry.make("masks", "magic", view)
    with pytest.raises(ValueError, match="unknown perception role 'pose3d'"):
        registry.make("pose3d", "precomputed", view)
    assert set(registry.names("depth")) == {"precomputed", "promptda"}


def test_solve_performer_picks_the_person_seen_in_both_views():
    T = 12
    # View 1: the performer every frame but 3..5, a bystander in frames 0..5; view 2: the performer only.
    v1 = [np.stack([_person(200 + t, 200)] + ([_person(40, 60, 0.6)] if t < 6 else []))
          if not 3 <= t <= 5 else _person(40, 60, 0.6)[None] for t in range(T)]
    v2 = [_person(150 - t, 210)[None] for t in range(T)]
    found = solve_performer({"v1": v1, "v2": v2}, {"v1": (320, 320), "v2": (320, 320)}, {"v1": 10.0, "v2": 10.0})
    p1, p2 = found["v1"], found["v2"]
    assert p1.seen.tolist() == [t not in (3, 4, 5) for t in range(T)] and p2.seen.all()
    np.testing.assert_allclose(p1.keypoints[7], _person(207, 200))
    assert p1.longest_gap_s == pytest.approx(0.3) and p1.seen_fraction == pytest.approx(0.75)
    assert np.isnan(p1.boxes[4]).all() and p1.figures("v1")["v1_frames_with_person"] == 9
    assert longest_run(np.array([1, 1, 0, 1, 1, 1, 0], bool)) == 3 and longest_run(np.zeros(3, bool)) == 0


def test_step_context_manager_times_records_skips_and_logs(tmp_path, caplog):
    out = tmp_path / "x.txt"
    sm = StageManifest(tmp_path / "manifest.json", "demo", {"a": 1})
    with caplog.at_level("INFO", logger="embodmocap.io.stage_manifest"):
        with sm.step("make", "fp1", label="demo s0") as step:
            assert step.run
            out.write_text("x")
            step.record([out], {"items": 3, "curve": [1, 2]})
    assert "demo s0: make done in" in caplog.text and "items=3" in caplog.text and "curve" not in caplog.text
    again = StageManifest(tmp_path / "manifest.json", "demo", {"a": 1})
    with again.step("make", "fp1") as step:
        assert not step.run
    assert again.skipped == ["make"]
    with again.step("make", "fp1", force=True) as step:
        assert step.run
        step.record([out])
    with pytest.raises(RuntimeError, match="ran but recorded nothing"):
        with again.step("other", "fp"):
            pass
    with pytest.raises(KeyError):  # an error inside a step propagates and records nothing
        with again.step("broken", "fp"):
            raise KeyError("x")
    data = json.loads(Path(tmp_path / "manifest.json").read_text())
    assert set(data["steps"]) == {"make"} and data["figures"]["items"] == 3
    # A step finished after a later one: postponed inside its `with`, recorded after it.
    with again.step("late", "fp2") as step:
        late = step.postpone()
    assert "late" not in json.loads(Path(tmp_path / "manifest.json").read_text())["steps"]
    late.record([out], {"placed": True})
    data = json.loads(Path(tmp_path / "manifest.json").read_text())
    assert data["steps"]["late"]["fingerprint"] == "fp2" and data["figures"]["placed"] is True


@pytest.mark.parametrize("env", [
    {},
    {"HF_HOME": "/data/hf-home"},
    {"XDG_CACHE_HOME": "/data/xdg", "HF_HUB_OFFLINE": "1"},
    {"HF_HOME": "/data/hf-home", "HF_HUB_CACHE": "/data/hub-cache", "HF_HUB_OFFLINE": "0"},
    {"HUGGINGFACE_HUB_CACHE": "/data/old-name", "TRANSFORMERS_OFFLINE": "yes"},
])
def test_cache_folder_and_offline_follow_the_environment_as_huggingface_hub_does(env):
    # Reference: huggingface_hub's own constants, computed at its import in a fresh interpreter
    # with the same environment; ours are read at call time.
    import os
    import subprocess
    import sys

    pytest.importorskip("huggingface_hub")
    clean = {k: v for k, v in os.environ.items()
             if k not in ("HF_HOME", "HF_HUB_CACHE", "HUGGINGFACE_HUB_CACHE", "XDG_CACHE_HOME", "HF_HUB_OFFLINE",
                          "TRANSFORMERS_OFFLINE")}
    code = ("import json, huggingface_hub.constants as c\n"
            "from embodmocap.perception.hub import downloads_off, hub_cache_dir\n"
            "print(json.dumps([c.HF_HUB_CACHE, str(hub_cache_dir()), c.HF_HUB_OFFLINE, downloads_off()]))")
    out = subprocess.run([sys.executable, "-c", code], env={**clean, **env}, capture_output=True, text=True, check=True)
    theirs_cache, ours_cache, theirs_off, ours_off = json.loads(out.stdout.strip().splitlines()[-1])
    assert ours_cache == theirs_cache and ours_off == theirs_off


def test_default_model_ids_are_documented_where_users_look():
    # The ids of hub.DEFAULT_MODELS are interfaces: the option help (SequenceConfig's docstrings, which
    # the CLI shows) and docs/formats.md must name the same ones.
    from embodmocap.perception.hub import DEFAULT_MODELS, model_or_default

    root = Path(__file__).resolve().parents[1]
    config_src = (root / "src/embodmocap/sequence/config.py").read_text()
    formats = (root / "docs/formats.md").read_text()
    for role, repo_id in DEFAULT_MODELS.items():
        assert repo_id in config_src and repo_id in formats, repo_id
        assert model_or_default("", role) == repo_id and model_or_default(None, role) == repo_id
    assert model_or_default("my/own-model", "masks") == "my/own-model"
    with pytest.raises(ValueError, match="unknown model role 'pose3d'"):
        model_or_default("", "pose3d")


def test_hub_unreachable_uses_the_cache_or_says_id_cache_and_fetch_command(tmp_path):
    # Downloads on, but the Hub endpoint is a closed local port (a real connection that fails, as on
    # a machine without network): a cached id still resolves, an uncached one is one clear line.
    # huggingface_hub reads HF_ENDPOINT at import, hence a fresh interpreter.
    import os
    import socket
    import subprocess
    import sys

    pytest.importorskip("huggingface_hub")
    from hub_cache import place_in_hub_cache

    model = tmp_path / "model"
    model.mkdir()
    (model / "config.json").write_text("{}")
    (model / "model.safetensors").write_bytes(b"\0" * 64)
    cache = tmp_path / "hf-cache"
    snapshot = place_in_hub_cache(model, "tiny-org/present", cache)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again when the block ends: connections are refused
    env = {k: v for k, v in os.environ.items() if k not in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE")}
    env.update(HF_HUB_CACHE=str(cache), HF_ENDPOINT=f"http://127.0.0.1:{port}")
    code = ("from embodmocap.perception.hub import resolve_model_folder\n"
            "from embodmocap.errors import InputError\n"
            "print(resolve_model_folder('tiny-org/present', 'detector'))\n"
            "try:\n    resolve_model_folder('tiny-org/absent', 'keypoints')\n"
            "except InputError as err:\n    print(err)\n")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True, timeout=120)
    found, error = out.stdout.strip().splitlines()[-2:]
    assert found == str(snapshot)
    assert error.startswith("tiny-org/absent: not a local folder, and it could not be downloaded into the Hugging Face "
                            f"cache {cache}")
    assert "ConnectError" in error and "`hf download tiny-org/absent`" in error


def test_the_registrys_default_model_sources_are_stage_twos():
    """registry.make's default settings (perception.config.ModelSources, so that perception needs no
    import of sequence) hold Stage II's defaults for every field the backends read."""
    from dataclasses import fields

    from embodmocap.perception.config import ModelSources
    from embodmocap.sequence.config import SequenceConfig

    ours, stage2 = ModelSources(), SequenceConfig()
    for f in fields(ModelSources):
        assert getattr(ours, f.name) == getattr(stage2, f.name), f.name
