"""A msgpack writer and reader for envelopes with large arrays: one copy out, none in.

:func:`wire._packb <kimera_multi_py.comms.wire._packb>` and ``msgpack.unpackb`` are fast for
small messages but copy every array several times: on encode :func:`wire.ext_of` joins the
header and the array (copy 1), the packer copies that into its buffer (copy 2) and into the
returned ``bytes`` (copy 3); on decode msgpack copies each ext's data into a fresh ``bytes``
before the ext hook sees it. For ~100 KB payloads the allocation churn (glibc mmap/munmap of the
blocks, with their page faults) costs more than the work itself. (``msgpack.packb`` also
mallocs a 256 KiB ``Packer`` buffer per call.)

:func:`pack` is a pure-Python msgpack writer whose output is **byte-identical** to
``wire._packb(obj)``: it collects small headers and the arrays' own buffers (no copy) in a list
and joins them once, so an array's bytes are copied exactly once. Anything it does not handle
itself (``Timestamp``, ``memoryview``, sizes beyond msgpack's limits, deep nesting, strings that
do not encode) is handed to ``wire._packb`` for the whole object, so results and exceptions
always match it; unsupported objects raise :class:`CodecError` (``body``) as :func:`wire._default`
does.

:func:`unpack` reads one envelope (a top-level map) and returns what
``msgpack.unpackb(data, raw=False, ext_hook=wire._ext_hook, strict_map_key=True)`` would, except
that arrays (ext type 1) are read-only numpy views into ``data`` itself, validated exactly as
:func:`wire._ext_hook` validates them (the same :class:`CodecError`, raised at the same point in
document order). It returns ``None`` for anything outside a conservative subset or anything odd
— the caller then falls back to ``msgpack.unpackb``::

    env = largemsg.unpack(data)
    if env is None:
        env = msgpack.unpackb(data, raw=False, ext_hook=wire._ext_hook, strict_map_key=True)

Its only exceptions are :class:`MessageError` for a malformed array. Input other than ``bytes``
(a ``bytearray`` could change under the views) is not taken. A view keeps the whole message
buffer alive, and (as with ``msgpack``) array data need not be aligned.

Cost: both run in Python, a few microseconds per envelope whatever its size (a Ping envelope:
about 4 us to pack, 4.5 us to unpack on CPython 3.11), against msgpack's ~1-2 us plus
per-byte copies and allocations. So they are for messages with big arrays (tens of KB and up),
not for small ones.
"""

from __future__ import annotations

import math
import struct
import sys
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np

from kimera_multi_py.comms import wire
from kimera_multi_py.comms.wire import EXT_NDARRAY, MAX_NDIM
from kimera_multi_py.core.errors import MessageError

__all__ = ["pack", "unpack"]

_ndarray = np.ndarray
_ExtType = msgpack.ExtType
_packb = wire._packb
_default = wire._default
_ext_of = wire.ext_of
_ext_hook = wire._ext_hook
_frombuffer = np.frombuffer
_prod = math.prod
_intern = sys.intern
_CODES = wire._CODES
_HEADS = wire._HEADS
_SHAPES = wire._SHAPES
_ITEM_LIMIT = 2**32 - 1
_MAX_NEST = 64  # deeper structures go to msgpack (whose own limit is 1024)


class _Delegate(Exception):
    """Internal: let ``wire._packb`` pack the whole object."""


class _Unsupported(Exception):
    """Internal: :func:`unpack` returns None."""


# ---------------------------------------------------------------------------- pack
_BYTE = [bytes((i,)) for i in range(256)]
_U8 = struct.Struct(">BB").pack
_U16 = struct.Struct(">BH").pack
_U32 = struct.Struct(">BI").pack
_U64 = struct.Struct(">BQ").pack
_I8 = struct.Struct(">Bb").pack
_I16 = struct.Struct(">Bh").pack
_I32 = struct.Struct(">Bi").pack
_I64 = struct.Struct(">Bq").pack
_F64 = struct.Struct(">Bd").pack
_EXT8 = struct.Struct(">BBb").pack
_EXT16 = struct.Struct(">BHb").pack
_EXT32 = struct.Struct(">BIb").pack
_FIXEXT = {1: 0xD4, 2: 0xD5, 4: 0xD6, 8: 0xD7, 16: 0xD8}
_ARRAY_EXT8 = [b"" if n in _FIXEXT else bytes((0xC7, n, EXT_NDARRAY)) for n in range(256)]
for _n, _h in _FIXEXT.items():
    _ARRAY_EXT8[_n] = bytes((_h, EXT_NDARRAY))
