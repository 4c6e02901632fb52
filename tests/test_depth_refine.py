"""Depth refinement backends: the LiDAR fallback and Prompt Depth Anything (a tiny random model).

The tiny model is built from a config, saved with ``save_pretrained`` and loaded back through the
same path a user's downloaded model takes, so every line of pre- and post-processing runs. Its
weights are random, so the tests check what does not depend on them: sizes, units, value range
(a "metric" head predicts within the prompt's [min, max]), batching, the exact network input.
"""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from embodmocap.errors import InputError, MissingExtraError
from embodmocap.perception import DepthRefiner, LidarDepth, PromptDepthAnything, make_depth_refiner
from embodmocap.perception.depth_refine import fill_invalid_nearest, network_input_size
from embodmocap.types import Intrinsics

torch = pytest.importorskip("torch")
transformers = pytest.importorskip("transformers")

K_RGB = Intrinsics(121.0, 121.0, 79.5, 59.5, 160, 120)
K_DEPTH = K_RGB.scaled(64, 48)
MEAN, STD = (0.5, 0.4, 0.3), (0.2, 0.25, 0.3)  # deliberately not ImageNet's: must come from the folder


# ------------------------------------------------------------------------------------------------
# Fixtures


@pytest.fixture(scope="module")
def frames():
    """Three RGB-D pairs of the synthetic studio (160x120 RGB, 64x48 exact depth), with holes."""
    from embodmocap.synth import trajectory
    from embodmocap.synth.render import Renderer
    from embodmocap.synth.scene import build_scene

    built = build_scene("indoor", np.random.default_rng(3))
    renderer = Renderer(built)
    poses = trajectory.scene_walk(built.spec, 10.0, 10.0, np.random.default_rng(0))
    rgbs, depths = [], []
    for k, i in enumerate((0, 40, 80)):
        out = renderer.render(K_RGB, poses[i], None, False, K_DEPTH)
        depth = out.depth_lr_m.copy()
        depth[5 + 10 * k:12 + 10 * k, 20:30] = 0.0  # a LiDAR hole, at a different place per frame
        rgbs.append(out.rgb)
        depths.append(depth)
    return rgbs, depths


@pytest.fixture(scope="module")
def tiny_model_dir(tmp_path_factory):
    """A tiny random Prompt Depth Anything saved like a downloaded model (plus a processor config)."""
    torch.manual_seed(0)
    backbone = transformers.Dinov2Config(
        image_size=56, patch_size=14, hidden_size=32, num_hidden_layers=2, num_attention_heads=2,
        intermediate_size=64, out_indices=[1, 2], reshape_hidden_states=False,
    )
    config = transformers.PromptDepthAnythingConfig(
        backbone_config=backbone, reassemble_hidden_size=32, reassemble_factors=[2, 1],
        neck_hidden_sizes=[8, 16], fusion_hidden_size=16, head_hidden_size=8, depth_estimation_type="metric",
    )
    model = transformers.PromptDepthAnythingForDepthEstimation(config)
    folder = tmp_path_factory.mktemp("models") / "tiny-promptda"
    model.save_pretrained(folder)
    (folder / "preprocessor_config.json").write_text(json.dumps({
        "image_processor_type": "PromptDepthAnythingImageProcessor", "do_rescale": True,
        "rescale_factor": 1 / 255, "do_normalize": True, "image_mean": list(MEAN), "image_std": list(STD),
    }))
    return folder


@pytest.fixture(scope="module")
def refiner(tiny_model_dir):
    return PromptDepthAnything(model=tiny_model_dir, batch_size=2, max_side=100)


def _capture_inputs(model):
    """Register a hook recording the tensors each forward pass receives; returns (seen, handle)."""
    seen = []

    def hook(_module, args, kwargs):
        seen.append({"pixel_values": kwargs["pixel_values"].clone(), "prompt_depth": kwargs["prompt_depth"].clone()})

    return seen, model.register_forward_pre_hook(hook, with_kwargs=True)


# ------------------------------------------------------------------------------------------------
# Pure helpers


