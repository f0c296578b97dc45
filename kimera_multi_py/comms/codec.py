"""msgpack codec with a numpy ext type and strict validation.

Wire format: a msgpack map ``{v, type, team, src, seq, stamp, body}`` (DESIGN §3) where
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
import struct
import threading
import time
from collections.abc import Collection
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from kimera_multi_py.comms.keys import check_team
from kimera_multi_py.comms.messages import (
    INT64_MAX,
    MAX_ROBOT_ID,
    SCHEMA_VERSION,
    Message,
    message_type,
)
from kimera_multi_py.errors import MessageError

EXT_NDARRAY = 1
MAX_MESSAGE_BYTES = 64 * 1024 * 1024
MAX_NDIM = 8
ENVELOPE_FIELDS = ("v", "type", "team", "src", "seq", "stamp", "body")

_DTYPES: dict[int, np.dtype] = {
    1: np.dtype("<f8"),
    2: np.dtype("<f4"),
    3: np.dtype("<i8"),
    4: np.dtype("<i4"),
    5: np.dtype("<i2"),
    6: np.dtype("i1"),
    7: np.dtype("<u8"),
    8: np.dtype("<u4"),
    9: np.dtype("<u2"),
    10: np.dtype("u1"),
    11: np.dtype("?"),
}
_CODES: dict[np.dtype, int] = {dt: code for code, dt in _DTYPES.items()}
_HEAD = struct.Struct("<BB")


class CodecError(MessageError):
    """A :class:`MessageError` that names the offending ``field`` (``team``, ``src``, ...)."""

    def __init__(self, field: str, problem: str) -> None:
        self.field = field
        self.problem = problem
        super().__init__(f"{field}: {problem}")


@dataclass(frozen=True)
class Envelope:
    """A decoded message with its envelope."""

    v: int
    type: str
    team: str
    src: int
    seq: int
    stamp: float
    msg: Message


# ---------------------------------------------------------------------------- arrays
def _pack_array(a: np.ndarray) -> msgpack.ExtType:
    dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
    code = _CODES.get(dt)
    if code is None:
        raise CodecError("array", f"unsupported dtype {a.dtype}")
    if a.ndim > MAX_NDIM:
        raise CodecError("array", f"more than {MAX_NDIM} dimensions")
    a = np.ascontiguousarray(a, dtype=dt)
    head = _HEAD.pack(code, a.ndim) + struct.pack(f"<{a.ndim}I", *a.shape)
    return msgpack.ExtType(EXT_NDARRAY, b"".join((head, memoryview(a))))  # one copy


def _unpack_array(data: bytes) -> np.ndarray:
    if len(data) < _HEAD.size:
        raise CodecError("array", "truncated header")
    code, ndim = _HEAD.unpack_from(data)
    dt = _DTYPES.get(code)
    if dt is None:
        raise CodecError("array", f"unknown dtype code {code}")
    if ndim > MAX_NDIM:
        raise CodecError("array", f"{ndim} dimensions (max {MAX_NDIM})")
    start = _HEAD.size + 4 * ndim
    if len(data) < start:
        raise CodecError("array", "truncated shape")
    shape = struct.unpack_from(f"<{ndim}I", data, _HEAD.size)
    n = math.prod(shape)
    if n * dt.itemsize != len(data) - start:
        raise CodecError("array", f"shape {shape} needs {n * dt.itemsize} bytes, has "
                         f"{len(data) - start}")
    if dt.kind == "b" and n and np.frombuffer(data, np.uint8, n, start).max() > 1:
        raise CodecError("array", "boolean array holds values other than 0 and 1")
    # a read-only view on the ext bytes (no copy): received messages are immutable values
    return np.frombuffer(data, dtype=dt.newbyteorder("="), count=n, offset=start).reshape(shape)


def _ext_hook(code: int, data: bytes) -> Any:
    if code != EXT_NDARRAY:
        raise CodecError("ext", f"unknown ext type {code}")
    return _unpack_array(data)


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return _pack_array(obj)
    raise CodecError("body", f"cannot encode {type(obj).__name__}")


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
    return msgpack.packb(env, default=_default, use_bin_type=True)


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
    try:
        env = msgpack.unpackb(data, raw=False, ext_hook=_ext_hook, strict_map_key=True)
    except MessageError:
        raise
    except Exception as exc:  # noqa: BLE001 - msgpack raises many types on hostile input
        raise CodecError("payload", f"not valid msgpack ({type(exc).__name__}: {exc})") from exc
    return _check_envelope(env, team, robots)


def _check_envelope(env: Any, team: str | None, robots: Collection[int] | None) -> Envelope:
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
    cls = message_type(env["type"]) if isinstance(env["type"], str) else None
    if cls is None:
        raise CodecError("type", "message type must be a string")
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
    msg = cls.from_wire(env["body"])
    if msg.robot != src:
        raise CodecError("src", f"sender {src} differs from {cls.TYPE}.robot={msg.robot}")
    return Envelope(SCHEMA_VERSION, cls.TYPE, env_team, src, seq, stamp, msg)


class Codec:
    """Encoder/decoder bound to one sender: stamps team, id and a thread-safe sequence number."""

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
        self._seq = 0
        self._lock = threading.Lock()

    def next_seq(self) -> int:
        with self._lock:
            seq = self._seq
            self._seq += 1
        return seq

    def encode(self, msg: Message) -> bytes:
        data = encode(msg, team=self.team, src=self.robot, seq=self.next_seq())
        if len(data) > self.max_bytes:
            raise CodecError("size", f"{len(data)} bytes exceeds the limit of {self.max_bytes}")
        return data

    def decode(self, data: bytes | bytearray | memoryview) -> Envelope:
        return decode(data, team=self.team, robots=self.robots, max_bytes=self.max_bytes)
