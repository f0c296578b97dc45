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

Initialisation: a robot starts from its own odometry (or its local chordal solution) in its own
frame; the lowest id of each connected robot graph is the team frame; the others align to an
aligned neighbour by GNC rotation + translation averaging over the inter-robot edges
(:mod:`.alignment`). A robot publishes public poses only once aligned, so late joiners and
robots without inter-robot edges simply wait (their edges are ignored by the others meanwhile).
Optionally (``distributed_init``) the team first runs block Gauss–Seidel on the chordal
relaxation (:mod:`.chordal`) until every robot has settled; the leader then sends ``start``.

Robust frame alignment (``align_hypotheses``, issue 11): the known inter-robot edges are
clustered into frame hypotheses (:func:`.alignment.frame_hypotheses`), each supported by the
number of distinct places its closures come from, over every neighbour at once. A robot adopts
the hypothesis that leads the runner-up by ``align_min_margin`` places and rests on at least
``align_min_places``; a lone single-place group with no competitor is adopted only once no
more edges can arrive, and reported as such. Otherwise the robot stays out of the team frame for
the epoch (own frame, inter-robot weights 0, ready so nobody waits) and says so in
:attr:`PgoAgent.alignment` and the log. Every epoch builds a fresh agent, so the decision is
revisited as closures accumulate: a robot aligned into an alias frame switches once the true
hypothesis leads. Edges outside the adopted hypothesis start at weight 0. At the end of an
epoch (:meth:`PgoAgent.final_poses`) an estimate that bends away from the robot's own odometry
beyond its drift model (:func:`.alignment.odometry_disagreement`) is not adopted either.

Robust mode: GNC-TLS weights (:mod:`.robust`) on loop closures and inter-robot edges (odometry
is trusted). The lowest robot id is the leader: it sends ``update_weights`` when every robot is
ready (or after a round cap) and ``stop`` when the team is done. GNC runs with *one* ``μ`` for
the team, as the centralised GNC does: at the first update every robot publishes its ``μ₀``
(a :class:`GncWeights` to itself, no edges) and all apply the smallest a few rounds later;
with per-robot ``μ₀`` a robot whose residuals happen to be small starts near-binary and locks
in aliased closures (structured outliers from identical places, which fit the least-squares
solution). Inter-robot edges start screened only against random outliers (an edge no other
edge agrees with); every mutually consistent group, true or aliased, is left to the joint
GNC, since for one robot pair the aliased group can be as large as the true one. After the GNC schedule, the
edges are re-decided at the converged solution with the plain TLS threshold (first with
``recheck_factor`` slack, since a dropped inlier is biased high while it is left out). An
inter-robot edge's weight is computed by its lower-id robot and shared in :class:`GncWeights`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import gtsam
import networkx as nx
import numpy as np

from kimera_multi_py.comms.messages import GncWeights, Message, PgoCommand, PgoStatus, PublicPoses
from kimera_multi_py.consensus.alignment import (
    Alignment,
    FrameHypothesis,
    align_frames,
    decide,
    frame_hypotheses,
    odometry_disagreement,
    supported_edges,
)
from kimera_multi_py.consensus.chordal import chordal_block, chordal_poses, edge_weights
from kimera_multi_py.consensus.factors import between, fixed_neighbour, residuals_sq, to_values
from kimera_multi_py.consensus.robust import GncSchedule, tls_threshold
from kimera_multi_py.consensus.server import chordal_initialization
from kimera_multi_py.geometry import inverse, so3_exp, so3_log, to_gtsam
from kimera_multi_py.io.pose_graph import INTER_ROBOT, ODOMETRY, PoseGraph, robot_key

log = logging.getLogger(__name__)


