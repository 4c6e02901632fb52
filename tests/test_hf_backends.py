"""transformers backends (RT-DETR, ViTPose, SAM 2) with tiny randomly initialised models.

Each model is built from a small config, saved with ``save_pretrained`` plus a
``preprocessor_config.json`` whose numbers differ from the defaults (so they must be read from the
folder), and loaded back through the backend as a user's model folder would be. Random weights
mean the predictions are meaningless, so the tests check what does not depend on them: the exact
network input (forward hooks), output shapes / types / ranges, batching and chunking invariance,
and the pre/post-processing maths against hand-computed cases.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from hub_cache import place_in_hub_cache

from embodmocap.errors import InputError
from embodmocap.perception.hf_backends import HF_BACKENDS, make_backend, resize_rgb
from embodmocap.types import Intrinsics

torch = pytest.importorskip("torch")
transformers = pytest.importorskip("transformers")

from embodmocap.perception.hf_detect import RtDetrPersonDetector, normalized_cxcywh_to_xyxy, person_scores  # noqa: E402
from embodmocap.perception.hf_pose import (  # noqa: E402
    VitPoseKeypoints, crop_windows, decode_heatmaps, grid_to_image, window_to_grid,
)
from embodmocap.perception.hf_sam2 import Sam2VideoMasks, box_prompt, upsample_mask_logits  # noqa: E402

K_RGB = Intrinsics(121.0, 121.0, 79.5, 59.5, 160, 120)
MEAN, STD = (0.5, 0.4, 0.3), (0.2, 0.25, 0.3)  # deliberately not ImageNet's


def _write_processor(folder, **extra) -> None:
    cfg = {"do_rescale": True, "rescale_factor": 1 / 255, "do_normalize": True,
           "image_mean": list(MEAN), "image_std": list(STD), **extra}
    (folder / "preprocessor_config.json").write_text(json.dumps(cfg))


def _expected_input(rgbs, hw) -> np.ndarray:
    """What the network must see: frames resized to hw, normalised with the folder's numbers."""
    x = np.stack([resize_rgb(f, hw) for f in rgbs]).astype(np.float32) / 255.0
    return ((x - np.float32(MEAN)) / np.float32(STD)).transpose(0, 3, 1, 2)


# ------------------------------------------------------------------------------------------------
# Fixtures


@pytest.fixture(scope="module")
def frames():
    """Four 160x120 frames of the synthetic studio along a camera walk."""
    from embodmocap.synth import trajectory
    from embodmocap.synth.render import Renderer
    from embodmocap.synth.scene import build_scene

    built = build_scene("indoor", np.random.default_rng(3))
    renderer = Renderer(built)
    poses = trajectory.scene_walk(built.spec, 10.0, 10.0, np.random.default_rng(0))
    return [renderer.render(K_RGB, poses[i], None, False, None).rgb for i in (0, 20, 40, 60)]


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    return tmp_path_factory.mktemp("hf_models")


@pytest.fixture(scope="module")
def rtdetr_dir(models):
    """Tiny RT-DETR (ResNet backbone, 20 queries), 'person' deliberately not class 0, input 96x128."""
    torch.manual_seed(0)
    backbone = transformers.RTDetrResNetConfig(embedding_size=8, hidden_sizes=[8, 16, 32, 64], depths=[1, 1, 1, 1],
                                               layer_type="basic", out_features=["stage2", "stage3", "stage4"])
    id2label = {0: "bicycle", 1: "car", 2: "person"}
    config = transformers.RTDetrConfig(
        backbone_config=backbone, encoder_hidden_dim=16, encoder_in_channels=[16, 32, 64], encoder_ffn_dim=32,
        encoder_attention_heads=2, d_model=16, num_queries=20, decoder_in_channels=[16, 16, 16],
        decoder_ffn_dim=32, decoder_layers=1, decoder_attention_heads=2, num_denoising=0,
        id2label=id2label, label2id={v: k for k, v in id2label.items()},
    )
    folder = models / "tiny-rtdetr"
    transformers.RTDetrForObjectDetection(config).save_pretrained(folder)
    _write_processor(folder, size={"height": 96, "width": 128})
    return folder


