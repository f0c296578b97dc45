"""Loop-closure traffic that was lost, or sent while a peer was out of reach, is recovered: the
leader learns robot pairs from the members' states and optimises again with them, and a query
that no reply answered is asked again (docs/deployment.md, faults)."""

import asyncio
import dataclasses

import numpy as np

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.node import AgentNode, NodeParams
from kimera_multi_py.comms import LoopbackNetwork, codec
from kimera_multi_py.comms.bus import PresenceEvent
from kimera_multi_py.comms.messages.closures import LoopClosureRequest
from kimera_multi_py.comms.messages.team import AgentState, PgoEpoch
from kimera_multi_py.pgo.params import PgoParams
from kimera_multi_py.pgo.team import ScheduleParams, TeamPgo
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.sim.source import keyframe_input
from kimera_multi_py.team.build import agent_params

from ..sim.helpers import TINY


def _state(robot: int, pairs: list[tuple[int, int]]) -> AgentState:
    return AgentState(robot=robot, keyframes=10, stamp=40.0, finished=True, epoch=1, complete=True,
                      closures=len(pairs), rounds=0, bytes_sent=0, pairs=np.array(pairs, np.int64).reshape(-1, 2))


def _robot(robot: int, accepted: int = 0) -> tuple[Agent, TeamPgo]:
    """An agent of ``sims/tiny.toml`` with 6 keyframes, and its TeamPgo (rounds end when forced)."""
    sim = Simulation(load_scenario(TINY), seed=0)
    agent = Agent(robot, None, agent_params(sim.cfg))
    for kf, _ in zip(sim.keyframes(robot), range(6), strict=False):
        agent.process_keyframe(keyframe_input(kf))
    return agent, TeamPgo(robot, PgoParams(max_rounds=50), ScheduleParams(round_timeout=None), agent.local_graph,
                          agent.apply_poses, lambda: agent.robot_graph, lambda: accepted)


def test_agent_state_carries_the_robot_graph_over_the_wire():
    def wire(msg: AgentState) -> AgentState:
        back = codec.decode(codec.encode(msg, team="t0", src=1, seq=0, stamp=1.0), team="t0").msg
        assert isinstance(back, AgentState)
        return back

    assert wire(_state(1, [(1, 2)])).pairs.tolist() == [[1, 2]]
    old = AgentState(robot=1, keyframes=0, stamp=0.0, finished=False, epoch=0, complete=False, closures=0,
                     rounds=0, bytes_sent=0)  # a state built without pairs: none
    assert wire(old).pairs.shape == (0, 2)


def test_a_pair_the_leader_learns_after_the_final_epoch_gets_another_final_epoch():
    """The leader lost every closure message between robots 1 and 2 (its own count of accepted
    closures never moves), so its final epoch left robot 1 the root of a frame of its own. A member's
    state names the pair: the leader joins them and runs the final epoch again, once."""
    agent, pgo = _robot(0, accepted=5)
    agent.robot_graph.add((0, 2))
    opened: list[PgoEpoch] = []
    alive = {1, 2}

    def run(start: int) -> list[bool]:
        for t in range(start, start + 200):
            opened.extend(m for m in pgo.tick(50.0, float(t), alive, finished=True, force=True)
                          if isinstance(m, PgoEpoch))
        return [h[2] for h in pgo.history]

    for r in (1, 2):
        pgo.handle(_state(r, []), alive)
    assert run(0) == [True] and pgo.final_done
    assert opened[-1].pairs.tolist() == [[0, 2]]
    assert run(200) == [True]  # nothing new
    # robot 2's state names the pair (1, 2), which the leader's agent absorbs
    assert agent.handle(_state(2, [(0, 2), (1, 2)])) == []
    assert (1, 2) in agent.robot_graph
    assert run(400) == [True, True] and pgo.final_done
    assert opened[-1].final and opened[-1].pairs.tolist() == [[0, 2], [1, 2]]
    assert run(600) == [True, True]  # and only once


def test_a_closure_whose_batch_the_leader_lost_still_gets_a_final_epoch():
    """Robots 1 and 2 are joined already; robot 1 verifies one more closure with robot 2 after the
    final epoch, and the leader loses that batch (robot 2 acknowledged it: no re-send comes). Robot
    1's periodic state counts the closures it verified: the leader's count moves, and the final
    epoch runs again, once. The receiver's count is not added to the verifier's (a closure is
    counted once, at its verifier)."""
    async def main() -> None:
        net = LoopbackNetwork(team="t0", seed=0)
        sim = Simulation(load_scenario(TINY), seed=0)
        node = AgentNode(Agent(0, None, agent_params(sim.cfg)), net.bus(0), PgoParams(max_rounds=50),
                         ScheduleParams(round_timeout=None))
        await node.start()
        for kf, _ in zip(sim.keyframes(0), range(6), strict=False):
            await node.process_keyframe(keyframe_input(kf))
        pgo, alive = node.pgo, {1, 2}
        assert pgo is not None

        def run(start: int) -> list[bool]:
            for t in range(start, start + 200):
                pgo.tick(50.0, float(t), alive, finished=True, force=True)
            return [h[2] for h in pgo.history]

        node._closure_counts[(1, 2)] = 3  # robot 1's batch to robot 2, heard
        pgo.handle(dataclasses.replace(_state(1, [(1, 2)]), closures=3), alive)
        pgo.handle(dataclasses.replace(_state(2, [(1, 2)]), closures=0), alive)
        assert node._accepted_inter() == 3
        assert run(0) == [True] and pgo.final_done
        assert run(200) == [True]  # nothing new
        pgo.handle(dataclasses.replace(_state(1, [(1, 2)]), closures=4), alive)  # the late closure's batch: lost
        assert node._accepted_inter() == 4
        assert run(400) == [True, True] and pgo.final_done
        assert run(600) == [True, True]  # and only once
        await node.close()

    asyncio.run(main())


