"""Submaps with exact re-anchoring: the robot's map is ``clamp(prior + sum_s T_s . dh_s)``.

Each submap (a group of consecutive keyframes) keeps its own evidence ``dh_s``: the sum of its
scans' log-odds updates, in fixed point. ``dh_s`` lives on the voxel grid of the submap's
*reference frame*, the world frame as it was when the submap was created (its pose then is
``T_ref``); the submap's local frame is ``T_ref^-1`` of it. While PGO leaves the submap where
it is, its cells map to the world grid one to one, with no resampling. When PGO moves the
submap to ``T_new``, its cell centres are moved by ``C = T_new T_ref^-1`` and re-binned.

The fused evidence ``A = sum_s C_s . dh_s`` is an int32 array with, per cell, the number of
submap cells that land there. Because it is integer, ``move_submap`` subtracts the old
contribution and adds the new one exactly: moving a submap away and back restores ``A``,
and the octree view ``clamp(prior + A)`` (canonically pruned), bit for bit.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import numpy as np

from kimera_multi_py.core.geometry import inverse, transform_points
from kimera_multi_py.mapping import morton
from kimera_multi_py.mapping.observation import SCALE
from kimera_multi_py.mapping.octree_block import BLOCK_SHIFT
from kimera_multi_py.mapping.palette import to_palette
from kimera_multi_py.mapping.semantic_octree import SemanticOctree

log = logging.getLogger(__name__)

_PENDING_MERGE = 64  # changed-cell arrays kept before they are merged into one
_BATCH_CELLS = 1 << 20  # cells gathered before a batch of moves is applied (bounds its memory)


class Submap:
    """One submap: reference and current pose, and its evidence on the reference grid.

    ``rows`` are int16 (within +-(h_max - h_min)). While a submap still takes scans they are held
    dense, with the world codes its cells are in (``world_codes``); :meth:`compact` (done when the
    next submap starts) keeps the rows as a palette of distinct rows and an index per cell
    (:mod:`.palette`), the same values in a fraction of the bytes, and drops the world codes, which
    :meth:`SubmapMap.world_codes` recomputes from the pose they were placed at. Reading ``rows``
    gives them back, and a scan into a compact submap expands it."""

    def __init__(self, id: int, T_ref: np.ndarray, T: np.ndarray, codes: np.ndarray | None = None,
                 rows: np.ndarray | None = None, world_codes: np.ndarray | None = None,
                 num_scans: int = 0) -> None:
        self.id = id
        self.T_ref = T_ref  # world pose of the submap frame when it was created
        self.T = T  # world pose at which its contribution is currently in the map
        self.codes = np.zeros(0, dtype=np.int64) if codes is None else codes
        self.rows = np.zeros((0, 1), dtype=np.int16) if rows is None else rows
        # the world codes of the cells (where they are in the map), or None: recomputed when needed
        self.world_codes: np.ndarray | None = np.zeros(0, dtype=np.int64) if world_codes is None else world_codes
        self.num_scans = num_scans

    @property
    def rows(self) -> np.ndarray:
        """The cells' evidence rows (materialised from the palette when compact: a copy then)."""
        if self._dense is not None:
            return self._dense
        assert self._palette is not None and self._index is not None
        return self._palette.take(self._index.astype(np.intp), axis=0)

    @rows.setter
    def rows(self, value: np.ndarray) -> None:
        self._dense: np.ndarray | None = value
        self._palette: np.ndarray | None = None
        self._index: np.ndarray | None = None

    @property
    def compact_rows(self) -> bool:
        return self._dense is None

    def rows_at(self, pos: np.ndarray) -> np.ndarray:
        """The rows of the cells at positions ``pos``."""
        if self._dense is not None:
            return self._dense[pos]
        assert self._palette is not None and self._index is not None
        return self._palette.take(self._index[pos].astype(np.intp), axis=0)

    def compact(self) -> None:
        """Hold the rows as a palette and an index (exactly the same values); drop the world codes."""
        if self._dense is not None:
            self._palette, self._index = to_palette(self._dense)
            self._dense = None
        self.world_codes = None

    def expand(self) -> None:
        """Hold the rows dense again (to take scans)."""
        if self._dense is None:
            self.rows = self.rows

    @property
    def nbytes(self) -> int:
        rows = self._dense.nbytes if self._dense is not None else (
            self._palette.nbytes + self._index.nbytes)  # type: ignore[union-attr]
        world = self.world_codes.nbytes if self.world_codes is not None else 0
        return int(self.codes.nbytes + rows + world)

    @property
    def correction(self) -> np.ndarray:
        """``C = T T_ref^-1``: how the submap moved since its cells were computed."""
        return correction(self.T, self.T_ref)