@pytest.fixture(scope="module")
def vitpose_dir(models):
    """Tiny ViTPose: 64x48 input, 8 px patches, 17 heatmaps of 16x12."""
    torch.manual_seed(1)
    backbone = transformers.VitPoseBackboneConfig(image_size=[64, 48], patch_size=[8, 8], hidden_size=32,
                                                  num_hidden_layers=2, num_attention_heads=2, mlp_ratio=2,
                                                  out_indices=[2])
    config = transformers.VitPoseConfig(backbone_config=backbone, num_labels=17, scale_factor=2)
    folder = models / "tiny-vitpose"
    transformers.VitPoseForPoseEstimation(config).save_pretrained(folder)
    _write_processor(folder, size={"height": 64, "width": 48})
    return folder


@pytest.fixture(scope="module")
def sam2_dir(models):
    """Tiny SAM 2 video model (128 px input); its object-score head is biased so the object is 'present'."""
    torch.manual_seed(2)
    hiera = transformers.Sam2HieraDetConfig(
        hidden_size=16, num_attention_heads=1, image_size=[128, 128], blocks_per_stage=[1, 1, 2, 1],
        embed_dim_per_stage=[16, 32, 64, 128], num_attention_heads_per_stage=[1, 1, 2, 2],
        window_size_per_stage=[4, 4, 4, 4], global_attention_blocks=[3],
        window_positional_embedding_background_size=[4, 4],
    )
    vision = transformers.Sam2VisionConfig(backbone_config=hiera, backbone_channel_list=[128, 64, 32, 16],
                                           backbone_feature_sizes=[[32, 32], [16, 16], [8, 8]], fpn_hidden_size=128)
    # Hidden sizes are 128 because the memory path has a fixed 64-channel memory and splits
    # object pointers into hidden/64 tokens.
    config = transformers.Sam2VideoConfig(
        vision_config=vision,
        prompt_encoder_config=dict(hidden_size=128, image_size=128, patch_size=16, mask_input_channels=4),
        mask_decoder_config=dict(hidden_size=128, mlp_dim=64, num_attention_heads=2, iou_head_hidden_dim=32),
        image_size=128, num_maskmem=3, max_object_pointers_in_encoder=2, memory_attention_hidden_size=128,
        memory_attention_num_layers=1, memory_attention_feed_forward_hidden_size=64,
        memory_attention_rope_feat_sizes=[8, 8], memory_encoder_hidden_size=128, memory_encoder_output_channels=64,
        mask_downsampler_embed_dim=128, memory_fuser_embed_dim=128, memory_fuser_intermediate_dim=64,
    )
    model = transformers.Sam2VideoModel(config)
    with torch.no_grad():
        model.mask_decoder.pred_obj_score_head.proj_out.bias.fill_(5.0)
    folder = models / "tiny-sam2"
    model.save_pretrained(folder)
    _write_processor(folder, size={"height": 128, "width": 128})
    return folder


@pytest.fixture(scope="module")
def detector(rtdetr_dir):
    return RtDetrPersonDetector(rtdetr_dir, score_threshold=0.0, batch_size=8)


@pytest.fixture(scope="module")
def pose(vitpose_dir):
    return VitPoseKeypoints(vitpose_dir, batch_size=16)


# ------------------------------------------------------------------------------------------------
# RT-DETR


def test_normalised_box_to_pixels_known_cases():
    boxes = np.array([[0.5, 0.5, 0.5, 0.5], [0.9, 0.5, 0.4, 0.2], [0.0, 0.0, 0.0, 0.0]])
    got = normalized_cxcywh_to_xyxy(boxes, 160, 120)
    np.testing.assert_allclose(got[0], [39.5, 29.5, 119.5, 89.5])  # quarter to three quarters of the image
    np.testing.assert_allclose(got[1], [111.5, 47.5, 159.5, 71.5])  # x2 = 1.1 * 160 - 0.5 clipped to the edge
    np.testing.assert_allclose(got[2], [-0.5, -0.5, -0.5, -0.5])  # the image's top-left corner


