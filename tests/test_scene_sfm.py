"""Stage I sparse model: triangulation with the capture's poses fixed, and the bundle adjustment
that removes the capture's drift from them, on rendered key frames whose scene geometry and true
poses are known exactly."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")
trimesh = pytest.importorskip("trimesh")

from embodmocap.errors import InputError  # noqa: E402
from embodmocap.geometry.transforms import apply_T, invert_T, make_T, rot_z  # noqa: E402
from embodmocap.io.colmap import colmap_camera_params, intrinsics_from_colmap, pixels_from_colmap  # noqa: E402
from embodmocap.scene.adjust import _fit_similarity  # noqa: E402
from embodmocap.scene.sfm import (  # noqa: E402
    SfmConfig,
    build_sparse_model,
    colmap_intrinsics,
    image_poses,
    overlap_matrix,
    read_sparse_model,
    select_pairs,
    sparse_points,
)
from embodmocap.synth import trajectory  # noqa: E402
from embodmocap.synth.render import Renderer  # noqa: E402
from embodmocap.synth.scene import build_scene  # noqa: E402
from embodmocap.types import Intrinsics  # noqa: E402

K = Intrinsics(483.0, 481.0, 321.3, 238.2, 640, 480)
NUM_FRAMES = 24


@pytest.fixture(scope="module")
def keyframes():
    """24 rendered key frames along a 14 s walk around a furnished room, with the room's mesh."""
    built = build_scene("indoor", np.random.default_rng(21))
    # The outward-looking walk (no glances, no turning in across the room): 24 key frames of walls
    # and furniture, as this test was written for.
    T_all = trajectory.scene_walk(built.spec, 14.0, 30.0, np.random.default_rng(21),
                                  trajectory.SceneWalkConfig(glance_every_s=0.0, turns_per_lap=0.0))
    T = T_all[np.linspace(0, len(T_all) - 1, NUM_FRAMES).round().astype(int)]
    renderer = Renderer(built)
    images = [(f"kf_{k:03d}", renderer.render(K, T[k]).rgb) for k in range(NUM_FRAMES)]
    mesh = trimesh.Trimesh(built.vertices, built.faces, process=False)
    return images, T, mesh


@pytest.fixture(scope="module")
def model(keyframes, tmp_path_factory):
    images, T, _ = keyframes
    out = tmp_path_factory.mktemp("sfm") / "sfm"
    # Triangulation alone (poses exactly as given): the tests below check it against the truth.
    return build_sparse_model(images, K, T, out, SfmConfig(refine_poses=False)), out


def _observations(out, names):
    """(image index, our-convention xy, point xyz) of every observation in the written model."""
    rec = pycolmap.Reconstruction(out / "sparse")
    rows, xy, xyz = [], [], []
    for k, name in enumerate(names):
        image = rec.find_image_with_name(name)
        for p in image.points2D:
            if p.has_point3D():
                rows.append(k)
                xy.append(p.xy)
                xyz.append(rec.point3D(p.point3D_id).xyz)
    return np.array(rows), pixels_from_colmap(np.array(xy)), np.array(xyz)


def _project(T_world_cam, intr: Intrinsics, X):
    """Pinhole projection (our convention) of world points X (N, 3) by per-point poses (N, 4, 4)."""
    Xc = np.einsum("nab,nb->na", invert_T(T_world_cam)[:, :3, :3], X) + invert_T(T_world_cam)[:, :3, 3]
    return np.column_stack([intr.fx * Xc[:, 0] / Xc[:, 2] + intr.cx, intr.fy * Xc[:, 1] / Xc[:, 2] + intr.cy])


def test_points_lie_on_the_scene_surface(keyframes, model):
    _, _, mesh = keyframes
    m, out = model
    xyz, rgb, track, err = sparse_points(out)
    assert m.num_points == len(xyz) >= 2000
    assert xyz.shape == (m.num_points, 3) and rgb.dtype == np.uint8 and track.min() >= 2
    _, dist, _ = trimesh.proximity.closest_point(mesh, xyz)
    assert np.median(dist) < 0.01
    assert np.mean(dist < 0.05) > 0.95
    assert m.mean_track_length == pytest.approx(track.mean())
    assert np.all(m.observations_per_image > 0)


