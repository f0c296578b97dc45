"""msgpack codec with a numpy ext type and strict validation.

Wire format: a msgpack map ``{v, type, team, src, seq, stamp, body}`` (docs/architecture.md) where
``body`` maps field names to values and numpy arrays travel as msgpack ext type 1::

    u8 dtype code | u8 ndim | ndim x u32 little-endian dims | raw little-endian C-order bytes

:func:`decode` checks the size limit, the envelope fields, the schema version, the message type,
every field's type/dtype/shape/range/finiteness, the team, the sender id (known robot, equal to
``body.robot``) and the sequence number. Any violation raises :class:`MessageError` (as a
:class:`CodecError` whose ``field`` names the culprit); no other exception escapes, whatever
the bytes.

Use :class:`Codec` to stamp a sender's team, id and increasing sequence numbers::

    codec = Codec(team="t0", robot=1, robots=range(3))
    data = codec.encode(Heartbeat(robot=1, keyframes=10))
    env = codec.decode(data)        # Envelope(v=1, type="Heartbeat", ..., msg=Heartbeat(...))
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass
from functools import lru_cache
from itertools import count
from typing import Any, NamedTuple

import msgpack
import numpy as np

from kimera_multi_py.comms import largemsg
from kimera_multi_py.comms.columnar import BATCH_TYPE, from_columns, to_columns
from kimera_multi_py.comms.keys import check_team
from kimera_multi_py.comms.messages import MESSAGE_TYPES, SCHEMA_VERSION, message_type
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.fields import INT64_MAX
from kimera_multi_py.comms.wire import (
    CodecError,
    _ext_hook,
    _packb,
    ext_of,
    unpackb,
    zipped,
)
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.ids import MAX_ROBOT_ID

MAX_MESSAGE_BYTES = 64 * 1024 * 1024
MAX_BATCH = 4096
LARGE_BYTES = 64 * 1024  # from this size on, encode/decode with comms.largemsg (fewer copies)
LARGE_BATCH_BYTES = 16 * 1024  # columnar batches with this many array bytes: encode with largemsg
ZIP_MIN_BYTES = 48  # envelopes of a type marked ZIP from this size on travel compressed (wire.zipped)
ENVELOPE_FIELDS = ("v", "type", "team", "src", "seq", "stamp", "body")
_N_FIELDS = len(ENVELOPE_FIELDS)
_isfinite = math.isfinite
_new = object.__new__


class Envelope(NamedTuple):
    """A decoded message with its envelope (a named tuple: cheap to build on the hot path)."""

    v: int
    type: str
    team: str
    src: int
    seq: int
    stamp: float
    msg: Message


# ---------------------------------------------------------------------------- encode / decode
def encode(msg: Message, *, team: str, src: int, seq: int, stamp: float | None = None) -> bytes:
    """Serialise ``msg`` in an envelope. Raises :class:`MessageError` on an invalid envelope."""
    if not isinstance(msg, Message):
        raise CodecError("body", f"not a message: {type(msg).__name__}")
    check_team(team)
    if msg.robot != src:
        raise CodecError("src", f"message robot {msg.robot} is not the sender {src}")
    if isinstance(seq, bool) or not isinstance(seq, int) or not 0 <= seq <= INT64_MAX:
        raise CodecError("seq", f"invalid sequence number {seq!r}")
    env = {
        "v": SCHEMA_VERSION,
        "type": msg.TYPE,
        "team": team,
        "src": src,
        "seq": seq,
        "stamp": float(time.time() if stamp is None else stamp),
        "body": msg.to_wire(),
    }
    return _packb(env)


def decode(
    data: bytes | bytearray | memoryview,
    *,
    team: str | None = None,
    robots: Collection[int] | None = None,
    max_bytes: int = MAX_MESSAGE_BYTES,
) -> Envelope:
    """Parse and validate one message; raise :class:`MessageError` naming the bad field.

    ``team``, when given, must equal the envelope's team; ``robots``, when given, must contain
    the sender id (otherwise any id in ``[0, MAX_ROBOT_ID]`` is accepted).
    """
    if not isinstance(data, bytes | bytearray | memoryview):
        raise CodecError("payload", f"expected bytes, got {type(data).__name__}")
    if len(data) > max_bytes:
        raise CodecError("size", f"{len(data)} bytes exceeds the limit of {max_bytes}")
    return _check_envelope(_unpack(data), team, robots)


def _unpack(data: bytes | bytearray | memoryview) -> Any:
    """msgpack -> Python objects (arrays as read-only views); only :class:`MessageError` escapes.

    Payloads of :data:`LARGE_BYTES` or more are read by :func:`largemsg.unpack`, whose arrays are
    views into ``data`` itself (no copy, no allocation per array), when it takes them.
    """
    if len(data) >= LARGE_BYTES and data.__class__ is bytes:
        env = largemsg.unpack(data)  # type: ignore[arg-type]
        if env is not None:
            return env
    return unpackb(data)


def decode_batch(
    data: bytes | bytearray | memoryview,
    *,
    team: str | None = None,
    robots: Collection[int] | None = None,
    max_bytes: int = MAX_MESSAGE_BYTES,
) -> list[Envelope | MessageError]:
    """Parse a payload holding one envelope (a map) or a batch (an array of envelopes).

    Returns one item per message, in order: its :class:`Envelope`, or the :class:`MessageError`
    that :func:`decode` would raise for that message alone (each envelope is validated exactly as
    :func:`decode` validates a single one; a columnar batch envelope stands for its messages, or
    for one error). A batch as a whole (size, msgpack, a non-empty array of at most
    :data:`MAX_BATCH` items) is checked first; a failure there raises.
    """
    out: list[Envelope | MessageError] = []
    for item in decode_groups(data, team=team, robots=robots, max_bytes=max_bytes):
        if item.__class__ is Group:
            g: Group = item  # type: ignore[assignment]
            out.extend(_envelope(m.TYPE, g.team, g.src, g.seq + i, g.stamp, m)
                       for i, m in enumerate(g.msgs))
        else:
            out.append(item)  # type: ignore[arg-type]
    return out


@dataclass(frozen=True)
class Group:
    """The messages of one columnar batch envelope: message ``i`` has sequence ``seq + i``."""

    team: str
    src: int
    seq: int
    stamp: float
    msgs: list[Message]


def decode_groups(
    data: bytes | bytearray | memoryview,
    *,
    team: str | None = None,
    robots: Collection[int] | None = None,
    max_bytes: int = MAX_MESSAGE_BYTES,
) -> list[Envelope | Group | MessageError]:
    """:func:`decode_batch` without expanding columnar batches: one item per envelope."""
    if data.__class__ is not bytes and not isinstance(data, bytearray | memoryview):
        raise CodecError("payload", f"expected bytes, got {type(data).__name__}")
    size = len(data)
    if size > max_bytes:
        raise CodecError("size", f"{size} bytes exceeds the limit of {max_bytes}")
    if not size or not 0x90 <= data[0] <= 0x9F and data[0] != 0xDC and data[0] != 0xDD:
        try:  # one envelope
            return [_check_item(_unpack(data), team, robots)]
        except MessageError as exc:
            return [exc]
    try:
        items = msgpack.unpackb(data, raw=False, ext_hook=_ext_hook, strict_map_key=True)
    except MessageError:
        # an array failed in some envelope: decode them one by one to blame only that one
        return _decode_each(data, team, robots)
    except Exception as exc:  # noqa: BLE001 - msgpack raises many types on hostile input
        raise CodecError("payload", f"not valid msgpack ({type(exc).__name__}: {exc})") from exc
    if not isinstance(items, list) or not 1 <= len(items) <= MAX_BATCH:
        raise CodecError("batch", f"expected 1 to {MAX_BATCH} envelopes")
    out: list[Envelope | Group | MessageError] = []
    for env in items:
        try:
            out.append(_check_item(env, team, robots))
        except MessageError as exc:
            out.append(exc)
    return out


def _decode_each(
    data: bytes | bytearray | memoryview, team: str | None, robots: Collection[int] | None
) -> list[Envelope | Group | MessageError]:
    """Slow path of :func:`decode_groups` when an element's arrays are malformed."""
    unpacker = msgpack.Unpacker(raw=False, strict_map_key=True, max_buffer_size=len(data) + 1)
    unpacker.feed(data)
    try:
        n = unpacker.read_array_header()
    except Exception as exc:  # noqa: BLE001
        raise CodecError("payload", f"not valid msgpack ({type(exc).__name__}: {exc})") from exc
    if not 1 <= n <= MAX_BATCH:
        raise CodecError("batch", f"expected 1 to {MAX_BATCH} envelopes")
    out: list[Envelope | Group | MessageError] = []
    for _ in range(n):
        start = unpacker.tell()
        try:
            unpacker.skip()
        except Exception as exc:  # noqa: BLE001
            raise CodecError("payload", f"not valid msgpack ({type(exc).__name__}: {exc})") \
                from exc
        try:
            out.append(_check_item(_unpack(bytes(data[start:unpacker.tell()])), team, robots))
        except MessageError as exc:
            out.append(exc)
    if unpacker.tell() != len(data):
        raise CodecError("payload", "not valid msgpack (extra data after the batch)")
    return out


