"""Places: the generalised Voronoi diagram of free space, compressed into a sparse graph.

Follows Hydra's ``gvd_integrator`` / ``graph_extractor`` (docs/algorithms/scene_graph.md), vectorised over the
whole grid: the distance field comes with parent (nearest obstacle) indices; a free voxel is
on the GVD when one of its 26 neighbours has a *distinct* parent (the parents are more than
``gvd_parent_voxels`` apart, or seen from the two voxels at an angle whose cosine is below
``gvd_parent_cos``) and both have clearance above ``gvd_min_clearance``. GVD voxels with
clearance of at least ``place_min_clearance`` are compressed per ``place_cell`` cell: each
connected cluster inside a cell is one place, at its voxel of largest clearance. Clusters
that touch across a cell boundary are joined by an edge whose weight is the smallest
clearance along the straight segment between the two places; weak edges are dropped and
places closer than ``place_merge_distance`` are merged.

Place ids depend only on geometry (the cell holding the place and its rank inside the cell),
so identical maps give identical ids and graphs of different maps can be compared cell by cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from kimera_multi_py.scene_graph.grid import DistanceField
from kimera_multi_py.scene_graph.params import SceneGraphParams

_OFFSETS = [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1) if (dx, dy, dz) > (0, 0, 0)]
_AXIS_BITS = 12  # per axis of the place-cell index in a place id
_RANK_BITS = 8


@dataclass
class Places:
    """Place nodes (sorted by id) and their edges (indices into the places)."""

    ids: np.ndarray  # (n,) int64
    positions: np.ndarray  # (n, 3) map frame
    clearance: np.ndarray  # (n,)
    edges: np.ndarray  # (m, 2) int64, i < j
    edge_clearance: np.ndarray  # (m,)

    def __len__(self) -> int:
        return len(self.ids)


def gvd_mask(field: DistanceField, params: SceneGraphParams) -> np.ndarray:
    """Boolean mask of the GVD voxels (vectorised over the voxel pairs of the candidates only)."""
    grid = field.grid
    clear = field.clearance
    shape = clear.shape
    ok = (grid.free & (clear > params.gvd_min_clearance)).reshape(-1)
    a0 = np.flatnonzero(ok)  # free cells are never on the grid border (it is padded with unknown cells)
    coords = np.unravel_index(a0, shape)
    par = [field.parents[k].reshape(-1) for k in range(3)]
    pa0 = [par[k][a0] for k in range(3)]
    rel0 = [pa0[k] - coords[k].astype(np.int32) for k in range(3)]
    norm = clear.reshape(-1) / np.float32(grid.resolution)  # |parent - voxel| in voxels
    na0 = norm[a0] * np.float32(params.gvd_parent_cos)
    strides = (shape[1] * shape[2], shape[2], 1)
    far2 = params.gvd_parent_voxels**2
    gvd = np.zeros(ok.shape, dtype=np.bool_)
    for off in _OFFSETS:
        b0 = a0 + (off[0] * strides[0] + off[1] * strides[1] + off[2] * strides[2])
        both = np.flatnonzero(ok[b0])
        b = b0[both]
        dp2 = np.zeros(len(b), dtype=np.int32)
        dot = np.zeros(len(b), dtype=np.int32)
        for k in range(3):
            pb = par[k][b]
            d = pa0[k][both] - pb
            dp2 += d * d
            dot += rel0[k][both] * (pb - (coords[k][both] + off[k]).astype(np.int32))
        distinct = (dp2 > far2) | (dot < na0[both] * norm[b])
        gvd[a0[both[distinct]]] = True
        gvd[b[distinct]] = True
    return gvd.reshape(shape)


def _cells(points: np.ndarray, cell: float) -> np.ndarray:
    return np.floor(points / cell + 1e-9).astype(np.int64)


def _segment_clearance(field: DistanceField, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest clearance along each straight segment ``a[i] -> b[i]`` (sampled at half a voxel)."""
    if len(a) == 0:
        return np.zeros(0)
    length = np.linalg.norm(b - a, axis=1)
    n = int(np.ceil(length.max() / (0.5 * field.grid.resolution))) + 1
    s = np.linspace(0.0, 1.0, max(n, 2))
    pts = a[:, None, :] + s[None, :, None] * (b - a)[:, None, :]
    return field.clearance_at(pts).min(axis=1)


def _freespace_edges(field: DistanceField, pos: np.ndarray, e: np.ndarray, w: np.ndarray,
                     params: SceneGraphParams) -> tuple[np.ndarray, np.ndarray]:
    """Join the components of the places graph through free space (Hydra's freespace edges): the
    GVD breaks where clutter or an unobserved patch leaves no voxel of enough clearance, though the
    space is one. Candidates are place pairs of different components at most
    ``freespace_edge_max_length`` apart whose straight segment keeps ``edge_min_clearance``; per pair
    of components the candidate of largest clearance is added (ties: the shorter, then by index)."""
    m = len(pos)
    if params.freespace_edge_max_length <= 0 or m < 2:
        return e, w
    _, comp = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(m, m)), directed=False)
    if comp.max() == 0:
        return e, w
    pairs = cKDTree(pos).query_pairs(params.freespace_edge_max_length, output_type="ndarray")
    pairs = pairs[comp[pairs[:, 0]] != comp[pairs[:, 1]]]
    if len(pairs) == 0:
        return e, w
    pairs = np.sort(pairs, axis=1)
    pw = _segment_clearance(field, pos[pairs[:, 0]], pos[pairs[:, 1]])
    ok = pw >= params.edge_min_clearance
    pairs, pw = pairs[ok], pw[ok]
    length = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1)
    ca, cb = np.sort(comp[pairs], axis=1).T
    order = np.lexsort((pairs[:, 1], pairs[:, 0], length, -pw, cb, ca))
    first = order[np.r_[True, (ca[order][1:] != ca[order][:-1]) | (cb[order][1:] != cb[order][:-1])]] \
        if len(order) else order
    return np.concatenate([e, pairs[first]]), np.concatenate([w, pw[first]])


