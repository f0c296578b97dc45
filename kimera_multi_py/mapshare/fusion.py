"""Fusion of submap evidence into a team map: incremental (per robot) and centralised
(docs/algorithms/map_consensus.md).

A *record* is one submap of one robot: its reference pose ``T_ref`` (where its voxel grid was
laid down), its current pose ``T`` and its integer evidence ``dh`` (fixed-point rows, column 0
free = 0) on the reference grid. The team map of a set of records is

    clamp(prior + sum_records map_codes(dh, T T_ref^-1))

with the cells that no record reaches left unknown, exactly as a robot's own
:class:`~kimera_multi_py.mapping.submaps.SubmapMap` builds its map from its own submaps. Since
the sums are integers, the order in which records, cells and poses arrive does not matter:
:class:`EvidenceMap` (updated incrementally by a robot's map consensus) and
:func:`fuse_records` (the centralised fusion, in one batch) give the same cells bit for bit.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from kimera_multi_py.mapping.palette import index_dtype, unique_rows
from kimera_multi_py.mapping.semantic_octree import SemanticOctree
from kimera_multi_py.mapping.submaps import (
    _BATCH_CELLS,
    SubmapMap,
    _Batch,
    _CellStore,
    _group_sum,
    correction,
    group_sum_indexed,
    group_sums,
    map_codes,
)

Key = tuple[int, int]  # (robot, submap)


@dataclass
class SubmapRecord:
    """One robot's submap evidence: reference and current pose, reference-grid cells and rows."""

    robot: int
    submap: int
    T_ref: np.ndarray  # (4, 4)
    T: np.ndarray  # (4, 4)
    codes: np.ndarray  # (n,) int64, sorted unique, on the reference grid
    rows: np.ndarray  # (n, K+1) int32

    @property
    def key(self) -> Key:
        return (self.robot, self.submap)


def records_of(robot: int, local: SubmapMap) -> list[SubmapRecord]:
    """The records of a robot's own map (its submaps at their applied poses)."""
    return [
        SubmapRecord(robot, sid, s.T_ref.copy(), s.T.copy(), s.codes.copy(), s.rows.copy())
        for sid, s in sorted(local.submaps.items())
    ]


def union_sorted(*arrays: np.ndarray) -> np.ndarray:
    """The sorted union of int64 code arrays (faster than ``np.union1d`` for large inputs)."""
    parts = [np.asarray(x, dtype=np.int64) for x in arrays]
    if not parts:
        return np.zeros(0, np.int64)
    base = max(parts, key=len)
    if all(_subset(p, base) for p in parts if p is not base):
        return base.copy()  # the common case once maps agree: no sort
    a = np.concatenate(parts)
    a.sort()
    keep = np.empty(len(a), np.bool_)
    keep[0] = True
    np.not_equal(a[1:], a[:-1], out=keep[1:])
    return a[keep]


def _subset(small: np.ndarray, big: np.ndarray) -> bool:
    """Whether the sorted codes ``small`` all occur in the sorted codes ``big``."""
    if len(small) == 0:
        return True
    if len(small) > len(big):
        return False
    pos = np.searchsorted(big, small).clip(max=len(big) - 1)
    return bool(np.all(big[pos] == small))


def view_rows(tree: SemanticOctree, summed: np.ndarray) -> np.ndarray:
    """``clamp(prior + evidence)`` with column 0 = 0, as int16 rows of the octree view."""
    m = tree.model
    vals = np.add(summed, m.prior_row, dtype=np.int32)
    np.clip(vals, m.lo, m.hi, out=vals)
    vals[:, 0] = 0
    return vals.astype(np.int16)


