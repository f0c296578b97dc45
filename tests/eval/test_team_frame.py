"""Which robots the evaluation scores in the team frame, and how the others are anchored."""

from types import SimpleNamespace

import numpy as np

from kimera_multi_py.core.geometry import yaw_pose
from kimera_multi_py.eval.team import excluded_robots, team_frame_estimates, team_frame_robots


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


def test_the_team_frame_robots_are_the_root_and_every_robot_not_kept_out():
    outs = [outcome(0, status="root", frame=0), outcome(1, status="excluded", frame=1),
            outcome(2, status="aligned", frame=0), outcome(3, status="root", frame=3)]
    assert team_frame_robots(outs) == [0, 2]
    # the root kept out by its drift check falls back to its own solution, which is the team
    # frame's root: the team's maps still hold its evidence (and the list is never empty)
    outs = [outcome(0, status="excluded", frame=0), outcome(1, status="excluded", frame=1)]
    assert excluded_robots(outs) == [0, 1] and team_frame_robots(outs) == [0]
    assert team_frame_robots([]) == []


def _mapped_agent(robot):
    """An agent that mapped six synthetic keyframes (its own evidence: points around x = 10 robot)."""
    from kimera_multi_py.agent.agent import Agent
    from kimera_multi_py.core.keyframe import KeyframeInput

    agent = Agent(robot)
    rng = np.random.default_rng(robot)
    for i in range(6):
        points = rng.uniform(-2.0, 2.0, (300, 3)) + [10.0 * robot, 0.0, 0.0]
        agent.process_keyframe(KeyframeInput(i, float(i), np.eye(4), points, np.ones(300, int),
                                             np.ones(300, bool), 30.0))
    return agent


def test_the_reference_team_map_leaves_out_a_robot_kept_out_of_the_team_frame():
    from kimera_multi_py.mapshare.fusion import centralised_team_map, octree_cells
    from kimera_multi_py.sim import load_scenario
    from kimera_multi_py.workflow.simulate import SimRunner

    from ..sim.helpers import TINY

    agents = [_mapped_agent(r) for r in (0, 1)]
    maps = {a.robot: a.map for a in agents}
    runner = SimRunner(load_scenario(TINY), seed=0, mode="distributed")
    runner.nodes = [SimpleNamespace(robot=a.robot, agent=a) for a in agents]

    def reference(*alignments):
        runner.outcomes = [outcome(r, **al) for r, al in enumerate(alignments)]
        runner._reference = None
        return octree_cells(runner._reference_map())[0]

    both, only_0 = (octree_cells(centralised_team_map(maps, robots))[0] for robots in ([0, 1], [0]))
    assert len(only_0) < len(both)  # robot 1's evidence is its own
    np.testing.assert_array_equal(reference({"status": "root", "frame": 0}, {"status": "aligned", "frame": 0}), both)
    np.testing.assert_array_equal(reference({"status": "root", "frame": 0}, {"status": "excluded", "frame": 1}),
                                  only_0)
    # no inter-robot edge ever joined robot 1 to the team: it is the root of its own frame
    np.testing.assert_array_equal(reference({"status": "root", "frame": 0}, {"status": "root", "frame": 1}), only_0)
