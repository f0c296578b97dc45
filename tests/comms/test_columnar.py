"""Columnar batch envelopes (``type = "Batch"``, one column per field): round trips for every
message type, refusal of every malformed column (a batch is accepted exactly when its messages
would be accepted one by one), mixing with ordinary envelopes in msgpack-array payloads, the
bus's counting of columnar payloads, and fuzzing: whatever the bytes, only MessageError."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kimera_multi_py.comms import codec, columnar, keys, wire
from kimera_multi_py.comms.bus import BusBase, Subscription
from kimera_multi_py.comms.codec import MAX_BATCH, Codec, CodecError, Envelope, Group
from kimera_multi_py.comms.counters import share, share_range
from kimera_multi_py.comms.messages import MESSAGE_TYPES, SCHEMA_VERSION
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.fields import INT64_MAX, INT64_MIN, Array, Bool, Float, Int, Str
from kimera_multi_py.comms.messages.pgo import GncWeights, PublicPoses
from kimera_multi_py.comms.messages.team import Heartbeat, Ping
from kimera_multi_py.core.errors import MessageError
from tests.support.samples import _random_array, random_message

TEAM = "t0"
ROBOTS = frozenset(range(4))
TYPES = sorted(MESSAGE_TYPES)
SYMBOLS = sorted({s for cls in MESSAGE_TYPES.values() for spec in cls.SPECS.values()
                  if isinstance(spec, Array) for s in spec.shape if isinstance(s, str)})
DIMS = {s: 2 + i for i, s in enumerate(SYMBOLS)}  # distinct non-zero sizes per symbolic dim


# ---------------------------------------------------------------------------- helpers
def sized(cls: type[Message], rng: np.random.Generator, robot: int, dims: dict[str, int]) -> Message:
    """A valid random ``cls`` whose symbolic dimensions have exactly the sizes ``dims``."""
    base = random_message(cls, rng, robot, max_len=0)
    values = {name: getattr(base, name) for name in cls.SPECS}
    for name, spec in cls.SPECS.items():
        if isinstance(spec, Array):
            shape = tuple(s if isinstance(s, int) else dims[s] for s in spec.shape)
            values[name] = _random_array(spec, shape, rng)
    return cls(**values)


def burst(cls: type[Message], seed: int, k: int = 3, robot: int = 1,
          dims: dict[str, int] | None = None) -> list[Message]:
    rng = np.random.default_rng(seed)
    if dims is None:
        return [random_message(cls, rng, robot, max_len=0) for _ in range(k)]
    return [sized(cls, rng, robot, dims) for _ in range(k)]


def envelope(body: Any, **fields: Any) -> dict[str, Any]:
    env = {"v": SCHEMA_VERSION, "type": columnar.BATCH_TYPE, "team": TEAM, "src": 1, "seq": 10,
           "stamp": 1.0, "body": body}
    env.update(fields)
    return env


def pack(env: dict[str, Any]) -> bytes:
    return wire._packb(env)


def wrap(parts: list[bytes]) -> bytes:
    """A msgpack-array batch payload of ``parts``."""
    return codec.batch_header(len(parts)) + b"".join(parts)


def decode_batch(data: bytes) -> list[Envelope | MessageError]:
    return codec.decode_batch(data, team=TEAM, robots=ROBOTS)


def decode_groups(data: bytes) -> list[Envelope | Group | MessageError]:
    return codec.decode_groups(data, team=TEAM, robots=ROBOTS)


def assert_valid(env: Envelope) -> None:
    """An accepted message is valid: it re-encodes, and decodes alone to the same message."""
    assert isinstance(env.msg, Message)
    assert env.team == TEAM and env.src in ROBOTS and env.msg.robot == env.src
    assert env.type == env.msg.TYPE and 0 <= env.seq <= INT64_MAX
    again = codec.decode(Codec(env.team, env.src).encode(env.msg), team=TEAM, robots=ROBOTS)
    assert again.msg == env.msg


def expand(groups: list[Envelope | Group | MessageError]) -> list[tuple[str, Any, Any]]:
    """decode_groups output flattened like decode_batch: (kind, seq or error text, message)."""
    out: list[tuple[str, Any, Any]] = []
    for item in groups:
        if isinstance(item, Group):
            out.extend(("env", item.seq + i, m) for i, m in enumerate(item.msgs))
        elif isinstance(item, Envelope):
            out.append(("env", item.seq, item.msg))
        else:
            out.append(("err", str(item), None))
    return out


def flat(items: list[Envelope | MessageError]) -> list[tuple[str, Any, Any]]:
    return [("env", i.seq, i.msg) if isinstance(i, Envelope) else ("err", str(i), None) for i in items]


# ---------------------------------------------------------------------------- 1. round trips
@pytest.mark.parametrize("type_name", TYPES)
@pytest.mark.parametrize(("k", "dims"), [(2, None), (5, None), (3, DIMS), (17, {s: 1 for s in SYMBOLS})])
def test_round_trip_every_type(type_name: str, k: int, dims: dict[str, int] | None) -> None:
    cls = MESSAGE_TYPES[type_name]
    msgs = burst(cls, seed=k + len(type_name), k=k, robot=2, dims=dims)
    c = Codec(TEAM, 2, ROBOTS)
    c.encode(msgs[0])  # seq 0: the batch starts at 1
    data = c.encode_many(msgs)
    assert data is not None
    items = c.decode_batch(data)
    assert len(items) == k
    stamps = set()
    for i, (env, want) in enumerate(zip(items, msgs, strict=True)):
        assert isinstance(env, Envelope)
        assert env.msg == want and type(env.msg) is cls
        assert env.type == type_name and env.v == SCHEMA_VERSION
        assert env.seq == 1 + i and env.src == 2 and env.team == TEAM
        stamps.add(env.stamp)
        for name, spec in cls.SPECS.items():
            value = getattr(env.msg, name)
            if isinstance(spec, Array):
                assert value.dtype == np.dtype(spec.dtype) and not value.flags.writeable
                with pytest.raises(ValueError, match="read-only"):
                    value[...] = 0
            else:  # plain Python scalars, as from a single envelope
                assert type(value) is type(getattr(want, name))
        assert_valid(env)
    assert len(stamps) == 1
    # decode_groups: one Group for the envelope, holding the same messages
    (group,) = c.decode_groups(data)
    assert isinstance(group, Group)
    assert (group.team, group.src, group.seq, group.stamp) == (TEAM, 2, 1, stamps.pop())
    assert group.msgs == msgs
    # the next sequence number follows the batch
    assert c.decode(c.encode(msgs[0])).seq == 1 + k
    # the same envelope inside a msgpack-array payload decodes identically
    assert flat(c.decode_batch(wrap([data]))) == flat(items)


def test_round_trip_with_symbolic_sizes_drawn_until_they_agree() -> None:
    """random_message with max_len > 0 gives random sizes: keep drawing until shapes agree."""
    rng = np.random.default_rng(21)
    c = Codec(TEAM, 1, ROBOTS)
    for cls in (PublicPoses, GncWeights, MESSAGE_TYPES["ObjectUpdate"], MESSAGE_TYPES["MapDelta"]):
        first = random_message(cls, rng, 1, max_len=2)
        shapes = [getattr(first, n).shape for n, s in cls.SPECS.items() if isinstance(s, Array)]
        msgs = [first]
        for _ in range(2000):
            m = random_message(cls, rng, 1, max_len=2)
            if [getattr(m, n).shape for n, s in cls.SPECS.items() if isinstance(s, Array)] == shapes:
                msgs.append(m)
                if len(msgs) == 4:
                    break
        assert len(msgs) == 4
        items = c.decode_batch(c.encode_many(msgs))  # type: ignore[arg-type]
        assert [e.msg for e in items] == msgs  # type: ignore[union-attr]


def test_max_batch_round_trips_and_one_more_is_refused() -> None:
    c = Codec(TEAM, 0, ROBOTS)
    msgs = [Heartbeat(robot=0, keyframes=i, status=str(i % 7)) for i in range(MAX_BATCH)]
    items = c.decode_batch(c.encode_many(msgs))  # type: ignore[arg-type]
    assert [e.msg for e in items] == msgs  # type: ignore[union-attr]
    assert [e.seq for e in items] == list(range(MAX_BATCH))  # type: ignore[union-attr]
    with pytest.raises(MessageError, match="^batch"):
        c.encode_many(msgs + [msgs[0]])


def large_pings(k: int = 80, robot: int = 1, seed: int = 8) -> list[Message]:
    """A burst of ``k`` pings with 1 KB payloads: 80 make an envelope of more than 64 KiB."""
    rng = np.random.default_rng(seed)
    return [Ping(robot=robot, nonce=i, sent_ns=3 * i, echo=bool(i % 2),
                 payload=rng.integers(0, 256, 1024, dtype=np.uint8)) for i in range(k)]


def test_large_columnar_batch_round_trips_on_both_decode_paths() -> None:
    """A batch of more than codec.LARGE_BYTES is read by largemsg when alone, by msgpack inside
    an array payload: the same messages either way, arrays read-only."""
    c = Codec(TEAM, 1, ROBOTS)
    pings = large_pings()
    descriptors = burst(MESSAGE_TYPES["KeyframeDescriptor"], seed=1, k=20, dims={"d": 1000})
    for msgs in (pings, descriptors):
        data = c.encode_many(msgs)
        assert data is not None and len(data) > getattr(codec, "LARGE_BYTES", 64 * 1024)
        alone, inside = decode_batch(data), decode_batch(wrap([data]))
        assert [e.msg for e in alone] == msgs  # type: ignore[union-attr]
        assert flat(inside) == flat(alone)
        for env in alone + inside:
            assert isinstance(env, Envelope)
            assert all(not getattr(env.msg, n).flags.writeable
                       for n, s in type(env.msg).SPECS.items() if isinstance(s, Array))
        assert expand(decode_groups(data)) == flat(alone)


# ---------------------------------------------------------------------------- 2. qualification
def test_encode_many_returns_none_when_the_messages_do_not_qualify() -> None:
    c = Codec(TEAM, 1, ROBOTS)
    hb = [Heartbeat(robot=1, keyframes=i) for i in range(3)]
    assert c.encode_many(hb[:1]) is None
    assert c.encode_many([hb[0], Ping(robot=1, nonce=0, sent_ns=0), hb[1]]) is None  # mixed types
    pings = [Ping(robot=1, nonce=i, sent_ns=0, payload=np.zeros(4 + (i == 2), np.uint8)) for i in range(3)]
    assert c.encode_many(pings) is None  # payload shapes differ
    poses = [PublicPoses(robot=1, round=0, keys=np.arange(k), poses=np.tile(np.eye(4), (k, 1, 1)))
             for k in (2, 2, 3)]
    assert c.encode_many(poses) is None
    assert c.encode_many(poses[:2]) is not None
    # refusals consume no sequence numbers: the accepted batch above took 0 and 1
    assert c.decode(c.encode(hb[0])).seq == 2


def test_encode_many_refuses_messages_of_another_robot() -> None:
    c = Codec(TEAM, 1, ROBOTS)
    with pytest.raises(MessageError, match="^src"):
        c.encode_many([Heartbeat(robot=2, keyframes=i) for i in range(3)])
    with pytest.raises(MessageError, match="^src"):  # one intruder is enough
        c.encode_many([Heartbeat(robot=1, keyframes=0), Heartbeat(robot=3, keyframes=1)])
    assert c.decode(c.encode(Heartbeat(robot=1, keyframes=0))).seq == 0


def test_encode_many_of_nothing_is_none() -> None:
    assert Codec(TEAM, 1).encode_many([]) is None


def test_encode_many_of_non_messages_is_a_message_error() -> None:
    with pytest.raises(MessageError):
        Codec(TEAM, 1).encode_many([1, 2])  # type: ignore[list-item]


# ---------------------------------------------------------------------------- 3. validation
Mutator = Callable[[dict[str, Any]], Any]


def setv(name: str, value: Any, row: int = 1) -> Mutator:
    """Put ``value`` in row ``row`` of column ``name`` (first element of an array row)."""
    def f(body: dict[str, Any]) -> None:
        col = body["cols"][name]
        if isinstance(col, list):
            col[row] = value
        elif col.ndim == 1:
            col[row] = value
        else:
            col.reshape(col.shape[0], -1)[row, 0] = value
    return f


def setcol(name: str, fn: Callable[[Any], Any]) -> Mutator:
    def f(body: dict[str, Any]) -> None:
        body["cols"][name] = fn(body["cols"][name])
    return f


def setbody(name: str, value: Any) -> Mutator:
    def f(body: dict[str, Any]) -> None:
        body[name] = value
    return f


def delcol(name: str) -> Mutator:
    def f(body: dict[str, Any]) -> None:
        del body["cols"][name]
    return f


def rows_only(n: int) -> Mutator:
    """Keep the first ``n`` rows of every column and say so in ``n``."""
    def f(body: dict[str, Any]) -> None:
        body["n"] = n
        body["cols"] = {k: v[:n] for k, v in body["cols"].items()}
    return f


@dataclass(frozen=True)
class Replace:
    """Returned by a mutator that replaces the whole body."""

    body: Any


def new_body(value: Any) -> Mutator:
    return lambda body: Replace(value)


NAN, INF = math.nan, math.inf

# value-level forgeries: every column keeps its wire format, one value is wrong. The batch must be
# refused, and so must (at least) one of its messages sent alone.
VALUE_CASES: list[tuple[str, Mutator, str]] = [
    ("Heartbeat", setv("keyframes", -1), "Batch.Heartbeat.keyframes"),
    ("LoopClosureRequest", setv("request_id", -5), "Batch.LoopClosureRequest.request_id"),
    ("MapDelta", setv("depth", 22), "Batch.MapDelta.depth"),
    ("MapDelta", setv("depth", -1), "Batch.MapDelta.depth"),
    ("GncWeights", setv("peer", 4096), "Batch.GncWeights.peer"),
    ("Heartbeat", setv("robot", 4096), "Batch.Heartbeat.robot"),
    ("Heartbeat", setv("robot", -1), "Batch.Heartbeat.robot"),
    ("Heartbeat", setv("robot", 2), "Batch.robot"),  # a valid id, but not the sender's
    ("Ping", setv("robot", 0, row=0), "Batch.robot"),
    ("PgoStatus", setv("cost", NAN), "Batch.PgoStatus.cost"),
    ("PgoStatus", setv("cost", INF), "Batch.PgoStatus.cost"),
    ("PgoStatus", setv("cost", -INF), "Batch.PgoStatus.cost"),
    ("PgoStatus", setv("rel_change", -1e-3), "Batch.PgoStatus.rel_change"),
    ("KeyframeDescriptor", setv("stamp", INF), "Batch.KeyframeDescriptor.stamp"),
    ("KeyframeDescriptor", setv("stamp", NAN), "Batch.KeyframeDescriptor.stamp"),
    ("MapDelta", setv("resolution", 0.0), "Batch.MapDelta.resolution"),
    ("MapDelta", setv("scale", -1.0), "Batch.MapDelta.scale"),
    ("GncWeights", setv("mu", NAN), "Batch.GncWeights.mu"),
    ("PgoCommand", setv("command", "go"), "Batch.PgoCommand.command"),
    ("PgoCommand", setv("command", ""), "Batch.PgoCommand.command"),
    ("KeyframeDescriptor", setv("kind", "k" * 65), "Batch.KeyframeDescriptor.kind"),
    ("Heartbeat", setv("status", "s" * 65), "Batch.Heartbeat.status"),
    ("Heartbeat", setv("status", b"ok"), "Batch.Heartbeat.status"),
    ("Heartbeat", setv("status", 7), "Batch.Heartbeat.status"),
    ("Heartbeat", setv("status", None), "Batch.Heartbeat.status"),
    ("PublicPoses", setcol("keys", lambda c: c.astype(np.int32)), "Batch.PublicPoses.keys"),
    ("PublicPoses", setcol("poses", lambda c: c.astype(np.float32)), "Batch.PublicPoses.poses"),
    ("MapDelta", setcol("logodds", lambda c: c.astype(np.uint8)), "Batch.MapDelta.logodds"),
    ("Ping", setcol("payload", lambda c: c.astype(np.int8)), "Batch.Ping.payload"),
    ("PublicPoses", setcol("poses", lambda c: c[:, :, :, :3].copy()), "Batch.PublicPoses.poses"),
    ("LoopClosures", setcol("sigmas", lambda c: c[:, :, :5].copy()), "Batch.LoopClosures.sigmas"),
    ("LoopClosureReply", setcol("pose", lambda c: c[:, :3].copy()), "Batch.LoopClosureReply.pose"),
    ("PublicPoses", setcol("poses", lambda c: c[:, :-1].copy()), "Batch.PublicPoses.poses"),
    ("GncWeights", setcol("keys_b", lambda c: c[:, :-1].copy()), "Batch.GncWeights.keys_b"),
    ("ObjectUpdate", setcol("classes", lambda c: c[:, :-1].copy()), "Batch.ObjectUpdate.classes"),
    ("LoopClosureReply", setcol("object_classes", lambda c: c[:, 1:].copy()),
     "Batch.LoopClosureReply.object_classes"),
    ("GncWeights", setv("weights", NAN), "Batch.GncWeights.weights"),
    ("GncWeights", setv("weights", INF), "Batch.GncWeights.weights"),
    ("GncWeights", setv("weights", 1.5), "Batch.GncWeights.weights"),
    ("GncWeights", setv("weights", -0.25), "Batch.GncWeights.weights"),
    ("LoopClosures", setv("poses", NAN), "Batch.LoopClosures.poses"),
    ("LoopClosures", setv("sigmas", -1.0), "Batch.LoopClosures.sigmas"),
    ("LoopClosures", setv("inliers", -1), "Batch.LoopClosures.inliers"),
    ("KeyframeDescriptor", setv("descriptor", -INF), "Batch.KeyframeDescriptor.descriptor"),
    ("KeyframeOdometry", setv("odometry", INF), "Batch.KeyframeOdometry.odometry"),
    ("KeyframeOdometry", setv("keyframes", -1), "Batch.KeyframeOdometry.keyframes"),
    ("PgoCommand", setv("active", 4096), "Batch.PgoCommand.active"),
    ("PgoCommand", setv("active", -1), "Batch.PgoCommand.active"),
    ("LoopClosureReply", setv("num_points", -1), "Batch.LoopClosureReply.num_points"),
    ("LoopClosureReply", setv("object_centroids", NAN), "Batch.LoopClosureReply.object_centroids"),
    ("ObjectUpdate", setv("probs", 1.01), "Batch.ObjectUpdate.probs"),
    ("ObjectUpdate", setv("extents", -1e-9), "Batch.ObjectUpdate.extents"),
    ("MapDelta", setv("keys", -1), "Batch.MapDelta.keys"),
]

# format-level forgeries: the columns themselves are malformed (no single-envelope equivalent)
FORMAT_CASES: list[tuple[str, Mutator, str]] = [
    ("PgoStatus", setcol("ready", lambda c: c.astype(np.uint8)), "Batch.PgoStatus.ready"),
    ("PgoStatus", setcol("ready", lambda c: c.astype(np.int64)), "Batch.PgoStatus.ready"),
    ("Heartbeat", setcol("keyframes", lambda c: c.astype(np.int32)), "Batch.Heartbeat.keyframes"),
    ("Heartbeat", setcol("keyframes", lambda c: c.astype(np.uint64)), "Batch.Heartbeat.keyframes"),
    ("Heartbeat", setcol("keyframes", lambda c: c.astype(np.float64)), "Batch.Heartbeat.keyframes"),
    ("PgoStatus", setcol("cost", lambda c: c.astype(np.float32)), "Batch.PgoStatus.cost"),
    ("PgoStatus", setcol("cost", lambda c: c.astype(np.int64)), "Batch.PgoStatus.cost"),
    ("Heartbeat", setcol("keyframes", lambda c: c.tolist()), "Batch.Heartbeat.keyframes"),  # a list
    ("PgoStatus", setcol("ready", lambda c: c.tolist()), "Batch.PgoStatus.ready"),
    ("PgoStatus", setcol("cost", lambda c: c.tolist()), "Batch.PgoStatus.cost"),
    ("Heartbeat", setcol("keyframes", lambda c: c[:, None].copy()), "Batch.Heartbeat.keyframes"),
    ("Heartbeat", setcol("keyframes", lambda c: c[:2].copy()), "Batch.Heartbeat.keyframes"),
    ("Heartbeat", setcol("keyframes", lambda c: np.array(5)), "Batch.Heartbeat.keyframes"),  # 0-d
    ("Heartbeat", setcol("keyframes", lambda c: 5), "Batch.Heartbeat.keyframes"),
    ("Heartbeat", setcol("status", lambda c: "ok"), "Batch.Heartbeat.status"),  # not a list
    ("Heartbeat", setcol("status", lambda c: c[:2]), "Batch.Heartbeat.status"),
    ("Heartbeat", setcol("status", lambda c: c + ["x"]), "Batch.Heartbeat.status"),
    ("Heartbeat", setcol("status", lambda c: {"a": "b"}), "Batch.Heartbeat.status"),
    ("PublicPoses", setcol("keys", lambda c: c.tolist()), "Batch.PublicPoses.keys"),  # a list
    ("PublicPoses", setcol("poses", lambda c: c.tolist()), "Batch.PublicPoses.poses"),
    ("PublicPoses", setcol("poses", lambda c: c[:, 0].copy()), "Batch.PublicPoses.poses"),  # ndim
    ("PublicPoses", setcol("keys", lambda c: c[:2].copy()), "Batch.PublicPoses.keys"),  # rows != n
    ("PublicPoses", setcol("keys", lambda c: c[0].copy()), "Batch.PublicPoses.keys"),
    ("PublicPoses", setcol("keys", lambda c: msgpack.ExtType(1, b"\x03\x02")), "array"),
    ("Heartbeat", setbody("n", 4), "Batch.Heartbeat.robot"),  # n and column lengths disagree
    ("Heartbeat", setbody("n", 2), "Batch.Heartbeat.robot"),
    ("Heartbeat", rows_only(1), "Batch.n"),
    ("Heartbeat", rows_only(0), "Batch.n"),
    ("Heartbeat", setbody("n", MAX_BATCH + 1), "Batch.n"),
    ("Heartbeat", setbody("n", -3), "Batch.n"),
    ("Heartbeat", setbody("n", True), "Batch.n"),
    ("Heartbeat", setbody("n", 3.0), "Batch.n"),
    ("Heartbeat", setbody("n", "3"), "Batch.n"),
    ("Heartbeat", setbody("n", None), "Batch.n"),
    ("Heartbeat", setbody("type", "Nope"), "Batch.type"),
    ("Heartbeat", setbody("type", "Batch"), "Batch.type"),
    ("Heartbeat", setbody("type", "heartbeat"), "Batch.type"),
    ("Heartbeat", setbody("type", 7), "Batch.type"),
    ("Heartbeat", setbody("type", ["Heartbeat"]), "Batch.type"),
    ("Heartbeat", setbody("type", "Ping"), "Batch.cols"),  # columns of another type
    ("Heartbeat", delcol("status"), "Batch.cols"),
    ("Heartbeat", delcol("robot"), "Batch.cols"),
    ("Heartbeat", lambda b: b["cols"].update(extra=np.zeros(3, np.int64)), "Batch.cols"),
    ("Heartbeat", setbody("cols", []), "Batch.cols"),
    ("Heartbeat", setbody("cols", None), "Batch.cols"),
    ("Heartbeat", setbody("cols", {}), "Batch.cols"),
    ("Heartbeat", lambda b: b.update(cols={k.encode(): v for k, v in b["cols"].items()}), "Batch.cols"),
    ("Heartbeat", new_body([]), "Batch.body"),
    ("Heartbeat", new_body(None), "Batch.body"),
    ("Heartbeat", new_body(3), "Batch.body"),
    ("Heartbeat", new_body({"robot": 1, "keyframes": 2, "status": "ok"}), "Batch.body"),  # a plain body
    ("Heartbeat", setbody("extra", 1), "Batch.body"),
    ("Heartbeat", lambda b: b.pop("n"), "Batch.body"),
    ("Heartbeat", lambda b: b.pop("cols"), "Batch.body"),
]

# envelope-level forgeries of a batch: the same checks, and fields, as for a single envelope
ENVELOPE_CASES: list[tuple[dict[str, Any], str]] = [
    ({"team": "t1"}, "team"),
    ({"team": "bad team"}, "team"),
    ({"src": 9}, "src"),  # not one of ROBOTS
    ({"src": True}, "src"),
    ({"src": 2}, "Batch.robot"),  # the robot column says 1
    ({"seq": -1}, "seq"),
    ({"seq": INT64_MAX - 1}, "seq"),  # seq + 2 overflows int64
    ({"stamp": NAN}, "stamp"),
    ({"stamp": 1}, "stamp"),
    ({"v": SCHEMA_VERSION + 1}, "v"),
]


def valid_body(type_name: str, k: int = 3, seed: int = 0) -> dict[str, Any]:
    """A valid (writable) columnar body of ``k`` messages of robot 1 with non-empty arrays."""
    body = columnar.to_columns(burst(MESSAGE_TYPES[type_name], seed, k=k, robot=1, dims=DIMS))
    assert body is not None
    body["cols"] = {name: col.copy() if isinstance(col, np.ndarray) else list(col)
                    for name, col in body["cols"].items()}
    return body


def forge_body(type_name: str, mutate: Mutator) -> Any:
    """Apply ``mutate`` (in place, or returning a replacement body) to a valid body."""
    body = valid_body(type_name)
    out = mutate(body)
    return out.body if isinstance(out, Replace) else body


def refused_alone(type_name: str, body: dict[str, Any], seq: int = 10) -> list[bool]:
    """For each row of a well-formed body: is that message refused when sent alone?"""
    n = body["n"]
    rows: list[dict[str, Any]] = [{} for _ in range(n)]
    for name, col in body["cols"].items():
        values = col.tolist() if isinstance(col, np.ndarray) and col.ndim == 1 else list(col)
        for i in range(n):
            rows[i][name] = values[i]
    out = []
    for i, row in enumerate(rows):
        env = envelope(row, type=type_name, seq=seq + i)
        try:
            codec.decode(pack(env), team=TEAM, robots=ROBOTS)
        except MessageError:
            out.append(True)
        else:
            out.append(False)
    return out


def assert_refused(data: bytes, field: str) -> CodecError:
    """The one error decode_batch / decode_groups give for the envelope, alone or in an array."""
    items = decode_batch(data)
    assert len(items) == 1 and isinstance(items[0], CodecError), items
    assert items[0].field == field, str(items[0])
    assert field.split(".")[0] in ("Batch", "array", "ext") or field in codec.ENVELOPE_FIELDS
    (group,) = decode_groups(data)
    assert isinstance(group, CodecError) and str(group) == str(items[0])
    (inner,) = decode_batch(wrap([data]))
    assert isinstance(inner, CodecError) and str(inner) == str(items[0])
    good = Codec(TEAM, 3).encode(Heartbeat(robot=3, keyframes=1))
    mixed = decode_batch(wrap([good, data, good]))
    assert isinstance(mixed[0], Envelope) and isinstance(mixed[2], Envelope) and len(mixed) == 3
    assert isinstance(mixed[1], CodecError) and str(mixed[1]) == str(items[0])
    with pytest.raises(MessageError):
        codec.decode(data, team=TEAM, robots=ROBOTS)
    return items[0]


@pytest.mark.parametrize(("type_name", "mutate", "field"), VALUE_CASES,
                         ids=[f"{t}-{f}-{i}" for i, (t, _, f) in enumerate(VALUE_CASES)])
def test_value_forgeries_are_refused_as_their_messages_would_be(type_name: str, mutate: Mutator,
                                                                field: str) -> None:
    body = forge_body(type_name, mutate)
    assert_refused(pack(envelope(body)), field)
    assert any(refused_alone(type_name, body)), "the batch was refused but every message passes alone"


@pytest.mark.parametrize(("type_name", "mutate", "field"), FORMAT_CASES,
                         ids=[f"{t}-{f}-{i}" for i, (t, _, f) in enumerate(FORMAT_CASES)])
def test_format_forgeries_are_refused(type_name: str, mutate: Mutator, field: str) -> None:
    assert_refused(pack(envelope(forge_body(type_name, mutate))), field)


@pytest.mark.parametrize(("fields", "field"), ENVELOPE_CASES, ids=[f for _, f in ENVELOPE_CASES])
def test_envelope_forgeries_are_refused(fields: dict[str, Any], field: str) -> None:
    assert_refused(pack(envelope(valid_body("Heartbeat"), **fields)), field)


def test_unforged_bodies_are_accepted_and_seq_may_end_at_int64_max() -> None:
    for type_name in TYPES:
        body = valid_body(type_name)
        items = decode_batch(pack(envelope(body)))
        assert [type(i) for i in items] == [Envelope] * 3, items
        assert not any(refused_alone(type_name, body))
    items = decode_batch(pack(envelope(valid_body("Heartbeat"), seq=INT64_MAX - 2)))
    assert [i.seq for i in items] == [INT64_MAX - 2, INT64_MAX - 1, INT64_MAX]  # type: ignore[union-attr]


def test_single_decode_of_a_batch_names_the_type() -> None:
    data = Codec(TEAM, 1, ROBOTS).encode_many([Heartbeat(robot=1, keyframes=i) for i in range(2)])
    assert data is not None
    for decode in (codec.decode, Codec(TEAM, 2, ROBOTS).decode):
        with pytest.raises(CodecError) as err:
            decode(data)
        assert err.value.field == "type"
    # envelope problems are still reported first, as for any envelope
    with pytest.raises(CodecError) as err:
        codec.decode(pack(envelope(valid_body("Heartbeat"), team="t9")), team=TEAM)
    assert err.value.field == "team"


def _perturbations(spec: Any) -> list[Any]:
    """Interesting values for one element of a column of ``spec``."""
    if isinstance(spec, Int):
        vals = [0, -1, 1, spec.lo, spec.hi, INT64_MAX, INT64_MIN]
        vals += [spec.lo - 1] if spec.lo > INT64_MIN else []
        vals += [spec.hi + 1] if spec.hi < INT64_MAX else []
        return vals
    if isinstance(spec, Float):
        vals = [NAN, INF, -INF, 0.0, -0.0, 1e300, -1e300, spec.lo, spec.hi]
        vals += [math.nextafter(spec.lo, -INF), math.nextafter(spec.hi, INF)]
        return vals
    if isinstance(spec, Bool):
        return [True, False]
    if isinstance(spec, Str):
        return ["", "x" * spec.max_len, "x" * (spec.max_len + 1), "nope", *spec.choices[:2]]
    dt = np.dtype(spec.dtype)
    vals = [0, 1, -1, spec.lo, spec.hi]
    vals += [spec.lo - 1, spec.lo - 0.5] if spec.lo is not None else []
    vals += [spec.hi + 1, spec.hi + 0.5] if spec.hi is not None else []
    if dt.kind == "f":
        vals += [NAN, INF, -INF, float(np.finfo(dt).max), -0.0]
        return [v for v in vals if v is not None]
    info = np.iinfo(dt)
    vals += [info.min, info.max]
    return [v for v in vals if v is not None and float(v).is_integer() and info.min <= v <= info.max]


def test_batch_accepted_exactly_when_every_message_is_accepted_alone() -> None:
    """Every interesting value in every column and row position: the batch's verdict is the
    conjunction of the messages' verdicts alone, and accepted messages are the same values."""
    refused = accepted = 0
    for type_name in TYPES:
        cls = MESSAGE_TYPES[type_name]
        for name, spec in cls.SPECS.items():
            for row in (0, 2):
                for value in _perturbations(spec) + ([0, 2, 4095] if name == "robot" else []):
                    body = valid_body(type_name, seed=row)
                    col = body["cols"][name]
                    with np.errstate(all="ignore"):
                        if isinstance(col, list):
                            col[row] = value
                        elif col.ndim == 1:
                            col[row] = value
                        else:
                            col.reshape(col.shape[0], -1)[row, -1] = value
                    items = decode_batch(pack(envelope(body)))
                    alone = refused_alone(type_name, body)
                    if any(alone):
                        refused += 1
                        assert len(items) == 1 and isinstance(items[0], CodecError), (type_name, name, value)
                        assert items[0].field.startswith("Batch."), str(items[0])
                    else:
                        accepted += 1
                        assert [type(i) for i in items] == [Envelope] * 3, (type_name, name, value, items)
                        for i, env in enumerate(items):
                            assert isinstance(env, Envelope)
                            alone_env = codec.decode(pack(envelope(env.msg.to_wire(), type=type_name,
                                                                   seq=10 + i)))
                            assert env.msg == alone_env.msg and env.seq == 10 + i
    assert refused > 200 and accepted > 200


