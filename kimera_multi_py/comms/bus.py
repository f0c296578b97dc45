"""The async Bus Protocol, and the bookkeeping both implementations share (:class:`BusBase`).

A bus belongs to one robot of one team. It publishes and receives typed messages
(:mod:`kimera_multi_py.comms.messages`) on key expressions (:mod:`kimera_multi_py.comms.keys`),
serves and sends queries for large data, holds a presence token and tracks peers, and counts
bytes and messages per topic (:mod:`.counters`); what it receives arrives on streams
(:mod:`.stream`). :class:`~kimera_multi_py.comms.loopback.LoopbackBus` and
:class:`~kimera_multi_py.comms.zenoh_bus.ZenohBus` implement it.

Received bytes are decoded and validated on the asyncio thread (:meth:`BusBase.accept`):
messages of another team, from an unknown robot, whose key names another robot than the
envelope's sender, or that fail validation are dropped, logged at debug level and counted in
``counters.dropped`` by reason (``team``, ``src``, ``key``, ``invalid``, ``queue_full``).
"""

from __future__ import annotations

import asyncio
import inspect
import logging
from collections.abc import Awaitable, Callable, Collection, Iterable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.codec import Codec, CodecError, Envelope, Group
from kimera_multi_py.comms.counters import TrafficCounters, share_range
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.stream import DEFAULT_QUEUE_SIZE, BusClosedError, Stream
from kimera_multi_py.core.errors import MessageError

log = logging.getLogger(__name__)

Reply = Message | Iterable[Message] | None
Handler = Callable[[str, Message | None], Awaitable[Reply] | Reply]
"""A queryable handler: ``(key, request or None) -> reply message(s) or None``; sync or async."""


class Subscription(Stream[Message]):
    """Messages arriving on ``key_expr``, decoded and validated on arrival by the owning bus."""

    def __init__(
        self,
        bus: BusBase,
        key_expr: str,
        maxsize: int = DEFAULT_QUEUE_SIZE,
        on_close: Callable[[Stream[Message]], None] | None = None,
    ) -> None:
        super().__init__(maxsize, on_close, lambda: bus.counters.count_dropped("queue_full"))
        self.key_expr = key_expr
        self._bus = bus

    def push(self, item: Any) -> None:
        """Decode ``(key, payload bytes)`` now (so counters reflect arrivals) and queue it.

        The payload holds one message or a batch of them (:func:`codec.decode_batch`).
        """
        if self.closed:
            return
        key, data = item
        self.push_messages(self._bus.accept_batch(key, data))

    def push_messages(self, msgs: list[Message]) -> None:
        """Queue messages already accepted by the bus (on the event-loop thread)."""
        if self.closed or not msgs:
            return
        room = self._maxsize - len(self._items)
        if room < len(msgs):
            for _ in range(len(msgs) - max(room, 0)):
                if self._on_overflow is not None:
                    self._on_overflow()
            msgs = msgs[:max(room, 0)]
        self._items.extend(msgs)
        for _ in range(min(len(msgs), len(self._waiters))):
            self._wake()


@dataclass(frozen=True)
class PresenceEvent:
    """Robot ``robot`` appeared (``alive``) or disappeared."""

    robot: int
    alive: bool


class Closeable(Protocol):
    def close(self) -> None: ...


# ---------------------------------------------------------------------------- protocol
@runtime_checkable
class Bus(Protocol):
    """What the runtime needs from a transport. All methods run on the asyncio thread."""

    team: str
    robot: int
    counters: TrafficCounters

    def key(self, topic: str, robot: int | None = None) -> str:
        """The concrete key of ``topic`` for ``robot`` (default: this bus's robot)."""
        ...

    async def publish(self, key: str, msg: Message) -> None:
        """Encode and send ``msg`` on the concrete ``key``."""
        ...

    def subscribe(self, key_expr: str) -> Subscription:
        """Start receiving on ``key_expr`` now; iterate the result for decoded messages."""
        ...

    async def wait_for_subscribers(self, key: str, timeout: float) -> None:
        """Wait until a subscriber matches ``key`` (so a publication is not lost)."""
        ...

    async def serve(self, key_expr: str, handler: Handler) -> Closeable:
        """Answer queries on ``key_expr`` with ``handler`` until the handle is closed."""
        ...

    async def query(
        self, selector: str, msg: Message | None = None, timeout: float = 1.0
    ) -> list[Message]:
        """Send a query (optionally carrying ``msg``) and collect valid replies until done."""
        ...

    async def announce(self) -> None:
        """Hold this robot's presence token until close."""
        ...

    def peers(self) -> frozenset[int]:
        """Robots of the team currently present (excluding this one)."""
        ...

    def presence(self) -> Stream[PresenceEvent]:
        """Presence events, starting with one ``alive`` event per current peer."""
        ...

    async def wait_for_peers(self, robots: Collection[int], timeout: float) -> frozenset[int]:
        """Wait until all ``robots`` are present; raise ``TimeoutError`` otherwise."""
        ...

    async def close(self) -> None:
        """Withdraw presence, stop every stream and release the transport. Idempotent."""
        ...


