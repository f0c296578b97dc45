"""Multi-class semantic octree: a linear octree of clamped semantic log-odds (docs/algorithms/mapping.md).

Representation
    Three parallel arrays sorted by Morton code (:mod:`kimera_multi_py.mapping.morton`):
    ``codes`` (int64, the first voxel of each leaf), ``levels`` (int8, 0 = one voxel) and
    ``values`` (int16, ``(n, K+1)``): per leaf the log-odds vector ``h`` against the free class,
    in fixed point (:mod:`.observation`). The arrays are kept per *block*
    (:mod:`.octree_block`), a node of level ``BLOCK_LEVEL`` (3.2 m at 0.1 m), so that a scan only
    moves the memory of the blocks it sees and its cost does not grow with the map; pruning
    therefore stops at block size.

Updates follow the inverse sensor model of :class:`~.observation.ObservationModel`.
Insertion (:meth:`SemanticOctree.insert_scan`) is vectorised end to end: the DDA of
:mod:`.raycast`, one ``np.searchsorted`` merge, an update of all touched rows at once, and
pruning of the touched branches level by level.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from kimera_multi_py.mapping import morton
from kimera_multi_py.mapping.observation import SCALE, ObservationModel, occupied_mask, quantise
from kimera_multi_py.mapping.octree_block import BLOCK_SHIFT, OctreeBlock, pruned, unique_sorted
from kimera_multi_py.mapping.raycast import ScanCells, scan_cells


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
        self._blocks: dict[int, OctreeBlock] = {}
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
            out[lev] = unique_sorted(codes[levels < lev] >> (3 * lev))[0]
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
        bids = codes >> BLOCK_SHIFT
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
                blk = self._blocks[bid] = OctreeBlock(k1)
            changed += blk.add(codes[sl], deltas[sl], self.model.prior_row, self._update_rows)
        return changed

    def set_cells(self, codes: np.ndarray, rows: np.ndarray) -> None:
        """Overwrite finest-level cells (sorted unique codes) with fixed-point rows."""
        if len(codes) == 0:
            return
        rows = self.model.clamp(np.asarray(rows, dtype=np.int16).copy())
        rows[:, 0] = 0
        if not self._blocks:  # an empty tree: the pruned leaves in one pass
            codes = np.asarray(codes, dtype=np.int64).reshape(-1)
            if codes[0] < 0 or np.any(codes[1:] <= codes[:-1]):
                raise ValueError("codes must be non-negative, sorted and unique")
            self._set_arrays(*pruned(codes, self._compress(rows)))
            return
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
            blk = self._blocks[bid] = OctreeBlock(k1)
            blk.codes = np.array(codes[sl], dtype=np.int64)
            blk.levels = np.array(levels[sl], dtype=np.int8)
            blk.values = np.array(values[sl], dtype=np.int16)

    def _update_rows(self, rows: np.ndarray, deltas: np.ndarray) -> np.ndarray:
        """The rows after an update: ``compress(clamp(rows + deltas))``."""
        return self._compress(self._clamped_sum(rows, deltas))

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
        value = self.model.clamp(quantise(hmax + np.log(mean)))
        occ = rows[:, 1:]
        np.copyto(occ, np.broadcast_to(value, occ.shape).astype(np.int16), where=others)
        return rows