def test_person_scores_sigmoid_and_softmax():
    logits = np.array([[[0.0, np.log(3.0), -2.0]]])
    np.testing.assert_allclose(person_scores(logits, 1, focal=True), [[0.75]])
    soft = np.exp([0.0, np.log(3.0), -2.0])
    np.testing.assert_allclose(person_scores(logits, 1, focal=False), [[3.0 / soft.sum()]])


def test_rtdetr_end_to_end_input_and_output(detector, frames):
    seen, raw = [], []
    h1 = detector.model.register_forward_pre_hook(lambda m, a, kw: seen.append(kw["pixel_values"].clone()),
                                                  with_kwargs=True)
    h2 = detector.model.register_forward_hook(lambda m, a, out: raw.append((out.logits.clone(), out.pred_boxes.clone())))
    try:
        dets = detector.detect(frames[:3], [0, 1, 2])
    finally:
        h1.remove()
        h2.remove()
    assert detector.person_id == 2 and detector.input_hw == (96, 128)
    np.testing.assert_allclose(seen[0].numpy(), _expected_input(frames[:3], (96, 128)), atol=1e-5)
    logits, boxes = raw[0][0].numpy(), raw[0][1].numpy()
    for i, d in enumerate(dets):
        assert d.shape == (20, 5) and d.dtype == np.float64  # threshold 0 keeps every query
        assert np.all(np.diff(d[:, 4]) <= 0), "sorted by decreasing score"
        assert np.all((d[:, [0, 2]] >= -0.5) & (d[:, [0, 2]] <= 159.5))
        assert np.all((d[:, [1, 3]] >= -0.5) & (d[:, [1, 3]] <= 119.5))
        assert np.all(d[:, 2] >= d[:, 0]) and np.all(d[:, 3] >= d[:, 1])
        # the person column (2) of the raw logits, not another class
        np.testing.assert_allclose(np.sort(d[:, 4]), np.sort(1 / (1 + np.exp(-logits[i, :, 2]))), rtol=1e-5)
        best = np.argmax(logits[i, :, 2])
        np.testing.assert_allclose(d[0, :4], normalized_cxcywh_to_xyxy(boxes[i, best], 160, 120), atol=1e-4)


def test_rtdetr_threshold_and_batching(rtdetr_dir, detector, frames):
    one = RtDetrPersonDetector(rtdetr_dir, score_threshold=0.0, batch_size=1)
    batched, single = detector.detect(frames, [0, 1, 2, 3]), one.detect(frames, [0, 1, 2, 3])
    for a, b in zip(batched, single):
        np.testing.assert_allclose(a, b, atol=1e-4)
    thr = float(np.median(batched[0][:, 4]))
    strict = RtDetrPersonDetector(rtdetr_dir, score_threshold=thr).detect(frames[:1], [0])[0]
    assert len(strict) == int((batched[0][:, 4] >= thr).sum()) and np.all(strict[:, 4] >= thr)
    assert detector.detect([], []) == []


def test_rtdetr_unknown_person_label(rtdetr_dir):
    with pytest.raises(InputError, match="id2label has no class 'human'"):
        RtDetrPersonDetector(rtdetr_dir, person_label="human")


# ------------------------------------------------------------------------------------------------
# ViTPose


def test_heatmap_decoding_finds_subpixel_gaussian_peaks():
    h, w = 32, 24
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    peaks = np.array([[7.3, 9.6], [12.0, 20.0], [0.4, 20.3]])  # x, y; the last one at the left border
    maps = np.stack([0.9 * np.exp(-((xx - px) ** 2 + (yy - py) ** 2) / (2 * 2.0 ** 2)) for px, py in peaks])
    coords, conf = decode_heatmaps(maps[None])
    np.testing.assert_allclose(coords[0, :2], peaks[:2], atol=0.05)
    # at the left border: x stays on the argmax column, y is refined along the border
    np.testing.assert_allclose(coords[0, 2], [0.0, 20.3], atol=0.05)
    np.testing.assert_allclose(conf[0], maps.reshape(3, -1).max(axis=1))
    flat, _ = decode_heatmaps(np.zeros((1, 1, 4, 4)))  # no peak: no refinement step, no NaN
    np.testing.assert_array_equal(flat[0, 0], [0.0, 0.0])


