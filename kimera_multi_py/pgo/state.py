"""What the parts of one distributed-PGO robot share: its estimate, the weights of its edges and
what it heard of its neighbours (docs/algorithms/pgo.md).

:class:`~.agent.PgoAgent` owns one :class:`SolveState` and hands it to its parts. The agent's
step moves the estimate; the frame decision (:mod:`.frame_decision`) moves it into the team
frame and starts the inter-robot edges it does not rest on at weight 0; the robust weights
(:mod:`.weights`, :mod:`.gn_weights`) set the weights of loop closures and inter-robot edges.
Neighbours' public poses and whether their frames are settled arrive in messages
(:meth:`.agent.PgoAgent.handle`). Nothing else is shared: every other piece of state belongs to
exactly one part.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np

from kimera_multi_py.pgo.factors import to_values
from kimera_multi_py.pgo.local_graph import LocalGraph


@dataclass
class SolveState:
    """One robot's estimate and edge weights (see the module docstring)."""

    keys: np.ndarray  # the robot's pose keys (:attr:`LocalGraph.keys`)
    poses: np.ndarray  # (n, 4, 4) the current iterate
    prev_poses: np.ndarray  # the previous iterate (momentum)
    published: np.ndarray  # what neighbours see (extrapolated)
    values: gtsam.Values  # the current iterate as gtsam values (the local solve's warm start)
    inter_weights: np.ndarray  # per inter-robot edge of the local graph
    intra_weights: np.ndarray  # per intra-robot edge (odometry stays 1)
    neighbour_poses: dict[int, np.ndarray] = field(default_factory=dict)  # pose key -> latest public pose
    peer_settled: dict[int, bool] = field(default_factory=dict)  # robot -> its frame is settled, as last heard
    barred: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))  # inter edges the maps refuted

    def bar(self, edges: np.ndarray) -> bool:
        """Hold inter-robot ``edges`` (a mask) at weight 0 for the rest of the epoch: they belong
        to a frame hypothesis the maps refute. Returns whether any edge is newly barred."""
        if len(self.barred) != len(self.inter_weights):
            self.barred = np.zeros(len(self.inter_weights), dtype=bool)
        new = bool(np.any(edges & ~self.barred))
        self.barred |= edges
        self.hold_bars()
        return new

    def hold_bars(self) -> None:
        """Put the barred edges back to weight 0 (after any part wrote the weights)."""
        if len(self.barred) == len(self.inter_weights) and self.barred.any():
            self.inter_weights[self.barred] = 0.0

    @classmethod
    def start(cls, local: LocalGraph, poses: np.ndarray) -> SolveState:
        """The state of a robot starting from ``poses``, every edge at weight 1, nothing heard."""
        return cls(local.keys, poses, poses.copy(), poses.copy(), to_values(local.keys, poses),
                   np.ones(len(local.inter_edge)), np.ones(len(local.intra_edge)))

    def restart_from(self, poses: np.ndarray) -> None:
        """Make ``poses`` the iterate and restart from it (no momentum, neighbours see it as is)."""
        self.poses = poses
        self.prev_poses = poses.copy()
        self.published = poses.copy()
        self.values = to_values(self.keys, poses)
