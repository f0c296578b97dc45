"""AgentNode as the whole robot: nodes that run on their own clocks, with no orchestrator."""

import asyncio
import math

import numpy as np
import pytest

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.node import AgentNode, NodeParams
from kimera_multi_py.comms import LoopbackNetwork
from kimera_multi_py.comms.messages.pgo import PgoStatus
from kimera_multi_py.comms.messages.team import AgentState, PgoEpoch
from kimera_multi_py.eval.metrics import ate_rmse
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.pgo.team import EPOCH_ROUNDS, ScheduleParams, TeamPgo
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.sim.source import keyframe_input
from kimera_multi_py.team.build import agent_params

from ..sim.helpers import SMALL, TINY


def _run_free(sim, period=20.0):
    """Every node runs its own loop (``AgentNode.run``) on wall-clock timers; nothing steps them."""
    async def main():
        net = LoopbackNetwork(team="t0", seed=0)
        schedule = ScheduleParams(period=period, round_timeout=None, final_grace=0.2)  # rounds wait for statuses
        nodes = [AgentNode(Agent(r, None, agent_params(sim.cfg)), net.bus(r), PgoParams(robust=True, max_rounds=200),
                           schedule, NodeParams()) for r in range(sim.num_robots)]
        for n in nodes:
            await n.start()
        streams = [[keyframe_input(kf) for kf in sim.keyframes(r)] for r in range(sim.num_robots)]
        runs = (n.run(s, rate=math.inf, linger=0.2) for n, s in zip(nodes, streams, strict=True))
        await asyncio.wait_for(asyncio.gather(*runs), 900)  # a hang guard only
        for n in nodes:
            await n.close()
        return nodes

    return asyncio.run(main())


@pytest.fixture(scope="module")
def small_free():
    # a non-aliased floor (sims/tiny.toml's twin rooms can leave a robot honestly out of the team frame)
    sim = Simulation(load_scenario(SMALL), seed=0)
    return sim, _run_free(sim)


@pytest.mark.slow
def test_free_running_nodes_finish_together_and_optimise(small_free):
    sim, nodes = small_free
    assert all(n.complete and n.finished for n in nodes)
    # every node took part in the same epochs, the last one final, opened by the lowest id
    assert len({n.pgo.completed for n in nodes}) == 1 and nodes[0].pgo.completed >= 2
    assert nodes[0].pgo.stats.opened == nodes[0].pgo.completed and nodes[1].pgo.stats.opened == 0
    assert all(n.pgo.final_done for n in nodes)
    # the inter-robot closures reached the solver, and robot 1 was aligned into robot 0's frame
    last = nodes[1].pgo.last_pgo
    assert last is not None and last.frame.aligned and len(last.local.inter_edge) > 0
    for n in nodes:
        assert n.agent.num_keyframes == len(sim.plans[n.robot].poses)
        assert sum(n.errors.values()) == 0


@pytest.mark.slow
def test_free_running_estimates_are_in_one_frame(small_free):
    """Robots' final estimates, aligned to the world once for the whole team, are not worse than
    each robot's own dead reckoning anchored at its true start."""
    sim, nodes = small_free
    est = np.concatenate([np.array(n.agent.poses)[:, :3, 3] for n in nodes])
    true = np.concatenate([sim.plans[n.robot].poses[:, :3, 3] for n in nodes])
    team = ate_rmse(est, true)
    dead = np.concatenate([(sim.plans[n.robot].poses[0] @ np.array(n.agent.dead_reckoning))[:, :3, 3]
                           for n in nodes])
    assert team < 2 * ate_rmse(dead, true)  # one frame: a robot left in its own frame would be metres off
    assert team < 0.5


def test_epoch_tags_keep_other_epochs_out():
    """A status of epoch 1 must not satisfy a round of epoch 2, and an older epoch is ignored."""
    async def main():
        net = LoopbackNetwork(team="t0", seed=0)
        sim = Simulation(load_scenario(TINY), seed=0)
        node = AgentNode(Agent(1, None, agent_params(sim.cfg)), net.bus(1), schedule=ScheduleParams(round_timeout=None))
        await node.start()
        for kf, _ in zip(sim.keyframes(1), range(5), strict=False):
            await node.process_keyframe(keyframe_input(kf))
        pgo = node.pgo
        members = np.array([0, 1], np.int64)
        pgo.handle(PgoEpoch(robot=0, epoch=2, members=members, pairs=np.array([[0, 1]]), final=False), {0})
        assert pgo.session is not None and pgo.session.epoch == 2
        pgo.handle(PgoStatus(robot=0, round=1 * EPOCH_ROUNDS + 7, ready=True, cost=0.0, rel_change=0.0), {0})
        assert pgo.session.seen == {}
        pgo.handle(PgoStatus(robot=0, round=2 * EPOCH_ROUNDS + 3, ready=True, cost=0.0, rel_change=0.0), {0})
        assert pgo.session.seen == {0: 3}
        pgo.handle(PgoEpoch(robot=0, epoch=1, members=members, pairs=np.zeros((0, 2)), final=False), {0})
        assert pgo.session.epoch == 2  # an old epoch does not replace the running one
        # a newer epoch heard of through a peer's state is not re-run from an old announcement
        pgo.handle(AgentState(robot=0, keyframes=5, stamp=1.0, finished=False, epoch=5, complete=False,
                              closures=0, rounds=0, bytes_sent=0), {0})
        assert pgo.session.epoch == 2 and pgo.epoch == 2  # a running epoch is not skipped by a peer's state
        await node.close()

    asyncio.run(main())