# ---------------------------------------------------------------------------- shared base
class BusBase:
    """Bookkeeping shared by the implementations: codec, counters, streams and peers."""

    def __init__(
        self,
        team: str,
        robot: int,
        robots: Collection[int] | None = None,
        queue_size: int = DEFAULT_QUEUE_SIZE,
    ) -> None:
        self.team = keys.check_team(team)
        self.robot = robot
        keys.robot_chunk(robot)
        self.robots = frozenset(robots) if robots is not None else None
        if self.robots is not None and robot not in self.robots:
            raise MessageError(f"robot: {robot} is not one of the team's robots")
        self.codec = Codec(team, robot, self.robots)
        self.counters = TrafficCounters()
        self.queue_size = queue_size
        self.closed = False
        self._own_keys: set[str] = set()
        self._key_verdicts: dict[str, tuple[CodecError | None, int | MessageError]] = {}
        self._peers: set[int] = set()
        self._presence_streams: list[Stream[PresenceEvent]] = []
        self._peers_changed = asyncio.Event()

    def key(self, topic: str, robot: int | None = None) -> str:
        return keys.topic_key(self.team, self.robot if robot is None else robot, topic)

    def _check_open(self) -> None:
        if self.closed:
            raise BusClosedError(f"bus of robot {self.robot} is closed")

    # decoding --------------------------------------------------------------------------
    def accept(self, key: str, data: bytes, from_owner: bool = True) -> Envelope | None:
        """Decode and validate bytes received on ``key``; count and return None if rejected.

        ``from_owner``: the sender must be the robot named in ``key`` (true for publications
        and replies, false for query requests, which name the server's key).
        """
        try:
            env = self.codec.decode(data)
        except MessageError as exc:
            self._reject(key, exc)
            return None
        team_error, owner = self._key_verdict(key)
        error = team_error or (self._owner_error(key, owner, env.src) if from_owner else None)
        if error is not None:
            self._reject(key, error)
            return None
        self.counters.count_received(key, len(data))
        return env

    def accept_batch(self, key: str, data: bytes, from_owner: bool = True) -> list[Message]:
        """:meth:`accept` for a payload holding one message or a batch (same checks per message).

        Returns the accepted messages in order. Each envelope of a batch is validated, counted
        and dropped on its own, exactly as if it had come alone (a columnar batch envelope is
        accepted or dropped as a whole); a message's share of the payload bytes is what the
        counters attribute to it.
        """
        try:
            items = self.codec.decode_groups(data)
        except MessageError as exc:  # the batch as a whole is malformed
            self._reject(key, exc)
            return []
        team_error, owner = self._key_verdict(key)
        if len(items) == 1:  # one envelope (the common case): the same checks, straight
            item = items[0]
            if item.__class__ is Envelope and team_error is None \
                    and (owner == item.src or not from_owner):  # type: ignore[union-attr]
                self.counters.count_received(key, len(data))
                return [item.msg]  # type: ignore[union-attr]
        out: list[Message] = []
        n = 0  # messages in the payload (a dropped columnar batch counts as one)
        accepted: list[tuple[int, int]] = []  # (first index, count) of accepted messages
        for item in items:
            if item.__class__ is Group:
                msgs = item.msgs  # type: ignore[union-attr]
            elif item.__class__ is Envelope:
                msgs = [item.msg]  # type: ignore[union-attr]
            else:
                self._reject(key, item)  # type: ignore[arg-type]
                n += 1
                continue
            if team_error is not None:
                self._reject(key, team_error)
            elif from_owner and owner != item.src:  # type: ignore[union-attr]
                self._reject(key, self._owner_error(key, owner, item.src))  # type: ignore[arg-type, union-attr]
            else:
                out.extend(msgs)
                accepted.append((n, len(msgs)))
            n += len(msgs)
        if out:
            size = len(data)
            self.counters.count_received(
                key, sum(share_range(size, n, i, k) for i, k in accepted), len(out))
        return out

    def _key_verdict(self, key: str) -> tuple[CodecError | None, int | MessageError]:
        """(error if ``key`` is not of this team, owner robot or parse error); cached per key."""
        verdict = self._key_verdicts.get(key)
        if verdict is None:
            chunks = key.split("/")
            team_error = None
            if len(chunks) < 3 or chunks[0] != keys.ROOT or chunks[1] != self.team:
                team_error = CodecError("team", f"key {key!r} is not of team {self.team!r}")
            owner: int | MessageError
            try:
                owner = keys.parse_key(key).robot  # type: ignore[assignment]
            except MessageError as exc:
                owner = exc
            verdict = (team_error, owner)
            if len(self._key_verdicts) < 10_000:
                self._key_verdicts[key] = verdict
        return verdict

    @staticmethod
    def _owner_error(key: str, owner: int | MessageError, src: int) -> MessageError | None:
        """Why a message from ``src`` may not arrive on ``key`` (owned by ``owner``), if not."""
        if owner == src:
            return None
        if isinstance(owner, MessageError):
            return owner
        return CodecError("key", f"key {key!r} does not belong to sender {src}")

    def _reject(self, key: str, exc: MessageError) -> None:
        reason = exc.field if isinstance(exc, CodecError) else "invalid"
        if reason not in ("team", "src", "key", "size"):
            reason = "invalid"
        self.counters.count_dropped(reason)
        log.debug("robot %d dropped a message on %s: %s", self.robot, key, exc)

    def encode_for(self, key: str, msg: Message) -> bytes:
        """Encode ``msg`` for sending on ``key``; refuse keys of other teams or robots."""
        self.check_sender(key, msg)
        return self.codec.encode(msg)

    def check_sender(self, key: str, msg: Message) -> None:
        """Raise ``MessageError`` unless this robot may send ``msg`` on ``key`` (bus open)."""
        self._check_open()
        if key not in self._own_keys:
            parsed = keys.parse_key(key)
            if parsed.alive or parsed.team != self.team or parsed.robot != self.robot:
                raise MessageError(
                    f"key: robot {self.robot} of {self.team} cannot send on {key!r}"
                )
            if len(self._own_keys) < 10_000:
                self._own_keys.add(key)
        if not isinstance(msg, Message):
            raise CodecError("body", f"not a message: {type(msg).__name__}")
        if msg.robot != self.robot:
            raise CodecError("src", f"message robot {msg.robot} is not the sender {self.robot}")

    # presence --------------------------------------------------------------------------
    def _set_alive(self, robot: int, alive: bool) -> None:
        if robot == self.robot or (self.robots is not None and robot not in self.robots):
            return
        if alive == (robot in self._peers):
            return
        if alive:
            self._peers.add(robot)
        else:
            self._peers.discard(robot)
        log.info("robot %d sees robot %d %s", self.robot, robot, "appear" if alive else "leave")
        event = PresenceEvent(robot, alive)
        for stream in list(self._presence_streams):
            stream.push(event)
        self._peers_changed.set()
        self._peers_changed = asyncio.Event()

    def peers(self) -> frozenset[int]:
        return frozenset(self._peers)

    def presence(self) -> Stream[PresenceEvent]:
        stream: Stream[PresenceEvent] = Stream(
            self.queue_size, on_close=self._presence_streams.remove
        )
        for robot in sorted(self._peers):
            stream.push(PresenceEvent(robot, True))
        self._presence_streams.append(stream)
        return stream

    async def wait_for_peers(self, robots: Collection[int], timeout: float) -> frozenset[int]:
        return await self._wait_peers(lambda p: set(robots) <= p, timeout)

    async def wait_for_absent(self, robots: Collection[int], timeout: float) -> frozenset[int]:
        """Wait until none of ``robots`` is present; raise ``TimeoutError`` otherwise."""
        return await self._wait_peers(lambda p: not (set(robots) & p), timeout)

    async def _wait_peers(self, done: Callable[[set[int]], bool], timeout: float) -> frozenset[int]:
        async def wait() -> None:
            while not done(self._peers):
                await self._peers_changed.wait()

        try:
            await asyncio.wait_for(wait(), timeout)
        except TimeoutError:
            raise TimeoutError(
                f"robot {self.robot}: peers still {sorted(self._peers)} after {timeout} s"
            ) from None
        return self.peers()

    def _close_streams(self) -> None:
        for stream in list(self._presence_streams):
            stream.close()

    # queries ---------------------------------------------------------------------------
    async def answer(
        self, served: Any, key: str, request: bytes | None
    ) -> tuple[str, list[Message]] | None:
        """Serve one query that reached ``served`` (``key_expr``, ``handler``, ``closed``) on
        ``key``: validate the request bytes, pick the concrete reply key, run the handler.

        Returns ``(reply key, replies)``, or None when nothing is to be sent (an invalid request
        is dropped and counted, a closed queryable or bus stays silent, a failing handler is
        logged and counted as ``handler_error``).
        """
        msg = None
        if request:
            env = self.accept(key, request, from_owner=False)
            if env is None:
                return None
            msg = env.msg
        reply_key = key if keys.is_concrete(key) else served.key_expr
        if served.closed or self.closed or not keys.is_concrete(reply_key):
            return None
        try:
            return reply_key, await self.run_handler(served.handler, reply_key, msg)
        except Exception:
            self.counters.count_dropped("handler_error")
            log.exception("robot %d: query handler for %s failed", self.robot, reply_key)
            return None

    @staticmethod
    async def run_handler(handler: Handler, key: str, request: Message | None) -> list[Message]:
        """Call a sync or async handler and normalise its result to a list of messages."""
        result = handler(key, request)
        if inspect.isawaitable(result):
            result = await result
        if result is None:
            return []
        if isinstance(result, Message):
            return [result]
        return list(result)

    async def __aenter__(self) -> BusBase:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def close(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError
