"""Overlay videos: the drawn body lands on the performer's true silhouette; MP4s decode as expected.

The session is a tiny synthetic one whose Stage IV outputs are written straight from the ground
truth (true body, true cameras), so the overlay must coincide with the person in the frames.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from embodmocap.errors import InputError
from embodmocap.io.layout import VIEWS, SessionLayout
from embodmocap.io.video import VideoReader
from embodmocap.types import PngMasks

from stage4_session import SYNTH, make_stage4_session  # noqa: E402  (tests/ helper module)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("render") / "session"
    return root, make_stage4_session(root)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


def _erode(mask: np.ndarray, px: int) -> np.ndarray:
    return cv2.erode(mask.astype(np.uint8), np.ones((2 * px + 1, 2 * px + 1), np.uint8)).astype(bool)


def _projected_triangles(K, T_world_cam, verts, faces, up: int = 5) -> np.ndarray:
    """Reference silhouette, independent of the ray caster: every projected triangle filled with
    OpenCV on a grid ``up`` times finer (odd), then sampled at the pixel centres (no occlusion).

    OpenCV fills the pixels an edge touches, so at full resolution it overfills by up to a pixel;
    on the fine grid that is 1/up pixel. Pixel centre x sits at fine pixel ``up * x + up // 2``.
    """
    pc = (verts - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    uv = pc[:, :2] / pc[:, 2:] * [K.fx, K.fy] + [K.cx, K.cy]
    fine = (uv + 0.5) * up - 0.5
    mask = np.zeros((K.height * up, K.width * up), np.uint8)
    shift = 4  # sub-pixel vertex positions (OpenCV fixed point)
    # One call per triangle: a single fillPoly over all of them applies the even-odd rule, and
    # overlapping triangles would cancel.
    for tri in np.round(fine[faces] * (1 << shift)).astype(np.int32):
        cv2.fillConvexPoly(mask, tri, 1, lineType=cv2.LINE_8, shift=shift)
    return mask[up // 2::up, up // 2::up].astype(bool)


def _studio_renderer(root: Path):
    """The studio's own renderer of the session's scene, for noise-free person masks.

    The studio builds its scene from the generator ``[seed, 1]``; the test checks that the rebuilt
    scene is the ground-truth mesh before trusting it.
    """
    from embodmocap.io.mesh_file import read_mesh_ply
    from embodmocap.synth.render import Renderer
    from embodmocap.synth.scene import build_scene

    built = build_scene(SYNTH.preset, np.random.default_rng([SYNTH.seed, 1]))
    v, f, _ = read_mesh_ply(SessionLayout(root).ground_truth.scene_mesh(SYNTH.scene_name))
    assert v.shape == built.vertices.shape and np.allclose(v, built.vertices) and np.array_equal(f, built.faces)
    return Renderer(built)


def test_silhouette_matches_the_true_person(session):
    from embodmocap.body.model import load_body_model
    from embodmocap.viz import BodyFrames, load_sequence
    from embodmocap.viz.render import RenderConfig, _occluder, body_pixels

    root, facts = session
    data = load_sequence(root, SYNTH.sequence_name)
    body = BodyFrames(load_body_model(data.body_model), data.params, chunk=4)
    faces = body.faces
    occ = _occluder(root, data, RenderConfig())
    assert occ is not None
    studio = _studio_renderer(root)
    lay = SessionLayout(root)
    checked = 0
    for v in VIEWS:
        cams = data.views[v]
        masks = PngMasks(tuple(lay.perception(SYNTH.sequence_name, v).mask_png(i) for i in range(200)))
        for i in range(0, facts["T"], 3):
            raw, T, verts = int(cams.raw_frames[i]), cams.T_world_cam[i], body.vertices(i)
            drawn = body_pixels(cams.intrinsics, T, verts, faces, occ).mask
            # The studio's exact person mask (nearest surface is the body; furniture occludes).
            exact = studio.render(cams.intrinsics, T, (verts, faces)).person_mask
            assert exact.sum() > 500
            assert _iou(drawn, exact) > 0.9
            # The capture's mask PNG is that mask with its edge moved by at most 5 px (noise):
            # the cores must nest both ways.
            noisy = masks.mask(raw)
            assert (_erode(drawn, 5) & ~noisy).sum() <= 0.01 * drawn.sum()
            assert (_erode(noisy, 5) & ~drawn).sum() <= 0.01 * noisy.sum()
            # Without occlusion, against an independent rasterisation of the projected triangles.
            bare = body_pixels(cams.intrinsics, T, verts, faces, None).mask
            assert _iou(bare, _projected_triangles(cams.intrinsics, T, verts, faces)) > 0.97
            checked += 1
    assert checked >= 8


def test_render_writes_decodable_overlays(session):
    from embodmocap.viz.render import RenderConfig, render_sequence

    root, facts = session
    cfg = RenderConfig(progress=False, alpha=1.0)
    paths = render_sequence(root, SYNTH.sequence_name, cfg)
    out = SessionLayout(root).sequence(SYNTH.sequence_name).renders_dir
    assert paths == [out / "v1_overlay.mp4", out / "v2_overlay.mp4", out / "side_by_side.mp4"]
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in paths)  # no temp files left
    sizes = [(SYNTH.width, SYNTH.height)] * 2 + [(2 * SYNTH.width, SYNTH.height)]
    for path, (w, h) in zip(paths, sizes):
        with VideoReader(path) as r:
            assert (r.info.num_frames, r.info.width, r.info.height) == (facts["T"], w, h)
            assert r.info.fps == pytest.approx(SYNTH.fps)
            frame = r.read(facts["T"] // 2)
        assert frame.shape == (h, w, 3)
    # An opaque body: the video's pixels inside the drawn body carry the body's blue colour.
    from embodmocap.body.model import load_body_model
    from embodmocap.viz import BodyFrames, load_sequence
    from embodmocap.viz.render import _occluder, body_pixels

    data = load_sequence(root, SYNTH.sequence_name)
    t = facts["T"] // 2
    verts = BodyFrames(load_body_model(data.body_model), data.params).vertices(t)
    cams = data.views["v1"]
    mask = body_pixels(cams.intrinsics, cams.T_world_cam[t], verts, np.asarray(load_body_model(data.body_model).faces),
                       _occluder(root, data, cfg)).mask
    with VideoReader(paths[0]) as r:
        frame = r.read(t).astype(float)
    core = _erode(mask, 2)
    assert core.sum() > 50
    b_minus_r = frame[..., 2] - frame[..., 0]
    assert b_minus_r[core].mean() > 40  # the body colour (110, 170, 255) is strongly blue
    assert b_minus_r[core].mean() > b_minus_r[~mask].mean() + 30


def test_missing_stage4_output_names_the_file(session, tmp_path):
    from embodmocap.viz.render import render_sequence

    root, _ = session
    copy = tmp_path / "s"
    shutil.copytree(root, copy, ignore=shutil.ignore_patterns("render"))
    missing = SessionLayout(copy).sequence(SYNTH.sequence_name).view("v2").cameras_final
    missing.unlink()
    with pytest.raises(InputError) as err:
        render_sequence(copy, SYNTH.sequence_name)
    assert str(missing) in str(err.value)
    assert f"embodmocap motion SESSION --seq {SYNTH.sequence_name}" in str(err.value)
    assert not SessionLayout(copy).sequence(SYNTH.sequence_name).renders_dir.exists()
