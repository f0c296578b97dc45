"""The wire form of map cells: Morton codes and integer rows, losslessly compressed.

Sorted codes travel as differences (small numbers: Morton order keeps neighbours close),
rows column by column; both are byte-shuffled (all low bytes, then all high bytes, as Blosc
does) and compressed (:mod:`kimera_multi_py.comms.compression`: zstd where it is installed,
zlib otherwise; the payload's first byte names which): on map cells zstd costs a small fraction
of zlib level 6's time and makes smaller payloads, and zstd's level 15 takes 12 % off level 3's
bytes for about 50 ms per MB of raw cells (docs/performance.md).
Unpacking checks every size before trusting the payload, so a corrupt or hostile payload raises
:class:`MessageError` instead of allocating without bound.

Two row layouts, named by the high bits of the payload's first byte (its low bits name the
compressor), so a receiver reads either:

* *plain* (:data:`PLAIN`): the int16 rows as they are, column by column;
* *palette* (:data:`PALETTE`, the default): the distinct rows once, most frequent first, and per
  cell the index of its row (uint8, uint16 or uint32 as their number needs). A submap's cells
  hold few distinct rows: a cell's row is the sum of a few kinds of steps (a ray passing through
  adds the same step to every class, an end point one step to every class and more to the
  observed one), so thousands of cells share each row. The table stores each row as its
  smallest entry and the (unsigned) differences to it, zeros except in the classes observed.
  The values are rebuilt exactly (docs/algorithms/map_consensus.md).
"""

from __future__ import annotations

import zlib

import numpy as np

from kimera_multi_py.comms.compression import DEFAULT, compress, decompress
from kimera_multi_py.core.errors import MessageError

LEVEL = 6  # zlib's, for the leaf levels of a whole tree
CELLS_LEVEL = 15  # zstd's (zlib's at most 9), for the cells: see the module docstring
_MAX_CODE = 1 << 48  # three 16-bit keys


def _shuffle(a: np.ndarray) -> bytes:
    b = np.ascontiguousarray(a).view(np.uint8).reshape(-1, a.dtype.itemsize)
    return np.ascontiguousarray(b.T).tobytes()


def _unshuffle(data: bytes, dtype: str, n: int) -> np.ndarray:
    size = np.dtype(dtype).itemsize
    b = np.frombuffer(data, np.uint8).reshape(size, n)
    return np.ascontiguousarray(b.T).view(dtype).reshape(n)


PLAIN = 0x00
PALETTE = 0x20
_LAYOUT = 0xF0  # the first byte's bits that name the row layout
_I16 = np.iinfo(np.int16)


def _index_dtype(distinct: int) -> str:
    return "<u1" if distinct <= 1 << 8 else "<u2" if distinct <= 1 << 16 else "<u4"


_MIX = np.random.default_rng(0x5EED).integers(1, 1 << 62, 4096, dtype=np.int64) | 1