@pytest.mark.parametrize(("hw", "max_side", "expected"), [
    ((1440, 1920), 1008, (756, 1008)),   # iPhone RGB at the release's scene setting
    ((720, 960), 960, (714, 952)),       # 960 is not a multiple of 14: the limit becomes 952
    ((960, 720), 720, (714, 532)),       # portrait view at the release's fast setting
    ((192, 256), 1008, (196, 252)),      # small images are not enlarged beyond rounding
    ((120, 160), 100, (70, 98)),
    ((5, 7), 1008, (14, 14)),            # at least one patch
])
def test_network_input_size_known_answers(hw, max_side, expected):
    assert network_input_size(*hw, max_side) == expected


def test_network_input_size_rules_hold_for_many_sizes():
    rng = np.random.default_rng(0)
    for _ in range(500):
        H, W = (int(v) for v in rng.integers(14, 4000, size=2))
        max_side = int(rng.integers(14, 2000))
        h, w = network_input_size(H, W, max_side)
        assert h % 14 == 0 and w % 14 == 0
        assert max(h, w) <= max(14, max_side // 14 * 14)
        assert h <= H + 7 and w <= W + 7 or min(h, w) == 14  # never enlarged beyond rounding
        if min(h, w) > 14:  # aspect kept up to the rounding of each side by at most half a patch
            assert abs(w / h - W / H) <= 7 * (1 + W / H) / h + 1e-12


def test_fill_invalid_nearest_known_answer():
    d = np.array([[1.0, 0.0, 0.0, 4.0],
                  [0.0, 0.0, 0.0, 0.0],
                  [2.0, 0.0, 0.0, 3.0]], np.float32)
    filled = fill_invalid_nearest(d)
    assert filled[0, 1] == 1.0 and filled[0, 2] == 4.0 and filled[2, 1] == 2.0 and filled[2, 2] == 3.0
    assert np.all(filled > 0) and np.array_equal(filled[d > 0], d[d > 0])
    assert np.array_equal(fill_invalid_nearest(np.zeros((3, 3), np.float32)), np.zeros((3, 3)))
    assert d[0, 1] == 0.0  # input untouched


# ------------------------------------------------------------------------------------------------
# LiDAR fallback


def test_lidar_depth_is_the_identity(frames):
    rgbs, depths = frames
    dirty = depths[0].copy()
    dirty[0, :3] = [np.nan, np.inf, -1.0]
    before = dirty.copy()
    refiner = make_depth_refiner("none", model="ignored/when-off")
    assert isinstance(refiner, LidarDepth) and isinstance(refiner, DepthRefiner) and refiner.name == "none"
    out = refiner.refine(rgbs[:2], [dirty, depths[1]])
    assert [o.dtype for o in out] == [np.float32, np.float32]
    assert np.array_equal(out[1], depths[1])
    assert np.array_equal(out[0][0, :3], [0, 0, 0]) and np.array_equal(out[0][:, 3:][1:], depths[0][:, 3:][1:])
    assert np.array_equal(before, dirty, equal_nan=True)  # input untouched


# ------------------------------------------------------------------------------------------------
# Prompt Depth Anything (tiny random model)


def test_refine_returns_metric_depth_at_rgb_resolution(refiner, frames):
    rgbs, depths = frames
    assert isinstance(refiner, DepthRefiner) and refiner.name == "promptda"
    out = refiner.refine(rgbs[:2], depths[:2])
    assert len(out) == 2
    for o, d in zip(out, depths[:2]):
        assert o.shape == (120, 160) and o.dtype == np.float32
        assert np.all(np.isfinite(o)) and np.all(o >= 0)
        # The metric head maps a sigmoid onto the prompt's [min, max]: holes filled from their
        # neighbours keep that range (a hole left at 0 would pull the minimum to 0).
        lo, hi = d[d > 0].min(), d[d > 0].max()
        assert o.min() >= lo - 1e-3 and o.max() <= hi + 1e-3
    assert not np.allclose(out[0], out[1])


def test_batching_does_not_mix_frames(refiner, frames):
    rgbs, depths = frames
    together = refiner.refine(rgbs, depths)  # batch_size 2: a batch of two and a batch of one
    alone = [refiner.refine([r], [d])[0] for r, d in zip(rgbs, depths)]
    for a, b in zip(together, alone):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5)


