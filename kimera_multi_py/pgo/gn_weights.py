"""Robust weights of one distributed Levenberg–Marquardt robot: GNC-TLS in the lock-step outer
loop (docs/algorithms/pgo.md).

The robust schedule is the block-SOR solver's (:mod:`.weights`): one team ``μ`` (the
smallest ``μ₀`` any robot proposes, floored at ``gnc_mu0_min``), ``μ ← 1.4 μ`` per weight
update, then re-checks of every closure at the settled solution (first with
``recheck_factor`` slack, then the plain threshold). What differs is the timing and the
bookkeeping, which ride on the lock-step:

- **Start.** The frame decision and the screen are the block-SOR robot's. The lower-id robot
  of each inter-robot edge owns its screened weight and sends it (:class:`GncWeights`) with the
  first step; the first step's scalars also carry each robot's ``μ₀`` proposal and whether it
  is excluded from the team frame (its edges are then off on both sides for the epoch).
- **Weight updates** happen between outer steps: after ``gn_weight_every`` accepted steps, or
  one that lowered the team cost by less than ``gn_weight_tol`` (relative: the solve at this
  ``μ`` has settled), or a converged one, at the same step on every robot, since every decision of the outer
  loop is team-wide. A TLS weight is a function of the edge's residual alone, and both robots
  of an inter-robot edge hold the same two poses (a neighbour's poses are tracked from its own
  float32 steps), so both compute the same weight and no weight message is needed.
- **End of GNC**: when every weight of the team is binary after an update (the count of
  non-binary weights travels with the linearisation) or after ``gnc_max_steps``; then the
  ``gnc_rechecks`` re-checks, each once a step lowered the team cost by less than
  ``gn_recheck_tol`` (or at convergence), and more (plain threshold, up to
  ``gnc_max_rechecks``) while the last one flipped a decision anywhere in the team (that count
  travels with the linearisation too), as the centralised reference does; then the solve stops
  when converged.

The team cost is re-summed at every linearisation (each robot's share travels with it), so a
weight change never corrupts the accept/reject test of the line search.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from kimera_multi_py.comms.messages.pgo import GncWeights, PcgState
from kimera_multi_py.core.robust import GncSchedule, tls_threshold
from kimera_multi_py.pgo.linear import edge_costs
from kimera_multi_py.pgo.local_graph import LocalGraph
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.pgo.state import SolveState


class GnRobust:
    """The robust-weights part of :class:`.gn.GnPcgAgent` (see module). It sets the weights in
    the shared :class:`~.state.SolveState`; the agent hands it its poses, the far ends of its
    inter-robot edges (``peer_X``) and whether its frame decision keeps it out (``excluded``)."""

    def __init__(self, local: LocalGraph, params: PgoParams, state: SolveState, root: bool) -> None:
        self.local = local
        self.params = params
        self.robot = local.robot
        self.state = state
        self.root = root
        self.gnc = GncSchedule(tls_threshold(params.inlier_probability, params.tls_dof), mu_step=params.gnc_mu_step)
        self.rechecks = 0
        self.phase = "gnc" if self.params.robust else "off"  # "gnc" -> "recheck" -> "final"
        self.off_peers: set[int] = set()  # excluded neighbours: their edges stay off
        self.weights_from: set[int] = set()  # owners whose start weights arrived
        self.start_weights: list[GncWeights] = []
        self.team_mu0 = self.mu0_proposal = self.params.gnc_mu0_max
        self.accepted_since_weights = 0
        self.weights_outer = 0  # the outer step of the last weight change
        self.team_nonbinary = 0
        self.flipped = 0  # inlier decisions the last weight change flipped (own)
        self.team_flipped = 0
        self.refresh_info()

    # ---------------------------------------------------------------- weighted information
    def refresh_info(self) -> None:
        """Information matrices scaled by the current weights (odometry keeps weight 1)."""
        lg = self.local
        self.w_intra_info = lg.intra_info * self.state.intra_weights[:, None, None]
        self.w_inter_info = lg.inter_info * self.state.inter_weights[:, None, None]

    def anchored(self) -> bool:
        """The robot holds its first pose: it is a frame root, or no inter-robot edge binds it."""
        return self.root or not bool(np.any(self.state.inter_weights > 0))

    def nonbinary(self) -> int:
        w = np.concatenate([self.state.intra_weights[~self.local.intra_odometry], self.state.inter_weights])
        return int(np.count_nonzero((w > 1e-4) & (w < 1.0 - 1e-4)))

    # ---------------------------------------------------------------- start
    def start_scalars(self, poses: np.ndarray, peer_X: np.ndarray | None, excluded: bool) -> list[float]:
        """The first step's scalars: ``[μ₀ proposal, excluded]`` (robust; none otherwise)."""
        if not self.params.robust:
            return []
        r2_loop, r2_inter = self.robust_r2_all(poses, peer_X)
        r2 = np.concatenate([r2_loop, r2_inter])
        trusted = np.concatenate([self.state.intra_weights[~self.local.intra_odometry] > 0.5,
                                  self.state.inter_weights > 0.5])
        p = self.params
        self.mu0_proposal = self.gnc.initial_mu(r2, trusted if p.gnc_mu0_trusted else None,
                                                p.gnc_mu0_min, p.gnc_mu0_max)
        return [self.mu0_proposal, float(excluded)]

    def start_weight_messages(self, rnd: int) -> list[GncWeights]:
        """The screened weights of the inter-robot edges this robot owns, one message per peer."""
        if not self.params.robust:
            return []
        lg = self.local
        out = []
        for peer in lg.neighbours:
            if peer < self.robot:
                continue
            sel = np.flatnonzero(lg.inter_peer == peer)
            out.append(GncWeights(robot=self.robot, peer=int(peer), round=rnd,
                                  keys_a=lg.keys[lg.inter_own[sel]], keys_b=lg.inter_peer_key[sel],
                                  weights=self.state.inter_weights[sel], mu=0.0))
        self.start_weights = out
        return out

    def resend_start_weights(self, rnd: int) -> list[GncWeights]:
        """The start weights again, as of round ``rnd`` (a neighbour may have lost them)."""
        self.start_weights = [dataclasses.replace(m, round=rnd) for m in self.start_weights]
        return self.start_weights

    def absorb_start_weights(self, msg: GncWeights) -> None:
        if msg.peer == self.robot and msg.robot < self.robot and msg.robot not in self.weights_from:
            self.weights_from.add(msg.robot)
            lg = self.local
            lookup = {(int(a), int(b)): float(w)
                      for a, b, w in zip(msg.keys_b, msg.keys_a, msg.weights, strict=True)}
            for e, (a, b) in enumerate(zip(lg.keys[lg.inter_own], lg.inter_peer_key, strict=True)):
                w = lookup.get((int(a), int(b)))
                if w is not None:
                    self.state.inter_weights[e] = w
            self.state.hold_bars()

    def start_weights_in(self) -> bool:
        """Every lower-id neighbour's start weights have arrived (robust; always true otherwise)."""
        if not self.params.robust:
            return True
        return all(r in self.weights_from for r in self.local.neighbours if r < self.robot)

    def apply_start(self, got: dict[int, PcgState], excluded: bool) -> None:
        """The team's ``μ₀`` and the excluded robots, from the first step's scalars."""
        if not self.params.robust:
            return
        self.team_mu0 = min([float(m.scalars[0]) for m in got.values()] + [self.mu0_proposal])
        self.off_peers = {r for r, m in got.items() if m.scalars[1] > 0.5}
        self._force_off(excluded)
        self.refresh_info()

    def _force_off(self, excluded: bool) -> None:
        lg = self.local
        if excluded:
            self.state.inter_weights[:] = 0.0
        elif self.off_peers:
            self.state.inter_weights[np.isin(lg.inter_peer, list(self.off_peers))] = 0.0
        self.state.hold_bars()

    # ---------------------------------------------------------------- between outer steps
    def robust_r2_all(self, poses: np.ndarray, peer_X: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Squared residuals of the robot's loop closures and of all its inter-robot edges, at
        ``poses`` and the edges' far ends ``peer_X``."""
        lg = self.local
        loop = ~lg.intra_odometry
        r2_loop = 2.0 * edge_costs(poses[lg.intra_i[loop]], poses[lg.intra_j[loop]],
                                   lg.intra_meas[loop], lg.intra_info[loop]) if loop.any() else np.zeros(0)
        r2_inter = np.zeros(0)
        if len(lg.inter_own) and peer_X is not None:
            own = poses[lg.inter_own]
            sel = lg.inter_own_is_i[:, None, None]
            Ti, Tj = np.where(sel, own, peer_X), np.where(sel, peer_X, own)
            r2_inter = 2.0 * edge_costs(Ti, Tj, lg.inter_meas, lg.inter_info) / np.asarray(lg.inter_vote)
        return r2_loop / np.asarray(lg.intra_vote)[loop], r2_inter  # the TLS test at Ω (votes)

    def _set_weights(self, w: np.ndarray, outer: int, excluded: bool) -> None:
        loop = np.flatnonzero(~self.local.intra_odometry)
        before = np.concatenate([self.state.intra_weights[loop], self.state.inter_weights]) > 0.5
        self.state.intra_weights[loop] = w[: len(loop)]
        self.state.inter_weights[:] = w[len(loop):]
        self._force_off(excluded)
        self.refresh_info()
        after = np.concatenate([self.state.intra_weights[loop], self.state.inter_weights]) > 0.5
        self.flipped = int(np.count_nonzero(before != after))
        self.weights_outer = outer
        self.accepted_since_weights = 0

    def count_team(self, got: dict[int, PcgState]) -> None:
        """The team's non-binary weights and flipped decisions, from the linearisation's scalars
        (this robot's own counts plus every other robot's in ``got``)."""
        self.team_nonbinary = self.nonbinary() + sum(int(m.scalars[1]) for m in got.values())
        self.team_flipped = self.flipped + sum(int(m.scalars[2]) for m in got.values())

    def after_step(self, accepted: bool, converged: bool, outer: int, decrease: float, poses: np.ndarray,
                   peer_X: np.ndarray | None, excluded: bool) -> bool:
        """Between outer steps: update the weights when due; True when the solve is done.
        ``poses`` and ``peer_X``: the estimate after the step; ``excluded``: the robot is kept out
        of the team frame."""
        p = self.params
        if self.phase == "off":
            return converged
        if self.phase == "gnc":
            self.accepted_since_weights += int(accepted)
            over = (self.gnc.steps > 0 and self.team_nonbinary == 0) or self.gnc.steps >= p.gnc_max_steps
            if over:
                self.phase = "recheck"
            elif (converged or self.accepted_since_weights >= p.gn_weight_every
                  or (accepted and decrease < p.gn_weight_tol)):
                r2 = np.concatenate(self.robust_r2_all(poses, peer_X))
                self._set_weights(self.gnc.update(r2, mu0=self.team_mu0), outer, excluded)
                return False
            else:
                return False
        # a re-check needs the solve at the current weights settled, not converged to the
        # last digit: its χ² decisions move with the residuals, not with a 1e-6 of the cost
        if not (converged or (accepted and decrease < p.gn_recheck_tol)):
            return False
        # re-checks until the decisions are stable (at most gnc_max_rechecks): a closure dropped
        # at the last one may fit the re-converged solution, and TLS keeps what fits
        unstable = self.rechecks < p.gnc_rechecks or (self.team_flipped > 0 and self.rechecks < p.gnc_max_rechecks)
        if self.phase == "recheck" and unstable:
            # the TLS decision at the converged solution, first with slack (see .weights)
            last = self.rechecks + 1 >= p.gnc_rechecks
            factor = 1.0 if last else p.recheck_factor
            r2 = np.concatenate(self.robust_r2_all(poses, peer_X))
            self._set_weights((r2 <= factor * self.gnc.barc2).astype(float), outer, excluded)
            self.rechecks += 1
            return False
        if not converged:
            return False
        self.phase = "final"
        return True
