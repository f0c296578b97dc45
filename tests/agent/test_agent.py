import asyncio

import numpy as np
import pytest

from kimera_multi_py.agent.agent import Agent, AgentParams
from kimera_multi_py.agent.node import AgentNode
from kimera_multi_py.comms import Heartbeat, KeyframeDescriptor, LoopbackNetwork
from kimera_multi_py.errors import KimeraMultiError
from kimera_multi_py.eval.slam import score_closures
from kimera_multi_py.geometry import yaw_pose
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.sim.runner import keyframe_input

from ..sim.helpers import OFFICE


@pytest.fixture(scope="module")
def office():
    return Simulation(load_scenario(OFFICE, robots=3), seed=0)


def run_agent(sim, robot, n):
    agent = Agent(robot, (0, 1, 2), AgentParams())
    out = []
    for kf in sim.keyframes(robot):
        if kf.index >= n:
            break
        out += agent.process_keyframe(keyframe_input(kf))
    return agent, out


def test_agent_maps_objects_and_publishes_descriptors(office):
    agent, out = run_agent(office, 0, 40)
    assert agent.num_keyframes == 40 and np.allclose(agent.poses[0], np.eye(4))
    assert agent.map.octree.num_leaves > 1000
    assert len(agent.objects.confirmed()) >= 5
    descs = [m for m in out if isinstance(m, KeyframeDescriptor)]
    assert descs and all(d.robot == 0 and d.descriptor.shape == (agent.spec.size,) for d in descs)
    reply = agent.serve_keyframe(descs[-1].keyframe, request_id=3)
    assert reply.found and reply.request_id == 3 and len(reply.object_centroids) >= 5
    assert not agent.serve_keyframe(10_000).found


def test_agent_rejects_bad_keyframes_and_unknown_robots(office):
    agent, _ = run_agent(office, 0, 3)
    kf = keyframe_input(next(office.keyframes(0)))
    with pytest.raises(ValueError, match="out of order"):
        agent.process_keyframe(kf)
    kf.index, kf.odometry = 3, np.full((4, 4), np.nan)
    with pytest.raises(ValueError, match="non-finite odometry"):
        agent.process_keyframe(kf)
    with pytest.raises(ValueError, match="unknown robot 7"):
        agent.handle(Heartbeat(robot=7, keyframes=1))
    assert agent.num_keyframes == 3  # nothing was lost


def test_apply_poses_moves_the_map_exactly_and_back(office):
    agent, _ = run_agent(office, 1, 25)
    before = agent.map.octree.codes.copy(), agent.map.octree.values.copy()
    poses = np.array(agent.poses)
    agent.apply_poses(yaw_pose(1.0, -2.0, 0.0, 0.3) @ poses)
    assert not np.array_equal(agent.map.octree.codes, before[0])
    agent.apply_poses(poses)
    assert np.array_equal(agent.map.octree.codes, before[0]) and np.array_equal(agent.map.octree.values, before[1])
    with pytest.raises(ValueError, match="bad optimised poses"):
        agent.apply_poses(np.concatenate([poses, poses[:1]]))


def test_two_nodes_find_true_inter_robot_closures_over_loopback(office):
    """Robot 0 starts in office_a, robot 2 passes through it after the meeting room."""
    async def main():
        net = LoopbackNetwork(team="t0", seed=0, robots=[0, 1, 2])
        agents = [Agent(r, (0, 1, 2), AgentParams()) for r in range(3)]
        nodes = [AgentNode(a, net.bus(a.robot)) for a in agents]
        for n in nodes:
            await n.start()
        streams = {0: office.keyframes(0), 2: office.keyframes(2)}
        for r, n_kf in ((0, 40), (2, 120)):
            for kf, _ in zip(streams[r], range(n_kf), strict=False):
                await nodes[r].process_keyframe(keyframe_input(kf))
                for n in nodes:
                    await n.drain()
        for n in nodes:
            await n.close()
        return agents, nodes

    agents, nodes = asyncio.run(main())
    closures = [c for c in agents[0].closures.get(2, []) if c.accepted]
    assert agents[0].stats.candidates > 0
    assert len(closures) >= 2
    truth0, truth2 = office.plans[0].poses, office.plans[2].poses
    ok = score_closures(np.stack([c.Z for c in closures]), truth0[[c.own_kf for c in closures]],
                        truth2[[c.peer_kf for c in closures]])
    assert ok.all()
    assert (0, 2) in agents[2].robot_graph  # the peer learned the edges
    assert len(agents[2].inter_edges) == len(closures)
    assert sum(nodes[r].errors.total() for r in range(3)) == 0


def test_checkpoint_round_trip_and_corrupt_file(office, tmp_path):
    agent, _ = run_agent(office, 0, 12)
    node = AgentNode(agent, None)  # type: ignore[arg-type]
    node.checkpoint(tmp_path / "a.ckpt")
    restored = AgentNode.restore(tmp_path / "a.ckpt")
    assert restored.num_keyframes == 12 and np.array_equal(restored.map.octree.codes, agent.map.octree.codes)
    (tmp_path / "bad.ckpt").write_bytes(b"\x80\x05garbage")
    with pytest.raises(KimeraMultiError, match="checkpoint"):
        AgentNode.restore(tmp_path / "bad.ckpt")