def _is_batch_head(byte: int) -> bool:
    """True for a msgpack array header (fixarray, array 16, array 32)."""
    return 0x90 <= byte <= 0x9F or byte in (0xDC, 0xDD)


def batch_header(n: int) -> bytes:
    """The msgpack array header that makes ``n`` concatenated envelopes one batch payload."""
    if not 1 <= n <= MAX_BATCH:
        raise CodecError("batch", f"expected 1 to {MAX_BATCH} envelopes")
    return bytes((0x90 | n,)) if n < 16 else b"\xdc" + n.to_bytes(2, "big")


def _check_envelope(env: Any, team: str | None, robots: Collection[int] | None) -> Envelope:
    """Validate a decoded envelope; the compiled common case, else the reference checks."""
    if env.__class__ is dict and len(env) == _N_FIELDS:
        try:
            v, type_name, env_team, src, seq, stamp, body = (
                env["v"], env["type"], env["team"], env["src"], env["seq"], env["stamp"],
                env["body"])
        except KeyError:
            return _check_envelope_slow(env, team, robots)
        cls = MESSAGE_TYPES.get(type_name) if type_name.__class__ is str else None
        if (
            v.__class__ is int and v == SCHEMA_VERSION
            and cls is not None
            and env_team.__class__ is str and (team is None or env_team == team)
            and _team_ok(env_team)
            and src.__class__ is int and 0 <= src <= MAX_ROBOT_ID
            and (robots is None or src in robots)
            and seq.__class__ is int and 0 <= seq <= INT64_MAX
            and stamp.__class__ is float and stamp >= 0 and _isfinite(stamp)
        ):
            msg = cls.from_wire(body)
            if msg.robot != src:
                raise CodecError("src", f"sender {src} differs from {cls.TYPE}.robot={msg.robot}")
            return _envelope(cls.TYPE, env_team, src, seq, stamp, msg)
    return _check_envelope_slow(env, team, robots)