def place_ids(positions: np.ndarray, cell: float) -> np.ndarray:
    """Geometry-derived ids: the place's cell and its rank among the cell's places (by position)."""
    c = _cells(positions, cell)
    half = 1 << (_AXIS_BITS - 1)
    if len(c) and (c.min() < -half or c.max() >= half):
        raise ValueError(f"places beyond +-{half * cell:.0f} m cannot be given ids")
    key = ((c[:, 0] + half) << (2 * _AXIS_BITS)) | ((c[:, 1] + half) << _AXIS_BITS) | (c[:, 2] + half)
    order = np.lexsort((positions[:, 2], positions[:, 1], positions[:, 0], key))
    sk = key[order]
    first = np.r_[True, sk[1:] != sk[:-1]]
    start = np.maximum.accumulate(np.where(first, np.arange(len(sk)), 0))
    rank = np.empty(len(sk), dtype=np.int64)
    rank[order] = np.arange(len(sk)) - start
    if len(rank) and rank.max() >= 1 << _RANK_BITS:
        raise ValueError("too many places in one cell")
    return (key << _RANK_BITS) | rank


def extract_places(field: DistanceField, params: SceneGraphParams) -> Places:
    """GVD -> clusters per cell -> places, merged, with clearance-weighted edges."""
    grid = field.grid
    shape = field.clearance.shape
    cand = gvd_mask(field, params) & (field.clearance >= params.place_min_clearance)
    lin = np.flatnonzero(cand)
    if len(lin) == 0:
        z = np.zeros(0)
        return Places(np.zeros(0, np.int64), np.zeros((0, 3)), z, np.zeros((0, 2), np.int64), z)
    centers = grid.centers(np.stack(np.unravel_index(lin, shape), -1))
    cell = _cells(centers, params.place_cell)
    clear = field.clearance.reshape(-1)[lin].astype(np.float64)
    # voxel pairs among candidates: same cell -> one cluster; across cells -> an edge
    slot = np.full(cand.size, -1, dtype=np.int64)
    slot[lin] = np.arange(len(lin))
    strides = (shape[1] * shape[2], shape[2], 1)
    same_u, same_v, cross_u, cross_v = [], [], [], []
    for off in _OFFSETS:
        j = slot[lin + (off[0] * strides[0] + off[1] * strides[1] + off[2] * strides[2])]
        iu = np.flatnonzero(j >= 0)
        iv = j[iu]
        same = np.all(cell[iu] == cell[iv], axis=1)
        same_u.append(iu[same])
        same_v.append(iv[same])
        cross_u.append(iu[~same])
        cross_v.append(iv[~same])
    su, sv = np.concatenate(same_u), np.concatenate(same_v)
    n = len(lin)
    _, cluster = connected_components(coo_matrix((np.ones(len(su)), (su, sv)), shape=(n, n)), directed=False)
    # a cluster's place is its voxel of largest clearance (ties: lowest grid index)
    order = np.lexsort((lin, -clear, cluster))
    first = order[np.r_[True, cluster[order][1:] != cluster[order][:-1]]]
    pos, pclear = centers[first], clear[first]
    # merge places closer than the merge distance into the one of largest clearance
    m = len(first)
    pairs = cKDTree(pos).query_pairs(params.place_merge_distance, output_type="ndarray")
    _, group = connected_components(coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m)),
                                    directed=False)
    gorder = np.lexsort((pos[:, 2], pos[:, 1], pos[:, 0], -pclear, group))
    rep = gorder[np.r_[True, group[gorder][1:] != group[gorder][:-1]]]
    rep_of_group = np.empty(group.max() + 1, dtype=np.int64)
    rep_of_group[group[rep]] = np.arange(len(rep))
    place_of_cluster = rep_of_group[group]
    pos, pclear = pos[rep], pclear[rep]
    # edges between touching clusters, weighted by the clearance of the segment
    cu, cv = np.concatenate(cross_u), np.concatenate(cross_v)
    eu, ev = place_of_cluster[cluster[cu]], place_of_cluster[cluster[cv]]
    keep = eu != ev
    lo_, hi_ = np.minimum(eu[keep], ev[keep]), np.maximum(eu[keep], ev[keep])
    key = np.unique(lo_ * m + hi_)
    e = np.stack([key // m, key % m], 1)
    w = _segment_clearance(field, pos[e[:, 0]], pos[e[:, 1]])
    strong = w >= params.edge_min_clearance
    e, w = _freespace_edges(field, pos, e[strong], w[strong], params)
    # sort places by id and renumber the edges
    ids = place_ids(pos, params.place_cell)
    order = np.argsort(ids)
    new = np.empty(len(order), dtype=np.int64)
    new[order] = np.arange(len(order))
    e = np.sort(new[e], axis=1)
    eo = np.lexsort((e[:, 1], e[:, 0]))
    return Places(ids[order], pos[order], pclear[order], e[eo], w[eo])
