"""A multi-robot SE(3) pose graph as flat numpy arrays (what the readers return).

Poses are indexed ``0..n-1``; ``robot[k]`` owns pose ``k`` and ``local[k]`` is its index in
that robot's own sequence, so its gtsam key is ``Symbol(chr(ord('a') + robot), local)``
(docs/architecture.md). Information matrices are in gtsam's tangent order ``[rotation, translation]``.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from kimera_multi_py.core.errors import GraphError
from kimera_multi_py.core.geometry import inverse
from kimera_multi_py.core.ids import MAX_AGENT_ID, MAX_ROBOTS

log = logging.getLogger(__name__)

ODOMETRY = 0
LOOP_CLOSURE = 1
INTER_ROBOT = 2


def robot_key(robot: int, index: int) -> int:
    """gtsam ``Symbol(chr(ord('a') + robot), index)`` as an integer key."""
    if not 0 <= robot <= MAX_AGENT_ID:
        raise GraphError(f"robot id {robot} outside 0..{MAX_AGENT_ID} (one Symbol letter per robot)")
    return ((ord("a") + robot) << 56) | int(index)


def split_key(key: int) -> tuple[int, int]:
    """Inverse of :func:`robot_key`: ``(robot, index)``."""
    key = int(key)
    return (key >> 56) - ord("a"), key & ((1 << 56) - 1)


@dataclass
class PoseGraph:
    """Poses, owners and relative measurements ``T_i^{-1} T_j ≈ measurement``."""

    poses: np.ndarray  # (n, 4, 4) initial values
    robot: np.ndarray  # (n,) int robot id
    local: np.ndarray  # (n,) int index within the robot's sequence (0..n_r-1, in order)
    ids: np.ndarray  # (n,) int64 id of the pose in the source file
    edge_i: np.ndarray  # (m,) int pose index
    edge_j: np.ndarray  # (m,) int pose index
    measurement: np.ndarray  # (m, 4, 4)
    information: np.ndarray  # (m, 6, 6) [rot, trans]
    source: str = ""
    outlier: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))  # (m,) injected
    planar: bool = False  # read from a 2-D (SE(2)) file: outputs are 2-D too (see io/planar.py)

    def __post_init__(self) -> None:
        m = len(self.edge_i)
        if len(self.outlier) != m:
            self.outlier = np.zeros(m, dtype=bool)
        self.validate()

    # structure
    @property
    def num_poses(self) -> int:
        return len(self.poses)

    @property
    def num_edges(self) -> int:
        return len(self.edge_i)

    @property
    def num_robots(self) -> int:
        return int(self.robot.max()) + 1 if len(self.robot) else 0

    @property
    def keys(self) -> np.ndarray:
        """gtsam Symbol keys of every pose, ``(n,)`` int64-safe Python ints in an object array."""
        pairs = zip(self.robot, self.local, strict=True)
        return np.array([robot_key(int(r), int(k)) for r, k in pairs], dtype=object)

    def edge_kind(self) -> np.ndarray:
        """``(m,)`` ODOMETRY (same robot, consecutive), LOOP_CLOSURE or INTER_ROBOT."""
        ri, rj = self.robot[self.edge_i], self.robot[self.edge_j]
        consecutive = np.abs(self.local[self.edge_i] - self.local[self.edge_j]) == 1
        kind = np.full(self.num_edges, LOOP_CLOSURE, dtype=int)
        kind[(ri == rj) & consecutive] = ODOMETRY
        kind[ri != rj] = INTER_ROBOT
        return kind

    def robot_indices(self, robot: int) -> np.ndarray:
        """Pose indices owned by ``robot``, in local order."""
        idx = np.flatnonzero(self.robot == robot)
        return idx[np.argsort(self.local[idx], kind="stable")]

    def validate(self) -> None:
        """Raise :class:`GraphError` on inconsistent arrays."""
        n, m = len(self.poses), len(self.edge_i)
        if self.poses.shape != (n, 4, 4) or len(self.robot) != n or len(self.local) != n:
            raise GraphError("pose arrays disagree in length")
        if len(self.edge_j) != m or self.measurement.shape != (m, 4, 4):
            raise GraphError("edge arrays disagree in length")
        if self.information.shape != (m, 6, 6):
            raise GraphError("information must be (m, 6, 6)")
        if m and (self.edge_i.min() < 0 or max(self.edge_i.max(), self.edge_j.max()) >= n):
            raise GraphError("edge refers to an unknown pose index")
        if not (np.all(np.isfinite(self.poses)) and np.all(np.isfinite(self.measurement))):
            raise GraphError("non-finite pose or measurement")

    def with_robots(self, robot: np.ndarray) -> PoseGraph:
        """Same graph with pose ownership reassigned (local indices recomputed in id order)."""
        robot = np.asarray(robot, dtype=int)
        local = np.zeros(len(robot), dtype=int)
        for r in np.unique(robot):
            idx = np.flatnonzero(robot == r)
            idx = idx[np.argsort(self.ids[idx], kind="stable")]
            local[idx] = np.arange(len(idx))
        return replace(self, robot=robot, local=local)

    def subset_edges(self, mask: np.ndarray) -> PoseGraph:
        """Same poses, only the edges in ``mask``."""
        return replace(
            self,
            edge_i=self.edge_i[mask],
            edge_j=self.edge_j[mask],
            measurement=self.measurement[mask],
            information=self.information[mask],
            outlier=self.outlier[mask],
        )


def split_contiguous(graph: PoseGraph, num_robots: int) -> PoseGraph:
    """Give each of ``num_robots`` robots one contiguous block of poses (in id order).

    Edges between blocks become inter-robot measurements, as in the DPGO benchmarks.
    """
    n = graph.num_poses
    if num_robots < 1 or num_robots > min(n, MAX_ROBOTS):
        raise GraphError(f"cannot split {n} poses among {num_robots} robots (1..{min(n, MAX_ROBOTS)})")
    order = np.argsort(graph.ids, kind="stable")
    robot = np.empty(n, dtype=int)
    robot[order] = (np.arange(n) * num_robots) // n
    return graph.with_robots(robot)


def merge_graphs(graphs: list[PoseGraph]) -> PoseGraph:
    """Concatenate graphs with disjoint ``(robot, local)`` poses (no cross edges added)."""
    if not graphs:
        raise GraphError("nothing to merge")
    offsets = np.cumsum([0] + [g.num_poses for g in graphs])
    merged = PoseGraph(
        poses=np.concatenate([g.poses for g in graphs]),
        robot=np.concatenate([g.robot for g in graphs]),
        local=np.concatenate([g.local for g in graphs]),
        ids=np.concatenate([g.ids for g in graphs]),
        edge_i=np.concatenate([g.edge_i + o for g, o in zip(graphs, offsets, strict=False)]),
        edge_j=np.concatenate([g.edge_j + o for g, o in zip(graphs, offsets, strict=False)]),
        measurement=np.concatenate([g.measurement for g in graphs]),
        information=np.concatenate([g.information for g in graphs]),
        source="+".join(g.source for g in graphs),
        outlier=np.concatenate([g.outlier for g in graphs]),
        planar=all(g.planar for g in graphs),
    )
    pairs = set(zip(merged.robot.tolist(), merged.local.tolist(), strict=False))
    if len(pairs) != merged.num_poses:
        raise GraphError("merged graphs share pose keys")
    return merged


def chain_odometry(where: str, robot: np.ndarray, edge_i: np.ndarray, edge_j: np.ndarray,
                   meas: np.ndarray) -> np.ndarray:
    """Initial poses for files without any (DPGO CSV, TORO edge lists), per robot from its
    first pose: compose odometry (consecutive poses) first, then reach any pose the chain
    misses through the robot's other measurements (breadth first). Pose indices of a robot
    must be consecutive and in local order."""
    n = len(robot)
    poses = np.tile(np.eye(4), (n, 1, 1))
    adj: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(n)]
    step: dict[int, np.ndarray] = {}  # pose index k -> T_{k-1, k}
    for e in np.flatnonzero(robot[edge_i] == robot[edge_j]):
        a, b = int(edge_i[e]), int(edge_j[e])
        adj[a].append((b, meas[e]))
        adj[b].append((a, inverse(meas[e])))
        if b == a + 1:
            step.setdefault(b, meas[e])
        elif a == b + 1:
            step.setdefault(a, inverse(meas[e]))
    seen = np.zeros(n, dtype=bool)
    for r in np.unique(robot):
        idx = np.flatnonzero(robot == r)  # consecutive, in local order
        seen[idx[0]] = True
        for k in idx[1:]:
            if k in step and seen[k - 1]:
                poses[k] = poses[k - 1] @ step[k]
                seen[k] = True
        if not seen[idx].all():
            log.warning("%s: robot %d odometry chain is broken; bridging it", where, r)
        queue = deque(int(k) for k in idx if seen[k])
        while queue:
            a = queue.popleft()
            for b, T in adj[a]:
                if not seen[b]:
                    seen[b] = True
                    poses[b] = poses[a] @ T
                    queue.append(b)
        if not seen[idx].all():
            log.warning("%s: robot %d is split into disconnected pieces", where, r)
    return poses


def pair_index(a: np.ndarray, b: np.ndarray, table_a: np.ndarray, table_b: np.ndarray) -> np.ndarray:
    """For each key pair ``(a[i], b[i])``, the index ``j`` of the same pair ``(table_a[j],
    table_b[j])`` in a table, or -1: one sort and one binary search, no loop over pairs."""
    def pairs(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        xy = np.stack([np.asarray(x, dtype=np.int64).ravel(), np.asarray(y, dtype=np.int64).ravel()], axis=1)
        return np.ascontiguousarray(xy).view([("a", "<i8"), ("b", "<i8")]).ravel()

    query, table = pairs(a, b), pairs(table_a, table_b)
    if len(table) == 0 or len(query) == 0:
        return np.full(len(query), -1, dtype=np.int64)
    order = np.argsort(table, kind="stable")
    pos = np.minimum(np.searchsorted(table[order], query), len(table) - 1)
    return np.where(table[order][pos] == query, order[pos], -1).astype(np.int64)