_MAP_HEADS = [_BYTE[0x80 | n] for n in range(16)]
_LIST_HEADS = [_BYTE[0x90 | n] for n in range(16)]
_STRS: dict[str, bytes] = {}  # short str -> its whole encoding (header + UTF-8)
_STRS_MAX = 4096
_STR_CACHED = 64  # longest cached encoding (bytes); longer strings are rare and may be big


def pack(obj: Any) -> bytes:
    """``wire._packb(obj)``, byte for byte, copying each array's data once.

    Raises what ``wire._packb`` raises (:class:`CodecError` for an object it cannot encode).
    """
    parts: list[Any] = []
    try:
        _pack(obj, parts.append, 0)
    except (_Delegate, RecursionError, UnicodeEncodeError):
        return _packb(obj)  # the reference, for its result or its exception
    return b"".join(parts)


def _str(s: str) -> bytes:
    """The whole encoding (header and UTF-8) of a str; cached for short ones."""
    h = _STRS.get(s)
    if h is None:
        b = str.encode(s)  # UnicodeEncodeError: msgpack decides
        n = len(b)
        if n < 32:
            h = _BYTE[0xA0 | n] + b
        elif n < 256:
            h = _U8(0xD9, n) + b
        elif n < 65536:
            h = _U16(0xDA, n) + b
        elif n <= _ITEM_LIMIT:
            h = _U32(0xDB, n) + b
        else:
            raise _Delegate
        if n <= _STR_CACHED and len(_STRS) < _STRS_MAX:
            _STRS[s] = h
    return h


def _int(v: int) -> bytes:
    """msgpack's shortest encoding (unsigned for v > 0, signed otherwise), like pack_template.h."""
    if v > 0:
        if v < 128:
            return _BYTE[v]
        if v < 256:
            return _U8(0xCC, v)
        if v < 65536:
            return _U16(0xCD, v)
        if v < 4294967296:
            return _U32(0xCE, v)
        if v < 18446744073709551616:
            return _U64(0xCF, v)
    elif v >= -32:
        return _BYTE[v & 0xFF]
    elif v >= -128:
        return _I8(0xD0, v)
    elif v >= -32768:
        return _I16(0xD1, v)
    elif v >= -2147483648:
        return _I32(0xD2, v)
    elif v >= -9223372036854775808:
        return _I64(0xD3, v)
    raise _Delegate  # out of range: msgpack calls default, which raises CodecError("body", ...)


def _bin(b: Any, n: int, append: Callable[[Any], Any]) -> None:
    if n < 256:
        append(_U8(0xC4, n))
    elif n < 65536:
        append(_U16(0xC5, n))
    elif n <= _ITEM_LIMIT:
        append(_U32(0xC6, n))
    else:
        raise _Delegate
    append(b)


def _ext(code: Any, data: Any, append: Callable[[Any], Any]) -> None:
    if data.__class__ is not bytes or code.__class__ is not int or not -128 <= code <= 127:
        raise _Delegate
    n = len(data)
    head = _FIXEXT.get(n)
    if head is not None:
        append(_I8(head, code))
    elif n < 256:
        append(_EXT8(0xC7, n, code))
    elif n < 65536:
        append(_EXT16(0xC8, n, code))
    elif n <= _ITEM_LIMIT:
        append(_EXT32(0xC9, n, code))
    else:
        raise _Delegate
    append(data)


def _array(a: Any, append: Callable[[Any], Any]) -> None:
    """An array as :func:`wire.ext_of` packs it, with its own buffer as the data part."""
    if a.__class__ is _ndarray and a.flags.c_contiguous:
        code = _CODES.get(a.dtype)
        ndim = a.ndim
        if code is not None and ndim <= MAX_NDIM:
            n = 2 + 4 * ndim + a.nbytes
            if n < 256:
                append(_ARRAY_EXT8[n])
            elif n < 65536:
                append(_EXT16(0xC8, n, EXT_NDARRAY))
            elif n <= _ITEM_LIMIT:
                append(_EXT32(0xC9, n, EXT_NDARRAY))
            else:
                raise _Delegate
            append(_HEADS[code][ndim])
            if ndim:
                append(_SHAPES[ndim].pack(*a.shape))
            append(a)  # joined straight from the array's buffer: the one copy
            return
    ext = _ext_of(a)  # the other cases (copies, or raises CodecError)
    _ext(ext.code, ext.data, append)


