"""Centralised mode, solver half: the joint graph optimised in one place (the PGO reference).

Chordal initialisation (``gtsam.InitializePose3``) per connected component, then
Levenberg–Marquardt, or gtsam's GNC-TLS when ``robust`` (odometry is a known inlier). Where
gtsam's relaxation fails (cubicle's indefinite matrices, the 2-D INTEL graph's nearly singular
ones) the reference starts LM both from the relaxation of :mod:`.chordal` (sparse least squares,
which does not give up) and from the file's initial values, and keeps the lower cost. An LM
that cannot take a single step (INTEL: the first damped system is rejected at every λ up to
gtsam's bound) is run again with diagonal (Marquardt) damping. ``docs/benchmarks.md`` lists the
graphs this was measured on.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import gtsam
import networkx as nx
import numpy as np

from kimera_multi_py.core.errors import GraphError
from kimera_multi_py.core.geometry import to_gtsam
from kimera_multi_py.core.posegraph import ODOMETRY, PoseGraph
from kimera_multi_py.core.robust import MU_STEP, chi2_quantile, initial_mu, tls_weights
from kimera_multi_py.pgo.chordal import chordal_poses
from kimera_multi_py.pgo.factors import (
    CostEvaluator,
    build_graph,
    from_values,
    residuals_sq,
    to_values,
)

log = logging.getLogger(__name__)


@dataclass
class CentralizedResult:
    """Optimised poses, cost over the inlier edges (unweighted), and how it was obtained."""

    poses: np.ndarray
    cost: float
    initial_cost: float
    init: str
    wall_s: float
    weights: np.ndarray | None = None  # GNC weights per edge (robust only)


def components(graph: PoseGraph) -> list[np.ndarray]:
    """Pose indices of each connected component, ordered by their smallest index."""
    g = nx.Graph()
    g.add_nodes_from(range(graph.num_poses))
    g.add_edges_from(zip(graph.edge_i.tolist(), graph.edge_j.tolist(), strict=False))
    comps = [np.array(sorted(c)) for c in nx.connected_components(g)]
    return sorted(comps, key=lambda c: int(c[0]))


def chordal_initialization(graph: PoseGraph, poses: np.ndarray | None = None,
                           mask: np.ndarray | None = None) -> tuple[np.ndarray, bool]:
    """Chordal relaxation per component, expressed in the frame of each component's first pose.

    Returns ``(poses, ok)``; where gtsam cannot initialise a component its ``poses`` are kept.
    """
    poses = (graph.poses if poses is None else poses).copy()
    sub = graph if mask is None else graph.subset_edges(mask)
    keys = graph.keys
    ok = True
    for comp in components(sub):
        if len(comp) < 2:
            continue
        in_comp = np.zeros(graph.num_poses, dtype=bool)
        in_comp[comp] = True
        fg = build_graph(sub, mask=in_comp[sub.edge_i])
        anchor = int(comp[0])
        fg.add(gtsam.PriorFactorPose3(int(keys[anchor]), to_gtsam(poses[anchor]),
                                      gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        try:
            values = gtsam.InitializePose3.initialize(fg)
        except RuntimeError as exc:
            log.info("chordal initialisation failed (%s); keeping given values",
                     str(exc).strip().splitlines()[0])
            ok = False
            continue
        est = from_values(values, keys[comp])
        # re-anchor: the component's first pose keeps its given value
        T = poses[anchor] @ np.linalg.inv(est[0])
        poses[comp] = T @ est
    return poses, ok


def _gnc(graph: PoseGraph, fg: gtsam.NonlinearFactorGraph, values: gtsam.Values,
         lm: gtsam.LevenbergMarquardtParams, barc2: float) -> tuple[gtsam.Values, np.ndarray]:
    """gtsam GNC-TLS with odometry and priors as known inliers."""
    params = gtsam.GncLMParams(lm)
    params.setLossType(gtsam.GncLossType.TLS)
    known = [int(e) for e in np.flatnonzero(graph.edge_kind() == ODOMETRY)]
    known += list(range(graph.num_edges, fg.size()))  # priors
    params.setKnownInliers(known)
    opt = gtsam.GncLMOptimizer(fg, values, params)
    opt.setInlierCostThresholds(0.5 * barc2)
    result = opt.optimize()
    return result, np.asarray(opt.getWeights())[: graph.num_edges]


def _gnc_votes(graph: PoseGraph, priors: list[gtsam.NonlinearFactor], values: gtsam.Values,
               lm: gtsam.LevenbergMarquardtParams, barc2: float, votes: np.ndarray,
               max_iterations: int = 100, weights_tol: float = 1e-4,
               cost_tol: float = 1e-5) -> tuple[gtsam.Values, np.ndarray]:
    """GNC-TLS with a vote per closure (:func:`kimera_multi_py.core.robust.correlated_votes`; ``graph``'s
    information already carries them): gtsam's schedule (μ₀ from the largest residual, μ ×1.4,
    odometry and priors known inliers, done when the weights are binary or the cost settles),
    the TLS test on ``r²/ω``. gtsam's Python GNC takes one threshold for every factor, which
    is why this loop is ours; each step is gtsam's LM on the weighted graph."""
    odo = graph.edge_kind() == ODOMETRY
    loop = ~odo
    keys = graph.keys
    w = np.ones(graph.num_edges)

    def solve(w: np.ndarray, values: gtsam.Values) -> gtsam.Values:
        on = odo | (w > 1e-9)
        fg = build_graph(graph, weights=w, mask=on)
        for f in priors:
            fg.add(f)
        return gtsam.LevenbergMarquardtOptimizer(fg, values, lm).optimize()

    r2 = residuals_sq(graph, from_values(values, keys)) / votes
    mu = initial_mu(float(r2[loop].max()) if loop.any() else 0.0, barc2)
    cost = np.inf
    for _ in range(max_iterations):
        w[loop] = tls_weights(r2[loop], mu, barc2)
        values = solve(w, values)
        r2 = residuals_sq(graph, from_values(values, keys)) / votes
        new = float((votes * np.where(odo, r2, np.minimum(r2, barc2))).sum())
        binary = np.all((w[loop] < weights_tol) | (w[loop] > 1.0 - weights_tol))
        if binary or abs(cost - new) <= cost_tol * max(new, 1e-12):
            break
        cost = new
        mu *= MU_STEP
    return values, np.where(odo, 1.0, w)


