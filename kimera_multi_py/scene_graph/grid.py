"""A dense free / occupied grid of a semantic octree, and its Euclidean distance field.

The scene graph works on a dense voxel grid in the map frame (Hydra downsamples its 0.1 m
TSDF to 0.2 m for the GVD). A leaf of the octree is *occupied* when its occupancy probability
exceeds 0.5 (:func:`~kimera_multi_py.mapping.observation.occupied_mask`) and *free* when it
is observed and the free class dominates it (occupancy below 0.5). A coarse cell is occupied
when any octree voxel in it is occupied, free when it holds free voxels and no occupied one,
and unknown otherwise. Unknown space counts as an obstacle for the distance field, except small
holes in free space (:func:`fill_holes`).

Grid cell ``(i, j, k)`` spans ``origin + resolution * [i, i+1) x ...``; origins are multiples
of the resolution, so two identical maps give identical grids.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from kimera_multi_py.mapping import morton
from kimera_multi_py.mapping.observation import SCALE
from kimera_multi_py.mapping.semantic_octree import SemanticOctree

_MARGIN = 2  # cells kept around the free space, so the distance field sees a closed border


@dataclass
class OccupancyGrid:
    """Dense boolean free / occupied masks of one map (map frame)."""

    origin: np.ndarray  # (3,) corner of cell (0, 0, 0)
    resolution: float
    free: np.ndarray  # bool (nx, ny, nz)
    occupied: np.ndarray  # bool (nx, ny, nz)
    labels: np.ndarray  # int8 (nx, ny, nz): most likely class of occupied cells, 0 elsewhere

    @property
    def shape(self) -> tuple[int, int, int]:
        s = self.free.shape
        return int(s[0]), int(s[1]), int(s[2])

    def centers(self, index: np.ndarray) -> np.ndarray:
        """Centres ``(n, 3)`` of cells given by integer indices ``(n, 3)``."""
        return self.origin + (np.asarray(index, dtype=np.float64) + 0.5) * self.resolution

    def index(self, points: np.ndarray) -> np.ndarray:
        """Integer cell indices ``(n, 3)`` of points (may fall outside the grid)."""
        return np.floor((np.asarray(points, dtype=np.float64) - self.origin) / self.resolution).astype(np.int64)

    def inside(self, index: np.ndarray) -> np.ndarray:
        return np.all((index >= 0) & (index < np.array(self.shape)), axis=-1)


@dataclass
class DistanceField:
    """Clearance (m) of every free cell and the index of its nearest obstacle cell (parent)."""

    grid: OccupancyGrid
    clearance: np.ndarray  # float32 (nx, ny, nz), 0 outside free space
    parents: np.ndarray  # int32 (3, nx, ny, nz)

    def clearance_at(self, points: np.ndarray) -> np.ndarray:
        """Clearance at points (nearest cell); 0 outside the grid."""
        idx = self.grid.index(points)
        ok = self.grid.inside(idx)
        out = np.zeros(idx.shape[:-1], dtype=np.float64)
        i = idx[ok]
        out[ok] = self.clearance[i[..., 0], i[..., 1], i[..., 2]]
        return out


def _occupied(values: np.ndarray) -> np.ndarray:
    """Rows whose occupancy probability exceeds 0.5, ``sum(exp(h[1:])) > 1`` (the rule of the octree's
    ``occupied_mask``, in float32: entries are clamped to a few units, so this does not overflow)."""
    h = values[:, 1:].astype(np.float32)
    h *= np.float32(1.0 / SCALE)
    return np.exp(h, out=h).sum(axis=1) > 1.0


def occupancy_grid(octree: SemanticOctree, resolution: float | None = None) -> OccupancyGrid:
    """Rasterise the octree's leaves into a dense grid of ``resolution`` (a power-of-two multiple
    of the octree's; default the octree's own)."""
    res = octree.resolution if resolution is None else float(resolution)
    ratio = res / octree.resolution
    c = int(round(np.log2(ratio))) if ratio > 0 else -1
    if c < 0 or not np.isclose(2.0**c, ratio):
        raise ValueError(f"grid resolution {res} must be the octree's {octree.resolution} times a power of two")
    codes, levels = octree.codes, octree.levels.astype(np.int64)
    if len(codes) == 0:
        empty = np.zeros((1, 1, 1), dtype=np.bool_)
        return OccupancyGrid(np.zeros(3), res, empty, empty.copy(), np.zeros((1, 1, 1), dtype=np.int8))
    occ = _occupied(octree.values)
    cls = (np.argmax(octree.values[:, 1:], axis=1) + 1).astype(np.int8)
    keys = morton.decode(codes) - morton.KEY_OFFSET  # signed voxel coordinates of each leaf's first voxel
    base = keys >> c  # coarse cell of each leaf's first voxel (arithmetic shift: floor division)
    top = max(int(levels.max()) - c, 0)
    step = 1 << top  # the grid is aligned to the largest leaf, so every leaf is a whole block of cells
    lo = ((base.min(0) >> top) << top) - step
    shape = tuple(int(v) for v in ((base.max(0) - lo) // step + 2) * step)
    occupied = np.zeros(shape, dtype=np.bool_)
    any_free = np.zeros(shape, dtype=np.bool_)
    labels = np.zeros(shape, dtype=np.int8)
    for lev in np.unique(levels).tolist():
        k = max(int(lev) - c, 0)  # a leaf covers 2**k coarse cells per axis
        sel = levels == lev
        cell = (base[sel] - lo) >> k
        small = tuple(n >> k for n in shape)
        for target, mask in ((occupied, occ[sel]), (any_free, ~occ[sel])):
            if not mask.any():
                continue
            coarse = np.zeros(small, dtype=np.bool_)
            coarse[tuple(cell[mask].T)] = True
            if k:
                coarse = coarse.repeat(1 << k, 0).repeat(1 << k, 1).repeat(1 << k, 2)
            target |= coarse
            if target is occupied:
                lab = np.zeros(small, dtype=np.int8)
                lab[tuple(cell[mask].T)] = cls[sel][mask]
                if k:
                    lab = lab.repeat(1 << k, 0).repeat(1 << k, 1).repeat(1 << k, 2)
                np.copyto(labels, lab, where=coarse)
    # crop to the free cells plus a margin: the nearest obstacle of a free cell is always inside
    free_all = any_free & ~occupied
    keep = free_all if free_all.any() else occupied | any_free
    nz = [np.flatnonzero(keep.any(axis=tuple(a for a in range(3) if a != ax))) for ax in range(3)]
    sl = tuple(slice(max(int(z[0]) - _MARGIN, 0), int(z[-1]) + _MARGIN + 1) for z in nz)
    origin = (lo + np.array([s.start for s in sl])).astype(np.float64) * res
    return OccupancyGrid(origin, res, np.ascontiguousarray(free_all[sl]), np.ascontiguousarray(occupied[sl]),
                         np.ascontiguousarray(labels[sl]))


def fill_holes(grid: OccupancyGrid, min_free: int = 4, iterations: int = 2) -> OccupancyGrid:
    """The grid with small unknown holes in free space counted as free: an unknown cell with at
    least ``min_free`` of its 6 face neighbours free becomes free, ``iterations`` times. A ray-cast
    map leaves such holes between rays far from the sensor; as obstacles they would collapse the
    clearance of an open room (a hole every few voxels leaves no place). ``min_free`` <= 0: none."""
    if min_free <= 0 or iterations <= 0:
        return grid
    free = grid.free.copy()
    unknown = ~(grid.free | grid.occupied)
    for _ in range(iterations):
        n = np.zeros(free.shape, dtype=np.int8)
        for ax in range(3):
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[ax], hi[ax] = slice(0, -1), slice(1, None)
            n[tuple(lo)] += free[tuple(hi)]
            n[tuple(hi)] += free[tuple(lo)]
        new = unknown & (n >= min_free)
        if not new.any():
            break
        free |= new
        unknown &= ~new
    return OccupancyGrid(grid.origin, grid.resolution, free, grid.occupied, grid.labels)


def distance_field(grid: OccupancyGrid) -> DistanceField:
    """Euclidean distance transform of free space with parent (nearest obstacle) indices."""
    dist, parents = ndimage.distance_transform_edt(grid.free, sampling=grid.resolution, return_indices=True)
    return DistanceField(grid, dist.astype(np.float32), parents.astype(np.int32))