def test_poses_and_intrinsics_are_untouched(keyframes, model):
    _, T, _ = keyframes
    m, out = model
    poses = image_poses(out)
    assert set(poses) == set(m.image_names) and len(poses) == NUM_FRAMES
    for k, name in enumerate(m.image_names):
        np.testing.assert_allclose(poses[name], T[k], atol=1e-9)
    back = colmap_intrinsics(out)
    np.testing.assert_allclose([back.fx, back.fy, back.cx, back.cy], [K.fx, K.fy, K.cx, K.cy], atol=1e-12)
    assert (back.width, back.height) == (K.width, K.height)


def test_reprojection_error_with_our_camera(keyframes, model):
    _, T, _ = keyframes
    m, out = model
    names = list(m.image_names)
    rows, xy, xyz = _observations(out, names)
    res = np.linalg.norm(_project(T[rows], K, xyz) - xy, axis=1)
    assert m.mean_reproj_error_px < 1.5
    # COLMAP's figure is the mean of per-point means; ours is per observation: close, not equal.
    assert res.mean() < 1.5 and res.mean() == pytest.approx(m.mean_reproj_error_px, rel=0.25)
    np.testing.assert_array_equal(np.bincount(rows, minlength=len(names)), m.observations_per_image)


def test_pixel_centre_convention_against_ground_truth(keyframes, model):
    """Observations, moved into our convention, sit where the true surface point projects with our K
    (measured: median offset ~0.005 px; COLMAP's raw coordinates would be 0.5 px off in x and y)."""
    _, T, mesh = keyframes
    m, out = model
    rows, xy, xyz = _observations(out, list(m.image_names))
    surface, _, _ = trimesh.proximity.closest_point(mesh, xyz)
    signed = xy - _project(T[rows], K, surface)
    assert np.all(np.abs(np.median(signed, axis=0)) < 0.1)


def test_colmap_camera_projects_half_a_pixel_off():
    params = colmap_camera_params(K)
    cam = pycolmap.Camera(model="PINHOLE", width=K.width, height=K.height, params=params)
    X = np.array([[0.3, -0.2, 2.0], [-1.0, 0.5, 3.5], [0.0, 0.0, 1.0]])
    ours = (K.K @ X.T).T
    ours = ours[:, :2] / ours[:, 2:]
    colmap = np.array([cam.img_from_cam(x) for x in X])[:, :2]
    np.testing.assert_allclose(pixels_from_colmap(colmap), ours, atol=1e-9)
    back = intrinsics_from_colmap(params, K.width, K.height)
    assert back == K


def test_feature_threads_give_the_same_database_and_model(keyframes, model, tmp_path):
    """SIFT extraction and matching on one thread give the files the default (two threads) gave,
    bit for bit: image ids fixed before extraction, the database rewritten in key order."""
    from embodmocap.io.stage_manifest import file_digest

    images, T, _ = keyframes
    _, out = model
    one = tmp_path / "sfm"
    build_sparse_model(images, K, T, one, SfmConfig(refine_poses=False, feature_threads=1))
    files = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file() and p.name != "summary.json")
    assert Path("database.db") in files and Path("sparse/points3D.bin") in files
    for rel in files:
        assert file_digest(one / rel) == file_digest(out / rel), rel


def test_model_and_database_reopen(keyframes, model):
    m, out = model
    again = read_sparse_model(out)
    assert again.image_names == m.image_names and again.num_points == m.num_points
    assert again.mean_reproj_error_px == pytest.approx(m.mean_reproj_error_px)
    np.testing.assert_array_equal(again.observations_per_image, m.observations_per_image)
    assert set(again.seconds) == {"write_images", "extract", "pairs", "match", "triangulate", "finish"}
    assert m.database_path == out / "database.db" and m.model_dir == out / "sparse"
    assert all((out / "images" / n).is_file() for n in m.image_names)
    with pycolmap.Database.open(m.database_path) as db:
        assert db.num_images() == NUM_FRAMES and db.num_cameras() == 1
        assert db.num_verified_image_pairs() == m.num_verified_pairs > 0
        assert all(db.num_keypoints_for_image(im.image_id) > 100 for im in db.read_all_images())
    pairs = (out / "pairs.txt").read_text().split("\n")[:-1]
    assert len(pairs) == m.num_pairs
    summary = json.loads((out / "summary.json").read_text())
    assert summary["format_version"] == 1 and summary["quality"]["sfm_points"] == m.num_points
    assert not any(p.name.startswith(".") for p in out.parent.iterdir())  # no temp folders left


