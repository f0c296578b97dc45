"""The run workflow (build, score, write), graph agreement, landmarks as input and the Rerun drawing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kimera_multi_py.eval.scene_graph import graphs_agree, scene_graph_and_outputs, scene_graph_outputs
from kimera_multi_py.mapping import morton
from kimera_multi_py.mapping.landmark import Landmark
from kimera_multi_py.scene_graph import load_scene_graph
from kimera_multi_py.scene_graph.viz import log_scene_graph
from tests.scene_graph.helpers import RES, TWO_ROOMS, K, box_world, octree_of

KEYS = {"rooms_found", "rooms_true", "room_precision", "room_recall", "object_room_accuracy", "place_coverage",
        "nodes_per_layer", "build_s"}


@pytest.fixture(scope="module")
def tree():
    return octree_of(*box_world(*TWO_ROOMS))


def _landmark(lid: int, cls: int, lo: np.ndarray, hi: np.ndarray) -> Landmark:
    c = np.stack(np.meshgrid(*[np.arange(a, b, RES) + RES / 2 for a, b in zip(lo, hi, strict=True)],
                             indexing="ij"), -1).reshape(-1, 3)
    codes = np.sort(morton.points_to_codes(c, RES))
    counts = np.ones(K + 1)
    counts[cls] = 50.0
    return Landmark(lid, 0, counts, c.sum(0), len(c), codes, np.full(len(codes), 5), resolution=RES)


def test_outputs_without_a_world(tree, tmp_path: Path) -> None:
    lms = [_landmark(4, 6, np.array([0.6, 0.6, 0.0]), np.array([1.6, 1.2, 0.7])),
           _landmark(5, 5, np.array([6.0, 3.0, 0.0]), np.array([6.5, 3.5, 0.9]))]
    T = np.eye(4)
    T[:3, 3] = [10.0, 0.0, 0.0]
    m = scene_graph_outputs(tree, T, lms, None, None, tmp_path / "robot0" / "dsg.json")
    assert m["rooms_found"] == 2 and m["nodes_per_layer"]["objects"] == 2
    g = load_scene_graph(tmp_path / "robot0" / "dsg.json")
    assert g.metadata["T_world_map"] == T.tolist()
    assert g.object_class.tolist() == [6, 5]
    np.testing.assert_allclose(g.object_pos[0], lms[0].position)
    assert g.object_room()[0] != g.object_room()[1]


def test_graphs_of_one_map_agree_and_of_two_do_not(tree) -> None:
    a, _ = scene_graph_and_outputs(tree, None, [], None, None, None)
    b, _ = scene_graph_and_outputs(tree, None, [], None, None, None)
    assert graphs_agree([a, b]) == {"places": True, "rooms": True, "object_rooms": True}
    c, free = box_world(*TWO_ROOMS)
    other, _ = scene_graph_and_outputs(octree_of(c, free & (c[:, 0] < 6.0)), None, [], None, None, None)
    assert not graphs_agree([a, other])["places"]


def test_rerun_drawing(tree, tmp_path: Path) -> None:
    import rerun as rr

    g, _ = scene_graph_and_outputs(tree, None, [(1, "chair", (1.0, 1.0, 0.5), (0.8, 0.8, 0.0), (1.2, 1.2, 0.9))],
                                   {0: (np.arange(2.0), np.repeat(np.eye(4)[None], 2, 0))}, None, None)
    rec = rr.RecordingStream("test-dsg")
    rec.save(str(tmp_path / "dsg.rrd"))
    log_scene_graph(g, rec, layer_gap=2.0)
    rec.flush()
    assert (tmp_path / "dsg.rrd").stat().st_size > 1000


def test_keys_of_results(tree) -> None:
    from kimera_multi_py.sim.scenario import ScenarioConfig

    cfg = ScenarioConfig.model_validate({"spaces": [{"name": "w", "min": [0.0, 0.0], "max": [4.0, 4.0]},
                                                    {"name": "e", "min": [4.0, 0.0], "max": [8.0, 4.0]}],
                                         "doors": [{"at": [4.0, 2.0], "leaf": False}]})
    m = scene_graph_outputs(tree, None, [], None, cfg, None)
    assert KEYS <= set(m)
    assert m["rooms_found"] == m["rooms_true"] == 2 and m["room_precision"] > 0.9


def test_team_objects_have_unique_ids(tree) -> None:
    from kimera_multi_py.scene_graph import build_scene_graph, team_objects

    lm = _landmark(0, 6, np.array([0.6, 0.6, 0.0]), np.array([1.6, 1.2, 0.7]))
    objs = team_objects({0: [lm], 2: [lm]})
    assert [o[0] for o in objs] == [0, 2 << 24]
    assert build_scene_graph(tree, objs).object_ids.tolist() == [0, 2 << 24]


def test_outcome_objects_as_dicts(tree) -> None:
    from kimera_multi_py.scene_graph import SceneGraphError, build_scene_graph

    ob = {"id": 3, "class": 5, "centroid": [6.0, 2.0, 0.5], "lo": [5.8, 1.8, 0.0], "hi": [6.2, 2.2, 0.9],
          "sightings": 9}
    g = build_scene_graph(tree, [ob])
    assert g.object_ids.tolist() == [3] and g.object_class.tolist() == [5]
    with pytest.raises(SceneGraphError, match="missing key 'hi'"):
        build_scene_graph(tree, [{k: v for k, v in ob.items() if k != "hi"}])
