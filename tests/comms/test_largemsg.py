"""largemsg: ``pack`` is byte-identical to ``wire._packb``; ``unpack`` returns what
``msgpack.unpackb(..., ext_hook=wire._ext_hook)`` returns (arrays as read-only views into the
message), or None, or the very MessageError msgpack's hook raises — whatever the bytes."""

from __future__ import annotations

import math
import random
import re
import struct
import time
from collections.abc import Iterator
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from kimera_multi_py.comms import codec, largemsg, wire
from kimera_multi_py.comms.codec import Codec, CodecError
from kimera_multi_py.comms.messages import MESSAGE_TYPES, SCHEMA_VERSION
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.team import Ping
from kimera_multi_py.core.errors import MessageError
from tests.support.samples import all_random_messages, random_message

DTYPES = [wire._DTYPES[c] for c in sorted(wire._DTYPES)]
LENGTHS = [0, 1, 15, 16, 31, 32, 127, 128, 255, 256, 65535, 65536]
INTS = [0, 1, 127, 128, 255, 256, 65535, 65536, 2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**63 - 1, 2**63,
        2**64 - 1, -1, -31, -32, -33, -127, -128, -129, -(2**15) + 1, -(2**15), -(2**15) - 1,
        -(2**31) + 1, -(2**31), -(2**31) - 1, -(2**63) + 1, -(2**63)]
BAD_INTS = [2**64, 2**100, -(2**63) - 1, -(2**80)]
FIXEXT = [1, 2, 4, 8, 16]
SETTINGS = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def ref_unpack(data: bytes) -> Any:
    return msgpack.unpackb(data, raw=False, ext_hook=wire._ext_hook, strict_map_key=True)


def same(a: Any, b: Any) -> bool:
    """Exact equality: same types, floats bit for bit, arrays by dtype, shape and bytes."""
    if a.__class__ is not b.__class__:
        return False
    if isinstance(a, dict):
        return list(a) == list(b) and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float):
        return struct.pack(">d", a) == struct.pack(">d", b)
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    return bool(a == b)


