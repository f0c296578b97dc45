"""People sharing: a person seen by two robots at once is one agent, with one id, on both."""

from __future__ import annotations

import numpy as np
import pytest

from kimera_multi_py.comms.messages.maps import PeopleUpdate, SubmapPoses
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.geometry import inverse, transform_points, yaw_pose
from kimera_multi_py.core.semantics import CLASS_IDS
from kimera_multi_py.mapping.object_fusion import team_id
from kimera_multi_py.mapshare.people import PeopleExchange
from kimera_multi_py.people import PeopleParams, PeopleTracker
from kimera_multi_py.people.fusion import TeamTrack, fuse_people

from .test_tracking import dets

HUMAN = CLASS_IDS["human"]


def walker(start, velocity):
    return lambda t: np.asarray(start, float) + t * np.asarray(velocity, float)


class Robot:
    """A robot whose odometry frame sits at ``T_world_odom``; one submap, aligned to the team frame."""

    def __init__(self, robot: int, T_world_odom: np.ndarray) -> None:
        self.robot, self.T = robot, T_world_odom
        self.tracker = PeopleTracker((HUMAN,), PeopleParams(confirm_hits=2))
        self.tracker.set_submap_pose(0, np.eye(4))
        self.held: dict[int, SubmapPoses] = {}
        self.ex = PeopleExchange(robot, lambda: self.tracker, self.held.get, period=1.0)
        self.ex.set_frame(0)

    def see(self, k: int, t: float, people_xy: list[np.ndarray]) -> None:
        world = np.array([[p[0], p[1], 0.9] for p in people_xy]).reshape(-1, 3)
        local = transform_points(inverse(self.T), world)  # in the robot's own estimate
        self.tracker.step(k, t, 0, dets(*local[:, :2]))

    def align(self) -> SubmapPoses:
        """PGO put the robot in the team frame: its submap moved by ``T``."""
        self.tracker.set_submap_pose(0, self.T)
        return SubmapPoses(robot=self.robot, source=self.robot, version=2, frame=0, submaps=np.array([0]),
                           T_ref=np.eye(4)[None], T=self.T[None])


def test_a_person_seen_by_two_robots_at_once_is_one_agent_on_both():
    shared = walker([2.0, 1.0], [0.8, 0.0])  # seen by both robots
    only0 = walker([2.0, -4.0], [0.0, 0.5])  # seen by robot 0 alone
    only1 = walker([9.0, 6.0], [-0.6, 0.0])  # seen by robot 1 alone
    r0, r1 = Robot(0, np.eye(4)), Robot(1, yaw_pose(10.0, 2.0, 0.0, 0.7))
    rng = np.random.default_rng(0)
    for k in range(6):
        t0, t1 = float(k), k + 0.5  # the robots' keyframes are not simultaneous
        r0.see(k, t0, [shared(t0) + rng.normal(0, 0.05, 2), only0(t0)])
        r1.see(k, t1, [only1(t1), shared(t1) + rng.normal(0, 0.05, 2)])
    tables = {0: r0.align(), 1: r1.align()}
    for r in (r0, r1):
        r.held.update(tables)
        r.ex.set_neighbours({0, 1})
    for now in (0.0, 1.0):
        out0, out1 = r0.ex.step(now), r1.ex.step(now)
        assert all(isinstance(m, PeopleUpdate) for m in out0 + out1)
        for m in out0:
            r1.ex.handle(m)
        for m in out1:
            r0.ex.handle(m)
    p0, p1 = r0.ex.team_people(), r1.ex.team_people()
    assert [p["id"] for p in p0] == [p["id"] for p in p1]
    assert len(p0) == 3
    both = [p for p in p0 if p["sources"] == [0, 1]]
    assert len(both) == 1
    # the shared person's id: the smaller team id of its two tracks; its samples in the team frame
    assert both[0]["id"] == min(both[0]["members"]) and len(both[0]["members"]) == 2
    stamps, pos = np.array(both[0]["stamps"]), np.array(both[0]["positions"])
    truth = np.array([shared(t) for t in stamps])
    assert np.sqrt(np.mean(np.sum((pos[:, :2] - truth) ** 2, axis=1))) < 0.15
    assert sorted(p["sources"] for p in p0) == [[0], [0, 1], [1]]


def test_two_tracks_of_one_robot_are_never_fused():
    t = np.arange(5.0)
    a = TeamTrack(0, t, np.column_stack([t, np.zeros(5), np.zeros(5)]))
    b = TeamTrack(0, t, np.column_stack([t, np.full(5, 0.3), np.zeros(5)]))  # walking side by side
    c = TeamTrack(1, t + 0.5, np.column_stack([t + 0.5, np.full(5, 0.15), np.zeros(5)]))
    people = fuse_people({team_id(0, 0): a, team_id(0, 1): b, team_id(1, 0): c})
    assert len(people) == 2
    assert sorted(len(p["members"]) for p in people) == [1, 2]


def test_a_bad_table_is_refused():
    ex = PeopleExchange(0, lambda: PeopleTracker((HUMAN,)), {}.get)
    ex.set_neighbours({1})
    with pytest.raises(MessageError, match="non-finite"):
        PeopleUpdate(robot=1, source=1, version=1, frame=0, tracks=np.array([0]), stamps=np.array([1.0]),
                     submaps=np.array([0]), positions=np.array([[np.nan, 0.0, 0.0]]))
    twice = PeopleUpdate(robot=1, source=1, version=1, frame=0, tracks=np.array([0, 0]), stamps=np.array([1.0, 1.0]),
                         submaps=np.array([0, 0]), positions=np.zeros((2, 3)))
    with pytest.raises(MessageError, match="two samples"):
        ex.handle(twice)
    assert ex.tables == {}
