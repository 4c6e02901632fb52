"""Stage III joint refinement of each view's yaw + translation offset.

Parameters: per view ``[yaw, tx, ty, tz]`` (radians, metres), the correction on top of the
initial (registration) offset, all starting at 0; rotation about the view's mean camera centre
(see :mod:`embodmocap.calibrate.losses`), reported as the equivalent world-side transform
``D = [Rz(yaw) | t]`` with ``T_world_cam' = D @ T_world_cam`` and ``T_world_vio' = D @ T_world_vio``.

Objective (the paper's Eq. calib, with robust kernels and each term normalised by its robust
scale so the weights are unit-free)::

    L = w_track L_track + sum_v w_chamfer L_chamfer,v + sum_v w_reproj L_reproj,v

Two solvers on the same residual blocks:

- ``adam``: Adam with gradient-norm clipping (the paper's choice; the release uses lr 1e-2 for 200
  iterations). A cosine decay of the learning rate (to ``adam_lr_final``) is added so the last
  iterations settle instead of dithering at the lr's step size.
- ``lm``: Levenberg-Marquardt on the 4 V parameters with central-difference Jacobians of the
  stacked whitened residual vector; robust kernels through IRLS weights re-computed each iteration, and
  Chamfer neighbours re-found each iteration (ICP-style).

``both`` runs the two and keeps the lower final loss; both runs are reported.

Slow VIO drift (``drift_knot_frames`` > 0): a real handheld VIO track errs with the path walked (a
scale error, drift of a per cent or two of the path), so no single yaw + translation fits every
frame of a view. The correction is then a piecewise-linear function of the frame: ``[yaw, t]`` at
knots every ``drift_knot_frames`` frames, interpolated per observation, with a smoothness prior on
the change between neighbouring knots (``drift_sigma_m``, ``drift_sigma_deg``). One knot (a
view shorter than two knot spacings, or ``drift_knot_frames = 0``) is the rigid offset above.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from numpy.typing import NDArray

from embodmocap.calibrate import losses as L
from embodmocap.calibrate.config import RefineConfig, Solver  # noqa: F401 (defined with the stage's settings)
from embodmocap.calibrate.drift import drift_transforms, knot_basis, knot_frames
from embodmocap.parallel import map_in_threads

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class ViewData:
    """One view's input to the refinement.

    T_world_cam: (T, 4, 4) camera-to-world of each sequence frame, already aligned by the initial
        offset (``T_world_vio_init @ T_vio_cam``).
    K: (3, 3) RGB intrinsics (pixels of the reprojection matches).
    background: the view's background cloud in camera coordinates for the Chamfer term, or None.
    matches: registered 2D-3D matches for the reprojection term, or None.
    T_world_vio_init: (4, 4) the initial offset, to report the refined ``T_world_vio``.
    """

    T_world_cam: NDArray
    K: NDArray
    background: L.BackgroundCloud | None = None
    matches: L.Matches2D3D | None = None
    T_world_vio_init: NDArray = field(default_factory=lambda: np.eye(4))


@dataclass(frozen=True)
class ViewOffset:
    """The refinement's correction of one view.

    yaw_delta_rad: rotation about +Z of the world-side correction, radians.
    t_delta_m: (3,) world-side translation of the correction, metres.
    T_delta: (4, 4) ``[Rz(yaw) | t]``; T_world_vio: (4, 4) ``T_delta @ T_world_vio_init``;
    T_world_cam: (T, 4, 4) refined cameras ``T_delta(t) @ T_world_cam_init(t)``.
    With drift knots, ``yaw_delta_rad``, ``t_delta_m``, ``T_delta`` and ``T_world_vio`` are the
    correction at the mean of the per-frame parameters (the best single offset); ``T_world_cam``
    carries each frame's own correction.
    knot_frames: (K,) frames of the knots; knots: (K, 4) ``[yaw, tx, ty, tz]`` at each knot, the
    pivot form (rotation about ``pivot``, then the translation); pivot: (3,) the view's pivot.
    """

    yaw_delta_rad: float
    t_delta_m: NDArray
    T_delta: NDArray
    T_world_vio: NDArray
    T_world_cam: NDArray
    knot_frames: NDArray = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    knots: NDArray = field(default_factory=lambda: np.zeros((1, 4)))
    pivot: NDArray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True)
class SolverRun:
    """One solver's run: final objective, iterations, wall time and its parameters (4 V,)."""

    name: str
    loss_final: float
    iterations: int
    seconds: float
    x: NDArray


