"""Web viewer: a real headless Chromium loads the page; the server holds the expected scene nodes.

The session is the tiny synthetic one of ``test_render`` with Stage IV outputs written from the
ground truth. Chromium is driven through the DevTools protocol (its websocket, with the
``websockets`` package viser depends on) so the screenshot is taken after the scene has arrived,
in real time (``--screenshot`` with a virtual-time budget shot the page before the websocket
messages were drawn).
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from stage4_session import SYNTH, make_stage4_session

viser = pytest.importorskip("viser", reason="the viewer extra is not installed: pip install 'embodmocap[viewer]'")

CHROMIUM = Path("/usr/bin/chromium")
INSTALLER = Path(__file__).resolve().parents[1] / ".ci" / "install-chromium"


def _chromium() -> Path:
    if not CHROMIUM.exists() and INSTALLER.exists():
        subprocess.run(["bash", str(INSTALLER)], check=False, timeout=600)
    if not CHROMIUM.exists():
        pytest.skip("/usr/bin/chromium is missing and .ci/install-chromium could not install it")
    return CHROMIUM


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _coloured_fraction(img: np.ndarray, rgb: tuple[int, int, int], tol: int = 60) -> float:
    """Fraction of pixels within ``tol`` (per channel) of a saturated colour."""
    return float((np.abs(img.astype(int) - rgb).max(axis=-1) < tol).mean())


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("viewer") / "session"
    make_stage4_session(root)
    return root


def test_viewer_serves_the_scene_to_a_browser(session, tmp_path):
    from embodmocap.viz.viewer import ViewerConfig, serve

    _chromium()  # installs it if needed, or skips the test
    handle = serve(session, SYNTH.sequence_name, ViewerConfig(port=_free_port(), max_image_side=160))
    try:
        # Server side: every layer exists, with the data of the first frame.
        scene = handle.server.scene
        assert scene.get_handle_by_name("/scene") is handle.nodes["scene"] is not None
        assert scene.get_handle_by_name("/body") is handle.nodes["body"]
        assert set(handle.nodes["cameras"]) == {"v1", "v2"}
        for v, frustum in handle.nodes["cameras"].items():
            assert scene.get_handle_by_name(f"/cameras/{v}") is frustum
            assert frustum.image is not None and max(frustum.image.shape[:2]) == 160
            np.testing.assert_allclose(frustum.position, handle.data.views[v].T_world_cam[0, :3, 3], atol=1e-5)
        assert scene.get_handle_by_name("/keypoints") is handle.nodes["keypoints"]
        assert len(handle.nodes["keypoints"].points) == 12  # frame 0 lost its 5 face points
        assert scene.get_handle_by_name("/path") is handle.nodes["path"]
        assert handle.nodes["path"].points.shape == (handle.num_frames - 1, 2, 3)

        # The timeline moves the body and the cameras.
        v0 = np.array(handle.nodes["body"].vertices)
        handle.set_frame(5)
        assert handle.frame == 5
        assert np.abs(np.array(handle.nodes["body"].vertices) - v0).max() > 1e-3
        t5 = handle.data.frames[5]
        np.testing.assert_allclose(handle.nodes["cameras"]["v2"].position,
                                   handle.data.views["v2"].T_world_cam[t5, :3, 3], atol=1e-5)
        handle.set_frame(0)

        # Client side: a headless Chromium connects and draws the scene.
        from embodmocap.viz.browser import HeadlessChromium

        with HeadlessChromium(handle.url, tmp_path / "chromium") as tools:
            deadline = time.monotonic() + 30
            while not handle.server.get_clients():
                assert time.monotonic() < deadline, "the browser never connected to the viewer"
                time.sleep(0.05)
            # Software WebGL is slow: poll until the body (blue) and a frustum (red) are drawn.
            img = None
            while time.monotonic() < deadline + 30:
                time.sleep(2.0)
                img = tools.screenshot()
                if _coloured_fraction(img, (110, 170, 255)) > 1e-4 and _coloured_fraction(img, (220, 60, 60)) > 1e-4:
                    break
            assert len(handle.server.get_clients()) == 1
        assert img is not None and img.shape[1] == 1280
        assert img.std() > 20  # not a blank page
        assert len(np.unique(img.reshape(-1, 3) // 16, axis=0)) > 50  # many colours: the scene is drawn
        assert _coloured_fraction(img, (110, 170, 255)) > 1e-4, "body not visible"
        assert _coloured_fraction(img, (220, 60, 60)) > 1e-4, "v1 frustum not visible"
    finally:
        handle.stop()


def test_missing_viewer_input_is_one_clear_error(session, tmp_path):
    from embodmocap.errors import InputError
    from embodmocap.viz.viewer import ViewerConfig, serve

    copy = tmp_path / "s"
    shutil.copytree(session, copy)
    smpl = copy / "sequences" / SYNTH.sequence_name / "smpl_world.npz"
    smpl.unlink()
    with pytest.raises(InputError) as err:
        serve(copy, SYNTH.sequence_name, ViewerConfig(port=_free_port()))
    assert str(smpl) in str(err.value) and "embodmocap motion SESSION" in str(err.value)
