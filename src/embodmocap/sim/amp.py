"""AMP-style style reward: the discriminator's input features and a least-squares discriminator.

**Discriminator input** (:func:`amp_frame_features`, ``AMP_FRAME_SIZE`` = 166 numbers per frame, in
this order; the character's heading frame: origin at the root, x along its facing on the ground,
z up):

====================  ====  ===============================================================
root height            1    root z above the scene's floor, metres
root rotation          6    the root's rotation relative to the heading frame, 6D (first two
                            columns)
root linear velocity   3    heading frame, m/s
root angular velocity  3    heading frame, rad/s
hinge angles          69    the humanoid's 69 hinges (qpos[7:]), radians
hinge velocities      69    qvel[6:], rad/s
key bodies            15    L_Ankle, R_Ankle, L_Hand, R_Hand, Head relative to the root,
                            heading frame, metres
====================  ====  ===============================================================

A transition is ``(s_t, s_t+1)``: two frames' features concatenated (``AMP_TRANSITION_SIZE`` =
332). Real transitions come from consecutive control-rate samples of the reference clips
(:func:`clip_transitions`), fake ones from the policy (the environment's ``info["amp_obs"]``).

**Discriminator** (:class:`Discriminator`): a small MLP trained as AMP does, least squares (LSGAN):
``(D(real) - 1)^2 + (D(fake) + 1)^2`` plus a gradient penalty on the real inputs; the style reward
is ``max(0, 1 - 0.25 (D(fake) - 1)^2)`` (1 for transitions it takes for real).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from embodmocap.geometry.rotations import quat_to_matrix, wxyz_to_xyzw
from embodmocap.sim.model import BODY_NAMES
from embodmocap.skills.tasks.common import heading_frame, rot6d

KEY_BODIES: tuple[str, ...] = ("L_Ankle", "R_Ankle", "L_Hand", "R_Hand", "Head")
KEY_INDEX = np.array([BODY_NAMES.index(n) for n in KEY_BODIES])
AMP_FRAME_SIZE = 1 + 6 + 3 + 3 + 69 + 69 + 3 * len(KEY_BODIES)
AMP_TRANSITION_SIZE = 2 * AMP_FRAME_SIZE


def amp_frame_features(qpos: NDArray, qvel: NDArray, xpos: NDArray, floor_z: float) -> NDArray[np.float32]:
    """(N, 166) discriminator features of N frames (layout in the module docstring).

    Args:
        qpos: (N, 76), qvel: (N, 75) the humanoid's state (MuJoCo: free-joint linear velocity in
            the world, angular velocity in the root's frame).
        xpos: (N, 24, 3) body positions, world.
        floor_z: the scene floor's height.
    """
    qpos, qvel, xpos = (np.asarray(a, dtype=np.float64) for a in (qpos, qvel, xpos))
    R = quat_to_matrix(wxyz_to_xyzw(qpos[:, 3:7]))  # MuJoCo qpos: w x y z
    H = heading_frame(R)
    Ht = np.swapaxes(H, -1, -2)
    lin = (Ht @ qvel[:, :3, None])[..., 0]
    ang = (Ht @ (R @ qvel[:, 3:6, None]))[..., 0]
    key = np.einsum("nij,nkj->nki", Ht, xpos[:, KEY_INDEX] - xpos[:, :1])
    out = np.concatenate([qpos[:, 2:3] - floor_z, rot6d(Ht @ R), lin, ang, qpos[:, 7:], qvel[:, 6:],
                          key.reshape(len(qpos), -1)], axis=-1)
    return out.astype(np.float32)


def clip_transitions(features: NDArray) -> NDArray[np.float32]:
    """(N - 1, 332) the (s_t, s_t+1) pairs of one clip's (N, 166) frame features."""
    f = np.asarray(features, dtype=np.float32)
    return np.concatenate([f[:-1], f[1:]], axis=-1)


class Discriminator:
    """AMP's least-squares discriminator over transitions, with its own input normalisation.

    Args:
        real: (M, D) reference transitions (sampled from when training).
        hidden: hidden layer widths; lr: Adam learning rate; grad_penalty: weight of the
            gradient penalty on real inputs; device: torch device.
    """

    def __init__(self, real: NDArray, hidden: tuple[int, ...] = (256, 128), lr: float = 1e-4,
                 grad_penalty: float = 5.0, device: str = "cpu", seed: int = 0) -> None:
        import torch

        self.torch = torch
        torch.manual_seed(seed)
        self.device = device
        self.real = torch.as_tensor(np.asarray(real, dtype=np.float32), device=device)
        self.mean = self.real.mean(0)
        self.std = self.real.std(0).clamp_min(1e-2)
        layers, d = [], self.real.shape[1]
        for h in hidden:
            layers += [torch.nn.Linear(d, h), torch.nn.ReLU()]
            d = h
        layers.append(torch.nn.Linear(d, 1))
        self.net = torch.nn.Sequential(*layers).to(device)
        self.opt = torch.optim.Adam(self.net.parameters(), lr=lr)
        self.grad_penalty = grad_penalty
        self.rng = np.random.default_rng(seed)

    def _d(self, x):
        return self.net((x - self.mean) / self.std)[:, 0]

    def style_reward(self, transitions: NDArray) -> NDArray[np.float32]:
        """(N,) ``max(0, 1 - 0.25 (D(x) - 1)^2)`` of (N, D) transitions."""
        with self.torch.no_grad():
            x = self.torch.as_tensor(np.asarray(transitions, dtype=np.float32), device=self.device)
            d = self._d(x)
            return (1.0 - 0.25 * (d - 1.0) ** 2).clamp_min(0.0).cpu().numpy()

    def update(self, fake: NDArray, epochs: int = 2, batch: int = 256) -> dict:
        """Train on (F, D) policy transitions against as many sampled real ones; returns the losses."""
        torch = self.torch
        fake_t = torch.as_tensor(np.asarray(fake, dtype=np.float32), device=self.device)
        n = len(fake_t)
        if n == 0:
            return {}
        stats = {"disc_loss": 0.0, "d_real": 0.0, "d_fake": 0.0}
        steps = 0
        for _ in range(epochs):
            order = self.rng.permutation(n)
            for s in range(0, n, batch):
                fb = fake_t[torch.as_tensor(order[s:s + batch], device=self.device)]
                rb = self.real[torch.as_tensor(self.rng.integers(len(self.real), size=len(fb)), device=self.device)]
                # The penalty is on the normalised input (what the network sees), as AMP's on its
                # normalised observations: per raw unit, a near-constant feature would dominate it.
                rn = ((rb - self.mean) / self.std).requires_grad_(True)
                dr, df = self.net(rn)[:, 0], self._d(fb)
                loss = ((dr - 1) ** 2).mean() + ((df + 1) ** 2).mean()
                g = torch.autograd.grad(dr.sum(), rn, create_graph=True)[0]
                loss = loss + self.grad_penalty * (g ** 2).sum(-1).mean()
                self.opt.zero_grad()
                loss.backward()
                self.opt.step()
                stats["disc_loss"] += float(loss.detach())
                stats["d_real"] += float(dr.detach().mean())
                stats["d_fake"] += float(df.detach().mean())
                steps += 1
        return {k: v / max(steps, 1) for k, v in stats.items()}

    def state_dict(self) -> dict:
        return {"net": self.net.state_dict(), "mean": self.mean.cpu(), "std": self.std.cpu()}