@pytest.mark.parametrize(("mutator", "field"), [
    (setv("robot", 2, row=79), "Batch.robot"),
    (setv("nonce", -1, row=40), "Batch.Ping.nonce"),
    (setcol("payload", lambda c: c.astype(np.int8)), "Batch.Ping.payload"),
    (setcol("payload", lambda c: c[:, :-1].copy()), None),  # shorter payloads: still valid
    (setcol("payload", lambda c: c[:-1].copy()), "Batch.Ping.payload"),
    (setcol("payload", lambda c: msgpack.ExtType(1, b"\x0a\x02" + bytes(8) + bytes(70_000))), "array"),
], ids=["robot", "nonce", "dtype", "shorter", "rows", "ext"])
def test_large_forged_batches_are_refused_on_both_decode_paths(mutator: Mutator, field: str | None) -> None:
    body = columnar.to_columns(large_pings())
    assert body is not None
    body["cols"] = {name: col.copy() for name, col in body["cols"].items()}
    mutator(body)
    data = pack(envelope(body))
    assert len(data) > 64 * 1024
    if field is None:
        assert [type(i) for i in decode_batch(data)] == [Envelope] * 80
        assert [type(i) for i in decode_batch(wrap([data]))] == [Envelope] * 80
        return
    assert_refused(data, field)


