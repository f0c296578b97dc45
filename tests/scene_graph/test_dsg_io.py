"""dsg.json through spark_dsg, the networkx view, the queries and the ``kimera-multi query`` CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import spark_dsg as dsg
from typer.testing import CliRunner

from kimera_multi_py.cli.main import app
from kimera_multi_py.scene_graph import (
    SceneGraphError,
    build_scene_graph,
    load_scene_graph,
    objects_in,
    path,
    room_of,
    save_scene_graph,
    to_networkx,
    where,
)
from tests.scene_graph.helpers import TWO_ROOMS, add_box, box_world, octree_of

FIELDS = ["place_ids", "place_pos", "place_clearance", "place_room", "place_edges", "place_edge_clearance", "room_pos",
          "room_edges", "object_ids", "object_class", "object_pos", "object_lo", "object_hi", "object_place",
          "agent_robot", "agent_index", "agent_stamp", "agent_pose", "agent_place", "building_pos"]


@pytest.fixture(scope="module")
def graph():
    c, free = box_world(*TWO_ROOMS)
    free = add_box(c, free, (0.5, 0.5, 0.0), (1.7, 1.3, 0.75))
    objects = [(7, "table", (1.1, 0.9, 0.4), (0.5, 0.5, 0.0), (1.7, 1.3, 0.75)),
               (8, "chair", (6.0, 1.0, 0.45), (5.75, 0.75, 0.0), (6.25, 1.25, 0.9)),
               (9, "chair", (6.5, 3.0, 0.45), (6.25, 2.75, 0.0), (6.75, 3.25, 0.9))]
    traj = {}
    for r, xs in ((0, [1.0, 3.0, 5.0, 7.0]), (1, [7.0, 6.0])):
        poses = np.repeat(np.eye(4)[None], len(xs), axis=0)
        poses[:, :3, 3] = [[x, 2.0, 1.0] for x in xs]
        yaw = 0.3 * r
        poses[:, :2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        traj[r] = (np.arange(len(xs)) * 10.0 + 0.123456789, poses)
    return build_scene_graph(octree_of(c, free), objects, traj)


def test_round_trip_through_spark_dsg(graph, tmp_path: Path) -> None:
    p = save_scene_graph(graph, tmp_path / "dsg.json")
    back = load_scene_graph(p)
    for f in FIELDS:
        np.testing.assert_allclose(getattr(back, f), getattr(graph, f), atol=1e-6, err_msg=f)
    assert back.metadata["delta"] == graph.metadata["delta"]
    # the file is a standard Spark-DSG graph: layers 2..5, parents through the hierarchy
    G = dsg.DynamicSceneGraph.load(str(p))
    assert G.layer_ids == [2, 3, 4, 5]
    assert G.get_layer(3).num_nodes() == len(graph.place_ids) and G.get_layer(4).num_nodes() == 2
    table = G.get_node(dsg.NodeSymbol("O", 7))
    place = G.get_node(table.get_parent())
    assert place.layer.layer == 3
    room = G.get_node(place.get_parent())
    assert dsg.NodeSymbol(room.id.value).category == "R"
    assert room.get_parent() == dsg.NodeSymbol("B", 0).value
    assert G.get_layer(2, ord("b")).num_nodes() == 2  # robot 1's agent partition
    assert table.attributes.name == "table"
    doc = json.loads(p.read_text())
    assert {"nodes", "edges", "layer_keys"} <= set(doc)  # networkx node-link, as Hydra writes it


def test_bad_files_raise(tmp_path: Path) -> None:
    with pytest.raises(SceneGraphError, match="no such"):
        load_scene_graph(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(SceneGraphError, match="not a Spark-DSG file"):
        load_scene_graph(tmp_path / "bad.json")


def test_networkx_view(graph) -> None:
    G = to_networkx(graph)
    assert G.number_of_nodes() == len(graph.place_ids) + 2 + 1 + 3 + 6
    assert G.nodes["O(7)"]["label"] == "table" and G.nodes["B(0)"]["layer"] == 5
    kinds = {d["kind"] for _, _, d in G.edges(data=True)}
    assert kinds == {"hierarchy", "place", "room", "agent"}


def test_room_of_and_objects_in(graph) -> None:
    west = room_of(graph, "O(7)")["room"]
    east = room_of(graph, 8)["room"]
    assert west != east and room_of(graph, "O9")["room"] == east
    assert [o["object"] for o in objects_in(graph, east)] == ["O(8)", "O(9)"]
    assert objects_in(graph, east, "table") == []
    assert [o["object"] for o in objects_in(graph, west, "table")] == ["O(7)"]
    with pytest.raises(SceneGraphError, match="no object O\\(3\\)"):
        room_of(graph, "O(3)")
    with pytest.raises(SceneGraphError, match="no room R\\(5\\)"):
        objects_in(graph, "R(5)")


def test_path_goes_through_the_door(graph) -> None:
    ans = path(graph, [1.0, 1.0, 1.2], [7.0, 3.0, 1.2])
    pts = np.array(ans["waypoints"])
    assert ans["rooms"] == [room_of(graph, 7)["room"], room_of(graph, 8)["room"]]
    cross = np.flatnonzero(np.diff(np.sign(pts[:, 0] - 4.0)) != 0)[0]  # where it crosses the wall
    y = np.interp(4.0, pts[cross:cross + 2, 0], pts[cross:cross + 2, 1])
    assert 1.5 < y < 2.5  # through the door opening
    assert ans["length"] >= np.linalg.norm(pts[-1] - pts[0])
    assert path(graph, "O(7)", "O(7)")["rooms"] == [room_of(graph, 7)["room"]]


def test_where(graph) -> None:
    west, east = room_of(graph, 7)["room"], room_of(graph, 8)["room"]
    assert where(graph, 0, 0.0)["room"] == west
    assert where(graph, 0, 25.0)["node"] == "a(2)"  # last keyframe at or before t
    assert where(graph, "a", 1e9)["room"] == east
    assert where(graph, 1, -5.0)["node"] == "b(0)"
    with pytest.raises(SceneGraphError, match="robot 4 has no poses"):
        where(graph, 4, 0.0)


def test_cli_query(graph, tmp_path: Path) -> None:
    save_scene_graph(graph, tmp_path / "robot1" / "dsg.json")
    runner = CliRunner()
    res = runner.invoke(app, ["query", str(tmp_path), "room-of", "O(8)", "--robot", "1", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["room"] == room_of(graph, 8)["room"]
    res = runner.invoke(app, ["query", str(tmp_path), "objects-in", "R(0)", "--robot", "1"])
    assert res.exit_code == 0 and "O(" in res.output
    res = runner.invoke(app, ["query", str(tmp_path), "path", "1,1,1.2", "O(9)", "--robot", "1", "--json"])
    assert res.exit_code == 0 and json.loads(res.output)["length"] > 5.0
    res = runner.invoke(app, ["query", str(tmp_path), "where", "a", "12.5", "--robot", "1", "--json"])
    assert json.loads(res.output)["node"] == "a(1)"
    res = runner.invoke(app, ["query", str(tmp_path), "where", "0", "1"])  # no RUN_DIR/dsg.json
    assert res.exit_code == 1 and "no such scene-graph file" in res.output
