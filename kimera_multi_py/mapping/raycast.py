"""Vectorised 3-D DDA: the voxels every ray of a scan passes through, computed all at once.

A ray from the sensor origin to its end point enters a new voxel exactly where it crosses a
voxel face. So instead of stepping rays one voxel at a time (Amanatides & Woo), we list, for
every ray and axis, all the face crossings at once (``np.repeat`` + a cumulative count), and
read the voxel entered at each crossing: the crossing axis steps by one, the other two axes
are ``floor`` of the ray at the crossing parameter. The set of traversed voxels is the start
voxel plus one voxel per crossing; no sort by ray parameter is needed because a scan update
only needs the *set* of cells (each cell is updated once per scan, as in OctoMap). The
crossings of all rays are generated together, in slices of about 64k crossings so that the
temporaries stay in cache; arithmetic is float32 on per-ray arithmetic progressions.

De-duplication uses a dense bitmap over the scan's bounding box (linear time, no sort) and
falls back to ``np.unique`` when that box is too large. Rules of one scan:

- a ray ending on a static class marks its end voxel occupied with that label;
- rays longer than ``max_range`` are cut at ``max_range`` and update free space only;
- rays whose label is dynamic (or 0, "no return") update free space only;
- free voxels are the traversed voxels minus every ray's end voxel (occupied wins over free,
  and the end voxel of a free-only ray is left untouched).

Two optional sensor-model terms (both 0 reproduce OctoMap): ``free_margin`` stops the free
space of a ray that hit something that far before the hit, so rays grazing a surface do not
erode the surface cells they skim near their end; ``surface_offset`` bins a hit that far
behind the measured point, into the matter behind the surface, so that a surface lying on a
voxel boundary lands in the cell that holds the object rather than, half of the time, in the
free cell in front of it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from kimera_multi_py.mapping import morton

_DENSE_LIMIT = 1 << 27  # largest bounding box (voxels) de-duplicated with a bitmap
_BLOCK = 1 << 16  # crossings per vectorised block (fits in cache)


@dataclass
class ScanCells:
    """The cells one scan updates, as sorted unique Morton codes at the finest level."""

    free: np.ndarray  # (f,) int64 codes passed through (never also occupied)
    occupied: np.ndarray  # (m,) int64 codes holding end points of static classes
    label_counts: np.ndarray  # (m, K+1) int32 end-point labels per occupied cell (column 0 = 0)
    num_rays: int

    @property
    def num_cells(self) -> int:
        return len(self.free) + len(self.occupied)


def _mark_axis_crossings(
    grid: np.ndarray | None,
    sink: list[np.ndarray],
    a: int,
    n_a: np.ndarray,
    frac: np.ndarray,
    delta: np.ndarray,
    lo: np.ndarray,
    strides: np.ndarray,
) -> None:
    """Mark the voxel entered at every face crossing of axis ``a``, all rays at once.

    ``delta`` is ``(3, n)``: each ray's extent in voxels, one contiguous row per axis.

    Linear box indices are set in the bitmap ``grid``, or appended to ``sink`` when the box is
    too large for a bitmap.

    For a ray with ``n`` crossings on axis ``a``, crossing ``j = 0..n-1`` happens at
    ``t_j = t_0 + j / |D_a|``, so the other two voxel coordinates are arithmetic progressions
    ``u_b = B0 + j B1`` and their voxel indices are ``floor(u_b)``. Coordinates are shifted by
    ``1 - lo`` (a one-voxel margin) so they are positive and float-to-int truncation is the
    floor. Work is split in blocks of about ``_BLOCK`` crossings to stay in cache.
    """
    b, c = (a + 1) % 3, (a + 2) % 3
    rays = np.flatnonzero(n_a)
    if len(rays) == 0:
        return
    counts = n_a[rays]
    d_a, d_b, d_c = delta[a][rays], delta[b][rays], delta[c][rays]
    inv = 1.0 / np.abs(d_a)
    t0 = ((d_a > 0) - frac[a]) / d_a  # parameter of the first crossing
    step = np.where(d_a > 0, 1, -1)
    B0 = (frac[b] + 1 - lo[b] + d_b * t0).astype(np.float32)
    B1 = (d_b * inv).astype(np.float32)
    C0 = (frac[c] + 1 - lo[c] + d_c * t0).astype(np.float32)
    C1 = (d_c * inv).astype(np.float32)
    itype = np.int32 if grid is not None else np.int64
    A0 = ((step + 1 - lo[a]) * strides[a]).astype(itype)
    A1 = (step * strides[a]).astype(itype)
    sb, sc = itype(strides[b]), itype(strides[c])
    cum = np.cumsum(counts)
    cuts = np.searchsorted(cum, np.arange(_BLOCK, int(cum[-1]), _BLOCK), side="right")
    bounds = np.unique(np.concatenate([[0], cuts, [len(rays)]]))
    for s, e in zip(bounds[:-1], bounds[1:], strict=True):
        cnt = counts[s:e]
        m = int(cum[e - 1] - (cum[s - 1] if s else 0))
        first = (np.cumsum(cnt) - cnt).astype(np.int32)
        j: np.ndarray = np.arange(m, dtype=itype)
        j -= np.repeat(first, cnt)
        jf = j.astype(np.float32)
        ub: npt.NDArray[np.float32] = np.repeat(B1[s:e], cnt)
        ub *= jf
        ub += np.repeat(B0[s:e], cnt)
        uc: npt.NDArray[np.float32] = np.repeat(C1[s:e], cnt)
        uc *= jf
        uc += np.repeat(C0[s:e], cnt)
        lin = np.repeat(A1[s:e], cnt)
        lin *= j
        lin += np.repeat(A0[s:e], cnt)
        ib: npt.NDArray[np.signedinteger[Any]] = ub.astype(itype)
        ib *= sb
        lin += ib
        ic: npt.NDArray[np.signedinteger[Any]] = uc.astype(itype)
        if sc != 1:
            ic *= sc
        lin += ic
        if grid is not None:
            grid[lin] = True
        else:
            sink.append(lin)


def scan_cells(
    origin: np.ndarray,
    endpoints: np.ndarray,
    labels: np.ndarray,
    resolution: float,
    num_classes: int,
    max_range: float = -1.0,
    dynamic_labels: tuple[int, ...] = (),
    free_margin: float = 0.0,
    surface_offset: float = 0.0,
) -> ScanCells:
    """Cells updated by one scan taken from ``origin`` (see the module docstring for the rules).

    ``endpoints`` are ``(n, 3)`` world points, ``labels`` ``(n,)`` class ids in ``0..K``.
    ``free_margin`` stops the free space of a ray that hit something this far before the hit;
    ``surface_offset`` bins a hit this far behind the measured point (both 0 in OctoMap).
    Non-finite end points are ignored. Raises ``ValueError`` on bad shapes or labels and when
    a cell falls outside the octree's addressable extent.
    """
    o = np.asarray(origin, dtype=np.float64).reshape(3)
    pts = np.asarray(endpoints, dtype=np.float64)
    lab = np.asarray(labels).astype(np.int64, copy=False).reshape(-1)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(lab) != len(pts):
        raise ValueError(f"need (n, 3) end points and (n,) labels, got {pts.shape}, {lab.shape}")
    if not np.all(np.isfinite(o)):
        raise ValueError("origin must be finite")
    if lab.size and (lab.min() < 0 or lab.max() > num_classes):
        raise ValueError(f"labels must lie in 0..{num_classes}")
    finite = np.all(np.isfinite(pts), axis=1)
    if not finite.all():
        pts, lab = pts[finite], lab[finite]
    n = len(pts)
    empty = np.zeros(0, dtype=np.int64)
    if n == 0:
        return ScanCells(empty, empty, np.zeros((0, num_classes + 1), np.int32), 0)

    # per-axis rows (3, n): numpy is slow on (n, 3) element-wise work
    d = np.ascontiguousarray(pts.T) - o[:, None]
    returned = lab > 0  # something was hit (static or dynamic)
    hit = returned.copy()
    if dynamic_labels:
        hit &= ~np.isin(lab, np.asarray(dynamic_labels, dtype=np.int64))
    dist = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    if max_range > 0:  # rays cut at max range clear space only
        far = dist > max_range
        if far.any():
            d[:, far] *= max_range / dist[far]
            dist[far] = max_range
            hit &= ~far
            returned &= ~far
    occ_d = d[:, hit]
    if surface_offset > 0:  # bin hits a little behind the measured surface
        occ_d = occ_d * (1.0 + surface_offset / np.maximum(dist[hit], 1e-12))
    free_d = d
    if free_margin > 0 and returned.any():  # free space stops short of a return
        keep = np.maximum(dist - free_margin, 0.0) / np.maximum(dist, 1e-12)
        free_d = d * np.where(returned, keep, 1.0)

    # voxel coordinates relative to the origin's voxel
    u0 = o / resolution
    start = np.floor(u0)
    frac = u0 - start
    delta = free_d / resolution
    f = frac[:, None]
    trav_rel = np.floor(f + delta).astype(np.int64)
    end_rel = np.floor(f + d / resolution).astype(np.int64)
    occ_rel = np.floor(f + occ_d / resolution).astype(np.int64)
    start_key = start.astype(np.int64) + morton.KEY_OFFSET
    lo = np.zeros(3, dtype=np.int64)
    hi = np.zeros(3, dtype=np.int64)
    for rel in (trav_rel, end_rel, occ_rel):
        if rel.shape[1]:
            lo, hi = np.minimum(lo, rel.min(axis=1)), np.maximum(hi, rel.max(axis=1))
    if (start_key + lo).min() < 0 or (start_key + hi).max() > morton.KEY_MAX:
        raise ValueError("scan reaches outside the octree's addressable extent")
    dims = hi - lo + 3  # one voxel of margin on each side
    strides = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
    volume = int(dims.prod())
    shift = (1 - lo) @ strides

    def linear(rel: np.ndarray) -> np.ndarray:
        return rel[0] * strides[0] + rel[1] * strides[1] + rel[2] + shift

    end_lin = linear(end_rel)
    hit_lin = linear(occ_rel)
    n_axis = np.abs(trav_rel)

    # traverse: mark every voxel entered, then drop all end voxels
    origin_lin = int((1 - lo) @ strides)
    sink: list[np.ndarray] = [np.array([origin_lin], dtype=np.int64)]
    grid = np.zeros(volume, dtype=np.bool_) if volume <= _DENSE_LIMIT else None
    for a in range(3):
        _mark_axis_crossings(grid, sink, a, n_axis[a], frac, delta, lo, strides)
    if grid is not None:
        grid[origin_lin] = True
        grid[end_lin] = False
        grid[hit_lin] = False
        free_lin = np.flatnonzero(grid)
    else:
        free_lin = np.unique(np.concatenate(sink))
        ends = np.unique(np.concatenate([end_lin, hit_lin]))
        pos = np.searchsorted(ends, free_lin).clip(max=len(ends) - 1)
        free_lin = free_lin[ends[pos] != free_lin]

    # occupied cells with their label histograms
    occ_lin, inv = np.unique(hit_lin, return_inverse=True)
    k1 = num_classes + 1
    counts = np.bincount(inv * k1 + lab[hit], minlength=len(occ_lin) * k1)
    counts = counts.reshape(len(occ_lin), k1).astype(np.int32)
    counts[:, 0] = 0

    base = start_key + lo - 1
    free = _lin_to_codes(free_lin, dims, base)
    occ = _lin_to_codes(occ_lin, dims, base)
    oo = np.argsort(occ)  # codes are unique: no need for a stable sort
    return ScanCells(np.sort(free), occ[oo], counts[oo], n)


def _lin_to_codes(lin: np.ndarray, dims: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Morton codes of linear indices into a box of ``dims`` voxels whose first key is ``base``."""
    ix, rem = np.divmod(lin, dims[1] * dims[2])
    iy, iz = np.divmod(rem, dims[2])
    return (
        morton.spread(ix + base[0])
        | (morton.spread(iy + base[1]) << 1)
        | (morton.spread(iz + base[2]) << 2)
    )