def fuse_records(records: Iterable[SubmapRecord], template: SemanticOctree) -> SemanticOctree:
    """The centralised fusion: one batch sum of every record's world contribution.

    ``template`` gives resolution, classes, clamping, prior and top-K of the result.
    """
    tree = template.empty_like()
    k1 = tree.num_classes + 1
    codes, rows = [], []
    for r in records:
        if len(r.codes) == 0:
            continue
        codes.append(map_codes(r.codes, correction(r.T, r.T_ref), tree.resolution))
        rows.append(np.asarray(r.rows, dtype=np.int32))
    if not codes:
        return tree
    uniq, summed, _ = _group_sum(np.concatenate(codes), np.concatenate(rows).reshape(-1, k1))
    tree.set_cells(uniq, view_rows(tree, summed))
    return tree


def centralised_team_map(
    maps: Mapping[int, SubmapMap], robots: Iterable[int] | None = None
) -> SemanticOctree:
    """The reference team map: every robot's submap evidence fused centrally (``robots``: whose)."""
    ids = sorted(maps) if robots is None else sorted(set(robots))
    if not ids:
        raise ValueError("centralised_team_map needs at least one robot")
    template = maps[ids[0]].template
    return fuse_records((r for i in ids for r in records_of(i, maps[i])), template)


def octree_cells(tree: SemanticOctree) -> tuple[np.ndarray, np.ndarray]:
    """Every known finest-level cell of a tree (pruned leaves expanded): codes and int16 rows."""
    codes, levels, values = tree.codes, tree.levels, tree.values
    if len(codes) == 0:
        return np.zeros(0, np.int64), np.zeros((0, tree.num_classes + 1), np.int16)
    span = np.left_shift(np.int64(1), 3 * levels.astype(np.int64))
    total = int(span.sum())
    starts = np.repeat(codes, span)
    offset = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(span) - span, span)
    return starts + offset, np.repeat(values, span, axis=0)


class _Entry:
    """One record as held: its cells on the reference grid and their rows as a palette.

    A submap's evidence rows repeat (a free cell's row is a multiple of the miss row, and a few
    hundred distinct rows cover a whole submap), so each cell keeps an index into the record's
    palette of distinct int16 rows (docs/performance.md)."""

    __slots__ = ("T_ref", "T", "codes", "palette", "index", "world", "active")

    def __init__(self, k1: int) -> None:
        self.T_ref: np.ndarray | None = None
        self.T: np.ndarray | None = None
        self.codes = np.zeros(0, np.int64)
        self.palette = np.zeros((0, k1), np.int16)  # a submap's evidence stays within +-(h_max - h_min)
        self.index = np.zeros(0, np.uint16)  # per cell: its row in the palette
        self.world: np.ndarray | None = None  # world codes while the entry is in the map
        self.active = False

    @property
    def rows(self) -> np.ndarray:
        """The cells' int16 rows (materialised from the palette)."""
        return self.palette.take(self.index.astype(np.intp), axis=0)

    def rows_at(self, pos: np.ndarray) -> np.ndarray:
        """The int16 rows of the cells at positions ``pos``."""
        return self.palette.take(self.index[pos].astype(np.intp), axis=0)

    def set_rows(self, codes: np.ndarray, rows: np.ndarray, pos: np.ndarray, known: np.ndarray,
                 world: np.ndarray | None) -> None:
        """Set the int16 ``rows`` of sorted unique ``codes`` (``pos``: their insertion points,
        ``known``: which are held already; ``world``: the world codes of the new ones while the
        entry is in the map). The palette ends as exactly the distinct rows the cells hold, so
        the bytes held depend on the evidence only, not on its history."""
        m = len(self.palette)
        uniq, inv = unique_rows(np.concatenate([self.palette, rows.astype(np.int16)]))
        index = inv[:m][self.index.astype(np.intp)] if m else np.zeros(0, np.intp)
        add = inv[m:]
        index[pos[known]] = add[known]
        new = ~known
        if new.any():
            self.codes = np.insert(self.codes, pos[new], codes[new])
            index = np.insert(index, pos[new], add[new])
            if self.world is not None:
                assert world is not None
                self.world = np.insert(self.world, pos[new], world)
        used = np.zeros(len(uniq), np.bool_)
        used[index] = True
        if not used.all():  # rows no cell holds any more
            index = (np.cumsum(used) - 1)[index]
            uniq = uniq[used]
        self.palette = uniq
        self.index = index.astype(index_dtype(len(uniq)))

    @property
    def nbytes(self) -> int:
        world = self.world.nbytes if self.world is not None else 0
        return int(self.codes.nbytes + self.palette.nbytes + self.index.nbytes + world)


