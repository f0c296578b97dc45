"""Pairwise consistency maximisation (PCM, Mangelson et al. 2018) for inter-robot loop closures.

Closure ``k`` between robots a and b measures ``Z_k ≈ A_{i_k}^{-1} B_{j_k}`` in a common frame.
Two closures k, l are consistent when the cycle through them and both robots' odometry

    E_kl = Z_k^{-1} · (A_{i_k}^{-1} A_{i_l}) · Z_l · (B_{j_k}^{-1} B_{j_l})^{-1}

is close to identity: its squared Mahalanobis norm, with a covariance that grows with the
odometry path length spanned on each robot (random-walk rotation and translation drift, plus
the translation drift that integrated heading error causes), stays below a χ² quantile. The accepted set is the
maximum clique of the consistency graph (exact; ties go to the smallest total cycle error, see
:mod:`kimera_multi_py.core.clique`). Everything is vectorised over pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kimera_multi_py.core.clique import max_clique
from kimera_multi_py.core.geometry import inverse, se3_log
from kimera_multi_py.core.robust import chi2_quantile


@dataclass(frozen=True)
class PcmNoise:
    """Per-closure and per-metre-of-odometry standard deviations (rotation rad, translation m)."""

    closure_rot: float = 0.05
    """Loop-closure rotation noise (rad)."""
    closure_trans: float = 0.1
    """Loop-closure translation noise (m)."""
    odom_rot_per_m: float = 0.01
    """Odometry rotation drift per metre travelled (rad)."""
    odom_trans_per_m: float = 0.02
    """Odometry translation drift per metre travelled (m)."""
    probability: float = 0.99
    """χ² quantile two closures' cycle error must stay within to be consistent."""


def consistency_errors(
    Z: np.ndarray, A_i: np.ndarray, B_j: np.ndarray, path_a: np.ndarray, path_b: np.ndarray, noise: PcmNoise
) -> np.ndarray:
    """Squared Mahalanobis norms ``(c, c)`` of every closure pair's cycle error.

    ``Z``: ``(c, 4, 4)`` closures; ``A_i``/``B_j``: ``(c, 4, 4)`` the robots' own estimates of the
    closure end poses; ``path_a``/``path_b``: ``(c,)`` cumulative odometry distance at those poses.
    """
    Zinv = inverse(Z)
    A_rel = np.einsum("kab,lbc->klac", inverse(A_i), A_i)  # A_k^{-1} A_l
    B_rel = np.einsum("kab,lbc->klac", inverse(B_j), B_j)
    E = np.einsum("kab,klbc->klac", Zinv, A_rel)
    E = np.einsum("klab,lbc->klac", E, Z)
    E = np.einsum("klab,klbc->klac", E, inverse(B_rel))
    xi = se3_log(E)  # (c, c, 6)
    span = np.abs(path_a[:, None] - path_a[None]) + np.abs(path_b[:, None] - path_b[None])
    return _drift_r2(xi, span, 2, noise)


def _drift_r2(xi: np.ndarray, span: np.ndarray, closures: int, noise: PcmNoise) -> np.ndarray:
    """Squared Mahalanobis norm of cycle errors ``xi (..., 6)`` spanning ``span`` metres of odometry."""
    var_rot = closures * noise.closure_rot**2 + (noise.odom_rot_per_m**2) * span
    # translation also drifts through integrated heading error: a lever arm of ~span^3 / 3
    var_trans = (closures * noise.closure_trans**2 + (noise.odom_trans_per_m**2) * span
                 + (noise.odom_rot_per_m**2) * span**3 / 3)
    return (xi[..., :3] ** 2).sum(-1) / var_rot + (xi[..., 3:] ** 2).sum(-1) / var_trans


def odometry_consistent(Z: np.ndarray, A_i: np.ndarray, A_j: np.ndarray, path_i: np.ndarray, path_j: np.ndarray,
                        noise: PcmNoise) -> np.ndarray:
    """Intra-robot closures ``Z ≈ A_i^{-1} A_j`` that agree with the robot's own odometry (mask)."""
    xi = se3_log(inverse(Z) @ inverse(A_i) @ A_j)
    r2 = _drift_r2(xi, np.abs(np.asarray(path_i) - np.asarray(path_j)), 1, noise)
    return r2 <= chi2_quantile(noise.probability, 6)


def max_consistent_set(r2: np.ndarray, threshold: float) -> np.ndarray:
    """Indices of the maximum clique of ``r2 <= threshold`` (exact; sorted). Of equally large
    cliques, the one with the smallest summed ``r2`` (the most mutually consistent)."""
    r2 = np.asarray(r2, dtype=float)
    if len(r2) == 0:
        return np.zeros(0, dtype=int)
    adj = (r2 <= threshold) & (r2.T <= threshold)
    np.fill_diagonal(adj, False)
    return max_clique(adj, r2 + r2.T)


