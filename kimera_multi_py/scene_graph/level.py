"""Levelling: the gravity direction of a map from its floor, and its grid in a level frame.

A team map is in the root robot's frame, which the distributed solver's gauge can leave tilted
(measured on the office: 31 degrees after seven epochs). Places and rooms only need a grid that
is level: floor layers, the ceiling cut and the clearance of a doorway are all stated in it, and a
tilted map's axis-aligned box holds ten times the cells of the floor it covers. The floor
class's occupied cells give the up direction (a plane fit); the map is resampled on a level grid
by looking every level cell's centre up in the octree (nearest leaf, so no holes are made).
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.core.semantics import CLASS_IDS
from kimera_multi_py.mapping import morton
from kimera_multi_py.mapping.semantic_octree import Leaves, SemanticOctree
from kimera_multi_py.scene_graph.grid import OccupancyGrid, _occupied

_MARGIN = 2


def level_frame(octree: SemanticOctree) -> np.ndarray | None:
    """The rotation ``R`` (map -> level frame) to build a graph in, or None when the map is level
    already (tilted by under a degree, or without a floor to tell)."""
    if len(octree.codes) == 0:
        return None
    lv, occ = octree.leaves(), _occupied(octree.values)
    R = level_rotation(octree, lv=lv, occ=occ)
    return None if np.allclose(R, np.eye(3)) else yaw_rotation(octree, R, lv=lv, occ=occ)


def level_rotation(octree: SemanticOctree, min_cells: int = 200, min_tilt_deg: float = 1.0,
                   lv: Leaves | None = None, occ: np.ndarray | None = None) -> np.ndarray:
    """``R`` (3x3) turning the map frame level (floor normal onto +z); the identity when the map has
    fewer than ``min_cells`` floor cells or is tilted by less than ``min_tilt_deg``. The normal is a
    least-squares plane fit to the occupied floor cells, refit once without cells more than 0.2 m
    off the plane (furniture tops, a ramp); it points towards the ceiling class (or map +z)."""
    floor, ceiling = CLASS_IDS.get("floor"), CLASS_IDS.get("ceiling")
    if floor is None or floor > octree.num_classes or len(octree.codes) == 0:
        return np.eye(3)
    lv = octree.leaves() if lv is None else lv
    occ = _occupied(octree.values) if occ is None else occ
    cls = np.argmax(lv.logodds[:, 1:], axis=1) + 1
    P = lv.centers[occ & (cls == floor)]
    if len(P) < min_cells:
        return np.eye(3)
    keep = np.ones(len(P), dtype=bool)
    for _ in range(2):
        c = P[keep].mean(0)
        n = np.linalg.svd(P[keep] - c, full_matrices=False)[2][-1]
        keep = np.abs((P - c) @ n) <= 0.2
        if keep.sum() < min_cells:
            return np.eye(3)
    up = np.array([0.0, 0.0, 1.0])
    if ceiling is not None and ceiling <= octree.num_classes:
        C = lv.centers[occ & (cls == ceiling)]
        if len(C) >= min_cells:
            up = C.mean(0) - P[keep].mean(0)
    n = n if n @ up >= 0 else -n
    z = np.array([0.0, 0.0, 1.0])
    tilt = np.degrees(np.arccos(np.clip(n @ z, -1.0, 1.0)))
    if tilt < min_tilt_deg:
        return np.eye(3)
    axis = np.cross(n, z)
    s, c = np.linalg.norm(axis), float(n @ z)
    k = axis / s
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)  # Rodrigues: n -> z


def _voxels(octree: SemanticOctree) -> tuple[np.ndarray, np.ndarray]:
    """Centres of every finest-level voxel the leaves cover, and the leaf index of each."""
    lv = octree.leaves()
    res = octree.resolution
    pts, leaf = [], []
    for lev in np.unique(lv.levels).tolist():
        sel = np.flatnonzero(lv.levels == lev)
        n = 1 << int(lev)
        o = (np.arange(n) + 0.5) * res - 0.5 * n * res
        off = np.stack(np.meshgrid(o, o, o, indexing="ij"), -1).reshape(-1, 3)
        pts.append((lv.centers[sel, None, :] + off[None]).reshape(-1, 3))
        leaf.append(np.repeat(sel, len(off)))
    return np.concatenate(pts), np.concatenate(leaf)


def yaw_rotation(octree: SemanticOctree, R: np.ndarray, lv: Leaves | None = None,
                 occ: np.ndarray | None = None) -> np.ndarray:
    """``R`` followed by the yaw that lines the level map's principal horizontal axis (of its free
    cells) up with x: walls then run along the grid axes and the grid's box is as small as it gets."""
    lv = octree.leaves() if lv is None else lv
    free = ~(_occupied(octree.values) if occ is None else occ)
    if free.sum() < 10:
        return R
    xy = (lv.centers[free] @ R.T)[:, :2]
    w = lv.sizes[free] ** 3
    c = (xy * w[:, None]).sum(0) / w.sum()
    cov = ((xy - c) * w[:, None]).T @ (xy - c) / w.sum()
    _, evecs = np.linalg.eigh(cov)
    a = evecs[:, -1]
    yaw = -np.arctan2(a[1], a[0])
    cz, sz = np.cos(yaw), np.sin(yaw)
    return np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]]) @ R


