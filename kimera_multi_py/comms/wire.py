"""The array and packing layer under the codec: numpy arrays as msgpack ext type 1, compressed
envelopes as msgpack ext type 2, and one msgpack Packer per thread. Both the codec and the
large-message path build on it (docs/outputs.md describes the wire format).

    ext 1: u8 dtype code | u8 ndim | ndim x u32 little-endian dims | raw little-endian C-order bytes
    ext 2: u8 compressor (comms.compression) | u32 little-endian size | the compressed msgpack
           envelope of that size (never itself compressed)

The compressor is zstd, or for envelopes of a few dozen bytes raw deflate primed with
:data:`SCHEMA_DICT` (every message type's envelope with placeholder values, made from the message
registry, so every robot of one schema version holds the same), whichever is smaller.

A compressed envelope is a msgpack value like any other, so it stands alone as a payload or as
one element of a batch; :func:`_ext_hook` inflates it (never beyond its stated size, at most
:data:`MAX_ZIPPED_BYTES`) and reads the envelope inside.
"""

from __future__ import annotations

import math
import struct
import threading
from typing import Any

import msgpack
import numpy as np

from kimera_multi_py.comms import compression
from kimera_multi_py.core.errors import MessageError

EXT_NDARRAY = 1
EXT_ZIPPED = 2
MAX_NDIM = 8
MAX_ZIPPED_BYTES = 64 * 1024 * 1024  # the codec's message size limit
_ZHEAD = struct.Struct("<BI")

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
_NATIVE: dict[int, np.dtype] = {code: dt.newbyteorder("=") for code, dt in _DTYPES.items()}
_HEAD = struct.Struct("<BB")
_SHAPES = [struct.Struct(f"<{ndim}I") for ndim in range(MAX_NDIM + 1)]




class CodecError(MessageError):
    """A :class:`MessageError` that names the offending ``field`` (``team``, ``src``, ...)."""

    def __init__(self, field: str, problem: str) -> None:
        self.field = field
        self.problem = problem
        super().__init__(f"{field}: {problem}")


# ---------------------------------------------------------------------------- arrays
def _pack_array(a: np.ndarray) -> msgpack.ExtType:
    dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
    code = _CODES.get(dt)
    if code is None:
        raise CodecError("array", f"unsupported dtype {a.dtype}")
    if a.ndim > MAX_NDIM:
        raise CodecError("array", f"more than {MAX_NDIM} dimensions")
    a = np.ascontiguousarray(a, dtype=dt)
    head = _HEAD.pack(code, a.ndim) + _SHAPES[a.ndim].pack(*a.shape)
    # ndarray is a Buffer at runtime; numpy declares __buffer__ only for Python >= 3.12
    return msgpack.ExtType(EXT_NDARRAY, b"".join((head, memoryview(a))))  # type: ignore[arg-type]  # one copy


def _unpack_array(data: bytes) -> np.ndarray:
    if len(data) < _HEAD.size:
        raise CodecError("array", "truncated header")
    code, ndim = _HEAD.unpack_from(data)
    dt = _NATIVE.get(code)
    if dt is None:
        raise CodecError("array", f"unknown dtype code {code}")
    if ndim > MAX_NDIM:
        raise CodecError("array", f"{ndim} dimensions (max {MAX_NDIM})")
    start = _HEAD.size + 4 * ndim
    if len(data) < start:
        raise CodecError("array", "truncated shape")
    shape = _SHAPES[ndim].unpack_from(data, _HEAD.size)
    n = math.prod(shape)
    if n * dt.itemsize != len(data) - start:
        raise CodecError("array", f"shape {shape} needs {n * dt.itemsize} bytes, has "
                         f"{len(data) - start}")
    if dt.kind == "b" and n and np.frombuffer(data, np.uint8, n, start).max() > 1:
        raise CodecError("array", "boolean array holds values other than 0 and 1")
    # a read-only view on the ext bytes (no copy): received messages are immutable values
    a = np.frombuffer(data, dtype=dt, count=n, offset=start)
    return a if ndim == 1 else a.reshape(shape)


# 1-D arrays of a non-bool dtype (the common case): header and size checked inline
_BY_CODE: list[np.dtype | None] = [
    _NATIVE[c] if c in _NATIVE and _NATIVE[c].kind != "b" else None for c in range(256)]
_U32 = struct.Struct("<I")


def _ext_hook(code: int, data: bytes) -> Any:
    if code == EXT_NDARRAY and len(data) >= 6 and data[1] == 1:
        dt = _BY_CODE[data[0]]
        if dt is not None:
            n = _U32.unpack_from(data, 2)[0]
            if n * dt.itemsize == len(data) - 6:
                return _frombuffer(data, dt, n, 6)
    if code == EXT_ZIPPED:
        return _unzip(data)
    if code != EXT_NDARRAY:
        raise CodecError("ext", f"unknown ext type {code}")
    return _unpack_array(data)  # the reference checks, for everything else


def _inner_hook(code: int, data: bytes) -> Any:
    """The ext hook inside a compressed envelope: arrays only."""
    if code != EXT_NDARRAY:
        raise CodecError("ext", f"ext type {code} inside a compressed envelope")
    return _ext_hook(code, data)


