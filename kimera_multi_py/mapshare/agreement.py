"""A robot's map against the team's, for frame decisions (docs/algorithms/pgo.md).

:func:`map_view` freezes, at one moment, the robot's own evidence and the other robots'
evidence whose poses are in one team frame, and returns the function that scores a frame
hypothesis on them (:func:`kimera_multi_py.alignment.map_check.map_agreement`). The PGO asks it
about each hypothesis when an epoch opens; the node asks it about the frame the robot is in
after each epoch (the safety net).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from kimera_multi_py.alignment.map_check import (
    CellStates,
    MapAgreement,
    cell_states,
    map_agreement,
    refined_agreement,
)
from kimera_multi_py.mapping.submaps import SubmapMap
from kimera_multi_py.mapshare.consensus import MapConsensus
from kimera_multi_py.mapshare.fusion import view_rows

MapView = Callable[[np.ndarray], MapAgreement | None]


def _own_states(own: SubmapMap, occupancy: float) -> CellStates | None:
    codes, rows, _ = own.evidence()
    return cell_states(codes, view_rows(own.octree, rows), own.resolution, occupancy) if len(codes) else None


def map_view(maps: MapConsensus | None, own: SubmapMap, frame: int, coarse: float = 0.3,
             occupancy: float = 1.0, sources: list[int] | None = None) -> MapView | None:
    """Scores of frames ``T`` (own estimate -> the frame rooted at ``frame``) against ``sources``
    (default: every other robot in that frame), or None when none of their evidence is held (or
    the map consensus keeps none per robot)."""
    peers = None if maps is None else maps.frame_cells(frame, sources)
    mine = _own_states(own, occupancy)
    if peers is None or not len(peers[0]) or mine is None:
        return None
    team = cell_states(peers[0], peers[1], own.resolution, occupancy)
    return lambda T: refined_agreement(mine, team, T, coarse)


@dataclass
class FrameCheck:
    """The safety net's verdict on the frame a robot is in: its map against each other robot's."""

    refuted: bool
    conflicting: list[int]  # robots whose maps contradict ours here
    agreeing: list[int]  # robots whose maps overlap ours enough to contradict it, and do not
    per_robot: dict[int, MapAgreement]

    def as_dict(self) -> dict[str, object]:
        return {"refuted": self.refuted, "conflicting": self.conflicting, "agreeing": self.agreeing,
                "per_robot": {str(r): a.as_dict() for r, a in self.per_robot.items()}}


def frame_check(maps: MapConsensus | None, own: SubmapMap, frame: int, min_conflicts: int, min_ratio: float,
                coarse: float = 0.3, occupancy: float = 1.0) -> FrameCheck | None:
    """Whether the robot's map, where it is now, contradicts the maps of the robots in frame ``frame``.

    Each robot is compared on its own, so one robot in a wrong frame cannot outvote the rest:
    the frame is refuted when the map contradicts the frame's root robot, or more of the robots
    whose maps overlap ours enough to tell (``min_conflicts / min_ratio`` common cells) than
    agree with it. None when no robot's evidence is held for that frame.
    """
    if maps is None:
        return None
    mine = _own_states(own, occupancy)
    sources = maps.frame_sources(frame)
    if mine is None or not sources:
        return None
    per: dict[int, MapAgreement] = {}
    for src in sources:
        cells = maps.frame_cells(frame, [src])
        if cells is not None and len(cells[0]):
            per[src] = map_agreement(mine, cell_states(cells[0], cells[1], own.resolution, occupancy), None, coarse)
    conflicting = sorted(r for r, a in per.items() if a.refutes(min_conflicts, min_ratio))
    enough = min_conflicts / max(min_ratio, 1e-9)
    agreeing = sorted(r for r, a in per.items() if r not in conflicting and a.overlap >= enough)
    refuted = frame in conflicting or len(conflicting) > len(agreeing)
    return FrameCheck(refuted, conflicting, agreeing, per)