# ---------------------------------------------------------------------------- 4. mixed payloads
def mixed_payload(bad: bytes) -> tuple[bytes, list[Message]]:
    rng = np.random.default_rng(4)
    c = Codec(TEAM, 1, ROBOTS)
    hb = Heartbeat(robot=1, keyframes=0)
    pings = [Ping(robot=1, nonce=i, sent_ns=i, payload=rng.integers(0, 256, 1024, dtype=np.uint8))
             for i in range(4)]
    poses = PublicPoses(robot=1, round=3, keys=[5, 6], poses=np.tile(np.eye(4), (2, 1, 1)))
    hbs = [Heartbeat(robot=1, keyframes=i, status="s") for i in range(3)]
    parts = [c.encode(hb), c.encode_many(pings), bad, c.encode(poses), c.encode_many(hbs)]
    return wrap(parts), [hb, *pings, poses, *hbs]  # type: ignore[list-item]


@pytest.mark.parametrize(("bad", "field"), [
    (pack(envelope(forge_body("Heartbeat", setv("robot", 2)))), "Batch.robot"),
    (pack(envelope(forge_body("GncWeights", setv("weights", NAN)))), "Batch.GncWeights.weights"),
    (pack(envelope(forge_body("Heartbeat", setbody("n", 1)))), "Batch.n"),
    (pack(envelope(valid_body("Heartbeat"), team="t1")), "team"),
    # a malformed array ext inside the batch: msgpack fails, the slow path blames only this envelope
    (pack(envelope(forge_body("Ping", setcol("payload", lambda c: msgpack.ExtType(1, b"\x63\x02" + bytes(8)))))),
     "array"),
    (pack(envelope(forge_body("Ping", setcol("payload", lambda c: msgpack.ExtType(5, b""))))), "ext"),
], ids=["robot", "nan", "n", "team", "array-ext", "ext-code"])
def test_mixed_payload_decodes_each_envelope_on_its_own(bad: bytes, field: str) -> None:
    data, msgs = mixed_payload(bad)
    items = decode_batch(data)
    kinds = ["E"] * 5 + ["X"] + ["E"] * 4
    assert "".join("E" if isinstance(i, Envelope) else "X" for i in items) == "".join(kinds), items
    assert isinstance(items[5], CodecError) and items[5].field == field
    envs = [i for i in items if isinstance(i, Envelope)]
    assert [e.msg for e in envs] == msgs
    assert [e.seq for e in envs] == list(range(9))
    assert all(e.src == 1 and e.team == TEAM for e in envs)
    assert envs[1].stamp == envs[4].stamp  # one stamp per columnar envelope
    groups = decode_groups(data)
    assert [type(g).__name__ for g in groups] == ["Envelope", "Group", "CodecError", "Envelope", "Group"]
    assert groups[1].seq == 1 and groups[1].msgs == msgs[1:5]  # type: ignore[union-attr]
    assert groups[4].seq == 6 and groups[4].msgs == msgs[6:]  # type: ignore[union-attr]
    assert expand(groups) == flat(items)


