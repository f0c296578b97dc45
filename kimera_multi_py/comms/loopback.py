"""In-process bus with deterministic fault injection, for the single-process sim and tests.

One :class:`LoopbackNetwork` connects the buses of many robots inside one asyncio loop. Every
message really goes through the codec (so validation runs and byte counts are real), then
crosses a link per receiving robot where :class:`Faults` may drop, delay (``delay`` plus
uniform ``±jitter``), duplicate or reorder (hold back by ``reorder_delay``) it, or cut it
during a :class:`Partition`. All random draws come from one ``random.Random(seed)`` in
publish order, so a run is reproducible for a given seed. A robot hears its own publications
without faults, as a Zenoh session does.

Queries cross the same faulty links (request and reply each may be dropped or delayed).
Presence follows ``announce()`` and ``close()``; ``peers()`` also hides robots that a partition
currently separates from this one.

With a :class:`~kimera_multi_py.comms.link_budget.LinkBudget`, every link between two robots is a
:class:`~kimera_multi_py.comms.link_budget.LinkQueue` on the network's clock: a message arrives
when its transfer ends, by priority class, and :meth:`LoopbackNetwork.link_report` says what each
link carried, how long messages waited and what could not be sent. On a custom clock (the
simulation's) nothing moves by itself: the owner calls :meth:`LoopbackNetwork.pump` as its clock
advances (:meth:`LoopbackNetwork.next_delivery` says when the next transfer ends), so a run is
deterministic. On the loop's clock the network pumps itself. A query is answered at once, but its
request and reply bytes are charged to their links at the top class, so they delay what follows
them. A budget replaces the fault delays (``delay``, ``jitter``, ``reorder`` must be 0).

On a custom clock no wait costs wall time (docs/deployment.md, "Faults on the simulated clock").
Fault delays run on the network's own event time, which never falls behind the clock: a delayed
delivery waits in a queue until its owner moves on (:meth:`LoopbackNetwork.step` delivers the next
ones, :meth:`LoopbackNetwork.settle` all), in order of due time. A query's wait ends once its
reply has arrived or can no longer arrive (request or reply lost, no answer): the deterministic
equivalent of its timeout, which is not used there. On the loop's clock delays and query timeouts
are real, as over Zenoh.

Example::

    net = LoopbackNetwork(seed=1, faults=Faults(drop=0.1, delay=0.01, jitter=0.005))
    a, b = net.bus(0), net.bus(1)
    sub = b.subscribe(keys.topic_all(b.team, keys.HEARTBEAT))
    await a.publish(a.key(keys.HEARTBEAT), Heartbeat(robot=0, keyframes=3))
    await net.settle()              # wait until nothing is in flight
    print(net.stats, b.counters.snapshot())
"""

from __future__ import annotations

import asyncio
import logging
import math
import random
from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.bus import BusBase, Handler, Subscription
from kimera_multi_py.comms.deliveries import Deliveries
from kimera_multi_py.comms.faults import Faults, FaultStats, Partition
from kimera_multi_py.comms.link_budget import CONTROL, LinkBudget, LinkQueue, priority_of
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.stream import DEFAULT_QUEUE_SIZE, Stream
from kimera_multi_py.core.errors import ConfigError, MessageError

log = logging.getLogger(__name__)


@dataclass
class _Served:
    bus: LoopbackBus
    key_expr: str
    handler: Handler
    closed: bool = False

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.bus.network._served.remove(self)