def _distinct_rows(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distinct rows, each row's index among them and their counts: ``np.unique(axis=0)``,
    a hundred times faster. Rows are told apart by a 64-bit mix of their entries; should two
    distinct rows ever share it, the exact sort decides."""
    mix = (values.astype(np.int64) * _MIX[: values.shape[1]]).sum(axis=1)  # wraps around: a hash
    _, first, inverse, counts = np.unique(mix, return_index=True, return_inverse=True, return_counts=True)
    table = values[first]
    if not np.array_equal(table[inverse], values):  # a collision
        table, inverse, counts = np.unique(values, axis=0, return_inverse=True, return_counts=True)
    return table, inverse.reshape(-1), counts


def pack_cells(codes: np.ndarray, values: np.ndarray, palette: bool = True) -> np.ndarray:
    """A uint8 payload of sorted unique codes ``(n,)`` int64 and rows ``(n, c)`` int16
    (``palette``: the distinct rows once and an index per cell, else the rows as they are)."""
    codes = np.asarray(codes, dtype="<i8")
    values = np.asarray(values, dtype="<i2")
    if len(codes) > 1 and np.any(codes[1:] <= codes[:-1]):
        raise ValueError("codes must be sorted and unique")
    steps = np.diff(codes, prepend=np.int64(0))
    if not palette or values.size == 0:
        raw = _shuffle(steps) + _shuffle(np.ascontiguousarray(values.T).reshape(-1))
        return np.frombuffer(bytes([PLAIN | DEFAULT]) + compress(raw, DEFAULT, CELLS_LEVEL), np.uint8).copy()
    table, inverse, counts = _distinct_rows(values)
    # the most frequent rows get the smallest indices; rows as often, in row order
    order = np.lexsort((*table.T[::-1], -counts))
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    index = rank[inverse].astype(_index_dtype(len(table)))
    table = table[order]
    low = table.min(axis=1)
    rest = (table.astype(np.int32) - low[:, None]).astype("<u2")
    raw = _shuffle(steps) + _shuffle(index) + _shuffle(low.astype("<i2")) + \
        _shuffle(np.ascontiguousarray(rest.T).reshape(-1))
    head = bytes([PALETTE | DEFAULT]) + np.array([len(table)], "<u4").tobytes()
    return np.frombuffer(head + compress(raw, DEFAULT, CELLS_LEVEL), np.uint8).copy()


def unpack_cells(payload: np.ndarray, n: int, c: int, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Codes ``(n,)`` and rows ``(n, c)`` of a payload made by :func:`pack_cells` (either layout)."""
    data = np.ascontiguousarray(payload, dtype=np.uint8).tobytes()
    if not data:
        raise MessageError(f"{where}: empty payload")
    layout, method = data[0] & _LAYOUT, data[0] & ~_LAYOUT
    if layout not in (PLAIN, PALETTE):
        raise MessageError(f"{where}: corrupt payload (unknown row layout {layout >> 4})")
    body, distinct, width = data[1:], 0, 0
    if layout == PALETTE:
        if len(data) < 5:
            raise MessageError(f"{where}: corrupt payload (cut before its palette size)")
        distinct = int(np.frombuffer(data[1:5], "<u4")[0])
        if distinct > n or (n > 0 and c > 0 and distinct == 0):
            raise MessageError(f"{where}: corrupt payload ({distinct} distinct rows for {n} cells)")
        width = np.dtype(_index_dtype(distinct)).itemsize
        body = data[5:]
        expected = n * (8 + width) + distinct * 2 * (1 + c)
    else:
        expected = n * (8 + 2 * c)
    try:
        raw = decompress(body, method, expected, where)
    except MessageError as exc:
        detail = str(exc).removeprefix(f"{where}: ")
        raise MessageError(f"{where}: payload does not hold {n} cells of {c} classes "
                           f"(corrupt or cut: {detail})") from None
    steps = _unshuffle(raw[: 8 * n], "<i8", n)
    if n and (steps[0] < 0 or np.any(steps[1:] <= 0) or np.any(steps >= _MAX_CODE)
              or int(steps.sum(dtype=np.float64)) >= _MAX_CODE):
        raise MessageError(f"{where}: codes are not sorted and unique")
    codes = np.cumsum(steps, dtype=np.int64)
    if layout == PLAIN:
        values = _unshuffle(raw[8 * n:], "<i2", n * c).reshape(c, n).T.astype(np.int16)
        return codes, np.ascontiguousarray(values)
    at = 8 * n
    index = _unshuffle(raw[at: at + width * n], _index_dtype(distinct), n).astype(np.int64)
    at += width * n
    low = _unshuffle(raw[at: at + 2 * distinct], "<i2", distinct).astype(np.int32)
    rest = _unshuffle(raw[at + 2 * distinct:], "<u2", distinct * c).reshape(c, distinct).T.astype(np.int32)
    table = rest + low[:, None]
    if n and (np.any(index >= distinct) or np.any(table > _I16.max) or (c > 0 and np.any(rest.min(axis=1) != 0))):
        raise MessageError(f"{where}: corrupt payload (palette rows or indices out of range)")
    return codes, np.ascontiguousarray(table.astype(np.int16)[index].reshape(n, c))


def pack_leaves(codes: np.ndarray, levels: np.ndarray, values: np.ndarray) -> np.ndarray:
    """A uint8 payload of a tree's leaves: start codes, levels ``(n,)`` int8, rows ``(n, c)`` int16."""
    cells = pack_cells(codes, values)
    lev = zlib.compress(np.asarray(levels, dtype=np.int8).tobytes(), LEVEL)
    head = np.array([len(lev)], dtype="<u4").view(np.uint8)
    return np.concatenate([head, np.frombuffer(lev, np.uint8), cells])


def unpack_leaves(payload: np.ndarray, n: int, c: int, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Start codes, levels and rows of a payload made by :func:`pack_leaves` (levels checked)."""
    payload = np.ascontiguousarray(payload, dtype=np.uint8)
    if len(payload) < 4:
        raise MessageError(f"{where}: payload too short")
    m = int(payload[:4].view("<u4")[0])
    if 4 + m > len(payload):
        raise MessageError(f"{where}: payload too short")
    d = zlib.decompressobj()
    try:
        raw = d.decompress(payload[4:4 + m].tobytes(), n + 1)
    except zlib.error as exc:
        raise MessageError(f"{where}: corrupt payload ({exc})") from None
    if len(raw) != n:
        raise MessageError(f"{where}: payload does not hold {n} leaves")
    levels = np.frombuffer(raw, np.int8).copy()
    if n and (levels.min() < 0 or levels.max() > 16):
        raise MessageError(f"{where}: leaf levels outside 0..16")
    codes, values = unpack_cells(payload[4 + m:], n, c, where)
    span = np.left_shift(np.int64(1), 3 * levels.astype(np.int64))
    if np.any(codes & (span - 1)) or np.any(codes[:-1] + span[:-1] > codes[1:]):
        raise MessageError(f"{where}: leaves must be aligned to their level, sorted and disjoint")
    return codes, levels, values