def test_crop_window_geometry_known_case():
    # a 48x64 box already has the 3:4 input aspect: only the 1.25 padding applies
    centres, sizes = crop_windows(np.array([[10.0, 20.0, 58.0, 84.0]]), 48 / 64)
    np.testing.assert_allclose(centres, [[34.0, 52.0]])
    np.testing.assert_allclose(sizes, [[60.0, 80.0]])
    # a wide box grows in height to the aspect ratio
    _, wide = crop_windows(np.array([[0.0, 0.0, 90.0, 30.0]]), 0.75, padding=1.0)
    np.testing.assert_allclose(wide, [[90.0, 120.0]])
    # first / last grid pixels sit on the window edges; the affine map and its inverse agree
    grid = grid_to_image(np.array([[[0.0, 0.0], [47.0, 63.0]]]), centres, sizes, (64, 48))
    np.testing.assert_allclose(grid[0], [[4.0, 12.0], [64.0, 92.0]])
    m = window_to_grid(centres, sizes, (64, 48))[0]
    pts = np.array([[20.0, 30.0], [50.5, 77.25]])
    back = grid_to_image((pts @ m[:, :2].T + m[:, 2])[None], centres, sizes, (64, 48))
    np.testing.assert_allclose(back[0], pts, atol=1e-9)


def test_vitpose_crop_samples_the_right_pixels(pose):
    # R = x, G = y: the crop's pixel values tell which image pixel each input pixel sampled
    yy, xx = np.mgrid[0:120, 0:160]
    ramp = np.stack([xx, yy, np.zeros_like(xx)], axis=-1).astype(np.uint8)
    box = np.array([[30.0, 20.0, 78.0, 84.0]])  # centre (54, 52), window 60x80
    crops, centres, sizes = pose.crops([ramp], box)
    assert crops.shape == (1, 64, 48, 3)
    i, j = np.array([0, 10, 47]), np.array([0, 30, 63])
    expect = grid_to_image(np.stack([i, j], axis=1)[None].astype(float), centres, sizes, (64, 48))[0]
    np.testing.assert_allclose(crops[0, j, i, 0], expect[:, 0], atol=1.0)
    np.testing.assert_allclose(crops[0, j, i, 1], expect[:, 1], atol=1.0)


def test_vitpose_end_to_end(pose, vitpose_dir, frames):
    boxes = [np.array([[40.0, 10.0, 90.0, 110.0, 0.9]]), np.zeros((0, 5)),
             np.array([[5.0, 5.0, 60.0, 50.0], [np.nan] * 4, [150.0, 100.0, 170.0, 140.0]]),
             np.array([[20.0, 20.0, 20.0, 80.0]])]  # zero width: missing
    seen = []
    hook = pose.model.register_forward_pre_hook(lambda m, a, kw: seen.append(kw["pixel_values"].clone()),
                                                with_kwargs=True)
    try:
        out = pose.estimate(frames, [0, 1, 2, 3], boxes)
    finally:
        hook.remove()
    assert [o.shape for o in out] == [(1, 17, 3), (0, 17, 3), (3, 17, 3), (1, 17, 3)]
    assert pose.input_hw == (64, 48)
    # one pooled batch of the 3 valid boxes, normalised with the folder's mean / std
    crops, _, _ = pose.crops([frames[0], frames[2], frames[2]], np.array([boxes[0][0, :4], boxes[2][0], boxes[2][2]]))
    expect = ((crops.astype(np.float32) / 255 - np.float32(MEAN)) / np.float32(STD)).transpose(0, 3, 1, 2)
    assert len(seen) == 1 and tuple(seen[0].shape) == (3, 3, 64, 48)
    np.testing.assert_allclose(seen[0].numpy(), expect, atol=1e-5)
    np.testing.assert_array_equal(out[2][1], 0.0)
    np.testing.assert_array_equal(out[3][0], 0.0)
    for kp, box in ((out[0][0], boxes[0][0]), (out[2][0], boxes[2][0])):
        assert np.all((kp[:, 2] >= 0) & (kp[:, 2] <= 1)) and np.any(kp[:, 2] > 0)
        c, s = crop_windows(box[None, :4], 0.75)
        assert np.all(np.abs(kp[:, :2] - c) <= s / 2 + 1e-6), "keypoints inside the crop window"
    one = VitPoseKeypoints(vitpose_dir, batch_size=1).estimate(frames, [0, 1, 2, 3], boxes)
    for a, b in zip(out, one):
        np.testing.assert_allclose(a, b, atol=1e-4)


