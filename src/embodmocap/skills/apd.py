"""APD, the average pairwise distance between generated motions (the paper's diversity metric).

Following the metric the paper cites (CASE; as in DLow and ACTOR's diversity measures): each of
the K generated motions is one feature vector, its joint positions and joint rotations over all
frames, flattened; APD is the mean Euclidean distance over the K (K - 1) ordered pairs of distinct
motions. Higher is more diverse. numpy arrays or torch tensors.
"""

from __future__ import annotations

from embodmocap.skills.tasks.common import ops


def apd(positions, rotations=None) -> float:
    """Average pairwise distance of K motions.

    Args:
        positions: (K, T, J, 3) joint positions, metres (world or root-relative, as the caller
            compares them).
        rotations: optional (K, T, J, R) joint rotations in any vector form (axis-angle R = 3,
            6D R = 6, ...), concatenated to the positions per motion.
    Returns:
        APD (a Python float); 0 for fewer than two motions.
    """
    o = ops(positions)
    K = positions.shape[0]
    if K < 2:
        return 0.0
    feats = [positions.reshape(K, -1)]
    if rotations is not None:
        feats.append(rotations.reshape(K, -1))
    f = o.cat(feats, -1)
    d2 = o.sum((f[:, None, :] - f[None, :, :]) ** 2, -1)
    d = o.sqrt(o.clip(d2, 0.0, None))
    return float(o.sum(d.reshape(-1), 0) / (K * (K - 1)))
