import asyncio
import copy
import itertools
from collections import deque

import numpy as np
import pytest

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.checkpoint import load_checkpoint, save_checkpoint
from kimera_multi_py.agent.node import AgentNode, NodeParams
from kimera_multi_py.agent.params import AgentParams
from kimera_multi_py.comms import Heartbeat, KeyframeDescriptor, LoopbackNetwork, codec
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.closures import LoopClosureRequest
from kimera_multi_py.core.geometry import yaw_pose
from kimera_multi_py.core.keyframe import KeyframeInput
from kimera_multi_py.eval.slam import score_closures
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.sim.source import SimSource, keyframe_input

from ..sim.helpers import OFFICE, TINY


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


def run_office_pair(office, node_params: NodeParams | None = None):
    """Robots 0 (40 keyframes) and 2 (120) over loopback, robot 1 listening: robot 0 starts in
    office_a, robot 2 passes through it after the meeting room. Returns the agents and nodes."""
    async def main():
        net = LoopbackNetwork(team="t0", seed=0, robots=[0, 1, 2])
        agents = [Agent(r, (0, 1, 2), AgentParams()) for r in range(3)]
        nodes = [AgentNode(a, net.bus(a.robot), params=node_params) for a in agents]
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

    return asyncio.run(main())


@pytest.mark.slow
def test_two_nodes_find_true_inter_robot_closures_over_loopback(office):
    agents, nodes = run_office_pair(office)
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


def _wire(msg: Message) -> Message:
    """A message as a peer receives it: through the codec."""
    return codec.decode(codec.encode(msg, team="t0", src=msg.robot, seq=0, stamp=0.0)).msg


class _Team:
    """Agents wired synchronously, as the nodes do over a bus: every published message reaches
    every other agent at once; a LoopClosureRequest is answered by its target's serve_keyframe.
    ``sent`` holds the encoded bytes of everything the agents emitted, in order."""

    def __init__(self, agents: list[Agent]) -> None:
        self.agents = {a.robot: a for a in agents}
        self.sent: list[bytes] = []

    def feed(self, kf: KeyframeInput, robot: int) -> None:
        queue = deque((robot, m) for m in self.agents[robot].process_keyframe(copy.deepcopy(kf)))
        while queue:
            src, msg = queue.popleft()
            self.sent.append(codec.encode(msg, team="t0", src=src, seq=0, stamp=0.0))
            if isinstance(msg, LoopClosureRequest):
                reply = self.agents[msg.target].serve_keyframe(msg.keyframe, msg.request_id)
                self.sent.append(codec.encode(reply, team="t0", src=reply.robot, seq=0, stamp=0.0))
                queue.extend((src, m) for m in self.agents[src].handle(_wire(reply)))
                continue
            received = _wire(msg)
            for r, agent in self.agents.items():
                if r != src:
                    queue.extend((r, m) for m in agent.handle(received))


def _same_arrays(a: list[np.ndarray] | np.ndarray, b: list[np.ndarray] | np.ndarray) -> bool:
    return len(a) == len(b) and all(np.array_equal(x, y) and np.asarray(x).dtype == np.asarray(y).dtype
                                    for x, y in zip(a, b, strict=True))


def assert_same_agent(a: Agent, b: Agent) -> None:
    """Bit-identical state, read through the agents' public structures (not the checkpoint codec)."""
    assert a.num_keyframes == b.num_keyframes
    for name in ("poses", "dead_reckoning", "odometry"):
        assert _same_arrays(getattr(a, name), getattr(b, name)), name
    assert a.stamps == b.stamps and a.submap_of == b.submap_of and a.kf_landmarks == b.kf_landmarks
    # octree: codes and values
    assert _same_arrays([a.map.octree.codes, a.map.octree.values], [b.map.octree.codes, b.map.octree.values])
    # submap evidence, and the fused evidence it adds up to
    assert sorted(a.map.submaps) == sorted(b.map.submaps)
    for sid, sa in a.map.submaps.items():
        sb = b.map.submaps[sid]
        assert _same_arrays([sa.codes, sa.rows, sa.world_codes, sa.T, sa.T_ref],
                            [sb.codes, sb.rows, sb.world_codes, sb.T, sb.T_ref]) and sa.num_scans == sb.num_scans
    assert _same_arrays(a.map._fused.arrays(), b.map._fused.arrays())
    # objects
    assert sorted(a.objects.landmarks) == sorted(b.objects.landmarks)
    for lid, la in a.objects.landmarks.items():
        lb = b.objects.landmarks[lid]
        assert _same_arrays([la.class_counts, la.point_sum, la.voxels, la.voxel_hits, la.T_world_ref],
                            [lb.class_counts, lb.point_sum, lb.voxels, lb.voxel_hits, lb.T_world_ref]), lid
        assert (la.submap, la.num_points, la.num_observations, la.first_seen, la.last_seen, la.confirmed) == (
            lb.submap, lb.num_points, lb.num_observations, lb.first_seen, lb.last_seen, lb.confirmed)
        assert _same_arrays(la.box(), lb.box())
    # loop closures
    assert sorted(a.closures) == sorted(b.closures)
    for peer, ca in a.closures.items():
        cb = b.closures[peer]
        assert [(c.own_kf, c.peer, c.peer_kf, c.inliers, c.accepted) for c in ca] == [
            (c.own_kf, c.peer, c.peer_kf, c.inliers, c.accepted) for c in cb]
        assert _same_arrays([x for c in ca for x in (c.Z, c.own_pose, c.peer_pose)],
                            [x for c in cb for x in (c.Z, c.own_pose, c.peer_pose)])
    assert sorted(a.inter_edges) == sorted(b.inter_edges) and a.robot_graph == b.robot_graph
    assert _same_arrays([v[0] for _, v in sorted(a.inter_edges.items())],
                        [v[0] for _, v in sorted(b.inter_edges.items())])
    assert a.stats == b.stats
    assert sorted(a.constellations) == sorted(b.constellations)
    assert _same_arrays([c.descriptor for c in a.constellations.values()],
                        [c.descriptor for c in b.constellations.values()])