def test_folder_input_exhaustive_and_thinning(keyframes, tmp_path):
    import cv2

    images, T, _ = keyframes
    src = tmp_path / "kf"
    src.mkdir()
    for name, rgb in images[4:10]:
        cv2.imwrite(str(src / f"{name}.png"), rgb[..., ::-1])
    before = {p.name: p.read_bytes() for p in src.iterdir()}
    cfg = SfmConfig(pairing="exhaustive", max_images=4)
    m = build_sparse_model(src, K, T[4:10], tmp_path / "out", cfg)
    assert m.image_names == ("kf_004.png", "kf_006.png", "kf_007.png", "kf_009.png")
    assert m.num_pairs == 6 and m.num_points > 100
    poses = image_poses(tmp_path / "out")
    for name, k in zip(m.image_names, [4, 6, 7, 9]):
        np.testing.assert_allclose(poses[name], T[k], atol=1e-9)
    assert {p.name: p.read_bytes() for p in src.iterdir()} == before  # input untouched
    # Rebuilding into the same folder replaces the previous model whole.
    again = build_sparse_model(src, K, T[4:10], tmp_path / "out", SfmConfig(pairing="exhaustive", max_images=3))
    assert again.image_names == ("kf_004.png", "kf_006.png", "kf_009.png")
    assert sorted(p.name for p in (tmp_path / "out" / "images").iterdir()) == list(again.image_names)
    with pytest.raises(InputError, match="inside the SfM output folder"):
        build_sparse_model(tmp_path / "out" / "images", K, T[:4], tmp_path / "out", cfg)


def _reference_overlap(T, intr, depths):
    """Plain-loop version of overlap_matrix."""
    us = np.array([1, 3, 5]) * intr.width / 6 - 0.5
    vs = np.array([1, 3, 5]) * intr.height / 6 - 0.5
    n = len(T)
    out = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            seen = []
            for d in depths:
                for v in vs:
                    for u in us:
                        p = np.array([(u - intr.cx) / intr.fx * d, (v - intr.cy) / intr.fy * d, d])
                        q = apply_T(invert_T(T[j]), apply_T(T[i], p[None]))[0]
                        x, y = intr.fx * q[0] / q[2] + intr.cx, intr.fy * q[1] / q[2] + intr.cy
                        seen.append(q[2] > 0.05 and -0.5 <= x <= intr.width - 0.5 and -0.5 <= y <= intr.height - 0.5)
            out[i, j] = np.mean(seen)
    return out


def test_pairs_follow_viewing_direction_and_overlap(keyframes):
    # Cameras at one spot looking horizontally (OpenCV: z forward), yawed by 0, 20, 40, 110, 180 deg.
    look_x = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)
    yaws = np.deg2rad([0, 20, 40, 110, 180])
    T = make_T(rot_z(yaws) @ look_x, np.zeros((5, 3)))
    ov = overlap_matrix(T, K)
    np.testing.assert_allclose(ov, _reference_overlap(T, K, (1.0, 2.0, 3.0)))
    np.testing.assert_allclose(np.diag(ov), 1.0)
    pairs = {tuple(p) for p in select_pairs(T, K, SfmConfig(max_view_angle_deg=60.0, min_overlap=0.1))}
    assert pairs == {(0, 1), (0, 2), (1, 2)}
    # With one neighbour each, the 40-degree pair is never anyone's best.
    pairs = {tuple(p) for p in select_pairs(T, K, SfmConfig(num_neighbours=1, min_overlap=0.1))}
    assert pairs == {(0, 1), (1, 2)}
    # On the walk, every key frame gets a partner and pairs come out sorted and unique.
    _, T_walk, _ = keyframes
    P = select_pairs(T_walk, K)
    assert np.all(P[:, 0] < P[:, 1]) and len(np.unique(P, axis=0)) == len(P)
    assert set(P.ravel()) == set(range(NUM_FRAMES))
    np.testing.assert_allclose(overlap_matrix(T_walk[:6], K), _reference_overlap(T_walk[:6], K, (1.0, 2.0, 3.0)))


