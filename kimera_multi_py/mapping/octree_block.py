"""One block of a linear octree: the sorted leaves below one node of level ``BLOCK_LEVEL``
(docs/algorithms/mapping.md).

A :class:`~.semantic_octree.SemanticOctree` keeps its leaves per block (3.2 m at 0.1 m), so
that a scan only moves the memory of the blocks it sees and its cost does not grow with the
map; pruning therefore stops at block size. A block holds three parallel arrays sorted by
Morton code (:mod:`.morton`): ``codes`` (int64, the first voxel of each leaf), ``levels``
(int8, 0 = one voxel) and ``values`` (int16 fixed-point log-odds rows, :mod:`.observation`).
Every operation is vectorised over the codes it is given: one ``np.searchsorted`` merge, an
update of all touched rows at once, and pruning of the touched branches level by level.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

import numpy as np

BLOCK_LEVEL = 5  # leaves are stored per node of this level; it is also the largest leaf
PRUNE_MAX_LEVEL = BLOCK_LEVEL
BLOCK_SHIFT = 3 * BLOCK_LEVEL  # a finest-level code's block id is ``code >> BLOCK_SHIFT``
_ARANGE8 = np.arange(8, dtype=np.int64)


def unique_sorted(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique values of a sorted array and the index of each first occurrence."""
    if len(a) == 0:
        return a, np.zeros(0, dtype=np.int64)
    first = np.empty(len(a), dtype=np.bool_)
    first[0] = True
    np.not_equal(a[1:], a[:-1], out=first[1:])
    idx = np.flatnonzero(first)
    return a[idx], idx