def _pack(o: Any, append: Callable[[Any], Any], nest: int) -> None:
    cls = o.__class__
    if cls is dict:
        n = len(o)
        if n < 16:
            append(_MAP_HEADS[n])
        elif n < 65536:
            append(_U16(0xDE, n))
        else:
            append(_U32(0xDF, n))  # a dict cannot exceed msgpack's item limit in practice
        nest += 1
        if nest > _MAX_NEST:
            raise _Delegate
        strs = _STRS
        for k, v in o.items():
            if k.__class__ is str:
                h = strs.get(k)
                append(_str(k) if h is None else h)
            else:
                _pack(k, append, nest)
            vc = v.__class__
            if vc is str:
                h = strs.get(v)
                append(_str(v) if h is None else h)
            elif vc is int:
                append(_BYTE[v] if 0 <= v < 128 else _int(v))
            elif vc is float:
                append(_F64(0xCB, v))
            elif vc is _ndarray:
                _array(v, append)
            else:
                _pack(v, append, nest)
    elif cls is str:
        append(_str(o))
    elif cls is int:
        append(_int(o))
    elif cls is float:
        append(_F64(0xCB, o))
    elif cls is _ndarray:
        _array(o, append)
    elif o is None:
        append(b"\xc0")
    elif o is True:
        append(b"\xc3")
    elif o is False:
        append(b"\xc2")
    elif cls is list or cls is tuple:
        n = len(o)
        if n < 16:
            append(_LIST_HEADS[n])
        elif n < 65536:
            append(_U16(0xDC, n))
        elif n <= _ITEM_LIMIT:
            append(_U32(0xDD, n))
        else:
            raise _Delegate
        nest += 1
        if nest > _MAX_NEST:
            raise _Delegate
        for v in o:
            vc = v.__class__
            if vc is int:
                append(_BYTE[v] if 0 <= v < 128 else _int(v))
            elif vc is float:
                append(_F64(0xCB, v))
            else:
                _pack(v, append, nest)
    elif cls is bytes:
        _bin(o, len(o), append)
    elif cls is _ExtType:
        _ext(o.code, o.data, append)
    else:
        _pack_other(o, append, nest)


def _pack_other(o: Any, append: Callable[[Any], Any], nest: int) -> None:
    """Subclasses and the rest, in the order of msgpack's ``Packer._pack_inner``."""
    if isinstance(o, int):
        append(_int(int.__int__(o)))  # the int value, as msgpack takes it
    elif isinstance(o, float):
        append(_F64(0xCB, o))
    elif o.__class__ is bytearray:
        _bin(o, len(o), append)
    elif isinstance(o, str):
        append(_str(str.__str__(o)))  # the str value, as msgpack takes it
    elif isinstance(o, bytes | bytearray | dict | _ExtType | list | tuple):
        raise _Delegate  # subclasses with overridable len/items/iter: leave them to msgpack
    elif isinstance(o, _ndarray):
        _array(o, append)  # msgpack's default: wire.ext_of
    elif isinstance(o, memoryview | msgpack.Timestamp):
        raise _Delegate
    else:
        _pack(_default(o), append, nest)  # raises CodecError("body", ...), like msgpack's default


# ---------------------------------------------------------------------------- unpack
# Bounds: a single-byte read past the end raises IndexError and a struct read struct.error (both
# mean "truncated": None); every slice (str, bin, ext data) is checked against the end first, so
# the offset never passes the end and no truncated value is ever returned or handed to the hook.
_MAX_DEPTH = 4  # container nesting (the envelope is 1, its body 2)
_MAX_ITEMS = 256  # entries of a map, items of a list
_KEYS: dict[bytes, str] = {}  # map key bytes -> interned str (msgpack interns keys too)
_KEYS_MAX = 1024
_KEY_CACHED = 31  # bytes: keys as short as fixstr ones
_uH = struct.Struct(">H").unpack_from
_uI = struct.Struct(">I").unpack_from
_uQ = struct.Struct(">Q").unpack_from
_ub = struct.Struct(">b").unpack_from
_uh = struct.Struct(">h").unpack_from
_ui = struct.Struct(">i").unpack_from
_uq = struct.Struct(">q").unpack_from
_uf = struct.Struct(">f").unpack_from
_ud = struct.Struct(">d").unpack_from
_uBb = struct.Struct(">Bb").unpack_from
_uHb = struct.Struct(">Hb").unpack_from
_uIb = struct.Struct(">Ib").unpack_from
_U32LE = struct.Struct("<I").unpack_from
_DT: list[np.dtype | None] = [wire._NATIVE.get(c) for c in range(256)]
_BOOL_CODE = next(c for c, dt in wire._NATIVE.items() if dt.kind == "b")
_FIXEXT_LEN = {0xD4: 1, 0xD5: 2, 0xD6: 4, 0xD7: 8, 0xD8: 16}
_uint8 = np.uint8
_struct_error = struct.error


