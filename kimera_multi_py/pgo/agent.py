"""Distributed pose-graph optimisation: one robot's pure per-round step (docs/algorithms/pgo.md).

A :class:`PgoAgent` owns its poses. Its *public* poses are those touching inter-robot edges.
It never touches the network: :meth:`PgoAgent.handle` takes incoming messages and
:meth:`PgoAgent.step` returns the messages to publish (see :mod:`.runtime` for the runtime).

A round ``r``:

1. neighbours' latest public poses are held fixed;
2. robots of colour ``r mod C`` (a greedy colouring of the robot graph, so adjacent robots
   never update together) solve their local block: warm-started gtsam LM on their own poses,
   each inter-robot edge turned into the exactly equivalent unary factor;
3. the updated robots publish their public poses, over-relaxed (block SOR: ``X ⊕ ω(X* ⊖ X)``,
   kept only when it lowers the block's cost, so the team cost is monotone; ``ω`` adapted per
   robot from the ratio of successive block steps, Hageman–Young). Nesterov momentum with
   restart on a team cost rise (RBCD++-style) is the alternative (``acceleration=True``);
   measured, it is slower and non-monotone on parking-garage and cubicle.

A robot's first update waits until it knows every neighbour pose it is joined to (or
``align_patience`` rounds): a block solved against part of its separator lands far away.

Initialisation (:mod:`.initialisation`): a robot starts from its own odometry (or its local chordal solution) in its own
frame; the lowest id of each connected robot graph is the team frame; the others align to an
aligned neighbour (:mod:`.frame_decision`, robust frame hypotheses included). A robot publishes
public poses only once aligned, so late joiners and robots without inter-robot edges simply
wait (their edges are ignored by the others meanwhile). Optionally (``distributed_init``) the
team first runs block Gauss–Seidel on the chordal relaxation until every robot has settled.

Robust mode: GNC-TLS weights on loop closures and inter-robot edges, one ``μ`` for the team
(:mod:`.weights`). The lowest robot id is the leader: it orders the weight updates and
sends ``stop`` when the team is done.

The agent owns its parts: :class:`~.initialisation.Initialisation`,
:class:`~.frame_decision.FrameDecision`, :class:`~.weights.RobustWeights` and
:class:`~.relaxation.Relaxation`. What several of them read or move (the estimate, the edge
weights, what was heard of the neighbours) is one :class:`~.state.SolveState`; everything else
belongs to one of them, and each takes what else it needs as arguments.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np

from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.pgo import EdgeVeto, GncWeights, PgoCommand, PgoStatus, PublicPoses
from kimera_multi_py.core.geometry import to_gtsam
from kimera_multi_py.core.posegraph import pair_index
from kimera_multi_py.pgo.factors import between, neighbour_factor, neighbour_parts, to_values
from kimera_multi_py.pgo.frame_decision import FrameDecision
from kimera_multi_py.pgo.initialisation import Initialisation
from kimera_multi_py.pgo.local_graph import LocalGraph, colour_robots, component_root
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.pgo.relaxation import Relaxation, extrapolate
from kimera_multi_py.pgo.state import SolveState
from kimera_multi_py.pgo.weights import RobustWeights

log = logging.getLogger(__name__)


class PgoAgent:
    """One robot's distributed-PGO state and its pure round step (see the module docstring).

    ``neighbour_poses`` (pose key -> public pose) and ``peer_settled`` (robot -> settled) seed
    what the robot has heard; ``in_team_frame``: its poses are already in the team frame (an
    earlier epoch aligned it; :class:`~.frame_decision.FrameDecision`).
    """

    def __init__(self, local: LocalGraph, params: PgoParams | None = None, *,
                 neighbour_poses: dict[int, np.ndarray] | None = None, peer_settled: dict[int, bool] | None = None,
                 in_team_frame: bool = False) -> None:
        self.local = local
        self.params = params or PgoParams()
        self.robot = local.robot
        p = self.params
        team = local.team or (local.robot,)
        self.team = team
        self.leader = min(team)
        colours = colour_robots(team, local.robot_graph)
        self.colour = colours[self.robot]
        self.num_colours = max(colours.values()) + 1
        self.root_robot = component_root(self.robot, team, local.robot_graph)  # the team frame's root
        self.root = self.root_robot == self.robot
        # the parts (module docstring) and what they share
        self.initialisation = Initialisation(local, p)
        self.state = SolveState.start(local, self.initialisation.initial_poses())
        self.state.neighbour_poses.update(neighbour_poses or {})
        self.state.peer_settled.update(peer_settled or {})
        self.frame = FrameDecision(local, p, self.state, self.root_robot, in_team_frame)
        self.weights = RobustWeights(local, p, self.state)
        self.relaxation = Relaxation(p)
        # stage: "init" (distributed chordal relaxation) until the leader's start, then "solve"
        self.stage = "init" if p.distributed_init and local.robot_graph else "solve"
        self.solve_from: int | None = None  # round the BCD starts (from the leader's command)
        self.solve_round = 0  # statuses older than this belong to the init stage
        self.updates = 0
        self.updates_since_weights = 0
        self.ready = False
        self.rel_change = np.inf
        self.cost = 0.0
        self.done = False
        self.wait_updates = 0
        self.relaxed = 0
        self.statuses: dict[int, PgoStatus] = {}
        self.last_sent_round = -10**9
        self._veto_round = -10**9
        self._base: gtsam.NonlinearFactorGraph | None = None
        self._parts: dict[int, tuple[float, tuple[gtsam.Pose3, gtsam.noiseModel.Base]]] = {}

    def drop(self, robots: set[int]) -> None:
        """Robots that left the epoch: no longer waited for nor counted in the team's sums."""
        self.team = tuple(r for r in self.team if r not in robots)

    def final_poses(self) -> np.ndarray:
        """The poses to adopt at the end of the epoch (:meth:`.frame_decision.FrameDecision.final_poses`)."""
        return self.frame.final_poses(self._solve_alone)

    def dependencies(self) -> set[int]:
        """The robots whose previous round this one waits for: its neighbours (the leader: all)."""
        deps = set(self.team if self.robot == self.leader else self.local.neighbours)
        deps.discard(self.robot)
        return deps

    # ---------------------------------------------------------------- messages in
    def handle(self, msg: Message) -> None:
        """Absorb one message from another robot (or an own command)."""
        if isinstance(msg, PublicPoses):
            if msg.robot == self.robot:
                return
            for k, T in zip(msg.keys.tolist(), msg.poses, strict=False):
                self.state.neighbour_poses[int(k)] = np.array(T)
            self.state.peer_settled[msg.robot] = bool(msg.settled)
        elif isinstance(msg, PgoStatus):
            old = self.statuses.get(msg.robot)
            if old is None or msg.round >= old.round:
                self.statuses[msg.robot] = msg
        elif isinstance(msg, PgoCommand):
            if msg.command == "stop":
                self.done = True
            elif msg.command == "update_weights":
                self.weights.order(msg.round)
            elif msg.command == "start" and self.stage == "init" and self.solve_from is None:
                self.solve_from = msg.round
        elif isinstance(msg, GncWeights):
            self.weights.absorb(msg)
        elif isinstance(msg, EdgeVeto):
            self._absorb_veto(msg)

    # ---------------------------------------------------------------- the step
    def active(self, rnd: int) -> bool:
        return rnd % self.num_colours == self.colour

    def step(self, rnd: int) -> list[Message]:
        """Run round ``rnd``; return the messages to publish."""
        out: list[Message] = []
        if self.done:
            return out
        if not self.frame.aligned:
            self.frame.try_align()
            if not self.frame.aligned:
                out.append(self._status(rnd))
                return out
            out.append(self._public(rnd, self.state.poses))
        if self.params.robust and not self.frame.screened and self.params.screen != "none":
            self.frame.screen()
        out.extend(self._vetoes(rnd))
        if self.stage == "init" and self.solve_from is not None and rnd >= self.solve_from:
            self._start_solve(rnd)
        if (self.params.robust and self.stage == "solve" and self.weights.pending is not None
                and rnd >= self.weights.pending):
            out.extend(self._update_weights(rnd))
        updated = False
        if self.active(rnd) and self._neighbours_known():
            if self.stage == "init":
                self._init_update()
            else:
                self._update(rnd)
            updated = True
        if updated or rnd - self.last_sent_round >= self.params.resend_interval:
            out.append(self._public(rnd, self.state.published if self.stage == "solve" else self.state.poses))
        out.append(self._status(rnd))
        if self.robot == self.leader:
            out.extend(self._lead(rnd))
        return out

    def _neighbours_known(self) -> bool:
        """Update only once every neighbour pose is known (or after ``align_patience`` waits):
        a block solved against a partial separator drifts far from the team's solution."""
        if self.updates > 0 or all(int(k) in self.state.neighbour_poses for k in self.local.inter_peer_key):
            return True
        self.wait_updates += 1
        return self.wait_updates > self.params.align_patience

    def _vetoes(self, rnd: int) -> list[EdgeVeto]:
        """The barred inter-robot edges (:meth:`.state.SolveState.bar`), one message per peer, when
        newly barred and then every ten ``resend_interval`` (a peer may have lost them: until it
        hears, its GNC may weigh them, and the safety net stays the backstop)."""
        st = self.state
        due = self.frame.veto_news or rnd - self._veto_round >= 10 * self.params.resend_interval
        if not st.barred.any() or not due:
            return []
        self.frame.veto_news = False
        self._veto_round = rnd
        lg = self.local
        out = []
        for peer in np.unique(lg.inter_peer[st.barred]):
            sel = np.flatnonzero(st.barred & (lg.inter_peer == peer))
            out.append(EdgeVeto(robot=self.robot, peer=int(peer), round=rnd, keys_a=lg.keys[lg.inter_own[sel]],
                                keys_b=lg.inter_peer_key[sel]))
        return out

    def _absorb_veto(self, msg: EdgeVeto) -> None:
        """A peer's barred edges with this robot: held at weight 0 here too."""
        if msg.peer != self.robot:
            return
        lg = self.local
        vetoed = pair_index(lg.keys[lg.inter_own], lg.inter_peer_key, msg.keys_b, msg.keys_a) >= 0
        self.state.bar(vetoed & (lg.inter_peer == msg.robot))

    def _status(self, rnd: int) -> PgoStatus:
        rel = float(self.rel_change) if np.isfinite(self.rel_change) else 1e300
        # an excluded robot has nothing to converge: it never holds the team up
        ready = (self.ready and self.frame.aligned) or self.frame.excluded
        return PgoStatus(robot=self.robot, round=rnd, ready=bool(ready), cost=float(self.cost), rel_change=rel)

    def _public(self, rnd: int, poses: np.ndarray) -> PublicPoses:
        self.last_sent_round = rnd
        pub = self.local.public
        return PublicPoses(robot=self.robot, round=rnd, keys=self.local.keys[pub],
                           poses=poses[pub], settled=bool(self.frame.settled and not self.frame.excluded))

    # ---------------------------------------------------------------- stages
    def _init_update(self) -> None:
        """One block of the team's chordal relaxation (:meth:`.initialisation.Initialisation.update`)."""
        st = self.state
        new = self.initialisation.update(st, self.root)
        change = np.sqrt(np.sum((new - st.poses) ** 2) / max(np.sum(st.poses**2), 1e-300))
        self.rel_change = float(change)
        self.ready = self.rel_change < self.params.init_rel_tol
        st.poses = new
        self.updates += 1

    def _start_solve(self, rnd: int) -> None:
        """Leave the initialisation: the BCD starts from the relaxation's poses."""
        self.stage = "solve"
        self.solve_round = rnd
        self.state.restart_from(self.state.poses)
        self.ready = False
        self.rel_change = np.inf
        self.updates = 0
        self.updates_since_weights = 0
        self.relaxation.restart(team_cost=True)

    def _update_weights(self, rnd: int) -> list[Message]:
        """The ordered weight update (:meth:`.weights.RobustWeights.update`); new weights are a
        new problem: the block graph is rebuilt and the robot converges anew."""
        out, changed = self.weights.update(rnd)
        if changed:
            self._base = None
            self.updates_since_weights = 0
            self.ready = False
            self.relaxation.restart()
        return out

    # ---------------------------------------------------------------- local solve
    def _base_graph(self) -> gtsam.NonlinearFactorGraph:
        if self._base is None:
            lg = self.local
            fg = gtsam.NonlinearFactorGraph()
            for e in range(len(lg.intra_i)):
                w = self.state.intra_weights[e]
                if w > 0:
                    fg.add(between(lg.keys[lg.intra_i[e]], lg.keys[lg.intra_j[e]],
                                   lg.intra_meas[e], lg.intra_info[e], w))
            self._base = fg
        return self._base

    def _inter_graph(self) -> gtsam.NonlinearFactorGraph:
        lg = self.local
        fg = gtsam.NonlinearFactorGraph()
        follows = self._followers()
        for e in range(len(lg.inter_edge)):
            w = self.state.inter_weights[e]
            nb = self.state.neighbour_poses.get(int(lg.inter_peer_key[e]))
            if w <= 0 or nb is None or int(lg.inter_peer[e]) in follows:
                continue
            fg.add(neighbour_factor(lg.keys[lg.inter_own[e]], nb, self._neighbour_parts(e, float(w))))
        return fg

    def _neighbour_parts(self, e: int, w: float) -> tuple[gtsam.Pose3, gtsam.noiseModel.Base]:
        """Edge ``e``'s factor parts at weight ``w``, computed once per edge and weight."""
        cached = self._parts.get(e)
        if cached is None or cached[0] != w:
            lg = self.local
            cached = (w, neighbour_parts(bool(lg.inter_own_is_i[e]), lg.inter_meas[e], lg.inter_info[e], w))
            self._parts[e] = cached
        return cached[1]

    def _followers(self) -> set[int]:
        """Peers whose edges this robot's solve leaves out: a robot in a settled frame (the root,
        or one aligned on a clear lead) is not pulled by peers whose frames are not settled (one
        place, or the consensus of a tie). They align to it and follow it; it does not follow
        them, so an alias they sit in cannot bend the team frame (two robots adopted on a start
        room that is the twin of the root's would otherwise rotate the root towards their
        alias). Once a peer settles, its edges count both ways again, and so do all edges once
        the GNC schedule is over: the re-checks and the final solve are the joint ones, so the
        converged estimate is the team's optimum over the closures GNC kept."""
        p = self.params
        if not (p.robust and p.align_hypotheses and self.frame.settled and not self.frame.excluded) \
                or self.weights.gnc.steps >= p.gnc_max_steps:
            return set()
        return {r for r, ok in self.state.peer_settled.items() if not ok}

    def _update(self, rnd: int) -> None:
        lg = self.local
        st = self.state
        inter = self._inter_graph()
        fg = gtsam.NonlinearFactorGraph(self._base_graph())
        fg.push_back(inter)
        if inter.size() == 0:
            fg.add(gtsam.PriorFactorPose3(int(lg.keys[0]), to_gtsam(st.poses[0]),
                                          gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(self.params.lm_iterations)
        lm.setRelativeErrorTol(self.params.lm_rel_tol)
        lm.setAbsoluteErrorTol(0.0)
        values = gtsam.LevenbergMarquardtOptimizer(fg, st.values, lm).optimize()
        new = _poses_of(values)
        change = np.sqrt(np.sum((new - st.poses) ** 2) / max(np.sum(st.poses**2), 1e-300))
        self.rel_change = float(change)
        self.ready = self.rel_change < self.params.rel_tol and self.updates_since_weights > 0
        omega = self.relaxation.factor(float(np.sqrt(np.sum((new - st.poses) ** 2))), self.updates_since_weights)
        if omega != 1.0 and self.updates_since_weights > 0:
            # block over-relaxation: on a quadratic cost X ⊕ ω(X* ⊖ X) lowers the cost by
            # ω(2−ω) times the exact step's decrease; kept only when it does lower it here
            relaxed = extrapolate(new, st.poses, omega - 1.0)
            relaxed_values = to_values(lg.keys, relaxed)
            if fg.error(relaxed_values) <= fg.error(st.values):
                new, values = relaxed, relaxed_values
                self.relaxed += 1
            else:
                self.relaxation.back_off()
        self.cost = float(self._base_graph().error(values) + 0.5 * inter.error(values))
        # Nesterov momentum on what neighbours see; restart on a team cost rise or interval
        self.updates += 1
        self.updates_since_weights += 1
        st.published = self.relaxation.momentum(new, st.poses, self.updates, self.cost, self.statuses, self.team,
                                                self.robot)
        st.prev_poses = st.poses
        st.poses = new
        st.values = values

    def _solve_alone(self) -> np.ndarray:
        """The robot's own graph alone (odometry and the intra-robot closures GNC kept), its
        first pose held."""
        lg = self.local
        poses = self.state.poses
        fg = gtsam.NonlinearFactorGraph(self._base_graph())
        fg.add(gtsam.PriorFactorPose3(int(lg.keys[0]), to_gtsam(poses[0]),
                                      gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        values = gtsam.LevenbergMarquardtOptimizer(fg, to_values(lg.keys, poses)).optimize()
        return _poses_of(values)

    # ---------------------------------------------------------------- leader
    def _lead(self, rnd: int) -> list[Message]:
        p = self.params
        if self.stage == "init" or self.initialisation.start_sent is not None:
            starting = self._lead_init(rnd)
            if self.stage == "init" or starting:
                return starting
        statuses = [self.statuses.get(r) for r in self.team if r != self.robot]
        statuses = [s if s is not None and s.round >= self.solve_round else None for s in statuses]
        known = all(s is not None for s in statuses)
        all_ready = known and self.ready and all(s.ready for s in statuses if s is not None)
        if p.robust:
            return self._lead_weights(rnd, all_ready)
        return self._stop(rnd) if all_ready else []

    def _lead_init(self, rnd: int) -> list[Message]:
        """Start the BCD when the team's relaxation has settled (:meth:`.initialisation.Initialisation.lead`)."""
        start = self.initialisation.lead(rnd, self.team, self.ready and self.frame.aligned, self.statuses)
        if start is None:
            return []
        return self._command(start, "start", np.array(self.team, dtype=np.int64))

    def _lead_weights(self, rnd: int, all_ready: bool) -> list[Message]:
        """Robust mode: weight updates, then ``stop`` (:meth:`.weights.RobustWeights.lead`)."""
        order = self.weights.lead(rnd, all_ready)
        if order == "stop":
            return self._stop(rnd)
        if order == "update_weights":
            return self._command(rnd + 1, "update_weights", np.array(self.team, dtype=np.int64))
        return []

    def _stop(self, rnd: int) -> list[Message]:
        return self._command(rnd, "stop", np.zeros(0, dtype=np.int64))

    def _command(self, rnd: int, command: str, active: np.ndarray) -> list[Message]:
        """A leader's command: applied to this robot too, and sent."""
        cmd = PgoCommand(robot=self.robot, round=rnd, command=command, active=active)
        self.handle(cmd)
        return [cmd]


def _poses_of(values: gtsam.Values) -> np.ndarray:
    """Poses of a Values in key order as ``(n, 4, 4)`` (keys are one robot's, so in order)."""
    flat = gtsam.utilities.extractPose3(values)
    T = np.zeros((len(flat), 4, 4))
    T[:, :3, :3] = flat[:, :9].reshape(-1, 3, 3)
    T[:, :3, 3] = flat[:, 9:]
    T[:, 3, 3] = 1.0
    return T
