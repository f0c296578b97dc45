"""Compressed envelopes (msgpack ext type 2, kimera_multi_py.comms.wire.zipped): round trips alone
and inside batches, and corrupt ones refused (MessageError), never a crash nor a bomb."""

from __future__ import annotations

import random
import struct

import msgpack
import numpy as np
import pytest

from kimera_multi_py.comms import compression
from kimera_multi_py.comms.codec import Codec, batch_header, decode, decode_batch
from kimera_multi_py.comms.messages import MESSAGE_TYPES, ZIPPED_TYPES
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.closures import LoopClosuresAck
from kimera_multi_py.comms.messages.maps import ObjectUpdate
from kimera_multi_py.comms.messages.pgo import GncWeights, PgoCommand, PgoStatus, PublicPoses
from kimera_multi_py.comms.wire import EXT_ZIPPED, SCHEMA_DICT, zipped
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.posegraph import robot_key
from tests.support.fuzz import mutate
from tests.support.samples import random_message


def _is_zipped(data: bytes) -> bool:
    obj = msgpack.unpackb(data, raw=False, ext_hook=lambda c, d: msgpack.ExtType(c, d))
    return isinstance(obj, msgpack.ExtType) and obj.code == EXT_ZIPPED


def _tables() -> list[Message]:
    """Messages as the team sends them: keys in runs, binary weights, sparse class posteriors."""
    n = 80
    probs = np.zeros((n, 30), np.float32)
    probs[np.arange(n), np.arange(n) % 30] = 1.0
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = np.arange(3 * n).reshape(n, 3) * 0.25
    return [
        GncWeights(robot=0, peer=1, round=7, keys_a=[robot_key(0, k) for k in range(0, 2 * n, 2)],
                   keys_b=[robot_key(1, k) for k in range(n)], weights=(np.arange(n) % 5 > 0).astype(float), mu=2.5),
        ObjectUpdate(robot=0, source=0, version=3, frame=0, ids=np.arange(n), submaps=np.arange(n) // 10,
                     classes=np.arange(n, dtype=np.int32) % 30, probs=probs, centroids=np.zeros((n, 3)) + 1.5,
                     extents=np.ones((n, 3)) * 0.5, sightings=np.full(n, 4, np.int32)),
        PublicPoses(robot=0, round=3, keys=[robot_key(0, k) for k in range(n)], poses=poses),
    ]



def _both(tx: Codec, msg: Message) -> tuple[bytes, bytes]:
    """``msg`` encoded by ``tx`` as it travels (compressed where that pays) and plain."""
    data = tx.encode(msg)
    tx.compress = False
    plain = tx.encode(msg)
    tx.compress = True
    return data, plain

def test_tables_travel_compressed_and_come_back_equal() -> None:
    tx, rx = Codec("t0", 0, range(3)), Codec("t0", 1, range(3))
    for msg in _tables():
        data, plain = _both(tx, msg)
        assert _is_zipped(data) and not _is_zipped(plain) and len(data) < 0.6 * len(plain)
        assert rx.decode(data).msg == msg == rx.decode(plain).msg
    # a columnar batch compresses too, and compressed envelopes sit in a batch payload like any other
    batch = tx.encode_many(_tables()[:1] * 3)
    assert batch is not None and _is_zipped(batch)
    payload = batch_header(2) + batch + tx.encode(_tables()[1])
    got = [e.msg for e in decode_batch(payload, team="t0")]  # type: ignore[union-attr]
    assert got == _tables()[:1] * 3 + [_tables()[1]]


@pytest.mark.parametrize("seed", range(3))
def test_every_type_round_trips_whatever_the_codec_chose(seed: int) -> None:
    rng = np.random.default_rng(seed)
    tx = Codec("t0", 0, range(3))
    for cls in MESSAGE_TYPES.values():
        msg = random_message(cls, rng, robot=0, max_len=40)
        data = tx.encode(msg)
        assert _is_zipped(data) <= (cls in ZIPPED_TYPES)
        assert decode(data, team="t0").msg == msg


def _ext(payload: bytes) -> bytes:
    return msgpack.packb(msgpack.ExtType(EXT_ZIPPED, payload))


def test_corrupt_compressed_envelopes_are_refused() -> None:
    inner = Codec("t0", 0, range(3)).encode(_tables()[0])
    z = compression.compress(inner)
    head = struct.Struct("<BI")
    bad = {
        "truncated": _ext(b"\x02"),
        "unknown compressor": _ext(head.pack(9, len(inner)) + z),
        "stated size too small": _ext(head.pack(compression.DEFAULT, len(inner) - 1) + z),
        "stated size too large": _ext(head.pack(compression.DEFAULT, len(inner) + 1) + z),
        "a bomb": _ext(head.pack(compression.DEFAULT, 2**31) + compression.compress(bytes(2**20))),
        "nested": zipped(_ext(head.pack(compression.DEFAULT, len(inner)) + z) + bytes(300)),
        "nested exactly": _ext(head.pack(compression.DEFAULT, len(_ext(head.pack(compression.DEFAULT, len(inner)) + z)))
                               + compression.compress(_ext(head.pack(compression.DEFAULT, len(inner)) + z))),
        "not msgpack inside": _ext(head.pack(compression.DEFAULT, 4) + compression.compress(b"\xc1\xc1\xc1\xc1")),
    }
    for what, data in bad.items():
        with pytest.raises(MessageError):
            decode(data, team="t0")
        (item,) = decode_batch(data, team="t0")
        assert isinstance(item, MessageError), what


def test_small_envelopes_shrink_with_the_schema_dictionary() -> None:
    """A status, a command, an ack: mostly field names, which the dictionary both ends hold."""
    tx, rx = Codec("office", 1, range(3)), Codec("office", 0, range(3))
    for msg in _small():
        data, plain = _both(tx, msg)
        obj = msgpack.unpackb(data, ext_hook=lambda c, d: msgpack.ExtType(c, d))
        assert obj.data[0] == compression.DEFLATE_DICT and len(data) < 0.7 * len(plain)
        assert rx.decode(data).msg == msg
    # without the dictionary the same bytes do not inflate to the envelope
    z = compression.compress(plain, compression.DEFLATE_DICT, zdict=SCHEMA_DICT)
    with pytest.raises(MessageError):
        assert compression.decompress(z, compression.DEFLATE_DICT, len(plain), "test") == plain


def _small() -> list[Message]:
    return [PgoStatus(robot=1, round=3_000_017, ready=False, cost=123.456789, rel_change=0.00123),
            PgoCommand(robot=1, round=3_000_020, command="stop", active=np.zeros(0, np.int64)),
            LoopClosuresAck(robot=1, peer=0, batch=12)]


def test_fuzzed_compressed_envelopes_are_refused_or_whole_never_crash() -> None:
    tx = Codec("t0", 0, range(3))
    seeds = [tx.encode(m) for m in _tables()] + [Codec("t0", 1, range(3)).encode(m) for m in _small()]
    assert all(_is_zipped(d) for d in seeds)
    rng = random.Random(0)
    refused = whole = 0
    for i in range(3000):
        data = mutate(seeds[i % len(seeds)], rng, seeds)
        try:
            env = decode(data, team="t0")
        except MessageError:
            refused += 1
            continue
        assert isinstance(env.msg, Message)
        whole += 1
    assert refused > 2000 and refused + whole == 3000
