"""Robust kernels on squared residual norms (torch), shared by Stage III and Stage IV losses.

A kernel ``rho(s)`` takes squared residual norms ``s = |r|^2`` (any shape) and a robust scale
``c`` in the residual's unit, and returns a dimensionless cost ``~ s / c^2`` for inliers, so terms
of different units can be summed with plain weights. :func:`irls_weight` is its derivative,
scaled so that an inlier's weight is 1: the weight iteratively reweighted least squares uses.
"""

from __future__ import annotations

import torch

#: Kernel names :func:`robust_rho` and :func:`irls_weight` accept.
ROBUST_KINDS = ("l2", "huber", "geman_mcclure")


def robust_rho(s: torch.Tensor, kind: str, scale: float) -> torch.Tensor:
    """Robust cost of squared residual norms ``s`` (any shape), divided by ``scale**2``.

    ``l2``: s/c^2. ``huber``: quadratic up to |r| = c, linear beyond (C1). ``geman_mcclure``:
    s/(s + c^2), bounded by 1, so gross outliers stop pulling.
    """
    c2 = scale * scale
    if kind == "l2":
        return s / c2
    if kind == "huber":
        # sqrt of a clamped value keeps the unused branch's gradient finite at s = 0.
        r = torch.sqrt(torch.clamp(s, min=c2))
        return torch.where(s <= c2, s / c2, (2.0 * scale * r - c2) / c2)
    if kind == "geman_mcclure":
        return s / (s + c2)
    raise ValueError(f"unknown robust kernel {kind!r}; use one of {ROBUST_KINDS}")


def irls_weight(s: torch.Tensor, kind: str, scale: float) -> torch.Tensor:
    """``d robust_rho / d s`` times ``scale**2``: the IRLS weight of each residual (1 for inliers)."""
    c2 = scale * scale
    if kind == "l2":
        return torch.ones_like(s)
    if kind == "huber":
        return torch.where(s <= c2, torch.ones_like(s), scale / torch.sqrt(torch.clamp(s, min=c2)))
    if kind == "geman_mcclure":
        return c2 * c2 / (s + c2) ** 2
    raise ValueError(f"unknown robust kernel {kind!r}; use one of {ROBUST_KINDS}")