class _Recorder(AgentNode):
    """An AgentNode whose constellation queries are recorded, not sent (the unit under test is
    when they are asked again)."""

    asked: list[LoopClosureRequest]

    async def _query(self, msg: LoopClosureRequest) -> None:
        self.asked.append(msg)


def test_an_unanswered_query_is_asked_again_while_unanswered_and_when_its_target_reappears():
    async def main() -> None:
        net = LoopbackNetwork(team="t0", seed=0)
        sim = Simulation(load_scenario(TINY), seed=0)
        node = _Recorder(Agent(0, None, agent_params(sim.cfg)), net.bus(0), params=NodeParams(query_reasks=2))
        node.asked = []
        peer = net.bus(1)
        await node.start()
        await peer.announce()
        agent = node.agent
        # two queries no reply answered: keyframe 7 of robot 1 against our 3, keyframe 9 of robot 2
        agent._pending.update({5: (1, 7, 3), 6: (2, 9, 4)})
        assert [(q.request_id, q.target, q.keyframe, q.query_keyframe) for q in agent.unanswered(1)] == [(5, 1, 7, 3)]
        assert node.verifying() == 1 and node._state().verifying == 1  # robot 2 is absent: not waited on
        for wall in (0.0, 1.0, 5.0, 10.0, 15.0, 20.0):  # present: asked every resend period, up to the cap
            await node.tick(wall)
        assert [q.request_id for q in node.asked] == [5, 5]  # robot 2 is absent: never asked
        assert node.verifying() == 0  # asked as often as it will be: nothing more comes of it
        node.asked.clear()
        await node._on_presence(PresenceEvent(robot=2, alive=True))  # it appears: asked now
        await node._on_presence(PresenceEvent(robot=1, alive=True))  # reappears: asked beyond the cap
        assert [q.request_id for q in node.asked] == [6, 5]
        # a reply (here: the request settled) ends the asking
        agent._pending.clear()
        node.asked.clear()
        await node._on_presence(PresenceEvent(robot=1, alive=True))
        await node.tick(30.0)
        assert node.asked == []
        await node.close()

    asyncio.run(main())


def test_a_robot_that_was_the_root_of_its_own_frame_is_not_taken_for_in_the_team_frame():
    """Robot 1 ran an epoch alone (the root of its own frame, its pairs unknown to the leader).
    When an epoch joins it to robot 0 its poses are not in robot 0's frame: its frame is decided
    afresh, not kept against a tie; an epoch rooted alike keeps it."""
    _, pgo = _robot(1)

    def epoch(e: int, members: list[int], pairs: list[tuple[int, int]]) -> bool:
        pgo.handle(PgoEpoch(robot=min(members), epoch=e, members=np.array(members, np.int64),
                            pairs=np.array(pairs, np.int64).reshape(-1, 2), final=False), set(members) - {1})
        assert pgo.session is not None
        kept = pgo.session.pgo.frame.in_team_frame
        for t in range(100):
            pgo.tick(10.0, float(t), set(members) - {1}, finished=False, force=True)
        assert pgo.session is None and pgo.completed == e
        return kept

    assert not epoch(1, [1], [])  # nothing before it
    assert epoch(2, [1], [])  # alone again: its own frame, which it is in
    assert pgo.last_pgo is not None and pgo.last_pgo.root
    assert not epoch(3, [0, 1], [(0, 1)])  # another root: decided afresh


def test_a_peer_gone_before_its_stream_ended_and_its_return_are_logged(caplog):
    """A fault leaves a trace in a robot's log: a peer out of reach while it still streamed, and
    its return; a peer leaving after its stream ended (a normal exit) does not."""
    async def main() -> None:
        net = LoopbackNetwork(team="t0", seed=0)
        sim = Simulation(load_scenario(TINY), seed=0)
        node = _Recorder(Agent(0, None, agent_params(sim.cfg)), net.bus(0))
        node.asked = []
        await node.start()
        assert node.pgo is not None
        for r in (1, 2):
            await node._on_presence(PresenceEvent(robot=r, alive=True))
        node.pgo.handle(dataclasses.replace(_state(1, []), finished=False), {1, 2})
        node.pgo.handle(_state(2, []), {1, 2})  # robot 2's stream ended
        with caplog.at_level("WARNING", logger="kimera_multi_py.agent.node"):
            await node._on_presence(PresenceEvent(robot=1, alive=False))
            await node._on_presence(PresenceEvent(robot=2, alive=False))
            await node._on_presence(PresenceEvent(robot=1, alive=True))
        assert [r.getMessage() for r in caplog.records] == ["robot 0: robot 1 is out of reach",
                                                            "robot 0: robot 1 is back"]
        await node.close()

    asyncio.run(main())
