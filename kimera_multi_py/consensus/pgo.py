"""Distributed pose-graph optimisation: one robot's pure per-round step (DESIGN §4.4).

A :class:`PgoAgent` owns its poses. Its *public* poses are those touching inter-robot edges.
It never touches the network: :meth:`PgoAgent.handle` takes incoming messages and
:meth:`PgoAgent.step` returns the messages to publish (see :mod:`.runner` for the runtime).

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

Initialisation (:mod:`.pgo_init`): a robot starts from its own odometry (or its local chordal solution) in its own
frame; the lowest id of each connected robot graph is the team frame; the others align to an
aligned neighbour (:mod:`.frame_decision`, robust frame hypotheses included). A robot publishes
public poses only once aligned, so late joiners and robots without inter-robot edges simply
wait (their edges are ignored by the others meanwhile). Optionally (``distributed_init``) the
team first runs block Gauss–Seidel on the chordal relaxation until every robot has settled.

Robust mode: GNC-TLS weights on loop closures and inter-robot edges, one ``μ`` for the team
(:mod:`.pgo_weights`). The lowest robot id is the leader: it orders the weight updates and
sends ``stop`` when the team is done.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import gtsam
import networkx as nx
import numpy as np

from kimera_multi_py.comms.messages import GncWeights, Message, PgoCommand, PgoStatus, PublicPoses
from kimera_multi_py.consensus.chordal import edge_weights
from kimera_multi_py.consensus.factors import between, neighbour_factor, neighbour_parts, to_values
from kimera_multi_py.consensus.frame_decision import FrameDecision
from kimera_multi_py.consensus.pgo_init import Initialisation
from kimera_multi_py.consensus.pgo_params import PgoParams
from kimera_multi_py.consensus.pgo_relaxation import Relaxation, extrapolate
from kimera_multi_py.consensus.pgo_weights import RobustWeights
from kimera_multi_py.consensus.robust import GncSchedule, tls_threshold
from kimera_multi_py.geometry import inverse, to_gtsam
from kimera_multi_py.io.pose_graph import INTER_ROBOT, ODOMETRY, PoseGraph, robot_key

log = logging.getLogger(__name__)


@dataclass
class LocalGraph:
    """What robot ``robot`` knows: its poses, its own edges, and its inter-robot edges."""

    robot: int
    keys: np.ndarray  # (n,) own Symbol keys, local order
    poses: np.ndarray  # (n, 4, 4) initial values in the robot's own frame
    intra_i: np.ndarray
    intra_j: np.ndarray
    intra_meas: np.ndarray
    intra_info: np.ndarray
    intra_odometry: np.ndarray  # (m,) bool
    intra_edge: np.ndarray  # (m,) global edge index (for bookkeeping only)
    inter_own: np.ndarray  # (k,) own local index
    inter_own_is_i: np.ndarray  # (k,) bool
    inter_peer: np.ndarray  # (k,) neighbour robot id
    inter_peer_key: np.ndarray  # (k,) int64 neighbour Symbol key
    inter_meas: np.ndarray
    inter_info: np.ndarray
    inter_edge: np.ndarray  # (k,) global edge index
    robot_graph: list[tuple[int, int]] = field(default_factory=list)  # team topology
    team: tuple[int, ...] = ()
    # robust votes (:func:`.robust.correlated_votes`; the infos above already carry them, the TLS
    # decisions divide the squared residuals by them); None: 1 for every edge
    intra_vote: np.ndarray | None = None
    inter_vote: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.intra_vote is None:
            self.intra_vote = np.ones(len(self.intra_i))
        if self.inter_vote is None:
            self.inter_vote = np.ones(len(self.inter_own))

    @property
    def neighbours(self) -> list[int]:
        return sorted(set(self.inter_peer.tolist()))

    @property
    def public(self) -> np.ndarray:
        """Own local indices touching inter-robot edges."""
        return np.unique(self.inter_own)

    def subgraph(self) -> PoseGraph:
        """The intra-robot part as a :class:`PoseGraph` (for chordal initialisation)."""
        n = len(self.keys)
        return PoseGraph(poses=self.poses, robot=np.full(n, self.robot), local=np.arange(n),
                         ids=np.asarray(self.keys, dtype=np.int64), edge_i=self.intra_i,
                         edge_j=self.intra_j, measurement=self.intra_meas,
                         information=self.intra_info)


def split_local(graph: PoseGraph, frames: str = "own", votes: np.ndarray | None = None) -> list[LocalGraph]:
    """Each robot's :class:`LocalGraph`; ``frames="own"`` re-expresses a robot's initial values
    relative to its first pose (robots do not share a frame), ``"given"`` keeps them.
    ``votes``: robust votes per edge (already in ``graph``'s information), as the agents'."""
    vote = np.ones(graph.num_edges) if votes is None else np.asarray(votes, dtype=float)
    kind = graph.edge_kind()
    inter_edges = kind == INTER_ROBOT
    ra, rb = graph.robot[graph.edge_i[inter_edges]], graph.robot[graph.edge_j[inter_edges]]
    pairs = sorted({(int(min(a, b)), int(max(a, b))) for a, b in zip(ra, rb, strict=True)})
    team = tuple(range(graph.num_robots))
    out = []
    for r in team:
        own = graph.robot_indices(r)
        pos = np.full(graph.num_poses, -1)
        pos[own] = np.arange(len(own))
        poses = graph.poses[own]
        if frames == "own" and len(own):
            poses = inverse(poses[0]) @ poses
        ei, ej = graph.edge_i, graph.edge_j
        intra = np.flatnonzero((pos[ei] >= 0) & (pos[ej] >= 0))
        inter = np.flatnonzero((pos[ei] >= 0) ^ (pos[ej] >= 0))
        own_is_i = pos[ei[inter]] >= 0
        peer_idx = np.where(own_is_i, ej[inter], ei[inter])
        out.append(LocalGraph(
            robot=r,
            keys=np.array([robot_key(r, k) for k in range(len(own))], dtype=np.int64),
            poses=poses,
            intra_i=pos[ei[intra]], intra_j=pos[ej[intra]],
            intra_meas=graph.measurement[intra], intra_info=graph.information[intra],
            intra_odometry=kind[intra] == ODOMETRY, intra_edge=intra,
            inter_own=np.where(own_is_i, pos[ei[inter]], pos[ej[inter]]),
            inter_own_is_i=own_is_i,
            inter_peer=graph.robot[peer_idx],
            inter_peer_key=np.array([robot_key(int(graph.robot[p]), int(graph.local[p]))
                                     for p in peer_idx], dtype=np.int64),
            inter_meas=graph.measurement[inter], inter_info=graph.information[inter],
            inter_edge=inter, robot_graph=pairs, team=team, intra_vote=vote[intra], inter_vote=vote[inter],
        ))
    return out


def colour_robots(robots: tuple[int, ...], pairs: list[tuple[int, int]]) -> dict[int, int]:
    """Deterministic greedy colouring: adjacent robots get different colours."""
    g = nx.Graph()
    g.add_nodes_from(robots)
    g.add_edges_from(pairs)
    colour: dict[int, int] = {}
    for r in sorted(robots, key=lambda r: (-g.degree[r], r)):
        used = {colour[n] for n in g.neighbors(r) if n in colour}
        colour[r] = next(c for c in range(len(robots) + 1) if c not in used)
    return colour


def component_root(robot: int, robots: tuple[int, ...], pairs: list[tuple[int, int]]) -> int:
    """The lowest id of ``robot``'s connected component of the robot graph: its frame's root."""
    g = nx.Graph()
    g.add_nodes_from(robots)
    g.add_node(robot)
    g.add_edges_from(pairs)
    return int(min(nx.node_connected_component(g, robot)))


def frame_root(robot: int, robots: tuple[int, ...], pairs: list[tuple[int, int]]) -> bool:
    """True when ``robot`` is the lowest id of its connected component of the robot graph."""
    return robot == component_root(robot, robots, pairs)


class PgoAgent(Initialisation, FrameDecision, RobustWeights, Relaxation):
    """One robot's distributed-PGO state and its pure round step (its initialisation, frame
    decision, robust weights and step-size control are the mixins of :mod:`.pgo_init`,
    :mod:`.frame_decision`, :mod:`.pgo_weights` and :mod:`.pgo_relaxation`)."""

    def __init__(self, local: LocalGraph, params: PgoParams | None = None) -> None:
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
        # state
        self.kappa_intra, self.tau_intra = edge_weights(local.intra_info)
        self.kappa_inter, self.tau_inter = edge_weights(local.inter_info)
        self.poses = self._initial_poses()
        # stage: "init" (distributed chordal relaxation) until the leader's start, then "solve"
        self.stage = "init" if p.distributed_init and local.robot_graph else "solve"
        self.solve_from: int | None = None  # round the BCD starts (from the leader's command)
        self.solve_round = 0  # statuses older than this belong to the init stage
        self.start_sent: int | None = None
        self.prev_poses = self.poses.copy()  # previous iterate (momentum)
        self.published = self.poses.copy()  # what neighbours see (extrapolated)
        self.aligned = self.root
        # the frame rests on the root or on >= align_min_places places of settled peers' poses
        # (see :class:`.messages.PublicPoses`); peers' flags, by robot, as last heard
        self.settled = self.root
        self.peer_settled: dict[int, bool] = {}
        self.neighbour_poses: dict[int, np.ndarray] = {}
        self.inter_weights = np.ones(len(local.inter_edge))
        self.intra_weights = np.ones(len(local.intra_edge))
        self.gnc = GncSchedule(tls_threshold(p.inlier_probability, p.tls_dof), mu_step=p.gnc_mu_step)
        self.gnc_pending: int | None = None  # round of a pending weight update
        self.gnc_last_round = 0
        self.mu_proposals: dict[int, float] = {}  # robot -> proposed μ₀ (team-wide GNC)
        self.rechecks = 0
        self.updates = 0
        self.updates_since_weights = 0
        self.ready = False
        self.rel_change = np.inf
        self.cost = 0.0
        self.done = False
        self.wait_rounds = 0
        self.wait_updates = 0
        self.relaxed = 0
        self.omega = 1.0
        self.last_step = 0.0
        self.step_ratios: list[float] = []
        self.recent_steps: list[float] = []  # block steps since the last weight update (divergence check)
        self.gamma = 1.0
        self.last_team_cost = np.inf
        self.statuses: dict[int, PgoStatus] = {}
        self.last_sent_round = -10**9
        self.alignment_inliers: np.ndarray | None = None
        # object landmarks (set by TeamPgo, :meth:`set_landmarks`): own ones anchored to their
        # nearest keyframes, so they move with the estimate; settled peers' by robot
        self.landmark_anchor: np.ndarray | None = None
        self.landmark_offset = np.zeros((0, 3))
        self.landmark_classes = np.zeros(0, dtype=np.int32)
        self.peer_landmarks: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}
        self.screened = False  # robust mode: inter-robot edges checked for consistency
        self.excluded = False  # kept out of the team frame this epoch (see :attr:`alignment`)
        # the poses are already in the team frame (an earlier epoch aligned this robot); set by
        # the epoch runner (TeamPgo); a tie between frame hypotheses then keeps the frame
        self.in_team_frame = False
        # what the frame rests on (JSON-ready): status, hypothesis, support, margin, reason
        self.alignment: dict[str, object] = {"status": "root" if self.root else "unaligned"}
        self._no_peer_rounds = 0
        self._tried = b""  # the known-edge mask of the last alignment attempt
        self._base: gtsam.NonlinearFactorGraph | None = None
        self._parts: dict[int, tuple[float, tuple[gtsam.Pose3, gtsam.noiseModel.Base]]] = {}
        self._values = to_values(local.keys, self.poses)

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
                self.neighbour_poses[int(k)] = np.array(T)
            self.peer_settled[msg.robot] = bool(msg.settled)
        elif isinstance(msg, PgoStatus):
            old = self.statuses.get(msg.robot)
            if old is None or msg.round >= old.round:
                self.statuses[msg.robot] = msg
        elif isinstance(msg, PgoCommand):
            if msg.command == "stop":
                self.done = True
            elif msg.command == "update_weights" and msg.round > self.gnc_last_round:
                self.gnc_pending = msg.round
            elif msg.command == "start" and self.stage == "init" and self.solve_from is None:
                self.solve_from = msg.round
        elif isinstance(msg, GncWeights):
            if msg.peer == msg.robot:  # a μ₀ proposal, for the whole team
                self.mu_proposals[msg.robot] = float(msg.mu)
                return
            if msg.peer != self.robot:
                return
            own_keys = self.local.keys[self.local.inter_own]
            lookup = {(int(a), int(b)): w
                      for a, b, w in zip(msg.keys_b, msg.keys_a, msg.weights, strict=True)}
            for e, (a, b) in enumerate(zip(own_keys, self.local.inter_peer_key, strict=False)):
                w = lookup.get((int(a), int(b)))
                if w is not None:
                    self.inter_weights[e] = float(w)

    # ---------------------------------------------------------------- the step
    def active(self, rnd: int) -> bool:
        return rnd % self.num_colours == self.colour

    def step(self, rnd: int) -> list[Message]:
        """Run round ``rnd``; return the messages to publish."""
        out: list[Message] = []
        if self.done:
            return out
        if not self.aligned:
            self._try_align()
            if not self.aligned:
                out.append(self._status(rnd))
                return out
            out.append(self._public(rnd, self.poses))
        if self.params.robust and not self.screened and self.params.screen != "none":
            self._screen()
        if self.stage == "init" and self.solve_from is not None and rnd >= self.solve_from:
            self._start_solve(rnd)
        if (self.params.robust and self.stage == "solve" and self.gnc_pending is not None
                and rnd >= self.gnc_pending):
            out.extend(self._update_weights(rnd))
        updated = False
        if self.active(rnd) and self._neighbours_known():
            if self.stage == "init":
                self._init_update()
            else:
                self._update(rnd)
            updated = True
        if updated or rnd - self.last_sent_round >= self.params.resend_interval:
            out.append(self._public(rnd, self.published if self.stage == "solve" else self.poses))
        out.append(self._status(rnd))
        if self.robot == self.leader:
            out.extend(self._lead(rnd))
        return out

    def _neighbours_known(self) -> bool:
        """Update only once every neighbour pose is known (or after ``align_patience`` waits):
        a block solved against a partial separator drifts far from the team's solution."""
        if self.updates > 0 or all(int(k) in self.neighbour_poses for k in self.local.inter_peer_key):
            return True
        self.wait_updates += 1
        return self.wait_updates > self.params.align_patience

    def _status(self, rnd: int) -> PgoStatus:
        rel = float(self.rel_change) if np.isfinite(self.rel_change) else 1e300
        # an excluded robot has nothing to converge: it never holds the team up
        return PgoStatus(robot=self.robot, round=rnd, ready=bool((self.ready and self.aligned) or self.excluded),
                         cost=float(self.cost), rel_change=rel)

    def _public(self, rnd: int, poses: np.ndarray) -> PublicPoses:
        self.last_sent_round = rnd
        pub = self.local.public
        return PublicPoses(robot=self.robot, round=rnd, keys=self.local.keys[pub],
                           poses=poses[pub], settled=bool(self.settled and not self.excluded))

    # ---------------------------------------------------------------- local solve
    def _base_graph(self) -> gtsam.NonlinearFactorGraph:
        if self._base is None:
            lg = self.local
            fg = gtsam.NonlinearFactorGraph()
            for e in range(len(lg.intra_i)):
                w = self.intra_weights[e]
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
            w = self.inter_weights[e]
            nb = self.neighbour_poses.get(int(lg.inter_peer_key[e]))
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
        them, so an alias they sit in cannot bend the team frame (aliased_wing, 3 robots, seed 6:
        two robots adopted on their start office, the twin of the root's, rotated the root by
        34°). Once a peer settles, its edges count both ways again, and so do all edges once
        the GNC schedule is over: the re-checks and the final solve are the joint ones, so the
        converged estimate is the team's optimum over the closures GNC kept."""
        p = self.params
        if not (p.robust and p.align_hypotheses and self.settled and not self.excluded) \
                or self.gnc.steps >= p.gnc_max_steps:
            return set()
        return {r for r, ok in self.peer_settled.items() if not ok}

    def _update(self, rnd: int) -> None:
        lg = self.local
        inter = self._inter_graph()
        fg = gtsam.NonlinearFactorGraph(self._base_graph())
        fg.push_back(inter)
        if inter.size() == 0:
            fg.add(gtsam.PriorFactorPose3(int(lg.keys[0]), to_gtsam(self.poses[0]),
                                          gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(self.params.lm_iterations)
        lm.setRelativeErrorTol(self.params.lm_rel_tol)
        lm.setAbsoluteErrorTol(0.0)
        values = gtsam.LevenbergMarquardtOptimizer(fg, self._values, lm).optimize()
        new = _poses_of(values)
        change = np.sqrt(np.sum((new - self.poses) ** 2) / max(np.sum(self.poses**2), 1e-300))
        self.rel_change = float(change)
        self.ready = self.rel_change < self.params.rel_tol and self.updates_since_weights > 0
        omega = self._omega(float(np.sqrt(np.sum((new - self.poses) ** 2))))
        if omega != 1.0 and self.updates_since_weights > 0:
            # block over-relaxation: on a quadratic cost X ⊕ ω(X* ⊖ X) lowers the cost by
            # ω(2−ω) times the exact step's decrease; kept only when it does lower it here
            relaxed = extrapolate(new, self.poses, omega - 1.0)
            relaxed_values = to_values(lg.keys, relaxed)
            if fg.error(relaxed_values) <= fg.error(self._values):
                new, values = relaxed, relaxed_values
                self.relaxed += 1
            else:
                self.omega = 1.0 + 0.5 * (self.omega - 1.0)
                self.step_ratios.clear()
        self.cost = float(self._base_graph().error(values) + 0.5 * inter.error(values))
        # Nesterov momentum on what neighbours see; restart on a team cost rise or interval
        self.updates += 1
        self.updates_since_weights += 1
        if self.params.acceleration and self._should_restart():
            self.gamma = 1.0
        if self.params.acceleration:
            gamma_next = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * self.gamma**2))
            beta = (self.gamma - 1.0) / gamma_next
            self.gamma = gamma_next
            self.published = extrapolate(new, self.poses, beta)
        else:
            self.published = new
        self.prev_poses = self.poses
        self.poses = new
        self._values = values

    def _solve_alone(self) -> np.ndarray:
        """The robot's own graph alone (odometry and the intra-robot closures GNC kept), its
        first pose held."""
        lg = self.local
        fg = gtsam.NonlinearFactorGraph(self._base_graph())
        fg.add(gtsam.PriorFactorPose3(int(lg.keys[0]), to_gtsam(self.poses[0]),
                                      gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        values = gtsam.LevenbergMarquardtOptimizer(fg, to_values(lg.keys, self.poses)).optimize()
        return _poses_of(values)

    # ---------------------------------------------------------------- leader
    def _lead(self, rnd: int) -> list[Message]:
        p = self.params
        if self.stage == "init" or self.start_sent is not None:
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

    def _stop(self, rnd: int) -> list[Message]:
        cmd = PgoCommand(robot=self.robot, round=rnd, command="stop",
                         active=np.zeros(0, dtype=np.int64))
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
