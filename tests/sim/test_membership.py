"""The team is who is alive: a robot that joins late is aligned and optimised with the others."""

import json

import numpy as np
import pytest

from kimera_multi_py.sim import load_scenario
from kimera_multi_py.sim.runner import SimRunner

from .helpers import REPO

SMALL = REPO / "sims" / "small.toml"


@pytest.mark.slow
def test_a_robot_joining_late_is_aligned_and_in_pgo(tmp_path):
    runner = SimRunner(load_scenario(SMALL), seed=0, mode="distributed", out_dir=tmp_path, join={2: 70.0})
    res = runner.run().to_dict()
    late = runner.nodes[2]
    assert late.agent.stamps[0] == pytest.approx(70.0)
    last = late.pgo.last_pgo
    assert last is not None and last.aligned and len(last.local.inter_edge) > 0
    # robot 2 is a member of the first epoch after it joined, within one PGO period
    first = next(h for h in runner.nodes[0].pgo.history if 2 in h[1])
    assert 70.0 <= first[3] <= 70.0 + runner.schedule.period
    assert all(2 not in h[1] for h in runner.nodes[0].pgo.history if h[3] < 70.0)
    odo = json.loads((tmp_path / "results.json").read_text())["robots"][2]["ate_rmse_m"]
    assert odo == res["robots"][2]["ate_rmse_m"]
    # robot 2's estimate is in the team frame: its part of the team trajectory is as good as the rest
    truth = runner.sim.plans[2].poses[:, :3, 3]
    est = np.array(late.agent.poses)[:, :3, 3]
    T = runner.sim.plans[0].poses[0]  # the team frame is robot 0's first pose
    world = est @ T[:3, :3].T + T[:3, 3]
    assert np.sqrt(np.mean(np.sum((world - truth) ** 2, axis=1))) < 1.0
    assert res["loop_closures"]["false_accepted_inter"] == 0
