"""Rooms by kind: the kind table (data) gives each room a kind from its objects; queries accept a
kind wherever they accept a room; the kinds are scored against the scenario's layouts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.semantics import CLASS_IDS
from kimera_multi_py.eval.scene_graph_metrics import scene_graph_metrics
from kimera_multi_py.eval.scene_graph_truth import perfect_octree
from kimera_multi_py.scene_graph import SceneGraphError, build_scene_graph, load_scene_graph, save_scene_graph
from kimera_multi_py.scene_graph.kinds import load_kind_table
from kimera_multi_py.scene_graph.queries import objects_in, people_in
from kimera_multi_py.sim.scenario import load_scenario
from kimera_multi_py.sim.world import World
from tests.scene_graph.helpers import TWO_ROOMS, box_world, octree_of

SIMS = Path(__file__).resolve().parents[2] / "sims"


def box(oid, cls, x, y):
    return (oid, cls, (x, y, 0.45), (x - 0.25, y - 0.25, 0.05), (x + 0.25, y + 0.25, 0.9))


@pytest.fixture(scope="module")
def graph():
    c, free = box_world(*TWO_ROOMS)
    objects = [(1, "bed", (1.5, 3.0, 0.3), (0.7, 2.2, 0.05), (2.3, 3.6, 0.55))]
    objects += [box(10 + i, "chair", 5.0 + 0.6 * i, 1.0) for i in range(5)]
    objects += [(20, "table", (6.0, 2.0, 0.4), (5.0, 1.6, 0.05), (7.0, 2.4, 0.75))]
    people = [{"id": 3, "stamps": [1.0, 2.0], "positions": [[6.5, 3.0, 0.9], [6.6, 3.0, 0.9]]}]
    return build_scene_graph(octree_of(c, free), objects, people=people)


def test_rooms_get_their_kind_with_a_confidence(graph, tmp_path):
    west = int(graph.place_room[np.argmin(graph.place_pos[:, 0])])
    east = 1 - west
    assert graph.room_kind[west] == "bedroom" and graph.room_kind[east] == "meeting"
    assert 0.5 < graph.room_kind_confidence[west] <= 1.0 and 0.5 < graph.room_kind_confidence[east] <= 1.0
    save_scene_graph(graph, tmp_path / "dsg.json")
    back = load_scene_graph(tmp_path / "dsg.json")
    assert back.room_kind == graph.room_kind
    np.testing.assert_allclose(back.room_kind_confidence, graph.room_kind_confidence)


def test_queries_accept_a_kind(graph):
    assert {o["class"] for o in objects_in(graph, "meeting")} == {"chair", "table"}
    assert [o["class"] for o in objects_in(graph, "bedroom")] == ["bed"]
    assert [p["person"] for p in people_in(graph, "meeting", 1.5)] == ["P(3)"]
    assert people_in(graph, "bedroom", 1.5) == []
    with pytest.raises(SceneGraphError, match="no room of kind 'kitchen'"):
        objects_in(graph, "kitchen")


def test_the_rule_is_data(tmp_path):
    (tmp_path / "kinds.toml").write_text('min_score = 0.5\n[kinds.workshop]\nweights = { table = 1.0 }\n')
    t = load_kind_table(tmp_path / "kinds.toml")
    kinds, conf = t.kinds(np.array([0, 1, -1]), np.array([CLASS_IDS["table"], CLASS_IDS["chair"], 1]), 2)
    assert kinds == ["workshop", "unknown"] and conf[0] == 1.0 and conf[1] == 0.0
    (tmp_path / "bad.toml").write_text('[kinds.x]\nweights = { spoon = 1.0 }\n')
    with pytest.raises(ConfigError, match="spoon"):
        load_kind_table(tmp_path / "bad.toml")


def test_kinds_against_the_office_layouts():
    """A flawless map of office.toml with its true objects: the kinds match the layouts' names."""
    world = World(load_scenario(SIMS / "office.toml"))
    objects = [(o.id, o.cls, o.centroid, o.centroid - o.size / 2, o.centroid + o.size / 2) for o in world.objects
               if o.cls != "door"]
    g = build_scene_graph(perfect_octree(world), objects)
    m = scene_graph_metrics(g, world)["room_kinds"]
    assert m["scored"] >= 7 and m["accuracy"] >= 0.9, m["rooms"]
