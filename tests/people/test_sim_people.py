"""Simulated people: room-to-room routes, pauses, a delayed start, several people at once."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.sim.scenario import HumanConfig, load_scenario
from kimera_multi_py.sim.simulation import Human, Simulation

SIMS = Path(__file__).resolve().parents[2] / "sims"


def test_back_and_forth_without_pauses_is_unchanged():
    h = Human(np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 2.0]]), 1.0, 0.25, 1.75, 0.0)
    for t, xy in ((0.0, (0, 0)), (3.0, (3, 0)), (5.0, (4, 1)), (6.0, (4, 2)), (7.0, (4, 1)), (10.0, (2, 0)),
                  (12.0, (0, 0)), (13.0, (1, 0))):
        np.testing.assert_allclose(h.position(t)[:2], xy, atol=1e-12)
    assert h.position(0.0)[2] == pytest.approx(1.75 / 2)


def test_pauses_start_and_loop():
    h = Human(np.array([[0.0, 0.0], [4.0, 0.0]]), 1.0, 0.25, 1.75, 0.0, np.array([2.0, 1.0]), start=3.0, loop=True)
    # stands until 3 s, then 2 s at the first waypoint; walks 4 s; 1 s at the second; walks back
    for t, x in ((0.0, 0), (4.9, 0), (6.0, 1), (9.0, 4), (9.9, 4), (11.0, 3), (14.0, 0), (16.0, 0), (17.0, 1)):
        assert h.position(t)[0] == pytest.approx(x), t


def test_route_people_pause_in_rooms_not_in_doors():
    cfg = load_scenario(SIMS / "people.toml")
    sim = Simulation(cfg, 0)
    assert len(sim.humans) >= 3
    walker = sim.humans[[h.route is not None for h in cfg.humans].index(True)]
    # the route is planned through doors: every point of the path is inside the building
    xy = np.array([walker.position(t)[:2] for t in np.arange(0, walker.period, 0.5)])
    spaces = {s.name: s for s in cfg.spaces}
    assert all(any(s.min[0] <= x <= s.max[0] and s.min[1] <= y <= s.max[1] for s in spaces.values()) for x, y in xy)
    visited = {n for n, s in spaces.items() for x, y in xy if s.min[0] < x < s.max[0] and s.min[1] < y < s.max[1]}
    assert {"office_b", "meeting", "lounge", "corridor"} <= visited
    # it stands still somewhere (a pause), and never at a door's opening
    still = np.flatnonzero(np.all(np.abs(np.diff(xy, axis=0)) < 1e-9, axis=1))
    assert len(still) > 0
    doors = np.array([d.center for d in sim.world.doors])
    assert np.linalg.norm(xy[still][:, None] - doors[None], axis=2).min() > 0.5


def test_people_cross_in_a_room_and_in_the_corridor():
    cfg = load_scenario(SIMS / "people.toml")
    sim = Simulation(cfg, 0)
    t = np.arange(0.0, sim.duration, 0.25)
    pos = np.array([[h.position(s)[:2] for s in t] for h in sim.humans])  # (people, time, 2)
    gap = np.linalg.norm(pos[:, None] - pos[None], axis=3)  # (p, p, time)
    close = {(i, j) for i in range(len(pos)) for j in range(i + 1, len(pos)) if gap[i, j].min() < 1.5}
    in_corridor = lambda p: 5.0 < p[1] < 7.0  # noqa: E731
    where = {"corridor": False, "room": False}
    for i, j in close:
        k = int(np.argmin(gap[i, j]))
        where["corridor" if in_corridor(pos[i, k]) else "room"] = True
    assert where == {"corridor": True, "room": True}


def test_a_human_needs_one_path():
    with pytest.raises(ValueError, match="exactly one"):
        HumanConfig(waypoints=[(0.0, 0.0), (1.0, 0.0)], route=["a"])
    with pytest.raises(ValueError, match="exactly one"):
        HumanConfig()


def test_unknown_room_in_a_human_route(tmp_path):
    text = (SIMS / "people.toml").read_text().replace('route = ["office_b", "meeting", "lounge"]',
                                                       'route = ["office_b", "kitchen"]')
    (tmp_path / "bad.toml").write_text(text)
    with pytest.raises(ConfigError, match=r"humans\[2\]\.route\[1\]"):
        load_scenario(tmp_path / "bad.toml")
