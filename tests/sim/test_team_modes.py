"""The team modes end to end: the tiny scenario (fast, but fully aliased: its two rooms are twins;
with both rooms toured robot 1 aligns into the true frame, with one it is kept out of the team
frame), faults' and small's non-aliased building for a shared team map and objects and for
accuracy (slow), and the server's joint graph."""

import json

import numpy as np
import pytest

from kimera_multi_py.comms.messages.closures import KeyframeOdometry, LoopClosures
from kimera_multi_py.core.geometry import inverse, yaw_pose
from kimera_multi_py.core.posegraph import robot_key
from kimera_multi_py.io.tum import read_tum
from kimera_multi_py.server.node import Server
from kimera_multi_py.sim import load_scenario
from kimera_multi_py.workflow.simulate import SimRunner

from .helpers import REPO, SMALL, TINY


def run_modes(tmp_path_factory, modes, route_1=None):
    """tiny (robot 1 on ``route_1`` when given) in each mode: results.json by mode, the run folder
    by ``mode/dir``."""
    out = {}
    for mode in modes:
        cfg = load_scenario(TINY)
        if route_1 is not None:
            cfg.robots[1].route = route_1
        d = tmp_path_factory.mktemp(mode)
        SimRunner(cfg, seed=0, mode=mode, out_dir=d).run()
        out[mode] = json.loads((d / "results.json").read_text())
        out[f"{mode}/dir"] = d
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return run_modes(tmp_path_factory, ("odometry", "distributed", "centralized"))


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


def team_objects(folder, robot):
    """(the robot's team object map, its own objects) as the run wrote them."""
    team = json.loads((folder / f"robot{robot}" / "team_objects.json").read_text())["objects"]
    return team, json.loads((folder / f"robot{robot}" / "objects.json").read_text())["objects"]


@pytest.mark.parametrize("mode", ["distributed", "centralized"])
def test_tiny_twin_rooms_toured_both_align_robot_1_into_the_true_frame(runs, mode):
    """Both robots tour both twin rooms: the true frame is explained by closures in two places,
    the twin's (one room shifted onto the other) by one, so the true frame leads. Robot 1 is
    aligned, every accepted inter-robot closure is true, and both robots hold the team map."""
    r = runs[mode]
    assert r["alignment"]["0"]["status"] == "root"
    assert r["alignment"]["1"]["status"] == "aligned" and r["alignment"]["1"]["frame"] == 0
    assert r["alignment"]["1"]["settled"] is True
    lc = r["loop_closures"]
    assert lc["false_accepted_inter"] == 0 and lc["false_accepted_intra"] == 0
    assert lc["true_accepted_inter"] > 0
    assert r["team"]["ate_rmse_m"] < runs["odometry"]["team"]["ate_rmse_m"]
    mc = r["map_consensus"]
    for robot in ("0", "1"):
        assert mc["team_map"][robot] == mc["centralised_fusion"]


@pytest.fixture(scope="module")
def one_twin(tmp_path_factory):
    """tiny with robot 1 touring room_b only: its closures with robot 0 fit the true frame and
    the twin's (room_b onto room_a) from one place each."""
    return run_modes(tmp_path_factory, ("distributed", "centralized"), route_1=["room_b"])


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["distributed", "centralized"])
def test_one_twin_room_keeps_robot_1_out_of_the_team_frame_and_out_of_the_team_map(one_twin, mode):
    """Robot 1 saw one of the twin rooms: its closures with robot 0 fit two frames from one place
    each (the true one and the twin room's), neither leads, and the agents (distributed) or the
    server (centralised) keep it out of the team frame. It is reported so, in its own frame, and
    nothing of it is merged: robot 0's team map is the centralised fusion of the team frame's
    evidence (robot 0's alone), robot 1's holds its own evidence only, and the team objects and the
    team scene graph leave robot 1 out."""
    r = one_twin[mode]
    assert r["alignment"]["0"]["status"] == "root" and r["alignment"]["0"]["frame"] == 0
    kept_out = r["alignment"]["1"]
    assert kept_out["status"] == "excluded" and kept_out["frame"] == 1 and kept_out["settled"] is False
    assert r["loop_closures"]["false_accepted_inter"] == 0
    mc = r["map_consensus"]
    assert mc["mode"] == "exact" and mc["rounds"] >= 2
    assert mc["agreement"]["0"]["label"] == 1.0 and mc["agreement"]["0"]["identical"] == 1.0
    assert mc["team_map"]["0"] == mc["centralised_fusion"]
    assert mc["centralised_fusion"]["observed_cells"] == r["map"]["0"]["observed_cells"]  # robot 0's evidence
    assert mc["team_map"]["1"]["observed_cells"] == r["map"]["1"]["observed_cells"]  # robot 1's own
    assert mc["agreement"]["1"]["identical"] < 0.5  # in its own frame: not the team's map
    d = one_twin[f"{mode}/dir"]
    for robot in (0, 1):  # each robot's team objects are its own, all of them
        team, own = team_objects(d, robot)
        members = {m for ob in team for m in ob["members"]}
        assert {m >> 24 for m in members} == {robot}
        assert {(robot << 24) | ob["id"] for ob in own} <= members
    sg = r["scene_graph"]  # the team graph: the team map, robot 0's trajectory and objects
    assert sg["nodes_per_layer"]["agents"] == r["robots"][0]["keyframes"] < r["team"]["keyframes"]
    assert sg["nodes_per_layer"]["objects"] == len(team_objects(d, 0)[0])


