"""Multi-class semantic octree: a linear octree of clamped semantic log-odds (docs/algorithms/mapping.md).

Representation
    Three parallel arrays sorted by Morton code (:mod:`kimera_multi_py.mapping.morton`):
    ``codes`` (int64, the first voxel of each leaf), ``levels`` (int8, 0 = one voxel) and
    ``values`` (int16, ``(n, K+1)``): per leaf the log-odds vector ``h`` against the free class,
    in fixed point (``SCALE`` steps per unit), column 0 (free) is the pivot and always 0.
    Fixed point makes every update an exact integer addition, so identical evidence gives
    bit-identical cells (pruning) and de-integrating a submap is exact (:mod:`.submaps`).
    The arrays are kept per *block*, a node of level ``BLOCK_LEVEL`` (3.2 m at 0.1 m), so that
    a scan only moves the memory of the blocks it sees and its cost does not grow with the
    map; pruning therefore stops at block size.

Observation model (all configurable)
    A cell holding end points of one scan gets ``l = phi_hit + psi * f`` where ``f`` is the
    fraction of its end points per class; a cell a ray passes through gets ``l = miss`` on every
    class. ``phi_hit`` is "occupied, class unknown" spread evenly over the K classes and chosen so
    that a cell at the uniform prior gains exactly ``hit`` in occupancy log-odds.
    ``psi = log(acc (K-1) / (1-acc))`` is the log-likelihood ratio of a label that is right with
    probability ``acc`` (this lets the observed class win and the others fall, so clamped cells
    converge to identical vectors). New cells start at the prior ``-log K`` on every class
    (occupancy probability 0.5). After each update every entry is clamped to ``[h_min, h_max]``.

Insertion (:meth:`SemanticOctree.insert_scan`) is vectorised end to end: the DDA of
:mod:`.raycast`, one ``np.searchsorted`` merge, an update of all touched rows at once, and
pruning of the touched branches level by level.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from kimera_multi_py.mapping import morton
from kimera_multi_py.mapping.raycast import ScanCells, scan_cells

log = logging.getLogger(__name__)

SCALE = 1024  # fixed-point steps per unit of log-odds
MAX_ABS_LOGODDS = 15.0  # keeps h + l inside int16
BLOCK_LEVEL = 5  # leaves are stored per node of this level; it is also the largest leaf
PRUNE_MAX_LEVEL = BLOCK_LEVEL
_BLOCK_SHIFT = 3 * BLOCK_LEVEL
_ARANGE8 = np.arange(8, dtype=np.int64)


def _q(x: float | np.ndarray) -> np.ndarray:
    """Quantise log-odds to fixed point."""
    return np.round(np.asarray(x, dtype=np.float64) * SCALE).astype(np.int64)


def _unique_sorted(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


class ObservationModel:
    """Fixed-point inverse sensor model shared by the octree and the submaps."""

    def __init__(
        self,
        num_classes: int,
        hit: float = 0.85,
        miss: float = -0.4,
        psi: float | None = None,
        label_accuracy: float = 0.9,
        h_min: float = -5.0,
        h_max: float = 5.0,
        prior: float | None = None,
    ) -> None:
        if num_classes < 1:
            raise ValueError(f"num_classes must be at least 1, got {num_classes}")
        if not 0.0 < label_accuracy < 1.0:
            raise ValueError(f"label_accuracy must lie in (0, 1), got {label_accuracy}")
        given = {
            "hit": hit,
            "miss": miss,
            "psi": psi,
            "h_min": h_min,
            "h_max": h_max,
            "prior": prior,
        }
        bad = [k for k, v in given.items() if v is not None and not np.isfinite(v)]
        if bad:
            raise ValueError(f"non-finite observation model parameters: {', '.join(bad)}")
        K = int(num_classes)
        if psi is None:
            psi = float(np.log(label_accuracy * max(K - 1, 1) / (1.0 - label_accuracy)))
        if prior is None:
            prior = -float(np.log(K))
        phi = hit - float(np.log((K - 1 + np.exp(psi)) / K))
        if not (-MAX_ABS_LOGODDS <= h_min < 0.0 < h_max <= MAX_ABS_LOGODDS):
            raise ValueError(
                f"need -{MAX_ABS_LOGODDS} <= h_min < 0 < h_max <= {MAX_ABS_LOGODDS}, "
                f"got [{h_min}, {h_max}]"
            )
        if not h_min <= prior <= h_max:
            raise ValueError(f"prior {prior} outside [{h_min}, {h_max}]")
        for name, v in (("miss", miss), ("phi_hit", phi), ("phi_hit + psi", phi + psi)):
            if abs(v) > MAX_ABS_LOGODDS:
                raise ValueError(f"{name} = {v} exceeds {MAX_ABS_LOGODDS} in magnitude")
        if miss >= 0:
            raise ValueError(f"miss must be negative, got {miss}")
        self.num_classes = K
        self.hit, self.miss, self.psi, self.phi = float(hit), float(miss), float(psi), float(phi)
        self.label_accuracy = float(label_accuracy)
        self.h_min, self.h_max, self.prior = float(h_min), float(h_max), float(prior)
        self.lo, self.hi = int(_q(h_min)), int(_q(h_max))
        self.miss_row = np.zeros(K + 1, dtype=np.int16)
        self.miss_row[1:] = _q(miss)
        self.prior_row = np.zeros(K + 1, dtype=np.int16)
        self.prior_row[1:] = _q(prior)
        # quantised hit rows for every label fraction are built on demand

    def params(self) -> dict[str, float]:
        return {
            "hit": self.hit,
            "miss": self.miss,
            "psi": self.psi,
            "label_accuracy": self.label_accuracy,
            "h_min": self.h_min,
            "h_max": self.h_max,
            "prior": self.prior,
        }

    def hit_rows(self, label_counts: np.ndarray) -> np.ndarray:
        """Update rows ``(m, K+1)`` int16 for cells with these end-point label histograms."""
        counts = np.asarray(label_counts, dtype=np.float64)
        total = counts[:, 1:].sum(axis=1, keepdims=True)
        rows = np.zeros(counts.shape, dtype=np.int16)
        frac = counts[:, 1:] / np.maximum(total, 1.0)
        rows[:, 1:] = _q(self.phi + self.psi * frac)
        return rows

    def deltas(self, cells: ScanCells) -> tuple[np.ndarray, np.ndarray]:
        """Sorted codes and their update rows ``(m, K+1)`` int16 for one scan's cells."""
        free, occ = cells.free, cells.occupied
        m = len(free) + len(occ)
        at = np.searchsorted(free, occ) + np.arange(len(occ))  # merge two sorted runs
        is_free = np.ones(m, dtype=np.bool_)
        is_free[at] = False
        codes = np.empty(m, dtype=np.int64)
        codes[at] = occ
        codes[is_free] = free
        rows = np.empty((m, self.num_classes + 1), dtype=np.int16)
        rows[:] = self.miss_row
        rows[at] = self.hit_rows(cells.label_counts)
        return codes, rows

    def clamp(self, rows: np.ndarray) -> np.ndarray:
        """Clamp fixed-point rows in place (column 0 stays 0 since ``lo < 0 < hi``)."""
        return np.clip(rows, self.lo, self.hi, out=rows)