def _unzip(data: bytes) -> Any:
    """The envelope inside a compressed one (ext type 2); :class:`CodecError` if it is corrupt."""
    if len(data) < _ZHEAD.size:
        raise CodecError("payload", "truncated compressed envelope")
    method, size = _ZHEAD.unpack_from(data)
    if size > MAX_ZIPPED_BYTES:
        raise CodecError("size", f"compressed envelope of {size} bytes exceeds the limit of {MAX_ZIPPED_BYTES}")
    try:
        raw = compression.decompress(data[_ZHEAD.size:], method, size, "envelope", SCHEMA_DICT)
    except MessageError as exc:
        raise CodecError("payload", str(exc)) from exc
    return unpackb(raw, _inner_hook, "compressed envelope is ")


def unpackb(data: Any, ext_hook: Any = _ext_hook, what: str = "") -> Any:
    """msgpack's ``unpackb`` with the wire's ext types; hostile bytes (msgpack raises many types
    on them) become one :class:`CodecError` saying ``what`` was not valid msgpack."""
    try:
        return msgpack.unpackb(data, raw=False, ext_hook=ext_hook, strict_map_key=True)
    except MessageError:
        raise
    except Exception as exc:  # noqa: BLE001 - msgpack raises many types on hostile input
        raise CodecError("payload", f"{what}not valid msgpack ({type(exc).__name__}: {exc})") from exc


def zipped(data: bytes, level: int = 3) -> bytes:
    """The encoded envelope ``data`` as a compressed one (ext type 2) if that is smaller, else itself."""
    method, z = compression.DEFAULT, compression.compress(data, level=level)
    if len(data) <= SMALL_ENVELOPE:
        zd = compression.compress(data, compression.DEFLATE_DICT, zdict=SCHEMA_DICT)
        if len(zd) < len(z):
            method, z = compression.DEFLATE_DICT, zd
    if len(z) + _ZHEAD.size + 3 >= len(data):
        return data
    return _packb(msgpack.ExtType(EXT_ZIPPED, _ZHEAD.pack(method, len(data)) + z))


SMALL_ENVELOPE = 2048  # envelopes up to this size also try deflate with the schema dictionary
_LAST = ("LoopClosureRequest", "LoopClosuresAck", "PoseDeltas", "PgoCommand", "PgoStatus")  # the most frequent


def _schema_dict() -> bytes:
    """Every message type's envelope with placeholder values (empty arrays of the field's dtype),
    the most frequent types last (nearest to the data in deflate's window)."""
    from kimera_multi_py.comms.messages import MESSAGE_TYPES, SCHEMA_VERSION
    from kimera_multi_py.comms.messages.fields import Array, Bool, Float, Int

    def placeholder(spec: Any) -> Any:
        if isinstance(spec, Array):
            return ext_of(np.zeros((0,) * len(spec.shape), spec.dtype))
        return 0 if isinstance(spec, Int) else 0.0 if isinstance(spec, Float) else False if isinstance(spec, Bool) \
            else ""

    names = sorted(MESSAGE_TYPES, key=lambda n: _LAST.index(n) if n in _LAST else -1)
    return b"".join(_packb({"v": SCHEMA_VERSION, "type": name, "team": "", "src": 0, "seq": 0, "stamp": 0.0,
                            "body": {f: placeholder(s) for f, s in MESSAGE_TYPES[name].SPECS.items()}})
                    for name in names)


_frombuffer = np.frombuffer


def ext_of(a: np.ndarray) -> msgpack.ExtType:
    """The ext value of an array: :func:`_pack_array`, with a shortcut for the common case."""
    if a.__class__ is np.ndarray and a.flags.c_contiguous:
        code = _CODES.get(a.dtype)
        if code is not None:
            head = _HEADS[code][a.ndim] if a.ndim <= MAX_NDIM else None
            if head is not None:
                # the fields are valid by construction: skip ExtType.__new__'s type checks
                return _ext_new(msgpack.ExtType, (EXT_NDARRAY, b"".join(
                    (head, _SHAPES[a.ndim].pack(*a.shape), memoryview(a)))))  # type: ignore[arg-type]
    return _pack_array(a)


_ext_new = tuple.__new__
_HEADS = {code: [_HEAD.pack(code, ndim) for ndim in range(MAX_NDIM + 1)] for code in _DTYPES}


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return ext_of(obj)
    raise CodecError("body", f"cannot encode {type(obj).__name__}")


def _packb(obj: Any) -> bytes:
    """``msgpack.packb(obj, default=_default, use_bin_type=True)`` with one Packer per thread.

    ``msgpack.packb`` builds a Packer, and mallocs its 256 KiB buffer, on every call: for a
    stream of messages that allocation churn (and its page faults) costs more than the packing.
    A Packer resets its buffer after each ``pack`` (also when it raises).
    """
    try:
        packer = _local.packer
    except AttributeError:
        packer = _local.packer = msgpack.Packer(default=_default, use_bin_type=True)
    return packer.pack(obj)  # type: ignore[no-any-return]


_local = threading.local()


SCHEMA_DICT = _schema_dict()
