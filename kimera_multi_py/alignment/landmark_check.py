"""Landmark agreement of frame hypotheses: which frame the team's object map supports.

Closures cannot tell twin rooms apart: when a robot met its peers only in rooms that have
identical twins, the true frame and the frame shifted by one room rest on as many places. The
object maps can. Moved by
the true hypothesis, a robot's landmarks land on landmarks of the same class wherever its peers
mapped the same part of the building (corridor bays, unique rooms, every room); moved by an
alias, only those in the twin rooms do, and the rest land next to objects of other classes.

:func:`landmark_scores` scores each hypothesis; :func:`landmark_lead` names the one the
landmarks clearly favour, or none. The frame decision asks only when closures do not decide
(:mod:`kimera_multi_py.pgo.frame_decision`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from kimera_multi_py.alignment.frames import count_places


@dataclass(frozen=True)
class LandmarkScore:
    """How one frame hypothesis puts the robot's landmarks onto the team's."""

    matched: int  # own landmarks within ``match_radius`` of a team landmark of their class
    places: int  # distinct places of those (single linkage at ``place_radius``)
    conflicts: int  # own landmarks near team landmarks (``near_radius``) but on none of their class

    def refuted(self) -> bool:
        """More of the robot's landmarks land on other classes than on their own."""
        return self.conflicts > self.matched

    def as_list(self) -> list[int]:
        return [self.places, self.matched, self.conflicts]


def landmark_scores(own_xyz: np.ndarray, own_cls: np.ndarray, team_xyz: np.ndarray, team_cls: np.ndarray,
                    transforms: list[np.ndarray], match_radius: float = 0.5, near_radius: float = 1.5,
                    place_radius: float = 2.0) -> list[LandmarkScore]:
    """Score each transform (own estimate frame -> team frame) of the robot's landmarks
    ``own_xyz (n, 3)`` / ``own_cls (n,)`` against the team's ``team_xyz (m, 3)`` / ``team_cls``."""
    own_xyz = np.asarray(own_xyz, dtype=float).reshape(-1, 3)
    team_xyz = np.asarray(team_xyz, dtype=float).reshape(-1, 3)
    own_cls, team_cls = np.asarray(own_cls), np.asarray(team_cls)
    if not len(own_xyz) or not len(team_xyz):
        return [LandmarkScore(0, 0, 0) for _ in transforms]
    tree = cKDTree(team_xyz)
    # per class seen by both: the robot's landmarks of it, and a tree of the team's
    by_class = [(own_cls == c, cKDTree(team_xyz[team_cls == c])) for c in np.intersect1d(own_cls, team_cls)]
    out = []
    for T in transforms:
        p = own_xyz @ np.asarray(T)[:3, :3].T + np.asarray(T)[:3, 3]
        # nearest team landmark of the own landmark's class: distance per own landmark
        d_same = np.full(len(p), np.inf)
        for on, same in by_class:
            d_same[on] = same.query(p[on])[0]
        d_any = tree.query(p)[0]
        matched = d_same <= match_radius
        conflicts = (d_any <= near_radius) & ~matched
        out.append(LandmarkScore(int(matched.sum()), count_places(p[matched], place_radius), int(conflicts.sum())))
    return out


def landmark_lead(scores: list[LandmarkScore], eligible: list[bool], lead_ratio: float = 2.0, min_places: int = 2,
                  max_conflict_ratio: float = 0.25) -> int | None:
    """The index of the hypothesis the landmarks clearly favour, or None.

    Only ``eligible`` hypotheses can win. The winner's matched landmarks span at least
    ``min_places`` places, at most ``max_conflict_ratio`` of its matches are conflicts, and its
    places are ``lead_ratio`` times (and at least one more than) those of every competitor the
    landmarks do not refute (:meth:`LandmarkScore.refuted`), eligible or not.
    """
    for i, s in enumerate(scores):
        if not eligible[i] or s.places < min_places or s.conflicts > max_conflict_ratio * s.matched:
            continue
        rivals = [o for j, o in enumerate(scores) if j != i and not o.refuted()]
        if all(s.places >= max(lead_ratio * o.places, o.places + 1) for o in rivals):
            return i
    return None