def test_closures_accepted_after_the_final_epoch_get_a_final_epoch_of_their_own():
    """A closure the team accepts once its final epoch opened (verified during it, or answered
    late) is optimised: the leader runs one more final epoch, and only when there is something new."""

    sim = Simulation(load_scenario(TINY), seed=0)
    agent = Agent(0, None, agent_params(sim.cfg))
    for kf, _ in zip(sim.keyframes(0), range(6), strict=False):
        agent.process_keyframe(keyframe_input(kf))
    accepted = [3]  # inter-robot closures accepted in the team, as this robot heard
    pgo = TeamPgo(0, PgoParams(robust=True, max_rounds=50), ScheduleParams(round_timeout=None),
                  agent.local_graph, agent.apply_poses, lambda: agent.robot_graph, lambda: accepted[0])

    def run(ticks: int = 200) -> list[bool]:
        for t in range(ticks):
            pgo.tick(10.0, float(t), set(), finished=True, force=True)
        return [h[2] for h in pgo.history]

    assert run() == [True] and pgo.final_done
    assert run() == [True]  # nothing new: no epoch
    accepted[0] = 4  # one more closure, after the final epoch
    assert run() == [True, True] and pgo.final_done
    assert run() == [True, True]


def _leader_pgo() -> TeamPgo:
    """Robot 0's TeamPgo over its first six keyframes of the tiny scenario, no closures."""
    sim = Simulation(load_scenario(TINY), seed=0)
    agent = Agent(0, None, agent_params(sim.cfg))
    for kf, _ in zip(sim.keyframes(0), range(6), strict=False):
        agent.process_keyframe(keyframe_input(kf))
    return TeamPgo(0, PgoParams(max_rounds=50), ScheduleParams(round_timeout=None),
                   agent.local_graph, agent.apply_poses, lambda: agent.robot_graph, lambda: 0)


def test_a_robot_met_after_the_final_epoch_gets_another() -> None:
    """A partition that healed after the streams ended: the robot met again was not a member of
    the final epoch, so the final epoch runs again, with it (and only while it is present)."""
    from kimera_multi_py.comms.messages.team import AgentState

    pgo = _leader_pgo()
    for t in range(200):
        pgo.tick(10.0, float(t), set(), finished=True, force=True)
    assert [h[2] for h in pgo.history] == [True] and pgo.final_done

    def state(robot: int) -> AgentState:
        return AgentState(robot=robot, keyframes=10, stamp=40.0, finished=True, epoch=1, complete=True,
                          closures=0, rounds=0, bytes_sent=0)

    pgo.handle(state(0), alive={0})  # itself, a member of the final epoch: nothing to do
    assert pgo.final_done
    pgo.handle(state(2), alive=set())  # heard of, but not present: not waited for
    assert pgo.final_done
    pgo.handle(state(2), alive={2})  # met again, its stream ended too
    assert not pgo.final_done
    for t in range(200, 400):  # the leader opens another final epoch, with it
        pgo.tick(50.0, float(t), {2}, finished=True, force=True)
    assert pgo.history[-1][1] == (0, 2) and pgo.history[-1][2]


def test_a_member_out_of_the_frame_after_the_final_epoch_gets_it_run_again_a_bounded_number_of_times() -> None:
    """A member whose safety net took it out of the team frame after the final epoch reports that
    it is no longer complete; the leader runs the final epoch again so that it can decide afresh,
    at most MAX_REOPEN times for one robot."""
    from kimera_multi_py.comms.messages.team import AgentState
    from kimera_multi_py.pgo.team import MAX_REOPEN

    pgo = _leader_pgo()

    def state(epoch: int, complete: bool) -> AgentState:
        return AgentState(robot=1, keyframes=10, stamp=40.0, finished=True, epoch=epoch, complete=complete,
                          closures=0, rounds=0, bytes_sent=0)

    t = 0

    def run() -> list[bool]:
        nonlocal t
        for _ in range(200):
            pgo.tick(10.0, float(t), {1}, finished=True, force=True)
            t += 1
        return [h[2] for h in pgo.history]

    pgo.handle(state(0, False), alive={1})
    assert run() == [True] and pgo.final_done and pgo.history[-1][1] == (0, 1)
    pgo.handle(state(1, True), alive={1})  # it completed the final epoch too
    pgo.handle(state(0, False), alive={1})  # an old state, from before the final epoch
    assert run() == [True]
    for k in range(MAX_REOPEN):
        pgo.handle(state(pgo.completed, False), alive={1})  # out of the frame: no longer complete
        assert not pgo.final_done
        assert run() == [True] * (k + 2) and pgo.history[-1][1] == (0, 1)
    pgo.handle(state(pgo.completed, False), alive={1})  # the cap: the team does not run again
    assert pgo.final_done and run() == [True] * (MAX_REOPEN + 1)