def test_payload_of_only_columnar_batches() -> None:
    c = Codec(TEAM, 3, ROBOTS)
    parts, msgs = [], []
    for j, type_name in enumerate(TYPES):
        run = burst(MESSAGE_TYPES[type_name], seed=j, k=2 + j % 3, robot=3, dims=DIMS)
        parts.append(c.encode_many(run))
        msgs.extend(run)
    data = wrap(parts)  # type: ignore[arg-type]
    items = decode_batch(data)
    assert [i.msg for i in items] == msgs  # type: ignore[union-attr]
    assert [i.seq for i in items] == list(range(len(msgs)))  # type: ignore[union-attr]
    groups = decode_groups(data)
    assert len(groups) == len(TYPES) and all(isinstance(g, Group) for g in groups)


# ---------------------------------------------------------------------------- 5. the bus
def ping_burst(robot: int, k: int, size: int = 16) -> list[Message]:
    rng = np.random.default_rng(robot * 100 + k)
    return [Ping(robot=robot, nonce=i, sent_ns=i, payload=rng.integers(0, 256, size, dtype=np.uint8))
            for i in range(k)]


async def test_bus_accepts_a_columnar_batch_on_the_senders_key() -> None:
    bus = BusBase(TEAM, 1, ROBOTS)
    msgs = ping_burst(0, 7)
    payload = Codec(TEAM, 0, ROBOTS).encode_many(msgs)
    assert payload is not None
    got = bus.accept_batch(bus.key(keys.PING, 0), payload)
    assert got == msgs
    c = bus.counters
    assert c.received["diag/ping"].messages == 7 and c.received["diag/ping"].bytes == len(payload)
    assert c.dropped == {}
    # the same payload inside a msgpack array, and in a mixed array: bytes still add up exactly
    wrapped = wrap([payload])
    assert bus.accept_batch(bus.key(keys.PING, 0), wrapped) == msgs
    assert c.received["diag/ping"].messages == 14
    assert c.received["diag/ping"].bytes == len(payload) + len(wrapped)


