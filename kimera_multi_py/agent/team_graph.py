"""The team's joint pose graph, assembled from per-robot agents (export and evaluation).

Inter-robot edges are taken from their verifier (the lower robot id), so each appears once.
Poses are the agents' current estimates; robots not yet aligned remain in their own frames.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.core.posegraph import PoseGraph, robot_key


def joint_graph(agents: Sequence[Agent]) -> tuple[PoseGraph, list[tuple[int, int, int, int]]]:
    """``(graph, inter)``: the joint graph and, per inter-robot edge in order, ``(a, kf_a, b, kf_b)``."""
    offsets = np.cumsum([0] + [a.num_keyframes for a in agents])
    poses, robot, local, ei, ej, Z, info = [], [], [], [], [], [], []
    inter: list[tuple[int, int, int, int]] = []
    for a, off in zip(agents, offsets, strict=False):
        poses += a.poses
        robot += [a.robot] * a.num_keyframes
        local += list(range(a.num_keyframes))
        i, j, meas, inf, _ = a.intra_edges()
        ei += list(i + off)
        ej += list(j + off)
        Z += list(meas)
        info += list(inf)
    cinfo = np.diag(np.repeat(1.0 / np.square(agents[0].params.closure_sigmas), 3)) if agents else np.eye(6)
    for a, off in zip(agents, offsets, strict=False):
        for (own_kf, peer, peer_kf), (meas, _) in sorted(a.inter_edges.items()):
            if peer <= a.robot:
                continue
            ei.append(off + own_kf)
            ej.append(offsets[peer] + peer_kf)
            Z.append(meas)
            info.append(cinfo)
            inter.append((a.robot, own_kf, peer, peer_kf))
    graph = PoseGraph(
        poses=np.array(poses).reshape(-1, 4, 4), robot=np.array(robot, dtype=int), local=np.array(local, dtype=int),
        ids=np.array([robot_key(r, k) for r, k in zip(robot, local, strict=True)], dtype=np.int64),
        edge_i=np.array(ei, dtype=int), edge_j=np.array(ej, dtype=int),
        measurement=np.array(Z).reshape(-1, 4, 4), information=np.array(info).reshape(-1, 6, 6), source="team",
    )
    return graph, inter