def _isin_sorted(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.isin(a, b)`` for a sorted, unique ``b``."""
    if len(b) == 0:
        return np.zeros(len(a), dtype=np.bool_)
    pos = np.searchsorted(b, a).clip(max=len(b) - 1)
    return b[pos] == a


def _span(levels: np.ndarray) -> np.ndarray:
    """Number of voxels (Morton codes) a node of each level covers."""
    return np.left_shift(np.int64(1), 3 * levels.astype(np.int64))


def pruned(codes: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The canonical pruned leaves of finest-level cells (sorted unique ``codes``, int16 rows):
    every 8 sibling leaves of one level with identical rows become their parent, bottom-up to
    ``PRUNE_MAX_LEVEL``. The same leaves as inserting the cells one update at a time, in one
    pass per level over all blocks at once. Returns codes, levels and values."""
    codes = np.asarray(codes, dtype=np.int64)
    levels = np.zeros(len(codes), dtype=np.int8)
    for lev in range(1, PRUNE_MAX_LEVEL + 1):
        n = len(codes)
        if n < 8:
            break
        child = np.int64(1) << (3 * (lev - 1))
        first = np.flatnonzero((levels[: n - 7] == lev - 1) & ((codes[: n - 7] & ((child << 3) - 1)) == 0))
        # eight non-overlapping leaves of the child level from the first child to the last are
        # exactly the eight children
        first = first[codes[first + 7] == codes[first] + 7 * child]
        idx = first[:, None] + _ARANGE8
        ok = np.all(levels[idx] == lev - 1, axis=1)
        idx = idx[ok]
        rv = values.take(idx.ravel(), axis=0).reshape(idx.shape + values.shape[1:])
        idx = idx[np.all(rv == rv[:, :1], axis=(1, 2))]
        if len(idx) == 0:
            continue
        keep = np.ones(n, dtype=np.bool_)
        keep[idx[:, 1:].ravel()] = False
        levels[idx[:, 0]] = lev
        kept = np.flatnonzero(keep)
        codes, levels, values = codes[kept], levels[kept], values.take(kept, axis=0)
    return codes, levels, values


class OctreeBlock:
    """The linear octree of one block: sorted leaf codes, levels and fixed-point rows."""

    __slots__ = ("codes", "levels", "values")

    def __init__(self, k1: int) -> None:
        self.codes = np.zeros(0, dtype=np.int64)
        self.levels = np.zeros(0, dtype=np.int8)
        self.values = np.zeros((0, k1), dtype=np.int16)

    def __len__(self) -> int:
        return len(self.codes)

    def find(self, codes: np.ndarray) -> np.ndarray:
        """Index of the leaf holding each (sorted) code, -1 where unknown."""
        out = np.full(len(codes), -1, dtype=np.int64)
        if len(self.codes) == 0:
            return out
        pos = np.searchsorted(self.codes, codes, side="right") - 1
        p = np.maximum(pos, 0)
        ok = (pos >= 0) & (codes < self.codes[p] + _span(self.levels[p]))
        out[ok] = pos[ok]
        return out

    def add(self, codes: np.ndarray, deltas: np.ndarray, prior_row: np.ndarray,
            update: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> int:
        """``h <- update(h, delta)`` at sorted unique codes of this block, unknown cells starting
        at ``prior_row`` (see :meth:`~.semantic_octree.SemanticOctree.add`)."""
        pos, state = self._locate(codes)
        exact = state == 1
        fresh = state == 0
        coarse = np.flatnonzero(state == 2)
        split_codes = np.zeros(0, dtype=np.int64)
        split_rows = np.zeros((0, self.values.shape[1]), dtype=np.int16)
        split_nodes = np.zeros(0, dtype=np.int64)
        whole_codes = np.zeros(0, dtype=np.int64)
        whole_levels = np.zeros(0, dtype=np.int8)
        n_changed = int(exact.sum() + fresh.sum())
        if len(coarse):
            cpos = pos[coarse]
            old = self._rows(cpos)
            new = update(old, deltas[coarse])
            change = np.any(new != old, axis=1)
            coarse, cpos, new = coarse[change], cpos[change], new[change]
            n_changed += len(coarse)
            nodes, first = unique_sorted(cpos)
            count = np.diff(np.append(first, len(cpos)))
            whole = count == _span(self.levels[nodes])
            if whole.any():
                same = np.all(deltas[coarse] == deltas[coarse[first]].repeat(count, axis=0), axis=1)
                whole &= np.logical_and.reduceat(same, first)
                whole_nodes = nodes[whole]
                self._set_rows(whole_nodes, new[first[whole]])
                whole_codes = self.codes[whole_nodes]
                whole_levels = self.levels[whole_nodes].copy()
            part = ~np.repeat(whole, count)
            split_codes, split_rows = codes[coarse[part]], new[part]
            split_nodes = cpos[part]
        if exact.any():
            idx = pos[exact]
            self._set_rows(idx, update(self._rows(idx), deltas[exact]))
        new_codes = [codes[fresh]]
        new_levels = [np.zeros(int(fresh.sum()), dtype=np.int8)]
        new_rows = [update(prior_row[None, :], deltas[fresh])]
        gone = np.zeros(0, dtype=np.int64)
        if len(split_codes):
            cover_codes, cover_levels, cover_src = self._cover(split_codes, split_nodes)
            new_codes += [cover_codes, split_codes]
            new_levels += [cover_levels, np.zeros(len(split_codes), dtype=np.int8)]
            new_rows += [self._rows(cover_src), split_rows]
            gone = unique_sorted(split_nodes)[0]
        all_codes = np.concatenate(new_codes)
        if len(all_codes):
            order = np.argsort(all_codes)
            self._splice(
                gone,
                all_codes[order],
                np.concatenate(new_levels)[order],
                np.concatenate(new_rows)[order],
            )
        touched = np.concatenate([codes[exact], codes[fresh], split_codes])
        touched.sort()
        self._prune_from(touched, whole_codes, whole_levels)
        return n_changed

    def remove(self, codes: np.ndarray) -> None:
        """Forget finest-level cells (sorted unique codes of this block)."""
        if len(self.codes) == 0:
            return
        pos, state = self._locate(codes)
        inside = state == 2
        gone = np.concatenate([pos[state == 1], unique_sorted(pos[inside])[0]])
        if len(gone) == 0:
            return
        cc, cl, src = self._cover(codes[inside], pos[inside])
        self._splice(np.sort(gone), cc, cl, self._rows(src))

    def _locate(self, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Leaf index per code and its state: 0 unknown, 1 finest leaf, 2 inside a coarser leaf."""
        n = len(self.codes)
        if n == 0:
            return np.full(len(codes), -1, dtype=np.int64), np.zeros(len(codes), dtype=np.int8)
        pos = np.searchsorted(self.codes, codes, side="right") - 1
        p = np.maximum(pos, 0)
        lev = self.levels[p]
        inside = (pos >= 0) & (codes < self.codes[p] + _span(lev))
        state = np.where(inside, np.where(lev == 0, 1, 2), 0).astype(np.int8)
        return pos, state

    def _rows(self, idx: np.ndarray) -> np.ndarray:
        """Rows at leaf indices (``take`` is several times faster than fancy indexing)."""
        return self.values.take(idx, axis=0)

    def _set_rows(self, idx: np.ndarray, rows: np.ndarray) -> None:
        self._row_view(self.values)[idx] = self._row_view(np.asarray(rows, dtype=np.int16))

    def _row_view(self, rows: np.ndarray) -> np.ndarray:
        """Rows as one opaque item each, so that moving rows is a single copy per row."""
        return np.ascontiguousarray(rows).view(np.dtype((np.void, rows.shape[1] * 2))).reshape(-1)

    def _splice(
        self, gone: np.ndarray, codes: np.ndarray, levels: np.ndarray, rows: np.ndarray
    ) -> None:
        """Delete the leaves at sorted indices ``gone`` and merge in sorted new leaves."""
        old_codes, old_levels, old_values = self.codes, self.levels, self.values
        if len(gone):
            keep = np.ones(len(old_codes), dtype=np.bool_)
            keep[gone] = False
            kept = np.flatnonzero(keep)
            old_codes, old_levels = old_codes[kept], old_levels[kept]
            old_values = old_values.take(kept, axis=0)
        n, m = len(old_codes), len(codes)
        at = np.searchsorted(old_codes, codes) + np.arange(m)
        rest = np.ones(n + m, dtype=np.bool_)
        rest[at] = False
        out_codes = np.empty(n + m, dtype=np.int64)
        out_levels = np.empty(n + m, dtype=np.int8)
        out_values = np.empty((n + m, self.values.shape[1]), dtype=np.int16)
        out_codes[at], out_codes[rest] = codes, old_codes
        out_levels[at], out_levels[rest] = levels, old_levels
        ov = self._row_view(out_values)
        ov[at], ov[rest] = self._row_view(rows), self._row_view(old_values)
        self.codes, self.levels, self.values = out_codes, out_levels, out_values

    def _cover(
        self, targets: np.ndarray, node_pos: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The leaves that replace coarse leaves split down to the ``targets`` (excluded).

        Along the path from a coarse leaf to each target, every split node's other children
        become leaves with the coarse leaf's value (OctoMap's ``expandNode``). Returns their
        sorted codes, levels and the index of the coarse leaf whose value they take.
        """
        if len(targets) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int8), np.zeros(0, np.int64)
        tlev = self.levels[node_pos].astype(np.int64)
        out_codes, out_levels, out_src = [], [], []
        for lev in range(int(tlev.max()) - 1, -1, -1):
            act = tlev > lev
            t, src = targets[act], node_pos[act]
            parents, first = unique_sorted(t >> (3 * (lev + 1)))
            children = ((parents[:, None] << 3) | _ARANGE8).ravel()
            keep = ~_isin_sorted(children, unique_sorted(t >> (3 * lev))[0])
            out_codes.append(children[keep] << (3 * lev))
            out_levels.append(np.full(int(keep.sum()), lev, dtype=np.int8))
            out_src.append(np.repeat(src[first], 8)[keep])
        codes = np.concatenate(out_codes)
        order = np.argsort(codes)
        return codes[order], np.concatenate(out_levels)[order], np.concatenate(out_src)[order]

    def _prune_from(
        self,
        touched: np.ndarray,
        extra_codes: np.ndarray | None = None,
        extra_levels: np.ndarray | None = None,
        full: bool = False,
    ) -> None:
        """Collapse identical sibling groups on the branches above the changed leaves.

        ``touched`` are changed finest-level codes; ``extra_codes``/``extra_levels`` are
        coarser leaves changed as a whole. Level 1 checks the 8 consecutive entries after the
        first child (the arrays are still compact). Higher levels look children up by their
        exact start code, which never hits an entry already collapsed away in this pass (those
        starts are not aligned to the level), so deletions wait for one compaction at the end.
        ``full`` re-checks every node of the block (used by :meth:`~.semantic_octree.SemanticOctree.prune`).
        """
        n = len(self.codes)
        if n < 8:
            return
        codes, levels, values = self.codes, self.levels, self.values
        seeds: dict[int, np.ndarray] = {}
        if extra_codes is not None and len(extra_codes):
            el = cast(np.ndarray, extra_levels).astype(np.int64)  # given with extra_codes
            for lev in np.unique(el):
                seeds[int(lev) + 1] = np.unique(extra_codes[el == lev] >> (3 * (int(lev) + 1)))
        deleted = np.zeros(n, dtype=np.bool_)
        any_deleted = False
        cand = unique_sorted(touched >> 3)[0]
        for lev in range(1, PRUNE_MAX_LEVEL + 1):
            if lev in seeds:
                cand = np.union1d(cand, seeds[lev])
            if len(cand) == 0:
                if not any(k > lev for k in seeds):
                    break
                continue
            base = cand << (3 * lev)
            if lev == 1:
                first = np.searchsorted(codes, base)
                ok = first + 7 < n
                first, base, cand = first[ok], base[ok], cand[ok]
                ok = (codes[first] == base) & (codes[first + 7] == base + 7)
                first, cand = first[ok], cand[ok]
                idx = first[:, None] + _ARANGE8
                ok = np.all(levels[idx] == 0, axis=1)
            else:
                starts = base[:, None] + (_ARANGE8 << (3 * (lev - 1)))
                idx = np.searchsorted(codes, starts).clip(max=n - 1)
                ok = np.all((codes[idx] == starts) & (levels[idx] == lev - 1), axis=1)
                ok &= ~np.any(deleted[idx], axis=1)
            idx, cand = idx[ok], cand[ok]
            rv = values.take(idx.ravel(), axis=0).reshape(idx.shape + values.shape[1:])
            same = np.all(rv == rv[:, :1], axis=(1, 2))
            idx, cand = idx[same], cand[same]
            if len(idx):
                levels[idx[:, 0]] = lev
                deleted[idx[:, 1:].ravel()] = True
                any_deleted = True
            nxt = cand >> 3
            if full:
                nxt = np.union1d(nxt, codes[(levels == lev) & ~deleted] >> (3 * (lev + 1)))
            cand = unique_sorted(nxt)[0]
        if any_deleted:
            kept = np.flatnonzero(~deleted)
            self.codes, self.levels = codes[kept], levels[kept]
            self.values = values.take(kept, axis=0)