def pcm(Z: np.ndarray, A_i: np.ndarray, B_j: np.ndarray, path_a: np.ndarray, path_b: np.ndarray,
        noise: PcmNoise | None = None, min_size: int = 1, groups: int = 1) -> np.ndarray:
    """Boolean mask of the closures PCM accepts.

    ``groups = 1`` is classic PCM: the maximum pairwise-consistent set. With ``groups > 1`` the
    next largest disjoint consistent sets are kept too: when odometry drift over long spans
    makes a true group and an alias group (identical rooms) look equally plausible to one robot
    pair, the choice is left to the back end's GNC, which sees every robot's closures at once.
    A clique smaller than ``min_size`` accepts nothing: one closure alone cannot be told apart
    from a perceptual alias.
    """
    noise = noise or PcmNoise()
    Z = np.asarray(Z, dtype=float).reshape(-1, 4, 4)
    mask = np.zeros(len(Z), dtype=bool)
    if len(Z) == 0:
        return mask
    r2 = consistency_errors(Z, np.asarray(A_i, float), np.asarray(B_j, float), np.asarray(path_a, float),
                            np.asarray(path_b, float), noise)
    threshold = chi2_quantile(noise.probability, 6)
    left = np.arange(len(Z))
    for _ in range(groups):
        if len(left) == 0:
            break
        best = left[max_consistent_set(r2[np.ix_(left, left)], threshold)]
        if len(best) < min_size:
            break
        mask[best] = True
        left = np.setdiff1d(left, best)
    return mask


def odometry_consistent_path(Z: np.ndarray, kf_i: np.ndarray, kf_j: np.ndarray, dead_reckoning: np.ndarray,
                             noise: PcmNoise, keyframe_distance: float) -> np.ndarray:
    """Intra-robot closures ``Z ≈ D_i^{-1} D_j`` that agree with the robot's own odometry (mask),
    with the drift model taken along the robot's real path.

    :func:`odometry_consistent` bounds the translation drift that heading error causes by a
    straight line (``σ_r² L³/3``): over a long tour that admits a room-sized error (a robot that
    drove 120 m through a 24 m floor may be "11 m" off), so identical rooms 6 m apart pass. The
    lever arm is really the distance from each intermediate keyframe to the closure's end:
    ``σ_r² d Σ_m |p_j − p_m|²`` over the keyframes ``m`` between the ends, which stays room-sized.
    ``dead_reckoning``: ``(n, 4, 4)`` the robot's odometry-chained poses; ``kf_i``/``kf_j``
    keyframe indices of the closures' ends; ``keyframe_distance`` the nominal metres per keyframe.
    """
    Z = np.asarray(Z, dtype=float).reshape(-1, 4, 4)
    D = np.asarray(dead_reckoning, dtype=float)
    a, b = np.asarray(kf_i, dtype=int), np.asarray(kf_j, dtype=int)
    if len(Z) == 0:
        return np.zeros(0, dtype=bool)
    if np.any(a < 0) or np.any(b < 0) or np.any(np.maximum(a, b) >= len(D)):
        raise ValueError(f"closure keyframes outside the {len(D)} dead-reckoning poses")
    xi = se3_log(inverse(Z) @ inverse(D[a]) @ D[b])
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    p = D[:, :3, 3]
    S = np.vstack([np.zeros(3), np.cumsum(p, axis=0)])  # S[k] = Σ_{m<k} p_m
    Q = np.concatenate([[0.0], np.cumsum((p**2).sum(1))])
    end = p[hi]
    count = (hi - lo).astype(float)
    lever2 = np.maximum(count * (end**2).sum(1) - 2.0 * (end * (S[hi] - S[lo])).sum(1) + Q[hi] - Q[lo], 0.0)
    span = count * keyframe_distance
    var_rot = noise.closure_rot**2 + noise.odom_rot_per_m**2 * span
    # heading error of 2 axes perpendicular to each lever arm, per keyframe (variance per m x d)
    var_trans = (noise.closure_trans**2 + noise.odom_trans_per_m**2 * span
                 + 2.0 * noise.odom_rot_per_m**2 * keyframe_distance * lever2)
    r2 = (xi[:, :3] ** 2).sum(-1) / var_rot + (xi[:, 3:] ** 2).sum(-1) / var_trans
    return np.asarray(r2 <= chi2_quantile(noise.probability, 6))
