"""LiDAR-like depth from a perfect depth map: noise, range limit, holes and a confidence map.

Models the iPhone depth stream as seen in Stray Scanner / ARKit exports: uint16 millimetres at
256 x 192 with a 0/1/2 confidence map. Confidence drops on depth edges and at grazing angles (both
show up as a large relative depth change within a pixel's 3x3 neighbourhood) and at far range;
low-confidence pixels get noisier depth, as on the real sensor. Everything is vectorised and
deterministic given the generator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class LidarConfig:
    """The simulated depth sensor."""

    sigma_base_m: float = 0.005
    """Constant part of the depth noise standard deviation, metres."""
    sigma_rel: float = 0.01
    """Depth-proportional part of the noise standard deviation (0.01 = 1 % of the depth)."""
    max_range_m: float = 5.0
    """Farther surfaces read 0 (no return), metres."""
    medium_range_m: float = 3.5
    """Beyond this depth confidence is at most 1 (medium), metres."""
    low_range_m: float = 4.5
    """Beyond this depth confidence is 0 (low), metres."""
    edge_medium: float = 0.04
    """Relative depth spread ``(max - min) / depth`` in a 3x3 window above which confidence is 1."""
    edge_low: float = 0.12
    """Relative depth spread above which confidence is 0 (depth edges, steep grazing angles)."""
    medium_noise_factor: float = 1.5
    """Noise multiplier for medium-confidence pixels."""
    low_noise_factor: float = 3.0
    """Noise multiplier for low-confidence pixels."""
    hole_fraction: float = 0.02
    """Approximate fraction of valid pixels dropped in small blobs (no return), 0..0.2."""
    hole_radius_px: int = 2
    """Radius of the hole blobs, pixels."""


def _spread3(depth: NDArray[np.float32], valid: NDArray[np.bool_]) -> NDArray[np.float32]:
    """Relative depth range ``(max - min) / depth`` over each pixel's 3x3 neighbourhood (invalid
    neighbours count as a jump: they are edges of the valid region)."""
    import cv2

    kernel = np.ones((3, 3), np.uint8)
    hi = cv2.dilate(np.where(valid, depth, 0.0).astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)
    lo = cv2.erode(np.where(valid, depth, np.float32(1e6)).astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)
    with np.errstate(divide="ignore", invalid="ignore"):
        spread = (hi - lo) / np.where(valid, depth, 1.0)
    return np.where(valid, spread, np.inf).astype(np.float32)


def _holes(shape: tuple[int, int], rng: np.random.Generator, cfg: LidarConfig) -> NDArray[np.bool_]:
    """Random small disc-shaped blobs covering about ``cfg.hole_fraction`` of the image."""
    import cv2

    r = max(int(cfg.hole_radius_px), 0)
    area = np.pi * (r + 0.5) ** 2
    n = rng.poisson(cfg.hole_fraction * shape[0] * shape[1] / area)
    seeds = np.zeros(shape, np.uint8)
    seeds[rng.integers(0, shape[0], n), rng.integers(0, shape[1], n)] = 1
    if r == 0:
        return seeds.astype(bool)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.dilate(seeds, disc).astype(bool)


def simulate_lidar(
    depth_m: NDArray[np.float32], rng: np.random.Generator, cfg: LidarConfig = LidarConfig()
) -> tuple[NDArray[np.uint16], NDArray[np.uint8]]:
    """Turn a perfect z-depth map into a LiDAR-like reading.

    Args:
        depth_m: (h, w) float32 true z-depth in metres, 0 where nothing was hit.
        rng: generator for noise and holes.
        cfg: the sensor model.

    Returns:
        ``depth_mm`` (h, w) uint16 millimetres (0 = no reading) and ``confidence`` (h, w) uint8
        (2 high, 1 medium, 0 low; 0 wherever depth is 0).
    """
    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be (h, w), got shape {depth.shape}")
    valid = np.isfinite(depth) & (depth > 0) & (depth <= cfg.max_range_m)
    spread = _spread3(depth, valid)

    conf = np.full(depth.shape, 2, dtype=np.uint8)
    conf[(spread > cfg.edge_medium) | (depth > cfg.medium_range_m)] = 1
    conf[(spread > cfg.edge_low) | (depth > cfg.low_range_m)] = 0

    sigma = cfg.sigma_base_m + cfg.sigma_rel * depth
    factor = np.choose(conf, [np.float32(cfg.low_noise_factor), np.float32(cfg.medium_noise_factor), np.float32(1.0)])
    noisy = depth + (sigma * factor * rng.standard_normal(depth.shape)).astype(np.float32)

    valid &= ~_holes(depth.shape, rng, cfg) & (noisy > 0)
    conf[~valid] = 0
    depth_mm = np.where(valid, np.clip(np.rint(noisy * 1000.0), 1, 65535), 0).astype(np.uint16)
    return depth_mm, conf
