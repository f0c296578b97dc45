"""A robot aligned into an aliased frame switches to the true frame once true closures arrive.

Two robots loop a corridor with two identical rooms (A and B, 6 m apart; see
:mod:`tests.consensus.test_pgo_aliased`). In the first epoch the only closures between them
match robot 0's room A to robot 1's room B: one consistent group, nothing to tell it from the
truth, so robot 1 ends up 6 m off. In the next epoch (warm-started from that estimate, as
``TeamPgo`` does) true closures arrive in room A and in a corner no other place resembles: the
true hypothesis now rests on two places against the alias's one, and robot 1 must switch.
"""

from __future__ import annotations

import asyncio

import numpy as np

from kimera_multi_py.comms.loopback import LoopbackNetwork
from kimera_multi_py.consensus.pgo import PgoAgent, PgoParams, split_local
from kimera_multi_py.consensus.runner import run_team
from kimera_multi_py.geometry import inverse, make_pose
from kimera_multi_py.io.pose_graph import PoseGraph, robot_key
from tests.consensus.test_pgo_aliased import CLOSURE_SIGMA, OFFSET, ROOM_A, ROOM_B, _noisy, _ring_pose

# the simulator's odometry noise per keyframe (0.15 deg, 2 cm per axis)
ODO_SIGMA = np.array([0.0026, 0.0026, 0.0026, 0.02, 0.02, 0.02])

CORNER = np.array([16.0, 8.0])  # a place unlike any other


def _team(seed: int = 0) -> tuple[list[np.ndarray], list[tuple[int, int, np.ndarray, np.ndarray, bool]], np.ndarray]:
    rng = np.random.default_rng(seed)
    trajs = [np.stack([_ring_pose(s0 + k, lat) for k in range(48)]) for s0, lat in ((0.5, 0.0), (20.5, 0.3))]
    first = np.array([0, len(trajs[0])])
    odo = []
    for r, T in enumerate(trajs):
        for k in range(len(T) - 1):
            odo.append((first[r] + k, first[r] + k + 1, _noisy(inverse(T[k]) @ T[k + 1], ODO_SIGMA, rng),
                        np.diag(1.0 / ODO_SIGMA**2), False))
    return trajs, odo, first


def _near(T: np.ndarray, centre: np.ndarray) -> list[int]:
    return [k for k in range(len(T)) if np.linalg.norm(T[k, :2, 3] - centre) <= 1.6]


def _closures(trajs: list[np.ndarray], first: np.ndarray, places: list[tuple[np.ndarray, np.ndarray, bool]],
              rng: np.random.Generator) -> list[tuple[int, int, np.ndarray, np.ndarray, bool]]:
    shift = make_pose(np.eye(3), np.array([-OFFSET, 0.0, 0.0]))  # room B seen as room A
    out = []
    for c0, c1, alias in places:
        for ka, kb in list(zip(_near(trajs[0], c0), _near(trajs[1], c1), strict=False))[:4]:
            Tb = shift @ trajs[1][kb] if alias else trajs[1][kb]
            out.append((first[0] + ka, first[1] + kb, _noisy(inverse(trajs[0][ka]) @ Tb, CLOSURE_SIGMA, rng),
                        np.diag(1.0 / CLOSURE_SIGMA**2), alias))
    return out


def _graph(trajs: list[np.ndarray], edges: list, poses: np.ndarray) -> PoseGraph:
    i, j, Z, info, outlier = zip(*edges, strict=True)
    robot = np.concatenate([np.full(len(T), r) for r, T in enumerate(trajs)])
    local = np.concatenate([np.arange(len(T)) for T in trajs])
    return PoseGraph(poses=poses, robot=robot, local=local,
                     ids=np.array([robot_key(int(r), int(k)) for r, k in zip(robot, local, strict=True)]),
                     edge_i=np.array(i), edge_j=np.array(j), measurement=np.array(Z), information=np.array(info),
                     outlier=np.array(outlier))


