"""Poses over time and the TF tree: ``/tf`` and ``/tf_static`` as chains of frames (docs/bags.md).

A :class:`PoseSeries` is one stamped transform stream (an odometry topic, or one edge of
``/tf``) interpolated at any stamp: translation linearly, rotation by slerp. It extrapolates by
at most the sync tolerance. :class:`TfTree` composes the edges on the path between two frames;
a missing edge is a gap, named with the frames the tree does have.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import networkx as nx
import numpy as np
from scipy.spatial.transform import Rotation, Slerp


class TfGap(ValueError):
    """No transform between two frames (or not at the stamps asked for)."""


def msg_pose(position: Any, orientation: Any) -> np.ndarray:
    """A 4x4 pose from a geometry_msgs position/translation and quaternion."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([orientation.x, orientation.y, orientation.z, orientation.w]).as_matrix()
    T[:3, 3] = [position.x, position.y, position.z]
    return T


def pose7(v: list[float]) -> np.ndarray:
    """A 4x4 pose from ``[x, y, z, qx, qy, qz, qw]``."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(v[3:]).as_matrix()
    T[:3, 3] = v[:3]
    return T


class PoseSeries:
    """Stamped poses ``(n,)``, ``(n, 4, 4)``, interpolated at other stamps."""

    def __init__(self, stamps: np.ndarray, poses: np.ndarray) -> None:
        order = np.argsort(stamps, kind="stable")
        stamps, poses = np.asarray(stamps, dtype=np.float64)[order], np.asarray(poses, dtype=np.float64)[order]
        keep = np.concatenate([[True], np.diff(stamps) > 0])  # one pose per stamp
        self.stamps, self.poses = stamps[keep], poses[keep]
        self._slerp = Slerp(self.stamps, Rotation.from_matrix(self.poses[:, :3, :3])) if len(self.stamps) > 1 else None

    def __len__(self) -> int:
        return len(self.stamps)

    def covers(self, t: np.ndarray, tolerance: float) -> np.ndarray:
        return (t >= self.stamps[0] - tolerance) & (t <= self.stamps[-1] + tolerance)

    def at(self, t: np.ndarray, tolerance: float) -> np.ndarray:
        """``(m, 4, 4)`` poses at stamps ``t``; a stamp further than ``tolerance`` outside raises TfGap."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        if len(self.stamps) == 0 or not self.covers(t, tolerance).all():
            span = f"{self.stamps[0]:.3f}..{self.stamps[-1]:.3f} s" if len(self.stamps) else "no stamps"
            bad = t[~self.covers(t, tolerance)] if len(self.stamps) else t
            raise TfGap(f"no pose at {bad[0]:.3f} s (poses cover {span})")
        tc = np.clip(t, self.stamps[0], self.stamps[-1])
        out = np.tile(np.eye(4), (len(t), 1, 1))
        if self._slerp is None:
            out[:] = self.poses[0]
            return out
        out[:, :3, :3] = self._slerp(tc).as_matrix()
        for i in range(3):
            out[:, i, 3] = np.interp(tc, self.stamps, self.poses[:, i, 3])
        return out


class TfTree:
    """``/tf_static`` edges (fixed) and ``/tf`` edges (stamped), looked up along the frames' tree."""

    def __init__(self) -> None:
        self.static: dict[tuple[str, str], np.ndarray] = {}
        self._dynamic: dict[tuple[str, str], tuple[list[float], list[np.ndarray]]] = defaultdict(lambda: ([], []))
        self._series: dict[tuple[str, str], PoseSeries] = {}

    def add(self, msg: Any, static: bool) -> None:
        """Add every transform of a ``tf2_msgs/TFMessage``."""
        for tr in msg.transforms:
            edge = (tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/"))
            T = msg_pose(tr.transform.translation, tr.transform.rotation)
            if static:
                self.static[edge] = T
            else:
                stamps, poses = self._dynamic[edge]
                stamps.append((int(tr.header.stamp.sec) * 1_000_000_000 + int(tr.header.stamp.nanosec)) / 1e9)
                poses.append(T)
        self._series.clear()

    @property
    def edges(self) -> list[tuple[str, str]]:
        return sorted(set(self.static) | set(self._dynamic))

    def series(self, edge: tuple[str, str]) -> PoseSeries:
        if edge not in self._series:
            stamps, poses = self._dynamic[edge]
            self._series[edge] = PoseSeries(np.array(stamps), np.array(poses).reshape(-1, 4, 4))
        return self._series[edge]

    def covers(self, parent: str, child: str, t: np.ndarray, tolerance: float) -> np.ndarray:
        """Which stamps ``t`` every stamped edge between the two frames covers (all false without a chain)."""
        ok = np.isfinite(t)
        try:
            path = nx.shortest_path(nx.Graph(self.edges), parent.lstrip("/"), child.lstrip("/"))
        except (nx.NetworkXException, nx.NodeNotFound):
            return np.zeros(len(t), dtype=bool)
        for a, b in zip(path[:-1], path[1:], strict=True):
            edge = (a, b) if (a, b) in self.static or (a, b) in self._dynamic else (b, a)
            if edge not in self.static:
                ok &= self.series(edge).covers(t, tolerance)
        return ok

    def lookup(self, parent: str, child: str, t: np.ndarray, tolerance: float) -> np.ndarray:
        """``(m, 4, 4)`` T_parent_child at stamps ``t``; TfGap names the break in the chain."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        parent, child = parent.lstrip("/"), child.lstrip("/")
        out = np.tile(np.eye(4), (len(t), 1, 1))
        if parent == child:
            return out
        graph = nx.Graph(self.edges)
        if parent not in graph or child not in graph or not nx.has_path(graph, parent, child):
            reach = sorted(nx.node_connected_component(graph, parent)) if parent in graph else []
            have = ", ".join(f"{a}->{b}" for a, b in self.edges) or "none"
            raise TfGap(f"no chain {parent} -> {child}" + (f" ({parent} reaches {', '.join(reach)})" if reach else "")
                        + f"; edges: {have}")
        path = nx.shortest_path(graph, parent, child)
        for a, b in zip(path[:-1], path[1:], strict=True):
            forward = (a, b) in self.static or (a, b) in self._dynamic
            edge = (a, b) if forward else (b, a)
            if edge in self.static:
                T = np.broadcast_to(self.static[edge], (len(t), 4, 4))
            else:
                try:
                    T = self.series(edge).at(t, tolerance)
                except TfGap as exc:
                    raise TfGap(f"edge {edge[0]} -> {edge[1]}: {exc}") from None
            out = out @ (T if forward else np.linalg.inv(T))
        return out
