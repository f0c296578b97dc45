"""Scan registration through a library (small_gicp's GICP), and fusion with odometry.

* :class:`ScanRegistration` aligns a source cloud to a target cloud from an initial guess
  (coarse to fine over correspondence distances) with one library call per stage; no Python
  loop ever touches a point. Its :class:`Registration` carries the pose and its information:
  the Gauss-Newton Hessian of the GICP cost, scaled to the sensor's noise.
* :func:`constrained_information` keeps only the directions in which the registration adds real
  information next to a prior (the odometry): the generalised eigenvalues of the Hessian
  against the prior's information, ``H v = λ Ω v``. A direction with ``λ`` below a threshold
  (the corridor's axis, a wall seen alone) is dropped, and the registration is flagged
  degenerate; along it the odometry keeps the estimate.
* :func:`fuse` combines two measurements of one relative pose by their information (a few
  Gauss-Newton steps on the tangent space), the estimate both factors give together.

Conventions: tangent vectors are ``[rotation, translation]`` with a right perturbation
``T Exp(ξ)``, as in gtsam's ``Pose3`` and small_gicp's optimiser, so a Hessian from small_gicp
is the information of a gtsam ``BetweenFactor`` measurement as it stands.

small_gicp regularises every point covariance to eigenvalues ``(ε, 1, 1)`` with ``ε = 1e-3``,
so the GICP cost weighs a residual along a surface normal by ``1 / (2 ε)`` whatever the
sensor. With a per-point noise ``σ`` along the normal (both clouds), the Hessian in metres is
``H · 2ε / (2 σ²)``; ``information_scale`` then discounts for the correlation of neighbouring
points (downsampling, a map made of earlier scans) measured against ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kimera_multi_py.core.geometry import inverse, se3_exp, se3_log

_COV_EPS = 1e-3  # small_gicp's covariance regularisation along the normal


@dataclass(frozen=True)
class Registration:
    """The outcome of one registration: ``T`` maps source points into the target frame."""

    T: np.ndarray  # (4, 4) T_target_source
    information: np.ndarray  # (6, 6) [rot, trans], right perturbation, metres and radians
    converged: bool
    inliers: int  # correspondences at the last stage
    source_points: int  # after downsampling
    error: float  # GICP cost at the solution

    @property
    def overlap(self) -> float:
        """Fraction of the (downsampled) source with a correspondence."""
        return self.inliers / self.source_points if self.source_points else 0.0


class ScanRegistration:
    """GICP of a source cloud onto a target cloud (small_gicp), coarse to fine.

    ``voxel``: downsampling of both clouds (m); ``max_correspondence``: the correspondence
    distances of the stages (m), each stage starting from the last; ``num_neighbors``: points
    per covariance; ``point_sigma``: per-point noise along a surface (m) for the information;
    ``information_scale``: discount of the Hessian for correlated points (1 = independent).
    """

    def __init__(self, voxel: float = 0.1, max_correspondence: tuple[float, ...] = (0.5, 0.2),
                 max_iterations: int = 30, num_neighbors: int = 10, point_sigma: float = 0.02,
                 information_scale: float = 1.0, min_points: int = 30) -> None:
        if voxel <= 0 or point_sigma <= 0 or information_scale <= 0 or not max_correspondence:
            raise ValueError("registration: voxel, point_sigma and information_scale must be > 0, "
                             "and there must be at least one correspondence distance")
        self.voxel = float(voxel)
        self.max_correspondence = tuple(float(d) for d in max_correspondence)
        self.max_iterations = int(max_iterations)
        self.num_neighbors = int(num_neighbors)
        self.point_sigma = float(point_sigma)
        self.information_scale = float(information_scale)
        self.min_points = int(min_points)

    @property
    def hessian_scale(self) -> float:
        """From small_gicp's Hessian to information in metres and radians."""
        return self.information_scale * _COV_EPS / self.point_sigma**2

    def _cloud(self, points: np.ndarray) -> tuple[object, object]:
        import small_gicp

        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        return small_gicp.preprocess_points(pts, downsampling_resolution=self.voxel,
                                            num_neighbors=self.num_neighbors, num_threads=1)

    def prepare(self, target: np.ndarray) -> tuple[object, object]:
        """``target`` downsampled, with its covariances and search tree: pass it to
        :meth:`register` in place of the points to align several sources to one target."""
        return self._cloud(target)

    def register(self, target: np.ndarray | tuple[object, object], source: np.ndarray | tuple[object, object],
                 T_init: np.ndarray) -> Registration | None:
        """Align ``source`` ``(n, 3)`` to ``target`` ``(m, 3)`` (either may be :meth:`prepare`-d)
        from ``T_init`` (T_target_source).

        Returns None when either cloud has fewer than ``min_points`` points after downsampling.
        """
        import small_gicp

        T0 = np.asarray(T_init, dtype=np.float64)
        if T0.shape != (4, 4) or not np.all(np.isfinite(T0)):
            raise ValueError(f"registration: the initial guess must be a finite 4x4 pose, not {T0.shape}")
        tgt, tree = target if isinstance(target, tuple) else self._cloud(target)
        src, _ = source if isinstance(source, tuple) else self._cloud(source)
        if tgt.size() < self.min_points or src.size() < self.min_points:  # type: ignore[attr-defined]
            return None
        T = T0
        res = None
        for d in self.max_correspondence:
            res = small_gicp.align(tgt, src, tree, T, registration_type="GICP", max_correspondence_distance=d,
                                   num_threads=1, max_iterations=self.max_iterations)
            T = np.array(res.T_target_source)
        assert res is not None
        H = np.array(res.H, dtype=np.float64)
        info = 0.5 * (H + H.T) * self.hessian_scale
        return Registration(T=T, information=info, converged=bool(res.converged), inliers=int(res.num_inliers),
                            source_points=int(src.size()), error=float(res.error))  # type: ignore[attr-defined]


