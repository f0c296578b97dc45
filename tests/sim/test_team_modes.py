"""The team modes end to end: the tiny scenario (fast, but fully aliased: its two rooms are twins),
the small non-aliased one for accuracy (slow), and the server's joint graph."""

import json

import numpy as np
import pytest

from kimera_multi_py.comms.messages import KeyframeOdometry, LoopClosures
from kimera_multi_py.consensus.server_node import Server
from kimera_multi_py.geometry import inverse, yaw_pose
from kimera_multi_py.io.pose_graph import robot_key
from kimera_multi_py.io.tum import read_tum
from kimera_multi_py.sim import load_scenario
from kimera_multi_py.sim.runner import SimRunner

from .helpers import SMALL, TINY


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    out = {}
    for mode in ("odometry", "distributed", "centralized"):
        d = tmp_path_factory.mktemp(mode)
        SimRunner(load_scenario(TINY), seed=0, mode=mode, out_dir=d).run()
        out[mode] = json.loads((d / "results.json").read_text())
        out[f"{mode}/dir"] = d
    return out


def test_team_results_have_the_fields_and_the_pipeline_ran(runs):
    for mode in ("distributed", "centralized"):
        r = runs[mode]
        lc = r["loop_closures"]
        assert lc["candidates"] > 0 and lc["verified"] > 0
        assert lc["verified"] + lc["rejected_verification"] == lc["candidates"]
        assert set(r["map"]) == {"0", "1"} and all(0 <= m["occupancy_f1"] <= 1 for m in r["map"].values())
        assert r["objects"]["landmarks"] > 5
        assert r["bytes_sent"]["total"] == sum(r["bytes_sent"]["per_robot"].values()) > 0
        assert "lc/descriptors" in r["bytes_sent"]["per_topic"]
        assert r["realtime_factor"] > 0 and r["pgo_runs"] >= 1
        assert all(not errs for errs in r["refused_messages"].values())
    assert "server/odometry" in runs["centralized"]["bytes_sent"]["per_topic"]
    assert "pgo/public_poses" in runs["distributed"]["bytes_sent"]["per_topic"]
    assert "map" not in runs["odometry"]


def test_every_robot_ends_with_the_centralised_fusion_of_all_evidence(runs, tmp_path_factory):
    """Exact map consensus inside the nodes: each robot's team map equals the centralised fusion of
    every robot's evidence, value for value, for a small fraction of ROAM's bytes."""
    mc = runs["distributed"]["map_consensus"]
    assert mc["mode"] == "exact" and mc["rounds"] >= 2
    for robot in ("0", "1"):
        assert mc["agreement"][robot]["label"] == 1.0 and mc["agreement"][robot]["identical"] == 1.0
        assert mc["team_map"][robot] == mc["centralised_fusion"]
        # the team map knows at least what the robot's own map knows
        assert mc["team_map"][robot]["observed_cells"] >= runs["distributed"]["map"][robot]["observed_cells"]
    assert mc["phi"][-1] == 0.0
    assert 0 < mc["bytes_ratio_vs_roam"] <= 0.1
    central = runs["centralized"]["map_consensus"]  # the server fuses everyone's evidence and serves it back
    assert all(central["agreement"][r]["identical"] == 1.0 for r in ("0", "1"))
    sg = runs["distributed"]["scene_graph"]
    assert sg["agree"]["places"] and sg["agree"]["rooms"]  # graphs built from one team map match


@pytest.mark.parametrize("mode", ["distributed", "centralized"])
def test_every_robot_holds_the_same_team_objects_from_every_robot(runs, mode):
    """Object sharing (peer to peer, or through the server): both robots' team object maps are
    identical, hold landmarks of both robots, and their scene graphs put every object in the same
    room; a robot's own landmarks are all in its team map."""
    d = runs[f"{mode}/dir"]
    team = [json.loads((d / f"robot{r}" / "team_objects.json").read_text())["objects"] for r in (0, 1)]
    assert len(team[0]) > 5
    assert [(o["id"], o["class"], o["members"], o["sightings"]) for o in team[0]] == \
        [(o["id"], o["class"], o["members"], o["sightings"]) for o in team[1]]
    for k in ("centroid", "lo", "hi"):  # the same numbers, up to float rounding of the pose tables
        np.testing.assert_allclose([o[k] for o in team[0]], [o[k] for o in team[1]], atol=1e-9)
    members = [m for ob in team[0] for m in ob["members"]]
    assert {m >> 24 for m in members} == {0, 1}
    for r in (0, 1):
        own = json.loads((d / f"robot{r}" / "objects.json").read_text())["objects"]
        assert {(r << 24) | ob["id"] for ob in own} <= set(members)
    assert runs[mode]["scene_graph"]["agree"] == {"places": True, "rooms": True, "object_rooms": True}
    per_robot = runs[mode]["objects"]["team_per_robot"]
    assert per_robot["0"]["matches"] == per_robot["1"]["matches"] and per_robot["0"]["objects"] == len(team[0])


