"""Object detections: Euclidean clusters of the same-class end points of one keyframe
(docs/algorithms/mapping.md).

Structure and dynamic classes are not objects. Points are linked at ``cluster_radius`` (about
two voxels) through *core* points, points with ``min_core`` neighbours (DBSCAN's rule), so a
few mislabelled points cannot chain two objects together. A cluster needs ``min_points``
points and must hold at least ``min_purity`` of all the points in the voxels it covers: label
noise on a large, densely sampled surface can form clusters, but it is always a small minority
where it lies. :class:`~.objects.ObjectMap` associates the detections with its landmarks.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from kimera_multi_py.mapping import morton


@dataclass
class Detection:
    """One cluster of same-class end points from one keyframe (world frame)."""

    label: int
    points: np.ndarray  # (n, 3)
    centroid: np.ndarray  # (3,)
    box_min: np.ndarray  # (3,)
    box_max: np.ndarray  # (3,)

    @property
    def num_points(self) -> int:
        return len(self.points)


def _core_clusters(P: np.ndarray, radius: float, min_core: int, pairs: np.ndarray | None = None) -> np.ndarray:
    """Cluster id per point (-1 for noise): single linkage over *core* points only.

    A core point has at least ``min_core`` neighbours within ``radius``; other points join
    the cluster of a core neighbour. Isolated mislabelled points therefore cannot chain two
    objects together (DBSCAN's rule). ``pairs`` (m, 2), when given, are the neighbours instead.
    """
    n = len(P)
    if pairs is None:
        pairs = cKDTree(P).query_pairs(radius, output_type="ndarray")
    degree = np.bincount(pairs.ravel(), minlength=n)
    core = degree >= min_core
    both = core[pairs[:, 0]] & core[pairs[:, 1]]
    cp = pairs[both]
    graph = coo_matrix((np.ones(len(cp)), (cp[:, 0], cp[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    out = np.where(core, comp, -1)
    # border points take the cluster of a core neighbour
    border = pairs[core[pairs[:, 0]] ^ core[pairs[:, 1]]]
    src = np.where(core[border[:, 0]], border[:, 0], border[:, 1])
    dst = np.where(core[border[:, 0]], border[:, 1], border[:, 0])
    out[dst] = comp[src]
    # relabel to 0..m-1
    valid = out >= 0
    _, out[valid] = np.unique(out[valid], return_inverse=True)
    return out


def detect_objects(
    points: np.ndarray,
    labels: np.ndarray,
    object_classes: Iterable[int],
    cluster_radius: float,
    min_points: int = 8,
    min_purity: float = 0.5,
    purity_voxel: float | None = None,
    min_core: int = 3,
) -> list[Detection]:
    """Euclidean clusters of same-class points, one detection per cluster of ``min_points``+.

    Clustering links points within ``cluster_radius`` through core points (points with
    ``min_core`` neighbours), so sparse label noise cannot bridge two objects.

    A cluster is kept only if its class holds at least ``min_purity`` of all the points
    (any class) in the voxels (edge ``purity_voxel``, default ``cluster_radius / 2``) it
    occupies: label noise on a large surface chains into clusters at high point densities,
    but it is always a small minority where it lies.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    lab = np.asarray(labels).reshape(-1).astype(np.int64)
    if len(pts) != len(lab):
        raise ValueError(f"{len(pts)} points but {len(lab)} labels")
    ok = np.all(np.isfinite(pts), axis=1)
    pts, lab = pts[ok], lab[ok]
    classes = np.array(sorted({int(x) for x in object_classes}), dtype=np.int64)
    sel = np.isin(lab, classes)
    if sel.sum() < min_points:
        return []
    P, L = pts[sel], lab[sel]
    # one clustering for all classes: classes are moved far apart along x
    comp = _core_clusters(
        P + (L * 1.0e4)[:, None] * np.array([1.0, 0.0, 0.0]), cluster_radius, min_core
    )
    keep = comp >= 0
    P, L, comp = P[keep], L[keep], comp[keep]
    if len(P) == 0:
        return []
    order = np.argsort(comp, kind="stable")
    P, L, comp = P[order], L[order], comp[order]
    sizes = np.bincount(comp)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    mins = np.minimum.reduceat(P, starts, axis=0)
    maxs = np.maximum.reduceat(P, starts, axis=0)
    sums = np.add.reduceat(P, starts, axis=0)
    # purity: the cluster's points over all points in the voxels it occupies
    voxel = cluster_radius / 2 if purity_voxel is None else purity_voxel
    vox, vox_count = np.unique(morton.points_to_codes(pts, voxel), return_counts=True)
    cells = np.unique(np.stack([comp, morton.points_to_codes(P, voxel)], axis=1), axis=0)
    total = np.bincount(
        cells[:, 0], weights=vox_count[np.searchsorted(vox, cells[:, 1])], minlength=len(sizes)
    )
    good = (sizes >= min_points) & (sizes >= min_purity * total)
    return [
        Detection(
            int(L[starts[k]]),
            P[starts[k] : starts[k] + sizes[k]],
            sums[k] / sizes[k],
            mins[k],
            maxs[k],
        )
        for k in np.flatnonzero(good)
    ]
