"""Robust PGO scored without ground truth: two solutions compared through their own decisions.

Where the outliers are unknown (data nobody here made), a plain least-squares cost over all
edges, or precision/recall against "every edge is an inlier", says nothing. What can be said:

- the robust (TLS) cost of each solution at its final weights,
  ``½ Σₑ [wₑ rₑ² + (1 − wₑ) c̄²]`` (odometry trusted, ``w = 1``); with binary weights it is the
  truncated cost ``½ Σ min(r², c̄²)`` of the solution's own inlier decision, the objective both
  GNC solvers minimise, so the two are comparable (``tls_gap``);
- the plain cost over the edges each solution kept (``w > ½``);
- the inlier sets of the closures (loop and inter-robot edges), their Jaccard index, and the
  counts per edge kind.

Precision and recall are added only when the truth is known (injected outliers).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from kimera_multi_py.core.posegraph import INTER_ROBOT, LOOP_CLOSURE, ODOMETRY, PoseGraph
from kimera_multi_py.core.robust import precision_recall
from kimera_multi_py.pgo.factors import residuals_sq

KIND_NAMES = {LOOP_CLOSURE: "loop_closure", INTER_ROBOT: "inter_robot"}


def tls_cost(r2: np.ndarray, weights: np.ndarray, barc2: float) -> float:
    """``½ Σ [w r² + (1 − w) c̄²]``: the TLS cost of residuals ``r2`` at ``weights``."""
    w = np.clip(np.asarray(weights, dtype=float), 0.0, 1.0)
    return float(0.5 * np.sum(w * r2 + (1.0 - w) * barc2))


def jaccard(a: np.ndarray, b: np.ndarray) -> float:
    """``|a ∩ b| / |a ∪ b|`` of two boolean masks (1 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    union = int(np.count_nonzero(a | b))
    return float(np.count_nonzero(a & b) / union) if union else 1.0


@dataclass
class RobustEvaluation:
    """Both robust solutions, scored against each other (and the truth when it is known)."""

    centralized_tls_cost: float
    distributed_tls_cost: float
    tls_gap: float  # (distributed − centralised) / centralised TLS cost
    centralized_kept_cost: float
    distributed_kept_cost: float
    inlier_jaccard: float  # of the closure inlier sets
    inlier_counts: dict[str, dict[str, int]]
    inliers_centralized: np.ndarray  # edge indices (closures judged inliers)
    inliers_distributed: np.ndarray
    truth_known: bool = False
    precision_recall: dict[str, dict[str, float]] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "centralized_tls_cost": self.centralized_tls_cost,
            "distributed_tls_cost": self.distributed_tls_cost, "tls_gap": self.tls_gap,
            "centralized_kept_cost": self.centralized_kept_cost,
            "distributed_kept_cost": self.distributed_kept_cost,
            "inlier_jaccard": self.inlier_jaccard, "inlier_counts": self.inlier_counts,
            "inlier_sets": {"centralized": self.inliers_centralized.tolist(),
                            "distributed": self.inliers_distributed.tolist()},
            "truth_known": self.truth_known,
        }
        if self.truth_known:
            out["precision_recall"] = self.precision_recall
        return out


def evaluate_robust(graph: PoseGraph, central_poses: np.ndarray, central_weights: np.ndarray,
                    dist_poses: np.ndarray, dist_weights: np.ndarray, barc2: float,
                    truth: np.ndarray | None = None) -> RobustEvaluation:
    """Score two robust solutions of ``graph`` (poses and per-edge weights each).

    ``truth`` marks the known outliers (``graph.outlier`` of injected ones); ``None`` means the
    evaluation uses no ground truth at all.
    """
    kind = graph.edge_kind()
    closure = kind != ODOMETRY
    scored = []
    for poses, weights in ((central_poses, central_weights), (dist_poses, dist_weights)):
        w = np.where(closure, np.clip(np.asarray(weights, dtype=float), 0.0, 1.0), 1.0)
        r2 = residuals_sq(graph, poses)
        kept = w > 0.5
        scored.append((tls_cost(r2, w, barc2), float(0.5 * r2[kept].sum()), kept & closure))
    (tc, kc, ic), (td, kd, id_) = scored
    counts = {
        name: {"edges": int(np.count_nonzero(kind == k)),
               "inliers_centralized": int(np.count_nonzero(ic & (kind == k))),
               "inliers_distributed": int(np.count_nonzero(id_ & (kind == k))),
               "inliers_both": int(np.count_nonzero(ic & id_ & (kind == k)))}
        for k, name in KIND_NAMES.items()
    }
    ev = RobustEvaluation(
        centralized_tls_cost=tc, distributed_tls_cost=td,
        tls_gap=(td - tc) / max(abs(tc), 1e-300), centralized_kept_cost=kc,
        distributed_kept_cost=kd, inlier_jaccard=jaccard(ic[closure], id_[closure]),
        inlier_counts=counts, inliers_centralized=np.flatnonzero(ic),
        inliers_distributed=np.flatnonzero(id_),
    )
    if truth is not None:
        true_inlier = ~np.asarray(truth, bool)
        ev.truth_known = True
        for name, pred in (("centralized", ic), ("distributed", id_)):
            p, r = precision_recall(pred[closure], true_inlier[closure])
            ev.precision_recall[name] = {"precision": p, "recall": r}
    return ev
