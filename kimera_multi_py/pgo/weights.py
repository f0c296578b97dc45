"""Robust weights of one distributed-PGO robot: team-wide GNC-TLS over its loop closures and
inter-robot edges (docs/algorithms/pgo.md).

Robust mode: GNC-TLS weights (:mod:`kimera_multi_py.core.robust`) on loop closures and
inter-robot edges (odometry is trusted). The lowest robot id is the leader: it sends
``update_weights`` when every robot is ready (or after a round cap) and ``stop`` when the team is
done. GNC runs with *one* ``μ`` for the team, as the centralised GNC does: at the first update
every robot publishes its ``μ₀`` (a :class:`GncWeights` to itself, no edges) and all apply the
smallest a few rounds later; with per-robot ``μ₀`` a robot whose residuals happen to be small
starts near-binary and locks in aliased closures (structured outliers from identical places,
which fit the least-squares solution). Inter-robot edges start screened only against random
outliers (an edge no other edge agrees with); every mutually consistent group, true or aliased,
is left to the joint GNC, since for one robot pair the aliased group can be as large as the true
one. After the GNC schedule, the edges are re-decided at the converged solution with the plain
TLS threshold (first with ``recheck_factor`` slack, since a dropped inlier is biased high while
it is left out). An inter-robot edge's weight is computed by its lower-id robot and shared in
:class:`GncWeights`.
"""

from __future__ import annotations

from typing import Literal

import gtsam
import numpy as np

from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.pgo import GncWeights
from kimera_multi_py.core.geometry import to_gtsam
from kimera_multi_py.core.posegraph import PoseGraph, pair_index
from kimera_multi_py.core.robust import GncSchedule, tls_threshold
from kimera_multi_py.pgo.factors import residuals_sq
from kimera_multi_py.pgo.local_graph import LocalGraph
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.pgo.state import SolveState


