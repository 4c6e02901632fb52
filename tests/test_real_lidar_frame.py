"""A real iPhone LiDAR frame (256x192 float32 TIFF in metres + 1920x1440 JPEG)."""

import cv2
import numpy as np
import pytest

from embodmocap.io.captures.common import depth_to_rgb_scale, read_depth_image
from shared_data import shared_data

DATA = shared_data("iphone_lidar_frame")
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="real data folder not available")


@pytest.fixture(scope="module")
def frame():
    depth = read_depth_image(next(DATA.glob("*_depth.tiff")))
    rgb = cv2.imread(str(next(DATA.glob("*_image.jpg"))), cv2.IMREAD_COLOR)[..., ::-1]
    return depth, rgb


def test_loads_with_expected_sizes_and_scale(frame):
    depth, rgb = frame
    assert depth.dtype == np.float32 and depth.shape == (192, 256)
    assert rgb.shape == (1440, 1920, 3)
    assert depth_to_rgb_scale((rgb.shape[1], rgb.shape[0]), (depth.shape[1], depth.shape[0])) == (7.5, 7.5)


def test_depth_values_are_sane(frame):
    depth, _ = frame
    valid = depth > 0
    assert valid.mean() > 0.9
    assert 0.1 < float(np.median(depth[valid])) < 10.0
    assert float(depth.max()) < 20.0


def test_uint16_png_gives_same_metres(frame, tmp_path):
    depth, _ = frame
    mm = np.round(depth * 1000).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "d.png"), mm)
    np.testing.assert_allclose(read_depth_image(tmp_path / "d.png"), depth, atol=0.0006)


def _grad(img: np.ndarray) -> np.ndarray:
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    return np.hypot(gx, gy)


def test_depth_edges_align_with_rgb_edges(frame):
    """Gradient magnitudes of depth (upsampled 7.5x) and RGB correlate best without a shift."""
    depth, rgb = frame
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY).astype(np.float32)
    # Compare at a quarter of RGB resolution (480x360) to keep it fast.
    small = cv2.resize(grey, (480, 360), interpolation=cv2.INTER_AREA)
    d_up = cv2.resize(np.log(np.maximum(depth, 0.05)), (480, 360), interpolation=cv2.INTER_LINEAR)
    gd = cv2.GaussianBlur(_grad(d_up), (0, 0), 3)
    gr = cv2.GaussianBlur(_grad(small), (0, 0), 3)

    def corr(dx: int, dy: int) -> float:
        m = 24
        a = gd[m:-m, m:-m]
        b = gr[m + dy: gr.shape[0] - m + dy, m + dx: gr.shape[1] - m + dx]
        return float(np.corrcoef(a.ravel(), b.ravel())[0, 1])

    aligned = corr(0, 0)
    shifted = [corr(dx, dy) for dx, dy in ((20, 0), (-20, 0), (0, 20), (0, -20))]
    assert aligned > 0.1
    assert aligned > 1.5 * max(shifted)