class LoopbackNetwork:
    """The shared medium of the in-process buses. Create buses with :meth:`bus`."""

    def __init__(
        self,
        team: str = "t0",
        seed: int = 0,
        faults: Faults | None = None,
        robots: Collection[int] | None = None,
        clock: Callable[[], float] | None = None,
        queue_size: int = DEFAULT_QUEUE_SIZE,
        budget: LinkBudget | None = None,
    ) -> None:
        self.team = keys.check_team(team)
        self.faults = faults or Faults()
        if budget is not None and (self.faults.delay or self.faults.jitter or self.faults.reorder):
            raise ConfigError("link_budget", "a link budget sets the links' delays: delay, jitter and reorder "
                                             "must be 0")
        self.budget = budget
        self._links: dict[tuple[int, int], LinkQueue] = {}
        self.robots = frozenset(robots) if robots is not None else None
        self.queue_size = queue_size
        self.stats = FaultStats()
        self._rng = random.Random(seed)
        self._clock = clock
        self._t0: float | None = None
        self._buses: dict[tuple[str, int], LoopbackBus] = {}
        self._served: list[_Served] = []
        self._alive: set[tuple[str, int]] = set()
        self._partitions: list[Partition] = list(self.faults.partitions)
        self.deliveries = Deliveries(clock)  # what fault delays postponed
        self._subs_changed = asyncio.Event()
        self._pump_due: float | None = None  # the pending pump timer's time (the loop's clock, a budget)

    # setup ----------------------------------------------------------------------------
    def bus(self, robot: int, team: str | None = None) -> LoopbackBus:
        """A new bus for ``robot`` (of ``team``, default the network's) on this network."""
        team = self.team if team is None else team
        if (team, robot) in self._buses:
            raise ConfigError("robot", f"robot {robot} of team {team} already has a bus")
        bus = LoopbackBus(self, team, robot)
        self._buses[(team, robot)] = bus
        return bus

    @property
    def simulated(self) -> bool:
        """On a custom clock: delays wait for the owner, and no wait costs wall time (module doc)."""
        return self.deliveries.simulated

    def now(self) -> float:
        """Network time in seconds: the custom clock, or loop time since first use."""
        if self._clock is not None:
            return self._clock()
        t = asyncio.get_running_loop().time()
        if self._t0 is None:
            self._t0 = t
        return t - self._t0

    def partition(self, groups: Iterable[Iterable[int]], duration: float = math.inf) -> Partition:
        """Cut the links between ``groups`` from now for ``duration`` seconds."""
        start = self.now()
        p = Partition(tuple(frozenset(g) for g in groups), start, start + duration)
        self._partitions.append(p)
        return p

    def heal(self) -> None:
        """Remove every partition, configured or manual."""
        self._partitions.clear()

    def reachable(self, a: int, b: int) -> bool:
        """True when no partition currently separates robots ``a`` and ``b``."""
        if a == b:
            return True
        now = self.now()
        return not any(p.cuts(a, b, now) for p in self._partitions)

    @property
    def in_flight(self) -> int:
        """Deliveries scheduled and not yet done."""
        return self.deliveries.count

    async def settle(self, timeout: float = 10.0) -> None:
        """Wait until no delayed delivery or query is in flight (and, on the loop's clock, every
        budgeted link is idle; on a custom clock budgeted links wait for :meth:`pump`). On a custom
        clock the delayed deliveries are made at once, in order of due time (``timeout``: wall s,
        against a bug)."""

        async def quiet() -> None:
            while True:
                await self.deliveries.idle.wait()
                nxt = self.next_delivery()
                if nxt is None:
                    return
                await asyncio.sleep(max(0.0, nxt - self.now()))
                self.pump()

        try:
            await asyncio.wait_for(self.deliveries.drain() if self.simulated else quiet(), timeout)
        except TimeoutError:
            raise TimeoutError(f"{self.in_flight} deliveries still in flight") from None

    def step(self) -> int:
        """On a custom clock: make the delayed deliveries due first and return how many (0: none
        waits; on the loop's clock they are timed)."""
        return self.deliveries.step()

    # links ----------------------------------------------------------------------------
    def _link_delays(self, src: int, dst: int) -> list[float]:
        """Delays of the copies that cross link src->dst (empty: lost). Draws in fixed order."""
        self.stats.attempted += 1
        if src == dst:
            self.stats.delivered += 1
            return [0.0]
        if not self.reachable(src, dst):
            self.stats.partitioned += 1
            return []
        f, rng = self.faults, self._rng
        if f.drop and rng.random() < f.drop:
            self.stats.dropped += 1
            return []
        copies = 2 if f.duplicate and rng.random() < f.duplicate else 1
        if copies == 2:
            self.stats.duplicated += 1
        delays = []
        for _ in range(copies):
            d = f.delay + (rng.uniform(-f.jitter, f.jitter) if f.jitter else 0.0)
            if f.reorder and rng.random() < f.reorder:
                d += f.reorder_delay
                self.stats.reordered += 1
            d = max(0.0, d)
            if d > 0:
                self.stats.delayed += 1
            delays.append(d)
        self.stats.delivered += 1
        return delays

    # link budget ----------------------------------------------------------------------
    def _link(self, src: int, dst: int) -> LinkQueue:
        q = self._links.get((src, dst))
        if q is None:
            assert self.budget is not None
            q = self._links[(src, dst)] = LinkQueue(self.budget, self.now())
        return q

    def _enqueue(self, src: int, dst: int, key: str, item: object, nbytes: int, priority: int) -> None:
        """Put a message (or, ``item`` None, a query's bytes) on the budgeted link src->dst."""
        now = self.now()
        self._link(src, dst).push(item, nbytes, priority, now)
        self._schedule_pump()

    def _schedule_pump(self) -> None:
        """On the loop's clock: a timer for the next transfer's end (one pending at a time)."""
        if self._clock is not None or (nxt := self.next_delivery()) is None:
            return
        if self._pump_due is not None and self._pump_due <= nxt:
            return
        self._pump_due = nxt
        asyncio.get_running_loop().call_later(max(1e-4, nxt - self.now()), self._timed_pump, nxt)

    def _timed_pump(self, due: float) -> None:
        if self._pump_due == due:
            self._pump_due = None
        self.pump()

    def pump(self) -> int:
        """Deliver every budgeted message whose transfer ended by now, in the order they ended
        (ties: by link); return how many."""
        if not self._links:
            return 0
        now = self.now()
        done = [(end, link, i, item) for link, q in sorted(self._links.items())
                for i, (item, end) in enumerate(q.advance(now))]
        done.sort(key=lambda d: d[:3])
        for *_, item in done:
            if item is not None:
                subs, key, data = item  # type: ignore[misc]
                for s in subs:
                    s.push((key, data))
        self._schedule_pump()
        return len(done)

    def next_delivery(self) -> float | None:
        """When the next budgeted transfer ends (None: every link is idle)."""
        ends = [e for q in self._links.values() if (e := q.next_done()) is not None]
        return min(ends) if ends else None

    def link_report(self) -> dict[str, dict[str, object]]:
        """Per link ``"src->dst"``: messages and bytes sent, queue delay (mean, max), and what
        was dropped or is still queued (docs/deployment.md, "Link budget")."""
        return {f"{a}->{b}": q.report() for (a, b), q in sorted(self._links.items())}

    def _route(self, sender: LoopbackBus, key: str, data: bytes) -> None:
        budget = self.budget is not None
        for (_, robot), bus in sorted(self._buses.items(), key=lambda kv: (kv[0][1], kv[0][0])):
            subs = [s for s in bus._subs if keys.intersects(s.key_expr, key)]
            if not subs:
                continue
            for d in self._link_delays(sender.robot, robot):
                if budget and robot != sender.robot:
                    self._enqueue(sender.robot, robot, key, (subs, key, data), len(data), priority_of(key))
                    continue
                # (mypy cannot infer lambdas whose parameters bind defaults)
                self.deliveries.after(d, lambda subs=subs: [s.push((key, data)) for s in subs])  # type: ignore[misc]

    def _set_alive(self, bus: LoopbackBus, alive: bool) -> None:
        ident = (bus.team, bus.robot)
        if alive:
            self._alive.add(ident)
        else:
            self._alive.discard(ident)
        for other in self._buses.values():
            if other is not bus and other.team == bus.team:
                other._set_alive(bus.robot, alive)

    def _forget(self, bus: LoopbackBus) -> None:
        self._buses.pop((bus.team, bus.robot), None)
        self._served = [s for s in self._served if s.bus is not bus]


