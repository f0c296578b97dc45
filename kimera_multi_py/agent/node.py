"""AgentNode: the asyncio runtime of one robot, end to end on its own clock (docs/deployment.md).

The node binds a pure :class:`Agent` and a :class:`TeamPgo` to a Bus and runs everything the
robot does, with no orchestrator:

* keyframes in (:meth:`process_keyframe`, from a source);
* the loop-closure protocol: descriptors out, constellation queries to peers (asked again while
  unanswered, and whenever their target (re)appears), verified closures out (re-sent until
  acknowledged, and again to a robot that (re)appears, together with our descriptors, so late
  joiners and restarted robots catch up), and the robot graph in every state (so the leader
  joins robots whose closure messages it lost);
* distributed PGO that the team starts and stops itself (:mod:`kimera_multi_py.pgo.team`),
  or in centralised mode the server's corrected poses;
* its progress as :class:`AgentState` on a period (the leader's view of who has finished).

Membership comes from presence (liveliness): whoever is alive is the team.

Two ways to drive it. The single-process simulation calls :meth:`drain` and :meth:`tick` with a
simulated clock (deterministic: a round's wait ends when the runtime says nothing more can
arrive). A robot process calls :meth:`run`, which feeds keyframes from a source at a rate, ticks
on wall time and returns when the team's final optimisation is done.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Iterable

import networkx as nx
import numpy as np

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.params import NodeParams as NodeParams  # re-exported: the node's knobs live with the agent's
from kimera_multi_py.comms import keys
from kimera_multi_py.comms.bus import Bus, Closeable, PresenceEvent, Subscription
from kimera_multi_py.comms.closure_stream import ClosureInbox, ClosureOutbox
from kimera_multi_py.comms.codec import Codec
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.closures import (
    KeyframeDescriptor,
    LoopClosureReply,
    LoopClosureRequest,
    LoopClosures,
    LoopClosuresAck,
)
from kimera_multi_py.comms.messages.pgo import PublicPoses
from kimera_multi_py.comms.messages.team import AgentState, PgoEpoch
from kimera_multi_py.comms.stream import BusClosedError, Stream
from kimera_multi_py.core.errors import KimeraMultiError
from kimera_multi_py.core.ids import MAX_AGENT_ID
from kimera_multi_py.core.keyframe import KeyframeInput
from kimera_multi_py.core.posegraph import split_key
from kimera_multi_py.mapshare.agreement import MapView, frame_check, map_view
from kimera_multi_py.mapshare.consensus import MAP_MESSAGES, MapConsensus, MapConsensusParams, get_map_consensus
from kimera_multi_py.mapshare.objects import OBJECT_MESSAGES, ObjectExchange
from kimera_multi_py.mapshare.people import PEOPLE_MESSAGES, PeopleExchange
from kimera_multi_py.pgo.agent import PgoAgent
from kimera_multi_py.pgo.params import PgoParams, team_params
from kimera_multi_py.pgo.pose_stream import PoseStreamParams
from kimera_multi_py.pgo.team import ScheduleParams, TeamPgo

log = logging.getLogger(__name__)

MAP_MODES = ("off", "roam", "exact", "laplacian")
MAX_FETCHED = 512  # peer keyframes kept for verification against more places of ours (compact: ~6 kB each)

class AgentNode:
    """One robot on a Bus (see the module docstring).

    ``clock`` gives team time in seconds (the simulation's clock, or the stream's); by default
    the stamp of the newest keyframe this node knows of (its own or a peer's state).
    """

    def __init__(self, agent: Agent, bus: Bus, pgo_params: PgoParams | None = None,
                 schedule: ScheduleParams | None = None, params: NodeParams | None = None,
                 clock: Callable[[], float] | None = None, map_params: MapConsensusParams | None = None) -> None:
        self.agent = agent
        self.bus = bus
        self.params = params or NodeParams()
        self.schedule = schedule or ScheduleParams()
        self.clock = clock or self._stream_time
        self.errors: Counter[str] = Counter()
        self.finished = False  # our stream ended
        self.complete = False  # the team's final optimisation reached us
        self.pgo: TeamPgo | None = None
        self.pgo_params = pgo_params or team_params()
        if not self.params.compact_wire:  # the full-size format: every GNC weight at every update
            self.pgo_params = dataclasses.replace(self.pgo_params, weights_full_every=1)
        if self.params.server is None:
            self.pgo = TeamPgo(agent.robot, self.pgo_params,
                               self.schedule, agent.local_graph, agent.apply_poses,
                               lambda: agent.robot_graph, self._accepted_inter, agent.objects.centres,
                               self._map_view, PoseStreamParams() if self.params.compact_wire else None)
        if self.params.map_consensus not in MAP_MODES:
            raise KimeraMultiError(f"map consensus: unknown mode {self.params.map_consensus!r} "
                                   f"(available: {', '.join(MAP_MODES)})")
        self.maps: MapConsensus | None = None
        if self.params.map_consensus != "off":
            if not self.params.compact_wire:  # the full-size evidence: plain rows, every period
                map_params = dataclasses.replace(map_params or MapConsensusParams(), palette_rows=False, hold=0.0)
            self.maps = get_map_consensus(agent.robot, agent.map, self.params.map_consensus, base=map_params)
        # the team's objects ride on the exact consensus's submap pose tables
        self.objects: ObjectExchange | None = None
        if self.maps is not None and self.maps.mode == "exact":
            maps = self.maps
            self.objects = ObjectExchange(agent.robot, agent.objects.confirmed,
                                          lambda src: maps.poses[src][0] if src in maps.poses else None,
                                          agent.objects.num_classes + 1)
        # and so do its people (docs/algorithms/people.md)
        self.people: PeopleExchange | None = None
        if self.maps is not None and self.maps.mode == "exact" and agent.params.people.enabled:
            maps = self.maps
            self.people = PeopleExchange(agent.robot, lambda: agent.people,
                                         lambda src: maps.poses[src][0] if src in maps.poses else None)
        # one-hop map neighbours (None: whoever is alive; the simulation can apply a radio range)
        self.map_neighbours: Callable[[], Iterable[int]] | None = None
        self.frame = agent.robot  # root robot of the frame our poses are in
        # centralised mode: the server's latest ``settled`` flag on our poses (None: none yet)
        self.server_settled: bool | None = None
        self._sub: Subscription | None = None
        self._serve: Closeable | None = None
        self._presence: Stream[PresenceEvent] | None = None
        self.closures_out = ClosureOutbox(self.params.compact_wire)  # our batches until acknowledged
        if isinstance(codec := getattr(bus, "codec", None), Codec):  # compressed tables (comms.wire.zipped)
            codec.compress = self.params.compact_wire
        self.closures_in = ClosureInbox()  # peers' batches to us, expanded
        self._fetched: dict[tuple[int, int], LoopClosureReply] = {}  # (peer, keyframe) -> its reply
        self._state_at = -math.inf
        self._peer_stamp = 0.0
        self.epochs_seen = 0
        self._frame_check_at: float | None = None  # when the safety net looks at the last epoch's frame
        self._closure_counts: dict[tuple[int, int], int] = {}
        self._recent_descriptors: list[KeyframeDescriptor] = []  # the last ones sent (repeated)
        self.queries_retried = 0
        self._reasked: Counter[int] = Counter()  # request id -> times asked again after its retries
        self._heard_peers: set[int] = set()  # robots whose presence we have seen
        self._reask_at = -math.inf

    @property
    def robot(self) -> int:
        return self.agent.robot

    @property
    def settled(self) -> bool:
        """The team's final optimisation reached this robot and its safety net has looked at the
        frame it left it in (which may send the team into another final epoch)."""
        return self.complete and self._frame_check_at is None

    def alive(self) -> frozenset[int]:
        """The agents present (the server is not a PGO member)."""
        return frozenset(r for r in self.bus.peers() if r <= MAX_AGENT_ID)

    def _stream_time(self) -> float:
        own = self.agent.stamps[-1] if self.agent.stamps else 0.0
        return max(own, self._peer_stamp)

    def _accepted_inter(self) -> int:
        """Inter-robot closures accepted anywhere in the team, as far as this node has heard: per
        verifying robot, its newest closure batches heard, or its periodic state's count of them,
        whichever is more (a batch lost on the way here that its peer then acknowledged is never
        re-sent; the state is). A late closure so still earns the leader's final epoch."""
        heard: Counter[int] = sum((Counter({s: n}) for (s, _), n in self._closure_counts.items()), Counter())
        states = self.pgo.states if self.pgo is not None else {}
        told = {r: st.closures for r, st in states.items() if r != self.robot}
        return sum(max(heard[r], told.get(r, 0)) for r in set(heard) | set(told))

    def _count_closures(self, msg: Message) -> None:
        if isinstance(msg, LoopClosures) and msg.robot != msg.peer:
            self._closure_counts[(msg.robot, msg.peer)] = len(msg.keys_a)

    # ------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        await self.bus.announce()
        self._serve = await self.bus.serve(keys.keyframe_key(self.bus.team, self.robot, "*"), self._serve_keyframe)
        self._sub = self.bus.subscribe(keys.team_all(self.bus.team))
        self._presence = self.bus.presence()

    async def close(self) -> None:
        for c in (self._sub, self._serve, self._presence):
            if c is not None:
                c.close()

    def _serve_keyframe(self, key: str, request: Message | None) -> LoopClosureReply:
        keyframe = int(key.rsplit("/", 1)[-1])
        rid = request.request_id if isinstance(request, LoopClosureRequest) else 0
        return self.agent.serve_keyframe(keyframe, rid, self.params.compact_wire)

    # ------------------------------------------------------------------ keyframes
    async def process_keyframe(self, kf: KeyframeInput) -> None:
        await self.send(self.agent.process_keyframe(kf))

    async def finish_stream(self) -> None:
        """Our source has no more keyframes: say so (the leader then runs the final epoch). The last
        submap's object fragments are merged now, so the final object table carries them."""
        self.agent.objects.merge_fragments(self.agent.map.octree)
        self.finished = True
        for old in self._recent_descriptors:  # the last descriptors' repeats
            await self._publish(old)
        self._recent_descriptors = []
        await self._publish_state()

    # ------------------------------------------------------------------ messages
    async def send(self, msgs: Iterable[Message]) -> None:
        for msg in msgs:
            if isinstance(msg, LoopClosureRequest):
                await self._query(msg)
                continue
            self._count_closures(msg)
            if isinstance(msg, LoopClosures):
                msg = self.closures_out.send(msg)
            if isinstance(msg, KeyframeDescriptor) and self.params.descriptor_repeats > 0:
                for old in self._recent_descriptors:
                    await self._publish(old)
                self._recent_descriptors = (self._recent_descriptors + [msg])[-self.params.descriptor_repeats:]
            await self._publish(msg)

    async def _publish(self, msg: Message) -> None:
        await self.bus.publish(self.bus.key(msg.TOPIC), msg)

    async def _query(self, msg: LoopClosureRequest) -> None:
        key = keys.keyframe_key(self.bus.team, msg.target, msg.keyframe)
        replies: list[Message] = []
        fetched = self._fetched.get((msg.target, msg.keyframe))
        if fetched is not None:  # fetched already, for another place of ours: it travels once
            replies = [dataclasses.replace(fetched, request_id=msg.request_id)]
        for attempt in range(0 if replies else 1 + max(self.params.query_retries, 0)):
            try:
                replies = await self.bus.query(key, msg, timeout=self.params.query_timeout)
            except (KimeraMultiError, TimeoutError) as exc:
                if attempt == self.params.query_retries:
                    self._refuse("query", exc)
                    return
                continue
            if replies or msg.target not in self.bus.peers():
                break
            self.queries_retried += 1
        for reply in replies:
            if fetched is None and isinstance(reply, LoopClosureReply) and reply.found and self.params.compact_wire:
                while len(self._fetched) >= MAX_FETCHED:
                    del self._fetched[next(iter(self._fetched))]
                self._fetched[(reply.robot, reply.keyframe)] = reply
            await self.send(self._handle_agent(reply))

    def _handle_agent(self, msg: Message) -> list[Message]:
        try:
            return self.agent.handle(msg)
        except (KimeraMultiError, ValueError, KeyError, IndexError) as exc:
            self._refuse(type(msg).__name__, exc)
            return []

    def _refuse(self, what: str, exc: Exception) -> None:
        self.errors[what] += 1
        log.warning("robot %d refused %s: %s", self.robot, what, exc, extra={"robot": self.robot})

    async def _dispatch(self, msg: Message) -> None:
        if msg.robot == self.robot:
            return
        if isinstance(msg, LoopClosures) and msg.peer == self.robot:
            try:
                msg = self.closures_in.expand(msg)
            except KimeraMultiError as exc:
                self._refuse("LoopClosures", exc)
                return
        self._count_closures(msg)
        if isinstance(msg, AgentState):
            self._peer_stamp = max(self._peer_stamp, msg.stamp)
        if isinstance(msg, LoopClosuresAck) and msg.peer == self.robot:
            self.closures_out.acked(msg.robot, msg.batch)
        if isinstance(msg, PEOPLE_MESSAGES):
            if self.people is not None:
                try:
                    self.people.handle(msg)
                except (KimeraMultiError, ValueError, KeyError, IndexError) as exc:
                    self._refuse(type(msg).__name__, exc)
            return
        if isinstance(msg, MAP_MESSAGES + OBJECT_MESSAGES):
            sink = self.maps if isinstance(msg, MAP_MESSAGES) else self.objects
            if sink is not None:
                try:
                    sink.handle(msg)
                except (KimeraMultiError, ValueError, KeyError, IndexError) as exc:
                    self._refuse(type(msg).__name__, exc)
            return
        if self.params.server is not None and msg.robot == self.params.server:
            if isinstance(msg, PublicPoses) and len(msg.keys) and split_key(int(msg.keys[0]))[0] == self.robot:
                # the server's poses for us: in the team frame, or (not settled) kept out, in our own
                self.server_settled = bool(msg.settled)
                self.frame = self._component_root(self.agent.robot_graph) if msg.settled else self.robot
            await self.send(self._handle_agent(msg))
            if isinstance(msg, PgoEpoch) and msg.final and self.finished and not self.complete:
                self.complete = True
                self.epochs_seen += 1
                await self._publish_state()
            return
        if self.pgo is not None:
            try:
                self.pgo.handle(msg, self.alive())
            except (KimeraMultiError, ValueError, KeyError, IndexError) as exc:
                self._refuse(type(msg).__name__, exc)
        await self.send(self._handle_agent(msg))

    async def _on_presence(self, event: PresenceEvent) -> None:
        """A robot (re)appeared: give it what it may have missed."""
        if event.robot <= MAX_AGENT_ID and event.robot != self.robot:  # a fault's trace in the log
            st = self.pgo.states.get(event.robot) if self.pgo is not None else None
            gone = not event.alive and st is not None and not st.finished  # before its stream ended
            if gone or (event.alive and event.robot in self._heard_peers):
                log.warning("robot %d: robot %d is %s", self.robot, event.robot, "out of reach" if gone else "back",
                            extra={"robot": self.robot})
            self._heard_peers.add(event.robot)
        if not event.alive or event.robot > MAX_AGENT_ID:
            if event.alive:  # the server: it needs our state to know who has finished
                await self._publish_state()
            return
        for k, c in sorted(self.agent.constellations.items()):
            await self._publish(KeyframeDescriptor(robot=self.robot, keyframe=k, stamp=c.stamp, kind="objects",
                                                   descriptor=c.descriptor))
        if event.robot in self.agent.closures and event.robot != self.robot:
            self.closures_out.forget(event.robot)
            await self._publish(self.closures_out.send(self.agent.closures_message(event.robot)))
        await self._publish_state()
        await self._reask(event.robot, appeared=True)

    async def _reask(self, peer: int, appeared: bool = False) -> None:
        """Ask ``peer`` again for what our unanswered queries wanted (a query lost on the way, or
        asked while it was out of reach); a robot that (re)appears is asked regardless of the cap."""
        for req in self.agent.unanswered(peer):
            if not appeared and self._reasked[req.request_id] >= self.params.query_reasks:
                continue
            self._reasked[req.request_id] += 1
            await self._query(req)

    async def drain(self) -> int:
        """Handle every message and presence event queued now; return how many."""
        if self._sub is None or self._presence is None:
            return 0  # not started (a robot that has not joined yet)
        n = 0
        while (event := self._presence.try_recv()) is not None:
            await self._on_presence(event)
            n += 1
        while (msg := self._sub.try_recv()) is not None:
            await self._dispatch(msg)
            n += 1
        return n

    # ------------------------------------------------------------------ the clock
    async def tick(self, wall: float | None = None, force: bool = False) -> int:
        """Timers: state, re-sends, the PGO schedule. Returns how many messages went out."""
        if self._sub is None:
            return 0
        now = self.clock()
        wall = time.monotonic() if wall is None else wall
        out: list[Message] = []
        if wall - self._state_at >= self.params.state_period:
            self._state_at = wall
            out.append(self._state())
        out += self.closures_out.due(wall, self.params.resend_period)
        if wall - self._reask_at >= self.params.resend_period:
            self._reask_at = wall
            for peer in sorted(self.alive() - {self.robot}):
                await self._reask(peer)
        if self.pgo is not None:
            before = self.pgo.completed
            try:
                out.extend(self.pgo.tick(now, wall, self.alive(), self.finished, force))
            except KimeraMultiError as exc:  # e.g. an epoch a peer pushed to the wire's limit
                self._refuse("pgo_tick", exc)
            if self.pgo.completed != before:
                self.epochs_seen += 1
                last = self.pgo.last_pgo
                if last is not None and last.frame.excluded:  # kept out: its poses are in its own frame
                    self.frame = self.robot
                elif last is not None and last.frame.aligned:
                    self.frame = self._component_root(last.local.robot_graph)
                    # after the peers' new pose tables had time to arrive: right after an epoch
                    # their maps may still sit where the epoch found them, ours where it left us
                    period = self.maps.params.period if self.maps is not None else 1.0
                    self._frame_check_at = wall + 2.0 * period
                out.append(self._state())
                if self.pgo.final_done and self.finished:
                    self.complete = True
        if self._frame_check_at is not None and wall >= self._frame_check_at and self.pgo is not None:
            self._frame_check_at = None
            if self.pgo.last_pgo is not None and self._safety_net(self.pgo.last_pgo):
                if self.complete and self.pgo.reopen(self.robot):
                    # out of the team frame after the final epoch: the team decides again, with
                    # the leader told by this state (no longer complete)
                    self.complete = False
                out.append(self._state())
        out.extend(self._map_step(wall))  # on the tick's clock: it goes on after the streams end
        for m in out:
            await self._publish(m)
        return len(out)

    def _map_view(self, frame: int) -> MapView | None:
        """How our map agrees with the other robots' evidence in the frame rooted at ``frame``."""
        if not self.pgo_params.map_check:
            return None
        p = self.pgo_params
        return map_view(self.maps, self.agent.map, frame, p.map_min_conflicts, p.map_conflict_ratio, p.map_coarse,
                        p.map_occupancy)

    def _safety_net(self, last: PgoAgent) -> bool:
        """After an epoch that left us in a team frame: if our map contradicts the team's there,
        leave the frame (our evidence then leaves every team map, which keys it by frame) and say
        so; the next epoch decides again, and the maps refute this frame there too."""
        p = self.pgo_params
        if self.frame == self.robot or not p.map_check:  # the root of its own frame has nothing to check
            return False
        check = frame_check(self.maps, self.agent.map, self.frame, p.map_min_conflicts, p.map_conflict_ratio,
                            p.map_coarse, p.map_occupancy)
        if check is None:
            return False
        last.frame.alignment = {**last.frame.alignment, "safety_net": check.as_dict()}
        if not check.refuted:
            return False
        log.warning("robot %d: leaves team frame %d: its map contradicts robots %s there (agrees with %s)",
                    self.robot, self.frame, check.conflicting, check.agreeing, extra={"robot": self.robot})
        last.frame.excluded = True
        last.frame.alignment.update(status="excluded", settled=False,
                              reason=f"safety net: its map contradicts the team's in frame {self.frame}")
        self.frame = self.robot
        return True

    def _map_step(self, now: float) -> list[Message]:
        if self.maps is None:
            return []
        if self.map_neighbours is not None:
            neighbours = set(self.map_neighbours())
        elif self.params.server is not None:
            neighbours = {self.params.server} & set(self.bus.peers())
        else:
            neighbours = set(self.alive())
        self.maps.set_neighbours(neighbours)
        self.maps.set_frame(self.frame)
        self.maps.set_team_size(len(self.alive()) + 1)
        out = self.maps.step(now)
        if self.objects is not None:
            self.objects.set_neighbours(neighbours)
            self.objects.set_frame(self.frame)
            out += self.objects.step(now)
        if self.people is not None:
            self.people.set_neighbours(neighbours)
            self.people.set_frame(self.frame)
            out += self.people.step(now)
        return out

    @property
    def alignment(self) -> dict[str, object]:
        """What the frame our poses are in rests on (``alignment`` in the outputs), with ``frame``:
        the last PGO epoch's frame decision, or in centralised mode the server's (``status`` root /
        aligned from a settled flag, excluded from one not settled: kept out, in our own frame)."""
        out: dict[str, object] = {}
        if self.pgo is not None:
            last = self.pgo.last_pgo
            out = dict(last.frame.alignment) if last is not None else {}
        elif self.server_settled is not None:
            status = "excluded" if not self.server_settled else "root" if self.frame == self.robot else "aligned"
            out = {"status": status, "settled": self.server_settled, "source": "server"}
            if status == "excluded":
                out["reason"] = "the server kept it out of the team frame"
        out["frame"] = int(self.frame)
        return out

    def _component_root(self, pairs: Iterable[tuple[int, int]]) -> int:
        """The lowest robot id connected to this one through ``pairs``."""
        g = nx.Graph()
        g.add_node(self.robot)
        g.add_edges_from((int(a), int(b)) for a, b in pairs)
        return min(nx.node_connected_component(g, self.robot))

    def blocked(self) -> bool:
        return self.pgo is not None and self.pgo.blocked()

    def memory(self) -> dict[str, int]:
        """Bytes the robot's own map holds (submaps, fused evidence, octree) and, with a team map,
        the map consensus's evidence store (docs/performance.md)."""
        store = {"map_store_bytes": self.maps.nbytes} if self.maps is not None else {}
        return {"own_map_bytes": self.agent.map.nbytes, **store}

    def verifying(self) -> int:
        """Our unanswered queries to peers present that we will ask again: closures may come of them."""
        alive, cap = self.alive(), self.params.query_reasks
        return sum(p in alive and self._reasked[r] < cap for r, p in self.agent.unanswered_requests().items())

    def _state(self) -> AgentState:
        completed = self.pgo.completed if self.pgo is not None else 0
        stamp = self.agent.stamps[-1] if self.agent.stamps else 0.0
        rounds = self.pgo.stats.rounds if self.pgo is not None else 0
        return AgentState(robot=self.robot, keyframes=self.agent.num_keyframes, stamp=stamp,
                          finished=self.finished, epoch=completed, complete=self.complete,
                          closures=self.agent.verified_inter(), rounds=rounds,
                          bytes_sent=self.bus.counters.total("sent").bytes,
                          pairs=np.array(sorted(self.agent.robot_graph), dtype=np.int64).reshape(-1, 2),
                          verifying=self.verifying())

    async def _publish_state(self) -> None:
        await self._publish(self._state())

    # ------------------------------------------------------------------ one robot per process
    async def run(self, keyframes: Iterable[KeyframeInput], rate: float = math.inf,
                  on_keyframe: Callable[[KeyframeInput], object] | None = None,
                  tick_s: float = 0.005, linger: float = 2.0, epoch_wait: float = 30.0) -> None:
        """Feed ``keyframes`` (paced at ``rate`` × their stamps; ``inf``: as fast as possible),
        handle messages and timers, and return once the team's final optimisation is done
        (then keep serving peers for ``linger`` s)."""
        assert self._sub is not None, "start() first"
        feeder = asyncio.create_task(self._feed(keyframes, rate, on_keyframe))
        try:
            while not self.complete:
                if feeder.done() and feeder.exception() is not None:
                    raise feeder.exception()  # type: ignore[misc]
                await self.drain()
                await self.tick()
                await asyncio.sleep(tick_s)
            # linger; an epoch still running then (a final epoch re-run for late closures) may
            # finish, for at most ``epoch_wait`` s more, so that its poses are in our outputs
            end = time.monotonic() + linger
            while time.monotonic() < end or (self.pgo is not None and self.pgo.busy
                                             and time.monotonic() < end + epoch_wait):
                await self.drain()
                await self.tick()
                await asyncio.sleep(tick_s)
        except BusClosedError:
            log.info("robot %d: bus closed", self.robot, extra={"robot": self.robot})
        finally:
            if not feeder.done():
                feeder.cancel()

    async def _feed(self, keyframes: Iterable[KeyframeInput], rate: float,
                    on_keyframe: Callable[[KeyframeInput], object] | None) -> None:
        t0: float | None = None
        s0 = 0.0
        for kf in keyframes:
            if t0 is None:
                t0, s0 = time.monotonic(), kf.stamp
            if math.isfinite(rate):
                wait = t0 + (kf.stamp - s0) / rate - time.monotonic()
                if wait > 0:
                    await asyncio.sleep(wait)
            await self.process_keyframe(kf)
            if on_keyframe is not None:
                on_keyframe(kf)
            await asyncio.sleep(0)
        await self.finish_stream()
