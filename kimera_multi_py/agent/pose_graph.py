"""What one robot contributes to the team's pose graph (docs/algorithms/pgo.md): its own edges
(odometry, scan registrations, accepted intra-robot closures) and, with its accepted inter-robot
closures and the robust votes of correlated closures, its
:class:`~kimera_multi_py.pgo.local_graph.LocalGraph`.
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.agent.closures import Closure
from kimera_multi_py.agent.params import AgentParams
from kimera_multi_py.core.geometry import inverse
from kimera_multi_py.core.posegraph import robot_key
from kimera_multi_py.core.robust import correlated_votes
from kimera_multi_py.pgo.local_graph import LocalGraph

Edges = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""``(i, j, Z, info, is_odometry)``: keyframe indices, measurements ``(m, 4, 4)``, information
``(m, 6, 6)`` and which edges are trusted odometry."""


def information(sigmas: tuple[float, float]) -> np.ndarray:
    """The diagonal information of (rotation rad, translation m) sigmas, three axes each."""
    return np.diag(np.repeat(1.0 / np.square(sigmas), 3))


def intra_edges(num_keyframes: int, steps: list[np.ndarray], odometry: list[np.ndarray],
                registrations: dict[int, tuple[np.ndarray, np.ndarray]] | None, closures: list[Closure],
                params: AgentParams) -> Edges:
    """Odometry, scan registrations and accepted intra-robot closures: ``(i, j, Z, info, is_odometry)``.

    ``steps`` are the registration-refined keyframe steps, ``odometry`` the raw ones,
    ``registrations`` the scan odometry's factors by keyframe (None without scan odometry) and
    ``closures`` the robot's intra-robot closures. ``registration_factor="fused"``: one trusted
    (``is_odometry``) factor per keyframe step, the registration-refined step under the
    odometry's information. ``"separate"``: a registration factor joins the odometry factor of
    its step; both are trusted, its information is the registration's (zero where degenerate)."""
    n = num_keyframes
    i = list(range(n - 1))
    j = list(range(1, n))
    fused = params.registration_factor == "fused"
    Z = list(steps[1:] if fused else odometry[1:])
    info = [information(params.odom_sigmas)] * (n - 1)
    odo = [True] * (n - 1)
    if registrations is not None and not fused:
        for k, (Zr, Ir) in sorted(registrations.items()):
            i.append(k - 1)
            j.append(k)
            Z.append(Zr)
            info.append(Ir)
            odo.append(True)
    for c in closures:
        if c.accepted:
            i.append(c.own_kf)
            j.append(c.peer_kf)
            Z.append(c.Z)
            info.append(information(params.closure_sigmas))
            odo.append(False)
    return (np.array(i, dtype=int), np.array(j, dtype=int), np.array(Z).reshape(-1, 4, 4),
            np.array(info).reshape(-1, 6, 6), np.array(odo, dtype=bool))


def local_graph(robot: int, team: tuple[int, ...] | None, poses: list[np.ndarray], intra: Edges,
                inter_edges: dict[tuple[int, int, int], tuple[np.ndarray, int]], robot_graph: set[tuple[int, int]],
                params: AgentParams) -> LocalGraph:
    """What robot ``robot`` contributes to distributed PGO, from its current estimate ``poses``.

    ``intra`` are its own edges (:func:`intra_edges`); ``inter_edges`` its accepted inter-robot
    edges, ``(own_kf, peer, peer_kf) -> (Z own<-peer, inliers)``. An inter-robot edge is the
    lower robot id's measurement, directed lower → higher (as in the joint graph): both robots
    must hold the same factor. The higher robot's stored copy is the inverse, and the inverse
    with the same (diagonal) information is a different factor; with it the two block problems
    disagree and the distributed solve cycles.
    """
    i, j, Z, info, odo = intra
    edges = sorted(inter_edges.items())
    cinfo = information(params.closure_sigmas)
    lower = np.array([k[1] < robot for k, _ in edges], dtype=bool)
    meas = np.array([v[0] for _, v in edges]).reshape(-1, 4, 4)
    # robust votes of correlated closures (core.robust.correlated_votes), in the infos;
    # one call over intra and inter closures: votes are counted per robot pair, so they don't mix
    own = np.array([k[0] for k, _ in edges], dtype=int)
    peer = np.array([k[1] for k, _ in edges], dtype=int)
    c = ~odo
    nc = int(c.sum())
    votes = np.ones(nc + len(edges))
    if params.closure_votes:
        votes = correlated_votes(np.full(len(votes), robot), np.r_[i[c], own],
                                 np.r_[np.full(nc, robot), peer],
                                 np.r_[j[c], np.array([k[2] for k, _ in edges], dtype=int)])
    intra_vote = np.ones(len(i))
    intra_vote[c] = votes[:nc]
    inter_vote = votes[nc:]
    return LocalGraph(
        robot=robot,
        keys=np.array([robot_key(robot, k) for k in range(len(poses))], dtype=np.int64),
        poses=np.array(poses),
        intra_i=i, intra_j=j, intra_meas=Z, intra_info=info * intra_vote[:, None, None], intra_odometry=odo,
        intra_edge=np.arange(len(i)),
        inter_own=own,
        inter_own_is_i=~lower,
        inter_peer=peer,
        inter_peer_key=np.array([robot_key(k[1], k[2]) for k, _ in edges], dtype=np.int64),
        inter_meas=np.where(lower[:, None, None], inverse(meas), meas),
        inter_info=np.tile(cinfo, (len(edges), 1, 1)) * inter_vote[:, None, None],
        inter_edge=np.arange(len(edges)),
        robot_graph=sorted(robot_graph), team=team or (robot,),
        intra_vote=intra_vote, inter_vote=inter_vote,
    )
