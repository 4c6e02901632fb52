"""Follow: move the root along a 2D path (the supplement's "Follow Skill").

- path: 2D waypoints every ``PATH_DT`` = 0.1 s (``path[k]`` is the waypoint at ``k * 0.1`` s after
  the episode start), held at its last point afterwards.
- observation g^f (20): the ``N_WAYPOINTS`` = 10 waypoints at t, t + 0.1, ..., t + 0.9 s (linear
  interpolation of the path), each relative to the root in the heading frame (x, y), waypoint
  after waypoint.
- reward ``r^f = exp(-2 |x_root_2d - x_t|^2)``, ``x_t`` the path's waypoint at time t.
- success: ``|x_root_2d - x_t| < 0.2`` m at the episode's end.
"""

from __future__ import annotations

from embodmocap.skills.tasks.common import norm, ops, to_heading

OBS_SIZE = 20
SUCCESS_M = 0.2
PATH_DT = 0.1
N_WAYPOINTS = 10
K_POS = 2.0


def sample_path(path, t, offsets_s=None):
    """Waypoints of ``path`` at times ``t + offsets_s`` by linear interpolation.

    Args:
        path: (P, 2) or (N, P, 2) waypoints every 0.1 s.
        t: (N,) seconds since the episode start.
        offsets_s: (K,) seconds ahead; default 0, 0.1, ..., 0.9 (the observation's ten).
    Returns:
        (N, K, 2) waypoints (the path's last point past its end, its first before its start).
    """
    o = ops(t)
    if offsets_s is None:
        offsets_s = [PATH_DT * k for k in range(N_WAYPOINTS)]
    off = o.like(offsets_s, t)
    P = path.shape[-2]
    u = o.clip((t[:, None] + off[None, :]) / PATH_DT, 0.0, float(P - 1))  # (N, K) path index
    i0 = o.clip(u // 1, 0.0, float(max(P - 2, 0)))
    w = (u - i0)[..., None]
    i0 = o.index(i0)
    i1 = o.clip(i0 + 1, 0, P - 1)
    if path.ndim == 2:
        a, b = path[i0], path[i1]
    else:
        n = o.index(o.like(list(range(path.shape[0])), t))[:, None]
        a, b = path[n, i0], path[n, i1]
    return a + w * (b - a)


def observation(root_pos, root_rot, waypoints):
    """(N, 20) task observation from (N, 10, 2) waypoints (:func:`sample_path`), world frame."""
    o = ops(root_pos)
    rel = waypoints - root_pos[:, None, :2]
    rel3 = o.cat([rel, rel[..., :1] * 0], -1)
    return to_heading(rel3, root_rot)[..., :2].reshape(root_pos.shape[0], -1)


def reward(root_pos, waypoint):
    """(N,) ``exp(-2 |x_root_2d - x_t|^2)``; ``waypoint`` (N, 2) the path at the current time."""
    o = ops(root_pos)
    return o.exp(-K_POS * o.sum((root_pos[:, :2] - waypoint) ** 2, -1))


def error(root_pos, waypoint):
    """(N,) horizontal distance of the root from the current waypoint, metres."""
    return norm(root_pos[:, :2] - waypoint)


def success(root_pos, waypoint, threshold_m: float = SUCCESS_M):
    """(N,) bool: the root within ``threshold_m`` of the current waypoint (2D)."""
    return error(root_pos, waypoint) < threshold_m
