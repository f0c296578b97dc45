"""Initialisation of one distributed-PGO robot (a mixin of :class:`.agent.PgoAgent`, whose state
it reads and writes; docs/algorithms/pgo.md).

A robot starts from its own odometry (or its local chordal solution) in its own frame.
Optionally (``distributed_init``) the team first runs block Gauss–Seidel on the chordal
relaxation (:mod:`.chordal`) until every robot has settled; the leader then sends ``start``.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.pgo import PgoCommand, PgoStatus
from kimera_multi_py.pgo.centralised import chordal_initialization
from kimera_multi_py.pgo.chordal import chordal_block, chordal_poses
from kimera_multi_py.pgo.factors import to_values

if TYPE_CHECKING:
    from kimera_multi_py.pgo.local_graph import LocalGraph
    from kimera_multi_py.pgo.params import PgoParams

log = logging.getLogger(__name__)


class Initialisation:
    """The initialisation part of :class:`.agent.PgoAgent`: own start, team chordal relaxation."""

    # state of the agent (set by PgoAgent.__init__)
    local: LocalGraph
    params: PgoParams
    robot: int
    team: tuple[int, ...]
    root: bool
    stage: str
    solve_round: int
    start_sent: int | None
    poses: np.ndarray
    prev_poses: np.ndarray
    published: np.ndarray
    aligned: bool
    neighbour_poses: dict[int, np.ndarray]
    inter_weights: np.ndarray
    intra_weights: np.ndarray
    kappa_intra: np.ndarray
    tau_intra: np.ndarray
    kappa_inter: np.ndarray
    tau_inter: np.ndarray
    statuses: dict[int, PgoStatus]
    ready: bool
    rel_change: float
    updates: int
    updates_since_weights: int
    gamma: float
    last_team_cost: float
    _values: gtsam.Values

    if TYPE_CHECKING:
        def handle(self, msg: Message) -> None: ...

    # ---------------------------------------------------------------- own start
    def _initial_poses(self) -> np.ndarray:
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
    def _init_update(self) -> None:
        """One block of the chordal relaxation: own rotations then translations, neighbours'
        public poses fixed (block Gauss–Seidel on a linear problem: fast and monotone)."""
        lg = self.local
        n = len(lg.keys)
        wi = self.intra_weights > 0
        ei, ej = [lg.intra_i[wi]], [lg.intra_j[wi]]
        meas, kappa, tau = [lg.intra_meas[wi]], [self.kappa_intra[wi]], [self.tau_intra[wi]]
        fixed: list[np.ndarray] = []
        for e in range(len(lg.inter_edge)):
            nb = self.neighbour_poses.get(int(lg.inter_peer_key[e]))
            if nb is None or self.inter_weights[e] <= 0:
                continue
            f = n + len(fixed)
            fixed.append(nb)
            own = int(lg.inter_own[e])
            ei.append(np.array([own if lg.inter_own_is_i[e] else f]))
            ej.append(np.array([f if lg.inter_own_is_i[e] else own]))
            meas.append(lg.inter_meas[e][None])
            kappa.append(self.kappa_inter[e:e + 1])
            tau.append(self.tau_inter[e:e + 1])
        if self.root or not fixed:
            # the team frame (or a lone robot's own frame): hold the first pose
            big = 1e6 * max(float(np.concatenate(kappa + [np.ones(1)]).max()), 1.0)
            fixed.append(self.poses[0])
            ei.append(np.array([n + len(fixed) - 1]))
            ej.append(np.array([0]))
            meas.append(np.eye(4)[None])
            kappa.append(np.array([big]))
            tau.append(np.array([big]))
        new = chordal_block(n, np.concatenate(ei), np.concatenate(ej), np.concatenate(meas),
                            np.concatenate(kappa), np.concatenate(tau), np.stack(fixed),
                            self.poses)
        change = np.sqrt(np.sum((new - self.poses) ** 2) / max(np.sum(self.poses**2), 1e-300))
        self.rel_change = float(change)
        self.ready = self.rel_change < self.params.init_rel_tol
        self.poses = new
        self.updates += 1

    def _start_solve(self, rnd: int) -> None:
        """Leave the initialisation: the BCD starts from the relaxation's poses."""
        self.stage = "solve"
        self.solve_round = rnd
        self.prev_poses = self.poses.copy()
        self.published = self.poses.copy()
        self._values = to_values(self.local.keys, self.poses)
        self.ready = False
        self.rel_change = np.inf
        self.updates = 0
        self.updates_since_weights = 0
        self.gamma = 1.0
        self.last_team_cost = np.inf

    # ---------------------------------------------------------------- leader
    def _lead_init(self, rnd: int) -> list[Message]:
        """Start the BCD when every robot's relaxation has settled (or at the round cap); the
        command is repeated for a few rounds so a lost copy does not strand a robot."""
        p = self.params
        if self.start_sent is None:
            statuses = [self.statuses.get(r) for r in self.team if r != self.robot]
            settled = (self.ready and self.aligned
                       and all(s is not None and s.ready for s in statuses))
            if not settled and rnd < p.init_max_rounds:
                return []
            self.start_sent = rnd
        if rnd - self.start_sent >= p.start_resend:
            return []
        cmd = PgoCommand(robot=self.robot, round=self.start_sent + 1, command="start",
                         active=np.array(self.team, dtype=np.int64))
        self.handle(cmd)
        return [cmd]