def recheck(graph: PoseGraph, priors: list[gtsam.NonlinearFactor], values: gtsam.Values,
            lm: gtsam.LevenbergMarquardtParams, barc2: float, factor: float = 3.0,
            rounds: int = 4, votes: np.ndarray | None = None) -> tuple[gtsam.Values, np.ndarray]:
    """TLS decisions at a converged robust solution: keep the closures with ``r² ≤ factor·c̄²``,
    re-solve (odometry and priors always in), then ``r² ≤ c̄²`` until the set is stable.
    Returns the solution and binary weights (odometry 1). ``votes``: the test is on ``r²/ω``."""
    odo = graph.edge_kind() == ODOMETRY
    keys = graph.keys
    w = np.ones(graph.num_edges)
    vote = np.ones(graph.num_edges) if votes is None else votes
    for k in range(rounds):
        r2 = residuals_sq(graph, from_values(values, keys)) / vote
        new = np.where(odo | (r2 <= (factor if k == 0 else 1.0) * barc2), 1.0, 0.0)
        if k > 0 and np.array_equal(new, w):
            break
        w = new
        fg = build_graph(graph, mask=w > 0)
        for f in priors:
            fg.add(f)
        values = gtsam.LevenbergMarquardtOptimizer(fg, values, lm).optimize()
    return values, w