def test_network_input_follows_the_size_and_normalisation_rules(refiner, frames):
    rgbs, depths = frames
    seen, handle = _capture_inputs(refiner.model)
    try:
        refiner.refine(rgbs[:2], depths[:2])
    finally:
        handle.remove()
    assert len(seen) == 1  # one forward pass for the two frames
    pixels, prompt = seen[0]["pixel_values"].numpy(), seen[0]["prompt_depth"].numpy()
    assert pixels.shape == (2, 3, 70, 98)  # 160x120 with max_side 100 -> limit 98, multiples of 14
    expected = cv2.resize(rgbs[1], (98, 70), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    expected = ((expected - np.float32(MEAN)) / np.float32(STD)).transpose(2, 0, 1)
    np.testing.assert_allclose(pixels[1], expected, atol=1e-5)
    # Prompt: metres at sensor resolution, holes filled, valid pixels as measured.
    assert prompt.shape == (2, 1, 48, 64)
    assert np.all(prompt > 0)
    valid = depths[0] > 0
    np.testing.assert_array_equal(prompt[0, 0][valid], depths[0][valid])


def test_output_at_depth_resolution_and_mixed_sizes(tiny_model_dir, frames):
    rgbs, depths = frames
    refiner = PromptDepthAnything(model=str(tiny_model_dir), batch_size=4, max_side=1008, output="depth")
    small = cv2.resize(rgbs[1], (128, 96), interpolation=cv2.INTER_AREA)
    seen, handle = _capture_inputs(refiner.model)
    try:
        out = refiner.refine([rgbs[0], small, rgbs[2]], depths)
    finally:
        handle.remove()
    assert [o.shape for o in out] == [(48, 64)] * 3
    # Two shapes -> two forward passes, neither enlarged beyond rounding to multiples of 14.
    assert sorted(tuple(s["pixel_values"].shape) for s in seen) == [(1, 3, 98, 126), (2, 3, 126, 154)]
    alone = refiner.refine([small], [depths[1]])[0]
    np.testing.assert_allclose(out[1], alone, atol=1e-5)  # order kept across the shape groups


def test_frames_without_valid_depth_and_masking(tiny_model_dir, frames):
    rgbs, depths = frames
    refiner = PromptDepthAnything(model=tiny_model_dir, max_side=100, output="depth", mask_invalid=True)
    empty = np.zeros_like(depths[1])
    out = refiner.refine(rgbs[:2], [depths[0], empty])
    assert np.array_equal(out[1], empty)
    assert np.all(out[0][depths[0] == 0] == 0) and np.all(out[0][depths[0] > 0] > 0)


def test_constant_prompt_gives_that_depth(refiner, frames):
    rgbs, _ = frames
    flat = np.full((48, 64), 2.5, np.float32)  # a wall seen head-on: max - min = 0
    out = refiner.refine([rgbs[0]], [flat])[0]
    assert np.all(np.isfinite(out)) and np.allclose(out, 2.5, atol=2e-4)


def test_missing_model_folder_is_one_line_input_error(tmp_path):
    missing = tmp_path / "no-such-model"
    with pytest.raises(InputError) as err:
        PromptDepthAnything(model=missing)
    assert str(missing) in str(err.value) and "\n" not in str(err.value)
    assert "no such model folder" in str(err.value)


def test_uncached_hub_id_offline_names_id_cache_and_fetch_command(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hf-cache"))
    with pytest.raises(InputError) as err:
        make_depth_refiner("promptda", model="nobody-here/no-such-promptda-model", offline=True)
    msg = str(err.value)
    assert msg.startswith("nobody-here/no-such-promptda-model: ") and "\n" not in msg
    assert str(tmp_path / "hf-cache") in msg and "`hf download nobody-here/no-such-promptda-model`" in msg


def test_default_hub_id_loads_from_the_cache_offline(tiny_model_dir, refiner, frames, tmp_path, monkeypatch):
    # The role's default id (no model given), placed in a fresh cache as a download leaves it, loads
    # offline (HF_HUB_OFFLINE=1) and is the same network as the folder it came from.
    from hub_cache import place_in_hub_cache

    from embodmocap.perception.hub import DEFAULT_MODELS

    cache = tmp_path / "hf-cache"
    monkeypatch.setenv("HF_HUB_CACHE", str(cache))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    snapshot = place_in_hub_cache(tiny_model_dir, DEFAULT_MODELS["depth"], cache, extra_files={"promptda_vits.ckpt": 99})
    by_id = PromptDepthAnything(batch_size=2, max_side=100)
    assert by_id.model_dir == snapshot and by_id.options.model == DEFAULT_MODELS["depth"]
    rgbs, depths = frames
    for a, b in zip(by_id.refine(rgbs, depths), refiner.refine(rgbs, depths)):
        np.testing.assert_array_equal(a, b)


def test_folder_that_is_not_a_promptda_model(tmp_path):
    with pytest.raises(InputError, match="no config.json"):
        PromptDepthAnything(model=tmp_path)
    (tmp_path / "config.json").write_text(json.dumps({"model_type": "dinov2", "hidden_size": 32}))
    with pytest.raises(InputError, match="not 'prompt_depth_anything'"):
        PromptDepthAnything(model=tmp_path)


def test_missing_transformers_names_the_extra(tiny_model_dir, monkeypatch):
    monkeypatch.setitem(sys.modules, "transformers", None)  # makes `import transformers` fail
    with pytest.raises(MissingExtraError, match=r"embodmocap\[perception\]"):
        PromptDepthAnything(model=tiny_model_dir)


def test_factory_and_argument_checks(tiny_model_dir, frames):
    rgbs, depths = frames
    assert isinstance(make_depth_refiner("PromptDA", model=tiny_model_dir, max_side=56), PromptDepthAnything)
    with pytest.raises(ValueError, match="unknown depth refiner"):
        make_depth_refiner("lingbot")
    with pytest.raises(ValueError, match="batch_size"):
        PromptDepthAnything(model=tiny_model_dir, batch_size=0)
    with pytest.raises(ValueError, match="aspect ratios"):
        LidarDepth().refine([rgbs[0]], [depths[0].T.copy()])
    with pytest.raises(ValueError, match="2 RGB images but 1 depth"):
        LidarDepth().refine(rgbs[:2], depths[:1])


def test_four_level_architecture_like_the_released_models(tmp_path, frames):
    """The released models fuse four backbone levels, one of them downsampled (factor 0.5)."""
    rgbs, depths = frames
    torch.manual_seed(1)
    backbone = transformers.Dinov2Config(
        hidden_size=48, num_hidden_layers=4, num_attention_heads=2, intermediate_size=96,
        out_indices=[1, 2, 3, 4], reshape_hidden_states=False,
    )
    config = transformers.PromptDepthAnythingConfig(  # reassemble factors (4, 2, 1, 0.5): the defaults
        backbone_config=backbone, reassemble_hidden_size=48, neck_hidden_sizes=[8, 16, 32, 48],
        fusion_hidden_size=16, head_hidden_size=8, depth_estimation_type="metric",
    )
    transformers.PromptDepthAnythingForDepthEstimation(config).save_pretrained(tmp_path / "vit4")
    out = PromptDepthAnything(model=tmp_path / "vit4", max_side=150).refine(rgbs[:1], depths[:1])[0]
    valid = depths[0][depths[0] > 0]
    assert out.shape == (120, 160) and np.all(np.isfinite(out))
    assert valid.min() - 1e-3 <= out.min() and out.max() <= valid.max() + 1e-3


def test_importing_the_package_does_not_import_torch():
    code = "import sys, embodmocap.perception; print('torch' in sys.modules, 'transformers' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["False", "False"]


def test_scene_and_sequence_stages_run_with_promptda(tiny_model_dir, tmp_path):
    # End to end through both stages that use the backend. Random weights give arbitrary depth, so
    # this checks the plumbing (the refined depth reaches the TSDF and the per-view depth stack at
    # the sizes promised), not accuracy.
    from embodmocap.scene import stage as scene_stage
    from embodmocap.scene.config import SceneConfig
    from embodmocap.scene.sfm import SfmConfig
    from embodmocap.sequence import stage as seq_stage
    from embodmocap.sequence.config import SequenceConfig
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    session = tmp_path / "s"
    synth = SynthConfig(seed=4, seconds=1.5, scene_seconds=3.0, width=320, height=240, depth_width=64, depth_height=48)
    synthesize(synth, session)
    scene = scene_stage.run(SceneConfig(voxel_m_indoor=0.03, depth_refine="promptda", depth_refine_model=str(tiny_model_dir),
                                        min_component_fraction=0.0, sfm=SfmConfig(max_images=12)), session)
    assert scene.figures["mesh_faces"] > 0 and scene.layout.mesh_raw.is_file()
    seq = seq_stage.run(SequenceConfig(depth="promptda", depth_model=str(tiny_model_dir)), session)
    depth = np.load(seq.layout.view("v1").depth)
    assert depth.shape == (seq.figures["frames"], synth.height, synth.width) and depth.dtype == np.uint16
