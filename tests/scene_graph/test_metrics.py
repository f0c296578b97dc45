"""Ground-truth rooms from a scenario and the scene-graph metrics on a flawless map."""

from __future__ import annotations

import numpy as np
import pytest

from kimera_multi_py.eval.scene_graph_metrics import scene_graph_metrics
from kimera_multi_py.eval.scene_graph_truth import perfect_octree, true_rooms
from kimera_multi_py.scene_graph import build_scene_graph
from kimera_multi_py.sim.scenario import ScenarioConfig
from kimera_multi_py.sim.world import World

PLAN = {
    "spaces": [
        {"name": "hall", "kind": "corridor", "min": [0.0, 4.0], "max": [12.0, 6.0]},
        {"name": "west", "min": [0.0, 0.0], "max": [6.0, 4.0]},
        {"name": "east", "min": [6.0, 0.0], "max": [12.0, 4.0]},
        {"name": "arm_a", "min": [0.0, 6.0], "max": [4.0, 10.0]},
        {"name": "arm_b", "min": [4.0, 8.0], "max": [9.0, 10.0]},
    ],
    "doors": [{"at": [3.0, 4.0]}, {"at": [9.0, 4.0]}, {"at": [2.0, 6.0]},
              {"at": [4.0, 9.0], "width": 2.0, "leaf": False}],  # arm_a + arm_b: one L-shaped room
}


@pytest.fixture(scope="module")
def world() -> World:
    return World(ScenarioConfig.model_validate(PLAN))


@pytest.fixture(scope="module")
def graph(world: World):
    objects = [(1, "table", (2.0, 1.0, 0.4), (1.5, 0.5, 0.05), (2.5, 1.5, 0.8)),
               (2, "chair", (10.0, 2.0, 0.5), (9.8, 1.8, 0.05), (10.2, 2.2, 0.9)),
               (3, "plant", (7.0, 9.0, 0.5), (6.8, 8.8, 0.05), (7.2, 9.2, 1.0))]
    return build_scene_graph(perfect_octree(world), objects)


def test_true_rooms_join_spaces_open_to_each_other(world: World) -> None:
    tr = true_rooms(world)
    assert tr.names == ["hall", "west", "east", "arm_a+arm_b"]
    assert tr.kinds == ["corridor", "room", "room", "room"]
    assert tr.containing(np.array([[1.0, 1.0, 1.0], [8.0, 9.0, 1.0], [2.0, 9.0, 1.0], [20.0, 0.0, 1.0]])).tolist() \
        == [1, 3, 3, -1]


def test_metrics_on_a_flawless_map(world: World, graph) -> None:
    m = scene_graph_metrics(graph, world)
    assert m["rooms_found"] == m["rooms_true"] == 4
    assert m["room_precision"] > 0.95 and m["room_recall"] > 0.9
    assert m["object_room_accuracy"] == 1.0
    assert m["place_coverage"] > 0.95
    assert sorted(v for v in m["room_match"].values()) == sorted(true_rooms(world).names)
    assert m["nodes_per_layer"]["rooms"] == 4 and m["build_s"] > 0


def test_metrics_see_merged_rooms_and_a_moved_map(world: World, graph) -> None:
    merged = graph.__class__(**{**graph.__dict__, "place_room": np.zeros_like(graph.place_room),
                                "room_pos": graph.room_pos[:1], "room_edges": np.zeros((0, 2), np.int64)})
    m = scene_graph_metrics(merged, world)
    assert m["rooms_found"] == 1 and m["room_precision"] < 0.5  # one room covering four
    assert m["room_recall"] > 0.9 and m["object_room_accuracy"] < 0.5  # recall cannot see a merge; precision does
    T = np.eye(4)
    T[:3, 3] = [3.0, 0.0, 0.0]  # the map is off by 3 m in the world
    moved = scene_graph_metrics(graph, world, T)
    assert moved["room_precision"] < scene_graph_metrics(graph, world)["room_precision"] - 0.1