@dataclass
class PgoParams:
    """Knobs of the distributed solver (defaults tuned on the DPGO benchmark graphs)."""

    max_rounds: int = 500
    rel_tol: float = 1e-8  # ready when the relative pose change of an update is below this
    lm_iterations: int = 20  # per local solve (warm-started; usually 1-3 are used)
    lm_rel_tol: float = 1e-10
    chordal_init: bool = True  # local chordal initialisation (else the robot's odometry)
    acceleration: bool = False  # Nesterov momentum on published poses (measured: SOR is better)
    # block SOR: publish X ⊕ ω(X* ⊖ X). None adapts ω per robot (Young's estimate from the
    # ratio of successive block steps); a number fixes it (1.0: plain Gauss–Seidel)
    over_relaxation: float | None = None
    max_over_relaxation: float = 1.98
    restart_interval: int = 50  # momentum restart every this many updates (besides on cost rise)
    resend_interval: int = 5  # re-publish unchanged public poses this often (message loss)
    robust: bool = False
    inlier_probability: float = 0.999  # χ²₆ quantile of the TLS threshold c̄² (22.5)
    tls_dof: int = 6  # degrees of freedom of that χ² (3 for a planar, 2-D graph)
    gnc_round_cap: int = 10  # rounds between weight updates at most
    # robust: which inter-robot edges start at weight 0 (GNC revisits them): "support" those no
    # other edge agrees with (random outliers; every consistent group stays for the joint GNC),
    # "alignment" those outside the alignment's majority hypothesis, "none"
    screen: str = "support"
    gnc_mu0_trusted: bool = True  # μ₀ from the largest residual of the current inliers only
    # one μ for the team: robots propose their μ₀ and apply the smallest this many rounds later
    gnc_team_mu: bool = True
    gnc_mu_delay: int = 3
    # ceiling of μ₀: start at least this convex. μ₀ from the current residuals is too large when
    # the start already sits in an aliased hypothesis (a warm restart after a wrong solve: the
    # aliased closures fit, so GNC starts near-binary and keeps them; gtsam's GNC takes μ₀ from
    # the initial values' residuals, usually far larger). Measured on the office graphs.
    gnc_mu0_max: float = 1e-3
    gnc_max_steps: int = 40
    gnc_rechecks: int = 2  # after GNC: re-decide every edge at the converged solution (χ² test)
    recheck_factor: float = 3.0  # first re-check admits r² ≤ factor·c̄², the last one r² ≤ c̄²
    align_patience: int = 20  # rounds with < 3 alignment inliers before a plain alignment
    # robust mode: frame alignment by hypotheses (alignment.frame_hypotheses). A robot aligns to
    # the hypothesis supported by the most distinct places, when it leads the runner-up by
    # ``align_min_margin`` places and rests on ``align_min_places`` or more; it decides before
    # every neighbour pose is known only with a lead of ``align_early_margin``. A robot with no
    # such hypothesis stays out of the team frame for the epoch (its own frame, edges off).
    align_hypotheses: bool = True
    align_min_places: int = 2
    align_min_margin: int = 1
    align_early_margin: int = 1
    # no hypothesis leads when the epoch's evidence is in: "consensus" aligns by the robust
    # consensus of every edge and leaves the choice to GNC; "exclude" keeps the robot out of the
    # team frame (its own frame) for the epoch
    align_tie: str = "consensus"
    place_radius: float = 2.0  # m: own closure poses closer than this are one place
    # safety: an estimate that bends away from the robot's own odometry beyond its drift model
    # (odometry_disagreement > 1) is not adopted; the robot falls back to its own frame
    drift_check: bool = True
    drift_z: float = 4.0
    drift_floor: float = 0.5  # m
    # chordal block Gauss–Seidel over the team before the BCD (measured: no faster on the
    # benchmark graphs, worse on cubicle whose chordal relaxation is poor; off by default)
    distributed_init: bool = False
    init_rel_tol: float = 1e-3  # an initialising robot is ready below this relative change
    init_max_rounds: int = 40  # the leader starts the BCD after this many rounds at most
    start_resend: int = 5  # the leader repeats ``start`` this many rounds (message loss)


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


def split_local(graph: PoseGraph, frames: str = "own") -> list[LocalGraph]:
    """Each robot's :class:`LocalGraph`; ``frames="own"`` re-expresses a robot's initial values
    relative to its first pose (robots do not share a frame), ``"given"`` keeps them."""
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
            inter_edge=inter, robot_graph=pairs, team=team,
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