class _Block:
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

    def add(self, codes: np.ndarray, deltas: np.ndarray, tree: SemanticOctree) -> int:
        """``h <- clamp(h + delta)`` at sorted unique codes of this block (see the tree's)."""
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
            new = tree._compress(tree._clamped_sum(old, deltas[coarse]))
            change = np.any(new != old, axis=1)
            coarse, cpos, new = coarse[change], cpos[change], new[change]
            n_changed += len(coarse)
            nodes, first = _unique_sorted(cpos)
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
            self._set_rows(idx, tree._compress(tree._clamped_sum(self._rows(idx), deltas[exact])))
        new_codes = [codes[fresh]]
        new_levels = [np.zeros(int(fresh.sum()), dtype=np.int8)]
        new_rows = [tree._compress(tree._clamped_sum(tree.model.prior_row[None, :], deltas[fresh]))]
        gone = np.zeros(0, dtype=np.int64)
        if len(split_codes):
            cover_codes, cover_levels, cover_src = self._cover(split_codes, split_nodes)
            new_codes += [cover_codes, split_codes]
            new_levels += [cover_levels, np.zeros(len(split_codes), dtype=np.int8)]
            new_rows += [self._rows(cover_src), split_rows]
            gone = _unique_sorted(split_nodes)[0]
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
        gone = np.concatenate([pos[state == 1], _unique_sorted(pos[inside])[0]])
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
            parents, first = _unique_sorted(t >> (3 * (lev + 1)))
            children = ((parents[:, None] << 3) | _ARANGE8).ravel()
            keep = ~_isin_sorted(children, _unique_sorted(t >> (3 * lev))[0])
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
        ``full`` re-checks every node of the block (used by :meth:`SemanticOctree.prune`).
        """
        n = len(self.codes)
        if n < 8:
            return
        codes, levels, values = self.codes, self.levels, self.values
        seeds: dict[int, np.ndarray] = {}
        if extra_codes is not None and len(extra_codes):
            el = extra_levels.astype(np.int64)
            for lev in np.unique(el):
                seeds[int(lev) + 1] = np.unique(extra_codes[el == lev] >> (3 * (int(lev) + 1)))
        deleted = np.zeros(n, dtype=np.bool_)
        any_deleted = False
        cand = _unique_sorted(touched >> 3)[0]
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
            cand = _unique_sorted(nxt)[0]
        if any_deleted:
            kept = np.flatnonzero(~deleted)
            self.codes, self.levels = codes[kept], levels[kept]
            self.values = values.take(kept, axis=0)


@dataclass
class Leaves:
    """All leaves at once: centres, edge lengths, levels and float log-odds."""

    centers: np.ndarray  # (n, 3)
    sizes: np.ndarray  # (n,)
    levels: np.ndarray  # (n,)
    logodds: np.ndarray  # (n, K+1) float32


class SemanticOctree:
    """A multi-class semantic occupancy octree stored as a linear octree (see module docs).

    ``dynamic_classes`` are class ids whose end points only clear free space (dynamic masking).
    ``top_k`` keeps, after each update, the ``top_k`` most likely classes and replaces the
    others by their log-mean-exp ("others"), as SSMI does; ``None`` keeps all K classes.
    ``free_margin`` and ``surface_offset`` are the sensor-model options of
    :func:`~.raycast.scan_cells` (both 0 reproduce OctoMap's scan insertion).
    """

    def __init__(
        self,
        resolution: float,
        num_classes: int,
        *,
        hit: float = 0.85,
        miss: float = -0.4,
        psi: float | None = None,
        label_accuracy: float = 0.9,
        h_min: float = -5.0,
        h_max: float = 5.0,
        prior: float | None = None,
        dynamic_classes: Iterable[int] = (),
        top_k: int | None = None,
        free_margin: float = 0.0,
        surface_offset: float = 0.0,
    ) -> None:
        if not (resolution > 0 and np.isfinite(resolution)):
            raise ValueError(f"resolution must be positive, got {resolution}")
        self.resolution = float(resolution)
        self.model = ObservationModel(
            num_classes, hit, miss, psi, label_accuracy, h_min, h_max, prior
        )
        self.num_classes = self.model.num_classes
        self.dynamic_classes = tuple(sorted({int(c) for c in dynamic_classes}))
        if any(c < 1 or c > self.num_classes for c in self.dynamic_classes):
            raise ValueError(f"dynamic classes must lie in 1..{self.num_classes}")
        if top_k is not None and not 1 <= top_k <= self.num_classes:
            raise ValueError(f"top_k must lie in 1..{self.num_classes}, got {top_k}")
        self.top_k = None if top_k is None or top_k >= self.num_classes - 1 else int(top_k)
        if not (free_margin >= 0 and surface_offset >= 0):
            raise ValueError("free_margin and surface_offset must be non-negative")
        self.free_margin = float(free_margin)
        self.surface_offset = float(surface_offset)
        self._blocks: dict[int, _Block] = {}
        self._flat_cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def options(self) -> dict[str, object]:
        """The keyword arguments that build an empty octree like this one."""
        return {
            **self.model.params(),
            "dynamic_classes": self.dynamic_classes,
            "top_k": self.top_k,
            "free_margin": self.free_margin,
            "surface_offset": self.surface_offset,
        }

    def empty_like(self, **overrides: object) -> SemanticOctree:
        """An empty octree with this one's resolution, classes and options (``overrides`` win)."""
        return SemanticOctree(self.resolution, self.num_classes, **{**self.options(), **overrides})  # type: ignore[arg-type]

    # ---- read access ----------------------------------------------------------------------
    def _flat(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All blocks' arrays concatenated in Morton order (cached until the next change)."""
        if self._flat_cache is None:
            blocks = [self._blocks[b] for b in sorted(self._blocks)]
            k1 = self.num_classes + 1
            codes = np.concatenate([b.codes for b in blocks]) if blocks else np.zeros(0, np.int64)
            levels = np.concatenate([b.levels for b in blocks]) if blocks else np.zeros(0, np.int8)
            values = (
                np.concatenate([b.values for b in blocks])
                if blocks
                else np.zeros((0, k1), np.int16)
            )
            for a in (codes, levels, values):
                a.flags.writeable = False
            self._flat_cache = (codes, levels, values)
        return self._flat_cache

    @property
    def codes(self) -> np.ndarray:
        """Start Morton codes of the leaves (sorted, read-only)."""
        return self._flat()[0]

    @property
    def levels(self) -> np.ndarray:
        """Leaf levels (0 = one voxel), read-only."""
        return self._flat()[1]

    @property
    def values(self) -> np.ndarray:
        """Fixed-point log-odds ``(n, K+1)`` int16 (divide by ``SCALE``), read-only."""
        return self._flat()[2]

    @property
    def logodds(self) -> np.ndarray:
        """Float log-odds ``(n, K+1)`` of the leaves."""
        return self.values.astype(np.float32) / np.float32(SCALE)

    @property
    def num_leaves(self) -> int:
        return sum(len(b) for b in self._blocks.values())

    @property
    def num_nodes(self) -> int:
        """Leaves plus inner nodes (root included), as OctoMap's ``size()`` counts them."""
        return self.num_leaves + sum(len(ids) for ids in self._inner_nodes().values())

    @property
    def nbytes(self) -> int:
        """Bytes held by the leaf arrays."""
        return int(
            sum(b.codes.nbytes + b.levels.nbytes + b.values.nbytes for b in self._blocks.values())
        )

    def __len__(self) -> int:
        return self.num_leaves

    def _inner_nodes(self) -> dict[int, np.ndarray]:
        """Sorted ids (``start >> 3*level``) of the inner nodes at each level 1..16."""
        out: dict[int, np.ndarray] = {}
        codes, levels, _ = self._flat()
        if len(codes) == 0:
            return out
        for lev in range(1, morton.TREE_DEPTH + 1):
            out[lev] = _unique_sorted(codes[levels < lev] >> (3 * lev))[0]
        return out

    def leaves(self) -> Leaves:
        """All leaves at once (vectorised), in Morton order."""
        codes, levels, _ = self._flat()
        sizes = self.resolution * np.ldexp(1.0, levels.astype(np.int64))
        return Leaves(
            morton.node_centers(codes, levels, self.resolution), sizes, levels.copy(), self.logodds
        )

    def iter_leaves(self) -> Iterator[tuple[np.ndarray, float, np.ndarray]]:
        """Yield ``(center, size, logodds)`` per leaf, in Morton order."""
        lv = self.leaves()
        for i in range(len(lv.sizes)):
            yield lv.centers[i], float(lv.sizes[i]), lv.logodds[i]

    # ---- queries ---------------------------------------------------------------------------
    def _groups(self, codes: np.ndarray) -> Iterator[tuple[int, slice]]:
        """``(block id, slice)`` runs of sorted codes."""
        if len(codes) == 0:
            return
        bids = codes >> _BLOCK_SHIFT
        cuts = np.flatnonzero(bids[1:] != bids[:-1]) + 1
        bounds = [0, *cuts.tolist(), len(codes)]
        for s, e in zip(bounds[:-1], bounds[1:], strict=True):
            yield int(bids[s]), slice(s, e)

    def _lookup(self, codes: np.ndarray, want_rows: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Rows (or flat leaf indices) at any codes; -1 codes and unknown cells are not found.

        Returns ``(rows (m, K+1) int16, known)`` or, with ``want_rows=False``,
        ``(leaf index (m,), known)`` into the Morton-ordered leaf arrays.
        """
        codes = np.asarray(codes, dtype=np.int64).reshape(-1)
        m = len(codes)
        known = np.zeros(m, dtype=np.bool_)
        out = (
            np.zeros((m, self.num_classes + 1), dtype=np.int16)
            if want_rows
            else np.full(m, -1, dtype=np.int64)
        )
        if m == 0 or not self._blocks:
            return out, known
        order = np.argsort(codes)
        sc = codes[order]
        first_valid = int(np.searchsorted(sc, 0))
        offsets = {}
        if not want_rows:
            start = 0
            for b in sorted(self._blocks):
                offsets[b] = start
                start += len(self._blocks[b])
        for bid, sl in self._groups(sc[first_valid:]):
            blk = self._blocks.get(bid)
            if blk is None:
                continue
            sl = slice(sl.start + first_valid, sl.stop + first_valid)
            idx = blk.find(sc[sl])
            ok = idx >= 0
            dst = order[sl][ok]
            known[dst] = True
            out[dst] = blk.values.take(idx[ok], axis=0) if want_rows else idx[ok] + offsets[bid]
        return out, known

    def find(self, points: np.ndarray) -> np.ndarray:
        """Index into the Morton-ordered leaf arrays of the leaf holding each point, or -1."""
        return self._lookup(morton.points_to_codes(points, self.resolution), want_rows=False)[0]

    def logodds_at(self, points: np.ndarray) -> np.ndarray:
        """Log-odds ``(n, K+1)`` at points; NaN rows where unknown."""
        rows, ok = self._lookup(morton.points_to_codes(points, self.resolution))
        out = rows.astype(np.float32) / np.float32(SCALE)
        out[~ok] = np.nan
        return out

    def pmf_at(self, points: np.ndarray) -> np.ndarray:
        """Class PMF ``softmax(h)`` ``(n, K+1)`` at points (column 0 = free); NaN if unknown."""
        h = self.logodds_at(points).astype(np.float64)
        known = ~np.isnan(h[:, 0])
        e = np.exp(h[known] - h[known].max(axis=1, keepdims=True))
        h[known] = e / e.sum(axis=1, keepdims=True)
        return h

    def occupancy_at(self, points: np.ndarray) -> np.ndarray:
        """Probability of being occupied (any class) at points; NaN where unknown."""
        return 1.0 - self.pmf_at(points)[:, 0]

    def class_at(self, points: np.ndarray) -> np.ndarray:
        """Most likely class at points: 0 free, 1..K a class, -1 unknown."""
        rows, ok = self._lookup(morton.points_to_codes(points, self.resolution))
        return np.where(ok, np.argmax(rows, axis=1), -1)

    def occupied_leaves(self) -> np.ndarray:
        """Boolean mask (Morton order) of leaves whose occupancy probability exceeds 0.5."""
        return occupied_mask(self.values)

    def cell_values(self, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fixed-point rows at finest-level codes and a mask of the known ones."""
        return self._lookup(codes)

    # ---- insertion -------------------------------------------------------------------------
    def insert_scan(
        self, origin: np.ndarray, endpoints: np.ndarray, labels: np.ndarray, max_range: float = -1.0
    ) -> int:
        """Integrate one scan (world-frame end points and labels); returns cells updated."""
        return self.insert_cells(self.scan_cells(origin, endpoints, labels, max_range))

    def scan_cells(
        self, origin: np.ndarray, endpoints: np.ndarray, labels: np.ndarray, max_range: float = -1.0
    ) -> ScanCells:
        """The cells a scan would update, with this map's sensor-model options."""
        return scan_cells(
            origin,
            endpoints,
            labels,
            self.resolution,
            self.num_classes,
            max_range,
            self.dynamic_classes,
            self.free_margin,
            self.surface_offset,
        )

    def insert_cells(self, cells: ScanCells) -> int:
        """Integrate the cells of one scan computed by :func:`~.raycast.scan_cells`."""
        codes, rows = self.model.deltas(cells)
        return self.add(codes, rows)

    def add(self, codes: np.ndarray, deltas: np.ndarray) -> int:
        """``h <- clamp(h + delta)`` at unique sorted finest-level ``codes``; returns cells changed.

        Unknown cells start at the prior. A pruned leaf whose voxels all receive the same
        delta is updated as a whole; otherwise it is split only along the paths to the changed
        voxels. The touched branches are pruned again afterwards.
        """
        codes = np.asarray(codes, dtype=np.int64).reshape(-1)
        deltas = np.asarray(deltas, dtype=np.int16)
        if len(codes) == 0:
            return 0
        if deltas.shape != (len(codes), self.num_classes + 1):
            raise ValueError(f"deltas must be ({len(codes)}, {self.num_classes + 1})")
        if codes[0] < 0 or np.any(codes[1:] <= codes[:-1]):
            raise ValueError("codes must be non-negative, sorted and unique")
        self._flat_cache = None
        changed = 0
        k1 = self.num_classes + 1
        for bid, sl in self._groups(codes):
            blk = self._blocks.get(bid)
            if blk is None:
                blk = self._blocks[bid] = _Block(k1)
            changed += blk.add(codes[sl], deltas[sl], self)
        return changed

    def set_cells(self, codes: np.ndarray, rows: np.ndarray) -> None:
        """Overwrite finest-level cells (sorted unique codes) with fixed-point rows."""
        if len(codes) == 0:
            return
        rows = self.model.clamp(np.asarray(rows, dtype=np.int16).copy())
        rows[:, 0] = 0
        current, known = self.cell_values(codes)
        current[~known] = self.model.prior_row
        self.add(codes, rows - current)

    def remove_cells(self, codes: np.ndarray) -> None:
        """Forget finest-level cells (sorted unique codes): they become unknown again."""
        codes = np.asarray(codes, dtype=np.int64).reshape(-1)
        if len(codes) == 0:
            return
        self._flat_cache = None
        for bid, sl in self._groups(codes):
            blk = self._blocks.get(bid)
            if blk is None:
                continue
            blk.remove(codes[sl])
            if len(blk) == 0:
                del self._blocks[bid]

    def prune(self) -> None:
        """Collapse every group of 8 identical sibling leaves, bottom-up over the whole tree."""
        self._flat_cache = None
        for blk in self._blocks.values():
            blk._prune_from(blk.codes[blk.levels == 0], full=True)

    def clear(self) -> None:
        self._blocks = {}
        self._flat_cache = None

    def _set_arrays(self, codes: np.ndarray, levels: np.ndarray, values: np.ndarray) -> None:
        """Replace the content by validated, Morton-ordered leaf arrays (used when loading)."""
        self.clear()
        k1 = self.num_classes + 1
        for bid, sl in self._groups(np.asarray(codes, dtype=np.int64)):
            blk = self._blocks[bid] = _Block(k1)
            blk.codes = np.array(codes[sl], dtype=np.int64)
            blk.levels = np.array(levels[sl], dtype=np.int8)
            blk.values = np.array(values[sl], dtype=np.int16)

    def _clamped_sum(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        out = np.add(a, b, dtype=np.int16)
        return self.model.clamp(out)

    def _compress(self, rows: np.ndarray) -> np.ndarray:
        """Top-K + "others": non-top classes share their log-mean-exp (in place)."""
        if self.top_k is None or len(rows) == 0:
            return rows
        h = rows[:, 1:].astype(np.float64) / SCALE
        order = np.argpartition(-h, self.top_k - 1, axis=1)
        others = np.ones(h.shape, dtype=np.bool_)
        np.put_along_axis(others, order[:, : self.top_k], False, axis=1)
        hmax = h.max(axis=1, keepdims=True)
        mean = np.where(others, np.exp(h - hmax), 0.0).sum(1, keepdims=True) / others.sum(
            1, keepdims=True
        )
        value = self.model.clamp(_q(hmax + np.log(mean)))
        occ = rows[:, 1:]
        np.copyto(occ, np.broadcast_to(value, occ.shape).astype(np.int16), where=others)
        return rows


def occupied_mask(values: np.ndarray) -> np.ndarray:
    """Rows (fixed point) whose occupancy probability exceeds 0.5: ``logsumexp(h[1:]) > 0``."""
    h = values[:, 1:].astype(np.float64) / SCALE
    hmax = h.max(axis=1) if h.shape[1] else np.zeros(len(h))
    lse = hmax + np.log(np.exp(h - hmax[:, None]).sum(axis=1))
    return lse > 0.0