@dataclass(frozen=True)
class RefineResult:
    """Refined offsets and the residual report.

    views: per view name, the correction. loss_before/after: the total objective.
    terms_before/after: each weighted robust term ("track", "chamfer/<view>", "reproj/<view>").
    stats_before/after: per term, "rms" and "median" residual norm in the term's unit (metres or
    pixels) and "inliers", the fraction of residuals within ``inlier_ratio`` robust scales.
    solver: the solver whose result is kept; iterations: its iterations; runs: every run.
    diverged: the loss did not decrease, is not finite, or the update exceeds the thresholds;
    message: why (empty if not diverged). warnings: other findings (terms that disagree).
    phase_frames: the track term's estimate of how much later view b films than view a within a
    frame, sequence frames (None without it: ``track_phase`` off, no track pairs or no motion).
    """

    views: dict[str, ViewOffset]
    loss_before: float
    loss_after: float
    terms_before: dict[str, float]
    terms_after: dict[str, float]
    stats_before: dict[str, dict[str, float]]
    stats_after: dict[str, dict[str, float]]
    solver: str
    iterations: int
    runs: dict[str, SolverRun]
    diverged: bool
    message: str
    warnings: tuple[str, ...]
    phase_frames: float | None = None


# ---------------------------------------------------------------------------------------------
# The problem: residual blocks of all terms as functions of the stacked parameters
# ---------------------------------------------------------------------------------------------


@dataclass
class _Block:
    """One term's residuals: r (n, k), confidence weights (n,), kernel, scale, term weight."""

    name: str
    r: torch.Tensor
    conf: torch.Tensor
    kind: str
    scale: float
    weight: float

    def loss(self) -> torch.Tensor:
        s = (self.r * self.r).sum(-1)
        return self.weight * (self.conf * L.robust_rho(s, self.kind, self.scale)).sum() / self.norm()

    def norm(self) -> torch.Tensor:
        return self.conf.sum().clamp(min=1e-12)

    def whitened(self, irls: torch.Tensor) -> torch.Tensor:
        """Residuals e with ||e||^2 = the term's IRLS-linearised loss at fixed ``irls`` (n,)."""
        w = torch.sqrt(self.weight * self.conf * irls / self.norm()) / self.scale
        return (self.r * w[:, None]).reshape(-1)


def _offset_points_each(P: torch.Tensor, pivot: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """:func:`embodmocap.calibrate.losses.offset_points` with each point's own ``[yaw, t]`` (N, 4)."""
    q = p - pivot
    c, s = torch.cos(P[:, 0]), torch.sin(P[:, 0])
    rot = torch.stack([c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1], q[:, 2]], -1)
    return rot + pivot + P[:, 1:4]


