from dataclasses import replace

import numpy as np
import pytest

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.params import AgentParams
from kimera_multi_py.agent.pose_graph import information
from kimera_multi_py.eval.metrics import ate_rmse
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.sim.source import keyframe_input
from kimera_multi_py.team.build import agent_params
from kimera_multi_py.workflow.simulate import SimRunner

from ..sim.helpers import REPO, TINY

SMALL = REPO / "sims" / "small.toml"


@pytest.fixture(scope="module")
def small_robot():
    sim = Simulation(load_scenario(SMALL), seed=0)
    kfs = [kf for kf, _ in zip(sim.keyframes(0), range(60), strict=False)]
    return sim, kfs


def _run(kfs, **params):
    agent = Agent(0, None, AgentParams(**params))
    for kf in kfs:
        agent.process_keyframe(keyframe_input(kf))
    return agent


def test_fused_steps_are_the_trusted_edges(small_robot):
    """Default: one trusted factor per step, the registration-refined step (what the server gets)."""
    _, kfs = small_robot
    agent = _run(kfs)
    i, j, Z, info, odo = agent.intra_edges()
    n = agent.num_keyframes
    assert np.array_equal(i[: n - 1], np.arange(n - 1)) and np.array_equal(j[: n - 1], np.arange(1, n))
    assert np.all(odo[: n - 1]) and not np.any(odo[n - 1:])  # after the steps: closures only
    assert np.allclose(Z[: n - 1], np.array(agent.steps[1:]))
    assert not np.allclose(Z[: n - 1], np.array(agent.odometry[1:]))  # registration refined them
    assert np.allclose(info[: n - 1], information(agent.params.odom_sigmas))


def test_registration_factors_join_the_odometry_as_trusted_edges(small_robot):
    _, kfs = small_robot
    agent = _run(kfs, registration_factor="separate")
    i, j, Z, info, odo = agent.intra_edges()
    n = agent.num_keyframes
    reg = np.arange(len(i)) >= n - 1
    reg &= odo
    assert reg.sum() == len(agent.scan_odometry.edges) > n // 2
    assert np.all(j[reg] == i[reg] + 1) and np.all(odo[: n - 1])
    assert all(np.linalg.eigvalsh(I).min() > -1e-6 * np.abs(I).max() for I in info[reg])
    # the estimate chains the fused steps, not the raw odometry
    chained = [np.eye(4)]
    for s in agent.steps[1:]:
        chained.append(chained[-1] @ s)
    assert np.allclose(np.array(chained), np.array(agent.poses))
    assert not np.allclose(np.array(agent.poses), np.array(agent.dead_reckoning))
    # a PGO correction of the first half: the rest follows by the fused steps
    half = n // 2
    agent.apply_poses(np.array(agent.poses[:half]))
    assert np.allclose(np.array(agent.poses), np.array(chained))


def test_without_registration_the_agent_is_dead_reckoning(small_robot):
    _, kfs = small_robot
    agent = _run(kfs, registration=False)
    assert agent.scan_odometry is None
    assert np.allclose(np.array(agent.poses), np.array(agent.dead_reckoning))
    assert len(agent.intra_edges()[0]) == agent.num_keyframes - 1 + sum(
        c.accepted for c in agent.closures.get(0, []))


def test_registration_refined_odometry_drifts_less_than_dead_reckoning(small_robot):
    _, kfs = small_robot
    agent = _run(kfs)
    true = np.array([kf.true_pose for kf in kfs])
    reg = true[0] @ np.array(agent.scan_odometry.poses)
    dead = true[0] @ np.array(agent.dead_reckoning)
    assert ate_rmse(reg[:, :3, 3], true[:, :3, 3]) < ate_rmse(dead[:, :3, 3], true[:, :3, 3])


def test_the_floor_keeps_the_agents_chain_at_its_height(small_robot):
    _, kfs = small_robot
    true = np.array([kf.true_pose for kf in kfs])
    height = {}
    for floor in (True, False):
        agent = _run(kfs, floor_reference=floor)
        reg = true[0] @ np.array(agent.scan_odometry.poses)
        height[floor] = float(np.sqrt(np.mean((reg[:, 2, 3] - true[:, 2, 3]) ** 2)))
    assert height[True] < 0.02 and height[True] < 0.5 * height[False]


@pytest.mark.slow
def test_tiny_end_to_end_reports_accuracy_by_cause():
    cfg = load_scenario(TINY)
    d = SimRunner(cfg, 0, "distributed", params=replace(agent_params(cfg), floor_reference=True)).run().to_dict()
    ate = d["ate_rmse_m"]
    assert ate["registration_odometry"] < ate["dead_reckoning"]
    tm = d["team_map"]
    assert 0 <= tm["occupancy_f1"] <= 1 and 0 <= tm["semantic_miou"] <= 1
    assert tm["true_poses"]["occupancy_f1"] > 0.9  # the ceiling: the same scans at the true poses
    assert tm["true_poses"]["occupancy_f1"] > tm["dead_reckoning"]["occupancy_f1"]
    assert d["closure_error"]["inter"]["count"] == d["loop_closures"]["accepted_inter"]
    assert d["front_end_ms_per_keyframe"]["total"] > d["front_end_ms_per_keyframe"]["registration"] > 0
    assert d["scan_odometry"]["registered"] > 0
    # every keyframe after each robot's first is counted once by the floor reference (tiny's
    # 384-ray sensor sees fewer floor points than a fit needs at most of them: mostly missing)
    so, n = d["scan_odometry"], sum(r["keyframes"] for r in d["robots"])
    assert n - len(d["robots"]) <= so["floor_corrected"] + so["floor_missing"] + so["floor_gated"] <= n
    assert n - len(d["robots"]) <= so["heading_corrected"] + so["heading_missing"] + so["heading_gated"] <= n


@pytest.mark.slow
def test_the_walls_keep_the_agents_chain_at_its_heading(small_robot):
    sim, _ = small_robot
    kfs = list(sim.keyframes(0))  # the whole run: yaw drift needs distance to show
    true = np.array([kf.true_pose for kf in kfs])
    yaw = {}
    for walls in (True, False):
        agent = _run(kfs, heading_reference=walls)
        reg = true[0] @ np.array(agent.scan_odometry.poses)
        err = np.angle(np.exp(1j * (np.arctan2(reg[:, 1, 0], reg[:, 0, 0]) - np.arctan2(true[:, 1, 0], true[:, 0, 0]))))
        yaw[walls] = float(np.degrees(np.sqrt(np.mean(err**2))))
    assert agent.scan_odometry.heading is None and yaw[True] < 0.5 * yaw[False]
