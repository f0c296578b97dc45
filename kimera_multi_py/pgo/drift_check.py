"""The drift check at the end of an epoch (docs/algorithms/pgo.md, "Drift check").

An estimate that bends away from the robot's own dead reckoning beyond its drift model
(:func:`.alignment.odometry_disagreement`) is not adopted: the robot keeps its own graph solved
alone, or its dead reckoning when its own loop closures bend it away too. The dead reckoning is
chained from the local graph's odometry edges, and their information gives the drift model.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from kimera_multi_py.alignment.frames import odometry_disagreement
from kimera_multi_py.core.geometry import inverse
from kimera_multi_py.pgo.local_graph import LocalGraph
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.pgo.state import SolveState


def odometry_chain(local: LocalGraph) -> tuple[np.ndarray, float, float]:
    """Dead reckoning from the odometry edges (first pose at the identity) and its sigmas
    (rotation, translation per step)."""
    lg = local
    n = len(lg.keys)
    D = np.tile(np.eye(4), (n, 1, 1))
    odo = np.flatnonzero(lg.intra_odometry)
    steps = {int(lg.intra_i[e]): e for e in odo if int(lg.intra_j[e]) == int(lg.intra_i[e]) + 1}
    for k in range(1, n):
        e = steps.get(k - 1)
        D[k] = D[k - 1] @ (lg.intra_meas[e] if e is not None else inverse(lg.poses[k - 1]) @ lg.poses[k])
    if len(odo):
        info = lg.intra_info[odo[0]]
        return D, float(1.0 / np.sqrt(info[0, 0])), float(1.0 / np.sqrt(info[3, 3]))
    return D, 0.0, 0.0


def odometry_ratio(local: LocalGraph, poses: np.ndarray, params: PgoParams) -> float:
    """How far ``poses`` bend away from the robot's dead reckoning, in units of its drift model
    (above 1: beyond what drift explains)."""
    D, s_rot, s_trans = odometry_chain(local)
    return odometry_disagreement(poses, D, s_rot, s_trans, params.drift_z, params.drift_floor)


def own_solution(local: LocalGraph, state: SolveState, params: PgoParams,
                 solve_alone: Callable[[], np.ndarray]) -> np.ndarray:
    """The robot's own graph alone (odometry and the intra-robot closures GNC kept, solved by
    ``solve_alone``), or its dead reckoning when its own closures bend it away from the
    odometry too (their weights then go to 0)."""
    own = solve_alone()
    if odometry_ratio(local, own, params) > 1.0:
        state.intra_weights[~local.intra_odometry] = 0.0  # its own closures bend it too: dead reckoning
        D, _, _ = odometry_chain(local)
        return state.poses[0] @ D
    return own
