"""Rows kept as a palette: the distinct rows once, and per cell an index into them.

A submap's evidence rows repeat (a free cell's row is a multiple of the miss row, and a few
hundred distinct rows cover a whole submap), so a palette of its distinct int16 rows and a
uint16 index per cell hold exactly what the dense rows hold in a fraction of the bytes
(docs/performance.md).
"""

from __future__ import annotations

import numpy as np


def unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct rows of a 2-D array (any order) and each row's index among them."""
    rows = np.ascontiguousarray(rows)
    if len(rows) == 0:
        return rows.copy(), np.zeros(0, np.intp)
    keys = rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).reshape(-1)
    _, first, inv = np.unique(keys, return_index=True, return_inverse=True)
    return rows[first], inv.reshape(-1)


def index_dtype(palette_rows: int) -> type[np.unsignedinteger]:
    """The smallest index type for a palette of this many rows."""
    return np.uint16 if palette_rows <= 1 << 16 else np.uint32


def to_palette(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``rows`` as (palette, index): ``palette.take(index, axis=0)`` gives them back exactly."""
    palette, inv = unique_rows(rows)
    return palette, inv.astype(index_dtype(len(palette)))
