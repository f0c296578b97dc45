"""Codec: envelope validation, and fuzzing: whatever the bytes, decode returns a valid
message or raises MessageError, nothing else."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kimera_multi_py.comms import codec, wire
from kimera_multi_py.comms.codec import Codec, CodecError, Envelope
from kimera_multi_py.comms.messages import MESSAGE_TYPES, SCHEMA_VERSION
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.pgo import PublicPoses
from kimera_multi_py.comms.messages.team import Heartbeat
from kimera_multi_py.core.errors import MessageError
from tests.support.samples import all_random_messages, random_message

ROBOTS = frozenset(range(4))
SEEDS = [codec.encode(m, team="t0", src=1, seq=i, stamp=1.0)
         for i, m in enumerate(all_random_messages(seed=3, robot=1))]


def _raw(msg: Message, **env: object) -> bytes:
    """Encode, then overwrite envelope fields at the msgpack level."""
    obj = msgpack.unpackb(codec.encode(msg, team="t0", src=msg.robot, seq=0, stamp=1.0),
                          raw=False, ext_hook=lambda c, d: msgpack.ExtType(c, d))
    obj.update(env)
    return msgpack.packb(obj, use_bin_type=True)


def check(data: bytes) -> Envelope | None:
    """The fuzz oracle: a valid, re-encodable message, or MessageError."""
    try:
        env = codec.decode(data, team="t0", robots=ROBOTS)
    except MessageError:
        return None
    assert isinstance(env.msg, Message)
    assert env.msg.robot == env.src and env.src in ROBOTS
    again = codec.decode(codec.encode(env.msg, team=env.team, src=env.src, seq=env.seq,
                                      stamp=env.stamp), team="t0")
    assert again.msg == env.msg
    return env


@pytest.mark.parametrize(
    ("data", "field"),
    [
        (_raw(Heartbeat(robot=1, keyframes=1), team="t1"), "team"),
        (_raw(Heartbeat(robot=1, keyframes=1), team="bad team"), "team"),
        (_raw(Heartbeat(robot=1, keyframes=1), src=9), "src"),
        (_raw(Heartbeat(robot=1, keyframes=1), src=2), "src"),  # body.robot is 1
        (_raw(Heartbeat(robot=1, keyframes=1), src=True), "src"),
        (_raw(Heartbeat(robot=1, keyframes=1), v=SCHEMA_VERSION + 1), "v"),
        (_raw(Heartbeat(robot=1, keyframes=1), v=[1]), "v"),
        (_raw(Heartbeat(robot=1, keyframes=1), type="Nope"), "type"),
        (_raw(Heartbeat(robot=1, keyframes=1), type=7), "type"),
        (_raw(Heartbeat(robot=1, keyframes=1), seq=-1), "seq"),
        (_raw(Heartbeat(robot=1, keyframes=1), stamp=math.nan), "stamp"),
        (_raw(Heartbeat(robot=1, keyframes=1), extra=1), "extra"),
        (_raw(Heartbeat(robot=1, keyframes=1), body={"robot": 1}), "Heartbeat.keyframes"),
        (_raw(Heartbeat(robot=1, keyframes=1),
              body={"robot": 1, "keyframes": 1, "status": "ok", "x": 0}), "Heartbeat.'x'"),
        (_raw(Heartbeat(robot=1, keyframes=1),
              body={"robot": 1, "keyframes": 1.0, "status": "ok"}), "Heartbeat.keyframes"),
        (SEEDS[0] + b"\x00", "payload"),
        (SEEDS[0][:-1], "payload"),
        (b"", "payload"),
        (msgpack.packb([1, 2]), "envelope"),
    ],
)
def test_envelope_violations_name_the_field(data: bytes, field: str) -> None:
    with pytest.raises(MessageError, match=f"^{field}"):
        codec.decode(data, team="t0", robots=ROBOTS)


def test_wire_types_are_strict() -> None:
    poses = PublicPoses(robot=1, round=0, keys=[1], poses=np.eye(4)[None])
    body = poses.to_wire()
    body["keys"] = np.array([1], np.int32)  # right values, wrong dtype: refused on the wire
    data = _raw(poses, body={k: wire._pack_array(v) if isinstance(v, np.ndarray) else v
                             for k, v in body.items()})
    with pytest.raises(MessageError, match=r"PublicPoses\.keys: expected dtype int64"):
        codec.decode(data)


def test_array_ext_violations() -> None:
    for blob, what in [
        (b"\x01", "truncated header"),
        (b"\x63\x01\x01\x00\x00\x00", "unknown dtype"),
        (b"\x01\x09" + b"\x00" * 36, "dimensions"),
        (b"\x03\x01\x02\x00\x00\x00" + b"\x00" * 8, "needs 16 bytes"),
        (b"\x0b\x01\x01\x00\x00\x00\x07", "boolean"),
    ]:
        with pytest.raises(CodecError, match=what):
            wire._unpack_array(blob)


def test_size_limit_and_non_bytes() -> None:
    with pytest.raises(MessageError, match="^size"):
        codec.decode(SEEDS[0], max_bytes=10)
    with pytest.raises(MessageError, match="^payload"):
        codec.decode("text")  # type: ignore[arg-type]
    big = PublicPoses(robot=0, round=0, keys=np.arange(3000), poses=np.zeros((3000, 4, 4)))
    with pytest.raises(MessageError, match="^size"):
        Codec("t0", 0, max_bytes=1000).encode(big)


def test_codec_numbers_messages_and_rejects_wrong_sender() -> None:
    c = Codec("t0", 1, robots=ROBOTS)
    seqs = [c.decode(c.encode(Heartbeat(robot=1, keyframes=k))).seq for k in range(3)]
    assert seqs == [0, 1, 2]
    with pytest.raises(MessageError, match="^src"):
        c.encode(Heartbeat(robot=2, keyframes=0))
    with pytest.raises(MessageError, match="^src: unknown robot"):
        Codec("t0", 1, robots={0, 1}).decode(Codec("t0", 3).encode(Heartbeat(robot=3, keyframes=0)))


# ---------------------------------------------------------------------------- fuzzing
FUZZ = settings(max_examples=1000, deadline=None, derandomize=True, database=None,
                suppress_health_check=list(HealthCheck))


@FUZZ
@given(st.binary(max_size=512))
def test_fuzz_random_bytes(data: bytes) -> None:
    check(data)


_scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-(2**63), 2**64 - 1), st.floats(), st.text(max_size=8),
    st.binary(max_size=16),
)
_values = st.recursive(_scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=4)),
    max_leaves=10)


@FUZZ
@given(st.sampled_from(sorted(MESSAGE_TYPES)), st.integers(0, 2**32), st.data())
def test_fuzz_structured_mutations(type_name: str, seed: int, data: st.DataObject) -> None:
    """Replace one envelope or body field by an arbitrary msgpack value (or drop it)."""
    msg = random_message(MESSAGE_TYPES[type_name], np.random.default_rng(seed), robot=1)
    obj = msgpack.unpackb(codec.encode(msg, team="t0", src=1, seq=0, stamp=1.0), raw=False,
                          ext_hook=lambda c, d: msgpack.ExtType(c, d))
    target = obj["body"] if data.draw(st.booleans()) else obj
    name = data.draw(st.sampled_from(sorted(target)))
    if data.draw(st.booleans()):
        del target[name]
    else:
        target[name] = data.draw(_values)
    check(msgpack.packb(obj, use_bin_type=True))


def _mutate(data: bytes, rng: np.random.Generator) -> bytes:
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        op = int(rng.integers(6))
        i = int(rng.integers(len(b))) if b else 0
        if op == 0 and b:  # flip a bit
            b[i] ^= 1 << int(rng.integers(8))
        elif op == 1 and b:  # random byte
            b[i] = int(rng.integers(256))
        elif op == 2:  # truncate
            del b[i:]
        elif op == 3:  # insert junk
            b[i:i] = rng.bytes(int(rng.integers(1, 9)))
        elif op == 4 and b:  # interesting byte (msgpack markers, ext, sizes)
            b[i] = int(rng.choice([0x00, 0x7F, 0x80, 0xC0, 0xC1, 0xC2, 0xC3, 0xC7, 0xD4, 0xDB,
                                   0xDD, 0xDF, 0xFF]))
        else:  # splice with another valid message
            other = SEEDS[int(rng.integers(len(SEEDS)))]
            j = int(rng.integers(len(other)))
            b = b[:i] + bytearray(other[j:])
    return bytes(b)


def test_fuzz_mutated_payloads() -> None:
    """10,000 byte-level mutations of valid messages of every type."""
    rng = np.random.default_rng(1234)
    n, valid = 10_000, 0
    for _ in range(n):
        seed = SEEDS[int(rng.integers(len(SEEDS)))]
        valid += check(_mutate(seed, rng)) is not None
    # mutations that keep a message valid exist (e.g. a flipped float bit) but are a minority
    assert 0 < valid < n // 2


# ---------------------------------------------------------------------------- batches
def _batch(parts: list[bytes]) -> bytes:
    return codec.batch_header(len(parts)) + b"".join(parts)


def test_batch_round_trip_and_single_payloads() -> None:
    c = Codec("t0", 1, ROBOTS)
    msgs = all_random_messages(seed=5, robot=1) * 2  # 24 > 15: array 16 header
    items = c.decode_batch(_batch([c.encode(m) for m in msgs]))
    assert [e.msg for e in items] == msgs  # type: ignore[union-attr]
    assert [e.seq for e in items] == list(range(len(msgs)))  # type: ignore[union-attr]
    single = c.decode_batch(c.encode(msgs[0]))
    assert len(single) == 1 and single[0].msg == msgs[0]  # type: ignore[union-attr]
    bad = c.decode_batch(b"\x81\xa1v\x01")
    assert len(bad) == 1 and isinstance(bad[0], MessageError)


def test_batch_blames_only_the_bad_envelopes() -> None:
    """Each element is validated as decode() validates it alone; the others still arrive."""
    c = Codec("t0", 1, ROBOTS)
    c.compress = False  # the plain envelope, to break an array in it
    good = [c.encode(Heartbeat(robot=1, keyframes=i)) for i in range(3)]
    foreign = Codec("t1", 1).encode(Heartbeat(robot=1, keyframes=9))
    blob = bytearray(c.encode(PublicPoses(robot=1, round=0, keys=[1], poses=np.eye(4)[None])))
    blob[blob.index(b"\x01\x03\x01\x00\x00\x00\x04\x00")] = 99  # unknown dtype code in the ext
    items = c.decode_batch(_batch([good[0], foreign, good[1], bytes(blob), good[2]]))
    assert [type(i).__name__ for i in items] == ["Envelope", "CodecError", "Envelope",
                                                 "CodecError", "Envelope"]
    assert items[1].field == "team" and items[3].field == "array"  # type: ignore[union-attr]
    for i in (1, 3):  # the same error decode() raises for the message alone
        with pytest.raises(CodecError) as alone:
            c.decode([foreign, bytes(blob)][i // 2])
        assert str(alone.value) == str(items[i])


@pytest.mark.parametrize("payload", [b"\x90", b"\x91", b"\x92\xc0", b"\x91\x81\xa1v\x01\xc0",
                                     b"\xdd\xff\xff\xff\xff", b"\x9f" + b"\xc0" * 3])
def test_malformed_batches_raise_message_error(payload: bytes) -> None:
    c = Codec("t0", 1, ROBOTS)
    try:
        items = c.decode_batch(payload)
    except MessageError:
        return
    assert all(isinstance(i, MessageError) for i in items)


def test_fuzz_mutated_batches() -> None:
    """Mutated batches: MessageError for the batch, or one valid envelope / error per element."""
    rng = np.random.default_rng(99)
    c = Codec("t0", 1, ROBOTS)
    parts = [c.encode(m) for m in all_random_messages(seed=8, robot=1)]
    for _ in range(2_000):
        k = int(rng.integers(1, len(parts) + 1))
        data = _mutate(_batch(parts[:k]), rng)
        try:
            items = codec.decode_batch(data, team="t0", robots=ROBOTS)
        except MessageError:
            continue
        for item in items:
            assert isinstance(item, Envelope | MessageError)
            if isinstance(item, Envelope):
                assert item.msg.robot == item.src and item.src in ROBOTS
