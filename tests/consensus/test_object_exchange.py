"""Object sharing: tables flood the team, follow PGO through the pose tables, and fuse the same everywhere."""

import numpy as np
import pytest

from kimera_multi_py.comms.messages.maps import ObjectUpdate, SubmapPoses
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.geometry import make_pose
from kimera_multi_py.mapping import ObjectMap
from kimera_multi_py.mapping.object_fusion import fuse_objects, object_groups, team_id
from kimera_multi_py.mapshare.objects import ObjectExchange

from ..mapping.helpers import CHAIR, TABLE, K
from ..mapping.test_objects import OBJECT_CLASSES, box_points

NC = K + 1  # class posterior length (free + K classes)


class Robot:
    """A robot's object map in one submap (id 0, created at ``T_ref``) and its pose table."""

    def __init__(self, robot: int, objects: list[tuple[tuple[float, float], int]], T_ref: np.ndarray,
                 seed: int) -> None:
        rng = np.random.default_rng(seed)
        self.robot = robot
        self.om = ObjectMap(K, OBJECT_CLASSES, resolution=0.1, confirm_after=2)
        self.om.set_submap_pose(0, T_ref)
        self.T_ref, self.T = T_ref.copy(), T_ref.copy()
        self.version = 1
        for _ in range(3):
            pts, lab = [], []
            for (x, y), cls in objects:
                p = box_points([x, y, 0.45], [0.5, 0.5, 0.9], 40, rng)
                pts.append(p)
                lab.append(np.full(len(p), cls))
            self.om.update(np.concatenate(pts), np.concatenate(lab), 0)
        self.held: dict[int, SubmapPoses] = {robot: self.table()}
        self.ex = ObjectExchange(robot, self.om.confirmed, self.held.get, NC, period=1.0, refresh_every=3)

    def table(self) -> SubmapPoses:
        return SubmapPoses(robot=self.robot, source=self.robot, version=self.version, frame=0,
                           submaps=np.array([0]), T_ref=self.T_ref[None], T=self.T[None])

    def move(self, T: np.ndarray) -> None:
        """PGO moved the submap: the object map re-anchors, a new pose table is made."""
        self.T = T.copy()
        self.version += 1
        self.om.set_submap_pose(0, T)
        self.held[self.robot] = self.table()


def run(robots: list[Robot], links: set[tuple[int, int]], periods: int, t0: float = 0.0,
        drop: float = 0.0, seed: int = 0) -> float:
    """Step every robot each period; deliver what it publishes to its linked neighbours (the pose
    tables too, as the map consensus would)."""
    rng = np.random.default_rng(seed)
    nbrs = {r.robot: {b for a, b in links if a == r.robot} | {a for a, b in links if b == r.robot} for r in robots}
    t = t0
    for _ in range(periods):
        for r in robots:
            r.ex.set_neighbours(nbrs[r.robot])
            r.ex.set_frame(0)
        out = [(r.robot, m) for r in robots for m in r.ex.step(t)]
        for src, m in out:
            for r in robots:
                if r.robot in nbrs[src] and rng.random() >= drop:
                    r.ex.handle(m)
        # pose tables reach everyone (the map consensus's job, tested elsewhere)
        for r in robots:
            for q in robots:
                r.held[q.robot] = q.held[q.robot]
        t += 1.0
    return t


def test_every_robot_ends_with_the_same_team_objects_over_a_chain() -> None:
    # 0 - 1 - 2: robot 2 hears robot 0 only through robot 1's relay
    a = Robot(0, [((1.0, 1.0), CHAIR), ((3.0, 1.0), TABLE)], np.eye(4), 0)
    b = Robot(1, [((1.02, 1.0), CHAIR)], np.eye(4), 1)  # the same chair, seen by robot 1
    c = Robot(2, [((6.0, 2.0), CHAIR)], np.eye(4), 2)
    robots = [a, b, c]
    run(robots, {(0, 1), (1, 2)}, 4)
    team = [r.ex.team_objects() for r in robots]
    assert team[0] == team[1] == team[2]
    ids = sorted(o["id"] for o in team[0])
    # one fused chair from robots 0 and 1, robot 0's table, robot 2's chair
    assert len(ids) == 3
    fused = [o for o in team[0] if len(o["members"]) == 2]
    assert len(fused) == 1 and fused[0]["class"] == CHAIR
    assert {m >> 24 for m in fused[0]["members"]} == {0, 1}
    assert fused[0]["id"] == min(fused[0]["members"])
    assert np.allclose(fused[0]["centroid"][:2], [1.01, 1.0], atol=0.1)
    assert any(o["class"] == CHAIR and np.allclose(o["centroid"][:2], [6.0, 2.0], atol=0.1) for o in team[0])