def test_bad_input(keyframes, tmp_path):
    images, T, _ = keyframes
    with pytest.raises(InputError, match="at least 2"):
        build_sparse_model(images[:1], K, T[:1], tmp_path / "a")
    blank = [(f"b{k}", np.full((K.height, K.width, 3), 128, np.uint8)) for k in range(3)]
    with pytest.raises(InputError, match="SIFT features"):
        build_sparse_model(blank, K, T[:3], tmp_path / "b")
    with pytest.raises(InputError, match="poses of shape"):
        build_sparse_model(images[:3], K, T[:2], tmp_path / "c")
    bad_T = T[:3].copy()
    bad_T[0, :3, :3] *= 2.0
    with pytest.raises(InputError, match="rigid"):
        build_sparse_model(images[:3], K, bad_T, tmp_path / "d")
    small = [(n, rgb[::2, ::2]) for n, rgb in images[:3]]
    with pytest.raises(InputError, match="expected uint8"):
        build_sparse_model(small, K, T[:3], tmp_path / "e")
    with pytest.raises(InputError, match="repeat"):
        build_sparse_model([images[0], images[0]], K, T[:2], tmp_path / "f")
    with pytest.raises(InputError, match="no COLMAP model"):
        read_sparse_model(tmp_path / "nothing")
    assert not any((tmp_path / x).exists() for x in "abcdef")  # failed runs leave nothing behind
    precious = tmp_path / "g"
    precious.mkdir()
    (precious / "notes.txt").write_text("keep me")
    with pytest.raises(InputError, match="does not hold a sparse model"):
        build_sparse_model(images[:3], K, T[:3], precious)
    assert (precious / "notes.txt").read_text() == "keep me"


def test_fit_similarity_recovers_a_known_similarity():
    rng = np.random.default_rng(5)
    T = np.stack([make_T(rot_z(a), rng.uniform(-3, 3, 3)) for a in rng.uniform(-np.pi, np.pi, 12)])
    S = make_T(rot_z(0.3) @ _rx(0.02), np.array([0.5, -1.0, 0.2]))
    S[:3, :3] *= 1.01
    moved = S @ T
    moved[:, :3, :3] /= 1.01  # camera rotations stay rotations; the scale acts on the centres
    np.testing.assert_allclose(_fit_similarity(T, moved), S, atol=1e-9)


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _drifted(T):
    """Key frame poses with a VIO-like drift (1.5 cm and 0.12 deg by the end of the 14 s walk, zero
    at its start, where the VIO world is set) and their capture times."""
    s = np.linspace(0, 1, len(T))
    drift = np.stack([make_T(rot_z(np.radians(0.12) * k), np.array([0.015, -0.01, 0.003]) * k**1.5) for k in s])
    return drift @ T, 14.0 * s


def test_adjustment_with_the_vio_prior_removes_drift_from_the_key_frames(keyframes, tmp_path):
    """The adjusted model's key frames sit on the true ones (no similarity allowed: the first key
    frame fixes the world, as the capture's VIO world is set at its start), far closer than the
    drifted input; the correction is recorded for the mesh's fusion."""
    images, T, _ = keyframes
    T_in, times = _drifted(T)
    model = build_sparse_model(images, K, T_in, tmp_path / "sfm", SfmConfig(refine_poses=True), times_s=times)
    poses = image_poses(tmp_path / "sfm")
    T_out = np.stack([poses[n] for n in model.image_names])
    before = np.linalg.norm(T_in[:, :3, 3] - T[:, :3, 3], axis=1)
    after = np.linalg.norm(T_out[:, :3, 3] - T[:, :3, 3], axis=1)
    assert before.max() > 0.012
    assert np.median(after) < 0.5 * np.median(before) and after.max() < 0.6 * before.max()
    drift = json.loads((tmp_path / "sfm" / "summary.json").read_text())["drift_correction"]
    assert drift["accepted"] and drift["gain"] > 0.01 and drift["prior_rms"] < 2.0
    C = np.asarray(drift["T_correction"])
    np.testing.assert_allclose(C @ T_in, T_out, atol=1e-6)  # the recorded correction is the model's


def test_adjustment_that_disagrees_with_the_vio_is_not_used(keyframes, tmp_path):
    """One key frame 8 cm off its neighbours (a tracking glitch, not drift): the images pull it back
    further than VIO can drift in 0.6 s, so the correction is refused and the capture's poses kept."""
    images, T, _ = keyframes
    T_in = T.copy()
    T_in[12, :3, 3] += np.array([0.08, 0.0, 0.0])
    build_sparse_model(images, K, T_in, tmp_path / "sfm", SfmConfig(refine_poses=True),
                       times_s=np.linspace(0, 14, len(T)))
    drift = json.loads((tmp_path / "sfm" / "summary.json").read_text())["drift_correction"]
    assert not drift["accepted"] and "VIO" in drift["reason"]
    poses = image_poses(tmp_path / "sfm")
    names = json.loads((tmp_path / "sfm" / "summary.json").read_text())["image_names"]
    np.testing.assert_allclose(np.stack([poses[n] for n in names]), T_in, atol=1e-9)
