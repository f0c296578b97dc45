"""gtsam factors and costs for a :class:`~kimera_multi_py.core.posegraph.PoseGraph`.

The cost of a graph is gtsam's error: ``½ Σ eᵀ Λ e`` with ``e = Log(Z⁻¹ Xᵢ⁻¹ Xⱼ)``.
"""

from __future__ import annotations

import gtsam
import numpy as np

from kimera_multi_py.core.geometry import from_gtsam, hat, inverse, so3_log, to_gtsam
from kimera_multi_py.core.posegraph import PoseGraph


def noise(information: np.ndarray, weight: float = 1.0) -> gtsam.noiseModel.Base:
    """Gaussian noise model from a 6x6 information matrix (diagonal when it is diagonal)."""
    info = np.asarray(information, dtype=float) * weight
    diag = np.diag(info)
    if np.count_nonzero(info - np.diag(diag)) == 0:
        return gtsam.noiseModel.Diagonal.Precisions(diag)
    return gtsam.noiseModel.Gaussian.Information(info)


def sqrt_information(information: np.ndarray, weight: float = 1.0) -> np.ndarray:
    """``R`` with ``RᵀR`` the (weighted) information, as gtsam's noise model factors it."""
    model = noise(information, weight)
    if isinstance(model, gtsam.noiseModel.Diagonal):
        return np.diag(1.0 / model.sigmas())
    return np.asarray(model.R())  # type: ignore[attr-defined]  # a Gaussian model here


def between(key_i: int, key_j: int, measurement: np.ndarray, information: np.ndarray,
            weight: float = 1.0) -> gtsam.BetweenFactorPose3:
    """``BetweenFactorPose3`` for ``Xᵢ⁻¹ Xⱼ ≈ measurement``."""
    return gtsam.BetweenFactorPose3(int(key_i), int(key_j), to_gtsam(measurement),
                                    noise(information, weight))


def fixed_neighbour(key: int, own_is_i: bool, neighbour: np.ndarray, measurement: np.ndarray,
                    information: np.ndarray, weight: float = 1.0) -> gtsam.PriorFactorPose3:
    """Exact unary equivalent of a between factor whose other end is held fixed.

    For ``own = j``: ``Log(Z⁻¹Xᵢ⁻¹Xⱼ) = Log(P⁻¹Xⱼ)`` with ``P = Xᵢ Z``. For ``own = i`` the
    prior ``P = Xⱼ Z⁻¹`` has error ``−Ad_Z e``, so its information is ``Ad_{Z⁻¹}ᵀ Λ Ad_{Z⁻¹}``.
    """
    return neighbour_factor(key, neighbour, neighbour_parts(own_is_i, measurement, information, weight))


def neighbour_parts(own_is_i: bool, measurement: np.ndarray, information: np.ndarray,
                    weight: float = 1.0) -> tuple[gtsam.Pose3, gtsam.noiseModel.Base]:
    """What a :func:`fixed_neighbour` factor takes from its edge alone: the offset from the
    neighbour's pose to the prior (``Z`` or ``Z⁻¹``) and the noise model. A solver that rebuilds
    the factor for every new neighbour pose computes these once per edge and weight."""
    Z = to_gtsam(measurement)
    if own_is_i:
        # whiten with R·Ad_{Z⁻¹} (R the square root the between factor would use) rather than
        # re-factoring Ad ᵀΛ Ad: that Cholesky fails on the singular R'R matrices of cubicle
        ad = Z.inverse().AdjointMap()
        return Z.inverse(), gtsam.noiseModel.Gaussian.SqrtInformation(sqrt_information(information, weight) @ ad)
    return Z, noise(information, weight)


def neighbour_factor(key: int, neighbour: np.ndarray,
                     parts: tuple[gtsam.Pose3, gtsam.noiseModel.Base]) -> gtsam.PriorFactorPose3:
    """The :func:`fixed_neighbour` factor from its :func:`neighbour_parts`."""
    offset, model = parts
    return gtsam.PriorFactorPose3(int(key), to_gtsam(neighbour) * offset, model)


def to_values(keys: np.ndarray, poses: np.ndarray) -> gtsam.Values:
    values = gtsam.Values()
    for k, T in zip(keys, poses, strict=False):
        values.insert(int(k), to_gtsam(T))
    return values


def from_values(values: gtsam.Values, keys: np.ndarray) -> np.ndarray:
    return np.stack([from_gtsam(values.atPose3(int(k))) for k in keys])


def build_graph(graph: PoseGraph, weights: np.ndarray | None = None,
                mask: np.ndarray | None = None) -> gtsam.NonlinearFactorGraph:
    """Between factors of ``graph`` (edges in ``mask``, information scaled by ``weights``)."""
    keys = graph.keys
    fg = gtsam.NonlinearFactorGraph()
    for e in range(graph.num_edges):
        if mask is not None and not mask[e]:
            continue
        w = 1.0 if weights is None else float(weights[e])
        if w <= 0.0:
            continue
        fg.add(between(keys[graph.edge_i[e]], keys[graph.edge_j[e]], graph.measurement[e],
                       graph.information[e], w))
    return fg


class CostEvaluator:
    """Evaluates the cost of one fixed edge set at many pose arrays (factors built once)."""

    def __init__(self, graph: PoseGraph, mask: np.ndarray | None = None) -> None:
        self.keys = graph.keys
        self.graph = build_graph(graph, mask=mask)

    def __call__(self, poses: np.ndarray) -> float:
        return float(self.graph.error(to_values(self.keys, poses)))


def residuals_sq(graph: PoseGraph, poses: np.ndarray,
                 edges: np.ndarray | None = None) -> np.ndarray:
    """Squared Mahalanobis residuals ``eᵀΛe`` of the chosen edges (all by default)."""
    sub = graph if edges is None else graph.subset_edges(np.asarray(edges, dtype=int))
    e = edge_errors(sub, poses)
    return np.einsum("mi,mij,mj->m", e, sub.information, e)


def se3_log_full(T: np.ndarray) -> np.ndarray:
    """gtsam's ``Pose3.Logmap`` batched: ``[ω, V(ω)⁻¹ t]`` for ``(..., 4, 4)`` poses."""
    w = so3_log(T[..., :3, :3])
    t = T[..., :3, 3]
    theta2 = np.sum(w * w, axis=-1)
    theta = np.sqrt(theta2)
    W = hat(w)
    small = theta < 1e-5
    th = np.where(small, 1.0, theta)
    coef = np.where(small, 1.0 / 12.0,
                    (1.0 - th * np.sin(th) / (2.0 * (1.0 - np.cos(th))))
                    / np.where(small, 1.0, th**2))
    Vinv = np.eye(3) - 0.5 * W + coef[..., None, None] * (W @ W)
    return np.concatenate([w, (Vinv @ t[..., None])[..., 0]], axis=-1)


def edge_errors(graph: PoseGraph, poses: np.ndarray) -> np.ndarray:
    """Per-edge tangent errors ``Log(Z⁻¹ Xᵢ⁻¹ Xⱼ)`` ``(m, 6)``, vectorised."""
    A = inverse(graph.measurement) @ inverse(poses[graph.edge_i]) @ poses[graph.edge_j]
    return se3_log_full(A)


def graph_cost(graph: PoseGraph, poses: np.ndarray, mask: np.ndarray | None = None) -> float:
    """gtsam error ``½ Σ eᵀΛe`` over the edges in ``mask`` (numpy, no factor graph)."""
    e = edge_errors(graph, poses)
    r2 = np.einsum("mi,mij,mj->m", e, graph.information, e)
    return float(0.5 * (r2 if mask is None else r2[mask]).sum())
