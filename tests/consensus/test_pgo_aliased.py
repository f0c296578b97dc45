"""Distributed robust PGO against *structured* outliers: aliased closures from identical places.

Three robots walk a corridor with two identical rooms 6 m apart. Closures between the rooms are
mutually consistent (they all claim the same ±6 m offset), so per robot pair the alias group can
be as large as the true one; only the joint graph (the third robot, odometry) tells them apart.
The distributed GNC must reject every aliased closure, as the centralised GNC does.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from kimera_multi_py.comms.loopback import LoopbackNetwork
from kimera_multi_py.core.geometry import inverse, make_pose, so3_exp
from kimera_multi_py.core.posegraph import PoseGraph, robot_key
from kimera_multi_py.pgo.agent import PgoAgent
from kimera_multi_py.pgo.centralised import solve_centralized
from kimera_multi_py.pgo.factors import graph_cost
from kimera_multi_py.pgo.local_graph import split_local
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.pgo.runtime import run_team

ROOM_A, ROOM_B, OFFSET = 4.0, 10.0, 6.0  # room centres along x; the rooms look identical
# the simulator's noise: odometry stiff in translation, closures loose (σ [rot rad, trans m])
ODO_SIGMA = np.array([0.05, 0.05, 0.05, 0.003, 0.003, 0.003])
CLOSURE_SIGMA = np.array([0.05, 0.05, 0.05, 0.15, 0.15, 0.15])


def _noisy(Z: np.ndarray, sigma: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    d = rng.normal(size=6) * sigma
    return Z @ make_pose(so3_exp(d[:3]), d[3:])


SIZES = (4, 4, 3, 2, 4)  # closures per group: 0-1 true, 0-1 alias, x-2 true, x-2 alias, 2-2 alias
RING = ((0.0, 0.0), (16.0, 0.0), (16.0, 8.0), (0.0, 8.0))  # a corridor loop; rooms on its first side


def _ring_pose(s: float, lateral: float) -> np.ndarray:
    """The pose at arc length ``s`` along the ring, heading along it, ``lateral`` to its left."""
    sides = [(np.array(RING[k]), np.array(RING[(k + 1) % 4])) for k in range(4)]
    s %= sum(float(np.linalg.norm(b - a)) for a, b in sides)
    for a, b in sides:
        length = float(np.linalg.norm(b - a))
        if s <= length:
            d = (b - a) / length
            yaw = float(np.arctan2(d[1], d[0]))
            p = a + s * d + lateral * np.array([-d[1], d[0]])
            return make_pose(so3_exp(np.array([0.0, 0.0, yaw])), np.array([p[0], p[1], 0.0]))
        s -= length
    raise AssertionError("unreachable")


def aliased_ring(seed: int = 0, loops: int = 2) -> PoseGraph:
    """Joint graph of three robots looping a corridor with two identical rooms (6 m apart).

    Per robot pair the aliased closures form one consistent group (room A of one robot against
    room B of the other); for robots 0-1 it is as large as the true group. Robot 2 also has an
    intra-robot alias group (its room A against its own room B), and owns no inter-robot edge.
    """
    rng = np.random.default_rng(seed)
    starts, lateral = (0.5, 20.5, 34.5), (0.0, 0.3, -0.3)
    trajs = [np.stack([_ring_pose(s0 + k, lat) for k in range(48 * loops)])
             for s0, lat in zip(starts, lateral, strict=True)]
    shift = make_pose(np.eye(3), np.array([-OFFSET, 0.0, 0.0]))  # room B seen as room A
    first = np.cumsum([0] + [len(T) for T in trajs])
    edges: list[tuple[int, int, np.ndarray, np.ndarray, bool]] = []
    odo_info = np.diag(1.0 / ODO_SIGMA**2)
    lc_info = np.diag(1.0 / CLOSURE_SIGMA**2)
    for r, T in enumerate(trajs):
        for k in range(len(T) - 1):
            edges.append((first[r] + k, first[r] + k + 1,
                          _noisy(inverse(T[k]) @ T[k + 1], ODO_SIGMA, rng), odo_info, False))

    def near(r: int, centre: float) -> list[int]:
        return [k for k, T in enumerate(trajs[r]) if abs(T[0, 3] - centre) <= 1.0 and T[1, 3] < 1.0]

    def closure(a: int, ka: int, b: int, kb: int, alias: bool) -> None:
        Tb = shift @ trajs[b][kb] if alias else trajs[b][kb]
        edges.append((first[a] + ka, first[b] + kb,
                      _noisy(inverse(trajs[a][ka]) @ Tb, CLOSURE_SIGMA, rng), lc_info, alias))

    def group(a: int, ra: float, b: int, rb: float, alias: bool, most: int) -> None:
        for ka, kb in list(zip(near(a, ra), near(b, rb), strict=False))[:most]:
            closure(a, ka, b, kb, alias)

    group(0, ROOM_A, 1, ROOM_A, False, SIZES[0])  # robots 0-1: as many aliased as true closures
    group(0, ROOM_A, 1, ROOM_B, True, SIZES[1])
    for a in (0, 1):  # robots 0-2 and 1-2: true closures in both rooms, a smaller alias group
        group(a, ROOM_A, 2, ROOM_A, False, SIZES[2])
        group(a, ROOM_B, 2, ROOM_B, False, SIZES[2])
        group(a, ROOM_B, 2, ROOM_A, True, SIZES[3])
    group(2, ROOM_A, 2, ROOM_B, True, SIZES[4])  # robot 2's own alias group
    i, j, Z, info, outlier = zip(*edges, strict=True)
    robot = np.concatenate([np.full(len(T), r) for r, T in enumerate(trajs)])
    local = np.concatenate([np.arange(len(T)) for T in trajs])
    # every robot starts in its own odometry frame: its first pose at the identity, odometry chained
    init = np.zeros((len(robot), 4, 4))
    for r, T in enumerate(trajs):
        X = np.eye(4)
        for k in range(len(T)):
            init[first[r] + k] = X
            if k + 1 < len(T):
                X = X @ edges[first[r] - r + k][2]
    return PoseGraph(poses=init, robot=robot, local=local,
                     ids=np.array([robot_key(int(r), int(k)) for r, k in zip(robot, local, strict=True)]),
                     edge_i=np.array(i), edge_j=np.array(j), measurement=np.array(Z),
                     information=np.array(info), outlier=np.array(outlier))


def previous_solve_aliased(graph: PoseGraph, robot: int = 1) -> PoseGraph:
    """The team-frame start a warm restart inherits when an earlier solve (with fewer closures)
    put ``robot`` in the aliased hypothesis: its poses off by the room offset."""
    shift = make_pose(np.eye(3), np.array([OFFSET, 0.0, 0.0]))
    idx = graph.robot_indices(robot)
    graph.poses[idx] = shift @ graph.poses[idx]
    return graph


async def distributed(graph: PoseGraph, params: PgoParams,
                      votes: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The distributed robust solve over loopback: every robot's poses and each edge's weight."""
    agents = [PgoAgent(local, params) for local in split_local(graph, frames="given", votes=votes)]
    net = LoopbackNetwork(team="aliased", seed=0, robots=[a.robot for a in agents])
    buses = [net.bus(a.robot) for a in agents]
    try:
        await run_team(agents, buses, params.max_rounds)  # over loopback: waits end when the team is quiet
    finally:
        for b in buses:
            await b.close()
    poses = np.empty_like(graph.poses)
    weights = np.ones(graph.num_edges)
    for a in agents:
        poses[graph.robot_indices(a.robot)] = a.state.poses
        weights[a.local.intra_edge] = a.state.intra_weights
        owned = a.local.inter_peer > a.robot
        weights[a.local.inter_edge[owned]] = a.state.inter_weights[owned]
    return poses, weights


