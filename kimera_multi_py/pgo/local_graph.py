"""A robot's share of the team's pose graph, and the robot graph's colouring and roots (docs/algorithms/pgo.md)."""

from __future__ import annotations

from dataclasses import dataclass, field

import networkx as nx
import numpy as np

from kimera_multi_py.core.geometry import inverse
from kimera_multi_py.core.posegraph import INTER_ROBOT, ODOMETRY, PoseGraph, robot_key


@dataclass
class LocalGraph:
    """What robot ``robot`` knows: its poses, its own edges, and its inter-robot edges."""

    robot: int
    keys: np.ndarray  # (n,) own Symbol keys, local order
    poses: np.ndarray  # (n, 4, 4) initial values in the robot's own frame
    intra_i: np.ndarray
    intra_j: np.ndarray
    intra_meas: np.ndarray
    intra_info: np.ndarray
    intra_odometry: np.ndarray  # (m,) bool
    intra_edge: np.ndarray  # (m,) global edge index (for bookkeeping only)
    inter_own: np.ndarray  # (k,) own local index
    inter_own_is_i: np.ndarray  # (k,) bool
    inter_peer: np.ndarray  # (k,) neighbour robot id
    inter_peer_key: np.ndarray  # (k,) int64 neighbour Symbol key
    inter_meas: np.ndarray
    inter_info: np.ndarray
    inter_edge: np.ndarray  # (k,) global edge index
    robot_graph: list[tuple[int, int]] = field(default_factory=list)  # team topology
    team: tuple[int, ...] = ()
    # robust votes (:func:`kimera_multi_py.core.robust.correlated_votes`; the infos above already carry them, the TLS
    # decisions divide the squared residuals by them); None: 1 for every edge
    intra_vote: np.ndarray | None = None
    inter_vote: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.intra_vote is None:
            self.intra_vote = np.ones(len(self.intra_i))
        if self.inter_vote is None:
            self.inter_vote = np.ones(len(self.inter_own))

    @property
    def neighbours(self) -> list[int]:
        return sorted(set(self.inter_peer.tolist()))

    @property
    def public(self) -> np.ndarray:
        """Own local indices touching inter-robot edges."""
        return np.unique(self.inter_own)

    def subgraph(self) -> PoseGraph:
        """The intra-robot part as a :class:`PoseGraph` (for chordal initialisation)."""
        n = len(self.keys)
        return PoseGraph(poses=self.poses, robot=np.full(n, self.robot), local=np.arange(n),
                         ids=np.asarray(self.keys, dtype=np.int64), edge_i=self.intra_i,
                         edge_j=self.intra_j, measurement=self.intra_meas,
                         information=self.intra_info)


def split_local(graph: PoseGraph, frames: str = "own", votes: np.ndarray | None = None) -> list[LocalGraph]:
    """Each robot's :class:`LocalGraph`; ``frames="own"`` re-expresses a robot's initial values
    relative to its first pose (robots do not share a frame), ``"given"`` keeps them.
    ``votes``: robust votes per edge (already in ``graph``'s information), as the agents'."""
    vote = np.ones(graph.num_edges) if votes is None else np.asarray(votes, dtype=float)
    kind = graph.edge_kind()
    inter_edges = kind == INTER_ROBOT
    ra, rb = graph.robot[graph.edge_i[inter_edges]], graph.robot[graph.edge_j[inter_edges]]
    pairs = sorted({(int(min(a, b)), int(max(a, b))) for a, b in zip(ra, rb, strict=True)})
    team = tuple(range(graph.num_robots))
    out = []
    for r in team:
        own = graph.robot_indices(r)
        pos = np.full(graph.num_poses, -1)
        pos[own] = np.arange(len(own))
        poses = graph.poses[own]
        if frames == "own" and len(own):
            poses = inverse(poses[0]) @ poses
        ei, ej = graph.edge_i, graph.edge_j
        intra = np.flatnonzero((pos[ei] >= 0) & (pos[ej] >= 0))
        inter = np.flatnonzero((pos[ei] >= 0) ^ (pos[ej] >= 0))
        own_is_i = pos[ei[inter]] >= 0
        peer_idx = np.where(own_is_i, ej[inter], ei[inter])
        out.append(LocalGraph(
            robot=r,
            keys=np.array([robot_key(r, k) for k in range(len(own))], dtype=np.int64),
            poses=poses,
            intra_i=pos[ei[intra]], intra_j=pos[ej[intra]],
            intra_meas=graph.measurement[intra], intra_info=graph.information[intra],
            intra_odometry=kind[intra] == ODOMETRY, intra_edge=intra,
            inter_own=np.where(own_is_i, pos[ei[inter]], pos[ej[inter]]),
            inter_own_is_i=own_is_i,
            inter_peer=graph.robot[peer_idx],
            inter_peer_key=np.array([robot_key(int(graph.robot[p]), int(graph.local[p]))
                                     for p in peer_idx], dtype=np.int64),
            inter_meas=graph.measurement[inter], inter_info=graph.information[inter],
            inter_edge=inter, robot_graph=pairs, team=team, intra_vote=vote[intra], inter_vote=vote[inter],
        ))
    return out


def colour_robots(robots: tuple[int, ...], pairs: list[tuple[int, int]]) -> dict[int, int]:
    """Deterministic greedy colouring: adjacent robots get different colours."""
    g = nx.Graph()
    g.add_nodes_from(robots)
    g.add_edges_from(pairs)
    colour: dict[int, int] = {}
    for r in sorted(robots, key=lambda r: (-g.degree[r], r)):
        used = {colour[n] for n in g.neighbors(r) if n in colour}
        colour[r] = next(c for c in range(len(robots) + 1) if c not in used)
    return colour


def component_root(robot: int, robots: tuple[int, ...], pairs: list[tuple[int, int]]) -> int:
    """The lowest id of ``robot``'s connected component of the robot graph: its frame's root."""
    g = nx.Graph()
    g.add_nodes_from(robots)
    g.add_node(robot)
    g.add_edges_from(pairs)
    return int(min(nx.node_connected_component(g, robot)))


def frame_root(robot: int, robots: tuple[int, ...], pairs: list[tuple[int, int]]) -> bool:
    """True when ``robot`` is the lowest id of its connected component of the robot graph."""
    return robot == component_root(robot, robots, pairs)