def solve_centralized(graph: PoseGraph, robust: bool = False, chordal: bool = True,
                      inlier_probability: float = 0.999, relative_tol: float = 1e-8,
                      max_iterations: int = 500, dof: int = 6, recheck_factor: float = 3.0,
                      votes: np.ndarray | None = None) -> CentralizedResult:
    """Optimise the joint graph. The cost reported is over the non-outlier edges, unweighted.
    ``dof``: degrees of freedom of a residual for the TLS threshold (3 for a planar graph).
    ``votes``: robust votes per edge (:func:`_gnc_votes`), already in the graph's information."""
    if graph.num_poses == 0:
        raise GraphError("empty graph")
    t0 = time.perf_counter()
    keys = graph.keys
    init_poses, ok = chordal_initialization(graph) if chordal else (graph.poses, False)
    init = "chordal" if chordal and ok else ("chordal+given" if chordal else "given")
    fg = build_graph(graph)
    for comp in components(graph):
        a = int(comp[0])
        fg.add(gtsam.PriorFactorPose3(int(keys[a]), to_gtsam(init_poses[a]),
                                      gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    values = to_values(keys, init_poses)
    lm = gtsam.LevenbergMarquardtParams()
    lm.setRelativeErrorTol(relative_tol)
    lm.setAbsoluteErrorTol(0.0)
    lm.setMaxIterations(max_iterations)
    weights = None
    if robust:
        # chordal relaxation sees the outliers too: run GNC from it and from the given values,
        # keep the lower truncated (TLS) cost
        barc2 = chi2_quantile(inlier_probability, dof)
        best = None
        starts = [(init, values)]
        if chordal:
            starts.append(("given", to_values(keys, graph.poses)))
        priors = [fg.at(k) for k in range(graph.num_edges, fg.size())]
        # GNC's inner solves at gtsam's default LM tolerances (each graduated step is re-solved
        # from the last one; the re-check below solves to ``relative_tol``): on cubicle a GNC at
        # 1e-8 / 500 iterations runs for half an hour, at the defaults 7 minutes
        gnc_lm = gtsam.LevenbergMarquardtParams()
        voted = votes is not None and not np.all(votes == 1.0)
        vote = np.ones(graph.num_edges) if votes is None else np.asarray(votes, dtype=float)

        def gnc(start: gtsam.Values) -> tuple[gtsam.Values, np.ndarray]:
            if voted:
                return _gnc_votes(graph, priors, start, gnc_lm, barc2, vote)
            return _gnc(graph, fg, start, gnc_lm, barc2)

        for name, start in starts:
            res, w = gnc(start)
            # gtsam's GNC can stop with every weight at 1 (it judged the start converged), aliased
            # closures included: re-decide every closure at the converged solution with the plain
            # TLS threshold (first with slack, as the distributed solver's rechecks), re-solve
            checked, w_checked = recheck(graph, priors, res, lm, barc2, recheck_factor, votes=vote)
            if not np.array_equal(w_checked > 0.5, w > 0.5):
                # GNC's decisions did not survive the check: GNC again from the checked solution
                # (measured on the aliased ring: the all-in least-squares start re-checked keeps no
                # alias but drops 9 true closures; GNC from there keeps every true one)
                res, _ = gnc(checked)
                checked, w_checked = recheck(graph, priors, res, lm, barc2, recheck_factor, votes=vote)
            res, w = checked, w_checked
            r2 = residuals_sq(graph, from_values(res, keys))
            tls = float(0.5 * np.minimum(r2, vote * barc2).sum())
            if best is None or tls < best[0]:
                best = (tls, res, w, name)
        assert best is not None
        _, result, weights, init = best
    else:
        result = _lm(fg, values, lm)
    poses = from_values(result, keys)
    evaluate = CostEvaluator(graph, mask=~graph.outlier)
    cost, initial_cost = evaluate(poses), evaluate(init_poses)
    if not robust and chordal and not ok:
        # gtsam's relaxation gave up somewhere: also from the sparse relaxation, keep the lower
        alt = sparse_chordal(graph)
        if alt is not None:
            alt_poses = from_values(_lm(fg, to_values(keys, alt), lm), keys)
            alt_cost = evaluate(alt_poses)
            log.info("reference from the given values: %.6g; from the sparse chordal "
                     "relaxation: %.6g", cost, alt_cost)
            if alt_cost < cost:
                poses, cost, initial_cost, init = alt_poses, alt_cost, evaluate(alt), "chordal_sparse"
    wall = time.perf_counter() - t0
    return CentralizedResult(poses=poses, cost=cost, initial_cost=initial_cost,
                             init=init, wall_s=wall, weights=weights)


def _lm(fg: gtsam.NonlinearFactorGraph, values: gtsam.Values,
        lm: gtsam.LevenbergMarquardtParams) -> gtsam.Values:
    """gtsam's LM; when it cannot take one step from ``values``, again with diagonal damping."""
    opt = gtsam.LevenbergMarquardtOptimizer(fg, values, lm)
    result = opt.optimize()
    if opt.iterations() == 0 and fg.error(values) > 0.0:
        log.info("LM took no step (error %.6g); again with diagonal damping", fg.error(values))
        lm.setDiagonalDamping(True)
        try:
            result = gtsam.LevenbergMarquardtOptimizer(fg, values, lm).optimize()
        finally:
            lm.setDiagonalDamping(False)
    return result


def sparse_chordal(graph: PoseGraph) -> np.ndarray | None:
    """The chordal relaxation of :mod:`.chordal` per component (each anchored at its first
    pose's given value); ``None`` where it is not finite."""
    poses = graph.poses.copy()
    for comp in components(graph):
        if len(comp) < 2:
            continue
        index = np.full(graph.num_poses, -1)
        index[comp] = np.arange(len(comp))
        e = np.flatnonzero(index[graph.edge_i] >= 0)
        try:
            est = chordal_poses(poses[comp], index[graph.edge_i[e]], index[graph.edge_j[e]],
                                graph.measurement[e], graph.information[e])
        except (RuntimeError, np.linalg.LinAlgError) as exc:
            log.info("sparse chordal relaxation failed (%s)", exc)
            return None
        poses[comp] = est
    return poses if np.isfinite(poses).all() else None
