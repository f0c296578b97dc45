"""Compact verification clouds on the office: the closure registration sees the same cloud, the
closures stay the same, and a corrupt cloud is a counted refusal."""

import asyncio

import numpy as np
import pytest

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.node import AgentNode, NodeParams
from kimera_multi_py.agent.params import AgentParams
from kimera_multi_py.comms import LoopbackNetwork
from kimera_multi_py.comms.clouds import RAW
from kimera_multi_py.core.geometry import inverse, so3_log
from kimera_multi_py.eval.slam import score_closures
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.sim.source import keyframe_input

from ..sim.helpers import OFFICE
from .test_agent import run_office_pair


@pytest.fixture(scope="module")
def office():
    return Simulation(load_scenario(OFFICE, robots=3), seed=0)


@pytest.fixture(scope="module")
def agent0(office):
    agent = Agent(0, (0, 1, 2), AgentParams())
    for kf, _ in zip(office.keyframes(0), range(80), strict=False):
        agent.process_keyframe(keyframe_input(kf))
    return agent


def test_a_compact_reply_registers_as_the_full_cloud_does(agent0):
    """The compact cloud is the registration's own downsampling of the full one (one mean per
    voxel), so GICP from a perturbed guess lands where it lands with the full cloud."""
    ks = sorted(agent0.constellations)
    assert len(ks) >= 6
    reg = agent0.closure_registration
    raw_bytes = compact_bytes = compared = 0
    for a, b in zip(ks[:-1], ks[1:], strict=True):
        full, compact = agent0.serve_keyframe(b, compact=False), agent0.serve_keyframe(b)
        assert full.cloud[0] == RAW and compact.num_points < full.num_points
        raw_bytes += full.cloud.nbytes
        compact_bytes += compact.cloud.nbytes
        guess = inverse(agent0.odometric[a]) @ agent0.odometric[b]
        start = guess.copy()
        start[:3, 3] += [0.15, -0.1, 0.05]  # within the first correspondence distance
        target = agent0.constellations[a].cloud
        r_full = reg.register(target, np.asarray(full.points()[0], float), start)
        r_compact = reg.register(target, np.asarray(compact.points()[0], float), start)
        assert r_full is not None and r_compact is not None
        assert (r_compact.overlap >= agent0.params.icp_min_overlap) == (r_full.overlap >= agent0.params.icp_min_overlap)
        if b - a > 4:  # places apart (a jump in the keyframes that have constellations): no overlap to compare
            continue
        compared += 1
        assert r_full.converged and r_compact.converged
        d = inverse(r_full.T) @ r_compact.T
        assert np.linalg.norm(d[:3, 3]) < 0.005 and np.linalg.norm(so3_log(d[:3, :3])) < np.deg2rad(0.1)
        assert abs(r_full.overlap - r_compact.overlap) < 0.02
    assert compared >= 8 and compact_bytes * 4 < raw_bytes


def test_a_corrupt_cloud_is_refused_and_counted(office, agent0):
    async def main():
        net = LoopbackNetwork(team="t0", seed=0, robots=[0, 1])
        other = Agent(1, (0, 1), AgentParams())
        node = AgentNode(other, net.bus(1))
        reply = agent0.serve_keyframe(sorted(agent0.constellations)[-1], request_id=7)
        cloud = reply.cloud.copy()
        cloud[len(cloud) // 2:] ^= 0x5A
        bad = type(reply)(**{**reply.to_wire(), "cloud": cloud})
        other._pending[7] = (0, reply.keyframe, 0)  # as if robot 1 had asked for it
        assert node._handle_agent(bad) == []
        assert node.errors["LoopClosureReply"] == 1

    asyncio.run(main())


def _two_robots(office, compact: bool):
    agents, nodes = run_office_pair(office, NodeParams(compact_wire=compact))
    sent = sum(n.bus.counters.snapshot()["sent"].get("keyframe", {}).get("bytes", 0) for n in nodes)
    return agents, nodes, sent


@pytest.mark.slow
def test_compact_clouds_keep_the_closures(office):
    (a_raw, _, raw_bytes), (a_compact, nodes, compact_bytes) = (_two_robots(office, c) for c in (False, True))
    raw = [c for c in a_raw[0].closures.get(2, []) if c.accepted]
    compact = [c for c in a_compact[0].closures.get(2, []) if c.accepted]
    assert len(raw) >= 2 and len(compact) >= len(raw)
    truth0, truth2 = office.plans[0].poses, office.plans[2].poses
    ok = score_closures(np.stack([c.Z for c in compact]), truth0[[c.own_kf for c in compact]],
                        truth2[[c.peer_kf for c in compact]])
    assert ok.all()
    by_pair = {(c.own_kf, c.peer_kf): c.Z for c in raw}
    for c in compact:
        if (c.own_kf, c.peer_kf) in by_pair:
            d = inverse(by_pair[(c.own_kf, c.peer_kf)]) @ c.Z
            assert np.linalg.norm(d[:3, 3]) < 0.01 and np.linalg.norm(so3_log(d[:3, :3])) < np.deg2rad(0.2)
    assert 0 < compact_bytes * 4 < raw_bytes
    assert sum(n.errors.total() for n in nodes) == 0
