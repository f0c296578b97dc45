"""Initialisation of one distributed-PGO robot (docs/algorithms/pgo.md).

A robot starts from its own odometry (or its local chordal solution) in its own frame.
Optionally (``distributed_init``) the team first runs block Gauss–Seidel on the chordal
relaxation (:mod:`.chordal`) until every robot has settled; the leader then sends ``start``.
"""

from __future__ import annotations

import logging

import numpy as np

from kimera_multi_py.comms.messages.pgo import PgoStatus
from kimera_multi_py.pgo.centralised import chordal_initialization
from kimera_multi_py.pgo.chordal import chordal_block, chordal_poses, edge_weights
from kimera_multi_py.pgo.local_graph import LocalGraph
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.pgo.state import SolveState

log = logging.getLogger(__name__)


class Initialisation:
    """The initialisation part of :class:`.agent.PgoAgent`: own start, team chordal relaxation,
    and the leader's ``start`` of the solve."""

    def __init__(self, local: LocalGraph, params: PgoParams) -> None:
        self.local = local
        self.params = params
        self.robot = local.robot
        # the chordal relaxation's rotation and translation weights of every edge
        self.kappa_intra, self.tau_intra = edge_weights(local.intra_info)
        self.kappa_inter, self.tau_inter = edge_weights(local.inter_info)
        self.start_sent: int | None = None  # leader: the round it decided to start the solve

    # ---------------------------------------------------------------- own start
    def initial_poses(self) -> np.ndarray:
        """Own odometry/initial values, or the chordal relaxation of the own block (anchored
        at the first pose; components no edge reaches keep their given values).

        The rule is the centralised reference's: where gtsam's ``InitializePose3`` finds the
        block's system indeterminate (cubicle's degenerate information matrices), the given
        values are kept. Measured there: the chordal start puts the BCD in a slow valley
        (1.1e-2 above the optimum after 1000 rounds), the given values converge geometrically.
        """
        lg = self.local
        poses = lg.poses.copy()
        if not self.params.chordal_init or not len(lg.intra_i):
            return poses
        _, ok = chordal_initialization(lg.subgraph(), poses)
        if not ok:
            log.info("robot %d: chordal initialisation indeterminate; keeping given values",
                     self.robot)
            return poses
        try:
            return chordal_poses(poses, lg.intra_i, lg.intra_j, lg.intra_meas, lg.intra_info)
        except (RuntimeError, np.linalg.LinAlgError) as exc:
            log.warning("robot %d: chordal initialisation failed (%s)", self.robot, exc)
            return poses

    # ---------------------------------------------------------------- distributed init
    def update(self, state: SolveState, root: bool) -> np.ndarray:
        """One block of the chordal relaxation: own rotations then translations, neighbours'
        public poses fixed (block Gauss–Seidel on a linear problem: fast and monotone). Returns
        the new poses; ``root``: the robot holds the team frame."""
        lg = self.local
        n = len(lg.keys)
        wi = state.intra_weights > 0
        ei, ej = [lg.intra_i[wi]], [lg.intra_j[wi]]
        meas, kappa, tau = [lg.intra_meas[wi]], [self.kappa_intra[wi]], [self.tau_intra[wi]]
        fixed: list[np.ndarray] = []
        for e in range(len(lg.inter_edge)):
            nb = state.neighbour_poses.get(int(lg.inter_peer_key[e]))
            if nb is None or state.inter_weights[e] <= 0:
                continue
            f = n + len(fixed)
            fixed.append(nb)
            own = int(lg.inter_own[e])
            ei.append(np.array([own if lg.inter_own_is_i[e] else f]))
            ej.append(np.array([f if lg.inter_own_is_i[e] else own]))
            meas.append(lg.inter_meas[e][None])
            kappa.append(self.kappa_inter[e:e + 1])
            tau.append(self.tau_inter[e:e + 1])
        if root or not fixed:
            # the team frame (or a lone robot's own frame): hold the first pose
            big = 1e6 * max(float(np.concatenate(kappa + [np.ones(1)]).max()), 1.0)
            fixed.append(state.poses[0])
            ei.append(np.array([n + len(fixed) - 1]))
            ej.append(np.array([0]))
            meas.append(np.eye(4)[None])
            kappa.append(np.array([big]))
            tau.append(np.array([big]))
        return chordal_block(n, np.concatenate(ei), np.concatenate(ej), np.concatenate(meas),
                             np.concatenate(kappa), np.concatenate(tau), np.stack(fixed),
                             state.poses)

    # ---------------------------------------------------------------- leader
    def lead(self, rnd: int, team: tuple[int, ...], ready: bool, statuses: dict[int, PgoStatus]) -> int | None:
        """Leader: the round at which the solve starts, to announce now, or None. The solve
        starts when every robot's relaxation has settled (``ready``: this robot's has, and it is
        aligned) or at the round cap; the command is repeated for a few rounds so a lost copy
        does not strand a robot."""
        p = self.params
        if self.start_sent is None:
            others = [statuses.get(r) for r in team if r != self.robot]
            settled = ready and all(s is not None and s.ready for s in others)
            if not settled and rnd < p.init_max_rounds:
                return None
            self.start_sent = rnd
        if rnd - self.start_sent >= p.start_resend:
            return None
        return self.start_sent + 1