def arrays_in(obj: Any) -> Iterator[np.ndarray]:
    if isinstance(obj, np.ndarray):
        yield obj
    elif isinstance(obj, dict):
        for v in obj.values():
            yield from arrays_in(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from arrays_in(v)


def is_view_of(a: np.ndarray, data: bytes) -> bool:
    base: Any = a
    while isinstance(base, np.ndarray):
        base = base.base
    return base is data and (not a.size or np.shares_memory(a, np.frombuffer(data, np.uint8)))


def check_same_pack(obj: Any) -> bytes | None:
    """pack(obj) and wire._packb(obj): the same bytes, or the same exception."""
    try:
        want = wire._packb(obj)
    except Exception as exc:  # noqa: BLE001 - compared below
        with pytest.raises(type(exc)) as info:
            largemsg.pack(obj)
        assert str(info.value) == str(exc)
        return None
    got = largemsg.pack(obj)
    assert got == want
    return got


def check_unpack(data: bytes, *, supported: bool = False) -> Any:
    """The fuzz oracle: None, or msgpack's value (arrays as read-only views), or msgpack's
    MessageError; and the strict parser raises only its documented 'None' exceptions."""
    try:
        want: Any = ref_unpack(data)
        want_exc: Exception | None = None
    except Exception as exc:  # noqa: BLE001 - compared below
        want, want_exc = None, exc
    try:
        got = largemsg._unpack(data)
    except (largemsg._Unsupported, IndexError, struct.error, UnicodeDecodeError):
        assert not supported, data[:64]
        assert largemsg.unpack(data) is None
        return None
    except MessageError as exc:
        # raised only where msgpack's hook raises the same error
        assert isinstance(want_exc, MessageError) and str(exc) == str(want_exc)
        with pytest.raises(MessageError):
            largemsg.unpack(data)
        return None
    assert want_exc is None, (want_exc, data[:64])
    assert same(got, want)
    for a in arrays_in(got):
        assert is_view_of(a, data) and not a.flags.writeable
    return got


# ---------------------------------------------------------------------------- envelopes
def envelope(msg: Message, *, wire: bool, seq: int = 7, stamp: float = 1.7e9) -> dict[str, Any]:
    """The dict Codec.encode packs (``wire``: arrays already as codec.ext_of values)."""
    return {"v": SCHEMA_VERSION, "type": msg.TYPE, "team": "t0", "src": msg.robot, "seq": seq, "stamp": stamp,
            "body": msg._wire_body(codec.ext_of) if wire else msg.to_wire()}


def sample_messages() -> list[Message]:
    rng = np.random.default_rng(5)
    msgs = all_random_messages(seed=1, robot=1) + all_random_messages(seed=2, robot=3)
    msgs += [random_message(cls, rng, robot=2, max_len=40) for cls in MESSAGE_TYPES.values()]
    msgs += [random_message(cls, rng, robot=0, max_len=0) for cls in MESSAGE_TYPES.values()]
    for n in (0, 1, 10, 1024, 8192, 65535, 100_000):
        msgs.append(Ping(robot=1, nonce=n, sent_ns=time.monotonic_ns(), echo=bool(n % 2),
                         payload=rng.integers(0, 256, n, dtype=np.uint8)))
    return msgs


MESSAGES = sample_messages()
ENVELOPES = [wire._packb(envelope(m, wire=True, seq=i * 977)) for i, m in enumerate(MESSAGES)]


@pytest.mark.parametrize("msg", MESSAGES, ids=lambda m: f"{m.TYPE}")
def test_pack_envelopes_byte_identical(msg: Message) -> None:
    want = wire._packb(envelope(msg, wire=True))
    assert largemsg.pack(envelope(msg, wire=False)) == want
    assert largemsg.pack(envelope(msg, wire=True)) == want
    assert wire._packb(envelope(msg, wire=False)) == want


def test_pack_matches_codec_encode() -> None:
    c = Codec("t0", 1)
    c.compress = False  # largemsg packs the plain envelope (the codec may compress it after)
    for msg in MESSAGES:
        if msg.robot != 1:
            continue
        data = c.encode(msg)
        env = msgpack.unpackb(data)  # the seq and stamp Codec chose
        assert largemsg.pack(envelope(msg, wire=False, seq=env["seq"], stamp=env["stamp"])) == data


@pytest.mark.parametrize("data", ENVELOPES, ids=lambda d: f"{len(d)}B")
def test_unpack_envelopes(data: bytes) -> None:
    got = check_unpack(data, supported=True)
    env = codec._check_envelope(got, "t0", None)
    assert env == codec.decode(data)


def test_unpack_arrays_are_read_only_views() -> None:
    a = np.arange(24, dtype="<f4").reshape(2, 3, 4)
    data = largemsg.pack({"a": a, "b": np.ones(100_000, np.uint8), "c": np.array(2.0)})
    got = largemsg.unpack(data)
    assert got is not None
    for arr in got.values():
        assert is_view_of(arr, data)
        assert not arr.flags.writeable
        with pytest.raises(ValueError):
            arr[...] = 0
    assert got["a"].shape == (2, 3, 4) and got["c"].shape == ()
    assert np.array_equal(got["a"], a)


# ---------------------------------------------------------------------------- pack boundaries
@pytest.mark.parametrize("v", INTS + [-v for v in INTS if v > 0 and v <= 2**63])
def test_pack_ints(v: int) -> None:
    data = check_same_pack({"x": v, "l": [v, v]})
    assert data is not None
    check_unpack(data, supported=True)


@pytest.mark.parametrize("v", BAD_INTS)
def test_pack_out_of_range_int_raises_codec_error(v: int) -> None:
    with pytest.raises(CodecError, match="^body: cannot encode int"):
        largemsg.pack({"x": v})
    check_same_pack({"x": v})


@pytest.mark.parametrize("v", [0.0, -0.0, 1.5, -1e300, math.inf, -math.inf, math.nan, 5e-324])
def test_pack_floats(v: float) -> None:
    data = check_same_pack({"x": v, "y": [v], "z": np.float64(v)})
    assert data is not None
    check_unpack(data, supported=True)


@pytest.mark.parametrize("n", LENGTHS)
def test_pack_lengths(n: int) -> None:
    for obj in ({"s": "a" * n}, {"s": "é" * (n // 2)}, {"b": b"\x01" * n}, {"l": list(range(n))},
                {"m": {f"k{i}": i for i in range(n)}}, "x" * n, b"y" * n, [None] * n, (True,) * n):
        data = check_same_pack(obj)
        assert data is not None
        if isinstance(obj, dict):
            got = check_unpack(data, supported=n <= largemsg._MAX_ITEMS or "s" in obj or "b" in obj)
            if n > largemsg._MAX_ITEMS and ("l" in obj or "m" in obj):
                assert got is None  # beyond the parser's limits: msgpack's job
    keys = {"k" * n: n, "é" * (n // 2): None}  # str keys: fixstr, str 8, str 16 (str 32: fallback)
    assert check_unpack(check_same_pack(keys) or b"", supported=n < 65536) == (None if n >= 65536 else keys)


@pytest.mark.parametrize("n", [0, 1, 2, 3, 4, 5, 8, 15, 16, 17, 255, 256, 65535, 65536])
@pytest.mark.parametrize("code", [0, 1, 5, 127])
def test_pack_ext(n: int, code: int) -> None:
    ext = msgpack.ExtType(code, bytes(range(256)) * (n // 256) + bytes(range(n % 256)))
    data = check_same_pack({"e": ext, "l": [ext]})
    assert data is not None
    if n in FIXEXT:
        assert data[3] == 0xD4 + FIXEXT.index(n)
    if code != 1:
        assert largemsg.unpack(data) is None  # unknown ext type: msgpack's hook raises
    else:
        check_unpack(data)


def shapes_for(dt: np.dtype) -> list[tuple[int, ...]]:
    return [(), (0,), (1,), (5,), (2, 0), (2, 3, 4), (0, 3, 1), (1, 1, 1, 1, 1, 1, 1, 1),
            (100_000 // dt.itemsize,)]


@pytest.mark.parametrize("dt", DTYPES, ids=str)
def test_pack_arrays_every_dtype(dt: np.dtype) -> None:
    rng = np.random.default_rng(0)
    for shape in shapes_for(dt):
        a = (rng.integers(0, 2, shape) if dt.kind == "b" else rng.integers(0, 100, shape)).astype(dt)
        for obj in ({"a": a}, {"a": codec.ext_of(a)}, {"l": [a, a]}):
            data = check_same_pack(obj)
            assert data is not None
            check_unpack(data, supported=True)
        assert largemsg.pack(a) == wire._packb(a)
        assert msgpack.unpackb(largemsg.pack(a)) == codec.ext_of(a)


@pytest.mark.parametrize("n", range(0, 20))
def test_pack_small_arrays_hit_every_ext_size(n: int) -> None:
    # ext data = 2 + 4 * ndim + nbytes: 0-d and 1-d arrays of 0..19 bytes cover fixext 4/8/16
    for a in (np.arange(n, dtype="u1"), np.zeros(n // 2, "<u2"), np.array(n, "<i2"), np.array(n, "u1")):
        data = check_same_pack({"a": a})
        assert data is not None
        check_unpack(data, supported=True)


class SubArray(np.ndarray):
    pass


@pytest.mark.parametrize("a", [
    np.arange(10.0)[::2],  # not contiguous
    np.asfortranarray(np.arange(6, dtype="<i4").reshape(2, 3)),
    np.arange(5, dtype=">i4"),  # big-endian
    np.arange(4, dtype="<f8").view(SubArray),
    np.zeros((1,) * 9),  # too many dimensions
    np.zeros(3, np.float16),  # unsupported dtype
    np.zeros(3, np.complex128),
    np.array(["a"]),
], ids=lambda a: f"{a.dtype}{a.shape}")
def test_pack_other_arrays_as_codec(a: np.ndarray) -> None:
    check_same_pack({"a": a})
    check_same_pack([a])


@pytest.mark.parametrize("obj", [
    {"x": object()}, {"x": np.int64(3)}, {"x": np.bool_(True)}, {"x": {1, 2}}, {"x": 1j},
    {"x": memoryview(b"abc")}, {"x": bytearray(b"abc")}, {"x": msgpack.Timestamp(1, 2)},
    {"x": "\ud800"}, {1: 2, None: 3, 2.5: [b"x"]}, {"x": (1, (2, [3]))}, {"x": True, "y": False},
    {"x": None}, [[[[[[]]]]]] * 3,
], ids=lambda o: re.sub(r" at 0x[0-9a-f]+", "", repr(o)))  # ids must not hold addresses (pytest-xdist)
def test_pack_odd_objects_as_codec(obj: Any) -> None:
    check_same_pack(obj)


def test_pack_subclasses_as_codec() -> None:
    import enum

    class E(enum.IntEnum):
        A = 300

    class S(str):
        def __str__(self) -> str:
            return "not me"

    class F(float):
        pass

    class D(dict):  # type: ignore[type-arg]
        pass

    check_same_pack({"e": E.A, "s": S("hello"), "f": F(2.5), "d": D(a=1), "t": (1, 2)})
    check_same_pack({"big": type("I", (int,), {})(2**70)})


def test_pack_deep_nesting_as_codec() -> None:
    for depth in (10, 70, 900, 1100):
        obj: Any = {}
        for _ in range(depth):
            obj = {"a": [obj]}
        check_same_pack(obj)


# ---------------------------------------------------------------------------- hypothesis
ints = st.one_of(st.integers(-(2**63), 2**64 - 1), st.sampled_from(INTS))
exts = st.builds(msgpack.ExtType, st.integers(0, 127),
                 st.one_of(st.binary(max_size=20), st.sampled_from(FIXEXT).map(bytes)))
nd = st.sampled_from(DTYPES).flatmap(
    lambda dt: hnp.arrays(dt, hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=4)))
scalars = st.one_of(st.none(), st.booleans(), ints, st.floats(), st.floats(width=32), st.text(max_size=40),
                    st.binary(max_size=40), exts, nd)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=6), st.tuples(inner, inner),
                            st.dictionaries(st.text(max_size=6), inner, max_size=6)),
    max_leaves=24,
)
# what unpack must accept: str keys, nesting <= 4, ext values only arrays
flat = st.one_of(st.none(), st.booleans(), ints, st.floats(), st.text(max_size=40), st.binary(max_size=40), nd)
supported = st.dictionaries(st.text(max_size=6), st.one_of(
    flat, st.lists(flat, max_size=4), st.dictionaries(st.text(max_size=6), st.one_of(
        flat, st.lists(st.lists(flat, max_size=3), max_size=3)), max_size=4)), max_size=8)


@SETTINGS
@given(values)
def test_pack_hypothesis(obj: Any) -> None:
    data = check_same_pack(obj)
    if data is not None and isinstance(obj, dict):
        check_unpack(data)


@SETTINGS
@given(supported)
def test_unpack_hypothesis_supported(obj: dict[str, Any]) -> None:
    data = check_same_pack(obj)
    assert data is not None
    check_unpack(data, supported=True)


@SETTINGS
@given(st.one_of(st.binary(max_size=200),
                 st.tuples(st.sampled_from([b"\x81", b"\x82\xa1a", b"\x81\xa1a", b"\xde\x00\x01",
                                            b"\x81\xa1a\xc7", b"\x81\xa1a\xd6\x01"]),
                           st.binary(max_size=60)).map(b"".join)))
def test_unpack_hypothesis_bytes(data: bytes) -> None:
    check_unpack(data)


# ---------------------------------------------------------------------------- fallback and errors
def ext1(payload: bytes) -> msgpack.ExtType:
    return msgpack.ExtType(1, payload)


@pytest.mark.parametrize("data", [
    b"", b"\x90", b"\x01", b"\xc0", msgpack.packb([{"a": 1}]),  # not one map
    msgpack.packb({"a": 1}) + b"\x00",  # extra data
    msgpack.packb({"a": "xyz"})[:-1],  # truncated
    msgpack.packb({b"a": 1}),  # bytes key (msgpack accepts it)
    msgpack.packb({1: 1}, strict_types=False),  # int key (msgpack refuses)
    b"\x81\xa1a\xa2\xff\xfe",  # invalid UTF-8 value
    b"\x81\xa2\xc3\x28\x01",  # invalid UTF-8 key
    b"\x81\xa1a\xc1",  # reserved type byte
    msgpack.packb({"a": msgpack.ExtType(2, b"x")}),  # unknown ext type
    msgpack.packb({"a": msgpack.Timestamp(1, 0)}),  # timestamp
    msgpack.packb({"a": {"b": {"c": {"d": {"e": 1}}}}}),  # nested deeper than 4
    msgpack.packb({"a": [[[[1]]]]}),
    msgpack.packb({"a": list(range(257))}),  # more items than the parser takes
    msgpack.packb({f"k{i}": i for i in range(257)}),
    msgpack.packb({"a" * 40000: 1}),  # str 16 key: fine; str 32 key below
    b"\x81\xdb\x00\x00\x00\x01a\x01",
    b"\x81\xa1a\xdc\xff\xff",  # array 16 header with no items
    b"\xdf\xff\xff\xff\xff",  # map 32 header with no items
])
def test_unpack_falls_back(data: bytes) -> None:
    got = check_unpack(data)
    if len(data) < 30000:  # the long str 16 key is supported
        assert got is None


def test_unpack_only_bytes() -> None:
    data = ENVELOPES[0]
    assert largemsg.unpack(bytearray(data)) is None  # type: ignore[arg-type]
    assert largemsg.unpack(memoryview(data)) is None  # type: ignore[arg-type]
    assert largemsg.unpack(data) is not None


@pytest.mark.parametrize(("payload", "problem"), [
    (bytes([99, 1, 0, 0, 0, 0]), "unknown dtype code 99"),
    (bytes([1, 9]) + bytes(36), "9 dimensions"),
    (bytes([1, 1, 2, 0, 0, 0]) + bytes(8), "needs 16 bytes"),
    (bytes([10, 2, 2, 0, 0, 0, 1, 0, 0, 0]) + bytes(3), "needs 2 bytes"),
    (bytes([11, 1, 3, 0, 0, 0, 0, 1, 2]), "other than 0 and 1"),
    (bytes([11, 2, 1, 0, 0, 0, 1, 0, 0, 0, 7]), "other than 0 and 1"),
    (bytes([10]), "truncated header"),
    (bytes([10, 3, 1, 0]), "truncated shape"),
    (bytes([10, 1, 1, 0, 0, 0]), "needs 1 bytes"),
])
def test_unpack_bad_arrays_raise_like_the_hook(payload: bytes, problem: str) -> None:
    data = msgpack.packb({"v": 1, "body": {"a": ext1(payload), "z": "x" * 40}})
    with pytest.raises(CodecError, match=f"^array: .*{problem}"):
        ref_unpack(data)
    with pytest.raises(CodecError, match=f"^array: .*{problem}"):
        largemsg.unpack(data)
    check_unpack(data)
    # in document order: an earlier failure wins, a later one does not
    early = b"\x82\xa1z\xa1\xff" + msgpack.packb({"a": ext1(payload)})[1:]  # invalid UTF-8 first
    assert check_unpack(early) is None
    with pytest.raises(CodecError):
        largemsg.unpack(data[:-3])  # truncated after the array: msgpack raises the hook's error too


# ---------------------------------------------------------------------------- mutation fuzz
def fuzz_bases() -> list[bytes]:
    rng = np.random.default_rng(11)
    big = {"v": 1, "type": "X", "body": {"a": rng.integers(0, 256, 100_000, dtype=np.uint8), "b": "tail",
                                           "c": np.array([True, False]), "d": rng.random((3, 4)),
                                           "e": [1, -5, 2.5, None, b"raw"], "f": {"g": 2**40}}}
    scalars = {"i": INTS, "f": [0.5, -2.0], "s": ["", "é" * 20, "x" * 40], "b": [b"", b"\x00" * 300],
               "t": True, "n": None, "m": {"k": {"q": [1]}}}
    return [
        ENVELOPES[0], ENVELOPES[3], ENVELOPES[len(ENVELOPES) // 2],
        *(wire._packb(envelope(m, wire=True)) for m in MESSAGES if m.TYPE == "Ping"),
        largemsg.pack(big), largemsg.pack(scalars),
    ]


SPECIAL = [0x00, 0x01, 0x7F, 0x80, 0x8F, 0x90, 0xA0, 0xBF, 0xC0, 0xC1, 0xC2, 0xC4, 0xC7, 0xC8, 0xC9,
           0xCA, 0xCB, 0xCC, 0xCF, 0xD0, 0xD4, 0xD8, 0xD9, 0xDA, 0xDB, 0xDC, 0xDD, 0xDE, 0xDF, 0xE0, 0xFF]


def mutants(base: bytes, rng: random.Random, n: int) -> Iterator[bytes]:
    """Truncations, bit flips, special bytes, corrupted length fields, insertions, deletions;
    positions mostly in the structure (the first and last 200 bytes of big messages)."""
    size = len(base)
    hot = list(range(min(size, 200))) + list(range(max(200, size - 200), size))

    def pos() -> int:
        return rng.choice(hot) if rng.random() < 0.9 else rng.randrange(size)

    for _ in range(n):
        kind = rng.randrange(6)
        if kind == 0:
            yield base[:pos()]
            continue
        b = bytearray(base)
        i = pos()
        if kind == 1:
            for _ in range(rng.randint(1, 3)):
                j = pos()
                b[j] ^= 1 << rng.randrange(8)
        elif kind == 2:
            b[i] = rng.choice(SPECIAL)
        elif kind == 3:  # a length field: 1, 2 or 4 bytes of boundary or random values
            width = rng.choice((1, 2, 4))
            value = rng.choice((0, 1, 2**(8 * width) - 1, 2**(8 * width - 1), rng.randrange(2**(8 * width))))
            b[i:i + width] = value.to_bytes(width, "big")
        elif kind == 4:
            b.insert(i, rng.randrange(256))
        else:
            del b[i]
        yield bytes(b)


def test_mutation_fuzz() -> None:
    rng = random.Random(1234)
    outcomes = {"none": 0, "error": 0, "value": 0}
    count = 0
    for base in fuzz_bases():
        check_unpack(base, supported=True)
        for data in mutants(base, rng, 700):
            count += 1
            if check_unpack(data) is not None:
                outcomes["value"] += 1
            else:
                try:
                    outcomes["none" if largemsg.unpack(data) is None else "value"] += 1
                except MessageError:
                    outcomes["error"] += 1
    assert count >= 5000
    assert all(outcomes.values()), outcomes  # every kind of outcome was exercised
