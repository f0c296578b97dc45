"""Row deltas of versioned tables: a table sent as what changed against a version its receivers
hold (docs/algorithms/map_consensus.md, "Objects travel with the exact consensus").

A table (an object table, a people table) is a set of row fields of one length. Against a base
table, a new version is sent as ``reuse``, one int32 per row of the new table (the index of an
identical row of the base, or -1), and the row fields of only the rows marked -1, in order. Rows
are matched by their bytes, so the table the receiver expands is the sender's bit for bit, and no
key is needed: an object's row and a person's sample are alike to it.

:func:`delta_rows` computes ``reuse`` and the fresh rows' indices; :func:`expand_rows` rebuilds
the full row fields, refusing (``MessageError``) a ``reuse`` that does not fit the base or the
fresh rows. :class:`TableHistory` keeps the last few versions of each source's table, the bases
a delta may be taken against.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from kimera_multi_py.core.errors import MessageError


def _row_bytes(fields: Sequence[np.ndarray]) -> np.ndarray:
    """One void scalar per row: the row's bytes over every field, in field order."""
    n = len(fields[0])
    rows = np.ascontiguousarray(np.hstack([np.ascontiguousarray(f).reshape(n, -1).view(np.uint8) for f in fields]))
    return rows.view(np.dtype((np.void, rows.shape[1]))).reshape(n)


def delta_rows(base: Sequence[np.ndarray], new: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``(reuse, fresh)``: for each row of ``new`` the index of a row of ``base`` with the same
    bytes in every field (or -1), and the indices of the rows of ``new`` marked -1."""
    n = len(new[0])
    reuse = np.full(n, -1, np.int32)
    if n and len(base[0]):
        b, v = _row_bytes(base), _row_bytes(new)
        order = np.argsort(b, kind="stable")
        pos = np.minimum(np.searchsorted(b[order], v), len(b) - 1)
        hit = b[order][pos] == v
        reuse[hit] = order[pos[hit]]
    return reuse, np.flatnonzero(reuse < 0)


def expand_rows(what: str, base: Mapping[str, np.ndarray], fresh: Mapping[str, np.ndarray],
                reuse: np.ndarray) -> dict[str, np.ndarray]:
    """The full row fields: row ``i`` is ``base``'s row ``reuse[i]``, or the next fresh row where
    ``reuse[i]`` is -1. ``MessageError`` names what does not fit."""
    reuse = np.asarray(reuse)
    nb = len(next(iter(base.values()))) if base else 0
    new = reuse < 0
    n_fresh = int(new.sum())
    if np.any(reuse < -1) or np.any(reuse >= nb):
        raise MessageError(f"{what}: a reused row is not in the base table of {nb} rows")
    out: dict[str, np.ndarray] = {}
    for name, f in fresh.items():
        if len(f) != n_fresh:
            raise MessageError(f"{what}.{name}: {len(f)} fresh rows, the delta marks {n_fresh}")
        b = base[name]
        if b.shape[1:] != f.shape[1:]:
            raise MessageError(f"{what}.{name}: rows of shape {f.shape[1:]} against a base of {b.shape[1:]}")
        full = np.empty((len(reuse), *f.shape[1:]), f.dtype)
        full[new] = f
        full[~new] = b[reuse[~new]]
        out[name] = full
    return out


class TableHistory:
    """The last ``keep`` versions of each source's table (the bases deltas are taken against)."""

    def __init__(self, keep: int = 4) -> None:
        self.keep = int(keep)
        self._tables: dict[int, dict[int, Any]] = {}

    def add(self, source: int, version: int, table: Any) -> None:
        held = self._tables.setdefault(int(source), {})
        held[int(version)] = table
        for v in sorted(held)[:-self.keep]:
            del held[v]

    def get(self, source: int, version: int) -> Any | None:
        return self._tables.get(int(source), {}).get(int(version))

    def forget(self, source: int) -> None:
        self._tables.pop(int(source), None)
