"""The wire form of map cells: Morton codes and integer rows, losslessly compressed.

Sorted codes travel as differences (small numbers: Morton order keeps neighbours close),
rows column by column; both are byte-shuffled (all low bytes, then all high bytes, as Blosc
does) and deflated with zlib. Unpacking checks every size before trusting the payload, so a
corrupt or hostile payload raises :class:`MessageError` instead of allocating without bound.
"""

from __future__ import annotations

import zlib

import numpy as np

from kimera_multi_py.errors import MessageError

LEVEL = 6
_MAX_CODE = 1 << 48  # three 16-bit keys


def _shuffle(a: np.ndarray) -> bytes:
    b = np.ascontiguousarray(a).view(np.uint8).reshape(-1, a.dtype.itemsize)
    return np.ascontiguousarray(b.T).tobytes()


def _unshuffle(data: bytes, dtype: str, n: int) -> np.ndarray:
    size = np.dtype(dtype).itemsize
    b = np.frombuffer(data, np.uint8).reshape(size, n)
    return np.ascontiguousarray(b.T).view(dtype).reshape(n)


def pack_cells(codes: np.ndarray, values: np.ndarray) -> np.ndarray:
    """A uint8 payload of sorted unique codes ``(n,)`` int64 and rows ``(n, c)`` int16."""
    codes = np.asarray(codes, dtype="<i8")
    values = np.asarray(values, dtype="<i2")
    if len(codes) > 1 and np.any(codes[1:] <= codes[:-1]):
        raise ValueError("codes must be sorted and unique")
    steps = np.diff(codes, prepend=np.int64(0))
    raw = _shuffle(steps) + _shuffle(np.ascontiguousarray(values.T).reshape(-1))
    return np.frombuffer(zlib.compress(raw, LEVEL), np.uint8).copy()


def unpack_cells(payload: np.ndarray, n: int, c: int, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Codes ``(n,)`` and rows ``(n, c)`` of a payload made by :func:`pack_cells`."""
    expected = n * (8 + 2 * c)
    d = zlib.decompressobj()
    try:
        raw = d.decompress(np.ascontiguousarray(payload, dtype=np.uint8).tobytes(), expected + 1)
    except zlib.error as exc:
        raise MessageError(f"{where}: corrupt payload ({exc})") from None
    if len(raw) != expected or not d.eof or d.unconsumed_tail:
        raise MessageError(f"{where}: payload does not hold {n} cells of {c} classes")
    steps = _unshuffle(raw[: 8 * n], "<i8", n)
    if n and (steps[0] < 0 or np.any(steps[1:] <= 0) or np.any(steps >= _MAX_CODE)
              or int(steps.sum(dtype=np.float64)) >= _MAX_CODE):
        raise MessageError(f"{where}: codes are not sorted and unique")
    codes = np.cumsum(steps, dtype=np.int64)
    values = _unshuffle(raw[8 * n:], "<i2", n * c).reshape(c, n).T.astype(np.int16)
    return codes, np.ascontiguousarray(values)
