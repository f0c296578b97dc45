"""Distributed Levenberg–Marquardt with pipelined conjugate gradients across the robots.

:class:`GnPcgAgent` is a :class:`.agent.PgoAgent` (same initialisation and frame alignment) whose
solve is a Gauss–Newton outer loop instead of block Gauss–Seidel. The team's damped system
``(H + λ diag H) δ = −g`` is a sum of robot blocks coupled only through inter-robot edges
(:class:`.linear.LocalSystem`). It is solved by conjugate gradients preconditioned with
each robot's own block, factored exactly (block Jacobi over robots: bending inside a block is
solved exactly, CG fixes the coupling between blocks; its non-trivial spectrum is that of the
block-Jacobi-preconditioned Schur complement on the separator poses).

The CG is Ghysels–Vanroose's pipelined variant: the step's two team-wide inner products and its
one neighbour exchange (a direction at the public poses, 6 floats each) travel in the same
message, so one CG iteration is one round. The robots run in lock-step: step ``k`` of every
robot uses only the step ``k − 1`` messages (:class:`PcgState`) of the others, and a robot
missing one waits (repeating its own), so a lost message delays but never corrupts.

One outer iteration: ``lin`` (linearise at the team estimate, send ``u₀ = M⁻¹r₀``), ``cg0``
(``w₀ = A u₀``), CG iterations until the preconditioned residual drops by ``gn_forcing`` (or
``gn_max_cg``), the last one sending the step ``δ`` at the public poses instead of a direction;
``eval`` (each robot's cost at ``X ⊕ δ``, neighbours' trial poses from their ``δ``), then the
team accepts the step when the team cost fell (LM: ``λ`` shrinks) or rejects it (``λ`` grows).
Everything team-wide is a sum of per-robot scalars that every robot receives, so all robots
take the same decisions.

The coarse space also recycles the team's last ``gn_recycle`` steps (:mod:`.coarse`):
truncated CG leaves the same smooth error in consecutive linear systems. The team stops after
two accepted steps in a row that lower the team cost by less than ``gn_rel_tol`` (relative),
when a rejected step pushes ``λ`` past ``gn_damping_max``, or after ``gn_max_outer`` steps.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.pgo import GncWeights, PcgState, PgoStatus, PublicPoses
from kimera_multi_py.pgo.agent import PgoAgent
from kimera_multi_py.pgo.coarse import (
    INDEX_MASK,
    MAX_RECYCLE,
    CoarseRows,
    CoarseSolver,
    recycled_restriction,
    recycled_rows,
)
from kimera_multi_py.pgo.gn_weights import GnRobust
from kimera_multi_py.pgo.linear import LocalSystem, edge_costs, se3_expmap
from kimera_multi_py.pgo.local_graph import LocalGraph, frame_root
from kimera_multi_py.pgo.params import PgoParams

log = logging.getLogger(__name__)


class GnPcgAgent(PgoAgent):
    """One robot of the distributed Levenberg–Marquardt / pipelined-PCG solve (see module;
    robust mode: its part :class:`~.gn_weights.GnRobust`)."""

    gamma_prev: float  # the previous CG iteration's γ and α (set by the first one)
    alpha_prev: float

    def __init__(self, local: LocalGraph, params: PgoParams | None = None) -> None:
        super().__init__(local, params)
        self.k = 0  # the next lock-step to publish
        self.kind = "start"
        self.inbox: dict[tuple[int, int], PcgState] = {}
        self.peer_public: dict[int, np.ndarray] = {}  # robot -> its public keys (order of vectors)
        self.sent: list[PcgState] = []  # the last two steps sent (resent while waiting)
        self.lam = self.params.gn_damping
        self.team_cost = np.inf
        self.outer = 0
        self.cg_iterations = 0
        self.peer_X: np.ndarray | None = None  # poses at the inter-robot edges' far ends
        self._gather: np.ndarray | None = None
        self.coarse_rows: CoarseRows | None = None
        self.coarse: CoarseSolver | None = None
        self._peer_anchor = np.zeros(0, dtype=bool)
        self.last_decrease = np.inf  # relative team-cost decrease of the last outer step
        self.small_steps = 0  # consecutive accepted steps that lowered the cost by < gn_rel_tol
        self.coarse_built = 0
        self.recycle: list[tuple[np.ndarray, np.ndarray]] = []  # last steps (own, far ends)
        self.rec_steps: list[tuple[np.ndarray, np.ndarray]] = []  # those in this coarse space
        self._extend = False
        self._anchor_built: bool | None = None  # the anchoring the coarse space was built for
        self.joined = False  # aligned, or excluded for good: the robot takes part in the solve
        self.unaligned_rounds = 0
        self.gn_weights = GnRobust(local, self.params, self.state, self.root)

    def dependencies(self) -> set[int]:
        """Every step needs every robot's shares of the team sums."""
        return set(self.team) - {self.robot}

    # ---------------------------------------------------------------- messages in
    def handle(self, msg: Message) -> None:
        if isinstance(msg, PcgState):
            if msg.robot != self.robot and msg.step >= self.k - 1:
                self.inbox[(msg.robot, msg.step)] = msg
            return
        if isinstance(msg, PublicPoses) and msg.robot != self.robot:
            self.peer_public[msg.robot] = np.array(msg.keys)
            if self.peer_X is not None:
                return  # the solve tracks neighbour poses itself (from their steps)
        if isinstance(msg, GncWeights):
            if self.kind in ("start", "begin"):  # only the owners' screened weights, at the start
                self.gn_weights.absorb_start_weights(msg)
            return
        super().handle(msg)

    # ---------------------------------------------------------------- the step
    def step(self, rnd: int) -> list[Message]:
        out: list[Message] = []
        if self.done:
            return out
        p = self.params
        if not self.frame.aligned and not self.joined:
            # an excluded robot keeps deciding while evidence arrives; it takes part (edges off)
            # once the exclusion is final: every far end known, or waited long enough
            self.frame.try_align()
            self.joined = self.frame.aligned or (self.frame.excluded and self._exclusion_final())
            if not self.joined:
                return [self._status(rnd)]
            out.append(self._public(rnd, self.state.poses))
        elif self.peer_X is None and rnd - self.last_sent_round >= p.resend_interval:
            out.append(self._public(rnd, self.state.poses))
        if p.robust and not self.frame.screened and not self.frame.excluded and p.screen != "none":
            self.frame.screen()
        msg = self._advance(rnd)
        if msg is not None:
            out.append(msg)
            if msg.step == 0:
                out.extend(self.gn_weights.start_weight_messages(rnd))
        elif self.sent and rnd - self.sent[-1].round >= p.resend_interval:
            # another robot may still miss either of the last two steps (it is one behind at most)
            self.sent = [dataclasses.replace(m, round=rnd) for m in self.sent]
            out.extend(self.sent)
            if self.kind == "begin":
                out.extend(self.gn_weights.resend_start_weights(rnd))
        out.append(self._status(rnd))
        return out

    def _exclusion_final(self) -> bool:
        """No more evidence can change the exclusion: every inter-robot edge's far end is known
        (the frame decision has seen them all), or ``3·align_patience`` rounds have passed."""
        self.unaligned_rounds += 1
        known = all(int(k) in self.state.neighbour_poses for k in self.local.inter_peer_key)
        return known or self.unaligned_rounds >= 3 * self.params.align_patience

    def _status(self, rnd: int) -> PgoStatus:
        rel = float(self.rel_change) if np.isfinite(self.rel_change) else 1e300
        return PgoStatus(robot=self.robot, round=rnd, ready=bool(self.ready), cost=float(self.cost),
                         rel_change=rel)

    def _received(self, step: int, rnd: int) -> dict[int, PcgState] | None:
        """Every other robot's message of ``step``, if all were sent before round ``rnd`` (one
        step per communication round, even when a robot happens to run after the others)."""
        got = {r: self.inbox.get((r, step)) for r in self.team if r != self.robot}
        if any(m is None or m.round >= rnd for m in got.values()):
            return None
        return {r: m for r, m in got.items() if m is not None}

    def _send(self, rnd: int, scalars: list[float], vectors: np.ndarray | None = None,
              restrict: np.ndarray | None = None, rows: bool = False,
              recycled: bool = False) -> PcgState:
        """Publish step ``k``: scalars, ``vectors`` at the public poses, the coarse
        restriction of ``restrict`` and (``rows``) this robot's rows of the coarse matrix
        (its recycled steps' rows go with every linearisation that recycles)."""
        f4 = np.float32
        vec = np.zeros((0, 6), f4) if vectors is None else vectors.reshape(-1, 6)[self.local.public]
        chunks, coarse = np.zeros(0, np.int64), np.zeros((0, 6), f4)
        cr = self.coarse_rows
        if restrict is not None and cr is not None:
            chunks, coarse = cr.own_ids, cr.restrict(restrict)
            if self.rec_steps:
                ids, row = recycled_restriction(self.robot, self.rec_steps, restrict)
                chunks, coarse = np.concatenate([chunks, ids]), np.concatenate([coarse, row])
        pairs, blocks = np.zeros((0, 2), np.int64), np.zeros((0, 6, 6), f4)
        if rows and cr is not None:
            pairs, blocks = cr.rows(self.sys)
        if recycled and self.rec_steps and cr is not None:
            ids2, blk2 = recycled_rows(cr, self.sys, self.rec_steps)
            pairs, blocks = np.concatenate([pairs, ids2]), np.concatenate([blocks, blk2])
        msg = PcgState(robot=self.robot, round=rnd, step=self.k, scalars=np.asarray(scalars, float),
                       vectors=np.ascontiguousarray(vec, f4), chunks=chunks,
                       coarse=np.ascontiguousarray(coarse, f4), pairs=pairs,
                       blocks=np.ascontiguousarray(blocks, f4))
        self.k += 1
        self.sent = [*self.sent[-1:], msg]
        for key in [key for key in self.inbox if key[1] < self.k - 2]:
            del self.inbox[key]
        return msg

    def _advance(self, rnd: int) -> PcgState | None:
        p = self.params
        if self.kind == "start":
            if not all(int(k) in self.state.neighbour_poses for k in self.local.inter_peer_key):
                return None
            if not all(int(r) in self.peer_public for r in self.local.neighbours):
                return None
            self.peer_X = np.stack([self.state.neighbour_poses[int(k)] for k in self.local.inter_peer_key]) \
                if len(self.local.inter_peer_key) else np.zeros((0, 4, 4))
            self._gather = self._gather_index()
            # far ends that are a frame root's first pose: the team's gauge, never moved
            roots = np.array([frame_root(int(r), self.team, self.local.robot_graph)
                              for r in self.local.inter_peer], dtype=bool)
            self._peer_anchor = roots & ((self.local.inter_peer_key & INDEX_MASK) == 0)
            if p.robust and not (self.frame.screened or self.frame.excluded or p.screen == "none"):
                return None
            self.kind = "begin"
            return self._send(rnd, self.gn_weights.start_scalars(self.state.poses, self.peer_X, self.frame.excluded))
        got = self._received(self.k - 1, rnd)
        if got is None:
            return None
        if self.kind == "begin":
            if not self.gn_weights.start_weights_in():
                return None
            self.gn_weights.apply_start(got, self.frame.excluded)
            return self._linearise(rnd)
        if self.kind == "cg0":
            return self._cg_start(rnd, got)
        if self.kind == "cg":
            return self._cg_iterate(rnd, got)
        if self.kind == "eval":
            return self._evaluate(rnd, got)
        return self._decide(rnd, got)

    # ---------------------------------------------------------------- outer loop
    def _gather_index(self) -> np.ndarray:
        """For each inter-robot edge, its far end's row in the stacked neighbour vectors."""
        lg = self.local
        offsets, start = {}, 0
        for r in lg.neighbours:
            offsets[r] = start
            start += len(self.peer_public[r])
        idx = np.zeros(len(lg.inter_peer_key), dtype=int)
        for e, (r, key) in enumerate(zip(lg.inter_peer.tolist(), lg.inter_peer_key.tolist(), strict=True)):
            keys = self.peer_public[r]
            pos = int(np.searchsorted(keys, key))
            if pos >= len(keys) or keys[pos] != key:
                pos = int(np.flatnonzero(keys == key)[0])
            idx[e] = offsets[r] + pos
        return idx

    def _peer_vectors(self, got: dict[int, PcgState]) -> np.ndarray:
        assert self._gather is not None
        if not len(self._gather):
            return np.zeros((0, 6))
        stacked = np.concatenate([np.asarray(got[r].vectors, dtype=float) for r in self.local.neighbours])
        return stacked[self._gather]

    def _cost(self, poses: np.ndarray, peer_X: np.ndarray) -> float:
        """The robot's share of the team cost: its intra edges and half of each inter edge."""
        lg = self.local
        c = float(edge_costs(poses[lg.intra_i], poses[lg.intra_j], lg.intra_meas, self.gn_weights.w_intra_info).sum()) \
            if len(lg.intra_i) else 0.0
        if len(lg.inter_own):
            own = poses[lg.inter_own]
            sel = lg.inter_own_is_i[:, None, None]
            Ti, Tj = np.where(sel, own, peer_X), np.where(sel, peer_X, own)
            c += 0.5 * float(edge_costs(Ti, Tj, lg.inter_meas, self.gn_weights.w_inter_info).sum())
        return c

    def _linearise(self, rnd: int) -> PcgState:
        lg = self.local
        assert self.peer_X is not None
        rw = self.gn_weights
        anchored = rw.anchored()
        self.sys = LocalSystem(self.state.poses, lg.intra_i, lg.intra_j, lg.intra_meas, rw.w_intra_info,
                               lg.inter_own, lg.inter_own_is_i, self.peer_X, lg.inter_meas,
                               rw.w_inter_info, anchor=anchored, damping=self.lam)
        # the robot's share of the team cost (at the current weights) and its non-binary weights
        self.cost = self._cost(self.state.poses, self.peer_X)
        size = self.params.gn_coarse_size
        # the coarse space (its maps P and A_c = PᵀHP) is rebuilt every gn_coarse_refresh outer
        # steps (sooner while the team cost still falls by more than 1% a step: the poses,
        # hence P and H, still move a lot); in between the old one stays a valid (SPD)
        # preconditioner and costs no bytes
        rebuild = size > 0 and (self.coarse_rows is None or self.last_decrease > 1e-2
                                or self.outer - self.coarse_built >= self.params.gn_coarse_refresh
                                or anchored != self._anchor_built)
        self._anchor_built = anchored
        if rebuild:
            self.coarse_rows = CoarseRows(self.robot, self.state.poses, self.peer_X, lg.inter_peer,
                                          lg.inter_peer_key, size, self.sys.keep, self._peer_anchor)
            self.coarse = None
            self.coarse_built = self.outer
        k = min(self.params.gn_recycle, MAX_RECYCLE)
        self.rec_steps = self.recycle[-k:] if k > 0 and self.coarse_rows is not None else []
        self._extend = True
        self.x = np.zeros(6 * len(lg.keys))
        self.r = -self.sys.gradient
        self.ub = _single(self.sys.precondition(self.r))
        self.kind = "cg0"
        self.cg_i = 0
        scalars = [self.cost, float(rw.nonbinary()), float(rw.flipped)] if self.params.robust else [self.cost]
        return self._send(rnd, scalars, self.ub, restrict=self.r, rows=rebuild, recycled=True)

    def _apply(self, got: dict[int, PcgState], own_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The preconditioned vector at the own poses and at the inter-robot edges' far ends:
        block Jacobi (``own_b`` and the neighbours' received parts) plus the coarse correction."""
        peer = self._peer_vectors(got)
        cr = self.coarse_rows
        if cr is None:
            return own_b, peer
        mine = self.sent[-1]
        msgs = [got.get(r, mine) for r in sorted(self.team)]
        if self.coarse is None:  # the rows came with the first step after a rebuild
            self.coarse = CoarseSolver([np.asarray(m.pairs) for m in msgs],
                                       [np.asarray(m.blocks, dtype=float) for m in msgs],
                                       [np.asarray(m.chunks) for m in msgs])
        if self._extend:  # the recycled steps' rows came with the linearisation's message
            self.coarse.extend([np.asarray(m.pairs) for m in msgs],
                               [np.asarray(m.blocks, dtype=float) for m in msgs],
                               [np.asarray(m.chunks) for m in msgs], len(self.rec_steps))
            self._extend = False
        y, z = self.coarse.solve([np.asarray(m.chunks) for m in msgs],
                                 [np.asarray(m.coarse, dtype=float) for m in msgs])
        own = own_b + self.coarse.prolong(y, cr.own_ids[cr.local_chunk], cr.P_own).ravel()
        peer = peer + self.coarse.prolong(y, cr.peer_ids, cr.P_peer)
        for zj, (d_own, d_peer) in zip(z, self.rec_steps, strict=False):
            own = own + zj * d_own.ravel()
            peer = peer + zj * d_peer
        return own, peer

    def _cg_start(self, rnd: int, got: dict[int, PcgState]) -> PcgState:
        self.team_cost = self.cost + sum(float(m.scalars[0]) for m in got.values())
        if self.params.robust:
            self.gn_weights.count_team(got)
        self.u, u_peer = self._apply(got, self.ub)
        self.w = self.sys.multiply(self.u, u_peer)
        self.p = np.zeros_like(self.x)
        self.s, self.q, self.z = self.p.copy(), self.p.copy(), self.p.copy()
        self.mb = _single(self.sys.precondition(self.w))
        self.kind = "cg"
        return self._send(rnd, [float(self.r @ self.u), float(self.w @ self.u)], self.mb,
                          restrict=self.w)

    def _cg_iterate(self, rnd: int, got: dict[int, PcgState]) -> PcgState:
        """One pipelined-PCG iteration (the reduction and the matvec of ``m`` overlap)."""
        gamma = float(self.r @ self.u) + sum(float(m.scalars[0]) for m in got.values())
        delta = float(self.w @ self.u) + sum(float(m.scalars[1]) for m in got.values())
        self.m, m_peer = self._apply(got, self.mb)
        n = self.sys.multiply(self.m, m_peer)
        if self.cg_i == 0:
            self.gamma0 = gamma
            beta, alpha = 0.0, gamma / delta if delta > 0 else 0.0
        else:
            beta = gamma / self.gamma_prev
            denom = delta - beta * gamma / self.alpha_prev
            alpha = gamma / denom if denom > 0 else 0.0
        self.gamma_prev, self.alpha_prev = gamma, alpha
        self.z = n + beta * self.z
        self.q = self.m + beta * self.q
        self.s = self.w + beta * self.s
        self.p = self.u + beta * self.p
        self.x = self.x + alpha * self.p
        self.r = self.r - alpha * self.s
        self.u = self.u - alpha * self.q
        self.w = self.w - alpha * self.z
        self.cg_i += 1
        self.cg_iterations += 1
        p = self.params
        if alpha <= 0 or gamma <= (p.gn_forcing ** 2) * self.gamma0 or self.cg_i >= p.gn_max_cg:
            self.kind = "eval"
            self.x = _single(self.x)  # the step as the neighbours receive it
            return self._send(rnd, [], self.x)
        self.mb = _single(self.sys.precondition(self.w))
        return self._send(rnd, [float(self.r @ self.u), float(self.w @ self.u)], self.mb,
                          restrict=self.w)

    def _trial(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Own and far-end poses after ``t`` times the step."""
        assert self.peer_X is not None
        poses = self.state.poses @ se3_expmap(t * self.x.reshape(-1, 6))
        peer = self.peer_X @ se3_expmap(t * self.x_peer) if len(self.peer_X) else self.peer_X
        return poses, peer

    def _evaluate(self, rnd: int, got: dict[int, PcgState]) -> PcgState:
        """The robot's cost at every step length of the line search (one round for all)."""
        self.x_peer = self._peer_vectors(got)
        self.trial_costs = [self._cost(*self._trial(t)) for t in self.params.gn_step_lengths]
        self.kind = "decide"
        return self._send(rnd, self.trial_costs)

    def _decide(self, rnd: int, got: dict[int, PcgState]) -> PcgState | None:
        p = self.params
        costs = np.array(self.trial_costs) + sum(np.asarray(m.scalars) for m in got.values())
        best = int(np.argmin(costs))
        new_cost, t = float(costs[best]), float(p.gn_step_lengths[best])
        self.outer += 1
        self.recycle = [*self.recycle[-(MAX_RECYCLE - 1):], (self.x.reshape(-1, 6).copy(), self.x_peer.copy())]
        decrease = (self.team_cost - new_cost) / max(abs(self.team_cost), 1e-300)
        self.last_decrease = max(decrease, 0.0)
        accepted = new_cost < self.team_cost
        if accepted:
            poses, peer = self._trial(t)
            change = np.sqrt(np.sum((poses - self.state.poses) ** 2) / max(np.sum(self.state.poses**2), 1e-300))
            self.rel_change = float(change)
            self.state.poses, self.peer_X = poses, peer
            self.cost, self.team_cost = self.trial_costs[best], new_cost
            if t >= 1.0:
                self.lam = max(self.lam / p.gn_damping_factor, p.gn_damping_min)
            else:  # the model over-reached: damp a little more
                self.lam = min(self.lam * p.gn_damping_factor, p.gn_damping_max)
            self.small_steps = self.small_steps + 1 if decrease < p.gn_rel_tol else 0
            converged = self.small_steps >= 2
        else:
            self.lam *= p.gn_damping_factor ** 2
            converged = self.lam > p.gn_damping_max
        log.debug("robot %d round %d outer %d: cost %.9g t %g lambda %.2e cg %d", self.robot, rnd,
                  self.outer, self.team_cost, t, self.lam, self.cg_i)
        done = self.gn_weights.after_step(accepted, converged, self.outer, decrease, self.state.poses, self.peer_X,
                                          self.frame.excluded)
        if self.gn_weights.weights_outer == self.outer:  # the weights changed: a new problem to converge
            self.small_steps = 0
            self.lam = min(self.lam, p.gn_damping)
        if done or self.outer - self.gn_weights.weights_outer >= p.gn_max_outer:
            self.ready = True
            self.done = True
            return None
        return self._linearise(rnd)


def _single(v: np.ndarray) -> np.ndarray:
    """``v`` rounded to float32 (what travels), back in float64."""
    return np.asarray(v, dtype=np.float32).astype(np.float64)


def make_agent(local: LocalGraph, params: PgoParams) -> PgoAgent:
    """The agent of ``params.method``."""
    if params.method == "gn_pcg":
        return GnPcgAgent(local, params)
    return PgoAgent(local, params)