class EvidenceMap:
    """An incrementally maintained team map over keyed submap records (see the module docs).

    An entry contributes once it has a pose and is *active* (its robot is aligned into the team
    frame); until then its cells are kept but not in the map. Every change adds or subtracts
    exact integer contributions, so the result never depends on the order of updates.

    The evidence is what is kept up to date; the octree view (:attr:`octree`) is built from it
    when asked for after a change. Robots exchange and compare evidence, and only an export or a
    viewer needs the tree: keeping a tree current through every small update cost more than
    the whole rest of the map consensus.
    """

    def __init__(self, template: SemanticOctree) -> None:
        self.template = template.empty_like()  # resolution, classes, clamping, prior and top-K
        self.resolution = self.template.resolution
        self.k1 = self.template.num_classes + 1
        self.entries: dict[Key, _Entry] = {}
        self._fused = _CellStore(self.k1)
        self._tree: SemanticOctree | None = None  # the octree view while no change came since

    @property
    def octree(self) -> SemanticOctree:
        """The team map as an octree (built on first use after a change; do not change it)."""
        if self._tree is None:
            tree = self.template.empty_like()
            codes, rows, _ = self._fused.arrays()
            if len(codes):
                tree.set_cells(codes, view_rows(tree, rows))
            self._tree = tree
        return self._tree

    def _entry(self, key: Key) -> _Entry:
        e = self.entries.get(key)
        if e is None:
            e = self.entries[key] = _Entry(self.k1)
        return e

    def keys(self) -> list[Key]:
        return sorted(self.entries)

    def set_cells(self, key: Key, codes: np.ndarray, rows: np.ndarray) -> None:
        """Set (absolute values) reference-grid cells of a record; ``codes`` sorted unique."""
        codes = np.asarray(codes, dtype=np.int64)
        rows = np.asarray(rows, dtype=np.int32).reshape(len(codes), self.k1)
        if len(codes) == 0:
            return
        e = self._entry(key)
        pos = np.searchsorted(e.codes, codes)
        known = pos < len(e.codes)
        known[known] = e.codes[pos[known]] == codes[known]
        before = np.zeros_like(rows)
        before[known] = e.rows_at(pos[known])
        change = rows - before
        new = ~known
        w_new = None
        if e.world is not None and new.any():
            assert e.T is not None and e.T_ref is not None
            w_new = map_codes(codes[new], correction(e.T, e.T_ref), self.resolution)
        e.set_rows(codes, rows, pos, known, w_new)
        if e.world is not None:
            idx = np.searchsorted(e.codes, codes)
            self._apply(e.world[idx], change, new.astype(np.int32))

    def set_pose(self, key: Key, T_ref: np.ndarray, T: np.ndarray) -> None:
        """Place a record at pose ``T`` (reference ``T_ref``); moves its contribution exactly."""
        self.set_poses([(key, T_ref, T)])

    def set_poses(self, poses: Iterable[tuple[Key, np.ndarray, np.ndarray]]) -> None:
        """:meth:`set_pose` for several records (key, ``T_ref``, ``T``), their moves applied together."""
        batch = _Batch()
        for key, T_ref, T in poses:
            e = self._entry(key)
            T_ref = np.asarray(T_ref, dtype=np.float64)
            T = np.asarray(T, dtype=np.float64)
            if e.T is not None and e.T_ref is not None and np.array_equal(e.T, T) and np.array_equal(e.T_ref, T_ref):
                continue
            old = e.world
            e.T_ref, e.T = T_ref.copy(), T.copy()
            if old is None:
                if e.active:
                    self._deposit(e)
                continue
            # only the cells that change world cell move: a small correction moves few of them
            e.world = map_codes(e.codes, correction(T, T_ref), self.resolution)
            moved = np.flatnonzero(old != e.world)
            if len(moved):
                rows = e.rows_at(moved)
                batch.add(old[moved], rows, -1)
                batch.add(e.world[moved], rows, 1)
                if batch.size >= _BATCH_CELLS:
                    self._apply(*batch.take())
        if batch.size:
            self._apply(*batch.take())

    def set_active(self, key: Key, active: bool) -> None:
        """Let a record contribute (its robot is in the team frame) or withdraw it."""
        e = self._entry(key)
        e.active = bool(active)
        if e.active and e.world is None and e.T is not None:
            self._deposit(e)
        elif not e.active and e.world is not None:
            self._withdraw(e)

    def remove(self, key: Key) -> None:
        e = self.entries.pop(key, None)
        if e is not None and e.world is not None:
            self._withdraw(e)

    def cells(self, key: Key) -> np.ndarray:
        """Reference-grid codes held for a record (sorted; none for a key not held)."""
        e = self.entries.get(key)
        return e.codes if e is not None else np.zeros(0, np.int64)

    def record(self, key: Key) -> tuple[np.ndarray, np.ndarray]:
        """Reference-grid codes and int16 rows held for a record (none for a key not held); the
        rows are a copy."""
        e = self.entries.get(key)
        if e is None:
            return np.zeros(0, np.int64), np.zeros((0, self.k1), np.int16)
        return e.codes, e.rows

    def evidence(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The fused evidence: sorted world codes, int32 rows and support counts."""
        return self._fused.arrays()

    @property
    def nbytes(self) -> int:
        """Bytes held: every record's cells, row palette, palette indices and world codes, the
        fused evidence and the octree view while one is built."""
        rec = sum(e.nbytes for e in self.entries.values())
        return int(rec + self._fused.nbytes + (self._tree.nbytes if self._tree is not None else 0))

    def fused(self, keys: Iterable[Key], at: dict[Key, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The evidence of just these records (placed at their poses, or at ``at[key]`` where
        given; active or not): sorted world codes and int32 rows. Records without a pose are left out."""
        codes, index, palettes = [], [], []
        base = 0
        for key in keys:
            e = self.entries.get(key)
            if e is None or e.T is None or e.T_ref is None or not len(e.codes):
                continue
            if at is not None and key in at:
                world = map_codes(e.codes, correction(at[key], e.T_ref), self.resolution)
            else:
                world = e.world if e.world is not None else \
                    map_codes(e.codes, correction(e.T, e.T_ref), self.resolution)
            codes.append(world)
            index.append(e.index.astype(np.int64) + base)  # into the records' palettes, one after another
            palettes.append(e.palette)
            base += len(e.palette)
        if not codes:
            return np.zeros(0, np.int64), np.zeros((0, self.k1), np.int32)
        return group_sum_indexed(np.concatenate(codes), np.concatenate(palettes).astype(np.int32),
                                 np.concatenate(index))

    # ---- internals -------------------------------------------------------------------------
    def _deposit(self, e: _Entry) -> None:
        assert e.T is not None and e.T_ref is not None
        e.world = map_codes(e.codes, correction(e.T, e.T_ref), self.resolution)
        self._apply(e.world, e.rows, np.ones(len(e.codes), np.int32))

    def _withdraw(self, e: _Entry) -> None:
        assert e.world is not None
        self._apply(e.world, -e.rows.astype(np.int32), -np.ones(len(e.codes), np.int32))
        e.world = None

    def _apply(self, codes: np.ndarray, rows: np.ndarray, support: np.ndarray) -> None:
        if len(codes) == 0:
            return
        uniq, (summed, sup) = group_sums(codes, rows.astype(np.int32), support.astype(np.int32))
        self._fused.add(uniq, summed, sup)
        self._tree = None