async def test_bus_drops_a_columnar_batch_on_another_robots_key_as_a_whole() -> None:
    bus = BusBase(TEAM, 1, ROBOTS)
    payload = Codec(TEAM, 0, ROBOTS).encode_many(ping_burst(0, 5))
    assert payload is not None
    assert bus.accept_batch(bus.key(keys.PING, 1), payload) == []
    assert bus.counters.received == {}
    assert bus.counters.dropped == {"key": 1}
    # not from the owner (query requests): accepted
    assert len(bus.accept_batch(bus.key(keys.PING, 1), payload, from_owner=False)) == 5
    # a foreign team's key, an unknown sender, a forged column
    assert bus.accept_batch(f"kmp/t9/r0/{keys.PING}", payload) == []
    assert bus.accept_batch(bus.key(keys.PING, 5), Codec(TEAM, 5).encode_many(ping_burst(5, 3))) == []
    forged = pack(envelope(forge_body("Heartbeat", setv("keyframes", -1))))
    assert bus.accept_batch(bus.key(keys.HEARTBEAT, 1), forged) == []
    assert bus.counters.dropped == {"key": 1, "team": 1, "src": 1, "invalid": 1}


async def test_bus_counts_shares_of_a_partly_accepted_payload() -> None:
    bus = BusBase(TEAM, 1, ROBOTS)
    good = Codec(TEAM, 0, ROBOTS).encode_many(ping_burst(0, 4))
    bad = pack(envelope(forge_body("Ping", setv("robot", 2)), src=0))  # robot column says 1 and 2
    single = Codec(TEAM, 0, ROBOTS).encode(ping_burst(0, 1)[0])
    data = wrap([good, bad, single])  # type: ignore[list-item]
    got = bus.accept_batch(bus.key(keys.PING, 0), data)
    assert len(got) == 5
    # the refused batch counts as one message of the payload: 6 messages, 4 + 1 accepted
    want = share_range(len(data), 6, 0, 4) + share(len(data), 6, 5)
    assert bus.counters.received["diag/ping"].messages == 5
    assert bus.counters.received["diag/ping"].bytes == want
    assert bus.counters.dropped == {"invalid": 1}


