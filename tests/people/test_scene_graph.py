"""People in dsg.json: dynamic agents of layer 2 written through spark_dsg, read back, and asked
about (queries and the ``kimera-multi query`` CLI)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import spark_dsg as dsg
from typer.testing import CliRunner

from kimera_multi_py.cli.main import app
from kimera_multi_py.scene_graph import SceneGraphError, build_scene_graph, load_scene_graph, save_scene_graph
from kimera_multi_py.scene_graph.dsg_io import PEOPLE_PARTITION, to_networkx
from kimera_multi_py.scene_graph.queries import occupied_rooms, people_in, rooms_visited, where_was
from tests.scene_graph.helpers import TWO_ROOMS, box_world, octree_of

WALKER, SITTER = 16777219, 5  # a team id (robot 1, track 3) and a robot 0 track


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    c, free = box_world(*TWO_ROOMS)
    t = np.arange(0.0, 11.0)
    walker = np.column_stack([1.0 + 0.6 * t, np.full(len(t), 2.0), np.full(len(t), 0.9)])  # west -> east
    sitter = np.column_stack([np.full(4, 6.5), np.full(4, 1.0), np.full(4, 0.9)])
    people = [{"id": WALKER, "stamps": t.tolist(), "positions": walker.tolist()},
              {"id": SITTER, "stamps": [2.0, 3.0, 8.0, 9.0], "positions": sitter.tolist()}]
    traj = {0: (np.array([0.0, 5.0]), np.repeat(np.eye(4)[None], 2, axis=0))}
    g = build_scene_graph(octree_of(c, free), [], traj, people=people)
    d = tmp_path_factory.mktemp("run")
    save_scene_graph(g, d / "dsg.json")
    return g, d


def rooms_by_x(g):
    west = int(g.person_room()[np.argmin(g.person_pos[:, 0])])
    east = int(g.person_room()[np.argmax(g.person_pos[:, 0])])
    assert west != east and min(west, east) >= 0
    return west, east


def test_people_are_layer_2_agents_with_a_partition_each(saved):
    g, d = saved
    G = dsg.DynamicSceneGraph.load(str(d / "dsg.json"))
    people = [n for n in G.nodes if n.id.category == "H"]
    assert len(people) == 11 + 4
    assert {n.layer.layer for n in people} == {2}
    assert {n.layer.partition for n in people} == {PEOPLE_PARTITION, PEOPLE_PARTITION + 1}
    for n in people:
        meta = n.attributes.metadata.get()
        assert meta["person"] in (WALKER, SITTER)
        assert n.attributes.timestamp.total_seconds() == pytest.approx(meta["stamp"])
        parents = {dsg.NodeSymbol(p).category for p in n.parents()}
        assert parents == {"p", "R"}  # the place and the room it is in
    # the robot's own poses stay where they were
    assert sum(n.id.category == "a" for n in G.nodes) == 2


def test_people_round_trip(saved):
    g, d = saved
    h = load_scene_graph(d / "dsg.json")
    for f in ("person_id", "person_stamp", "person_pos", "person_place"):
        np.testing.assert_allclose(getattr(h, f), getattr(g, f), err_msg=f)
    assert len(h.agent_robot) == 2  # people are not taken for robots
    assert h.nodes_per_layer()["people"] == 2
    assert to_networkx(h).nodes["H(0)"]["person"] in (WALKER, SITTER)


def test_people_queries(saved):
    _, d = saved
    g = load_scene_graph(d / "dsg.json")
    west, east = rooms_by_x(g)
    assert [p["person"] for p in people_in(g, west, 1.0)] == [f"P({WALKER})"]
    assert sorted(p["person"] for p in people_in(g, east, 8.0)) == sorted([f"P({WALKER})", f"P({SITTER})"])
    assert people_in(g, east, 0.5) == []  # the walker is still west, the sitter not yet seen
    occ = occupied_rooms(g, 2.0)
    assert {o["room"]: sorted(o["people"]) for o in occ} == {f"R({west})": [f"P({WALKER})"],
                                                             f"R({east})": [f"P({SITTER})"]}
    w = where_was(g, f"P({WALKER})", 2.5)
    assert w["seen"] and w["position"][0] == pytest.approx(1.0 + 0.6 * 2.5, abs=1e-3)
    assert w["room"] == f"R({west})"
    assert not where_was(g, SITTER, 20.0)["seen"]
    visits = rooms_visited(g, WALKER)
    assert [v["room"] for v in visits] == [f"R({west})", f"R({east})"]
    assert visits[0]["first"] == 0.0 and visits[-1]["last"] == 10.0
    with pytest.raises(SceneGraphError, match="no person"):
        where_was(g, "P(77)", 1.0)


def test_cli_people_queries(saved):
    g, d = saved
    west, east = rooms_by_x(g)
    runner = CliRunner()
    res = runner.invoke(app, ["query", str(d), "people-in", f"R({east})", "--at", "8", "--json"])
    assert res.exit_code == 0, res.output
    assert sorted(p["person"] for p in json.loads(res.output)) == sorted([f"P({WALKER})", f"P({SITTER})"])
    res = runner.invoke(app, ["query", str(d), "where-was", f"P({WALKER})", "--at", "9", "--json"])
    assert res.exit_code == 0 and json.loads(res.output)["room"] == f"R({east})"
    res = runner.invoke(app, ["query", str(d), "rooms-visited", str(WALKER), "--json"])
    assert [v["room"] for v in json.loads(res.output)] == [f"R({west})", f"R({east})"]
    res = runner.invoke(app, ["query", str(d), "occupied-rooms", "--at", "9"])
    assert res.exit_code == 0 and f"P({SITTER})" in res.output
    res = runner.invoke(app, ["query", str(d), "where-was", "P(77)", "--at", "9"])
    assert res.exit_code == 1 and "no person P(77)" in res.output


def test_bad_people_input_is_refused():
    c, free = box_world(*TWO_ROOMS)
    with pytest.raises(SceneGraphError, match="finite"):
        build_scene_graph(octree_of(c, free), people=[{"id": 1, "stamps": [0.0], "positions": [[np.nan, 0, 0]]}])
    with pytest.raises(SceneGraphError, match="people\\[0\\]"):
        build_scene_graph(octree_of(c, free), people=[{"id": 1, "stamps": [0.0, 1.0], "positions": [[0, 0, 0]]}])


def test_empty_save(tmp_path: Path):
    c, free = box_world(*TWO_ROOMS)
    g = build_scene_graph(octree_of(c, free))
    save_scene_graph(g, tmp_path / "dsg.json")
    assert len(load_scene_graph(tmp_path / "dsg.json").person_id) == 0


def test_rerun_shows_each_person_with_their_id(tmp_path):
    from kimera_multi_py.viz.rerun_viz import RerunViz

    viz = RerunViz(tmp_path / "people.rrd")
    viz.log_people(3.0, [(12, np.array([[1.0, 2.0, 0.9], [1.5, 2.0, 0.9]])), (5, np.zeros((0, 3)))])
    viz.close()
    data = (tmp_path / "people.rrd").read_bytes()
    assert b"P12" in data and b"P(12)" in data  # the entity and the label with the person's id
    assert b"P5" not in data  # nothing to show for a person without samples
