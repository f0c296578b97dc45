"""A robot's map against the team's, for frame decisions (docs/algorithms/pgo.md).

:func:`map_view` freezes, at one moment, the robot's own evidence and the other robots'
evidence whose poses are in one team frame, and returns the function that scores a frame
hypothesis on them (:func:`kimera_multi_py.alignment.map_check.map_agreement`). The PGO asks it
about each hypothesis when an epoch opens; the node asks it about the frame the robot is in
after each epoch (the safety net). :func:`source_states` places one robot's held evidence at
any keyframe poses: the centralised server's frame screen asks it.
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
    team_agreement,
)
from kimera_multi_py.mapping.submaps import SubmapMap
from kimera_multi_py.mapshare.consensus import MapConsensus
from kimera_multi_py.mapshare.fusion import view_rows

MapView = Callable[[np.ndarray], MapAgreement | None]


def _own_states(own: SubmapMap, occupancy: float) -> CellStates | None:
    codes, rows, _ = own.evidence()
    return cell_states(codes, view_rows(own.template, rows), own.resolution, occupancy) if len(codes) else None


def _peer_states(maps: MapConsensus, frame: int, resolution: float, occupancy: float) -> dict[int, CellStates]:
    out = {}
    for src in maps.frame_sources(frame):
        cells = maps.frame_cells(frame, [src])
        if cells is not None and len(cells[0]):
            out[src] = cell_states(cells[0], cells[1], resolution, occupancy)
    return out


def map_view(maps: MapConsensus | None, own: SubmapMap, frame: int, min_conflicts: int, min_ratio: float,
             coarse: float = 0.3, occupancy: float = 1.0) -> MapView | None:
    """Scores of frames ``T`` (own estimate -> the frame rooted at ``frame``) against every other
    robot's evidence held in that frame, robot by robot (:func:`team_agreement`), or None when none
    is held (or the map consensus keeps none per robot)."""
    mine = _own_states(own, occupancy)
    peers = {} if maps is None or mine is None else _peer_states(maps, frame, own.resolution, occupancy)
    if mine is None or not peers:
        return None

    def view(T: np.ndarray) -> MapAgreement:
        per = {src: refined_agreement(mine, cells, T, coarse) for src, cells in peers.items()}
        return team_agreement(per, frame, min_conflicts, min_ratio)[0]

    return view


def source_states(maps: MapConsensus, src: int, poses: np.ndarray, keyframes_per_submap: int,
                  occupancy: float = 1.0) -> CellStates | None:
    """Robot ``src``'s evidence as held by ``maps``, each submap placed at the pose of its first
    keyframe in ``poses`` (n, 4, 4): the robot's map in any frame those poses are in (the
    centralised server's frame screen). None when nothing of it is held (or outside exact mode)."""
    entry = maps.poses.get(src) if maps.mode == "exact" else None
    if entry is None:
        return None
    at = {(src, sid): poses[k] for sid in entry[0].submaps.tolist()
          if (k := sid * keyframes_per_submap) < len(poses)}
    codes, rows = maps.team.fused(list(at), at)
    if not len(codes):
        return None
    return cell_states(codes, view_rows(maps.team.template, rows), maps.team.resolution, occupancy)


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
    """Whether the robot's map, where it is now, contradicts the maps of the robots in frame
    ``frame`` (:func:`team_agreement`); None when no robot's evidence is held for that frame."""
    mine = _own_states(own, occupancy)
    peers = {} if maps is None or mine is None else _peer_states(maps, frame, own.resolution, occupancy)
    if mine is None or not peers:
        return None
    per = {src: map_agreement(mine, cells, None, coarse) for src, cells in peers.items()}
    total, conflicting, agreeing = team_agreement(per, frame, min_conflicts, min_ratio)
    return FrameCheck(bool(total.verdict), conflicting, agreeing, per)
