"""Helpers that moved into shared packages: ray casting (geometry.raycast), robust kernels
(geometry.robust), COLMAP pixel conversions (io.colmap), picking a scene or sequence
(SessionManifest.sequence / .scene)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from embodmocap.errors import InputError
from embodmocap.geometry.raycast import camera_ray_dirs, cast_rays, pixel_rays, raycasting_scene
from embodmocap.geometry.robust import irls_weight, robust_rho
from embodmocap.io.colmap import colmap_camera_params, intrinsics_from_colmap, pixels_from_colmap, pixels_to_colmap
from embodmocap.io.manifest import SceneEntry, SequenceEntry, SessionManifest, ViewEntry
from embodmocap.types import Intrinsics

K = Intrinsics(400.0, 410.0, 31.5, 23.0, 64, 48)


def test_pixel_rays_and_mesh_hits_agree_with_plain_geometry():
    # A camera 3 m above a floor square, looking straight down (OpenCV z = world -z).
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [0.2, -0.1, 3.0]
    xy = np.array([[0.0, 0.0], [31.5, 23.0], [63.0, 47.0]])
    c, d = pixel_rays(K.K, T, xy)
    # Reference: one pixel at a time, K^-1 [u, v, 1] rotated into the world, normalised.
    for i, (u, v) in enumerate(xy):
        ref = T[:3, :3] @ np.array([(u - K.cx) / K.fx, (v - K.cy) / K.fy, 1.0])
        np.testing.assert_allclose(d[i], ref / np.linalg.norm(ref), atol=1e-12)
        np.testing.assert_allclose(c[i], T[:3, 3])
    floor = raycasting_scene(np.array([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], float),
                             np.array([[0, 1, 2], [0, 2, 3]]))
    hit = cast_rays(floor, T[:3, 3], d)
    np.testing.assert_allclose(c + hit["t_hit"][:, None] * d, np.c_[(c + 3.0 * d / -d[:, 2:3])[:, :2], np.zeros(3)],
                               atol=1e-5)
    # Unit-z camera directions: the hit distance is the z-depth (3 m everywhere on the floor).
    dirs = (T[:3, :3] @ camera_ray_dirs(K)).T
    np.testing.assert_allclose(cast_rays(floor, T[:3, 3], dirs)["t_hit"], 3.0, atol=1e-5)


def test_robust_kernels_are_quadratic_for_inliers_and_irls_is_their_slope():
    s = torch.tensor([0.0, 0.25, 4.0, 100.0], dtype=torch.float64, requires_grad=True)
    for kind in ("l2", "huber", "geman_mcclure"):
        rho = robust_rho(s, kind, 1.0)
        (g,) = torch.autograd.grad(rho.sum(), s)
        torch.testing.assert_close(g, irls_weight(s.detach(), kind, 1.0))
        assert float(rho[1]) == pytest.approx(0.25 if kind != "geman_mcclure" else 0.2)
    with pytest.raises(ValueError, match="unknown robust kernel"):
        robust_rho(s, "cauchy", 1.0)


def test_colmap_conversions_are_inverse():
    back = intrinsics_from_colmap(colmap_camera_params(K), K.width, K.height)
    assert back == K
    xy = np.random.default_rng(1).random((5, 2)) * 50
    np.testing.assert_allclose(pixels_from_colmap(pixels_to_colmap(xy)), xy)
    assert colmap_camera_params(K)[2] == K.cx + 0.5


def test_manifest_picks_the_only_or_the_named_entry(tmp_path):
    view = ViewEntry(capture=tmp_path / "c")
    seq = lambda n: SequenceEntry(name=n, scene="room", views={"v1": view, "v2": view})  # noqa: E731
    m = SessionManifest(tmp_path, scenes={"room": SceneEntry("room", tmp_path / "s")}, sequences={"a": seq("a")})
    assert m.sequence().name == "a" and m.sequence("a").name == "a" and m.scene().name == "room"
    with pytest.raises(InputError, match=r"session.toml: no sequence named 'b' \(sequences in this session: a\)"):
        m.sequence("b")
    two = SessionManifest(tmp_path, scenes=m.scenes, sequences={"a": seq("a"), "b": seq("b")})
    with pytest.raises(InputError, match="2 sequences in the session.*--seq"):
        two.sequence()
    with pytest.raises(InputError, match="no scene named 'hall'.*scenes in this session: room"):
        m.scene("hall")
