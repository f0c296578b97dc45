"""Correlated loop closures split one vote in the robust cost (office seed 9 with 5
robots): a keyframe that also matches a place shifted by the pitch of a repeated structure
registers that way against every keyframe of the other robot there, and the group of such
closures outvotes the odometry segment that would have to bend to fit them."""

from __future__ import annotations

import asyncio

import numpy as np

from kimera_multi_py.core.geometry import inverse, make_pose, so3_exp
from kimera_multi_py.core.posegraph import PoseGraph
from kimera_multi_py.core.robust import correlated_votes
from kimera_multi_py.pgo.centralised import solve_centralized
from kimera_multi_py.pgo.params import PgoParams
from tests.consensus.test_pgo_aliased import distributed

N, SLID = 60, 5  # poses per robot; slid closures from robot 0's keyframe 2


def test_votes_count_closures_per_keyframe_and_robot_and_agree_on_both_robots() -> None:
    # robot 3's keyframe 12 against robot 1's 54, 58, 60, 84; robot 1's 84 also against 3's 14;
    # robot 3's 12 against robot 2's 7 is another robot: it does not share the vote
    ra = np.array([1, 1, 1, 1, 1, 2])
    ka = np.array([54, 58, 60, 84, 84, 7])
    rb = np.array([3, 3, 3, 3, 3, 3])
    kb = np.array([12, 12, 12, 12, 14, 12])
    v = correlated_votes(ra, ka, rb, kb)
    assert np.allclose(v, [1 / 2, 1 / 2, 1 / 2, 1 / 2, 1 / np.sqrt(2), 1.0])  # 1/sqrt(n)
    assert np.allclose(correlated_votes(rb, kb, ra, ka), v)  # robot 3's view of the same edges
    # intra-robot closures: keyframes of one robot
    assert np.allclose(correlated_votes(np.zeros(3, int), np.array([50, 50, 70]), np.zeros(3, int),
                                        np.array([2, 3, 4])), [1 / np.sqrt(2), 1 / np.sqrt(2), 1.0])
    assert correlated_votes(*(np.zeros(0, int),) * 4).shape == (0,)


def _slid_graph() -> tuple[PoseGraph, np.ndarray, int]:
    """Two robots on one gently curving path; true closures every other keyframe from 30 on;
    robot 0's keyframe 2 (a segment no true closure holds) matched against robot 1's 2-6 with
    a 2 m lateral slide: one consistent group the odometry can only bend to."""
    steps = [np.eye(4)] + [make_pose(so3_exp([0.0, 0.0, 0.03]), [0.5, 0.0, 0.0])] * (N - 1)
    P = _chain(steps)
    odo = np.diag(np.repeat(1 / np.square([0.0026, 0.02]), 3))
    lc = np.diag(np.repeat(1 / np.square([0.05, 0.15]), 3))
    ei, ej, Z, info, tags = [], [], [], [], []
    for r in (0, 1):
        for k in range(N - 1):
            ei.append(r * N + k)
            ej.append(r * N + k + 1)
            Z.append(inverse(P[k]) @ P[k + 1])
            info.append(odo)
    for k in range(30, N, 2):
        ei.append(k)
        ej.append(N + k)
        Z.append(np.eye(4))
        info.append(lc)
        tags.append((0, k, 1, k))
    slide = make_pose(np.eye(3), [0.0, 2.0, 0.0])
    for b in range(2, 2 + SLID):
        ei.append(2)
        ej.append(N + b)
        Z.append(inverse(P[2]) @ P[b] @ slide)
        info.append(lc)
        tags.append((0, 2, 1, b))
    t = np.array(tags)
    votes = np.ones(len(ei))
    votes[len(ei) - len(t):] = correlated_votes(t[:, 0], t[:, 1], t[:, 2], t[:, 3])
    g = PoseGraph(poses=np.concatenate([P, P]), robot=np.repeat([0, 1], N), local=np.tile(np.arange(N), 2),
                  ids=np.arange(2 * N), edge_i=np.array(ei), edge_j=np.array(ej), measurement=np.array(Z),
                  information=np.array(info))
    return g, votes, len(t)


def _chain(steps: list[np.ndarray]) -> np.ndarray:
    out = [steps[0]]
    for s in steps[1:]:
        out.append(out[-1] @ s)
    return np.array(out)


def _voted(g: PoseGraph, votes: np.ndarray) -> PoseGraph:
    return PoseGraph(poses=g.poses, robot=g.robot, local=g.local, ids=g.ids, edge_i=g.edge_i, edge_j=g.edge_j,
                     measurement=g.measurement, information=g.information * votes[:, None, None])


def test_a_correlated_slid_group_outvotes_the_odometry_without_votes_and_not_with_them() -> None:
    g, votes, closures = _slid_graph()
    true = slice(g.num_edges - closures, g.num_edges - SLID)
    plain = solve_centralized(g, robust=True)
    assert plain.weights is not None and np.all(plain.weights[-SLID:] > 0.5)  # the failure mode
    voted = solve_centralized(_voted(g, votes), robust=True, votes=votes)
    assert voted.weights is not None
    assert np.all(voted.weights[-SLID:] < 0.5)
    assert np.all(voted.weights[true] > 0.5)


def test_distributed_gnc_with_votes_rejects_the_slid_group_as_the_centralised_does() -> None:
    g, votes, closures = _slid_graph()
    params = PgoParams(robust=True, max_rounds=400)
    _, w = asyncio.run(distributed(_voted(g, votes), params, votes))
    assert np.all(w[-SLID:] < 0.5)
    assert np.all(w[g.num_edges - closures: g.num_edges - SLID] > 0.5)