async def test_subscription_push_queues_the_messages_of_a_columnar_batch() -> None:
    bus = BusBase(TEAM, 1, ROBOTS)
    msgs = ping_burst(0, 5)
    payload = Codec(TEAM, 0, ROBOTS).encode_many(msgs)
    sub = Subscription(bus, keys.topic_all(TEAM, keys.PING), maxsize=3)
    sub.push((bus.key(keys.PING, 0), payload))
    assert sub.pending() == 3
    assert [await sub.recv(timeout=1) for _ in range(3)] == msgs[:3]
    assert bus.counters.dropped == {"queue_full": 2}
    assert bus.counters.received["diag/ping"].messages == 5  # counted on arrival
    sub.push((bus.key(keys.PING, 2), payload))  # wrong key: nothing queued
    assert sub.pending() == 0 and bus.counters.dropped["key"] == 1
    sub.close()


def test_share_range_sums_shares() -> None:
    rng = np.random.default_rng(17)
    for _ in range(3000):
        n = int(rng.integers(1, 40))
        nbytes = int(rng.integers(0, 5000))
        i = int(rng.integers(0, n))
        k = int(rng.integers(0, n - i + 1))
        assert share_range(nbytes, n, i, k) == sum(share(nbytes, n, j) for j in range(i, i + k))
    for nbytes in range(0, 30):
        for n in range(1, 9):
            assert share_range(nbytes, n, 0, n) == nbytes
            assert sum(share(nbytes, n, j) for j in range(n)) == nbytes