def test_a_pgo_correction_moves_everyones_copy_without_a_new_table() -> None:
    a = Robot(0, [((1.0, 1.0), CHAIR)], np.eye(4), 0)
    b = Robot(1, [((4.0, 1.0), TABLE)], np.eye(4), 1)
    t = run([a, b], {(0, 1)}, 2)
    sent = a.ex._published[0]
    a.move(make_pose(np.eye(3), [0.5, -0.25, 0.0]))
    run([a, b], {(0, 1)}, 2, t0=t)
    chair = [o for o in b.ex.team_objects() if o["class"] == CHAIR]
    assert len(chair) == 1 and np.allclose(chair[0]["centroid"][:2], [1.5, 0.75], atol=0.1)
    assert b.ex.team_objects() == a.ex.team_objects()
    assert a.ex._published[0] == sent  # the objects did not change, only the pose table


def test_lost_tables_are_recovered_by_the_refresh() -> None:
    robots = [Robot(i, [((1.0 + 3 * i, 1.0), CHAIR)], np.eye(4), i) for i in range(3)]
    run(robots, {(0, 1), (1, 2), (0, 2)}, 12, drop=0.5, seed=3)
    team = [r.ex.team_objects() for r in robots]
    assert team[0] == team[1] == team[2] and len(team[0]) == 3


def test_a_table_from_another_frame_waits() -> None:
    a = Robot(0, [((1.0, 1.0), CHAIR)], np.eye(4), 0)
    b = Robot(1, [((4.0, 1.0), TABLE)], np.eye(4), 1)
    run([a, b], {(0, 1)}, 2)
    other = b.held[1]
    a.held[1] = SubmapPoses(robot=1, source=1, version=other.version + 1, frame=1, submaps=other.submaps,
                            T_ref=other.T_ref, T=other.T)
    assert [o["class"] for o in a.ex.team_objects()] == [CHAIR]  # robot 1 is not in frame 0 yet


def test_inconsistent_tables_are_refused() -> None:
    a = Robot(0, [((1.0, 1.0), CHAIR)], np.eye(4), 0)
    a.ex.set_neighbours({1})
    bad = ObjectUpdate(robot=1, source=1, version=1, frame=0, ids=np.array([3, 3]), submaps=np.zeros(2, np.int64),
                       classes=np.full(2, CHAIR, np.int32), probs=np.full((2, NC), 1.0 / NC, np.float32),
                       centroids=np.zeros((2, 3)), extents=np.ones((2, 3)), sightings=np.ones(2, np.int32))
    with pytest.raises(MessageError, match="duplicate"):
        a.ex.handle(bad)
    narrow = ObjectUpdate(robot=1, source=1, version=1, frame=0, ids=np.array([3]), submaps=np.zeros(1, np.int64),
                          classes=np.full(1, CHAIR, np.int32), probs=np.full((1, 3), 0.3, np.float32),
                          centroids=np.zeros((1, 3)), extents=np.ones((1, 3)), sightings=np.ones(1, np.int32))
    with pytest.raises(MessageError, match="classes"):
        a.ex.handle(narrow)
    assert 1 not in a.ex.tables


def test_fusion_is_independent_of_row_order() -> None:
    rng = np.random.default_rng(5)
    lo = rng.uniform(0, 5, (12, 3))
    hi = lo + rng.uniform(0.3, 0.8, (12, 3))
    cls = rng.choice([CHAIR, TABLE], 12)
    ids = np.array([team_id(i % 3, i) for i in range(12)])
    perm = rng.permutation(12)
    assert fuse_objects(ids, cls, lo, hi, np.ones(12)) == fuse_objects(ids[perm], cls[perm], lo[perm], hi[perm],
                                                                          np.ones(12))
    comp = object_groups(cls, lo, hi)
    assert comp[0] == 0 and set(comp.tolist()) == set(range(comp.max() + 1))


def _team(holds: bool) -> tuple[list[Robot], int]:
    """Three robots that all hear each other, a PGO move half-way; the messages sent. ``holds``
    False: the robots forget what their neighbours said they hold (every table is relayed)."""
    robots = [Robot(0, [((1.0, 1.0), CHAIR)], np.eye(4), 0), Robot(1, [((3.0, 1.0), TABLE)], np.eye(4), 1),
              Robot(2, [((6.0, 2.0), CHAIR)], np.eye(4), 2)]
    sent = 0
    steps = [r.ex.step for r in robots]
    for r, step in zip(robots, steps, strict=True):
        def counted(now: float, r: Robot = r, step=step) -> list:
            nonlocal sent
            if not holds:
                r.ex.peer_holds.clear()
            out = step(now)
            sent += len(out)
            return out
        r.ex.step = counted  # type: ignore[method-assign]
    t = run(robots, {(0, 1), (1, 2), (0, 2)}, 5)
    robots[1].move(make_pose(np.eye(3), [0.5, 0.0, 0.0]))
    run(robots, {(0, 1), (1, 2), (0, 2)}, 7, t0=t)
    return robots, sent