FAULTS = REPO / "sims" / "faults.toml"  # small's building (no aliasing), 39 s of stream, three robots


@pytest.fixture(scope="module")
def aligned(tmp_path_factory):
    """sims/faults.toml in both team modes, maps and objects shared: every robot is aligned into
    the team frame (results.json, run folder)."""
    out = {}
    for mode in ("distributed", "centralized"):
        d = tmp_path_factory.mktemp(f"faults_{mode}")
        SimRunner(load_scenario(FAULTS), seed=0, mode=mode, out_dir=d).run()
        out[mode] = (json.loads((d / "results.json").read_text()), d)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["distributed", "centralized"])
def test_every_robot_ends_with_the_centralised_fusion_of_all_evidence(aligned, mode):
    """Exact map consensus inside the nodes (peer to peer, or through the server): with every robot
    in the team frame, each robot's team map equals the centralised fusion of every robot's
    evidence, value for value, for a small fraction of ROAM's bytes."""
    r, _ = aligned[mode]
    robots = ("0", "1", "2")
    assert all(r["alignment"][x]["status"] in ("root", "aligned") and r["alignment"][x]["frame"] == 0
               for x in robots), r["alignment"]
    mc = r["map_consensus"]
    assert mc["mode"] == "exact" and mc["rounds"] >= 2
    for robot in robots:
        assert mc["agreement"][robot]["label"] == 1.0 and mc["agreement"][robot]["identical"] == 1.0
        assert mc["team_map"][robot] == mc["centralised_fusion"]
        # the team map knows more than the robot's own map: the others' evidence is in it
        assert mc["team_map"][robot]["observed_cells"] > r["map"][robot]["observed_cells"]
    assert mc["phi"][-1] == 0.0
    assert 0 < mc["bytes_ratio_vs_roam"] <= 0.1
    sg = r["scene_graph"]
    assert sg["agree"]["places"] and sg["agree"]["rooms"]  # graphs built from one team map match
    assert sg["nodes_per_layer"]["agents"] == r["team"]["keyframes"]  # every trajectory in the team graph


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["distributed", "centralized"])
def test_every_robot_holds_the_same_team_objects_from_every_robot(aligned, mode):
    """Object sharing (peer to peer, or through the server): every robot's team object map is
    identical, holds landmarks of every robot, and their scene graphs put every object in the same
    room; a robot's own landmarks are all in its team map."""
    r, d = aligned[mode]
    team = [team_objects(d, robot)[0] for robot in (0, 1, 2)]
    assert len(team[0]) > 5
    for other in team[1:]:
        assert [(o["id"], o["class"], o["members"], o["sightings"]) for o in team[0]] == \
            [(o["id"], o["class"], o["members"], o["sightings"]) for o in other]
        for k in ("centroid", "lo", "hi"):  # the same numbers, up to float rounding of the pose tables
            np.testing.assert_allclose([o[k] for o in team[0]], [o[k] for o in other], atol=1e-9)
    members = [m for ob in team[0] for m in ob["members"]]
    assert {m >> 24 for m in members} == {0, 1, 2}
    for robot in (0, 1, 2):
        own = team_objects(d, robot)[1]
        assert {(robot << 24) | ob["id"] for ob in own} <= set(members)
    assert r["scene_graph"]["agree"] == {"places": True, "rooms": True, "object_rooms": True}
    per_robot = r["objects"]["team_per_robot"]
    assert per_robot["0"]["matches"] == per_robot["1"]["matches"] == per_robot["2"]["matches"]
    assert per_robot["0"]["objects"] == len(team[0])


@pytest.mark.slow
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


def test_the_server_team_map_is_in_its_joint_graph_roots_frame():
    """The server fuses the evidence in its team frame, its joint graph's root's: robot 1's while
    robot 0 has not streamed (a late joiner), robot 0's from when it has."""
    import asyncio

    from kimera_multi_py.comms import LoopbackNetwork
    from kimera_multi_py.mapping.config import get_submap_map
    from kimera_multi_py.pgo.team import ScheduleParams
    from kimera_multi_py.server.node import SERVER_ID, ServerNode
    from kimera_multi_py.team.build import agent_params

    async def main() -> list[tuple[int | None, int, int]]:
        net = LoopbackNetwork(team="t0", seed=0)
        node = ServerNode(Server(SERVER_ID, None, closure_sigmas=(0.02, 0.05), odom_sigmas=(0.01, 0.02)),
                          net.bus(SERVER_ID), ScheduleParams(period=1e9), clock=lambda: 0.0)
        node.fuse_maps(get_submap_map(agent_params(load_scenario(TINY)).mapping))
        await node.start()
        frames = []
        for robot in (2, 1, 0):
            node.server.handle(odometry_msgs(robot, 3))
            await node.tick(wall=0.0)
            frames.append((node.server.root, node.maps.frame, node.objects.frame))
        return frames

    assert asyncio.run(main()) == [(2, 2, 2), (1, 1, 1), (0, 0, 0)]