def test_vitpose_refuses_a_non_coco_head(models):
    backbone = transformers.VitPoseBackboneConfig(image_size=[32, 24], patch_size=[8, 8], hidden_size=16,
                                                  num_hidden_layers=1, num_attention_heads=1, out_indices=[1])
    folder = models / "vitpose-5kp"
    transformers.VitPoseForPoseEstimation(transformers.VitPoseConfig(backbone_config=backbone, num_labels=5)
                                          ).save_pretrained(folder)
    with pytest.raises(InputError, match="predicts 5 keypoints"):
        VitPoseKeypoints(folder)


# ------------------------------------------------------------------------------------------------
# SAM 2


def test_sam2_prompt_and_mask_upsampling_known_cases():
    np.testing.assert_allclose(box_prompt(np.array([40.0, 30.0, 120.0, 90.0]), (120, 160), 1024),
                               [[256.0, 256.0], [768.0, 768.0]])
    logits = -torch.ones(8, 8)
    logits[2:6, 2:6] = 1.0
    mask = upsample_mask_logits(torch, logits, (32, 32))
    # low-res pixel j covers hi-res [4j, 4j+4); the 0 crossing between low-res 1 and 2 is at hi-res 7.5
    expect = np.zeros((32, 32), bool)
    expect[8:24, 8:24] = True
    # corners of the block: bilinear weights 0.625^2 on the +1 sample only -> 0.39 - 0.61 < 0
    expect[[8, 8, 23, 23], [8, 23, 8, 23]] = False
    np.testing.assert_array_equal(mask, expect)
    assert upsample_mask_logits(torch, logits, (12, 20)).shape == (12, 20)


def test_sam2_video_propagation(sam2_dir, frames):
    seg = Sam2VideoMasks(sam2_dir)
    assert seg.input_side == 128
    video = [frames[i % 4] for i in range(10)]
    box = np.array([30.0, 10.0, 100.0, 110.0])
    boxes = np.full((10, 4), np.nan)
    boxes[[1, 2, 5, 6, 9]] = box  # unseen at 0 (before any prompt), 3-4 and 7-8 (gaps)
    seen = []
    hook = seg.model.vision_encoder.register_forward_pre_hook(
        lambda m, a, kw: seen.append((a[0] if a else kw["pixel_values"]).clone()), with_kwargs=True)
    try:
        masks = seg.segment(video[:4], list(range(4)), boxes[:4]) + seg.segment(video[4:], list(range(4, 10)), boxes[4:])
    finally:
        hook.remove()
    assert len(masks) == 10 and all(m.shape == (120, 160) and m.dtype == bool for m in masks)
    assert not masks[0].any(), "nothing before the first box"
    assert all(m.any() for m in masks[1:]), "propagated through the gaps"
    assert seg.prompted_frames == [1, 5, 9], "prompted at the first box and after each gap"
    np.testing.assert_allclose(seen[0].numpy(), _expected_input([video[1]], (128, 128)), atol=1e-5)
    # memory does not grow: the current frame's pixels and the last few tracked frames only
    session = seg._session
    assert len(session.processed_frames) == 1
    assert len(session.output_dict_per_obj[0]["non_cond_frame_outputs"]) <= seg._keep
    # one call or two chunks: the same video, the same masks
    whole = Sam2VideoMasks(sam2_dir).segment(video, list(range(10)), boxes)
    for a, b in zip(masks, whole):
        np.testing.assert_array_equal(a, b)
    # frame ids restarting = a new video: starts again without a prompt
    again = seg.segment(video[:2], [0, 1], np.full((2, 4), np.nan))
    assert not again[0].any() and not again[1].any() and seg.prompted_frames == []