def correction(T: np.ndarray, T_ref: np.ndarray) -> np.ndarray:
    """``C = T T_ref^-1``: how a submap created at ``T_ref`` and now at ``T`` moved."""
    return np.asarray(T, dtype=np.float64) @ inverse(np.asarray(T_ref, dtype=np.float64))


def map_codes(ref_codes: np.ndarray, C: np.ndarray, resolution: float) -> np.ndarray:
    """World codes of reference-grid cells moved by ``C`` (identity keeps them exactly).

    Cell centres are moved and re-binned; this is the one definition every fusion of submap
    evidence uses (a robot's map, the team map and the centralised fusion), so that all of them
    put a submap's cells in the same world cells.
    """
    if len(ref_codes) == 0 or np.allclose(C, np.eye(4), rtol=0.0, atol=1e-12):
        return np.array(ref_codes, dtype=np.int64)
    centers = morton.node_centers(ref_codes, np.zeros(len(ref_codes), np.int8), resolution)
    moved = transform_points(C, centers)
    return morton.encode(morton.points_to_keys(moved, resolution))


def _group_sum(codes: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique sorted codes, summed rows and multiplicities."""
    uniq, (summed,), count = _grouped(codes, rows)
    return uniq, summed, count


def group_sums(codes: np.ndarray, *columns: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Unique sorted codes and, per column array (one row or value per code), its sums over
    equal codes, in the column's dtype. One sort and one ``reduceat`` each (integer sums: the
    order of the terms does not matter)."""
    uniq, sums, _ = _grouped(codes, *columns)
    return uniq, sums


def group_sum_indexed(codes: np.ndarray, palette: np.ndarray, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`group_sums` of the rows ``palette[index]`` (one index per code), gathered once in
    the codes' sorted order: the rows are never built in their own order first."""
    uniq, (summed,), _ = _grouped(codes, index, palette=palette)
    return uniq, summed


def _grouped(codes: np.ndarray, *columns: np.ndarray,
             palette: np.ndarray | None = None) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """:func:`group_sums`, and the multiplicity of each code (with ``palette``: the one column
    is an index into its rows, which are summed).

    The sort is stable (timsort on int64): the codes come as concatenations of sorted or nearly
    sorted runs (a submap's cells, moved a little), which it merges instead of sorting afresh,
    and the rows are then gathered run by run."""
    codes = np.asarray(codes, dtype=np.int64)
    if len(codes) == 0:
        empty = [palette[:0].copy()] if palette is not None else [np.asarray(c)[:0].copy() for c in columns]
        return codes.copy(), empty, np.zeros(0, np.int64)
    order = np.argsort(codes, kind="stable")
    ordered = codes[order]
    first = np.empty(len(ordered), dtype=np.bool_)
    first[0] = True
    np.not_equal(ordered[1:], ordered[:-1], out=first[1:])
    starts = np.flatnonzero(first)
    sums = []
    for c in columns:
        c = np.asarray(c)
        taken = c.take(order, axis=0)
        if palette is not None:
            c, taken = palette, palette.take(taken.astype(np.intp, copy=False), axis=0)
        sums.append(taken if len(starts) == len(codes) else np.add.reduceat(taken, starts, axis=0, dtype=c.dtype))
    return ordered[starts], sums, np.diff(starts, append=len(codes))


class SubmapMap:
    """A robot's semantic map assembled from re-anchorable submaps (docs/algorithms/mapping.md).

    ``octree_kwargs`` are passed to :class:`SemanticOctree` (observation model, clamping,
    dynamic classes, top-K). ``move_threshold`` (default half a voxel) is how far any cell of a
    submap must move before :meth:`move_submap` re-integrates it.
    """

    def __init__(
        self,
        resolution: float,
        num_classes: int,
        *,
        move_threshold: float | None = None,
        **octree_kwargs: object,
    ) -> None:
        self._tree = SemanticOctree(resolution, num_classes, **octree_kwargs)  # type: ignore[arg-type]
        self._pending: list[np.ndarray] = []  # cells changed since the tree was last brought up to date
        self.resolution = self._tree.resolution
        self.num_classes = self._tree.num_classes
        self.move_threshold = (
            0.5 * self.resolution if move_threshold is None else float(move_threshold)
        )
        self.submaps: dict[int, Submap] = {}
        self._fused = _CellStore(self.num_classes + 1)  # sum of the submaps' world contributions
        m = self._tree.model
        self._span = m.hi - m.lo  # a submap's evidence per cell stays within +-span
        if self._span > np.iinfo(np.int16).max:  # submap evidence is kept (and sent) as int16
            raise ValueError(f"h_max - h_min must stay below {np.iinfo(np.int16).max / SCALE:.1f} for submaps")

    @property
    def octree(self) -> SemanticOctree:
        """The map as an octree, ``clamp(prior + evidence)`` (do not change it).

        The evidence is what every scan and move updates; the tree is brought up to date only
        when asked for, with every cell changed since in one update (docs/algorithms/mapping.md).
        """
        self._flush()
        return self._tree

    @property
    def template(self) -> SemanticOctree:
        """The octree whose resolution, observation model and options the map uses: read its
        parameters or ``empty_like()`` it, not its cells (they may lag the evidence)."""
        return self._tree

    # ---- submaps ---------------------------------------------------------------------------
    def new_submap(self, submap_id: int, pose: np.ndarray) -> Submap:
        """Start a submap whose frame is at world pose ``pose`` (4x4)."""
        if submap_id in self.submaps:
            raise KeyError(f"submap {submap_id} already exists")
        T = np.asarray(pose, dtype=np.float64).copy()
        for older in self.submaps.values():  # they take no more scans: hold their rows compactly
            older.compact()
        s = Submap(
            int(submap_id), T.copy(), T, rows=np.zeros((0, self.num_classes + 1), dtype=np.int16)
        )
        self.submaps[s.id] = s
        return s

    def integrate(
        self,
        submap_id: int,
        T_submap_sensor: np.ndarray,
        points_sensor: np.ndarray,
        labels: np.ndarray,
        max_range: float = -1.0,
    ) -> int:
        """Add one scan (sensor-frame end points) taken at ``T_submap_sensor`` in the submap.

        The scan is ray-cast on the submap's reference grid, its updates are added to the
        submap's evidence (clamped to +-(h_max - h_min) per cell), and the change is pushed
        into the fused map. Returns the number of cells updated.
        """
        s = self.submaps[submap_id]
        if s.compact_rows:
            s.world_codes = self.world_codes(s)
            s.expand()
        assert s.world_codes is not None
        T_ref_sensor = s.T_ref @ np.asarray(T_submap_sensor, dtype=np.float64)
        pts = transform_points(T_ref_sensor, np.asarray(points_sensor, dtype=np.float64))
        cells = self._tree.scan_cells(T_ref_sensor[:3, 3], pts, labels, max_range)
        codes, deltas = self._tree.model.deltas(cells)
        if len(codes) == 0:
            return 0
        # merge into the submap's evidence (sequentially clamped)
        pos = np.searchsorted(s.codes, codes)
        known = pos < len(s.codes)
        known[known] = s.codes[pos[known]] == codes[known]
        before = np.zeros((len(codes), self.num_classes + 1), dtype=np.int32)
        before[known] = s.rows[pos[known]]
        after = np.clip(before + deltas, -self._span, self._span)
        change = after - before
        s.rows[pos[known]] = after[known]
        new = ~known
        if new.any():
            new_world = self._map_codes(codes[new], s.correction)
            at = pos[new]
            s.codes = np.insert(s.codes, at, codes[new])
            s.rows = np.insert(s.rows, at, after[new], axis=0)
            s.world_codes = np.insert(s.world_codes, at, new_world)
        s.num_scans += 1
        # push the change into the fused evidence
        idx = np.searchsorted(s.codes, codes)
        world = s.world_codes[idx]
        self._apply(world, change, new.astype(np.int32))
        return int(len(codes))

    def move_submap(self, submap_id: int, new_pose: np.ndarray, force: bool = False) -> bool:
        """Re-anchor a submap at ``new_pose``: subtract its old contribution, add the new one.

        Nothing is re-integrated (returns False) unless some cell would move by more than
        ``move_threshold`` from where the map currently has it, or ``force`` is set; small
        corrections accumulate until they cross the threshold.
        """
        return bool(self.move_submaps({submap_id: new_pose}, force))

    def move_submaps(self, poses: Mapping[int, np.ndarray], force: bool = False) -> int:
        """:meth:`move_submap` for several submaps (id -> new pose), their changes applied
        together; returns how many moved. The sums are integers: the same map as one by one."""
        batch = _Batch()
        moved = 0
        for submap_id, pose in poses.items():
            s = self.submaps[submap_id]
            new_pose = np.asarray(pose, dtype=np.float64)
            motion = self._max_cell_motion(s, new_pose)
            if not force and motion <= self.move_threshold:
                continue
            old_world = self.world_codes(s)
            s.T = new_pose.copy()
            new_world = self._map_codes(s.codes, s.correction)
            # old contribution out and new one in, for the cells that change world cell (the
            # others' two terms cancel exactly: leaving them out gives the same sums)
            moved_cells = np.flatnonzero(old_world != new_world)
            if len(moved_cells):
                rows = s.rows_at(moved_cells)
                batch.add(old_world[moved_cells], rows, -1)
                batch.add(new_world[moved_cells], rows, 1)
                if batch.size >= _BATCH_CELLS:
                    self._apply(*batch.take())
            s.world_codes = None if s.compact_rows else new_world
            moved += 1
            log.debug("re-anchored submap %d (max cell motion %.3f m)", submap_id, motion)
        if batch.size:
            self._apply(*batch.take())
        return moved

    def remove_submap(self, submap_id: int) -> None:
        """Drop a submap and subtract its contribution."""
        s = self.submaps.pop(submap_id)
        if len(s.codes):
            self._apply(self.world_codes(s), -s.rows, -np.ones(len(s.codes), dtype=np.int32))

    def submap_ids(self) -> list[int]:
        return sorted(self.submaps)

    def contribution(self, submap_id: int) -> tuple[np.ndarray, np.ndarray]:
        """World codes and evidence rows a submap currently adds to the map."""
        s = self.submaps[submap_id]
        return self.world_codes(s).copy(), s.rows.copy()

    def world_codes(self, s: Submap) -> np.ndarray:
        """The world codes of a submap's cells: where its contribution is in the map (held while
        it takes scans, else recomputed from the pose it was placed at, ``s.T``: the same codes)."""
        return s.world_codes if s.world_codes is not None else self._map_codes(s.codes, s.correction)

    # ---- internals -------------------------------------------------------------------------
    def _max_cell_motion(self, s: Submap, new_pose: np.ndarray) -> float:
        """Largest displacement of the submap's bounding-box corners between two poses."""
        if len(s.codes) == 0:
            return 0.0
        keys = morton.decode(s.codes)
        lo = (keys.min(0) - morton.KEY_OFFSET) * self.resolution
        hi = (keys.max(0) + 1 - morton.KEY_OFFSET) * self.resolution
        corners = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        C_old = s.correction
        C_new = correction(new_pose, s.T_ref)
        d = transform_points(C_new, corners) - transform_points(C_old, corners)
        return float(np.linalg.norm(d, axis=1).max())

    def _map_codes(self, ref_codes: np.ndarray, C: np.ndarray) -> np.ndarray:
        """World codes of reference-grid cells moved by ``C`` (see :func:`map_codes`)."""
        return map_codes(ref_codes, C, self.resolution)

    def _apply(self, codes: np.ndarray, rows: np.ndarray, support: np.ndarray) -> None:
        """Add rows and support counts at (possibly repeated) world codes; note the cells for the view."""
        if len(codes) == 0:
            return
        uniq, (summed, sup) = group_sums(codes, rows.astype(np.int32), support.astype(np.int32))
        changed = (sup != 0) | summed.any(axis=1)  # cells a move leaves as they were are not touched
        if not changed.all():
            uniq, summed, sup = uniq[changed], summed[changed], sup[changed]
            if len(uniq) == 0:
                return
        self._fused.add(uniq, summed, sup)
        self._pending.append(uniq)
        if len(self._pending) >= _PENDING_MERGE:  # bound the list: one sorted array of distinct cells
            self._pending = [np.unique(np.concatenate(self._pending))]

    def _flush(self) -> None:
        """Bring the tree up to date: every cell changed since, at its value now or unknown."""
        if not self._pending:
            return
        codes = np.unique(np.concatenate(self._pending))
        self._pending = []
        rows, alive = self._fused.lookup(codes)
        self._tree.remove_cells(codes[~alive])
        if alive.any():
            m = self._tree.model
            vals = rows[alive] + m.prior_row.astype(np.int32)
            np.clip(vals, m.lo, m.hi, out=vals)
            vals[:, 0] = 0
            self._tree.set_cells(codes[alive], vals.astype(np.int16))

    def evidence(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The fused evidence: sorted world codes, int32 rows and support counts."""
        return self._fused.arrays()

    @property
    def nbytes(self) -> int:
        """Bytes held: the submaps' evidence, the fused evidence and the tree's leaves."""
        subs = sum(s.nbytes for s in self.submaps.values())
        return int(subs + self._fused.nbytes + self._tree.nbytes)


class _Batch:
    """Contributions gathered to be applied together: world codes, rows and support signs."""

    def __init__(self) -> None:
        self._clear()

    def _clear(self) -> None:
        self.codes: list[np.ndarray] = []
        self.rows: list[np.ndarray] = []
        self.support: list[np.ndarray] = []
        self.size = 0

    def add(self, codes: np.ndarray, rows: np.ndarray, sign: int) -> None:
        self.codes.append(codes)
        self.rows.append(rows if sign > 0 else -rows.astype(np.int32))
        self.support.append(np.full(len(codes), sign, dtype=np.int32))
        self.size += len(codes)

    def take(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Everything gathered (and the batch emptied)."""
        cat = np.concatenate
        out = cat(self.codes), cat([r.astype(np.int32, copy=False) for r in self.rows]), cat(self.support)
        self._clear()
        return out


class _CellStore:
    """Sparse int32 rows with support counts per finest-level code, kept per octree block.

    Like the octree's leaves, cells are grouped by their level-``BLOCK_LEVEL`` ancestor so
    that an update only moves the memory of the blocks it touches.
    """

    def __init__(self, k1: int) -> None:
        self.k1 = k1
        self.blocks: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def add(
        self, codes: np.ndarray, rows: np.ndarray, support: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Add at sorted unique codes; returns touched live codes, their rows, and dead codes."""
        bids = codes >> BLOCK_SHIFT
        cuts = np.flatnonzero(bids[1:] != bids[:-1]) + 1
        bounds = [0, *cuts.tolist(), len(codes)]
        live, live_rows, dead = [], [], []
        for s, e in zip(bounds[:-1], bounds[1:], strict=True):
            bid = int(bids[s])
            c, r, n = self.blocks.get(bid, _empty(self.k1))
            q, qr, qn = codes[s:e], rows[s:e], support[s:e]
            pos = np.searchsorted(c, q)
            known = pos < len(c)
            known[known] = c[pos[known]] == q[known]
            kp = pos[known]
            r[kp] += qr[known]
            n[kp] += qn[known]
            new = ~known
            if new.any():
                at = pos[new]
                c = np.insert(c, at, q[new])
                r = np.insert(r, at, qr[new], axis=0)
                n = np.insert(n, at, qn[new])
            idx = np.searchsorted(c, q)
            alive = n[idx] > 0
            live.append(q[alive])
            live_rows.append(r.take(idx[alive], axis=0))
            if not alive.all():
                dead.append(q[~alive])
                keep = np.ones(len(c), dtype=np.bool_)
                keep[idx[~alive]] = False
                c, r, n = c[keep], r[keep], n[keep]
            if len(c):
                self.blocks[bid] = (c, r, n)
            else:
                self.blocks.pop(bid, None)
        cat = np.concatenate
        empty = np.zeros(0, dtype=np.int64)
        return (
            cat(live) if live else empty,
            cat(live_rows) if live_rows else np.zeros((0, self.k1), np.int32),
            cat(dead) if dead else empty,
        )

    def lookup(self, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows at sorted unique codes and whether each cell is held (support above 0)."""
        rows = np.zeros((len(codes), self.k1), dtype=np.int32)
        alive = np.zeros(len(codes), dtype=np.bool_)
        if len(codes) == 0:
            return rows, alive
        bids = codes >> BLOCK_SHIFT
        cuts = np.flatnonzero(bids[1:] != bids[:-1]) + 1
        for s, e in zip([0, *cuts.tolist()], [*cuts.tolist(), len(codes)], strict=True):
            blk = self.blocks.get(int(bids[s]))
            if blk is None:
                continue
            c, r, n = blk
            pos = np.searchsorted(c, codes[s:e]).clip(max=len(c) - 1)
            hit = (c[pos] == codes[s:e]) & (n[pos] > 0)
            rows[s:e][hit] = r[pos[hit]]
            alive[s:e] = hit
        return rows, alive

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        keys = sorted(self.blocks)
        if not keys:
            return _empty(self.k1)
        return tuple(np.concatenate([self.blocks[k][i] for k in keys]) for i in range(3))  # type: ignore[return-value]

    def __len__(self) -> int:
        return sum(len(b[0]) for b in self.blocks.values())

    @property
    def nbytes(self) -> int:
        return int(sum(c.nbytes + r.nbytes + n.nbytes for c, r, n in self.blocks.values()))


def _empty(k1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (
        np.zeros(0, dtype=np.int64),
        np.zeros((0, k1), dtype=np.int32),
        np.zeros(0, dtype=np.int32),
    )