class _Problem:
    def __init__(self, views: dict[str, ViewData], cfg: RefineConfig, scene, tracks) -> None:
        self.names = list(views)
        self.cfg = cfg
        self.scene = scene
        self.cams = {v: L.Cameras.from_T(d.T_world_cam) for v, d in views.items()}
        # Each view's correction at its knots (one knot: the rigid offset); x stacks (K_v, 4) per view.
        n = {v: len(np.asarray(d.T_world_cam)) for v, d in views.items()}
        self.knot_frames = {v: knot_frames(n[v], cfg.drift_knot_frames) for v in self.names}
        self.basis = {v: torch.as_tensor(knot_basis(n[v], self.knot_frames[v])) for v in self.names}
        sizes = [4 * len(self.knot_frames[v]) for v in self.names]
        self.slices = dict(zip(self.names, (slice(a, a + b) for a, b in zip(np.cumsum([0] + sizes[:-1]), sizes))))
        self.num_params = int(sum(sizes))
        self.rigid = all(len(k) == 1 for k in self.knot_frames.values())
        self.K = {v: torch.as_tensor(np.asarray(d.K, dtype=np.float64)) for v, d in views.items()}
        self.views = views
        self.tracks = tracks
        if tracks is not None and not (tracks.view_a in views and tracks.view_b in views):
            log.info("track pairs of %s/%s skipped: not both views are refined", tracks.view_a, tracks.view_b)
            self.tracks = None
        if self.tracks is not None and len(self.tracks) == 0:
            self.tracks = None
        if scene is None:
            self.chamfer_views = []
        else:
            self.chamfer_views = [v for v in self.names if views[v].background is not None and len(views[v].background)]
        self.reproj_views = [v for v in self.names if views[v].matches is not None and len(views[v].matches)]
        if self.tracks is None and not self.chamfer_views and not self.reproj_views:
            raise ValueError("nothing to refine on: no track pairs, background clouds or 2D-3D matches")
        # The cameras do not change during the solve (only the offset on top of them does), so every
        # observation is taken to the world once here; each evaluation is then one rigid motion of
        # fixed points instead of a per-point gather of camera matrices (same values, far less work).
        self._world: dict[str, torch.Tensor] = {}
        self._frames: dict[str, torch.Tensor] = {}  # each key's observation frames (drift knots)
        self.phase_index: int | None = None
        self._motion: torch.Tensor | None = None
        if self.tracks is not None:
            tr = self.tracks
            self._world["track_a"] = _to_world(self.cams[tr.view_a], tr.frames, tr.p_a)
            self._world["track_b"] = _to_world(self.cams[tr.view_b], tr.frames, tr.p_b)
            self._frames["track_a"] = self._frames["track_b"] = tr.frames
            if cfg.track_phase:
                self._motion = _track_motion(tr, self._world["track_a"], self._world["track_b"])
            if self._motion is not None:
                self.phase_index = self.num_params
                self.num_params += 1
        for v in self.chamfer_views:
            bg = views[v].background
            self._world[f"chamfer/{v}"] = _to_world(self.cams[v], bg.frames, bg.p_cam)
            self._frames[f"chamfer/{v}"] = bg.frames
        self._reproj: dict[str, tuple[torch.Tensor, torch.Tensor]] = {
            v: (self.cams[v].R[views[v].matches.frames], self.cams[v].c[views[v].matches.frames]) for v in self.reproj_views}
        for v in self.reproj_views:
            self._frames[f"reproj/{v}"] = views[v].matches.frames
        # Per observation key: the knots about each observation's frame and its hat weights on them,
        # (k0, a0, a1) with the frame's parameters a0 X[k0] + a1 X[k0 + 1] (None: a rigid view).
        self._hat = {key: self._hat_weights(self._view_of(key), f) for key, f in self._frames.items()}
        self._knot_rows: dict[tuple[str, str], tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}

    def _hat_weights(self, v: str, frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        K = len(self.knot_frames[v])
        if K == 1:
            return None
        # a frame's hat weights are non-zero on the two knots about it only
        k0 = (torch.searchsorted(torch.as_tensor(self.knot_frames[v]), frames, right=True) - 1).clamp(0, K - 2)
        B = self.basis[v][frames]
        i = torch.arange(len(frames))
        return k0, B[i, k0], B[i, k0 + 1]

    def knot_rows(self, name: str, v: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Data block ``name``'s whitened rows that depend on view ``v``'s knots, as three (E,)
        tensors: row, knot and the row's hat weight on that knot (a row with knots: the two knots
        about its frame; a rigid view: knot 0, weight 1). Computed once per problem."""
        if (name, v) not in self._knot_rows:
            if name == "track":
                key, k = ("track_a" if self.tracks.view_a == v else "track_b"), 3
            else:
                key, k = name, (1 if name.startswith("chamfer/") else 2)
            n, hat = len(self._frames[key]), self._hat[key]
            rows = torch.arange(n * k)
            if hat is None:
                out = (rows, torch.zeros(n * k, dtype=torch.int64), torch.ones(n * k, dtype=torch.float64))
            else:
                k0, a0, a1 = hat
                out = (torch.cat([rows, rows]), torch.cat([k0.repeat_interleave(k), (k0 + 1).repeat_interleave(k)]),
                       torch.cat([a0.repeat_interleave(k), a1.repeat_interleave(k)]))
            self._knot_rows[(name, v)] = out
        return self._knot_rows[(name, v)]

    def _view_of(self, key: str) -> str:
        if key in ("track_a", "track_b"):
            return self.tracks.view_a if key == "track_a" else self.tracks.view_b
        return key.split("/", 1)[1]

    def params(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """view -> (K_v, 4) ``[yaw, tx, ty, tz]`` at the view's knots."""
        return {v: x[self.slices[v]].reshape(-1, 4) for v in self.names}

    def _each(self, X: torch.Tensor, key: str) -> torch.Tensor:
        """The observations of ``key``'s own parameters: (N, 4), or (1, 4) for a rigid view."""
        hat = self._hat[key]
        if hat is None:
            return X
        k0, a0, a1 = hat
        return a0[:, None] * X[k0] + a1[:, None] * X[k0 + 1]

    def neighbours(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """view -> each background point's scene neighbour at ``x`` (the views on the lent cores' threads)."""
        p = self.params(x.detach())
        return dict(zip(self.chamfer_views, map_in_threads(lambda v: L.nearest_scene(
            self.scene, self._moved(p[v], v, f"chamfer/{v}"), self.cfg.chamfer_max_distance_m), self.chamfer_views)))

    def _moved(self, X: torch.Tensor, v: str, key: str) -> torch.Tensor:
        """The fixed world points ``key`` moved by view ``v``'s offset ``X`` (K, 4) (same as
        :func:`embodmocap.calibrate.losses.cam_to_world` on the camera-space points)."""
        if self._hat[key] is None:
            return L.offset_points(X[0, 0], X[0, 1:4], self.cams[v].pivot, self._world[key])
        return _offset_points_each(self._each(X, key), self.cams[v].pivot, self._world[key])

    def blocks(self, x: torch.Tensor, nbrs: dict[str, torch.Tensor], data: bool = True,
               only: frozenset[str] | None = None) -> list[_Block]:
        """Every term's residual block at ``x`` (the drift priors last); ``data=False``: the priors
        only; ``only``: of the data blocks, those named (and no priors)."""
        cfg, p = self.cfg, self.params(x)
        out = []
        if data:
            out += self._data_blocks(p, nbrs, None if self.phase_index is None else x[self.phase_index], only)
        if only is not None:
            return out
        for v in self.names:
            if len(self.knot_frames[v]) > 1:
                # Smoothness prior: neighbouring knots differ by about drift_sigma (a Gaussian prior).
                dX = p[v][1:] - p[v][:-1]
                sig = torch.tensor([math.radians(cfg.drift_sigma_deg)] + [cfg.drift_sigma_m] * 3, dtype=dX.dtype)
                out.append(_Block(f"drift/{v}", dX / sig, torch.ones(len(dX), dtype=dX.dtype), "l2", 1.0, cfg.w_drift))
        return out

    def data_names(self, v: str | None = None) -> frozenset[str]:
        """The names of the data blocks (those that depend on view ``v`` when given)."""
        names = (["track"] if self.tracks is not None and v in (None, self.tracks.view_a, self.tracks.view_b) else []) \
            + [f"chamfer/{u}" for u in self.chamfer_views if v in (None, u)] \
            + [f"reproj/{u}" for u in self.reproj_views if v in (None, u)]
        return frozenset(names)

    def _data_blocks(self, p: dict[str, torch.Tensor], nbrs: dict[str, torch.Tensor], phase: torch.Tensor | None,
                     only: frozenset[str] | None = None) -> list[_Block]:
        cfg = self.cfg
        out = []
        if self.tracks is not None and (only is None or "track" in only):
            a, b = self.tracks.view_a, self.tracks.view_b
            r = self._moved(p[a], a, "track_a") - self._moved(p[b], b, "track_b")
            if phase is not None:
                # view b's frame shows the performer ``phase`` frames later than view a's
                r = r + phase * self._motion
            out.append(_Block("track", r, self.tracks.weight, cfg.track_kernel, cfg.track_scale_m, cfg.w_track))
        for v in self.chamfer_views:
            if only is not None and f"chamfer/{v}" not in only:
                continue
            pw = self._moved(p[v], v, f"chamfer/{v}")
            j = nbrs[v].clamp(min=0)
            valid = nbrs[v] >= 0
            # point-to-plane distance to the scene neighbour (as losses.chamfer_residuals)
            r = torch.where(valid, ((pw - self.scene.points[j]) * self.scene.normals[j]).sum(-1), torch.zeros_like(pw[:, 0]))[:, None]
            has_nbr = valid.to(r.dtype)  # points with no scene sample nearby do not count
            out.append(_Block(f"chamfer/{v}", r, has_nbr, cfg.chamfer_kernel, cfg.chamfer_scale_m, cfg.w_chamfer))
        for v in self.reproj_views:
            if only is not None and f"reproj/{v}" not in only:
                continue
            r = _reproj(self._each(p[v], f"reproj/{v}"), self.cams[v].pivot, *self._reproj[v], self.K[v], self.views[v].matches)
            out.append(_Block(f"reproj/{v}", r, torch.ones(len(r), dtype=r.dtype), cfg.reproj_kernel, cfg.reproj_scale_px, cfg.w_reproj))
        return out

    def loss(self, x: torch.Tensor) -> tuple[float, dict[str, torch.Tensor]]:
        """The objective at ``x`` with freshly found neighbours (as :meth:`evaluate`'s total) and
        those neighbours."""
        nbrs = self.neighbours(x)
        with torch.no_grad():
            return sum(float(b.loss()) for b in self.blocks(x, nbrs)), nbrs

    def evaluate(self, x: torch.Tensor) -> tuple[float, dict[str, float], dict[str, dict[str, float]]]:
        """The objective at ``x`` with freshly found neighbours: total, terms, per-term statistics."""
        with torch.no_grad():
            blocks = self.blocks(x, self.neighbours(x))
            terms = {b.name: float(b.loss()) for b in blocks}
            norms = {b.name: (b.r * b.r).sum(-1).sqrt()[b.conf > 0] for b in blocks}
            scales = {b.name: b.scale for b in blocks}
        nan = float("nan")
        stats = {
            k: {"rms": nan, "median": nan, "inliers": 0.0}
            if n.numel() == 0
            else {
                "rms": float((n * n).mean().sqrt()),
                "median": float(n.median()),
                "inliers": float((n < self.cfg.inlier_ratio * scales[k]).double().mean()),
            }
            for k, n in norms.items()
        }
        return sum(terms.values()), terms, stats


def _track_motion(tr: L.TrackPairs, world_a: torch.Tensor, world_b: torch.Tensor, half_span: int = 5,
                  max_span: int = 12) -> torch.Tensor | None:
    """(N, 3) each track pair's motion per sequence frame in the world: the mean of the two views'
    points, differenced between the same point's pairs at least ``half_span`` frames before and
    after (the nearest such; a wider span than one frame each side damps the keypoints' noise,
    which would otherwise shrink the fitted phase), both within ``max_span`` frames of each
    other; 0 where there are none. None without such neighbours (``tr.steps`` None, or fewer than
    10 pairs with them)."""
    if tr.steps is None:
        return None
    f = tr.frames
    ends = []
    for side, sign in ((0, -1), (1, 1)):
        i = torch.arange(len(f))
        for _ in range(max(half_span, 1)):
            nxt = tr.steps[i, side]
            short = (sign * (f[i] - f) < half_span) & (nxt >= 0)
            i = torch.where(short, nxt, i)
        ends.append(i)
    i0, i1 = ends
    span = (f[i1] - f[i0]).to(world_a.dtype)
    ok = (f - f[i0] >= min(half_span, 1)) & (f[i1] - f >= min(half_span, 1)) & (span <= max_span)
    if int(ok.sum()) < 10:
        return None
    w = 0.5 * (world_a + world_b)
    return torch.where(ok[:, None], (w[i1] - w[i0]) / span.clamp(min=1.0)[:, None], torch.zeros_like(w))


def _to_world(cams: L.Cameras, frames: torch.Tensor, p_cam: torch.Tensor) -> torch.Tensor:
    """(N, 3) world points of camera-space points ``p_cam`` (N, 3) of ``frames`` (N,), no offset."""
    return torch.einsum("nij,nj->ni", cams.R[frames], p_cam) + cams.c[frames]


def _reproj(P: torch.Tensor, pivot: torch.Tensor, R: torch.Tensor, c: torch.Tensor, K: torch.Tensor, m: L.Matches2D3D) -> torch.Tensor:
    """(P, 2) observed minus projected pixels (as :func:`embodmocap.calibrate.losses.reproj_residuals`)
    with each match's camera rotation ``R`` (P, 3, 3) and centre ``c`` (P, 3) gathered once, under
    the offset ``P`` (1, 4) (one for every match) or (P, 4) (each match its own, drift knots)."""
    if len(P) == 1:
        x_back = (m.xyz - pivot - P[0, 1:4]) @ L.rz_torch(P[0, 0]) + pivot  # the inverse offset on the points
    else:
        q = m.xyz - pivot - P[:, 1:4]
        cy, sy = torch.cos(P[:, 0]), torch.sin(P[:, 0])
        x_back = torch.stack([cy * q[:, 0] + sy * q[:, 1], -sy * q[:, 0] + cy * q[:, 1], q[:, 2]], -1) + pivot
    p_cam = torch.einsum("nji,nj->ni", R, x_back - c)
    z = p_cam[:, 2].clamp(min=1e-6)
    u = K[0, 0] * p_cam[:, 0] / z + K[0, 2]
    v = K[1, 1] * p_cam[:, 1] / z + K[1, 2]
    return m.xy - torch.stack([u, v], -1)


# ---------------------------------------------------------------------------------------------
# Solvers
# ---------------------------------------------------------------------------------------------


def _adam(prob: _Problem, cfg: RefineConfig) -> SolverRun:
    t0 = time.perf_counter()
    x = torch.zeros(prob.num_params, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([x], lr=cfg.adam_lr)
    n = max(cfg.adam_iterations, 1)
    nbrs: dict[str, torch.Tensor] = {}
    for it in range(cfg.adam_iterations):
        # cosine decay from adam_lr to adam_lr_final
        frac = it / max(n - 1, 1)
        lr = cfg.adam_lr_final + 0.5 * (cfg.adam_lr - cfg.adam_lr_final) * (1 + math.cos(math.pi * frac))
        for g in opt.param_groups:
            g["lr"] = lr
        if it % max(cfg.chamfer_refresh, 1) == 0:
            nbrs = prob.neighbours(x)
        opt.zero_grad()
        loss = sum(b.loss() for b in prob.blocks(x, nbrs))
        loss.backward()
        if cfg.adam_clip_norm > 0:
            torch.nn.utils.clip_grad_norm_([x], cfg.adam_clip_norm)
        opt.step()
    xf = x.detach().clone()
    return SolverRun("adam", prob.evaluate(xf)[0], cfg.adam_iterations, time.perf_counter() - t0, xf.numpy())


def _lm(prob: _Problem, cfg: RefineConfig) -> SolverRun:
    t0 = time.perf_counter()
    x = torch.zeros(prob.num_params, dtype=torch.float64)
    f, nbrs = prob.loss(x)
    lam = cfg.lm_damping
    it = 0
    for it in range(1, cfg.lm_iterations + 1):
        # (nbrs: the neighbours at x, found when x was evaluated)
        with torch.no_grad():
            irls = [L.irls_weight((b.r * b.r).sum(-1), b.kind, b.scale) for b in prob.blocks(x, nbrs)]

        if prob.rigid:
            def resid(xx: torch.Tensor) -> torch.Tensor:
                return torch.cat([b.whitened(w) for b, w in zip(prob.blocks(xx, nbrs), irls)])

            r = resid(x)
            J = _jacobian(resid, x)
            H, g = J.T @ J, J.T @ r
        else:
            H, g = _knot_normal_system(prob, x, nbrs, irls)
        # a tiny ridge keeps unobserved directions (e.g. the height with tracks only) solvable
        ridge = 1e-12 * max(float(H.diagonal().max()), 1e-12)
        accepted = False
        while lam < 1e10:
            A = H + lam * torch.diag(H.diagonal()) + ridge * torch.eye(len(x), dtype=x.dtype)
            dx = torch.linalg.solve(A, -g)
            f_new, nbrs_new = prob.loss(x + dx)
            if math.isfinite(f_new) and f_new <= f:
                x, f, nbrs, lam, accepted = x + dx, f_new, nbrs_new, max(lam / 10.0, 1e-12), True
                break
            lam *= 10.0
        if not accepted or float(dx.abs().max()) < cfg.lm_step_tol:
            break
    return SolverRun("lm", f, it, time.perf_counter() - t0, x.numpy())


def _knot_normal_system(prob: _Problem, x: torch.Tensor, nbrs, irls, step: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """``(J^T J, J^T r)`` of the whitened residuals ``r`` over the drift knots, with ``J`` their
    Jacobian (a sparse matrix: a row depends on at most two knots of each view it observes) in 8 V
    evaluations instead of two per knot parameter.

    A data residual depends on a view's knots only through its observation's own parameters
    ``B[frame] @ X`` (hat weights summing to 1), so moving every knot of one component together
    gives each row's derivative by its own parameter, and the chain rule spreads it on the knots by
    the row's hat weights. Each such move changes only the blocks of that view, so only those are
    evaluated. The smoothness prior's rows (the last ones) depend on two neighbouring knots each:
    moving every other knot of one component together gives each row's derivative by one of them.
    """
    from scipy import sparse

    with torch.no_grad():
        blocks = prob.blocks(x, nbrs)
        w_of = {b.name: w for b, w in zip(blocks, irls)}
        r = torch.cat([b.whitened(w_of[b.name]) for b in blocks])
        starts = dict(zip((b.name for b in blocks), np.cumsum([0] + [b.r.numel() for b in blocks[:-1]]).tolist()))
        rows: list[torch.Tensor] = []
        cols: list[torch.Tensor] = []
        vals: list[torch.Tensor] = []

        def diff(e: torch.Tensor, only: frozenset[str] | None) -> dict[str, torch.Tensor]:
            """Each evaluated block's central difference along ``e``."""
            plus = {b.name: b.whitened(w_of[b.name]) for b in prob.blocks(x + e, nbrs, data=only is not None, only=only)}
            minus = {b.name: b.whitened(w_of[b.name]) for b in prob.blocks(x - e, nbrs, data=only is not None, only=only)}
            return {k: (plus[k] - minus[k]) / (2.0 * step) for k in plus}

        if prob.phase_index is not None:  # the track phase: one column, differenced directly
            e = torch.zeros_like(x)
            e[prob.phase_index] = step
            d = diff(e, frozenset(["track"]))["track"]
            rows.append(starts["track"] + torch.arange(len(d)))
            cols.append(torch.full((len(d),), prob.phase_index))
            vals.append(d)

        def view_columns(v: str) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
            """(rows, columns, values) of view ``v``'s knot columns."""
            out = []
            with torch.no_grad():  # (per thread)
                sl = prob.slices[v]
                only = prob.data_names(v)
                hat = {name: prob.knot_rows(name, v) for name in only}
                for c in range(4):
                    e = torch.zeros_like(x)
                    e[sl.start + c: sl.stop: 4] = step
                    for name, d in diff(e, only).items():
                        i, k, w = hat[name]
                        out.append((starts[name] + i, sl.start + 4 * k + c, w * d[i]))
                K = len(prob.knot_frames[v])
                if K > 1:
                    # prior row (k, c) ties knots k and k + 1 of component c: one of each parity
                    ks = torch.arange(K - 1)
                    for c in range(4):
                        for parity in range(2):
                            e = torch.zeros_like(x)
                            e[sl.start + 4 * parity + c: sl.stop: 8] = step
                            d = diff(e, None)[f"drift/{v}"]
                            i = 4 * ks + c
                            out.append((starts[f"drift/{v}"] + i, sl.start + 4 * torch.where(ks % 2 == parity, ks, ks + 1) + c, d[i]))
            return out

        # the views' columns on the lent cores' threads, assembled in the views' order
        for part in map_in_threads(view_columns, prob.names):
            for i, k, d in part:
                rows.append(i)
                cols.append(k)
                vals.append(d)
        J = sparse.csr_matrix((torch.cat(vals).numpy(), (torch.cat(rows).numpy(), torch.cat(cols).numpy())),
                              shape=(len(r), prob.num_params))
        H = torch.as_tensor((J.T @ J).toarray())
        g = torch.as_tensor(J.T @ r.numpy())
    return H, g


def _jacobian(fn, x: torch.Tensor, step: float = 1e-6) -> torch.Tensor:
    """(m, n) Jacobian of ``fn`` (n,) -> (m,) at ``x`` by central differences.

    The parameters are radians and metres of order 1e-2, the residuals smooth in them (rigid
    motions and a projection), so a 1e-6 step is exact to ~1e-9 relative. Two evaluations per
    parameter (8 for two views) cost less than forward-mode AD, whose first use also imports
    torch's compiler stack (seconds)."""
    with torch.no_grad():
        cols = []
        for i in range(len(x)):
            e = torch.zeros_like(x)
            e[i] = step
            cols.append((fn(x + e) - fn(x - e)) / (2.0 * step))
        return torch.stack(cols, dim=1)


# ---------------------------------------------------------------------------------------------
# Entry point
# ---------------------------------------------------------------------------------------------


def refine_offsets(
    views: dict[str, ViewData],
    cfg: RefineConfig = RefineConfig(),
    *,
    scene: L.ScenePoints | None = None,
    tracks: L.TrackPairs | None = None,
) -> RefineResult:
    """Jointly refine every view's yaw + translation offset.

    views: name -> :class:`ViewData` (one view: single-view mode, no track term). scene: points
    sampled on the Stage I mesh (needed for the Chamfer term). tracks: cross-view pairs between two
    of ``views`` (ignored if either is missing). Raises ValueError when no term has data.
    """
    for v, d in views.items():
        if np.asarray(d.T_world_cam).ndim != 3 or np.asarray(d.T_world_cam).shape[1:] != (4, 4):
            raise ValueError(f"view {v}: T_world_cam must be (T, 4, 4)")
    if cfg.solver not in ("adam", "lm", "both"):
        raise ValueError(f"unknown solver {cfg.solver!r}: use adam, lm or both")
    prob = _Problem(views, cfg, scene, tracks)
    x0 = torch.zeros(prob.num_params, dtype=torch.float64)
    loss0, terms0, stats0 = prob.evaluate(x0)

    runs: dict[str, SolverRun] = {}
    if cfg.solver in ("adam", "both"):
        runs["adam"] = _adam(prob, cfg)
    if cfg.solver in ("lm", "both"):
        runs["lm"] = _lm(prob, cfg)
    finite = [r for r in runs.values() if math.isfinite(r.loss_final)]
    best = min(finite, key=lambda r: r.loss_final) if finite else next(iter(runs.values()))
    for r in runs.values():
        log.info("refine %s: loss %.6g -> %.6g in %d iterations (%.2f s)", r.name, loss0, r.loss_final, r.iterations, r.seconds)

    x = torch.as_tensor(best.x)
    loss1, terms1, stats1 = prob.evaluate(x)
    offsets = {v: _view_offset(views[v], prob, v, best.x[prob.slices[v]]) for v in prob.names}
    diverged, message = _divergence(loss0, loss1, offsets, cfg)
    warns = _disagreements(stats1, cfg)
    if diverged:
        log.warning("refinement diverged: %s", message)
    for w in warns:
        log.warning("refinement: %s", w)
    return RefineResult(
        views=offsets,
        loss_before=loss0,
        loss_after=loss1,
        terms_before=terms0,
        terms_after=terms1,
        stats_before=stats0,
        stats_after=stats1,
        solver=best.name,
        iterations=best.iterations,
        runs=runs,
        diverged=diverged,
        message=message,
        warnings=tuple(warns),
        phase_frames=None if prob.phase_index is None else float(best.x[prob.phase_index]),
    )


def _view_offset(view: ViewData, prob: _Problem, v: str, x: NDArray) -> ViewOffset:
    X = np.asarray(x, dtype=np.float64).reshape(-1, 4)
    mean = prob.basis[v].numpy().mean(axis=0) @ X  # the per-frame parameters' mean: the best single offset
    yaw = float(mean[0])
    pivot = prob.cams[v].pivot.numpy()
    t = L.world_side_translation(yaw, mean[1:4], pivot)
    c, s = math.cos(yaw), math.sin(yaw)
    D = np.eye(4)
    D[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    D[:3, 3] = t
    T_cam = np.asarray(view.T_world_cam, dtype=np.float64)
    frames = prob.knot_frames[v]
    per_frame = D[None] if len(frames) == 1 else drift_transforms(frames, X, pivot, len(T_cam))
    return ViewOffset(
        yaw_delta_rad=yaw,
        t_delta_m=t,
        T_delta=D,
        T_world_vio=D @ np.asarray(view.T_world_vio_init, dtype=np.float64),
        T_world_cam=per_frame @ T_cam,
        knot_frames=frames, knots=X, pivot=pivot,
    )


def _divergence(loss0: float, loss1: float, offsets: dict[str, ViewOffset], cfg: RefineConfig) -> tuple[bool, str]:
    problems = []
    if not math.isfinite(loss1):
        problems.append(f"the final loss is not finite ({loss1})")
    elif loss1 > loss0 * (1 + 1e-9) + 1e-15:
        problems.append(f"the loss rose from {loss0:.6g} to {loss1:.6g}")
    for v, o in offsets.items():
        # the largest correction of any knot (world side), not only the mean
        D = drift_transforms(o.knot_frames, o.knots, o.pivot, int(o.knot_frames[-1]) + 1)[o.knot_frames]
        dt = max(float(np.linalg.norm(o.t_delta_m)), float(np.linalg.norm(D[:, :3, 3], axis=1).max()))
        dyaw = math.degrees(max(abs(o.yaw_delta_rad), float(np.abs(o.knots[:, 0]).max())))
        if dt > cfg.max_translation_m or dyaw > cfg.max_yaw_deg:
            problems.append(
                f"view {v} moved {dt:.3f} m / {dyaw:.2f} deg from registration "
                f"(limits {cfg.max_translation_m} m / {cfg.max_yaw_deg} deg)"
            )
    return bool(problems), "; ".join(problems)


def _disagreements(stats: dict[str, dict[str, float]], cfg: RefineConfig) -> list[str]:
    """Terms with too few inliers after refinement: the data disagree with the others or are bad.

    An inlier fraction rather than the RMS: a few gross outliers (which the robust kernels are
    there to ignore) must not raise the warning, but a wall the view cannot fit must."""
    out = []
    for name, st in stats.items():
        if name.startswith("drift/"):  # the smoothness prior is no data term
            continue
        if not st["inliers"] >= cfg.min_inlier_fraction:
            out.append(
                f"{name}: only {100 * st['inliers']:.0f}% of residuals within {cfg.inlier_ratio} robust "
                f"scales after refinement (median {st['median']:.4g}, RMS {st['rms']:.4g}; "
                f"expected at least {100 * cfg.min_inlier_fraction:.0f}%)"
            )
    return out
