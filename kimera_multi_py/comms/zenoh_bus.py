"""The Bus over real eclipse-zenoh 1.x sessions (one session per bus).

Connection, as in zenoh-python's examples: peer mode with explicit ``listen``/``connect``
endpoints and multicast scouting off (the defaults here), client mode to a ``zenohd`` router
(``mode="client", connect=["tcp/host:7447"]``), or any Zenoh JSON5 config file
(``config_file=``, the ``--zenoh-config FILE`` of every process) — that is where TLS and
authentication go. Explicit arguments override the file.

Threading: Zenoh calls our callbacks on its own threads. They never block and never call
Zenoh: they hand the sample's payload (a ``ZBytes``, not yet copied) to the event loop with
``loop.call_soon_threadsafe(...)``. Samples are handed over in batches: a callback appends to
an inbox and schedules one drain unless one is already pending, so a burst costs one loop
wake-up instead of one per sample. Copying the payload out, decoding, validation, handlers and
replies run on the asyncio thread. Presence comes from liveliness tokens at
``kmp/{team}/alive/r{robot}``.

Sending: a message published alone goes out at once; a burst (publishes with no ``await`` that
yields in between) is coalesced into payloads of up to ``batch_bytes``, and each run of
same-type messages in it becomes one columnar batch envelope
(:mod:`~kimera_multi_py.comms.columnar`): one envelope and one column per field instead of one
envelope per message. Messages of 16 KiB or more always go alone, encoded with one copy of
their arrays (:mod:`~kimera_multi_py.comms.largemsg`).

Link budget: with a :class:`~kimera_multi_py.comms.link_budget.LinkBudget` every payload (a
put, a query's request, a reply) is paced by a :class:`~kimera_multi_py.comms.link_pacer.LinkPacer`.
A put reaches every peer at once, so the one queue is each peer link's:
:meth:`ZenohBus.link_report` gives its figures under ``"{robot}->*"``; what is still queued at
``close()`` is not sent.

Construct inside a running event loop and close it (or use ``async with``)::

    async with ZenohBus("t0", 1, connect=["tcp/127.0.0.1:7447"]) as bus:
        await bus.announce()
        ...

``close()`` undeclares every subscriber, queryable, publisher and token, then closes the session.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections import deque
from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.bus import BusBase, Handler, Subscription
from kimera_multi_py.comms.codec import MAX_BATCH, batch_header
from kimera_multi_py.comms.link_budget import LinkBudget
from kimera_multi_py.comms.link_pacer import LinkPacer
from kimera_multi_py.comms.messages import MESSAGE_TYPES
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.stream import DEFAULT_QUEUE_SIZE, Stream
from kimera_multi_py.core.errors import ConfigError, MessageError

log = logging.getLogger(__name__)

MODES = ("peer", "client", "router")
_TYPES = frozenset(MESSAGE_TYPES.values())
# Coalesced payloads of up to 250 kB: bigger batches amortise the per-put and per-batch costs
# (benchmarks/comms.py, 1 KB messages: 60 kB batches 0.40-0.53x raw throughput, 250 kB
# 0.66-0.71x; 500 kB and 1 MB were no better); Zenoh fragments them on the wire.
DEFAULT_BATCH_BYTES = 250_000
SOLO_BYTES = 16 * 1024  # messages this big are put on their own: coalescing would only copy them
BUDGET_BATCH_S = 0.1  # under a link budget a coalesced payload holds the link this long at most
INDIRECT_CALLBACKS = True  # run data callbacks on zenoh-python's callback thread


def tls_settings(ca: str | Path, cert: str | Path | None = None, key: str | Path | None = None,
                 mtls: bool = True) -> dict[str, Any]:
    """Zenoh's ``transport/link/tls`` block: trust ``ca``; present ``cert`` + ``key`` both when
    listening and when connecting; with ``mtls`` (zenoh's ``enable_mtls``) require the other
    end's certificate, signed by ``ca``, on every link, so a process without one cannot join."""
    if (cert is None) != (key is None):
        raise ConfigError("tls", "give both a certificate and its key, or neither")
    tls: dict[str, Any] = {"root_ca_certificate": str(ca)}
    if cert is not None and key is not None:
        tls.update({"listen_certificate": str(cert), "listen_private_key": str(key),
                    "connect_certificate": str(cert), "connect_private_key": str(key)})
    if mtls:
        if cert is None:
            raise ConfigError("tls", "mutual TLS needs this process's certificate and key")
        tls["enable_mtls"] = True
    return tls


@dataclass(frozen=True)
class Tls:
    """The TLS files of one process (PEM): the team CA, and its own certificate and key."""

    ca: str | Path
    cert: str | Path | None = None
    key: str | Path | None = None
    mtls: bool = True

    def settings(self) -> dict[str, Any]:
        for p in (self.ca, self.cert, self.key):
            if p is not None and not Path(p).is_file():
                raise ConfigError("tls", f"{p} is not a file")
        return tls_settings(self.ca, self.cert, self.key, self.mtls)


def zenoh_config(
    mode: str | None = None,
    listen: Iterable[str] = (),
    connect: Iterable[str] = (),
    config_file: str | Path | None = None,
    multicast_scouting: bool | None = None,
    extra: Mapping[str, Any] | None = None,
    tls: Tls | None = None,
) -> zenoh.Config:
    """Build a Zenoh config: the file (if any), then our defaults, then explicit arguments.

    Without a file the defaults are peer mode and multicast scouting off. ``extra`` maps config
    paths to JSON values, e.g. ``{"transport/link/tls": {"root_ca_certificate": "ca.pem"}}``;
    ``tls`` sets that block from a process's files (mutual TLS by default, see :class:`Tls`).
    """
    try:
        conf = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()
    except zenoh.ZError as exc:
        raise ConfigError("zenoh-config", f"cannot load {config_file}: {exc}") from exc
    if config_file is None:
        mode = mode or "peer"
        multicast_scouting = bool(multicast_scouting)
    if mode is not None and mode not in MODES:
        raise ConfigError("mode", f"{mode!r} is not one of {MODES}")
    entries: dict[str, Any] = {}
    if mode is not None:
        entries["mode"] = mode
    if multicast_scouting is not None:
        entries["scouting/multicast/enabled"] = multicast_scouting
    if listen := list(listen):
        entries["listen/endpoints"] = listen
    if connect := list(connect):
        entries["connect/endpoints"] = connect
    if tls is not None:
        entries["transport/link/tls"] = tls.settings()
    entries.update(extra or {})
    for path, value in entries.items():
        try:
            conf.insert_json5(path, json.dumps(value))
        except zenoh.ZError as exc:
            raise ConfigError(path, f"rejected by zenoh: {exc}") from exc
    return conf


@dataclass
class _Served:
    """A declared queryable; ``close()`` undeclares it."""

    bus: ZenohBus
    key_expr: str
    handler: Handler
    queryable: Any = None
    closed: bool = False

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.bus._undeclare(self.queryable)
        if self in self.bus._served:
            self.bus._served.remove(self)


@dataclass
class _PendingQuery:
    replies: list[tuple[str, bytes]] = field(default_factory=list)
    errors: int = 0
    done: asyncio.Event = field(default_factory=asyncio.Event)


class ZenohBus(BusBase):
    """One robot's bus on its own Zenoh session. See the module docstring."""

    def __init__(
        self,
        team: str,
        robot: int,
        *,
        robots: Collection[int] | None = None,
        mode: str | None = None,
        listen: Iterable[str] = (),
        connect: Iterable[str] = (),
        config_file: str | Path | None = None,
        multicast_scouting: bool | None = None,
        extra_config: Mapping[str, Any] | None = None,
        tls: Tls | None = None,
        block_on_congestion: bool = False,
        queue_size: int = DEFAULT_QUEUE_SIZE,
        batch_bytes: int = DEFAULT_BATCH_BYTES,
        budget: LinkBudget | None = None,
    ) -> None:
        super().__init__(team, robot, robots, queue_size)
        try:
            self._loop = asyncio.get_running_loop()
        except RuntimeError as exc:
            raise ConfigError("loop", "ZenohBus must be created inside a running event loop") \
                from exc
        conf = zenoh_config(mode, listen, connect, config_file, multicast_scouting, extra_config, tls)
        try:
            self.session = zenoh.open(conf)
        except zenoh.ZError as exc:
            raise ConfigError("zenoh", f"cannot open a session: {exc}") from exc
        self._congestion = (
            zenoh.CongestionControl.BLOCK if block_on_congestion else zenoh.CongestionControl.DROP
        )
        self._inbox: deque[tuple[Subscription, str, zenoh.ZBytes]] = deque()
        self._drain_scheduled = False
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._batch_bytes = batch_bytes
        self._burst = False  # a message went out in this loop iteration: coalesce the next ones
        self._runs: list[tuple[str, list[Message]]] = []  # pending runs, in publication order
        self._pending_bytes = 0
        self._pending_msgs = 0
        self._subs: dict[Subscription, Any] = {}
        self._served: list[_Served] = []
        self._tasks: set[asyncio.Task[None]] = set()
        self._token: zenoh.LivelinessToken | None = None
        self.budget = budget
        self._link = LinkPacer(budget, self._loop, self._put_now, self.counters, robot) if budget is not None else None
        if budget is not None:  # small batches: a message of a higher class waits for one at most
            self._batch_bytes = min(self._batch_bytes, max(1024, int(budget.rate * BUDGET_BATCH_S)))
        self._presence_sub = self.session.liveliness().declare_subscriber(
            keys.alive_all(self.team),
            zenoh.handlers.Callback(self._on_presence),
            history=True,
        )
        log.info("robot %d opened a zenoh session %s", robot, self.session.zid())

    # zenoh threads -> event loop ---------------------------------------------------------
    def _hand_over(self, fn: Callable[..., None], *args: Any) -> None:
        """Schedule ``fn(*args)`` on the event loop from a Zenoh thread; never blocks or raises."""
        try:
            self._loop.call_soon_threadsafe(fn, *args)
        except RuntimeError:  # the loop is closed: we are shutting down
            pass

    def _on_presence(self, sample: zenoh.Sample) -> None:
        alive = sample.kind == zenoh.SampleKind.PUT
        self._hand_over(self._presence_changed, str(sample.key_expr), alive)

    def _presence_changed(self, key: str, alive: bool) -> None:
        try:
            parsed = keys.parse_key(key)
        except MessageError:
            self.counters.count_dropped("presence")
            return
        if parsed.alive and parsed.team == self.team and parsed.robot is not None:
            self._set_alive(parsed.robot, alive)

    # publish / subscribe -----------------------------------------------------------------
    async def publish(self, key: str, msg: Message) -> None:
        """Send ``msg`` now or, within a burst, in a batch put before the loop idles.

        The first message of an event-loop iteration is encoded and put at once, so a lone
        message waits for nothing. Messages published after it in the same iteration (a burst:
        no ``await`` yielded to the loop in between) are coalesced, in publication order, into
        payloads of at most ``batch_bytes`` per key, one Zenoh put each; a run of same-type
        messages becomes one columnar batch envelope (:mod:`~kimera_multi_py.comms.columnar`).
        Whatever is pending is put when the loop next runs its callbacks, i.e. as soon as the
        publishing task yields. Order across keys is kept: pending payloads are put in the order
        their messages were published. Messages of :data:`SOLO_BYTES` or more are never coalesced.
        The key and the sender are checked here (raising ``MessageError``); an encoding failure
        of a deferred batch is logged and counted (``dropped["publish_error"]``).
        """
        if not self._burst:  # first in this loop iteration: send now
            data = self.encode_for(key, msg)
            self._burst = True
            self._loop.call_soon(self._end_burst)
            self._put(key, data, 1)
            return
        if self.closed or key not in self._own_keys or msg.__class__ not in _TYPES \
                or msg.robot != self.robot:  # the common case is checked inline
            self.check_sender(key, msg)
        size = msg.size_hint()
        if size >= SOLO_BYTES or size >= self._batch_bytes:  # large, or coalescing off
            data = self.codec.encode(msg)
            self._flush()  # keep publication order
            self._put(key, data, 1)
            return
        if self._pending_bytes + size > self._batch_bytes or self._pending_msgs >= MAX_BATCH:
            self._flush()
        runs = self._runs
        if runs and runs[-1][0] == key:
            runs[-1][1].append(msg)
        else:
            runs.append((key, [msg]))
        self._pending_bytes += size
        self._pending_msgs += 1

    def _end_burst(self) -> None:
        self._burst = False
        self._flush()

    def _flush(self) -> None:
        """Encode and put every pending run, in publication order (errors logged and counted)."""
        runs = self._runs
        if not runs:
            return
        self._runs = []
        self._pending_bytes = self._pending_msgs = 0
        for key, msgs in runs:
            try:
                parts = self._encode_run(msgs)
                data = parts[0] if len(parts) == 1 else batch_header(len(parts)) + b"".join(parts)
                self._put(key, data, len(msgs))
            except MessageError as exc:
                self.counters.count_dropped("publish_error")
                log.warning("robot %d: %s", self.robot, exc)

    def _encode_run(self, msgs: list[Message]) -> list[bytes]:
        """Envelopes for a run of messages on one key: columnar batches for same-type stretches."""
        codec = self.codec
        parts: list[bytes] = []
        i, n = 0, len(msgs)
        while i < n:
            cls = msgs[i].__class__
            j = i + 1
            while j < n and msgs[j].__class__ is cls:
                j += 1
            data = codec.encode_many(msgs[i:j]) if j - i > 1 else None
            if data is None:
                parts.extend(codec.encode(m) for m in msgs[i:j])
            else:
                parts.append(data)
            i = j
        return parts

    def _put(self, key: str, data: bytes, messages: int) -> None:
        """One Zenoh put of a payload carrying ``messages`` messages (under a budget: queued)."""
        if self._link is not None:
            self._check_open()
            self._link.put(key, data, messages)
            return
        self._put_now(key, data, messages)

    def _put_now(self, key: str, data: bytes, messages: int) -> None:
        try:
            self._publisher(key).put(data)
        except zenoh.ZError as exc:
            raise MessageError(f"key: zenoh refused to publish on {key!r}: {exc}") from exc
        self.counters.count_sent(key, len(data), messages)

    async def _wait_link(self, nbytes: int) -> bool:
        """Under a budget: wait until ``nbytes`` (a query or reply) have crossed the link; False
        if the link dropped them. Without a budget: at once."""
        return True if self._link is None else await self._link.wait(nbytes) and not self.closed

    def link_report(self) -> dict[str, dict[str, object]]:
        """Under a budget: the figures of this robot's peer links, which every put crosses alike
        (bytes, queue delay mean/max, dropped, still queued); empty without a budget."""
        return {f"{self.robot}->*": self._link.queue.report()} if self._link is not None else {}

    def _publisher(self, key: str) -> zenoh.Publisher:
        pub = self._publishers.get(key)
        if pub is None:
            pub = self.session.declare_publisher(key, congestion_control=self._congestion)
            self._publishers[key] = pub
        return pub

    def subscribe(self, key_expr: str) -> Subscription:
        self._check_open()
        sub = Subscription(self, key_expr, self.queue_size, on_close=self._unsubscribe)

        inbox = self._inbox

        def on_sample(sample: zenoh.Sample) -> None:
            inbox.append((sub, str(sample.key_expr), sample.payload))  # copied out in _drain
            if not self._drain_scheduled:
                self._drain_scheduled = True
                self._hand_over(self._drain)

        self._subs[sub] = self.session.declare_subscriber(
            key_expr, zenoh.handlers.Callback(on_sample, indirect=INDIRECT_CALLBACKS)
        )
        return sub

    def _drain(self) -> None:
        """On the loop: move every sample handed over so far into its subscription.

        The payload bytes are copied out of Zenoh here, on the loop thread that also frees them
        (a buffer malloc'ed on the callback thread and freed on the loop thread bounces between
        glibc arenas: see :func:`runtime.tune_allocator`).
        """
        self._drain_scheduled = False
        inbox = self._inbox
        while inbox:
            sub, key, payload = inbox.popleft()
            sub.push((key, payload.to_bytes()))

    def _unsubscribe(self, sub: Stream[Message]) -> None:
        self._undeclare(self._subs.pop(sub, None))  # type: ignore[call-overload]

    async def wait_for_subscribers(self, key: str, timeout: float) -> None:
        """Wait until some subscriber (remote or local) matches ``key``; else ``TimeoutError``."""
        self._check_open()
        pub = self._publisher(key)
        matched = asyncio.Event()

        def on_status(status: zenoh.MatchingStatus) -> None:
            if status.matching:
                self._hand_over(matched.set)

        listener = pub.declare_matching_listener(zenoh.handlers.Callback(on_status))
        try:
            if not pub.matching_status:
                await asyncio.wait_for(matched.wait(), timeout)
        except TimeoutError:
            raise TimeoutError(f"no subscriber matched {key!r} within {timeout} s") from None
        finally:
            self._undeclare(listener)

    # queries -----------------------------------------------------------------------------
    async def serve(self, key_expr: str, handler: Handler) -> _Served:
        self._check_open()
        served = _Served(self, key_expr, handler)

        def on_query(query: zenoh.Query) -> None:
            payload = query.payload
            data = payload.to_bytes() if payload is not None else None
            self._hand_over(self._start_answer, served, query, data)

        served.queryable = self.session.declare_queryable(
            key_expr, zenoh.handlers.Callback(on_query)
        )
        self._served.append(served)
        return served

    def _start_answer(self, served: _Served, query: zenoh.Query, data: bytes | None) -> None:
        task = self._loop.create_task(self._answer(served, query, data))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _answer(self, served: _Served, query: zenoh.Query, data: bytes | None) -> None:
        try:
            answered = await self.answer(served, str(query.key_expr), data)
            if answered is None:
                return
            reply_key, replies = answered
            for reply in replies:
                try:
                    out = self.encode_for(reply_key, reply)
                    if not await self._wait_link(len(out)):
                        continue
                    query.reply(reply_key, out)
                except (MessageError, zenoh.ZError) as exc:
                    log.warning("robot %d: cannot reply on %s: %s", self.robot, reply_key, exc)
                    continue
                self.counters.count_sent(reply_key, len(out))
        finally:
            try:
                query.drop()
            except zenoh.ZError as exc:
                log.debug("query already finalised: %s", exc)

    async def query(
        self, selector: str, msg: Message | None = None, timeout: float = 1.0
    ) -> list[Message]:
        self._check_open()
        payload = self.codec.encode(msg) if msg is not None else None
        if payload is not None and not await self._wait_link(len(payload)):
            return []
        pending = _PendingQuery()

        def on_reply(reply: zenoh.Reply) -> None:
            ok = reply.ok
            if ok is None:
                self._hand_over(self._query_error, pending)
            else:
                self._hand_over(pending.replies.append, (str(ok.key_expr), ok.payload.to_bytes()))

        def on_done() -> None:
            self._hand_over(pending.done.set)

        self.session.get(
            selector,
            zenoh.handlers.Callback(on_reply, on_done),
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            payload=payload,
            timeout=timeout,
        )
        if payload is not None:
            self.counters.count_sent(selector, len(payload))
        try:
            # zenoh finishes the query by its own timeout; the margin covers the hand-over
            await asyncio.wait_for(pending.done.wait(), timeout + 1.0)
        except TimeoutError:
            log.warning("robot %d: query %s did not finish", self.robot, selector)
        out = []
        for key, data in pending.replies:
            env = self.accept(key, data)
            if env is not None:
                out.append(env.msg)
        return out

    def _query_error(self, pending: _PendingQuery) -> None:
        pending.errors += 1
        self.counters.count_dropped("reply_error")

    # presence ----------------------------------------------------------------------------
    async def announce(self) -> None:
        self._check_open()
        if self._token is None:
            self._token = self.session.liveliness().declare_token(
                keys.alive_key(self.team, self.robot)
            )

    # shutdown ----------------------------------------------------------------------------
    @staticmethod
    def _undeclare(entity: Any) -> None:
        if entity is None:
            return
        try:
            entity.undeclare()
        except zenoh.ZError as exc:
            log.debug("undeclare failed: %s", exc)

    async def close(self) -> None:
        if self.closed:
            return
        self._flush()  # what was published before close() still goes out (unless a budget holds it)
        if self._link is not None:
            self._link.close()
        self.closed = True
        for sub in list(self._subs):
            sub.close()
        for served in list(self._served):
            served.close()
        for task in list(self._tasks):
            task.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        for pub in self._publishers.values():
            self._undeclare(pub)
        self._publishers.clear()
        self._undeclare(self._token)
        self._token = None
        self._undeclare(self._presence_sub)
        self._close_streams()
        self._peers.clear()
        self.session.close()
        log.info("robot %d closed its zenoh session", self.robot)