@dataclass(frozen=True)
class Constrained:
    """The registration's information kept next to a prior, and what was dropped."""

    information: np.ndarray  # (6, 6)
    ratios: np.ndarray  # (6,) generalised eigenvalues H v = λ Ω v, ascending
    degenerate: bool  # some direction was dropped
    basis: np.ndarray  # (6, m) the kept directions, in the prior's whitened coordinates
    whiten: np.ndarray  # (6, 6) Lᵀ: a tangent vector d in whitened coordinates is Lᵀ d

    def project(self, d: np.ndarray) -> np.ndarray:
        """The part of tangent vector ``d`` in the kept directions (zero along dropped ones)."""
        w = self.basis @ (self.basis.T @ (self.whiten @ np.asarray(d, dtype=np.float64)))
        return np.linalg.solve(self.whiten, w)

    def prior_distance(self, d: np.ndarray) -> float:
        """Squared Mahalanobis length (under the prior) of the kept part of tangent vector ``d``."""
        return float(np.sum((self.basis.T @ (self.whiten @ np.asarray(d, dtype=np.float64))) ** 2))


def constrained_information(information: np.ndarray, prior: np.ndarray, min_ratio: float) -> Constrained:
    """Keep the directions where ``information`` is at least ``min_ratio`` times ``prior``'s.

    In the prior's whitened coordinates (``Ω = L Lᵀ``) the registration's information is
    ``M = L⁻¹ H L⁻ᵀ = V diag(λ) Vᵀ``; eigen-directions with ``λ < min_ratio`` are zeroed and the
    rest mapped back, ``L V diag(λ kept) Vᵀ Lᵀ``. The ratios are unit-free, so rotation and
    translation are compared on the prior's own scale.
    """
    H = np.asarray(information, dtype=np.float64)
    P = np.asarray(prior, dtype=np.float64)
    if H.shape != (6, 6) or P.shape != (6, 6):
        raise ValueError(f"constrained_information: 6x6 matrices expected, got {H.shape} and {P.shape}")
    L = np.linalg.cholesky(0.5 * (P + P.T))
    Linv = np.linalg.inv(L)
    M = Linv @ (0.5 * (H + H.T)) @ Linv.T
    lam, V = np.linalg.eigh(M)
    keep = lam >= min_ratio
    kept = L @ (V * np.where(keep, lam, 0.0)) @ V.T @ L.T
    return Constrained(0.5 * (kept + kept.T), lam, bool(not keep.all()), V[:, keep], L.T)


def fuse(Z0: np.ndarray, info0: np.ndarray, Z1: np.ndarray, info1: np.ndarray, iterations: int = 3) -> np.ndarray:
    """The pose that best agrees with two measurements of it, weighted by their information.

    Minimises ``|Log(Z0⁻¹ X)|²_Ω0 + |Log(Z1⁻¹ X)|²_Ω1`` from ``X = Z0`` by Gauss-Newton (the
    Jacobians are the identity to first order; the measurements are centimetres apart).
    Along a direction where ``info1`` is zero, ``X`` keeps ``Z0``.
    """
    X = np.asarray(Z0, dtype=np.float64)
    A = np.asarray(info0, dtype=np.float64) + np.asarray(info1, dtype=np.float64)
    for _ in range(iterations):
        r0 = se3_log(inverse(Z0) @ X)
        r1 = se3_log(inverse(Z1) @ X)
        step = -np.linalg.solve(A, info0 @ r0 + info1 @ r1)
        X = X @ se3_exp(step)
        if np.linalg.norm(step) < 1e-12:
            break
    return X