@lru_cache(maxsize=256)
def _team_ok(team: str) -> bool:
    try:
        check_team(team)
    except MessageError:
        return False
    return True


def _envelope(type_name: str, team: str, src: int, seq: int, stamp: float, msg: Message) -> Envelope:
    """An :class:`Envelope` of validated fields."""
    return _tuple_new(Envelope, (SCHEMA_VERSION, type_name, team, src, seq, stamp, msg))


_tuple_new = tuple.__new__


def _check_envelope_slow(env: Any, team: str | None, robots: Collection[int] | None) -> Envelope:
    """The reference envelope check: what :func:`decode` accepts, raises or names."""
    cls, env_team, src, seq, stamp = _check_header(env, team, robots)
    if cls is None:
        raise CodecError("type", f"a columnar {BATCH_TYPE}: decode it with decode_batch")
    msg = cls.from_wire(env["body"])
    if msg.robot != src:
        raise CodecError("src", f"sender {src} differs from {cls.TYPE}.robot={msg.robot}")
    return Envelope(SCHEMA_VERSION, cls.TYPE, env_team, src, seq, stamp, msg)


def _check_header(
    env: Any, team: str | None, robots: Collection[int] | None
) -> tuple[type[Message] | None, str, int, int, float]:
    """Check every envelope field but the body: (message class or None for a batch, team, src,
    seq, stamp); raise :class:`CodecError` naming the first bad field."""
    if not isinstance(env, dict):
        raise CodecError("envelope", f"expected a map, got {type(env).__name__}")
    for name in ENVELOPE_FIELDS:
        if name not in env:
            raise CodecError(name, "missing envelope field")
    if len(env) != len(ENVELOPE_FIELDS):
        extra = next(k for k in env if k not in ENVELOPE_FIELDS)
        raise CodecError(str(extra), "unknown envelope field")
    v = env["v"]
    if isinstance(v, bool) or not isinstance(v, int) or v != SCHEMA_VERSION:
        raise CodecError("v", f"schema version {v!r}, expected {SCHEMA_VERSION}")
    if not isinstance(env["type"], str):
        raise CodecError("type", "message type must be a string")
    cls = None if env["type"] == BATCH_TYPE else message_type(env["type"])
    env_team = env["team"]
    if not isinstance(env_team, str):
        raise CodecError("team", "team must be a string")
    try:
        check_team(env_team)
    except MessageError as exc:
        raise CodecError("team", str(exc)) from exc
    if team is not None and env_team != team:
        raise CodecError("team", f"foreign team {env_team!r} (expected {team!r})")
    src = env["src"]
    if isinstance(src, bool) or not isinstance(src, int) or not 0 <= src <= MAX_ROBOT_ID:
        raise CodecError("src", f"invalid sender id {src!r}")
    if robots is not None and src not in robots:
        raise CodecError("src", f"unknown robot {src}")
    seq = env["seq"]
    if isinstance(seq, bool) or not isinstance(seq, int) or not 0 <= seq <= INT64_MAX:
        raise CodecError("seq", f"invalid sequence number {seq!r}")
    stamp = env["stamp"]
    if not isinstance(stamp, float) or not math.isfinite(stamp) or stamp < 0:
        raise CodecError("stamp", f"invalid stamp {stamp!r}")
    return cls, env_team, src, seq, stamp


