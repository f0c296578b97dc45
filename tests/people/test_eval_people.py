"""The people figures' ground truth: who is in view of a keyframe, and detections scored."""

from __future__ import annotations

import numpy as np

from kimera_multi_py.core.geometry import yaw_pose
from kimera_multi_py.eval.people import people_in_view
from kimera_multi_py.sim import load_scenario
from kimera_multi_py.sim.scenario import HumanConfig, SensorConfig
from kimera_multi_py.sim.simulation import Simulation
from tests.sim.helpers import TINY


def test_people_in_view_sees_through_free_space_only():
    cfg = load_scenario(TINY).model_copy(update={
        "sensor": SensorConfig(rows=32, cols=48),
        "humans": [HumanConfig(waypoints=[(5.0, 5.0), (5.0, 5.1)], speed=0.01),  # in the corridor
                   HumanConfig(waypoints=[(2.0, 2.0), (2.0, 2.1)], speed=0.01)]})  # in room_a
    sim = Simulation(cfg, 0)
    z = sim.world.floor_z + cfg.sensor.height
    east = yaw_pose(1.5, 5.0, z, 0.0)  # in the corridor, looking east at the first person
    assert people_in_view(sim, east, 0.0).tolist() == [0]
    west = yaw_pose(7.5, 5.0, z, np.pi)  # looking west: the first person is in view again
    assert people_in_view(sim, west, 0.0).tolist() == [0]
    away = yaw_pose(4.0, 5.0, z, np.pi)  # the first person is behind the sensor
    assert people_in_view(sim, away, 0.0).tolist() == []
    # looking south from the corridor at room_a's wall: the second person is behind it
    south = yaw_pose(3.5, 5.0, z, -np.pi / 2)
    assert 1 not in people_in_view(sim, south, 0.0).tolist()
    # from room_a's door, looking in
    door = yaw_pose(2.0, 4.3, z, -np.pi / 2)
    assert 1 in people_in_view(sim, door, 0.0).tolist()
    assert people_in_view(sim, door, 0.0, min_hits=10_000).tolist() == []


def test_a_person_hidden_behind_another_is_not_in_view():
    """The rays that pass near the far person stop at the near one: only the near one is in view
    (counting every ray that ends on someone held the hidden person in view, a miss for recall)."""
    cfg = load_scenario(TINY).model_copy(update={
        "sensor": SensorConfig(rows=32, cols=48),
        "humans": [HumanConfig(waypoints=[(3.0, 5.0), (3.0, 5.1)], speed=0.01),
                   HumanConfig(waypoints=[(5.0, 5.0), (5.0, 5.1)], speed=0.01)]})
    sim = Simulation(cfg, 0)
    z = sim.world.floor_z + cfg.sensor.height
    east = yaw_pose(1.5, 5.0, z, 0.0)  # the corridor, the two people in line ahead
    assert people_in_view(sim, east, 0.0).tolist() == [0]
    west = yaw_pose(7.5, 5.0, z, np.pi)  # from the other end the other one hides the first
    assert people_in_view(sim, west, 0.0).tolist() == [1]
