"""Async runtime for distributed PGO: moves :class:`PgoAgent` messages over one Bus per robot.

Each robot runs rounds. Before round ``r`` it waits (up to ``round_timeout``) for the status of
round ``r − 1`` from every robot it depends on (its neighbours; the leader waits for all), so
adjacent robots are never more than one round apart and the colour schedule holds. A lost
message costs one timeout; the agent then uses the latest values it has (stale by a round).
The runtime records every robot's poses per round so the caller can score convergence.

On the in-process network (:class:`LoopbackNetwork`) a timeout is not a wall-clock wait: a robot
gives up waiting when the whole team is quiet (every running robot waits, nothing is queued for
them and no delivery is in flight), which is exactly when a lost message can no longer arrive. A
lossy run then costs the rounds its losses cost and no wall time, and it is deterministic for a
seed; ``round_timeout`` is not used there (:data:`QUIET_CAP` bounds one wait, against a bug). On a
network with a custom clock, delayed deliveries are made then too, in order of due time, instead
of being waited for (:mod:`kimera_multi_py.comms.deliveries`).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.bus import Bus, Subscription
from kimera_multi_py.comms.loopback import LoopbackNetwork
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.pgo import PgoCommand, PgoStatus, PoseDeltas, PublicPoses
from kimera_multi_py.comms.stream import BusClosedError
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.pgo.agent import PgoAgent
from kimera_multi_py.pgo.pose_stream import PoseDecoder, PoseEncoder, PoseStreamParams

log = logging.getLogger(__name__)

RoundCallback = Callable[[int, dict[int, np.ndarray]], None]
QUIET_CAP = 60.0  # s: the wall-clock cap of one wait on the in-process network (a safety net)
QUIET_POLL = 0.005  # s between quiescence checks while a robot waits


class _Quiet:
    """Round timeouts on an in-process network: waits end when the team is quiet (module doc).

    A waiting robot polls its queue, yielding to the others (``sleep(0)``: the event loop runs
    the tasks in a fixed order, so the first robot to see the team quiet, and so every
    decision, is the same on every run)."""

    def __init__(self, network: LoopbackNetwork, robots: Sequence[int]) -> None:
        self.network = network
        self.running = set(robots)
        self.waiting: dict[int, Subscription] = {}
        self.expired: set[int] = set()

    def _quiet(self) -> bool:
        return not self.network.in_flight and self._waiting_on_delays()

    def _waiting_on_delays(self) -> bool:
        """Every running robot waits with nothing queued: only delayed deliveries can come."""
        return set(self.waiting) == self.running and all(sub.pending() == 0 for sub in self.waiting.values())

    async def recv(self, robot: int, sub: Subscription) -> Message | None:
        """The next message for ``robot``, or ``None`` once the team is quiet (a timeout)."""
        loop = asyncio.get_running_loop()
        cap = loop.time() + QUIET_CAP
        self.waiting[robot] = sub
        try:
            while True:
                if robot in self.expired:
                    self.expired.discard(robot)
                    return None
                if (msg := sub.try_recv()) is not None:
                    return msg
                if self._quiet():  # every waiting robot times out together
                    self.expired.update(r for r in self.waiting if r != robot)
                    return None
                if self._waiting_on_delays() and self.network.step():
                    continue  # on a custom clock: the next delayed deliveries, no wall time
                if loop.time() > cap:
                    log.warning("robot %d: no message and no quiet team within %.0f s", robot, QUIET_CAP)
                    return None
                # on a custom clock nothing moves by itself: no wall-clock poll
                await asyncio.sleep(QUIET_POLL if self.network.in_flight and not self.network.simulated else 0)
        finally:
            del self.waiting[robot]

    def leave(self, robot: int) -> None:
        self.running.discard(robot)


@dataclass
class RunStats:
    """What the runtime observed: rounds run, bytes on the wire and wall time."""

    rounds: int = 0
    bytes_sent: int = 0
    bytes_by_robot: dict[int, int] = field(default_factory=dict)
    bytes_by_topic: dict[str, int] = field(default_factory=dict)
    timeouts: int = 0
    wall_s: float = 0.0
    dropped: int = 0  # messages lost on the way (filled in by a caller that can count them)
    refused: int = 0  # pose messages that did not fit what their sender sent before (pose stream)
    unusable: int = 0  # pose deltas against a keyframe that was lost


class _RoundLog:
    """Collects per-robot poses per round; calls back when every robot has reported a round."""

    def __init__(self, robots: Sequence[int], callback: RoundCallback | None) -> None:
        self.robots = set(robots)
        self.callback = callback
        self.pending: dict[int, dict[int, np.ndarray]] = {}
        self.latest: dict[int, np.ndarray] = {}
        self.finished: set[int] = set()

    def report(self, robot: int, rnd: int, poses: np.ndarray) -> None:
        self.latest[robot] = poses
        self.pending.setdefault(rnd, {})[robot] = poses
        self._flush()

    def finish(self, robot: int) -> None:
        self.finished.add(robot)
        self._flush()

    def _flush(self) -> None:
        for rnd in sorted(self.pending):
            got = self.pending[rnd]
            missing = self.robots - set(got) - self.finished
            if missing:
                break
            for r in self.robots - set(got):
                got[r] = self.latest[r]
            del self.pending[rnd]
            if self.callback is not None:
                self.callback(rnd, got)


async def run_team(agents: Sequence[PgoAgent], buses: Sequence[Bus], max_rounds: int,
                   round_timeout: float = 0.5, on_round: RoundCallback | None = None,
                   start_round: dict[int, int] | None = None,
                   stream: PoseStreamParams | None = None) -> RunStats:
    """Run every agent on its own bus until all stop or ``max_rounds``.

    ``round_timeout``: wall seconds a round waits over a real transport; on the in-process network
    a wait ends when the team is quiet instead (module doc) and it is not used. ``start_round``
    lets a robot join late: it sits out (silent) until that round. ``stream``: public poses travel
    as a :mod:`.pose_stream` (keyframes and float32 deltas); None: every :class:`PublicPoses` in full.
    """
    t0 = time.perf_counter()
    stats = RunStats()
    robots = [a.robot for a in agents]
    log_ = _RoundLog(robots, on_round)
    subs = [bus.subscribe(keys.team_all(bus.team)) for bus in buses]
    for bus in buses:
        await bus.announce()
    start_round = start_round or {}
    network = getattr(buses[0], "network", None) if buses else None
    quiet = _Quiet(network, robots) if isinstance(network, LoopbackNetwork) else None
    tasks = [
        asyncio.create_task(_robot(agent, bus, sub, max_rounds, round_timeout, log_, stats,
                                   start_round.get(agent.robot, 0), stream, quiet))
        for agent, bus, sub in zip(agents, buses, subs, strict=True)
    ]
    try:
        stats.rounds = max(await asyncio.gather(*tasks)) + 1
    finally:
        for sub in subs:
            sub.close()
    for bus in buses:
        snap = bus.counters.snapshot()["sent"]
        total = sum(v["bytes"] for v in snap.values())
        stats.bytes_by_robot[bus.robot] = total
        stats.bytes_sent += total
        for topic, v in snap.items():
            stats.bytes_by_topic[topic] = stats.bytes_by_topic.get(topic, 0) + v["bytes"]
    stats.wall_s = time.perf_counter() - t0
    return stats


async def _robot(agent: PgoAgent, bus: Bus, sub: Subscription, max_rounds: int, timeout: float,
                 round_log: _RoundLog, stats: RunStats, start: int, stream: PoseStreamParams | None,
                 quiet: _Quiet | None = None) -> int:
    depends = agent.dependencies()
    # gn_pcg's lock-step wants the public poses exact (as :class:`~.team.TeamPgo` does)
    encoder = PoseEncoder(stream) if stream is not None and agent.params.method == "block_sor" else None
    decoder = PoseDecoder()
    seen: dict[int, int] = {}  # robot -> latest status round
    stopped: set[int] = set()
    rnd = 0

    def absorb(msg: Message) -> None:
        if isinstance(msg, PgoStatus):
            seen[msg.robot] = max(seen.get(msg.robot, -1), msg.round)
        if isinstance(msg, PgoCommand) and msg.command == "stop":
            stopped.add(msg.robot)
        if isinstance(msg, PublicPoses | PoseDeltas):
            try:
                decoded = decoder.decode(msg)
            except MessageError as exc:
                stats.refused += 1
                log.warning("robot %d refused %s: %s", agent.robot, type(msg).__name__, exc)
                return
            if decoded is None:
                stats.unusable += 1
                return
            msg = decoded
        agent.handle(msg)

    async def drain() -> None:
        while (msg := sub.try_recv()) is not None:
            absorb(msg)

    try:
        for rnd in range(max_rounds):
            if rnd < start:
                await asyncio.sleep(0)
                await drain()
                round_log.report(agent.robot, rnd, agent.state.poses)
                continue
            # wait for the statuses of round rnd-1 from the robots this one depends on
            deadline = time.perf_counter() + timeout
            while True:
                await drain()
                waiting = [r for r in depends if seen.get(r, -1) < rnd - 1 and r not in stopped]
                if not waiting or agent.done or rnd == start:
                    break
                if quiet is not None:
                    msg = await quiet.recv(agent.robot, sub)
                    if msg is None:
                        stats.timeouts += 1
                        break
                    absorb(msg)
                    continue
                left = deadline - time.perf_counter()
                if left <= 0:
                    stats.timeouts += 1
                    break
                try:
                    absorb(await sub.recv(timeout=left))
                except TimeoutError:
                    stats.timeouts += 1
                    break
            if agent.done:
                break
            for msg in agent.step(rnd):
                out = encoder.encode(msg) if encoder is not None and isinstance(msg, PublicPoses) else msg
                if out is not None:
                    await bus.publish(bus.key(out.TOPIC), out)
            round_log.report(agent.robot, rnd, agent.state.poses)
            await asyncio.sleep(0)
            if agent.done:
                break
        if agent.done:
            # echo the stop so a robot that lost the leader's copy still hears it
            await bus.publish(bus.key(PgoCommand.TOPIC), PgoCommand(
                robot=agent.robot, round=rnd, command="stop", active=np.zeros(0, np.int64)))
    except BusClosedError:
        log.info("robot %d: bus closed at round %d", agent.robot, rnd)
    finally:
        if quiet is not None:
            quiet.leave(agent.robot)
    round_log.finish(agent.robot)
    return rnd
