"""The team is who is alive: a robot that joins late is aligned and optimised with the others."""

import json

import numpy as np
import pytest

from kimera_multi_py.sim import load_scenario
from kimera_multi_py.workflow.simulate import SimRunner

from .helpers import REPO

FAULTS = REPO / "sims" / "faults.toml"  # small's building, 39 s of stream (see tests/sim/test_faults.py)
JOIN = 20.0  # robot 2 starts after the team's first epoch is due, when the others are halfway


@pytest.mark.slow
def test_a_robot_joining_late_is_aligned_and_in_pgo(tmp_path):
    runner = SimRunner(load_scenario(FAULTS), seed=0, mode="distributed", out_dir=tmp_path, join={2: JOIN},
                       pgo_period=20.0, quality=False)
    res = runner.run().to_dict()
    late = runner.nodes[2]
    assert late.agent.stamps[0] == pytest.approx(JOIN)
    last = late.pgo.last_pgo
    assert last is not None and last.frame.aligned and len(last.local.inter_edge) > 0
    # robot 2 is a member of the first epoch after it joined, within one PGO period
    first = next(h for h in runner.nodes[0].pgo.history if 2 in h[1])
    assert JOIN <= first[3] <= JOIN + runner.schedule.period
    assert all(2 not in h[1] for h in runner.nodes[0].pgo.history if h[3] < JOIN)
    odo = json.loads((tmp_path / "results.json").read_text())["robots"][2]["ate_rmse_m"]
    assert odo == res["robots"][2]["ate_rmse_m"]
    # robot 2's estimate is in the team frame: its part of the team trajectory is as good as the rest
    truth = runner.sim.plans[2].poses[:, :3, 3]
    est = np.array(late.agent.poses)[:, :3, 3]
    T = runner.sim.plans[0].poses[0]  # the team frame is robot 0's first pose
    world = est @ T[:3, :3].T + T[:3, 3]
    assert np.sqrt(np.mean(np.sum((world - truth) ** 2, axis=1))) < 1.0
    assert res["loop_closures"]["false_accepted_inter"] == 0


@pytest.mark.slow
def test_a_robot_that_leaves_does_not_stall_the_team():
    """Robot 2 disappears mid-run: the others are not held up by it, finish, and it is dropped
    from the schedule (later epochs are the two of them)."""
    from .helpers import TINY

    runner = SimRunner(load_scenario(TINY, robots=3), seed=0, mode="distributed", leave={2: 30.0})
    res = runner.run().to_dict()
    a, b, gone = runner.nodes
    assert a.complete and b.complete and not gone.complete
    assert gone.agent.stamps[-1] < 30.0 and res["robots"][2]["keyframes"] == gone.agent.num_keyframes
    late = [h for h in a.pgo.history if h[3] >= 30.0]
    assert late and all(h[1] == (0, 1) for h in late)  # (epoch, members, final, began)
    assert late[-1][2]  # the final epoch ran without robot 2
    assert a.pgo.stats.rounds < 0.8 * runner.pgo_params.max_rounds * len(a.pgo.history)  # nobody waited out caps