# ------------------------------------------------------------------------------------------------
# Loading and factory


def test_missing_model_folder_is_one_line_input_error(tmp_path):
    for role, name in HF_BACKENDS:
        with pytest.raises(InputError) as err:
            make_backend(role, name, model=str(tmp_path / "nope"))
        assert "\n" not in str(err.value) and "no such model folder" in str(err.value)


def test_wrong_model_type_and_unknown_backend(vitpose_dir, rtdetr_dir):
    with pytest.raises(InputError, match="model_type is 'vitpose'"):
        make_backend("detector", "rtdetr", model=vitpose_dir)
    with pytest.raises(InputError, match="model_type is 'rt_detr'"):
        make_backend("masks", "sam2", model=rtdetr_dir)
    with pytest.raises(ValueError, match="unknown transformers backend"):
        make_backend("keypoints", "openpose", model=vitpose_dir)
    built = make_backend("keypoints", "vitpose", model=vitpose_dir, batch_size=4)
    assert isinstance(built, VitPoseKeypoints) and built.batch_size == 4


def test_sequence_stage_runs_with_model_backends(rtdetr_dir, vitpose_dir, sam2_dir, tmp_path, monkeypatch):
    # The stage's model path end to end: RT-DETR boxes -> ViTPose keypoints -> tracking, and SAM 2
    # masks prompted by the performer's boxes. Random weights give arbitrary people, so only the
    # plumbing (shapes, one output per sliced frame, manifest figures) is checked here. The
    # detector comes by its default hub id from the Hugging Face cache (offline), the others from
    # local folders.
    from embodmocap.perception.hub import DEFAULT_MODELS
    from embodmocap.sequence import stage
    from embodmocap.sequence.config import SequenceConfig
    from embodmocap.synth.config import SynthConfig
    from embodmocap.synth.studio import synthesize

    session = tmp_path / "s"
    synthesize(SynthConfig(seed=2, seconds=1.5, scene_seconds=0.5, width=320, height=240,
                           depth_width=64, depth_height=48), session)
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hf-cache"))
    place_in_hub_cache(rtdetr_dir, DEFAULT_MODELS["detector"], tmp_path / "hf-cache")
    cfg = SequenceConfig(detector="rtdetr", offline=True, keypoints="vitpose",
                         keypoints_model=str(vitpose_dir), masks="sam2", masks_model=str(sam2_dir),
                         body_prior="none", min_person_fraction=0.0)
    out = stage.run(cfg, session)
    T = out.figures["frames"]
    for v in ("v1", "v2"):
        kp = np.load(out.layout.view(v).keypoints)
        assert kp["keypoints"].shape == (T, 17, 3) and np.isfinite(kp["keypoints"]).all()
        assert np.load(out.layout.view(v).masks).shape[0] == T
        assert f"{v}_frames_with_person" in out.figures


# ------------------------------------------------------------------------------------------------
# Weights by hub id (embodmocap.perception.hub): the standard cache, offline, the errors


@pytest.fixture()
def hf_cache(tmp_path, monkeypatch):
    """A fresh, empty Hugging Face cache selected the standard way (HF_HUB_CACHE), downloads allowed."""
    cache = tmp_path / "hf-cache"
    monkeypatch.setenv("HF_HUB_CACHE", str(cache))
    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    monkeypatch.delenv("TRANSFORMERS_OFFLINE", raising=False)
    return cache


# Backend name of each role's default model, as Stage II's settings choose it.
_ROLE_BACKENDS = {"detector": "rtdetr", "keypoints": "vitpose", "masks": "sam2", "depth": "promptda"}


