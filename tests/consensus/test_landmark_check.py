"""Landmark agreement of frame hypotheses (:mod:`kimera_multi_py.alignment.landmark_check`).

A row of three identical rooms 6 m apart (same objects, same classes) and a few objects that look
like nothing else. The robot's landmarks, moved by the true frame, land on the team's wherever
both mapped; moved by the frame one room over, only those in the twin rooms do.
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.alignment.landmark_check import LandmarkScore, landmark_lead, landmark_scores
from kimera_multi_py.core.geometry import make_pose, so3_exp

ROOM = np.array([[-1.0, -1.5, 0.4], [1.0, -1.5, 0.4], [0.0, -2.5, 0.8], [1.5, -0.5, 0.4]])
ROOM_CLASSES = np.array([3, 4, 5, 3])
UNIQUE = np.array([[20.5, 3.0, 0.5], [14.0, 8.8, 0.5], [8.0, 8.8, 1.0], [2.0, 8.8, 0.5], [-0.8, 4.0, 0.5]])
UNIQUE_CLASSES = np.array([6, 7, 3, 8, 4])


def _world(rooms: tuple[float, ...] = (4.0, 10.0, 16.0), unique: bool = True) -> tuple[np.ndarray, np.ndarray]:
    xyz = [ROOM + [x, 0.0, 0.0] for x in rooms] + ([UNIQUE] if unique else [])
    cls = [ROOM_CLASSES for _ in rooms] + ([UNIQUE_CLASSES] if unique else [])
    return np.concatenate(xyz), np.concatenate(cls)


def _own(world: np.ndarray, T_own_team: np.ndarray, rng: np.random.Generator, noise: float = 0.08) -> np.ndarray:
    """World landmarks as the robot's estimate has them (its own frame), a little noisy."""
    return world @ T_own_team[:3, :3].T + T_own_team[:3, 3] + rng.normal(scale=noise, size=world.shape)


def _frames() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The robot's own frame in the team frame (truth), the alias one room on, and own <- team."""
    truth = make_pose(so3_exp(np.array([0.0, 0.0, 0.7])), np.array([3.0, -2.0, 0.0]))  # own -> team
    alias = make_pose(np.eye(3), np.array([6.0, 0.0, 0.0])) @ truth
    return truth, alias, np.linalg.inv(truth)


def test_the_true_frame_puts_the_landmarks_on_the_teams_and_an_alias_only_in_the_twin_rooms() -> None:
    rng = np.random.default_rng(0)
    team_xyz, team_cls = _world()
    truth, alias, to_own = _frames()
    own_xyz, own_cls = _world(rooms=(4.0, 10.0))  # the robot saw two of the rooms and the unique spots
    own_xyz = _own(own_xyz, to_own, rng)
    t, a = landmark_scores(own_xyz, own_cls, team_xyz, team_cls, [truth, alias])
    assert t.matched == len(own_xyz) and t.conflicts == 0 and t.places == 2 + len(UNIQUE)
    assert a.matched == 2 * len(ROOM) and a.places == 2  # rooms A, B land on rooms B, C
    assert a.conflicts >= 2  # unique objects land next to objects of other classes
    assert landmark_lead([t, a], [True, True]) == 0
    assert landmark_lead([a, t], [True, True]) == 1
    assert landmark_lead([t, a], [False, True]) is None  # only eligible hypotheses win


def test_twin_rooms_alone_leave_the_frames_undecided() -> None:
    """Landmarks only in rooms with identical twins: truth and alias match as many, nothing leads."""
    rng = np.random.default_rng(1)
    team_xyz, team_cls = _world()
    truth, alias, to_own = _frames()
    own_xyz, own_cls = _world(rooms=(4.0, 10.0), unique=False)
    t, a = landmark_scores(_own(own_xyz, to_own, rng), own_cls, team_xyz, team_cls, [truth, alias])
    assert (t.places, t.matched) == (a.places, a.matched) == (2, 2 * len(ROOM))
    assert landmark_lead([t, a], [True, True]) is None


def test_a_refuted_competitor_does_not_count_and_a_conflicted_winner_does_not_win() -> None:
    strong, weak = LandmarkScore(matched=20, places=5, conflicts=1), LandmarkScore(matched=6, places=4, conflicts=12)
    assert weak.refuted() and landmark_lead([strong, weak], [True, True]) == 0
    assert landmark_lead([strong, LandmarkScore(matched=6, places=3, conflicts=2)], [True, True]) is None  # 5 < 2 x 3
    conflicted = LandmarkScore(matched=20, places=6, conflicts=8)  # 8 > 0.25 x 20
    assert landmark_lead([conflicted, LandmarkScore(1, 1, 0)], [True, True]) is None
    assert landmark_lead([LandmarkScore(3, 1, 0)], [True]) is None  # one place is no evidence


def test_no_landmarks_on_either_side_scores_nothing() -> None:
    truth, alias, _ = _frames()
    empty = np.zeros((0, 3))
    scores = landmark_scores(empty, np.zeros(0, int), *_world(), [truth, alias])
    assert scores == [LandmarkScore(0, 0, 0)] * 2 and landmark_lead(scores, [True, True]) is None
    xyz, cls = _world()
    assert landmark_scores(xyz, cls, empty, np.zeros(0, int), [truth]) == [LandmarkScore(0, 0, 0)]