# ---------------------------------------------------------------------------- 6. fuzzing
def _seed_payloads() -> list[bytes]:
    c = Codec(TEAM, 1, ROBOTS)
    rng = np.random.default_rng(8)
    pings = [Ping(robot=1, nonce=i, sent_ns=7 * i, payload=rng.integers(0, 256, 1024, dtype=np.uint8))
             for i in range(3)]
    out = [c.encode_many(pings)]
    for j, name in enumerate(["Heartbeat", "PublicPoses", "ObjectUpdate", "PgoStatus", "PgoCommand",
                              "LoopClosureReply", "MapDelta", "GncWeights", "KeyframeDescriptor"]):
        out.append(c.encode_many(burst(MESSAGE_TYPES[name], seed=j, k=2 + j % 3, robot=1,
                                       dims={s: 1 + (j % 2) for s in SYMBOLS})))
    hb = c.encode(Heartbeat(robot=1, keyframes=3))
    out.append(wrap([out[1], hb, out[3]]))  # type: ignore[list-item]
    out.append(wrap([hb, out[0]]))  # type: ignore[list-item]
    assert all(isinstance(d, bytes) for d in out)
    return out  # type: ignore[return-value]


SEEDS = _seed_payloads()


def mutate(data: bytes, rng: np.random.Generator, focus: int | None = None) -> bytes:
    """Byte-level mutations (as in test_codec): bit flips, bytes, truncation, junk, splices;
    at positions below ``focus`` when given (where the envelope and column headers are)."""
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        op = int(rng.integers(6))
        i = int(rng.integers(min(len(b), focus or len(b)))) if b else 0
        if op == 0 and b:
            b[i] ^= 1 << int(rng.integers(8))
        elif op == 1 and b:
            b[i] = int(rng.integers(256))
        elif op == 2:
            del b[i:]
        elif op == 3:
            b[i:i] = rng.bytes(int(rng.integers(1, 9)))
        elif op == 4 and b:
            b[i] = int(rng.choice([0x00, 0x01, 0x02, 0x7F, 0x80, 0x90, 0xC0, 0xC1, 0xC2, 0xC3, 0xC7, 0xD4,
                                   0xDB, 0xDC, 0xDD, 0xDF, 0xFF]))
        else:
            other = SEEDS[int(rng.integers(len(SEEDS)))]
            j = int(rng.integers(len(other)))
            b = b[:i] + bytearray(other[j:])
    return bytes(b)