def frame_root(robot: int, robots: tuple[int, ...], pairs: list[tuple[int, int]]) -> bool:
    """True when ``robot`` is the lowest id of its connected component of the robot graph."""
    g = nx.Graph()
    g.add_nodes_from(robots)
    g.add_edges_from(pairs)
    return robot == min(nx.node_connected_component(g, robot))


class PgoAgent:
    """One robot's distributed-PGO state and its pure round step."""

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
        self.root = frame_root(self.robot, team, local.robot_graph)
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
        self.neighbour_poses: dict[int, np.ndarray] = {}
        self.inter_weights = np.ones(len(local.inter_edge))
        self.intra_weights = np.ones(len(local.intra_edge))
        self.gnc = GncSchedule(tls_threshold(p.inlier_probability, p.tls_dof))
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
        self.gamma = 1.0
        self.last_team_cost = np.inf
        self.statuses: dict[int, PgoStatus] = {}
        self.last_sent_round = -10**9
        self.alignment_inliers: np.ndarray | None = None
        self.screened = False  # robust mode: inter-robot edges checked for consistency
        self.excluded = False  # kept out of the team frame this epoch (see :attr:`alignment`)
        # what the frame rests on (JSON-ready): status, hypothesis, support, margin, reason
        self.alignment: dict[str, object] = {"status": "root" if self.root else "unaligned"}
        self._no_peer_rounds = 0
        self._tried = b""  # the known-edge mask of the last alignment attempt
        self._base: gtsam.NonlinearFactorGraph | None = None
        self._values = to_values(local.keys, self.poses)

    # ---------------------------------------------------------------- initialisation
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

    def _try_align(self) -> None:
        """Align to the team frame from inter-robot edges whose other end is known."""
        lg = self.local
        known = np.array([int(k) in self.neighbour_poses for k in lg.inter_peer_key], dtype=bool)
        if not known.any():
            self._no_peer_rounds += 1
            if self.params.robust and self.params.align_hypotheses and \
                    self._no_peer_rounds > 2 * self.params.align_patience:
                self._exclude("no aligned neighbour", None, 0)
            return
        if self.params.robust and self.params.align_hypotheses:
            self._align_hypothesis(known)
            return
        nb = np.stack([self.neighbour_poses[int(k)] for k in lg.inter_peer_key[known]])
        res = align_frames(self.poses[lg.inter_own[known]], nb, lg.inter_meas[known],
                           lg.inter_own_is_i[known])
        self.wait_rounds += 1
        everything = bool(known.all())  # no further edge can arrive
        if not res.ok and not everything and self.wait_rounds < self.params.align_patience:
            return
        self._adopt_consensus(known, res)

    def _align_consensus(self, known: np.ndarray) -> None:
        """Align by the robust consensus of every known edge (:func:`.alignment.align_frames`)."""
        lg = self.local
        nb = np.stack([self.neighbour_poses[int(k)] for k in lg.inter_peer_key[known]])
        res = align_frames(self.poses[lg.inter_own[known]], nb, lg.inter_meas[known], lg.inter_own_is_i[known])
        self._adopt_consensus(known, res)
        self.alignment = {"status": "aligned", "support": int(res.inliers.sum()), "edges": int(res.inliers.sum()),
                          "margin": 0, "hypotheses": 0, "peers": sorted(set(lg.inter_peer[known].tolist())),
                          "hypothesis": np.round(res.T, 4).tolist(), "reason": "consensus of all edges"}

    def _adopt_consensus(self, known: np.ndarray, res: Alignment) -> None:
        lg = self.local
        if not res.ok:
            log.warning("robot %d: aligning with only %d consistent inter-robot edges",
                        self.robot, int(res.inliers.sum()))
        T = res.T
        self.poses = T @ self.poses
        self.prev_poses = self.poses.copy()
        self.published = self.poses.copy()
        self._values = to_values(lg.keys, self.poses)
        inliers = np.zeros(len(lg.inter_edge), dtype=bool)
        inliers[np.flatnonzero(known)[res.inliers]] = True
        self.alignment_inliers = inliers
        self.aligned = True
        self.excluded = False
        if self.params.robust and self.params.screen != "none":
            # edges the screen rejects start as outliers; GNC revisits them
            keep = inliers if self.params.screen == "alignment" else self._supported(known)
            self.inter_weights = np.where(known & ~keep, 0.0, 1.0)
        self.screened = bool(known.all())
        log.info("robot %d aligned with %d/%d inter-robot edges", self.robot,
                 int(inliers.sum()), int(known.sum()))

    def _hypotheses(self, known: np.ndarray) -> list[FrameHypothesis]:
        """Frame hypotheses of the known inter-robot edges (edge indices into the local graph)."""
        lg = self.local
        idx = np.flatnonzero(known)
        nb = np.stack([self.neighbour_poses[int(k)] for k in lg.inter_peer_key[idx]])
        hyps = frame_hypotheses(self.poses[lg.inter_own[idx]], nb, lg.inter_meas[idx], lg.inter_own_is_i[idx],
                                lg.inter_peer[idx], place_radius=self.params.place_radius)
        for h in hyps:
            h.edges = idx[h.edges]
        return hyps

    def _align_hypothesis(self, known: np.ndarray) -> None:
        """Robust alignment: adopt the frame hypothesis that clearly leads (module docstring)."""
        p = self.params
        lg = self.local
        self.wait_rounds += 1
        signature = known.tobytes()
        if self.excluded and signature == self._tried:
            return  # nothing new to decide on
        self._tried = signature
        hyps = self._hypotheses(known)
        best, margin = decide(hyps, p.align_min_places, p.align_min_margin)
        final = bool(known.all()) or self.wait_rounds >= p.align_patience
        if best is None and final and (not hyps or hyps[0].size < 3):
            # no group of mutually consistent edges at all (sparse or noisy edges, not
            # aliasing): the plain robust consensus of every edge decides
            self._align_consensus(known)
            return
        sole = bool(hyps) and margin == hyps[0].places and hyps[0].size >= 3
        if best is None and final and sole:
            # one group and no competitor: nothing to tell an alias from here; adopted, and
            # reported as resting on one place (the drift check and later epochs revisit it)
            best = hyps[0]
        if best is None and final and p.align_tie == "consensus":
            # competing hypotheses and none leads: the robust consensus of every edge aligns the
            # robot and the team's GNC decides between the groups; the report says it was a tie
            self._align_consensus(known)
            self.alignment.update(reason="no frame hypothesis leads: consensus of every edge", margin=int(margin),
                                  competitors=_competitors(hyps))
            return
        if best is None or (not final and margin < p.align_early_margin):
            if final:
                self._exclude("no frame hypothesis leads", hyps[0] if hyps else None, margin, hyps)
            return
        T = best.T
        self.poses = T @ self.poses
        self.prev_poses = self.poses.copy()
        self.published = self.poses.copy()
        self._values = to_values(lg.keys, self.poses)
        inliers = np.zeros(len(lg.inter_edge), dtype=bool)
        inliers[best.edges] = True
        # in the new frame, every group at the identity agrees with the chosen hypothesis
        # (a true group split by drift over long lever arms is re-joined)
        for h in self._hypotheses(known):
            if _near_identity(h.T):
                inliers[h.edges] = True
        self.alignment_inliers = inliers
        self.aligned = True
        self.excluded = False
        # edges outside the hypothesis start as outliers; GNC and its rechecks revisit them
        self.inter_weights = np.where(known & ~inliers, 0.0, 1.0)
        self.screened = bool(known.all())
        self.alignment = self._report("aligned", best, margin, len(hyps))
        log.info("robot %d aligned: %d edges from %d places (margin %d over %d other hypotheses)", self.robot,
                 best.size, best.places, margin, len(hyps) - 1)

    def _report(self, status: str, h: FrameHypothesis | None, margin: int, hypotheses: int,
                reason: str = "") -> dict[str, object]:
        out: dict[str, object] = {"status": status, "support": h.places if h is not None else 0,
                                  "edges": h.size if h is not None else 0, "margin": int(margin),
                                  "hypotheses": int(hypotheses),
                                  "peers": list(h.peers) if h is not None else [],
                                  "hypothesis": np.round(h.T, 4).tolist() if h is not None else None}
        if reason:
            out["reason"] = reason
        return out

    def _exclude(self, reason: str, h: FrameHypothesis | None, margin: int,
                 hyps: list[FrameHypothesis] | None = None) -> None:
        """Stay out of the team frame this epoch: no alignment, inter-robot edges off."""
        if self.excluded:
            return
        self.excluded = True
        self.inter_weights[:] = 0.0
        self.alignment = self._report("excluded", h, margin, len(hyps or []), reason)
        # every competing hypothesis: distinct places, edges, peers, and where it moves the robot's origin
        self.alignment["competitors"] = _competitors(hyps or [])
        log.warning("robot %d: kept out of the team frame (%s; best support %d places, margin %d)", self.robot,
                    reason, h.places if h is not None else 0, margin)

    def _screen(self) -> None:
        """Robust mode, aligned robot: start inconsistent inter-robot edges at weight 0.

        The same GNC rotation/translation consensus as the alignment (whose transform should
        now be the identity) flags the edges that disagree with the majority; GNC revisits them.
        """
        lg = self.local
        known = np.array([int(k) in self.neighbour_poses for k in lg.inter_peer_key], dtype=bool)
        self.wait_rounds += 1
        if not known.any() or (not known.all() and self.wait_rounds < self.params.align_patience):
            return
        hyps = self._hypotheses(known) if self.params.align_hypotheses else []
        here = [h for h in hyps if _near_identity(h.T)]
        if here:
            # already in the team frame: keep the hypothesis at the identity, the rest start at 0
            keep = np.zeros(len(lg.inter_edge), dtype=bool)
            for h in here:
                keep[h.edges] = True
            self.inter_weights = np.where(known & ~keep, 0.0, 1.0)
            self.screened = True
            if self.root and here:
                others = [h.places for h in hyps if not _near_identity(h.T)]
                self.alignment = self._report("root", here[0], here[0].places - max(others, default=0), len(hyps))
            return
        if self.params.screen == "support":
            self.inter_weights = np.where(known & ~self._supported(known), 0.0, 1.0)
            self.screened = True
            return
        nb = np.stack([self.neighbour_poses[int(k)] for k in lg.inter_peer_key[known]])
        res = align_frames(self.poses[lg.inter_own[known]], nb, lg.inter_meas[known],
                           lg.inter_own_is_i[known])
        if res.ok:
            inliers = np.zeros(len(lg.inter_edge), dtype=bool)
            inliers[np.flatnonzero(known)[res.inliers]] = True
            self.inter_weights = np.where(known & ~inliers, 0.0, 1.0)
            self.alignment_inliers = inliers
        self.screened = True

    def _supported(self, known: np.ndarray) -> np.ndarray:
        """The known inter-robot edges some other known edge agrees with (own poses in the team
        frame), see :func:`.alignment.supported_edges`."""
        lg = self.local
        out = np.zeros(len(lg.inter_edge), dtype=bool)
        if known.any():
            nb = np.stack([self.neighbour_poses[int(k)] for k in lg.inter_peer_key[known]])
            out[known] = supported_edges(self.poses[lg.inter_own[known]], nb, lg.inter_meas[known],
                                         lg.inter_own_is_i[known])
        return out

    # ---------------------------------------------------------------- messages in
    def handle(self, msg: Message) -> None:
        """Absorb one message from another robot (or an own command)."""
        if isinstance(msg, PublicPoses):
            if msg.robot == self.robot:
                return
            for k, T in zip(msg.keys.tolist(), msg.poses, strict=False):
                self.neighbour_poses[int(k)] = np.array(T)
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
                           poses=poses[pub])

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
        for e in range(len(lg.inter_edge)):
            w = self.inter_weights[e]
            nb = self.neighbour_poses.get(int(lg.inter_peer_key[e]))
            if w <= 0 or nb is None:
                continue
            fg.add(fixed_neighbour(lg.keys[lg.inter_own[e]], bool(lg.inter_own_is_i[e]), nb,
                                   lg.inter_meas[e], lg.inter_info[e], w))
        return fg

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
            relaxed = _extrapolate(new, self.poses, omega - 1.0)
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
            self.published = _extrapolate(new, self.poses, beta)
        else:
            self.published = new
        self.prev_poses = self.poses
        self.poses = new
        self._values = values

    def _omega(self, step: float) -> float:
        """The over-relaxation factor for this update.

        Adaptive (Hageman & Young): the ratio ``λ`` of successive exact block steps estimates
        the iteration's contraction; at ``ω = 1`` it is ``ρ_GS = ρ_J²``, above it
        ``ρ_J² = (λ + ω − 1)² / (λω²)`` while ``λ > ω − 1``; then ``ω ← 2 / (1 + √(1 − ρ_J²))``
        (only upwards; a rejected relaxed step halves ``ω − 1``).
        """
        p = self.params
        if p.acceleration:
            return 1.0  # momentum on top of over-relaxation diverges (measured on tinyGrid3D)
        if p.over_relaxation is not None:
            return p.over_relaxation
        if self.last_step > 0 and self.updates_since_weights > 1:
            self.step_ratios.append(step / self.last_step)
        self.last_step = step
        if len(self.step_ratios) >= 3:
            lam = float(np.median(self.step_ratios[-3:]))
            w = self.omega
            rho_j2 = None
            if lam < 1.0 and w == 1.0:
                rho_j2 = lam
            elif lam < 1.0 and lam > w - 1.0:
                rho_j2 = (lam + w - 1.0) ** 2 / (lam * w * w)
            if rho_j2 is not None and rho_j2 < 1.0:
                new_w = min(2.0 / (1.0 + np.sqrt(1.0 - rho_j2)), p.max_over_relaxation)
                if new_w > w + 1e-3:
                    self.omega = new_w
                    self.step_ratios.clear()
        return self.omega

    def _should_restart(self) -> bool:
        if self.updates % self.params.restart_interval == 0:
            return True
        if len(self.statuses) < len(self.team) - 1:
            return False
        team_cost = self.cost + sum(s.cost for r, s in self.statuses.items() if r != self.robot)
        rise = team_cost > self.last_team_cost
        self.last_team_cost = team_cost
        return bool(rise)

    def final_poses(self) -> np.ndarray:
        """The poses to adopt at the end of the epoch.

        Robust mode also settles the safety property here: a robot that never aligned (or that
        was excluded) returns its estimate in its own frame (first pose at the identity) with
        every inter-robot weight 0; an estimate that disagrees with the robot's own odometry
        beyond its drift model is not adopted either (the robot's own solution is).
        """
        if not self.params.robust:
            return self.poses
        lg = self.local
        known = np.array([int(k) in self.neighbour_poses for k in lg.inter_peer_key], dtype=bool)
        self.inter_weights[~known] = 0.0
        if not self.aligned and not self.excluded:
            self._exclude("not aligned when the epoch ended", None, 0)
        if self.params.drift_check and not self.excluded:
            ratio = self._odometry_disagreement()
            self.alignment["drift_ratio"] = round(ratio, 3)
            if ratio > 1.0:
                log.warning("robot %d: estimate disagrees with its odometry (%.2f x its drift model)",
                            self.robot, ratio)
                self._exclude(f"estimate disagrees with odometry ({ratio:.2f} x drift model)", None, 0)
                self.alignment["drift_ratio"] = round(ratio, 3)
                self.poses = self._own_solution()
        if self.excluded:
            return inverse(self.poses[0]) @ self.poses
        return self.poses

    def _odometry_chain(self) -> tuple[np.ndarray, float, float]:
        """Dead reckoning from the odometry edges (first pose at the identity) and its sigmas."""
        lg = self.local
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

    def _odometry_disagreement(self) -> float:
        D, s_rot, s_trans = self._odometry_chain()
        return odometry_disagreement(self.poses, D, s_rot, s_trans, self.params.drift_z, self.params.drift_floor)

    def _own_solution(self) -> np.ndarray:
        """The robot's own graph alone (odometry and the intra-robot closures GNC kept)."""
        lg = self.local
        fg = gtsam.NonlinearFactorGraph(self._base_graph())
        fg.add(gtsam.PriorFactorPose3(int(lg.keys[0]), to_gtsam(self.poses[0]),
                                      gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
        values = gtsam.LevenbergMarquardtOptimizer(fg, to_values(lg.keys, self.poses)).optimize()
        own = _poses_of(values)
        D, s_rot, s_trans = self._odometry_chain()
        if odometry_disagreement(own, D, s_rot, s_trans, self.params.drift_z, self.params.drift_floor) > 1.0:
            self.intra_weights[~lg.intra_odometry] = 0.0  # its own closures bend it too: dead reckoning
            return self.poses[0] @ D
        return own

    # ---------------------------------------------------------------- robust weights
    def _update_weights(self, rnd: int) -> list[Message]:
        lg = self.local
        p = self.params
        if p.gnc_team_mu and self.gnc.steps == 0 and self.robot not in self.mu_proposals:
            return self._propose_mu(rnd)
        self.gnc_last_round = self.gnc_pending or rnd
        self.gnc_pending = None
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
        self.intra_weights[loop] = w[: len(loop)]
        self.inter_weights[inter] = w[len(loop):]
        self._base = None
        self.updates_since_weights = 0
        self.ready = False
        self.gamma = 1.0
        out: list[Message] = []
        for peer in lg.neighbours:
            sel = inter[lg.inter_peer[inter] == peer]
            if len(sel) == 0:
                continue
            out.append(GncWeights(robot=self.robot, peer=int(peer), round=rnd,
                                  keys_a=lg.keys[lg.inter_own[sel]],
                                  keys_b=lg.inter_peer_key[sel],
                                  weights=self.inter_weights[sel], mu=self.gnc.mu))
        return out

    def _robust_r2(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Squared residuals of the robust edges this robot decides (its loop closures and the
        inter-robot edges it owns, where the other end is known), and which are inliers now:
        ``(r2, trusted, loop edges, owned inter edges)``."""
        lg = self.local
        loop = np.flatnonzero(~lg.intra_odometry)
        known = np.array([int(k) in self.neighbour_poses for k in lg.inter_peer_key], dtype=bool)
        inter = np.flatnonzero((lg.inter_peer > self.robot) & known)
        r2 = np.concatenate([self._intra_r2(loop), self._inter_r2(inter)])
        trusted = np.concatenate([self.intra_weights[loop] > 0.5, self.inter_weights[inter] > 0.5])
        return r2, trusted, loop, inter

    def _initial_mu(self, r2: np.ndarray, trusted: np.ndarray) -> float:
        """This robot's ``μ₀``: from its largest (trusted) residual, at most ``gnc_mu0_max``."""
        p = self.params
        return min(self.gnc.initial_mu(r2, trusted if p.gnc_mu0_trusted else None), p.gnc_mu0_max)

    def _propose_mu(self, rnd: int) -> list[Message]:
        """First GNC step, team-wide ``μ₀``: publish this robot's ``μ₀`` (from its largest
        residual) and apply the team's smallest proposal ``gnc_mu_delay`` rounds later.

        Per-robot ``μ₀`` breaks GNC: a robot whose own residuals are small starts almost binary
        and locks in the (outlier-biased) least-squares decisions (measured on the office
        graph: 35 aliased closures kept; with one team ``μ`` none)."""
        r2, trusted, _, _ = self._robust_r2()
        mu0 = self._initial_mu(r2, trusted)
        self.mu_proposals[self.robot] = mu0
        self.gnc_pending = rnd + self.params.gnc_mu_delay
        empty_k = np.zeros(0, dtype=np.int64)
        return [GncWeights(robot=self.robot, peer=self.robot, round=rnd, keys_a=empty_k,
                           keys_b=empty_k, weights=np.zeros(0), mu=mu0)]

    def _intra_r2(self, edges: np.ndarray) -> np.ndarray:
        lg = self.local
        sub = PoseGraph(poses=self.poses, robot=np.zeros(len(self.poses), dtype=int),
                        local=np.arange(len(self.poses)), ids=np.arange(len(self.poses)),
                        edge_i=lg.intra_i[edges], edge_j=lg.intra_j[edges],
                        measurement=lg.intra_meas[edges], information=lg.intra_info[edges])
        return residuals_sq(sub, self.poses)

    def _inter_r2(self, edges: np.ndarray) -> np.ndarray:
        lg = self.local
        out = np.zeros(len(edges))
        for n, e in enumerate(edges):
            own = self.poses[lg.inter_own[e]]
            nb = self.neighbour_poses[int(lg.inter_peer_key[e])]
            Xi, Xj = (own, nb) if lg.inter_own_is_i[e] else (nb, own)
            err = gtsam.Pose3.Logmap(to_gtsam(lg.inter_meas[e]).inverse()
                                     * to_gtsam(Xi).inverse() * to_gtsam(Xj))
            out[n] = err @ lg.inter_info[e] @ err
        return out

    def weights_binary(self) -> bool:
        return GncSchedule.binary(self.inter_weights) and GncSchedule.binary(self.intra_weights)

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
            since = rnd - self.gnc_last_round
            if self.gnc.steps >= p.gnc_max_steps:
                if self.rechecks >= p.gnc_rechecks:
                    return self._stop(rnd) if all_ready else []
                if not (all_ready or since >= 5 * p.gnc_round_cap) or self.gnc_pending is not None:
                    return []
                cmd = PgoCommand(robot=self.robot, round=rnd + 1, command="update_weights",
                                 active=np.array(self.team, dtype=np.int64))
                self.handle(cmd)
                return [cmd]
            if (all_ready or since >= p.gnc_round_cap) and self.gnc_pending is None:
                cmd = PgoCommand(robot=self.robot, round=rnd + 1, command="update_weights",
                                 active=np.array(self.team, dtype=np.int64))
                self.handle(cmd)
                return [cmd]
            return []
        return self._stop(rnd) if all_ready else []

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

    def _stop(self, rnd: int) -> list[Message]:
        cmd = PgoCommand(robot=self.robot, round=rnd, command="stop",
                         active=np.zeros(0, dtype=np.int64))
        self.handle(cmd)
        return [cmd]


def _competitors(hyps: list[FrameHypothesis]) -> list[list[object]]:
    """JSON-ready summary of frame hypotheses: ``[places, edges, peers, translation]`` each."""
    return [[h.places, h.size, list(h.peers), np.round(h.T[:3, 3], 2).tolist()] for h in hyps]


def _near_identity(T: np.ndarray, max_trans: float = 1.0, max_rot: float = 0.2) -> bool:
    """A frame hypothesis that is (within alignment tolerance) no change of frame."""
    return bool(np.linalg.norm(T[:3, 3]) <= max_trans and np.linalg.norm(so3_log(T[None, :3, :3])[0]) <= max_rot)


def _poses_of(values: gtsam.Values) -> np.ndarray:
    """Poses of a Values in key order as ``(n, 4, 4)`` (keys are one robot's, so in order)."""
    flat = gtsam.utilities.extractPose3(values)
    T = np.zeros((len(flat), 4, 4))
    T[:, :3, :3] = flat[:, :9].reshape(-1, 3, 3)
    T[:, :3, 3] = flat[:, 9:]
    T[:, 3, 3] = 1.0
    return T


def _extrapolate(new: np.ndarray, old: np.ndarray, beta: float) -> np.ndarray:
    """``new ⊕ β·(new ⊖ old)`` per pose (rotation on the right, translation added):
    Nesterov extrapolation on SE(3) with the decoupled retraction."""
    if beta <= 0:
        return new
    rot = so3_log(np.swapaxes(old[:, :3, :3], 1, 2) @ new[:, :3, :3])
    out = new.copy()
    out[:, :3, :3] = new[:, :3, :3] @ so3_exp(beta * rot)
    out[:, :3, 3] = new[:, :3, 3] + beta * (new[:, :3, 3] - old[:, :3, 3])
    return out