def test_a_table_every_neighbour_holds_is_not_sent_again() -> None:
    (with_holds, fewer), (without, more) = _team(True), _team(False)
    assert fewer < more / 2
    for a, b in zip(with_holds, without, strict=True):
        assert sorted(a.ex.tables) == sorted(b.ex.tables) == [0, 1, 2]
        assert all(a.ex.tables[s].version == b.ex.tables[s].version for s in a.ex.tables)
        assert a.ex.team_objects() == b.ex.team_objects()


def test_a_restarted_robot_continues_its_versions_above_what_its_neighbours_hold() -> None:
    """The exchange is not checkpointed: a robot that restarts counts its table versions from 0
    again. Its neighbour still holds its old table at a higher version, and would ignore the new
    table as a duplicate; hearing the neighbour's holdings, the restarted robot continues above
    them, and the neighbour ends with the new table."""
    a = Robot(0, [((1.0, 1.0), CHAIR)], np.eye(4), 0)
    b = Robot(1, [((4.0, 1.0), TABLE)], np.eye(4), 1)
    t = run([a, b], {(0, 1)}, 2)
    for x in (2.0, 3.0, 4.0):  # robot 0's table goes through several versions
        a.om = ObjectMap(K, OBJECT_CLASSES, resolution=0.1, confirm_after=2)
        a.om.set_submap_pose(0, a.T)
        rng = np.random.default_rng(int(x))
        for _ in range(3):
            p = box_points([x, 1.0, 0.45], [0.5, 0.5, 0.9], 40, rng)
            a.om.update(p, np.full(len(p), CHAIR), 0)
        a.ex.landmarks = a.om.confirmed
        t = run([a, b], {(0, 1)}, 1, t0=t)
    held = b.ex.tables[0].version
    assert held >= 3
    # robot 0 restarts: a fresh exchange, its map as before the restart plus a table
    rng = np.random.default_rng(9)
    for _ in range(3):
        p = box_points([7.0, 2.0, 0.45], [0.5, 0.5, 0.9], 40, rng)
        a.om.update(p, np.full(len(p), TABLE), 0)
    a.ex = ObjectExchange(0, a.om.confirmed, a.held.get, NC, period=1.0, refresh_every=3)
    run([a, b], {(0, 1)}, 2 * a.ex.refresh_every, t0=t)  # the neighbour's refresh says what it holds
    assert b.ex.tables[0].version > held
    assert b.ex.team_objects() == a.ex.team_objects()
    assert any(o["class"] == TABLE and np.allclose(o["centroid"][:2], [7.0, 2.0], atol=0.1)
               for o in b.ex.team_objects())


def test_in_a_team_that_hears_itself_a_changing_table_is_not_relayed() -> None:
    """Three robots that all hear each other, each finding a new object every period: every new
    version reaches the others from its source, and the others say so in their own tables before
    anyone would relay it, so nothing is relayed (each robot relayed each version once before the
    relay waited a period); every robot still ends with every table's newest version."""
    robots = [Robot(i, [((1.0 + 3 * i, 1.0), CHAIR)], np.eye(4), i) for i in range(3)]
    links = {(0, 1), (1, 2), (0, 2)}
    relayed: list = []
    for r in robots:
        def counted(now: float, step=r.ex.step) -> list:
            out = step(now)
            relayed.extend(m for m in out if m.source != m.robot)
            return out
        r.ex.step = counted  # type: ignore[method-assign]
    t = 0.0
    for period in range(6):
        for r in robots:  # a new object, seen three times: a new version of the robot's table
            rng = np.random.default_rng(10 * period + r.robot)
            for _ in range(3):
                p = box_points([1.0 + 3 * r.robot, 3.0 + period, 0.45], [0.5, 0.5, 0.9], 40, rng)
                r.om.update(p, np.full(len(p), TABLE), 0)
        t = run(robots, links, 1, t0=t)
    newest = {r.robot: r.ex.tables[r.robot].version for r in robots}
    run(robots, links, 1, t0=t)
    assert relayed == []
    assert all(v >= 6 for v in newest.values())
    for r in robots:
        assert {s: tab.version for s, tab in r.ex.tables.items()} == newest