def _check_item(env: Any, team: str | None, robots: Collection[int] | None) -> Envelope | Group:
    """Validate one decoded envelope: an :class:`Envelope`, or a columnar batch's :class:`Group`."""
    kind = env.get("type") if env.__class__ is dict else None
    if kind.__class__ is str and kind == BATCH_TYPE:
        _, env_team, src, seq, stamp = _check_header(env, team, robots)
        msgs = from_columns(env["body"], src, MAX_BATCH)
        if seq + len(msgs) - 1 > INT64_MAX:
            raise CodecError("seq", f"sequence numbers of the batch overflow from {seq}")
        return Group(env_team, src, seq, stamp, msgs)
    return _check_envelope(env, team, robots)


class Codec:
    """Encoder/decoder bound to one sender: stamps team, id and increasing sequence numbers.

    :meth:`encode` takes its number atomically (safe from any thread); :meth:`encode_many` takes
    a contiguous range, which is contiguous only while one thread encodes with this codec.
    """

    def __init__(
        self,
        team: str,
        robot: int,
        robots: Collection[int] | None = None,
        max_bytes: int = MAX_MESSAGE_BYTES,
    ) -> None:
        self.team = check_team(team)
        self.robot = robot
        self.robots = frozenset(robots) if robots is not None else None
        self.max_bytes = max_bytes
        self.compress = True  # compress the envelopes of types marked ZIP (False: the plain format)
        # the envelopes' stamps: a simulation gives its own clock, so that compressed sizes (which
        # depend on the stamp's bytes) repeat from run to run
        self.clock: Callable[[], float] = time.time
        self._seq = count()  # next() on a C iterator is atomic: thread-safe without a lock

    def next_seq(self) -> int:
        return next(self._seq)

    def encode(self, msg: Message) -> bytes:
        """:func:`encode` with this sender's team, id and next sequence number."""
        if not isinstance(msg, Message):
            raise CodecError("body", f"not a message: {type(msg).__name__}")
        if msg.robot != self.robot:
            raise CodecError("src", f"message robot {msg.robot} is not the sender {self.robot}")
        # the team was checked once in __init__ and seq comes from our own counter
        if msg.size_hint() < LARGE_BYTES:
            data = _packb({"v": SCHEMA_VERSION, "type": msg.TYPE, "team": self.team,
                           "src": self.robot, "seq": next(self._seq), "stamp": self.clock(),
                           "body": msg._wire_body(ext_of)})
        else:  # the same bytes, with one copy of the arrays instead of three
            data = largemsg.pack({"v": SCHEMA_VERSION, "type": msg.TYPE, "team": self.team,
                                  "src": self.robot, "seq": next(self._seq), "stamp": self.clock(),
                                  "body": msg.to_wire()})
        if self.compress and msg.ZIP and len(data) >= ZIP_MIN_BYTES:
            data = zipped(data)
        if len(data) > self.max_bytes:
            raise CodecError("size", f"{len(data)} bytes exceeds the limit of {self.max_bytes}")
        return data

    def encode_many(self, msgs: list[Message]) -> bytes | None:
        """One columnar batch envelope for ``msgs`` (see :mod:`columnar`), or None when they do
        not qualify (fewer than two, mixed types, or array shapes that differ)."""
        if len(msgs) > MAX_BATCH:
            raise CodecError("batch", f"{len(msgs)} messages, at most {MAX_BATCH} per batch")
        body = to_columns(msgs)
        if body is None:
            return None
        robot = self.robot
        for m in msgs:
            if m.robot != robot:
                raise CodecError("src", f"message robot {m.robot} is not the sender {robot}")
        seq = self._seq
        seq0 = next(seq)
        for _ in range(len(msgs) - 1):  # messages get seq0, seq0 + 1, ... (one sender thread)
            next(seq)
        env = {"v": SCHEMA_VERSION, "type": BATCH_TYPE, "team": self.team,
               "src": robot, "seq": seq0, "stamp": self.clock(), "body": body}
        # stacked columns of a burst are big: largemsg copies them once, the Packer three times
        big = sum(c.nbytes for c in body["cols"].values() if c.__class__ is np.ndarray)
        data = largemsg.pack(env) if big >= LARGE_BATCH_BYTES else _packb(env)
        if self.compress and msgs[0].ZIP and len(data) >= ZIP_MIN_BYTES:
            data = zipped(data)
        if len(data) > self.max_bytes:
            raise CodecError("size", f"{len(data)} bytes exceeds the limit of {self.max_bytes}")
        return data

    def decode(self, data: bytes | bytearray | memoryview) -> Envelope:
        return decode(data, team=self.team, robots=self.robots, max_bytes=self.max_bytes)

    def decode_batch(self, data: bytes | bytearray | memoryview) -> list[Envelope | MessageError]:
        return decode_batch(data, team=self.team, robots=self.robots, max_bytes=self.max_bytes)

    def decode_groups(
        self, data: bytes | bytearray | memoryview
    ) -> list[Envelope | Group | MessageError]:
        return decode_groups(data, team=self.team, robots=self.robots, max_bytes=self.max_bytes)