@pytest.mark.parametrize("role", sorted(_ROLE_BACKENDS))
def test_missing_default_model_offline_names_id_cache_and_fetch_command(role, hf_cache):
    from embodmocap.perception import registry
    from embodmocap.perception.hub import DEFAULT_MODELS
    from embodmocap.sequence.config import SequenceConfig

    cfg = SequenceConfig(**{role: _ROLE_BACKENDS[role]}, offline=True)  # no *_model: the role's default id
    with pytest.raises(InputError) as err:
        registry.make(role, _ROLE_BACKENDS[role], config=cfg)
    msg, repo_id = str(err.value), DEFAULT_MODELS[role]
    assert "\n" not in msg and msg.startswith(repo_id + ": ")
    assert str(hf_cache) in msg and f"`hf download {repo_id}`" in msg and "--offline" in msg
    assert not hf_cache.exists() or not any(hf_cache.rglob("*.safetensors"))  # nothing fetched, nothing faked


def test_hf_hub_offline_in_the_environment_is_offline(hf_cache, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(InputError, match=r"downloads are off .*`hf download nobody-here/no-such-detector`"):
        make_backend("detector", "rtdetr", model="nobody-here/no-such-detector")  # offline=False, env says off


def test_hub_id_in_a_fresh_cache_loads_offline(rtdetr_dir, detector, frames, hf_cache, monkeypatch):
    # The figure: a backend built from a hub id loads offline once the id is in the cache. The first
    # run's download is replaced by the files a download writes (tests/hub_cache.py), including a
    # repository file the download skips (an original checkpoint), so the offline look-up must ask
    # for the same files the download fetched.
    from huggingface_hub import scan_cache_dir

    from embodmocap.perception import registry
    from embodmocap.perception.hub import DEFAULT_MODELS
    from embodmocap.sequence.config import SequenceConfig

    repo_id = "tiny-org/tiny-rtdetr"
    with pytest.raises(InputError, match="not in the Hugging Face cache"):  # fresh cache: not there yet
        RtDetrPersonDetector(repo_id, offline=True)
    snapshot = place_in_hub_cache(rtdetr_dir, repo_id, hf_cache, extra_files={"rtdetr_r50vd_original.pth": 4096})
    info = scan_cache_dir(hf_cache)
    assert not info.warnings and [r.repo_id for r in info.repos] == [repo_id]

    by_id = RtDetrPersonDetector(repo_id, score_threshold=0.0, offline=True)
    assert by_id.model_dir == snapshot
    for a, b in zip(by_id.detect(frames, range(4)), detector.detect(frames, range(4))):
        np.testing.assert_array_equal(a, b)  # the same weights as the folder it came from

    # Through Stage II's settings, by the role's default id (empty detector_model), offline by flag...
    place_in_hub_cache(rtdetr_dir, DEFAULT_MODELS["detector"], hf_cache)
    built = registry.make("detector", "rtdetr", config=SequenceConfig(detector="rtdetr", offline=True))
    assert built.model_dir.parent.parent.name == "models--PekingU--rtdetr_r50vd_coco_o365"
    # ... and by the environment.
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    again = registry.make("detector", "rtdetr", config=SequenceConfig(detector="rtdetr", detector_model=repo_id))
    assert again.model_dir == snapshot


def test_partial_snapshot_offline_says_what_is_missing(rtdetr_dir, hf_cache):
    place_in_hub_cache(rtdetr_dir, "tiny-org/cut-short", hf_cache, drop=("model.safetensors",))
    with pytest.raises(InputError) as err:
        RtDetrPersonDetector("tiny-org/cut-short", offline=True)
    msg = str(err.value)
    assert "\n" not in msg and "only partly in the Hugging Face cache" in msg and "model.safetensors" in msg
    assert str(hf_cache) in msg


def test_every_model_role_loads_its_hub_id_from_the_cache(vitpose_dir, sam2_dir, hf_cache):
    for role, folder in (("keypoints", vitpose_dir), ("masks", sam2_dir)):
        snapshot = place_in_hub_cache(folder, f"tiny-org/{role}", hf_cache)
        built = make_backend(role, _ROLE_BACKENDS[role], model=f"tiny-org/{role}", offline=True)
        assert built.model_dir == snapshot and built.model.config.model_type in ("vitpose", "sam2_video")


def test_not_a_folder_and_not_a_hub_id(tmp_path):
    with pytest.raises(InputError, match="no such model folder, and not a Hugging Face hub id"):
        make_backend("detector", "rtdetr", model="./models/missing-detector")