def levelled_grid(octree: SemanticOctree, R: np.ndarray, resolution: float | None = None) -> OccupancyGrid:
    """The map on a grid of the level frame ``p_level = R p_map``: every voxel of the octree lands in
    the level cell holding its rotated centre; a cell is occupied when an occupied voxel lands in it,
    free when only free ones do; a cell the rotation left without a voxel, next to a free one, takes
    the octree's value at its centre; the rest are unknown. Cropped to the free cells plus a margin."""
    res = octree.resolution if resolution is None else float(resolution)
    pts, leaf = _voxels(octree)
    occ_leaf = _occupied(octree.values)
    cls_leaf = (np.argmax(octree.values[:, 1:], axis=1) + 1).astype(np.int8)
    cell = np.floor(pts @ R.T / res).astype(np.int64)
    occ = occ_leaf[leaf]
    base = cell[~occ].min(0) - _MARGIN if (~occ).any() else cell.min(0) - _MARGIN
    top = cell[~occ].max(0) + _MARGIN if (~occ).any() else cell.max(0) + _MARGIN
    inside = np.all((cell >= base) & (cell <= top), axis=1)
    cell, occ, leaf = cell[inside] - base, occ[inside], leaf[inside]
    shape = tuple(int(v) for v in top - base + 1)
    occupied = np.zeros(shape, dtype=bool)
    any_free = np.zeros(shape, dtype=bool)
    labels = np.zeros(shape, dtype=np.int8)
    occupied[tuple(cell[occ].T)] = True
    any_free[tuple(cell[~occ].T)] = True
    labels[tuple(cell[occ].T)] = cls_leaf[leaf[occ]]
    free = any_free & ~occupied
    # cells the rotation left without a voxel, next to free space: the octree's value at their centre
    near = np.zeros(shape, dtype=bool)
    for ax in range(3):
        lo_s, hi_s = [slice(None)] * 3, [slice(None)] * 3
        lo_s[ax], hi_s[ax] = slice(0, -1), slice(1, None)
        near[tuple(lo_s)] |= free[tuple(hi_s)]
        near[tuple(hi_s)] |= free[tuple(lo_s)]
    hole = np.argwhere(near & ~free & ~occupied)
    if len(hole):
        rows, known = octree.cell_values(morton.points_to_codes((base * res + (hole + 0.5) * res) @ R,
                                                                octree.resolution))
        o = np.zeros(len(hole), dtype=bool)
        o[known] = _occupied(rows[known])
        f = known & ~o
        free[tuple(hole[f].T)] = True
        occupied[tuple(hole[o].T)] = True
        labels[tuple(hole[o].T)] = (np.argmax(rows[o, 1:], axis=1) + 1).astype(np.int8)
    return OccupancyGrid(base * res, res, free, occupied, labels)