def _odometry_start(trajs: list[np.ndarray], odo: list) -> np.ndarray:
    poses, e = [], 0
    for T in trajs:
        X = np.eye(4)
        for k in range(len(T)):
            poses.append(X)
            if k + 1 < len(T):
                X = X @ odo[e][2]
                e += 1
    return np.stack(poses)


async def _epoch(graph: PoseGraph) -> tuple[list[PgoAgent], np.ndarray]:
    agents = [PgoAgent(local, PgoParams(robust=True, max_rounds=300)) for local in split_local(graph, frames="given")]
    net = LoopbackNetwork(team="switch", seed=0, robots=[a.robot for a in agents])
    buses = [net.bus(a.robot) for a in agents]
    try:
        await run_team(agents, buses, 300, round_timeout=0.2)
    finally:
        for b in buses:
            await b.close()
    poses = np.empty_like(graph.poses)
    for a in agents:
        poses[graph.robot_indices(a.robot)] = a.final_poses()
    return agents, poses


def _frame_error(trajs: list[np.ndarray], poses: np.ndarray, first: np.ndarray) -> float:
    """Mean position error of robot 1 in robot 0's frame (robot 0's first pose at the identity)."""
    to_team = inverse(trajs[0][0])
    est = poses[first[1]:, :3, 3]
    true = (to_team @ trajs[1])[:, :3, 3]
    return float(np.linalg.norm(est - true, axis=1).mean())


def test_aliased_robot_switches_to_the_true_frame() -> None:
    trajs, odo, first = _team()
    rng = np.random.default_rng(1)
    a, b = np.array([ROOM_A, 0.0]), np.array([ROOM_B, 0.0])
    alias = _closures(trajs, first, [(a, b, True)], rng)
    # epoch 1: only the aliased group (robot 0 in room A, robot 1 in room B)
    g1 = _graph(trajs, odo + alias, _odometry_start(trajs, odo))
    agents, poses = asyncio.run(_epoch(g1))
    assert agents[1].aligned and agents[1].alignment["support"] == 1  # the report says: one place
    assert abs(_frame_error(trajs, poses, first) - OFFSET) < 1.5  # merged into the alias frame
    # epoch 2: true closures in room A and at the corner, warm-started from epoch 1
    true = _closures(trajs, first, [(a, a, False), (CORNER, CORNER, False)], rng)
    g2 = _graph(trajs, odo + alias + true, poses)
    agents, poses = asyncio.run(_epoch(g2))
    assert agents[1].alignment["status"] == "aligned" and agents[1].alignment["support"] >= 2
    assert _frame_error(trajs, poses, first) < 0.5
    w = agents[0].inter_weights  # robot 0 owns (decides) the 0-1 edges
    outlier = g2.outlier[agents[0].local.inter_edge]
    assert outlier.sum() == len(alias) and np.all(w[outlier] < 0.5) and np.all(w[~outlier] > 0.5)


def test_a_tie_between_single_place_groups_keeps_the_robot_out_of_the_team_frame() -> None:
    """Twin rooms and nothing else: the alias (robot 0's room A against robot 1's room B) and the
    truth (room A against room A) each rest on one place. No number of edges tells them apart, so
    robot 1 is excluded (its own frame) instead of aligned by the consensus of every edge."""
    trajs, odo, first = _team()
    rng = np.random.default_rng(2)
    a, b = np.array([ROOM_A, 0.0]), np.array([ROOM_B, 0.0])
    edges = _closures(trajs, first, [(a, b, True), (a, a, False)], rng)
    agents, poses = asyncio.run(_epoch(_graph(trajs, odo + edges, _odometry_start(trajs, odo))))
    report = agents[1].alignment
    assert report["status"] == "excluded", report
    assert [c[0] for c in report["competitors"]] == [1, 1]  # two hypotheses, one place each
    assert np.allclose(poses[first[1]], np.eye(4), atol=1e-9)  # returned in its own frame