def unpack(data: bytes) -> Any | None:
    """The envelope map in ``data``, as ``msgpack.unpackb(..., ext_hook=wire._ext_hook)`` reads it.

    Arrays are read-only views into ``data``. Returns ``None`` when ``data`` is not ``bytes``, not
    one map, or uses anything outside the supported subset (the caller then uses msgpack); raises
    only the :class:`MessageError` that ``wire._ext_hook`` raises for a malformed array.
    """
    try:
        return _unpack(data)
    except (_Unsupported, IndexError, _struct_error, UnicodeDecodeError):
        return None
    except MessageError:
        raise
    except Exception:  # noqa: BLE001 - not expected; a bug here must only cost the fast path
        return None


def _unpack(data: bytes) -> Any:
    """:func:`unpack`; raises ``_Unsupported``, ``IndexError``, ``struct.error`` or
    ``UnicodeDecodeError`` where that returns None."""
    if data.__class__ is not bytes:
        raise _Unsupported
    end = len(data)
    b = data[0]
    if b & 0xF0 == 0x80:
        obj, p = _map(data, 1, end, b & 0x0F, 1)
    elif b == 0xDE:
        obj, p = _map(data, 3, end, _uH(data, 1)[0], 1)
    elif b == 0xDF:
        obj, p = _map(data, 5, end, _uI(data, 1)[0], 1)
    else:
        raise _Unsupported
    if p != end:
        raise _Unsupported  # extra data (msgpack raises ExtraData)
    return obj


def _key(data: bytes, p: int, end: int) -> tuple[str, int]:
    """A map key that is not a cached fixstr: a str (interned, as msgpack does), else unsupported."""
    b = data[p]
    if b & 0xE0 == 0xA0:
        p += 1
        q = p + (b & 0x1F)
    elif b == 0xD9:
        q = p + 2 + data[p + 1]
        p += 2
    elif b == 0xDA:
        q = p + 3 + _uH(data, p + 1)[0]
        p += 3
    else:
        raise _Unsupported  # bytes (msgpack allows them), str 32, anything else (msgpack refuses)
    if q > end:
        raise _Unsupported
    raw = data[p:q]
    k = _intern(raw.decode())
    if q - p <= _KEY_CACHED and len(_KEYS) < _KEYS_MAX:  # bounded: keys come from the network
        _KEYS[raw] = k
    return k, q


def _map(data: bytes, p: int, end: int, n: int, depth: int) -> tuple[dict[str, Any], int]:
    # msgpack refuses a map of more than len(data) // 2 entries before reading them: so do we
    if n > _MAX_ITEMS or 2 * n > end - p:
        raise _Unsupported
    keys = _KEYS
    d: dict[str, Any] = {}
    for _ in range(n):
        b = data[p]
        q = p + 1 + (b & 0x1F)
        if b & 0xE0 == 0xA0 and q <= end and (k := keys.get(data[p + 1:q])) is not None:
            p = q
        else:
            k, p = _key(data, p, end)
        d[k], p = _value(data, p, end, depth)
    return d, p


def _list(data: bytes, p: int, end: int, n: int, depth: int) -> tuple[list[Any], int]:
    if n > _MAX_ITEMS or n > end - p:
        raise _Unsupported
    out = []
    for _ in range(n):
        v, p = _value(data, p, end, depth)
        out.append(v)
    return out, p