def check_payload(data: bytes) -> int:
    """The fuzz oracle for decode_batch and decode_groups; returns the number of accepted messages."""
    try:
        items = decode_batch(data)
    except MessageError:
        with pytest.raises(MessageError):
            decode_groups(data)
        return 0
    groups = decode_groups(data)
    assert expand(groups) == flat(items)
    for g in groups:
        assert isinstance(g, Envelope | Group | MessageError)
        if isinstance(g, Group):
            assert len(g.msgs) >= columnar.MIN_COLUMNAR and g.src in ROBOTS and g.team == TEAM
    for item in items:
        assert isinstance(item, Envelope | MessageError)
        if isinstance(item, Envelope):
            assert_valid(item)
    return sum(isinstance(i, Envelope) for i in items)


def test_seed_payloads_are_valid() -> None:
    for data in SEEDS:
        items = decode_batch(data)
        assert items and all(isinstance(i, Envelope) for i in items)
        check_payload(data)


def test_fuzz_mutated_columnar_payloads() -> None:
    """8,000 byte-level mutations of columnar batch payloads: only MessageError, and anything
    accepted is a valid message."""
    rng = np.random.default_rng(2024)
    n, valid, refused = 8000, 0, 0
    for _ in range(n):
        got = check_payload(mutate(SEEDS[int(rng.integers(len(SEEDS)))], rng))
        valid += got > 0
        refused += got == 0
    assert valid > 200 and refused > 2000  # both outcomes are exercised


def test_fuzz_mutated_large_columnar_payloads() -> None:
    """1,500 mutations of a > 64 KiB Ping batch (the largemsg decode path), mostly near the headers."""
    c = Codec(TEAM, 1, ROBOTS)
    data = c.encode_many(large_pings())
    assert data is not None
    rng = np.random.default_rng(77)
    valid = refused = 0
    for j in range(1500):
        got = check_payload(mutate(data, rng, focus=None if j % 4 == 0 else 2048))
        valid += got > 0
        refused += got == 0
    assert valid > 50 and refused > 250


FUZZ = settings(max_examples=400, deadline=None, derandomize=True, database=None,
                suppress_health_check=list(HealthCheck))
_scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-(2**63), 2**64 - 1), st.floats(), st.text(max_size=8),
    st.binary(max_size=16),
)
_values = st.recursive(_scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=4)), max_leaves=10)
_dtypes = st.sampled_from(list(wire._DTYPES.values()))
_arrays = st.builds(
    lambda dt, shape, seed: np.random.default_rng(seed).integers(0, 256, int(np.prod(shape)) * dt.itemsize,
                                                               dtype=np.uint8).view(dt).reshape(shape)
    if dt.kind != "b" else np.random.default_rng(seed).integers(0, 2, shape).astype(bool),
    _dtypes, st.lists(st.integers(0, 5), max_size=4).map(tuple), st.integers(0, 2**32))


@FUZZ
@given(st.sampled_from(TYPES), st.integers(0, 2**32), st.data())
def test_fuzz_structured_column_mutations(type_name: str, seed: int, data: st.DataObject) -> None:
    """Replace (or drop) one column, body field or column element by an arbitrary value or array."""
    body = valid_body(type_name, seed=seed % 7)
    where = data.draw(st.sampled_from(["col", "col", "elem", "body"]))
    target = body if where == "body" else body["cols"]
    name = data.draw(st.sampled_from(sorted(target)))
    value = data.draw(st.one_of(_values, _arrays))
    if where == "elem" and isinstance(target[name], np.ndarray) and not isinstance(value, list | dict):
        try:
            with np.errstate(all="ignore"):
                target[name].reshape(-1)[0] = value
        except (TypeError, ValueError, OverflowError, IndexError):
            return
    elif where == "elem" and isinstance(target[name], list):
        target[name][0] = value
    elif data.draw(st.booleans()) and where != "elem":
        del target[name]
    else:
        target[name] = value
    check_payload(pack(envelope(body)))
