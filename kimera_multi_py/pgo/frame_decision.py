"""Frame decision of one distributed-PGO robot: which team frame it joins, and whether its
estimate is adopted at the end of the epoch (docs/algorithms/pgo.md).

Plain alignment: the lowest id of each connected robot graph is the team frame; the others align
to an aligned neighbour by GNC rotation + translation averaging over the inter-robot edges
(:mod:`.alignment`). A robot publishes public poses only once aligned.

Robust frame alignment (``align_hypotheses``): the known inter-robot edges are
clustered into frame hypotheses (:func:`.alignment.frame_hypotheses`), each supported by the
number of distinct places its closures come from, over every neighbour at once. A robot adopts
the hypothesis that leads the runner-up by ``align_min_margin`` places (twice the runner-up's
places, or twice the places only the runner-up explains, when it rests on several:
:func:`.alignment.decide`) and rests on at least
``align_min_places``. Settled frames (:class:`~kimera_multi_py.comms.messages.pgo.PublicPoses`): the
robot decides on settled peers' edges first; the rest decide only what those leave open, and evidence that leads
to two frames (settled peers against the rest, or two settled peers against each other) is
contested, no decision (:func:`.alignment.settled_decision`). A lone single-place group with no
competitor (one room seen by both robots, which an alias looks exactly like) is adopted once no
more edges can arrive, and reported as such (not settled); ``align_lone_place=False`` keeps the
robot out until a second place agrees. Where closures leave groups of several places competing
(twin rooms: the truth and the frame one room over rest on as many places, or closures through
different peers lead to different frames), the team's object
landmarks may decide (:mod:`.landmark_check`; settled peers publish theirs as
:class:`~kimera_multi_py.comms.messages.pgo.FrameLandmarks` when an epoch opens): adopted when they
clearly favour one hypothesis, reported as such and not settled. Without such a hypothesis the
robot stays out of the team frame for the epoch (own frame, inter-robot weights 0, ready so nobody waits) and says so in
:attr:`FrameDecision.alignment` and the log. A robot already in a settled team frame switches frames
only once every neighbour's poses are known (or patience ran out): at an epoch's start only the
root has published. Every epoch builds a fresh agent, so the decision is revisited as closures
accumulate: a robot aligned into an alias frame switches once the true hypothesis leads. Edges
outside the adopted hypothesis start at weight 0. At the end of an epoch
(:meth:`FrameDecision.final_poses`) an estimate that bends away from the robot's own odometry beyond
its drift model (:func:`.alignment.odometry_disagreement`) is not adopted either.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from kimera_multi_py.alignment.evidence import hypothesis_evidence
from kimera_multi_py.alignment.frames import (
    KEEP_M,
    SAME_FRAME_M,
    Alignment,
    FrameHypothesis,
    align_frames,
    frame_hypotheses,
    near_identity,
    settled_decision,
    supported_edges,
    unrefuted_rivals,
)
from kimera_multi_py.alignment.landmark_check import LandmarkScore, landmark_lead, landmark_scores
from kimera_multi_py.alignment.map_check import MapAgreement, frame_key
from kimera_multi_py.core.geometry import inverse
from kimera_multi_py.pgo.drift_check import odometry_ratio, own_solution
from kimera_multi_py.pgo.local_graph import LocalGraph
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.pgo.state import SolveState

log = logging.getLogger(__name__)


class FrameDecision:
    """The frame-alignment part of :class:`.agent.PgoAgent`: align, screen, exclude, settle.

    It moves the shared estimate into the team frame and starts the inter-robot edges the frame
    does not rest on at weight 0 (:class:`~.state.SolveState`). ``root_robot`` is the root of the
    robot's team frame (the robot itself: it is the team frame); ``in_team_frame``: its poses
    are already in the team frame (an earlier epoch aligned it), so a tie between frame
    hypotheses keeps the frame.
    """

    def __init__(self, local: LocalGraph, params: PgoParams, state: SolveState, root_robot: int,
                 in_team_frame: bool = False) -> None:
        self.local = local
        self.params = params
        self.robot = local.robot
        self.state = state
        self.root_robot = root_robot
        self.root = root_robot == local.robot
        self.in_team_frame = in_team_frame
        self.aligned = self.root
        # the frame rests on the root or on >= align_min_places places of settled peers' poses
        # (see :class:`~kimera_multi_py.comms.messages.pgo.PublicPoses`)
        self.settled = self.root
        self.excluded = False  # kept out of the team frame this epoch (see :attr:`alignment`)
        self.screened = False  # robust mode: inter-robot edges checked for consistency
        # what the frame rests on (JSON-ready): status, hypothesis, support, margin, reason
        self.alignment: dict[str, object] = {"status": "root" if self.root else "unaligned"}
        self.alignment_inliers: np.ndarray | None = None
        self.wait_rounds = 0
        self._no_peer_rounds = 0
        self._tried = b""  # the known-edge mask of the last alignment attempt
        # object landmarks (:meth:`set_landmarks`): own ones anchored to their nearest keyframes,
        # so they move with the estimate; settled peers' by robot
        self.landmark_anchor: np.ndarray | None = None
        self.landmark_offset = np.zeros((0, 3))
        self.landmark_classes = np.zeros(0, dtype=np.int32)
        self.peer_landmarks: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}
        # occupancy agreement of a frame hypothesis (:meth:`set_map_view`), cached per frame
        self.map_view: Callable[[np.ndarray], MapAgreement | None] | None = None
        self._map_scores: dict[tuple[int, ...], MapAgreement | None] = {}
        self.map_refuted: list[dict[str, object]] = []  # hypotheses the maps refuted, for the report
        # inter-robot edges of hypotheses the maps refuted: once a frame is adopted, those it does
        # not rest on are barred (held at weight 0, here and at their owners: :meth:`vetoes`)
        self.refuted_edges = np.zeros(len(local.inter_edge), dtype=bool)
        self.veto_news = False  # edges were newly barred: tell their owners

    # ---------------------------------------------------------------- alignment
    def try_align(self) -> None:
        """Align to the team frame from inter-robot edges whose other end is known."""
        lg = self.local
        known = np.array([int(k) in self.state.neighbour_poses for k in lg.inter_peer_key], dtype=bool)
        if not known.any():
            self._no_peer_rounds += 1
            if self.params.robust and self.params.align_hypotheses and \
                    self._no_peer_rounds > 2 * self.params.align_patience:
                self._exclude("no aligned neighbour", None, 0)
            return
        if self.params.robust and self.params.align_hypotheses:
            self._align_hypothesis(known)
            return
        nb = np.stack([self.state.neighbour_poses[int(k)] for k in lg.inter_peer_key[known]])
        res = align_frames(self.state.poses[lg.inter_own[known]], nb, lg.inter_meas[known],
                           lg.inter_own_is_i[known])
        self.wait_rounds += 1
        everything = bool(known.all())  # no further edge can arrive
        if not res.ok and not everything and self.wait_rounds < self.params.align_patience:
            return
        self._adopt_consensus(known, res)
        self.settled = True  # without frame hypotheses every aligned frame counts

    def _align_consensus(self, known: np.ndarray) -> None:
        """Align by the robust consensus of every known edge (:func:`.alignment.align_frames`)."""
        lg = self.local
        nb = np.stack([self.state.neighbour_poses[int(k)] for k in lg.inter_peer_key[known]])
        res = align_frames(self.state.poses[lg.inter_own[known]], nb, lg.inter_meas[known], lg.inter_own_is_i[known])
        if self.params.robust and self._map_refutes(res.T):
            self._exclude("the maps refute the consensus frame of every edge", None, 0)
            return
        self._adopt_consensus(known, res)
        self.settled = False
        self.alignment = {"status": "aligned", "settled": False, "support": int(res.inliers.sum()),
                          "edges": int(res.inliers.sum()),
                          "margin": 0, "hypotheses": 0, "peers": sorted(set(lg.inter_peer[known].tolist())),
                          "hypothesis": np.round(res.T, 4).tolist(), "reason": "consensus of all edges"}

    def _adopt_consensus(self, known: np.ndarray, res: Alignment) -> None:
        lg = self.local
        if not res.ok:
            log.warning("robot %d: aligning with only %d consistent inter-robot edges",
                        self.robot, int(res.inliers.sum()))
        inliers = np.zeros(len(lg.inter_edge), dtype=bool)
        inliers[np.flatnonzero(known)[res.inliers]] = True
        self._move_into(res.T, inliers)
        if self.params.robust and self.params.screen != "none":
            # edges the screen rejects start as outliers; GNC revisits them
            keep = inliers if self.params.screen == "alignment" else self._supported(known)
            self.state.inter_weights = np.where(known & ~keep, 0.0, 1.0)
            self._bar_refuted(inliers)
        self.screened = bool(known.all())
        log.info("robot %d aligned with %d/%d inter-robot edges", self.robot,
                 int(inliers.sum()), int(known.sum()))

    def _move_into(self, T: np.ndarray, inliers: np.ndarray) -> None:
        """Adopt frame ``T`` (own -> team): move the estimate and restart from it; ``inliers`` (an
        array the caller may still extend) are the inter-robot edges the frame rests on."""
        self.state.restart_from(T @ self.state.poses)
        self.alignment_inliers = inliers
        self.aligned = True
        self.excluded = False

    def _hypotheses(self, known: np.ndarray, merge_distance: float = SAME_FRAME_M) -> list[FrameHypothesis]:
        """Frame hypotheses of the known inter-robot edges (edge indices into the local graph),
        groups closer than ``merge_distance`` merged (:func:`.alignment.frame_hypotheses`)."""
        lg = self.local
        idx = np.flatnonzero(known)
        nb = np.stack([self.state.neighbour_poses[int(k)] for k in lg.inter_peer_key[idx]])
        hyps = frame_hypotheses(self.state.poses[lg.inter_own[idx]], nb, lg.inter_meas[idx], lg.inter_own_is_i[idx],
                                lg.inter_peer[idx], place_radius=self.params.place_radius,
                                merge_distance=merge_distance)
        for h in hyps:
            h.edges = idx[h.edges]
        kept = []
        for h in hyps:
            if self._map_refutes(h.T, h):
                self.refuted_edges[h.edges] = True
            else:
                kept.append(h)
        return kept

    def _bar_refuted(self, inliers: np.ndarray) -> None:
        """Bar the edges of map-refuted hypotheses that the adopted frame does not rest on: GNC
        must not bring back what the maps ruled out (an alias as large as the truth fits the
        least-squares solution as well as the truth does)."""
        if self.state.bar(self.refuted_edges & ~inliers):
            self.veto_news = True

    # ---------------------------------------------------------------- maps
    def set_map_view(self, view: Callable[[np.ndarray], MapAgreement | None] | None) -> None:
        """How the robot's map agrees with the team's under a frame ``T`` (own estimate -> team
        frame), or None where the maps cannot tell (:mod:`kimera_multi_py.alignment.map_check`)."""
        self.map_view = view if self.params.map_check else None
        self._map_scores.clear()

    def map_agreement(self, T: np.ndarray) -> MapAgreement | None:
        """The occupancy agreement of frame ``T`` (cached: hypotheses a few cm apart are one)."""
        if self.map_view is None:
            return None
        key = frame_key(T)
        if key not in self._map_scores:
            self._map_scores[key] = self.map_view(T)
        return self._map_scores[key]

    def _map_refutes(self, T: np.ndarray, h: FrameHypothesis | None = None) -> bool:
        """True when the maps contradict frame ``T``: the robot's walls in the team's clear free
        space (or the reverse) on enough cells (params ``map_min_conflicts``, ``map_conflict_ratio``)."""
        ag = self.map_agreement(T)
        p = self.params
        refuted = ag is not None and ag.refutes(p.map_min_conflicts, p.map_conflict_ratio)
        if refuted and ag is not None:
            entry: dict[str, object] = {"hypothesis": np.round(T[:3, 3], 2).tolist(), **ag.as_dict()}
            if h is not None:
                entry.update(places=h.places, edges=h.size, peers=list(h.peers))
            if entry not in self.map_refuted:
                self.map_refuted.append(entry)
        return refuted

    def _settled_edges(self) -> np.ndarray:
        """The inter-robot edges to peers whose frames are settled
        (:class:`~kimera_multi_py.comms.messages.pgo.PublicPoses`)."""
        return np.array([self.state.peer_settled.get(int(r), True) for r in self.local.inter_peer], dtype=bool)

    def _evidence(self, known: np.ndarray) -> tuple[list[FrameHypothesis], FrameHypothesis | None, int, str]:
        """The frame hypotheses over every known edge, the one that clearly leads (or None), its
        margin, and the verdict of :func:`.alignment.settled_decision` (edges to peers whose own
        frames are not settled decide only what settled peers' edges do not)."""
        p = self.params
        lg = self.local
        firm = known & self._settled_edges()
        hyps = self._hypotheses(known)
        firm_hyps = None if firm[known].all() else (self._hypotheses(firm) if firm.any() else [])
        peers = np.unique(lg.inter_peer[firm])
        per_peer = [self._hypotheses(firm & (lg.inter_peer == r)) for r in peers] if len(peers) > 1 else []
        return (hyps, *settled_decision(firm_hyps, hyps, per_peer, p.align_min_places, p.align_min_margin,
                                                p.place_radius))

    def _align_hypothesis(self, known: np.ndarray) -> None:
        """Robust alignment: adopt the frame hypothesis that clearly leads (module docstring)."""
        p = self.params
        lg = self.local
        self.wait_rounds += 1
        signature = known.tobytes() + self._settled_edges().tobytes()
        if self.excluded and signature == self._tried:
            return  # nothing new to decide on
        self._tried = signature
        hyps, best, margin, verdict = self._evidence(known)
        settles = verdict == "settled"
        contested = verdict == "contested"
        final = bool(known.all()) or self.wait_rounds >= p.align_patience
        if best is None and final and (not hyps or hyps[0].size < 3):
            # no group of mutually consistent edges at all (sparse or noisy edges, not
            # aliasing): the plain robust consensus of every edge decides
            self._align_consensus(known)
            return
        sole = bool(hyps) and margin == hyps[0].places and hyps[0].size >= 3
        if best is None and final and sole and p.align_lone_place:
            # one group and no competitor: nothing to tell an alias from here; adopted, and
            # reported as resting on one place (the drift check and later epochs revisit it)
            best = hyps[0]
        # a tie between groups of single places is aliasing itself (twin rooms): neither staying
        # nor the consensus of the edges is evidence, so the robot is kept out of the team frame
        placed = bool(hyps) and hyps[0].places >= p.align_tie_min_places
        if best is None and final and self.in_team_frame and placed:
            # a tie, and the robot already sits in the team frame (an earlier epoch aligned it):
            # it keeps that frame while the hypothesis at the identity is among the leaders;
            # switching frames takes a clear lead
            stay = [h for h in hyps if h.places == hyps[0].places and near_identity(h.T)]
            if stay:
                best, settles = stay[0], True  # the frame an earlier epoch settled
        landmarks: list[LandmarkScore] = []
        if best is None and final and placed:
            # closures do not decide between groups of several places (a tie, or peers' closures
            # leading to different frames): the team's object map may (the true frame puts the
            # robot's landmarks on the team's everywhere they both mapped, an alias only in the
            # twin rooms); decided so, the frame is not settled
            lead, landmarks = self._landmark_lead(hyps)
            if lead is not None:
                best, settles = lead, False
        ahead = len(hyps) < 2 or hyps[0].places > hyps[1].places
        if best is None and final and p.align_tie == "consensus" and placed and ahead and not contested:
            # opt-in only (not the default): the robust consensus of every edge aligns the robot
            # and the team's GNC decides between groups that the evidence does not separate,
            # which can carry the team into an alias; kept for studies of the back end alone
            self._align_consensus(known)
            self.alignment.update(reason="no frame hypothesis leads: consensus of every edge", margin=int(margin),
                                  competitors=_competitors(hyps), evidence=self._evidence_table(hyps, None))
            return
        # with the team map on, a frame is adopted only when every rival is refuted: by the maps
        # (dropped from ``hyps`` already) or by the team's landmarks; a lead on closures alone does
        # not do, and the robot stays out until a later epoch's maps tell the two apart
        rivals: list[FrameHypothesis] = []
        if best is not None and self.map_view is not None and p.align_rivals == "refuted":
            several = p.align_tie_min_places
            rivals = unrefuted_rivals(best, hyps, [sc.refuted() for sc in landmarks], several)
            if rivals and not landmarks:
                rival_scores = self._landmark_lead(hyps)[1]
                rivals = unrefuted_rivals(best, hyps, [sc.refuted() for sc in rival_scores], several)
            if rivals:
                best = None
        # a robot already in the team frame switches frames only on every neighbour's evidence:
        # at the start of an epoch only the root has published, and two of its places that look
        # like the robot's own outvote the one true place they share (an early 2-vs-1 lead can
        # move a robot that an earlier epoch aligned on many places into a twin room)
        switch = best is not None and self.in_team_frame and not near_identity(best.T)
        if best is None or (not final and (margin < p.align_early_margin or switch)):
            if final:
                why = "closures through different peers lead to different frames" if contested \
                    else (f"a rival frame on {rivals[0].places} places that neither the maps nor the landmarks "
                          "refute" if rivals else "no frame hypothesis leads")
                # out of patience before every neighbour's poses arrived: out for now, and
                # decided again as they come (only then is the exclusion news for the log)
                self._exclude(why, hyps[0] if hyps else None, margin, hyps,
                              level=logging.WARNING if bool(known.all()) else logging.INFO)
                if landmarks:
                    self.alignment["landmarks"] = [sc.as_list() for sc in landmarks]
                    self.alignment["evidence"] = self._evidence_table(hyps, None, landmarks)
            return
        inliers = np.zeros(len(lg.inter_edge), dtype=bool)
        self._move_into(best.T, inliers)
        # the edges the frame rests on: in the new frame, every group at the identity, groups
        # not merged (the merge joins what drift split for counting a frame's support, and it
        # would also join an alias closer than SAME_FRAME_M), as the server's screen keeps them
        for h in self._hypotheses(known, merge_distance=KEEP_M):
            if near_identity(h.T, max_trans=KEEP_M):
                inliers[h.edges] = True
        if not inliers.any():
            inliers[best.edges] = True
        # edges outside the hypothesis start as outliers; GNC and its rechecks revisit them,
        # except those of hypotheses the maps refuted
        self.state.inter_weights = np.where(known & ~inliers, 0.0, 1.0)
        self._bar_refuted(inliers)
        self.screened = bool(known.all())
        self.settled = settles
        self.alignment = self._report("aligned", best, margin, len(hyps))
        if landmarks:
            self.alignment.update(reason="closures do not decide: the team's landmarks do",
                                  competitors=_competitors(hyps), landmarks=[sc.as_list() for sc in landmarks])
        self.alignment["evidence"] = self._evidence_table(hyps, best, landmarks)
        log.info("robot %d aligned%s: %d edges from %d places (margin %d over %d other hypotheses), origin moved %s",
                 self.robot, "" if settles else " (not settled)", best.size, best.places, margin, len(hyps) - 1,
                 np.round(best.T[:3, 3], 2).tolist())

    # ---------------------------------------------------------------- landmarks
    def set_landmarks(self, classes: np.ndarray, centres: np.ndarray,
                      peers: dict[int, tuple[int, np.ndarray, np.ndarray]]) -> None:
        """The robot's object landmarks (MAP classes, centres in the frame of the estimate this
        solver starts from, :attr:`LocalGraph.poses`), each anchored to its nearest keyframe so
        it moves with the estimate; ``peers``: robot -> (root of its frame, classes, centres) of
        settled peers (read when deciding, so landmarks that arrive during the epoch count)."""
        P = self.local.poses
        c = np.asarray(centres, dtype=float).reshape(-1, 3)
        self.peer_landmarks = peers
        if not len(c) or not len(P):
            return
        k = cKDTree(P[:, :3, 3]).query(c)[1]
        self.landmark_anchor = np.asarray(k)
        self.landmark_offset = np.einsum("nji,nj->ni", P[k, :3, :3], c - P[k, :3, 3])  # Rᵀ (c − t)
        self.landmark_classes = np.asarray(classes)

    def _landmark_lead(self, hyps: list[FrameHypothesis]) -> tuple[FrameHypothesis | None, list[LandmarkScore]]:
        """The hypothesis the team's landmarks clearly favour (:mod:`.landmark_check`), among
        those resting on ``align_tie_min_places`` places, and every hypothesis's score."""
        team = [(c, x) for r, (f, c, x) in self.peer_landmarks.items() if f == self.root_robot and r != self.robot]
        if self.landmark_anchor is None or not team or not hyps:
            return None, []
        k = self.landmark_anchor
        own = np.einsum("nij,nj->ni", self.state.poses[k, :3, :3], self.landmark_offset) + self.state.poses[k, :3, 3]
        scores = landmark_scores(own, self.landmark_classes, np.concatenate([x for _, x in team]),
                                 np.concatenate([c for c, _ in team]), [h.T for h in hyps],
                                 place_radius=self.params.place_radius)
        i = landmark_lead(scores, [h.places >= self.params.align_tie_min_places for h in hyps])
        return (None if i is None else hyps[i]), scores

    def _evidence_table(self, hyps: list[FrameHypothesis], chosen: FrameHypothesis | None,
                        landmarks: list[LandmarkScore] | None = None) -> list[dict[str, object]]:
        """Every hypothesis weighed and why it was adopted or not (:mod:`.alignment.evidence`)."""
        return hypothesis_evidence(hyps, chosen, self.map_agreement, landmarks or [], self.map_refuted)

    def _report(self, status: str, h: FrameHypothesis | None, margin: int, hypotheses: int,
                reason: str = "") -> dict[str, object]:
        out: dict[str, object] = {"status": status, "settled": bool(self.settled and status != "excluded"),
                                  "support": h.places if h is not None else 0,
                                  "edges": h.size if h is not None else 0, "margin": int(margin),
                                  "hypotheses": int(hypotheses),
                                  "peers": list(h.peers) if h is not None else [],
                                  "hypothesis": np.round(h.T, 4).tolist() if h is not None else None}
        if reason:
            out["reason"] = reason
        if self.map_refuted:
            out["map_refuted"] = self.map_refuted
        ag = self.map_agreement(h.T) if h is not None and status == "aligned" else None
        if ag is not None:
            out["map"] = ag.as_dict()
        return out

    def _exclude(self, reason: str, h: FrameHypothesis | None, margin: int,
                 hyps: list[FrameHypothesis] | None = None, level: int = logging.WARNING) -> None:
        """Stay out of the team frame this epoch: no alignment, inter-robot edges off."""
        if self.excluded:
            return
        self.excluded = True
        self.state.inter_weights[:] = 0.0
        self.alignment = self._report("excluded", h, margin, len(hyps or []), reason)
        # every competing hypothesis: distinct places, edges, peers, and where it moves the robot's origin
        self.alignment["competitors"] = _competitors(hyps or [])
        self.alignment["evidence"] = self._evidence_table(hyps or [], None)
        log.log(level, "robot %d: kept out of the team frame (%s; best support %d places, margin %d)", self.robot,
                reason, h.places if h is not None else 0, margin)

    def screen(self) -> None:
        """Robust mode, aligned robot: start inconsistent inter-robot edges at weight 0.

        The same GNC rotation/translation consensus as the alignment (whose transform should
        now be the identity) flags the edges that disagree with the majority; GNC revisits them.
        """
        lg = self.local
        known = np.array([int(k) in self.state.neighbour_poses for k in lg.inter_peer_key], dtype=bool)
        self.wait_rounds += 1
        if not known.any() or (not known.all() and self.wait_rounds < self.params.align_patience):
            return
        hyps = self._hypotheses(known) if self.params.align_hypotheses else []
        here = [h for h in hyps if near_identity(h.T)]
        if here:
            # already in the team frame: keep the hypothesis at the identity, the rest start at 0
            keep = np.zeros(len(lg.inter_edge), dtype=bool)
            for h in here:
                keep[h.edges] = True
            self.state.inter_weights = np.where(known & ~keep, 0.0, 1.0)
            self._bar_refuted(keep)
            self.screened = True
            if self.root and here:
                others = [h.places for h in hyps if not near_identity(h.T)]
                self.alignment = self._report("root", here[0], here[0].places - max(others, default=0), len(hyps))
            return
        if self.params.screen == "support":
            self.state.inter_weights = np.where(known & ~self._supported(known), 0.0, 1.0)
            self.screened = True
            return
        nb = np.stack([self.state.neighbour_poses[int(k)] for k in lg.inter_peer_key[known]])
        res = align_frames(self.state.poses[lg.inter_own[known]], nb, lg.inter_meas[known],
                           lg.inter_own_is_i[known])
        if res.ok:
            inliers = np.zeros(len(lg.inter_edge), dtype=bool)
            inliers[np.flatnonzero(known)[res.inliers]] = True
            self.state.inter_weights = np.where(known & ~inliers, 0.0, 1.0)
            self.alignment_inliers = inliers
        self.screened = True

    def _supported(self, known: np.ndarray) -> np.ndarray:
        """The known inter-robot edges some other known edge agrees with (own poses in the team
        frame), see :func:`.alignment.supported_edges`."""
        lg = self.local
        out = np.zeros(len(lg.inter_edge), dtype=bool)
        if known.any():
            nb = np.stack([self.state.neighbour_poses[int(k)] for k in lg.inter_peer_key[known]])
            out[known] = supported_edges(self.state.poses[lg.inter_own[known]], nb, lg.inter_meas[known],
                                         lg.inter_own_is_i[known])
        return out

    # ---------------------------------------------------------------- end of the epoch
    def final_poses(self, solve_alone: Callable[[], np.ndarray]) -> np.ndarray:
        """The poses to adopt at the end of the epoch (``solve_alone``: the robot's own graph
        solved alone, see :func:`.drift_check.own_solution`).

        Robust mode also settles the safety property here: a robot that never aligned (or that
        was excluded) returns its estimate in its own frame (first pose at the identity) with
        every inter-robot weight 0; an estimate that disagrees with the robot's own odometry
        beyond its drift model is not adopted either (the robot's own solution is).
        """
        if not self.params.robust:
            return self.state.poses
        lg = self.local
        known = np.array([int(k) in self.state.neighbour_poses for k in lg.inter_peer_key], dtype=bool)
        self.state.inter_weights[~known] = 0.0
        if not self.aligned and not self.excluded:
            self._exclude("not aligned when the epoch ended", None, 0)
        if self.params.drift_check and not self.excluded:
            ratio = odometry_ratio(self.local, self.state.poses, self.params)
            self.alignment["drift_ratio"] = round(ratio, 3)
            if ratio > 1.0:
                log.warning("robot %d: estimate disagrees with its odometry (%.2f x its drift model)",
                            self.robot, ratio)
                self._exclude(f"estimate disagrees with odometry ({ratio:.2f} x drift model)", None, 0)
                self.alignment["drift_ratio"] = round(ratio, 3)
                self.state.poses = own_solution(self.local, self.state, self.params, solve_alone)
        if self.excluded:
            return inverse(self.state.poses[0]) @ self.state.poses
        return self.state.poses

def _competitors(hyps: list[FrameHypothesis]) -> list[list[object]]:
    """JSON-ready summary of frame hypotheses: ``[places, edges, peers, translation]`` each."""
    return [[h.places, h.size, list(h.peers), np.round(h.T[:3, 3], 2).tolist()] for h in hyps]
