"""Which robots the evaluation scores in the team frame, and how the others are anchored."""

from types import SimpleNamespace

import numpy as np

from kimera_multi_py.eval.team import excluded_robots, team_frame_estimates
from kimera_multi_py.geometry import yaw_pose


def outcome(robot, **alignment):
    return SimpleNamespace(robot=robot, alignment=alignment)


def test_a_robot_in_another_roots_frame_is_scored_in_its_own_frame():
    # robot 1 never got an inter-robot edge into PGO: it is the root of its own frame
    outs = [outcome(0, status="root", frame=0), outcome(1, status="root", frame=1),
            outcome(2, status="aligned", frame=0), outcome(3, status="excluded", frame=0), outcome(4)]
    assert excluded_robots(outs) == [1, 3]
    assert excluded_robots([]) == []


def test_own_frame_estimates_are_anchored_at_their_first_pose():
    truth = [np.stack([yaw_pose(0, 0, 0, 0), yaw_pose(1, 0, 0, 0)]),
             np.stack([yaw_pose(5, 2, 0, 0.3), yaw_pose(5, 3, 0, 0.3)])]
    drifted = yaw_pose(-7, 4, 0, 1.0)  # a lone robot's gauge wandered off the identity
    est = [truth[0], drifted @ np.linalg.inv(truth[1][0]) @ truth[1]]
    placed = team_frame_estimates(truth, est, own_frame=[1])
    assert np.allclose(placed[1], truth[1], atol=1e-9)
    assert placed[0] is est[0]
