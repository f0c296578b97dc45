"""The ``pgo`` workflow: load a graph, solve it centrally and distributed, score, write.

Inputs: g2o / TORO files (SE(3), or SE(2) solved as planar SE(3) with 2-D outputs) and DPGO CSV
folders. Robust runs are scored without ground truth (:mod:`kimera_multi_py.eval.pgo`); precision, recall
and the outlier-free reference appear only when the outliers were injected here.

``run_pgo(...)`` reads as its stages: ``_load``, ``_inject``, ``_centralized``,
``_distributed``, ``_score``, ``_write``. It returns a :class:`PgoRunResult`; only the CLI prints.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np

from kimera_multi_py.comms.loopback import LoopbackNetwork
from kimera_multi_py.comms.team import open_buses
from kimera_multi_py.core.errors import ConfigError, DatasetError
from kimera_multi_py.core.geometry import make_pose, quat_to_rot
from kimera_multi_py.core.posegraph import INTER_ROBOT, PoseGraph, merge_graphs, split_contiguous
from kimera_multi_py.core.robust import precision_recall, tls_threshold
from kimera_multi_py.eval.pgo import RobustEvaluation, evaluate_robust
from kimera_multi_py.io.dpgo_csv import read_dpgo_csv
from kimera_multi_py.io.g2o import read_g2o, write_g2o
from kimera_multi_py.io.planar import project_planar, se2_to_pose
from kimera_multi_py.io.tum import write_tum
from kimera_multi_py.pgo.agent import PgoAgent
from kimera_multi_py.pgo.centralised import CentralizedResult, solve_centralized
from kimera_multi_py.pgo.factors import graph_cost
from kimera_multi_py.pgo.gn import make_agent
from kimera_multi_py.pgo.local_graph import split_local
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.pgo.pose_stream import PoseStreamParams
from kimera_multi_py.pgo.runtime import RunStats, run_team

log = logging.getLogger(__name__)
Method = Literal["block_sor", "gn_pcg"]

METHODS = ("block_sor", "gn_pcg")
# the solver of ``run_pgo`` called without a method (the agents' team PGO uses PgoParams').
# ``kimera-multi pgo`` and benchmarks/pgo.py pass cli.pgo.CLI_METHOD ("gn_pcg"); block SOR
# stays the library default: it tolerates late joiners (gn_pcg needs the whole team at start)
DEFAULT_METHOD = "block_sor"
# the centralised reference "did not converge" when it ends above the distributed cost by more
# than this (relative): a gap to a failed reference is no figure (INTEL's LM from the odometry)
REFERENCE_TOL = 1e-4
NOT_CONVERGED = "reference did not converge"


@dataclass
class PgoRunResult:
    """Figures of one centralised-vs-distributed run (see :meth:`to_json`)."""

    dataset: str
    robots: int
    centralized_cost: float
    distributed_cost: float
    relative_gap: float
    rounds: int
    rounds_to_1e_2: int | None
    rounds_to_1e_3: int | None
    bytes_sent: int
    wall_s: float
    centralized_wall_s: float
    transport: str
    robust: bool
    outliers: int = 0
    inlier_precision: float | None = None
    inlier_recall: float | None = None
    outlier_free_cost: float | None = None
    gap_to_outlier_free: float | None = None
    bytes_by_topic: dict[str, int] = field(default_factory=dict)
    timeouts: int = 0
    dropped: int = 0  # messages the loopback network's fault injection dropped
    truth_known: bool = False  # outliers were injected here, so which edges are wrong is known
    robust_eval: RobustEvaluation | None = None
    centralized_weights: np.ndarray | None = None  # per-edge GNC weights (robust only)
    distributed_weights: np.ndarray | None = None
    history: list[float] = field(default_factory=list)
    poses: np.ndarray | None = None
    centralized_poses: np.ndarray | None = None
    graph: PoseGraph | None = None
    reference_converged: bool = True  # False: the reference ended above the distributed cost
    centralized_init: str = ""  # how the reference was started (centralised.solve_centralized)

    @property
    def reference(self) -> str:
        """One line on the reference: ``"converged"`` or :data:`NOT_CONVERGED` with both costs."""
        if self.reference_converged:
            return "converged"
        return (f"{NOT_CONVERGED}: centralised {self.centralized_cost:.6g} > distributed "
                f"{self.distributed_cost:.6g} (start: {self.centralized_init})")

    def to_json(self) -> dict[str, Any]:
        out = {
            "dataset": self.dataset, "robots": self.robots, "transport": self.transport,
            "robust": self.robust,
            "centralized_cost": self.centralized_cost, "distributed_cost": self.distributed_cost,
            "relative_gap": self.relative_gap, "rounds": self.rounds,
            "rounds_to_1e-2": self.rounds_to_1e_2, "rounds_to_1e-3": self.rounds_to_1e_3,
            "bytes_sent": self.bytes_sent, "bytes_by_topic": self.bytes_by_topic,
            "wall_s": self.wall_s, "centralized_wall_s": self.centralized_wall_s,
            "timeouts": self.timeouts, "dropped": self.dropped,
            "reference": self.reference, "centralized_init": self.centralized_init,
        }
        if not self.reference_converged:
            # measured against a failed reference, the gap and the rounds to reach it are false
            out.update({k: None for k in ("relative_gap", "rounds_to_1e-2", "rounds_to_1e-3")})
        if self.robust and not self.truth_known:
            # plain costs over all edges (outliers included) and the rounds to reach them mean
            # nothing when the outliers are unknown: the robust figures below replace them
            out.update({k: None for k in ("centralized_cost", "distributed_cost",
                                          "relative_gap", "rounds_to_1e-2", "rounds_to_1e-3")})
        if self.robust_eval is not None:
            out.update(self.robust_eval.to_json())
        if self.truth_known:
            out.update({
                "outliers": self.outliers, "inlier_precision": self.inlier_precision,
                "inlier_recall": self.inlier_recall, "outlier_free_cost": self.outlier_free_cost,
                "gap_to_outlier_free": self.gap_to_outlier_free,
            })
        return out


# ---------------------------------------------------------------------------- inputs
def load_graph(inputs: Sequence[str | Path], robots: int | None = None) -> PoseGraph:
    """Read a DPGO CSV folder, one g2o, or several multi-robot g2o files into one graph.

    A single-robot g2o is split into ``robots`` contiguous blocks (default 5).
    """
    paths = [Path(p) for p in inputs]
    if not paths:
        raise ConfigError("input", "no input given")
    for p in paths:
        if not p.exists():
            raise DatasetError(f"{p}: no such file or folder")
    if len(paths) == 1 and paths[0].is_dir():
        graph = read_dpgo_csv(paths[0])
    else:
        graphs = [read_g2o(p) for p in paths]
        graph = graphs[0] if len(graphs) == 1 else merge_graphs(graphs)
    if graph.num_robots == 1:
        graph = split_contiguous(graph, robots or 5)
    elif robots is not None and robots != graph.num_robots:
        log.warning("%s already has %d robots; --robots %d ignored", graph.source,
                    graph.num_robots, robots)
    return graph


def inject_outliers(graph: PoseGraph, fraction: float, seed: int = 0) -> PoseGraph:
    """Add ``round(fraction · #inter-robot edges)`` random wrong inter-robot closures.

    Each joins random poses of two different robots with a uniformly random rotation and a
    translation uniform in the trajectory's bounding box, and the information of a random true
    inter-robot edge. ``graph.outlier`` marks them (ground truth for scoring).
    """
    if fraction < 0:
        raise ConfigError("outliers", f"fraction must be >= 0, got {fraction}")
    inter = np.flatnonzero(graph.edge_kind() == INTER_ROBOT)
    count = int(round(fraction * len(inter)))
    if count == 0:
        return graph
    if graph.num_robots < 2 or len(inter) == 0:
        raise ConfigError("outliers", "outlier closures need at least one inter-robot edge")
    rng = np.random.default_rng(seed)
    ri = rng.integers(0, graph.num_robots, count)
    rj = (ri + rng.integers(1, graph.num_robots, count)) % graph.num_robots
    by_robot = [graph.robot_indices(r) for r in range(graph.num_robots)]
    ei = np.array([rng.choice(by_robot[r]) for r in ri])
    ej = np.array([rng.choice(by_robot[r]) for r in rj])
    q = rng.normal(size=(count, 4))
    lo, hi = graph.poses[:, :3, 3].min(0), graph.poses[:, :3, 3].max(0)
    span = np.maximum(hi - lo, 1.0)
    t = rng.uniform(-span / 2, span / 2, size=(count, 3))
    meas = make_pose(quat_to_rot(q), t)
    if graph.planar:  # a wrong 2-D closure: random heading and planar translation
        meas = se2_to_pose(np.column_stack([t[:, :2], rng.uniform(-np.pi, np.pi, count)]))
    info = graph.information[rng.choice(inter, count)]
    return PoseGraph(
        poses=graph.poses, robot=graph.robot, local=graph.local, ids=graph.ids,
        edge_i=np.concatenate([graph.edge_i, ei]), edge_j=np.concatenate([graph.edge_j, ej]),
        measurement=np.concatenate([graph.measurement, meas]),
        information=np.concatenate([graph.information, info]), source=graph.source,
        outlier=np.concatenate([graph.outlier, np.ones(count, dtype=bool)]),
        planar=graph.planar,
    )


# ---------------------------------------------------------------------------- workflow
def run_pgo(inputs: Sequence[str | Path], robots: int | None = None,
            transport: str = "loopback", robust: bool = False, outliers: float = 0.0,
            seed: int = 0, max_rounds: int = 500, out_dir: str | Path | None = None,
            params: PgoParams | None = None, drop: float = 0.0,
            round_timeout: float | None = None,
            start_round: dict[int, int] | None = None,
            method: str | None = None, stream: PoseStreamParams | None = None) -> PgoRunResult:
    """Centralised reference and distributed solve of the same graph, scored against each other.

    ``method`` picks the distributed solver (:data:`METHODS`; default :data:`DEFAULT_METHOD`
    unless ``params`` is given, whose ``method`` then holds). ``stream``: public poses as a
    pose stream (:mod:`kimera_multi_py.pgo.pose_stream`); None sends them in full.
    ``round_timeout``: wall seconds a round waits over Zenoh (default 2); over loopback a round's
    wait ends when the team is quiet, and it is not used (:mod:`kimera_multi_py.pgo.runtime`).
    """
    graph = _inject(load_graph(inputs, robots), outliers, seed)
    params = params or PgoParams(method=cast(Method, DEFAULT_METHOD))
    if method is not None:
        if method not in METHODS:
            raise ConfigError("method", f"must be one of {METHODS}, got {method!r}")
        params.method = cast(Method, method)
    params.robust = robust
    params.max_rounds = max_rounds
    if graph.planar:
        params.tls_dof = 3  # a 2-D residual has 3 degrees of freedom (the others are 0)
    central = _centralized(graph, robust, params)
    timeout = round_timeout if round_timeout is not None else (
        0.2 if transport == "loopback" else 2.0)
    poses, stats, history, agents = asyncio.run(
        _distributed(graph, params, transport, drop, seed, timeout, start_round, stream))
    result = _score(graph, central, poses, stats, history, agents, transport, robust,
                    truth_known=outliers > 0, barc2=tls_threshold(params.inlier_probability,
                                                                  params.tls_dof))
    if out_dir is not None:
        _write(Path(out_dir), result)
    return result


def _inject(graph: PoseGraph, outliers: float, seed: int) -> PoseGraph:
    return inject_outliers(graph, outliers, seed) if outliers > 0 else graph


def _centralized(graph: PoseGraph, robust: bool, params: PgoParams) -> CentralizedResult:
    return solve_centralized(graph, robust=robust, inlier_probability=params.inlier_probability,
                             dof=params.tls_dof)


async def _distributed(graph: PoseGraph, params: PgoParams, transport: str, drop: float,
                       seed: int, timeout: float, start_round: dict[int, int] | None,
                       stream: PoseStreamParams | None = None
                       ) -> tuple[np.ndarray, RunStats, list[float], list[PgoAgent]]:
    """Run the team; ``stats.dropped`` (set here) counts the messages the network dropped."""
    agents = [make_agent(local, params) for local in split_local(graph)]
    index = [graph.robot_indices(a.robot) for a in agents]
    inliers = ~graph.outlier
    history: list[float] = []

    def on_round(rnd: int, poses: dict[int, np.ndarray]) -> None:
        full = np.empty_like(graph.poses)
        for a, idx in zip(agents, index, strict=True):
            full[idx] = poses[a.robot]
        history.append(graph_cost(graph, full, inliers))

    async with open_buses([a.robot for a in agents], transport, drop, seed) as buses:
        stats = await run_team(agents, buses, params.max_rounds, timeout, on_round, start_round, stream)
        net = getattr(buses[0], "network", None) if buses else None
        dropped = int(net.stats.dropped) if isinstance(net, LoopbackNetwork) else 0
    stats.dropped = dropped
    full = np.empty_like(graph.poses)
    for a, idx in zip(agents, index, strict=True):
        full[idx] = a.state.poses
    return full, stats, history, agents


def _first_below(history: list[float], reference: float, tol: float) -> int | None:
    for rnd, cost in enumerate(history):
        if (cost - reference) / max(abs(reference), 1e-300) <= tol:
            return rnd
    return None


def _score(graph: PoseGraph, central: CentralizedResult, poses: np.ndarray, stats: RunStats,
           history: list[float], agents: list[PgoAgent], transport: str,
           robust: bool, truth_known: bool = True, barc2: float | None = None) -> PgoRunResult:
    inliers = ~graph.outlier
    cost = graph_cost(graph, poses, inliers)
    ref = central.cost
    result = PgoRunResult(
        dataset=graph.source, robots=graph.num_robots, centralized_cost=ref,
        distributed_cost=cost, relative_gap=(cost - ref) / max(abs(ref), 1e-300),
        rounds=stats.rounds, rounds_to_1e_2=_first_below(history, ref, 1e-2),
        rounds_to_1e_3=_first_below(history, ref, 1e-3), bytes_sent=stats.bytes_sent,
        wall_s=stats.wall_s, centralized_wall_s=central.wall_s, transport=transport,
        robust=robust, outliers=int(graph.outlier.sum()), bytes_by_topic=stats.bytes_by_topic,
        timeouts=stats.timeouts, dropped=stats.dropped, history=history,
        poses=poses, centralized_poses=central.poses, graph=graph, truth_known=truth_known,
        centralized_init=central.init,
        # (robust runs compare TLS costs at their own decisions: eval.pgo)
        reference_converged=robust or ref - cost <= REFERENCE_TOL * max(abs(cost), 1e-300),
    )
    if not result.reference_converged:
        log.warning("%s: %s", graph.source, result.reference)
    if robust:
        weights = distributed_weights(graph, agents)
        assert central.weights is not None
        result.centralized_weights, result.distributed_weights = central.weights, weights
        truth = graph.outlier if truth_known else None
        result.robust_eval = evaluate_robust(graph, central.poses, central.weights, poses, weights,
                                             tls_threshold(0.999) if barc2 is None else barc2,
                                             truth)
        if truth_known:
            inter = graph.edge_kind() == INTER_ROBOT
            result.inlier_precision, result.inlier_recall = precision_recall(
                weights[inter] > 0.5, inliers[inter])
    if truth_known and graph.outlier.any():
        free = solve_centralized(graph.subset_edges(inliers))
        result.outlier_free_cost = free.cost
        result.gap_to_outlier_free = (cost - free.cost) / max(abs(free.cost), 1e-300)
    return result


def distributed_weights(graph: PoseGraph, agents: Sequence[PgoAgent]) -> np.ndarray:
    """Per-edge GNC weights of a distributed run (odometry 1; an inter-robot edge's weight is
    its lower-id robot's, which decides it)."""
    weights = np.ones(graph.num_edges)
    for a in agents:
        weights[a.local.intra_edge] = a.state.intra_weights
        owned = a.local.inter_peer > a.robot
        weights[a.local.inter_edge[owned]] = a.state.inter_weights[owned]
    return weights


def _write(out: Path, result: PgoRunResult) -> None:
    """``distributed.g2o``, ``centralized.g2o``, one TUM file per robot, ``results.json``."""
    graph = result.graph
    assert graph is not None and result.poses is not None
    out.mkdir(parents=True, exist_ok=True)
    write_g2o(out / "distributed.g2o", graph, result.poses)
    if result.centralized_poses is not None:
        write_g2o(out / "centralized.g2o", graph, result.centralized_poses)
    # a 2-D graph's trajectories are 2-D (z = 0, yaw only); g2o files are written as SE(2)
    poses = project_planar(result.poses) if graph.planar else result.poses
    for r in range(graph.num_robots):
        idx = graph.robot_indices(r)
        write_tum(out / f"robot{r}.tum", graph.local[idx].astype(float), poses[idx])
    (out / "results.json").write_text(json.dumps(result.to_json(), indent=2))