@pytest.mark.slow
def test_distributed_gnc_rejects_aliased_closure_groups() -> None:
    # measured before the fix (per-robot μ₀ from the current residuals, alignment screening):
    # 4 true closures dropped and a cost of 12053 against the reference's 43.08
    graph = previous_solve_aliased(aliased_ring())
    assert graph.outlier.sum() >= 8
    central = solve_centralized(graph, robust=True)
    assert central.weights is not None
    assert not np.any(central.weights[graph.outlier] > 0.5)  # the reference resolves the aliasing
    # robot 1 is not settled (one place), so the root does not follow it while GNC decides
    # (PgoAgent._followers); the joint solve after GNC then moves both, which from this start
    # (robot 1 off by the room offset) takes more than the sim's 600 rounds per epoch
    # the robots align by the consensus of every edge (not the default, which keeps a robot out
    # of the team frame on a tie) so that GNC itself must tell the groups apart
    poses, weights = asyncio.run(distributed(graph, PgoParams(robust=True, max_rounds=800, align_tie="consensus")))
    assert not np.any(weights[graph.outlier] > 0.5), "an aliased closure survived"
    assert np.all(weights[~graph.outlier] > 0.5)
    cost = graph_cost(graph, poses, ~graph.outlier)
    assert abs(cost - central.cost) <= 1e-3 * central.cost