class RobustWeights:
    """The robust-weights part of :class:`.agent.PgoAgent`: GNC steps, rechecks, the leader's
    schedule. It sets the weights in the shared :class:`~.state.SolveState`."""

    def __init__(self, local: LocalGraph, params: PgoParams, state: SolveState) -> None:
        self.local = local
        self.params = params
        self.robot = local.robot
        self.state = state
        self.gnc = GncSchedule(tls_threshold(params.inlier_probability, params.tls_dof), mu_step=params.gnc_mu_step)
        self.pending: int | None = None  # round of a pending weight update
        self.last_round = 0  # round of the last weight update
        self.mu_proposals: dict[int, float] = {}  # robot -> proposed μ₀ (team-wide GNC)
        self.rechecks = 0
        self.sends = 0  # weight updates sent
        self.sent = np.full(len(local.inter_peer), np.nan)  # the weight last sent of each inter-robot edge

    # ---------------------------------------------------------------- messages in
    def order(self, rnd: int) -> None:
        """The leader ordered a weight update at round ``rnd`` (ignored unless newer)."""
        if rnd > self.last_round:
            self.pending = rnd

    def absorb(self, msg: GncWeights) -> None:
        """A ``μ₀`` proposal (to the sender itself), or the weights a peer decided for the
        inter-robot edges it owns with this robot."""
        if msg.peer == msg.robot:  # a μ₀ proposal, for the whole team
            self.mu_proposals[msg.robot] = float(msg.mu)
            return
        if msg.peer != self.robot:
            return
        j = pair_index(self.local.keys[self.local.inter_own], self.local.inter_peer_key, msg.keys_b, msg.keys_a)
        found = j >= 0
        self.state.inter_weights[found] = np.asarray(msg.weights, dtype=float)[j[found]]
        self.state.hold_bars()

    # ---------------------------------------------------------------- weight updates
    def update(self, rnd: int) -> tuple[list[Message], bool]:
        """The ordered weight update at round ``rnd``: the messages to send, and whether the
        weights changed (False while the team's ``μ₀`` is being agreed)."""
        p = self.params
        if p.gnc_team_mu and self.gnc.steps == 0 and self.robot not in self.mu_proposals:
            return self._propose_mu(rnd), False
        self.last_round = self.pending or rnd
        self.pending = None
        r2, trusted, loop, inter = self._robust_r2()
        if self.gnc.steps >= self.params.gnc_max_steps:
            # GNC is over: the TLS decision at the converged solution (μ → ∞) re-admits inliers
            # that the graduated schedule dropped while the estimate was still off
            # an inlier GNC dropped is biased high while it is left out: re-admit it with some
            # slack, re-converge, then apply the plain threshold at the joint solution
            last = self.rechecks + 1 >= self.params.gnc_rechecks
            factor = 1.0 if last else self.params.recheck_factor
            w = (r2 <= factor * self.gnc.barc2).astype(float)
            self.rechecks += 1
        else:
            mu0 = (min(self.mu_proposals.values()) if p.gnc_team_mu and self.mu_proposals
                   else self._initial_mu(r2, trusted))
            w = self.gnc.update(r2, mu0=mu0)
        self.state.intra_weights[loop] = w[: len(loop)]
        self.state.inter_weights[inter] = w[len(loop):]
        self.state.hold_bars()
        return self._weight_messages(rnd, inter), True

    def _weight_messages(self, rnd: int, inter: np.ndarray) -> list[Message]:
        """The weights of the owned edges ``inter`` for their peers: those that changed since they
        were last sent, every one at each ``weights_full_every``-th update; none unchanged."""
        lg = self.local
        w = self.state.inter_weights
        full = self.sends % max(self.params.weights_full_every, 1) == 0
        self.sends += 1
        changed = np.asarray(w[inter] != self.sent[inter])  # NaN: never sent
        self.sent[inter] = w[inter]
        out: list[Message] = []
        for peer in lg.neighbours:
            mine = lg.inter_peer[inter] == peer
            sel = inter[mine if full else mine & changed]
            if len(sel) == 0:
                continue
            out.append(GncWeights(robot=self.robot, peer=int(peer), round=rnd,
                                  keys_a=lg.keys[lg.inter_own[sel]],
                                  keys_b=lg.inter_peer_key[sel],
                                  weights=w[sel], mu=self.gnc.mu))
        return out

    def _robust_r2(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Squared residuals of the robust edges this robot decides (its loop closures and the
        inter-robot edges it owns, where the other end is known), and which are inliers now:
        ``(r2, trusted, loop edges, owned inter edges)``."""
        lg = self.local
        st = self.state
        loop = np.flatnonzero(~lg.intra_odometry)
        known = np.array([int(k) in st.neighbour_poses for k in lg.inter_peer_key], dtype=bool)
        inter = np.flatnonzero((lg.inter_peer > self.robot) & known)
        vote = np.concatenate([np.asarray(lg.intra_vote)[loop], np.asarray(lg.inter_vote)[inter]])
        r2 = np.concatenate([self._intra_r2(loop), self._inter_r2(inter)]) / vote  # the TLS test at Ω
        trusted = np.concatenate([st.intra_weights[loop] > 0.5, st.inter_weights[inter] > 0.5])
        return r2, trusted, loop, inter

    def _initial_mu(self, r2: np.ndarray, trusted: np.ndarray) -> float:
        """This robot's ``μ₀``: from its largest (trusted) residual, within
        [``gnc_mu0_min``, ``gnc_mu0_max``]."""
        p = self.params
        return self.gnc.initial_mu(r2, trusted if p.gnc_mu0_trusted else None, p.gnc_mu0_min, p.gnc_mu0_max)

    def _propose_mu(self, rnd: int) -> list[Message]:
        """First GNC step, team-wide ``μ₀``: publish this robot's ``μ₀`` (from its largest
        residual) and apply the team's smallest proposal ``gnc_mu_delay`` rounds later.

        Per-robot ``μ₀`` breaks GNC: a robot whose own residuals are small starts almost binary
        and locks in the (outlier-biased) least-squares decisions (measured on the office
        graph: 35 aliased closures kept; with one team ``μ`` none)."""
        r2, trusted, _, _ = self._robust_r2()
        mu0 = self._initial_mu(r2, trusted)
        self.mu_proposals[self.robot] = mu0
        self.pending = rnd + self.params.gnc_mu_delay
        empty_k = np.zeros(0, dtype=np.int64)
        return [GncWeights(robot=self.robot, peer=self.robot, round=rnd, keys_a=empty_k,
                           keys_b=empty_k, weights=np.zeros(0), mu=mu0)]

    def _intra_r2(self, edges: np.ndarray) -> np.ndarray:
        lg = self.local
        poses = self.state.poses
        sub = PoseGraph(poses=poses, robot=np.zeros(len(poses), dtype=int),
                        local=np.arange(len(poses)), ids=np.arange(len(poses)),
                        edge_i=lg.intra_i[edges], edge_j=lg.intra_j[edges],
                        measurement=lg.intra_meas[edges], information=lg.intra_info[edges])
        return residuals_sq(sub, poses)

    def _inter_r2(self, edges: np.ndarray) -> np.ndarray:
        lg = self.local
        out = np.zeros(len(edges))
        for n, e in enumerate(edges):
            own = self.state.poses[lg.inter_own[e]]
            nb = self.state.neighbour_poses[int(lg.inter_peer_key[e])]
            Xi, Xj = (own, nb) if lg.inter_own_is_i[e] else (nb, own)
            err = gtsam.Pose3.Logmap(to_gtsam(lg.inter_meas[e]).inverse()
                                     * to_gtsam(Xi).inverse() * to_gtsam(Xj))
            out[n] = err @ lg.inter_info[e] @ err
        return out

    def binary(self) -> bool:
        """Every weight is 0 or 1."""
        return GncSchedule.binary(self.state.inter_weights) and GncSchedule.binary(self.state.intra_weights)

    # ---------------------------------------------------------------- leader
    def lead(self, rnd: int, all_ready: bool) -> Literal["update_weights", "stop"] | None:
        """Leader, robust mode: order a weight update once every robot is ready (or at the round
        cap); after the GNC schedule, the rechecks likewise, then ``stop`` once every robot is ready."""
        p = self.params
        since = rnd - self.last_round
        if self.gnc.steps >= p.gnc_max_steps:
            if self.rechecks >= p.gnc_rechecks:
                return "stop" if all_ready else None
            if not (all_ready or since >= 5 * p.gnc_round_cap) or self.pending is not None:
                return None
            return "update_weights"
        if (all_ready or since >= p.gnc_round_cap) and self.pending is None:
            return "update_weights"
        return None