class LoopbackBus(BusBase):
    """One robot's bus on a :class:`LoopbackNetwork` (create it with ``network.bus(robot)``)."""

    def __init__(self, network: LoopbackNetwork, team: str, robot: int) -> None:
        super().__init__(team, robot, network.robots, network.queue_size)
        self.network = network
        if network._clock is not None:  # stamps on the simulated clock: the same bytes every run
            self.codec.clock = network._clock
        self._subs: list[Subscription] = []
        self._announced = False
        # presence already announced by others
        for team_, other in network._alive:
            if team_ == team:
                self._set_alive(other, True)

    async def publish(self, key: str, msg: Message) -> None:
        data = self.encode_for(key, msg)
        self.counters.count_sent(key, len(data))
        self.network._route(self, key, data)

    def subscribe(self, key_expr: str) -> Subscription:
        self._check_open()
        # the stream passes itself to on_close, and it is this Subscription
        sub = Subscription(self, key_expr, self.queue_size, on_close=self._subs.remove)  # type: ignore[arg-type]
        self._subs.append(sub)
        self.network._subs_changed.set()
        self.network._subs_changed = asyncio.Event()
        return sub

    async def wait_for_subscribers(self, key: str, timeout: float) -> None:
        """Wait until some bus on the network subscribes to ``key``; else ``TimeoutError``."""
        self._check_open()
        net = self.network

        def matched() -> bool:
            return any(
                keys.intersects(s.key_expr, key) for b in net._buses.values() for s in b._subs
            )

        async def wait() -> None:
            while not matched():
                await net._subs_changed.wait()

        try:
            await asyncio.wait_for(wait(), timeout)
        except TimeoutError:
            raise TimeoutError(f"no subscriber matched {key!r} within {timeout} s") from None

    async def serve(self, key_expr: str, handler: Handler) -> _Served:
        self._check_open()
        served = _Served(self, key_expr, handler)
        self.network._served.append(served)
        return served

    async def query(
        self, selector: str, msg: Message | None = None, timeout: float = 1.0
    ) -> list[Message]:
        self._check_open()
        request = None
        if msg is not None:
            request = self.codec.encode(msg)
        net = self.network
        targets = [
            s for s in net._served
            if s.bus.team == self.team and keys.intersects(s.key_expr, selector)
        ]
        loop = asyncio.get_running_loop()
        futures: list[asyncio.Future[list[Message] | None]] = []
        for served in targets:
            if request is not None:
                self.counters.count_sent(selector, len(request))
            fut: asyncio.Future[list[Message] | None] = loop.create_future()
            futures.append(fut)
            delays = net._link_delays(self.robot, served.bus.robot)[:1]
            if delays and net.budget is not None and served.bus.robot != self.robot:
                net._enqueue(self.robot, served.bus.robot, selector, None, len(request or b""), CONTROL)
            if not delays:
                self._lost(fut)
            for d in delays:
                net.deliveries.after(d, lambda s=served, f=fut: self._start_answer(s, selector, request, f))  # type: ignore[misc]
        if not futures:
            return []
        if net.simulated:
            await net.deliveries.until_done(futures)
            done = {f for f in futures if f.done()}
        else:
            done, _ = await asyncio.wait(futures, timeout=timeout)
        replies: list[Message] = []
        for fut in futures:
            if fut in done:
                replies.extend(fut.result() or [])
            else:
                fut.cancel()
        return replies

    def _lost(self, fut: asyncio.Future[list[Message] | None]) -> None:
        """A query's request or reply was lost: on a custom clock its wait ends now (None: no
        reply), on the loop's clock it ends at its timeout."""
        if self.network.simulated and not fut.done():
            fut.set_result(None)

    def _start_answer(self, served: _Served, selector: str, request: bytes | None,
                      fut: asyncio.Future[list[Message] | None]) -> None:
        self.network.deliveries.answering += 1
        asyncio.get_running_loop().create_task(self._answer(served, selector, request, fut))

    async def _answer(
        self, served: _Served, selector: str, request: bytes | None, fut: asyncio.Future[list[Message] | None]
    ) -> None:
        """Run ``served``'s handler for one query and route the replies back with link faults."""
        on_its_way = False
        try:
            on_its_way = await self._reply(served, selector, request, fut)
        finally:
            self.network.deliveries.answering -= 1
            if not on_its_way:
                self._lost(fut)

    async def _reply(
        self, served: _Served, selector: str, request: bytes | None, fut: asyncio.Future[list[Message] | None]
    ) -> bool:
        """Answer, and send the reply back over the link; whether a reply is on its way."""
        server, net = served.bus, self.network
        answered = await server.answer(served, selector, request)
        if answered is None:
            return False
        reply_key, replies = answered
        good: list[Message] = []
        nbytes = 0
        for reply in replies:
            try:
                data = server.encode_for(reply_key, reply)
            except MessageError as exc:
                log.warning("robot %d: cannot reply on %s: %s", server.robot, reply_key, exc)
                continue
            server.counters.count_sent(reply_key, len(data))
            nbytes += len(data)
            env = self.accept(reply_key, data)
            if env is not None:
                good.append(env.msg)
        delays = net._link_delays(server.robot, self.robot)[:1]
        if delays and net.budget is not None and server.robot != self.robot:
            net._enqueue(server.robot, self.robot, reply_key, None, nbytes, CONTROL)
        for d in delays:
            net.deliveries.after(d, lambda: fut.done() or fut.set_result(good))  # type: ignore[func-returns-value]
        return bool(delays)

    async def announce(self) -> None:
        self._check_open()
        if not self._announced:
            self._announced = True
            self.network._set_alive(self, True)

    def peers(self) -> frozenset[int]:
        return frozenset(p for p in self._peers if self.network.reachable(self.robot, p))

    async def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        if self._announced:
            self.network._set_alive(self, False)
        for sub in list(self._subs):
            sub.close()
        self._close_streams()
        self.network._forget(self)


__all__ = ["FaultStats", "Faults", "LoopbackBus", "LoopbackNetwork", "Partition", "Stream"]
