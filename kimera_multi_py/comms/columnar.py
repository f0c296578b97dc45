"""Columnar batches: a burst of same-type messages as one envelope, one column per field.

A publisher that sends many messages of one type back to back (a burst of pings, keyframe
descriptors, object updates) would otherwise pay a full envelope, a msgpack map per body and a
per-field validation for every message, on both sides. A columnar batch is one ordinary envelope
(docs/architecture.md: ``{v, type, team, src, seq, stamp, body}``) with ``type = "Batch"`` and::

    body = {"type": inner message type, "n": number of messages, "cols": {field: column}}

Columns, by field spec (:mod:`kimera_multi_py.comms.messages`):

- ``Int`` -> int64 array ``(n,)``; ``Float`` -> float64 array ``(n,)``; ``Bool`` -> bool
  array ``(n,)``; ``Str`` -> a list of ``n`` strings;
- ``Array`` -> the ``n`` arrays stacked, ``(n, *shape)`` (a burst qualifies only when every
  array field has one shape across the burst; otherwise the messages go as separate envelopes).

Message ``i`` carries sequence number ``seq + i`` and the batch's stamp. Decoding validates each
column against the spec as a whole (dtype, shape, symbolic dimensions, ranges, finiteness, every
``robot`` equal to the sender) with vectorised checks, so a batch accepts exactly the messages
that would be accepted one by one; the decoded arrays are read-only views on the received bytes.
A batch failing any check is rejected as a whole (:class:`~kimera_multi_py.comms.codec.CodecError`
naming ``Batch.<field>``).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache
from operator import itemgetter
from typing import Any

import numpy as np

from kimera_multi_py.comms.messages import MESSAGE_TYPES
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.fields import INT64_MAX, INT64_MIN, Array, Bool, Float, Int, Str
from kimera_multi_py.comms.wire import CodecError
from kimera_multi_py.core.errors import MessageError

BATCH_TYPE = "Batch"
MIN_COLUMNAR = 2  # shorter runs go as ordinary envelopes
_SCALAR_DTYPES = {Int: np.dtype(np.int64), Float: np.dtype(np.float64), Bool: np.dtype(np.bool_)}


def to_columns(msgs: list[Message]) -> dict[str, Any] | None:
    """The batch body of ``msgs`` (one type, >= 2), or None when they cannot share columns."""
    n = len(msgs)
    if n < MIN_COLUMNAR:
        return None
    cls = msgs[0].__class__
    if not issubclass(cls, Message) or MESSAGE_TYPES.get(cls.TYPE) is not cls:

        raise CodecError("body", f"not a message: {cls.__name__}")
    for m in msgs:
        if m.__class__ is not cls:
            return None
    specs = cls.SPECS
    # transpose in C: one tuple of field values per message, then one tuple per field
    # (classes are hashable; mypy reads Message.__hash__ = None as the class object's hash)
    columns = zip(*map(_getter(cls), [m.__dict__ for m in msgs]), strict=True)  # type: ignore[arg-type]
    cols: dict[str, Any] = {}
    for (name, spec), values in zip(specs.items(), columns, strict=True):
        kind = spec.__class__
        if kind is Array:
            shape = values[0].shape
            for v in values:
                if v.shape != shape:
                    return None
            # concatenate + reshape: a C loop, where np.stack slices every array in Python
            cols[name] = np.concatenate(values).reshape((n, *shape)) if shape else np.stack(values)
        elif kind is Str:
            cols[name] = list(values)
        else:
            cols[name] = np.array(values, dtype=_SCALAR_DTYPES[kind])
    return {"type": cls.TYPE, "n": n, "cols": cols}


@cache
def _getter(cls: type[Message]) -> Callable[[dict[str, Any]], tuple[Any, ...]]:
    names = list(cls.SPECS)
    get = itemgetter(*names)
    return get if len(names) > 1 else lambda d: (get(d),)


def from_columns(body: Any, src: int, max_batch: int) -> list[Message]:
    """Validate a batch body sent by ``src`` and build its messages; raise ``MessageError``."""
    try:
        return _from_columns(body, src, max_batch)
    except MessageError:
        raise
    except Exception as exc:  # noqa: BLE001 - a hostile body must only ever raise MessageError
        raise _err("body", f"malformed batch ({type(exc).__name__}: {exc})") from exc


def _err(field: str, problem: str) -> MessageError:

    return CodecError(f"{BATCH_TYPE}.{field}", problem)


def _from_columns(body: Any, src: int, max_batch: int) -> list[Message]:
    if body.__class__ is not dict or len(body) != 3 or not {"type", "n", "cols"} <= body.keys():
        raise _err("body", "expected a map of type, n and cols")
    type_name, n, cols = body["type"], body["n"], body["cols"]
    cls = MESSAGE_TYPES.get(type_name) if type_name.__class__ is str else None
    if cls is None:
        raise _err("type", f"unknown message type {type_name!r}")
    if n.__class__ is not int or not MIN_COLUMNAR <= n <= max_batch:
        raise _err("n", f"expected {MIN_COLUMNAR} to {max_batch} messages, got {n!r}")
    specs = cls.SPECS
    if cols.__class__ is not dict or len(cols) != len(specs) or not specs.keys() <= cols.keys():
        raise _err("cols", f"expected exactly the columns {list(specs)}")
    dims: dict[str, int] = {}
    rows: list[list[Any]] = []
    for name, spec in specs.items():
        col = cols[name]
        where = f"{type_name}.{name}"
        if spec.__class__ is Str:
            rows.append(_str_column(where, spec, col, n))  # type: ignore[arg-type]
        elif spec.__class__ is Array:
            rows.append(list(_array_column(where, spec, col, n, dims)))  # type: ignore[arg-type]
        else:
            rows.append(_scalar_column(where, spec, col, n).tolist())
    robots = rows[list(specs).index("robot")]
    if robots.count(src) != n:
        raise _err("robot", f"messages of another robot than the sender {src}")
    return cls._from_rows(*rows)  # type: ignore[attr-defined, no-any-return]


def _scalar_column(where: str, spec: Any, col: Any, n: int) -> np.ndarray:
    want = _SCALAR_DTYPES[spec.__class__]
    if col.__class__ is not np.ndarray or col.dtype != want or col.shape != (n,):
        raise _err(where, f"expected a {want} column of {n} values")
    if spec.__class__ is Int:
        if spec.lo > INT64_MIN and col.min() < spec.lo or spec.hi < INT64_MAX and col.max() > spec.hi:
            raise _err(where, f"a value outside [{spec.lo}, {spec.hi}]")
    elif spec.__class__ is Float:
        if np.isnan(col).any():
            raise _err(where, "NaN")
        if spec.finite and not np.isfinite(col).all():
            raise _err(where, "not finite")
        if col.min() < spec.lo or col.max() > spec.hi:
            raise _err(where, f"a value outside [{spec.lo}, {spec.hi}]")
    return col


def _str_column(where: str, spec: Str, col: Any, n: int) -> list[str]:
    if col.__class__ is not list or len(col) != n:
        raise _err(where, f"expected a list of {n} strings")
    for s in col:
        if s.__class__ is not str or len(s) > spec.max_len or spec.choices and s not in spec.choices:
            raise _err(where, f"invalid string {s!r}")
    return col


def _array_column(where: str, spec: Array, col: Any, n: int, dims: dict[str, int]) -> np.ndarray:
    want = np.dtype(spec.dtype)
    if col.__class__ is not np.ndarray or col.dtype != want or col.ndim != 1 + len(spec.shape) \
            or col.shape[0] != n:
        raise _err(where, f"expected a {want} column of shape ({n}, {', '.join(map(str, spec.shape))})")
    for size, fixed in zip(col.shape[1:], spec.shape, strict=True):
        if isinstance(fixed, int):
            if size != fixed:
                raise _err(where, f"dimension {size}, expected {fixed}")
        elif dims.setdefault(fixed, size) != size:
            raise _err(where, f"dimension {fixed}={size} disagrees with {dims[fixed]}")
    if col.size:
        if spec.finite and want.kind == "f" and not np.isfinite(col).all():
            raise _err(where, "contains non-finite values")
        if spec.lo is not None and col.min() < spec.lo:
            raise _err(where, f"a value below {spec.lo}")
        if spec.hi is not None and col.max() > spec.hi:
            raise _err(where, f"a value above {spec.hi}")
    return col