def test_same_seed_same_team_metrics(runs, tmp_path):
    SimRunner(load_scenario(TINY), seed=0, mode="centralized", out_dir=tmp_path).run()
    again = json.loads((tmp_path / "results.json").read_text())
    for key in ("robots", "team", "loop_closures", "objects", "map"):
        assert again[key] == runs["centralized"][key], key


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """The small scenario in every mode: (results.json, per-robot outcomes, run folder). Map
    consensus is off: it does not change the trajectories and it takes half the run time."""
    out = {}
    for mode in ("odometry", "distributed", "centralized"):
        d = tmp_path_factory.mktemp(f"small_{mode}")
        runner = SimRunner(load_scenario(SMALL), seed=0, mode=mode, out_dir=d, map_consensus="off")
        runner.run()
        out[mode] = (json.loads((d / "results.json").read_text()), runner.outcomes, d)
    return out


def closure_errors(outcomes, folder):
    """(translation m, rotation deg) error of every closure the back end kept between two robots,
    against the true keyframe poses the run wrote (independent of the runner's own scoring)."""
    truth = {o.robot: read_tum(folder / f"robot{o.robot}_gt.tum")[1] for o in outcomes}
    errs = []
    for o in outcomes:
        for c in o.closures:
            if c.peer != o.robot and c.accepted and c.weight is not None and c.weight >= 0.5:
                E = inverse(c.Z) @ inverse(truth[o.robot][c.own_kf]) @ truth[c.peer][c.peer_kf]
                cos = np.clip((np.trace(E[:3, :3]) - 1) / 2, -1.0, 1.0)
                errs.append((np.linalg.norm(E[:3, 3]), np.degrees(np.arccos(cos))))
    return np.array(errs).reshape(-1, 2)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["distributed", "centralized"])
def test_small_team_keeps_only_true_inter_robot_closures(small, mode):
    res, outcomes, folder = small[mode]
    lc = res["loop_closures"]
    assert lc["false_accepted_inter"] == 0 and lc["false_accepted_intra"] == 0
    errs = closure_errors(outcomes, folder)
    assert len(errs) == lc["accepted_inter"] >= 10  # every robot pair met, several times
    assert np.all(errs[:, 0] < 0.5) and np.all(errs[:, 1] < 5.0), errs.max(0)
    pairs = {frozenset((o.robot, c.peer)) for o in outcomes for c in o.closures if c.peer != o.robot}
    assert len(pairs) == 3, pairs  # every pair of the three robots closed loops


@pytest.mark.slow
def test_small_distributed_is_as_accurate_as_centralised(small):
    ate = {mode: small[mode][0]["team"]["ate_rmse_m"] for mode in small}
    assert ate["distributed"] <= 1.05 * ate["centralized"], ate


@pytest.mark.slow
def test_small_team_halves_the_odometry_error(small):
    ate = {mode: small[mode][0]["team"]["ate_rmse_m"] for mode in small}
    assert ate["distributed"] <= 0.5 * ate["odometry"] and ate["centralized"] <= 0.5 * ate["odometry"], ate


def odometry_msgs(robot, n):
    step = yaw_pose(0.5, 0.0, 0.0, 0.0)
    return KeyframeOdometry(robot=robot, keyframes=np.arange(n), odometry=np.stack([np.eye(4)] + [step] * (n - 1)))


def test_server_builds_the_joint_graph_and_rejects_an_outlier():
    server = Server(2, (0, 1), closure_sigmas=(0.02, 0.05), odom_sigmas=(0.01, 0.02))
    server.handle(odometry_msgs(0, 10))
    server.handle(odometry_msgs(1, 10))
    # robot 1 starts 3 m to the left of robot 0, both drive straight along x
    T0 = [yaw_pose(0.5 * k, 0.0, 0.0, 0.0) for k in range(10)]
    T1 = [yaw_pose(0.5 * k, 3.0, 0.0, 0.0) for k in range(10)]
    pairs = [(1, 1), (4, 4), (6, 5), (8, 8)]
    Z = [inverse(T0[a]) @ T1[b] for a, b in pairs] + [yaw_pose(4.0, -7.0, 0.0, 2.0)]  # the last is wrong
    pairs.append((2, 9))
    server.handle(LoopClosures(robot=0, peer=1, batch=1,
                               keys_a=np.array([robot_key(0, a) for a, _ in pairs], dtype=np.int64),
                               keys_b=np.array([robot_key(1, b) for _, b in pairs], dtype=np.int64),
                               poses=np.stack(Z), sigmas=np.full((5, 6), 0.05), inliers=np.full(5, 8, np.int32)))
    graph, tags = server.graph()
    assert graph.num_poses == 20 and len(tags) == 5
    out = server.optimise()
    assert [m.robot for m in out] == [2, 2]
    P0, P1 = out[0].poses, out[1].poses
    rel = inverse(P0[0]) @ P1[0]
    assert np.allclose(rel[:3, 3], [0.0, 3.0, 0.0], atol=0.05)
    assert server.stats.rejected_by_gnc == 1 and server.stats.weights[(0, 2, 1, 9)] < 0.5


def test_server_refuses_out_of_order_odometry():
    server = Server(2, (0, 1), closure_sigmas=(0.02, 0.05), odom_sigmas=(0.01, 0.02))
    server.handle(odometry_msgs(0, 3))
    with pytest.raises(ValueError, match="expected 3"):
        server.handle(KeyframeOdometry(robot=0, keyframes=np.array([7]), odometry=np.eye(4)[None]))
    assert len(server.odometry[0]) == 3  # nothing lost
