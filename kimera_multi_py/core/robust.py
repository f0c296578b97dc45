"""Graduated non-convexity with a truncated-least-squares cost (GNC-TLS, docs/algorithms/pgo.md).

For a squared (Mahalanobis) residual ``r²``, threshold ``c̄²`` and control parameter ``μ``:
``w = 1`` if ``r² ≤ μ/(μ+1)·c̄²``; ``w = 0`` if ``r² ≥ (μ+1)/μ·c̄²``; otherwise
``w = √(c̄²μ(μ+1)/r²) − μ``. ``μ`` starts small (a convex surrogate) and grows by ``1.4`` after
every weight update; as ``μ → ∞`` the weights become binary inlier/outlier decisions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import gammaincinv

MU_STEP = 1.4


def chi2_quantile(probability: float, dof: int) -> float:
    """The χ² quantile ``q`` with ``P(X ≤ q) = probability`` at ``dof`` degrees of freedom:
    ``scipy.stats.chi2.ppf``'s own formula, to the bit, without importing ``scipy.stats``, which
    every process would load for this alone (what that saves: docs/performance.md)."""
    return float(2.0 * gammaincinv(dof / 2.0, probability))


def tls_threshold(probability: float = 0.99, dof: int = 6) -> float:
    """``c̄²``: the χ² quantile an inlier's squared Mahalanobis residual stays below."""
    return chi2_quantile(probability, dof)


def tls_weights(r2: np.ndarray, mu: float, barc2: float) -> np.ndarray:
    """GNC-TLS weights of squared residuals ``r2`` (vectorised)."""
    r2 = np.asarray(r2, dtype=float)
    lower = mu / (mu + 1.0) * barc2
    upper = (mu + 1.0) / mu * barc2
    with np.errstate(over="ignore", divide="ignore"):
        w = np.sqrt(barc2 * mu * (mu + 1.0) / np.maximum(r2, 1e-300)) - mu
    w = np.where(r2 <= lower, 1.0, np.where(r2 >= upper, 0.0, w))
    return np.clip(w, 0.0, 1.0)


def initial_mu(r2_max: float, barc2: float) -> float:
    """``μ₀ = c̄² / (2 r²_max − c̄²)`` (Yang et al. 2020); large when nothing exceeds ``c̄²``."""
    denom = 2.0 * r2_max - barc2
    return float(barc2 / denom) if denom > 0 else 1e6


def correlated_votes(robot_i: np.ndarray, kf_i: np.ndarray, robot_j: np.ndarray, kf_j: np.ndarray) -> np.ndarray:
    """Each loop closure's vote ``ω = 1/√n`` in the robust cost: ``n`` closures between one
    keyframe and one robot (the most at either end) are not ``n`` independent observations of
    the same place (fully correlated would be ``1/n``; ``1/√n`` keeps the group's pull on the
    inter-robot alignment, which ``1/n`` weakens enough to slow the distributed solve: small
    seed 0 ended 6 % above centralised with ``1/n``). A keyframe whose view also matches a
    place shifted by the pitch of a repeated structure (a row of identical desks) registers that
    way against every keyframe of the other robot there, and the group would outvote an
    odometry segment that only bending can reconcile (office, 5 robots, seed 9: five 2 m-slid
    closures, all accepted by the centralised GNC as well). With votes, rejecting such a group
    costs less than the bend.

    The closure enters the least squares with ``ω·Ω``, and the TLS decision uses the residual
    with ``Ω`` (callers divide the squared residual by ``ω``): an edge is an inlier by the same
    test as before, it only pulls with its share. Both robots of an inter-robot pair hold the
    same closures between them, so both compute the same votes. The centralised server can apply
    the rule to the joint graph (``Server(closure_votes=True)``), but does not by default: see
    ``server_node.Server``. Arrays ``(m,)`` of the closures' two ends."""
    ends = np.concatenate([np.column_stack([robot_i, kf_i, robot_j]), np.column_stack([robot_j, kf_j, robot_i])])
    m = len(robot_i)
    if m == 0:
        return np.ones(0)
    _, inv, counts = np.unique(ends.astype(np.int64), axis=0, return_inverse=True, return_counts=True)
    n = counts[inv.reshape(-1)]
    return 1.0 / np.sqrt(np.maximum(n[:m], n[m:]).astype(float))


@dataclass
class GncSchedule:
    """One robot's GNC state: ``μ`` and the number of weight updates so far."""

    barc2: float
    mu: float = 0.0
    steps: int = 0
    mu_step: float = MU_STEP

    def update(self, r2: np.ndarray, trusted: np.ndarray | None = None,
               mu0: float | None = None) -> np.ndarray:
        """New weights for ``r2`` at the current ``μ``, then ``μ ← mu_step·μ``.

        ``μ₀`` is ``mu0`` when given (a team-wide value: distributed GNC needs one ``μ`` for the
        whole team), else it comes from the largest residual among the ``trusted`` edges
        (default: all). When the estimate is already robustly initialised, passing the current
        inliers keeps GNC from starting so convex that every closure is nearly switched off.
        """
        r2 = np.asarray(r2, dtype=float)
        if self.steps == 0 and mu0 is not None:
            self.mu = float(mu0)
        elif self.steps == 0:
            self.mu = self.initial_mu(r2, trusted)
        w = tls_weights(r2, self.mu, self.barc2)
        self.mu *= self.mu_step
        self.steps += 1
        return w

    def initial_mu(self, r2: np.ndarray, trusted: np.ndarray | None = None,
                   lo: float = 0.0, hi: float = np.inf) -> float:
        """``μ₀`` from the largest of ``r2`` (over the ``trusted`` edges when any is), clamped
        to ``[lo, hi]``."""
        r2 = np.asarray(r2, dtype=float)
        pool = r2 if trusted is None or not np.any(trusted) else r2[np.asarray(trusted, bool)]
        mu0 = initial_mu(float(pool.max()) if len(pool) else 0.0, self.barc2)
        return float(min(max(mu0, lo), hi))

    @staticmethod
    def binary(weights: np.ndarray, tol: float = 1e-4) -> bool:
        """True when every weight is (within ``tol``) 0 or 1: GNC has converged."""
        w = np.asarray(weights)
        return bool(np.all((w < tol) | (w > 1.0 - tol)))


def precision_recall(predicted_inlier: np.ndarray, true_inlier: np.ndarray) -> tuple[float, float]:
    """Inlier precision and recall of a boolean prediction against ground truth."""
    p, t = np.asarray(predicted_inlier, bool), np.asarray(true_inlier, bool)
    tp = int(np.count_nonzero(p & t))
    precision = tp / max(int(np.count_nonzero(p)), 1)
    recall = tp / max(int(np.count_nonzero(t)), 1)
    return float(precision), float(recall)