def _value(data: bytes, p: int, end: int, depth: int) -> tuple[Any, int]:
    """The object at ``data[p]`` and the offset after it (``depth``: of the enclosing container)."""
    b = data[p]
    p += 1
    if b < 0x80:
        return b, p
    if b >= 0xE0:
        return b - 256, p
    if b < 0xA0:  # fixmap, fixarray
        if depth >= _MAX_DEPTH:
            raise _Unsupported
        if b < 0x90:
            return _map(data, p, end, b & 0x0F, depth + 1)
        return _list(data, p, end, b & 0x0F, depth + 1)
    if b < 0xC0:  # fixstr
        q = p + (b & 0x1F)
        if q > end:
            raise _Unsupported
        return data[p:q].decode(), q
    if b == 0xC0:
        return None, p
    if b == 0xC2:
        return False, p
    if b == 0xC3:
        return True, p
    if b == 0xCB:
        return _ud(data, p)[0], p + 8
    if b == 0xCA:
        return _uf(data, p)[0], p + 4
    if 0xCC <= b <= 0xCF:  # uint 8/16/32/64
        if b == 0xCC:
            return data[p], p + 1
        if b == 0xCD:
            return _uH(data, p)[0], p + 2
        if b == 0xCE:
            return _uI(data, p)[0], p + 4
        return _uQ(data, p)[0], p + 8
    if 0xD0 <= b <= 0xD3:  # int 8/16/32/64
        if b == 0xD0:
            return _ub(data, p)[0], p + 1
        if b == 0xD1:
            return _uh(data, p)[0], p + 2
        if b == 0xD2:
            return _ui(data, p)[0], p + 4
        return _uq(data, p)[0], p + 8
    if 0xD9 <= b <= 0xDB or 0xC4 <= b <= 0xC6:  # str 8/16/32, bin 8/16/32
        if b == 0xD9 or b == 0xC4:
            n = data[p]
            p += 1
        elif b == 0xDA or b == 0xC5:
            n = _uH(data, p)[0]
            p += 2
        else:
            n = _uI(data, p)[0]
            p += 4
        q = p + n
        if q > end:
            raise _Unsupported
        return (data[p:q].decode() if b >= 0xD9 else data[p:q]), q
    if 0xC7 <= b <= 0xC9 or 0xD4 <= b <= 0xD8:  # ext 8/16/32: length, type, data; fixext
        if b == 0xC7:
            n, code = _uBb(data, p)
            p += 2
        elif b == 0xC8:
            n, code = _uHb(data, p)
            p += 3
        elif b == 0xC9:
            n, code = _uIb(data, p)
            p += 5
        else:
            n, code = _FIXEXT_LEN[b], _ub(data, p)[0]
            p += 1
        q = p + n
        if q > end:
            raise _Unsupported
        return _ext_value(data, p, n, code), q
    if 0xDC <= b <= 0xDF:  # array 16/32, map 16/32
        if depth >= _MAX_DEPTH:
            raise _Unsupported
        if b == 0xDC or b == 0xDE:
            n = _uH(data, p)[0]
            p += 2
        else:
            n = _uI(data, p)[0]
            p += 4
        if b <= 0xDD:
            return _list(data, p, end, n, depth + 1)
        return _map(data, p, end, n, depth + 1)
    raise _Unsupported  # 0xc1: never used


def _ext_value(data: bytes, p: int, n: int, code: int) -> Any:
    """The ext at ``data[p:p + n]``: an array view into ``data``, checked as ``wire._ext_hook`` does."""
    if code != EXT_NDARRAY:
        raise _Unsupported  # unknown types (msgpack: CodecError from the hook), timestamps (-1)
    if n >= 6 and data[p + 1] == 1:  # 1-D, the common case
        dt = _DT[data[p]]
        if dt is not None:
            count = _U32LE(data, p + 2)[0]
            if count * dt.itemsize == n - 6 and (
                data[p] != _BOOL_CODE or not count or _frombuffer(data, _uint8, count, p + 6).max() <= 1
            ):
                return _frombuffer(data, dt, count, p + 6)
    elif n >= 2:
        ndim = data[p + 1]
        dt = _DT[data[p]]
        if dt is not None and ndim <= MAX_NDIM and 2 + 4 * ndim <= n:
            start = p + 2 + 4 * ndim
            shape = _SHAPES[ndim].unpack_from(data, p + 2)
            count = _prod(shape)
            if count * dt.itemsize == p + n - start and (
                data[p] != _BOOL_CODE or not count or _frombuffer(data, _uint8, count, start).max() <= 1
            ):
                return _frombuffer(data, dt, count, start).reshape(shape)
    return _ext_hook(code, data[p:p + n])  # raises the reference's CodecError