@pytest.mark.slow
def test_restored_agents_continue_bit_identical_to_ones_that_never_stopped(tmp_path):
    """Two robots exchange descriptors, queries and closures; at keyframe ``k`` of the merged
    stream both are checkpointed and restored, and the restored team and a team that never stopped
    are given the same remaining keyframes (and so the same peer messages)."""
    cfg = load_scenario(TINY)
    per_robot, k = 80, 90
    stream = sorted(((kf.stamp, r, kf) for r in (0, 1) for kf in itertools.islice(SimSource(cfg, 0, r), per_robot)),
                    key=lambda t: t[:2])
    params = AgentParams(budget=2, budget_period=30.0)  # a budget that binds: its history matters
    team = _Team([Agent(r, (0, 1), params) for r in (0, 1)])
    for _, r, kf in stream[:k]:
        team.feed(kf, r)
    extra = {"next_keyframe": {r: a.num_keyframes for r, a in team.agents.items()}, "epoch": (3, "pgo")}
    for r, agent in team.agents.items():
        save_checkpoint(tmp_path / f"r{r}.ckpt", agent, extra)
    loaded = [load_checkpoint(tmp_path / f"r{r}.ckpt") for r in (0, 1)]
    assert all(e == extra for _, e in loaded)
    restored = _Team([a for a, _ in loaded])
    before = len(team.sent)
    candidates = sum(a.stats.candidates for a in team.agents.values())
    for _, r, kf in stream[k:]:
        team.feed(kf, r)
        restored.feed(kf, r)
    # the continuation did real work: more verification requests, closures and messages
    assert sum(a.stats.candidates for a in team.agents.values()) > candidates
    assert any(team.agents[0].closures.get(1, [])) and len(team.sent) > before
    assert team.sent[before:] == restored.sent  # the same messages, byte for byte
    # a PGO correction moves every submap of both (exact re-anchoring from the restored evidence)
    for r in (0, 1):
        for t in (team, restored):
            t.agents[r].apply_poses(yaw_pose(0.4, -0.3, 0.0, 0.05) @ np.array(t.agents[r].poses))
            t.agents[r].objects.merge_fragments(t.agents[r].map.octree)
        assert_same_agent(team.agents[r], restored.agents[r])


@pytest.mark.slow
def test_the_front_end_sends_the_same_messages_whatever_the_back_end_estimates():
    """The front end works in each robot's odometric frame: a team whose estimates a back end
    keeps moving (a shift and a bend every 10 keyframes) sends the same messages, byte for byte,
    as a team whose estimates nothing moves. So the distributed and centralised modes, whose back
    ends estimate differently and at other times, verify the same closures."""
    cfg = load_scenario(TINY)
    stream = sorted(((kf.stamp, r, kf) for r in (0, 1) for kf in itertools.islice(SimSource(cfg, 0, r), 80)),
                    key=lambda t: t[:2])
    still, moved = (_Team([Agent(r, (0, 1), AgentParams()) for r in (0, 1)]) for _ in range(2))
    for n, (_, r, kf) in enumerate(stream):
        still.feed(kf, r)
        moved.feed(kf, r)
        if n % 10 == 9:
            for a in moved.agents.values():
                P = np.array(a.poses)
                half = len(P) // 2
                P[half:] = yaw_pose(0.2 + 0.1 * a.robot, -0.1 * n / 10, 0.0, 0.03 * n / 10) @ P[half:]
                a.apply_poses(yaw_pose(0.05 * n / 10, 0.0, 0.0, -0.02) @ P)
    for r in (0, 1):
        assert not np.allclose(np.array(still.agents[r].poses), np.array(moved.agents[r].poses), atol=0.05)
    assert sum(a.stats.candidates for a in still.agents.values()) > 0 and still.agents[0].closures.get(1)
    assert still.sent == moved.sent



@pytest.mark.parametrize("compact", [True, False])
def test_a_peer_keyframe_travels_once_however_many_places_it_is_verified_against(office, compact):
    """The node keeps the peer keyframes it fetched (compact wire): asked again for another place
    of ours, it answers from there, the very reply the peer would send."""
    async def main():
        net = LoopbackNetwork(team="t0", seed=0, robots=[0, 2])
        agents = [Agent(r, (0, 2), AgentParams()) for r in (0, 2)]
        nodes = [AgentNode(a, net.bus(a.robot), params=NodeParams(compact_wire=compact)) for a in agents]
        for n in nodes:
            await n.start()
        for kf, _ in zip(office.keyframes(2), range(30), strict=False):
            await nodes[1].process_keyframe(keyframe_input(kf))
        k = sorted(agents[1].constellations)[-1]
        for rid in (1, 2, 3):
            await nodes[0]._query(LoopClosureRequest(robot=0, target=2, request_id=rid, keyframe=k, query_keyframe=rid))
        for n in nodes:
            await n.close()
        return nodes, k

    nodes, k = asyncio.run(main())
    asked, answered = (n.bus.counters.sent["keyframe"].messages for n in nodes)
    assert (asked, answered) == ((1, 1) if compact else (3, 3))
    if compact:
        kept = nodes[0]._fetched[(2, k)]
        assert kept.found and kept.request_id == 1 and kept.num_points > 0
    assert sum(n.errors.total() for n in nodes) == 0
