"""The metric scale of a stitched segment from the body: ``m = median(z_body / z_map)``.

The body (camera frame, metres: the human model is metric) is ray-cast at the point map's own
pixels (the RGB intrinsics scaled to the map's size, pixel-centre convention), which samples the
body's visible surface, vertex-exact, at the rays where the map has its points. A pixel
counts when it is inside the person mask (the RGB mask at the pixel's centre), inside the body's
rendered silhouette by ``erode_px`` pixels (no silhouette edge), its map confidence reaches
``min_conf`` and the map's depth is smooth around it (3x3 spread within ``max_edge_rel``: no
object in front of the person). For each such pixel ``u`` of frame ``i``:
``r = z_body(u) / (s_k z_map(u))`` with ``s_k`` the scale of the chunk's stitching similarity (so
``s_k z_map`` is in stitched units). The segment's metric scale is the median over frames of each frame's median
ratio, ``m = median_i median_u r_i(u)`` (metres per stitched unit), over the frames whose person
mask covers at least ``min_frame_samples`` map pixels (chosen by the mask, not by the body's own
pixels: a regressor that puts the body too near draws it larger, and choosing frames by its pixel
count kept those frames preferentially, 2 % low on a 20 s studio view). The paper writes one flat median over all samples (and its inverse,
``s = median(z_Pi3 / z_SMPL) = 1 / m``); a flat median weights each frame by its body pixels, and a
regressor that puts the body too near draws it larger, so it is biased towards those frames (5 %
on a 60 s studio view with the realistic prior); a median of frame medians is not.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import binary_erosion, maximum_filter, minimum_filter

from embodmocap.mono.config import ScaleConfig
from embodmocap.types import Intrinsics


def depth_ratios(verts_cam: NDArray, faces: NDArray, z_map: NDArray, conf: NDArray, masks: NDArray, K: NDArray,
                 rgb_size: tuple[int, int], chunk_scale: float, cfg: ScaleConfig) -> NDArray[np.float64]:
    """Samples ``z_body / (chunk_scale z_map)`` of n frames (see the module).

    Args:
        verts_cam: (n, V, 3) body vertices in each frame's camera frame, metres; ``faces`` (F, 3).
        z_map: (n, H, W) local point-map depth (the chunk's units).
        conf: (n, H, W) point-map confidence.
        masks: (n, H_rgb, W_rgb) bool person masks.
        K: (3, 3) RGB intrinsics; ``rgb_size`` = (W_rgb, H_rgb).
        chunk_scale: scale of the chunk's stitching similarity.

    Returns:
        Per frame, the (S_i,) ratios (metres per stitched unit), and (n,) the number of map pixels
        the person mask covers (which frames vote, see :func:`summarise`).
    """
    from embodmocap.geometry.raycast import depth_map

    n, H, W = z_map.shape
    Wr, Hr = rgb_size
    Km = Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], Wr, Hr).scaled(W, H)
    ur = np.clip(np.rint((np.arange(W) + 0.5) * Wr / W - 0.5), 0, Wr - 1).astype(np.int64)
    vr = np.clip(np.rint((np.arange(H) + 0.5) * Hr / H - 0.5), 0, Hr - 1).astype(np.int64)
    out, covered = [], np.zeros(n, dtype=np.int64)
    for i in range(n):
        person = masks[i][vr][:, ur]
        covered[i] = int(person.sum())
        zb = depth_map(verts_cam[i], faces, Km, np.eye(4)).astype(np.float64)
        body = np.isfinite(zb)
        if not body.any():
            out.append(np.zeros(0))
            continue
        if cfg.erode_px > 0:
            body = binary_erosion(body, iterations=cfg.erode_px)
        zm = np.asarray(z_map[i], dtype=np.float64)
        ok = body & person & (conf[i] >= cfg.min_conf) & (zm > 0)
        if not ok.any():
            out.append(np.zeros(0))
            continue
        spread = maximum_filter(zm, size=3) - minimum_filter(zm, size=3)
        ok &= spread <= cfg.max_edge_rel * zm
        out.append(zb[ok] / (chunk_scale * zm[ok]))
    return out, covered


def summarise(per_frame: list[NDArray], covered: NDArray | None = None, min_frame_samples: int = 10,
              frames: NDArray | None = None, fps: float = 30.0, block_s: float = 2.0) -> dict:
    """The scale (median of the frames' median ratios) and its spread over frames: ``scale``,
    ``mad_rel`` (1.4826 MAD / median of the frame medians), ``p10``, ``p90`` (of the frame medians),
    ``samples`` (pixels used), ``frames`` (frames voting: ``covered`` (mask pixels) at least
    ``min_frame_samples`` and at least one ratio; without ``covered``, the ratios' own count),
    ``se_rel`` (the scale's relative standard error, :func:`block_se_rel`, from the voting frames'
    sequence frame numbers ``frames`` (n,) at ``fps``; their list positions without ``frames``)."""
    meds, ids, n = [], [], 0
    for i, r in enumerate(per_frame):
        r = np.asarray(r, dtype=np.float64)
        r = r[np.isfinite(r)]
        count = r.size if covered is None else int(covered[i])
        if count >= min_frame_samples and r.size:
            meds.append(np.median(r))
            ids.append(i if frames is None else int(frames[i]))
            n += r.size
    if not meds:
        return {"scale": float("nan"), "mad_rel": float("nan"), "p10": float("nan"), "p90": float("nan"),
                "samples": 0, "frames": 0, "se_rel": float("nan")}
    f = np.asarray(meds)
    m = float(np.median(f))
    return {"scale": m, "mad_rel": float(1.4826 * np.median(np.abs(f - m)) / m), "p10": float(np.percentile(f, 10)),
            "p90": float(np.percentile(f, 90)), "samples": int(n), "frames": int(f.size),
            "se_rel": block_se_rel(f, np.asarray(ids), fps, block_s)}


def block_se_rel(values: NDArray, frames: NDArray, fps: float, block_s: float) -> float:
    """Relative standard error of ``median(values)`` when neighbouring frames' errors are correlated
    (a regressor's depth error drifts over a fraction of a second, so 600 frames are not 600
    independent votes): the frames are cut into blocks of ``block_s`` seconds by frame number,
    each block votes with its median, and ``se = 1.2533 * 1.4826 MAD(block medians) / sqrt(blocks)``
    (the median's standard error for Gaussian votes), over the median of ``values``. NaN with fewer
    than 3 blocks.

    Args:
        values: (n,) per-frame estimates; ``frames`` (n,) their sequence frame numbers.
    """
    v = np.asarray(values, dtype=np.float64)
    fr = np.asarray(frames, dtype=np.float64)
    ok = np.isfinite(v)
    v, fr = v[ok], fr[ok]
    if v.size == 0:
        return float("nan")
    block = np.floor(fr / max(block_s * fps, 1.0)).astype(np.int64)
    meds = np.array([np.median(v[block == b]) for b in np.unique(block)])
    if len(meds) < 3:
        return float("nan")
    mad = 1.4826 * np.median(np.abs(meds - np.median(meds)))
    return float(1.2533 * mad / np.sqrt(len(meds)) / np.median(v))


def combine_cues(cues: dict[str, dict]) -> dict:
    """One scale from several cues' scales: the inverse-variance weighted mean of their logarithms,
    weights ``1 / se_rel^2`` (each cue's own :func:`block_se_rel`, floored at 1e-9: an exact cue
    takes all the weight). Cues without a finite positive scale are left out; cues without a finite
    standard error (too short for 3 blocks) too, unless no cue has one: then equal weights.
    Returns ``scale`` (NaN when no cue is left), ``se_rel`` (the combination's, as if the cues'
    errors were independent: a lower bound when they share the body model's depth error; NaN with
    equal weights) and ``weights`` (per cue name, summing to 1)."""
    use = {k: c for k, c in cues.items() if np.isfinite(c.get("scale", np.nan)) and c["scale"] > 0}
    with_se = {k: c for k, c in use.items() if np.isfinite(c.get("se_rel", np.nan))}
    if not use:
        return {"scale": float("nan"), "se_rel": float("nan"), "weights": {}}
    if with_se:
        w = {k: 1.0 / max(c["se_rel"], 1e-9) ** 2 for k, c in with_se.items()}
    else:
        w = {k: 1.0 for k in use}
    tot = sum(w.values())
    log_m = sum(w[k] * np.log(use[k]["scale"]) for k in w) / tot
    return {"scale": float(np.exp(log_m)), "se_rel": float(1.0 / np.sqrt(tot)) if with_se else float("nan"),
            "weights": {k: round(v / tot, 4) for k, v in w.items()}}
