"""Frame screen of the centralised server: the agents' robust frame decision, on the joint graph.

The server receives each robot's odometry in the robot's own frame, and every loop closure the
front ends accepted, aliases included. GNC on that graph alone has no notion of a frame: an
alias group spread over many keyframes can be cheaper than the truth, and GNC then keeps the
alias and drops the truth. So before GNC the server decides each robot's frame as the
agents do (:mod:`kimera_multi_py.pgo.frame_decision`):

* the root (lowest id) is the team frame; the other robots join it one at a time;
* for a robot not yet aligned, its closures with the aligned robots are clustered into frame
  hypotheses (:func:`.frames.frame_hypotheses`), each supported by the distinct places its
  closures come from; :func:`.frames.decide` says whether one clearly leads;
* of all robots with a clear lead, the one with the largest margin joins first; closures with
  robots that are not *settled* (the root, and robots that joined on a clear lead are) decide
  only what the settled robots' closures do not (:func:`.frames.settled_decision`);
* only when no robot has a clear lead does a lone single-place group (one group, no competitor)
  join its robot, unsettled (``lone``); ties and robots without closures stay out (own frame);
* each inter-robot closure is judged once, when the later of its two robots joins: it is kept
  when it lies in the adopted hypothesis or in any group at the identity after the move.

With the team map (``cells``: a robot's occupancy cells placed at given keyframe poses), every
hypothesis first faces the maps, as the agents' do (:mod:`.map_check`): the robot's map moved by
it against each aligned robot's map at its screened poses; a hypothesis the maps refute is
dropped, and listed in the robot's report (``map_refuted``). A robot whose leader still has a
rival the maps did not refute (:func:`.frames.unrefuted_rivals`) does not join on that lead: it
waits for a later screen, as an agent waits for a later epoch (``MapRule.every_rival``).

Closures that are not kept leave the graph GNC sees, and the poses of the aligned robots start
in the team frame. Every edge is judged on the same information the agents would have at the
end of the run, which they have only once every peer has published.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from kimera_multi_py.alignment.evidence import hypothesis_evidence
from kimera_multi_py.alignment.frames import (
    KEEP_M,
    SAME_FRAME_M,
    FrameHypothesis,
    frame_hypotheses,
    near_identity,
    settled_decision,
    unrefuted_rivals,
)
from kimera_multi_py.alignment.map_check import CellStates, MapAgreement, frame_key, refined_agreement, team_agreement
from kimera_multi_py.core.posegraph import PoseGraph

# robot, its keyframe poses (n, 4, 4) -> its occupancy cells placed there (None: no map held)
CellsAt = Callable[[int, np.ndarray], CellStates | None]


@dataclass(frozen=True)
class MapRule:
    """The map check of the screen: where robots' cells come from, and when conflicts refute
    (the agents' ``PgoParams.map_*``)."""

    cells: CellsAt
    min_conflicts: int = 20
    min_ratio: float = 0.005
    coarse: float = 0.3
    every_rival: bool = True  # a frame is adopted only when the maps refute every rival (``align_rivals``)


@dataclass
class FrameScreen:
    """The server's frame decisions: poses with each aligned robot moved into the team frame,
    the edges GNC should see, and per robot what its frame rests on (JSON-ready)."""

    poses: np.ndarray
    keep: np.ndarray  # (num_edges,) bool: odometry, intra-robot closures, kept inter-robot ones
    report: dict[int, dict[str, object]] = field(default_factory=dict)

    def excluded(self) -> list[int]:
        return sorted(r for r, rep in self.report.items() if rep["status"] == "excluded")


class _Screen:
    def __init__(self, graph: PoseGraph, min_places: int, min_margin: int, place_radius: float,
                 maps: MapRule | None = None) -> None:
        self.g = graph
        self.min_places, self.min_margin, self.place_radius = min_places, min_margin, place_radius
        self.poses = graph.poses.copy()
        self.ri, self.rj = graph.robot[graph.edge_i], graph.robot[graph.edge_j]
        self.inter = self.ri != self.rj
        self.maps = maps
        self.refuted: dict[int, list[dict[str, object]]] = {}  # robot -> hypotheses the maps refuted
        self._cells: dict[int, CellStates | None] = {}  # robot -> its cells at its screened poses
        self._agree: dict[tuple[object, ...], MapAgreement] = {}  # (robot, aligned robot, frame) -> agreement

    def cells(self, robot: int) -> CellStates | None:
        """The robot's map at its screened poses (its own frame, or the team frame once aligned:
        :meth:`moved` forgets it)."""
        if robot not in self._cells:
            self._cells[robot] = None if self.maps is None else \
                self.maps.cells(robot, self.poses[self.g.robot_indices(robot)])
        return self._cells[robot]

    def moved(self, robot: int) -> None:
        self._cells.pop(robot, None)
        self._agree = {k: v for k, v in self._agree.items() if robot not in k[:2]}

    def agreement(self, robot: int, T: np.ndarray, aligned: set[int], root: int
                  ) -> tuple[MapAgreement | None, list[int]]:
        """How ``robot``'s map moved by ``T`` agrees with the aligned robots' maps (their total,
        with the team's verdict, :func:`.map_check.team_agreement`), and the robots it
        contradicts; None where no map overlaps."""
        rule, mine = self.maps, self.cells(robot)
        if rule is None or mine is None:
            return None, []
        key = frame_key(T)
        per = {}
        for a in sorted(aligned):
            if (c := self.cells(a)) is not None:
                if (robot, a, key) not in self._agree:  # hypotheses a few cm apart are one
                    self._agree[(robot, a, key)] = refined_agreement(mine, c, T, rule.coarse)
                per[a] = self._agree[(robot, a, key)]
        if not per:
            return None, []
        total, conflicting, _ = team_agreement(per, root, rule.min_conflicts, rule.min_ratio)
        return total, conflicting

    def map_refutes(self, robot: int, h: FrameHypothesis, aligned: set[int], root: int) -> bool:
        """True when moving ``robot``'s map by ``h`` contradicts the aligned robots' maps (the
        root's, or more of them than agree); the refuted hypothesis is listed for the report."""
        total, conflicting = self.agreement(robot, h.T, aligned, root)
        if total is None or self.maps is None or not total.refutes(self.maps.min_conflicts, self.maps.min_ratio):
            return False
        entry = {"hypothesis": np.round(h.T[:3, 3], 2).tolist(), "places": int(h.places), "edges": int(h.size),
                 "peers": list(h.peers), "conflicting": conflicting, **total.as_dict()}
        if entry not in self.refuted.setdefault(robot, []):
            self.refuted[robot].append(entry)
        return True

    def evidence(self, robot: int, hyps: list[FrameHypothesis], chosen: FrameHypothesis | None,
                 aligned: set[int], root: int) -> list[dict[str, object]]:
        """Every hypothesis weighed for ``robot`` and its verdict (:mod:`.evidence`)."""
        return hypothesis_evidence(hyps, chosen, lambda T: self.agreement(robot, T, aligned, root)[0],
                                   refuted=self.refuted.get(robot, []))

    def edges(self, robot: int, peers: set[int]) -> np.ndarray:
        """Inter-robot edges between ``robot`` and ``peers``."""
        a = (self.ri == robot) & np.isin(self.rj, list(peers))
        b = (self.rj == robot) & np.isin(self.ri, list(peers))
        return np.flatnonzero(self.inter & (a | b))

    def hypotheses(self, robot: int, E: np.ndarray, merge_distance: float = SAME_FRAME_M) -> list[FrameHypothesis]:
        g = self.g
        own_is_i = self.ri[E] == robot
        own = np.where(own_is_i, g.edge_i[E], g.edge_j[E])
        other = np.where(own_is_i, g.edge_j[E], g.edge_i[E])
        hyps = frame_hypotheses(self.poses[own], self.poses[other], g.measurement[E], own_is_i,
                                g.robot[other], place_radius=self.place_radius, merge_distance=merge_distance)
        for h in hyps:
            h.edges = E[h.edges]
        return hyps

    def lead(self, robot: int, settled: set[int], aligned: set[int], root: int
             ) -> tuple[FrameHypothesis | None, int, bool, list[FrameHypothesis]]:
        """The hypothesis that clearly leads for ``robot`` (:func:`.frames.settled_decision`),
        its margin, whether it is settled, and the hypotheses over every aligned robot (those the
        maps refute dropped)."""
        def faced(E: np.ndarray) -> list[FrameHypothesis]:
            return [h for h in self.hypotheses(robot, E) if not self.map_refutes(robot, h, aligned, root)]

        self.refuted.pop(robot, None)
        firm = self.edges(robot, settled)
        every = self.edges(robot, aligned)
        hyps = faced(every)
        firm_hyps = None if len(firm) == len(every) else (faced(firm) if len(firm) else [])
        by_peer = [E for E in (self.edges(robot, {p}) for p in settled) if len(E)]
        per_peer = [faced(E) for E in by_peer] if len(by_peer) > 1 else []
        best, margin, verdict = settled_decision(firm_hyps, hyps, per_peer, self.min_places, self.min_margin,
                                                  self.place_radius)
        return best, margin, verdict == "settled", hyps


def screen_frames(graph: PoseGraph, min_places: int = 2, min_margin: int = 1, place_radius: float = 2.0,
                  lone: bool = True, maps: MapRule | None = None, rival_places: int = 2) -> FrameScreen:
    """Decide every robot's frame on the joint graph (see the module docstring); ``maps``: the
    hypotheses face the robots' maps first, and with ``maps.every_rival`` a rival resting on
    ``rival_places`` places or more must be refuted (the agents' ``align_tie_min_places``)."""
    s = _Screen(graph, min_places, min_margin, place_radius, maps)
    robots = sorted(set(graph.robot.tolist()))
    keep = ~s.inter
    if not robots:
        return FrameScreen(s.poses, keep)
    root = robots[0]
    aligned, settled = {root}, {root}
    report: dict[int, dict[str, object]] = {root: {"status": "root", "settled": True}}
    weighed: dict[int, list[FrameHypothesis]] = {}  # robot -> the hypotheses of its last decision
    rivals: dict[int, list[FrameHypothesis]] = {}  # robot -> rivals of its leader the maps left standing
    while True:
        leads, lones = [], []
        for r in robots:
            if r in aligned or not len(s.edges(r, aligned)):
                continue
            best, margin, firm, hyps = s.lead(r, settled, aligned, root)
            weighed[r] = hyps
            rivals.pop(r, None)
            if best is not None and s.maps is not None and s.maps.every_rival:
                rivals[r] = unrefuted_rivals(best, hyps, min_places=rival_places)
                if rivals[r]:
                    continue  # a lead on closures alone: the robot waits for maps that tell the frames apart
            if best is not None:
                leads.append((firm, margin, best.places, -r, best, hyps))
            elif hyps and hyps[0].size >= 3 and margin == hyps[0].places:
                lones.append((hyps[0].size, -r, hyps[0], hyps))
        if leads:
            firm, margin, _, neg, best, hyps = max(leads, key=lambda c: c[:4])
        elif lones and lone:
            _, neg, best, hyps = max(lones, key=lambda c: c[:2])
            firm, margin = False, best.places
        else:
            break
        r = -neg
        evidence = s.evidence(r, hyps, best, aligned, root)  # in the robot's frame before the move
        idx = graph.robot_indices(r)
        s.poses[idx] = best.T @ s.poses[idx]
        s.moved(r)
        # the edges GNC sees: every group at the identity in the new frame, groups not merged. The
        # merge (SAME_FRAME_M) joins what drift split for counting a frame's support, but it also
        # joins an alias closer than that (a repeated corridor stretch), which GNC may then keep
        kept: set[int] = set()
        for h in s.hypotheses(r, s.edges(r, aligned), merge_distance=KEEP_M):
            if near_identity(h.T, max_trans=KEEP_M):
                kept.update(h.edges.tolist())
        keep[list(kept)] = True
        aligned.add(r)
        if firm:
            settled.add(r)
        report[r] = {"status": "aligned", "settled": bool(firm), "support": int(best.places),
                     "edges": int(best.size), "margin": int(margin), "hypotheses": len(hyps),
                     "peers": list(best.peers), "hypothesis": np.round(best.T, 4).tolist(), "evidence": evidence}
        if s.refuted.get(r):
            report[r]["map_refuted"] = s.refuted[r]
    for r in robots:
        if r not in aligned:
            why = "no frame hypothesis leads" if len(s.edges(r, aligned)) else "no closure to the team"
            if rivals.get(r):
                why = f"a rival frame on {rivals[r][0].places} places that the maps do not refute"
            report[r] = {"status": "excluded", "settled": False, "reason": why,
                         "evidence": s.evidence(r, weighed.get(r, []), None, aligned, root)}
            if s.refuted.get(r):
                report[r]["map_refuted"] = s.refuted[r]
    return FrameScreen(s.poses, keep, report)
