"""People end to end: a simulated team tracks a person walking the corridor, shares the tracks,
writes them into dsg.json and scores them against the truth (slow)."""

from __future__ import annotations

import json

import pytest

from kimera_multi_py.scene_graph import load_scene_graph
from kimera_multi_py.scene_graph.queries import occupied_rooms, rooms_visited
from kimera_multi_py.sim import load_scenario
from kimera_multi_py.sim.scenario import HumanConfig, SensorConfig
from kimera_multi_py.workflow.simulate import SimRunner
from tests.sim.helpers import TINY


@pytest.mark.slow
def test_a_team_tracks_shares_and_scores_people(tmp_path):
    cfg = load_scenario(TINY)
    cfg = cfg.model_copy(update={
        "sensor": SensorConfig(rows=32, cols=48, max_range=8.0),
        "humans": [HumanConfig(waypoints=[(0.6, 5.3), (7.4, 5.3)], speed=0.5)]})
    SimRunner(cfg, seed=0, mode="distributed", out_dir=tmp_path).run()
    r = json.loads((tmp_path / "results.json").read_text())
    people = r["people"]
    assert people["people_true"] == 1 and people["people_tracked"] >= 1
    det = people["detection"]
    assert det["people_in_view"] > 5 and det["precision"] >= 0.8 and det["recall"] >= 0.5
    assert people["trajectory_rmse"]["human0"] < 0.3
    assert people["mota"] is not None and people["id_switches"] is not None
    assert people["ids_agree"] is True
    assert "map/people" in r["bytes_sent"]["per_topic"]
    for robot in (0, 1):
        g = load_scene_graph(tmp_path / f"robot{robot}" / "dsg.json")
        assert len(g.person_id) > 0
        pid = int(g.person_id[0])
        assert rooms_visited(g, pid)
        t = float(g.person_stamp[len(g.person_stamp) // 2])
        assert any(f"P({pid})" in o["people"] for o in occupied_rooms(g, t)) or g.person_room().max() < 0
    saved = json.loads((tmp_path / "robot0" / "people.json").read_text())
    assert saved["tracks"] and saved["keyframes"] and saved["team"] is not None
