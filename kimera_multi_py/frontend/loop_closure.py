"""Loop-closure front end: object-constellation descriptors and geometric verification.

* **Descriptor.** A place is summarised by the objects around it: a histogram over
  (unordered class pair, pairwise distance bin) plus per-class counts, L2-normalised.
  It is invariant to the viewpoint and a few hundred bytes on the wire; similarity is the
  cosine of two descriptors.
* **Verification** (TEASER-style). Class-consistent correspondences between two object
  sets, the maximum clique of pairwise-distance-consistent correspondences (exact, igraph; see
  :mod:`kimera_multi_py.core.clique`), then a Umeyama pose on the clique. Accepted with enough
  inliers that span more than a line.
  The agent then refines the pose by GICP on the semantic clouds
  (:class:`~kimera_multi_py.mapping.registration.ScanRegistration`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kimera_multi_py.core.clique import max_clique
from kimera_multi_py.core.geometry import make_pose, umeyama


@dataclass(frozen=True)
class DescriptorSpec:
    """Layout of the constellation descriptor."""

    num_classes: int
    max_distance: float = 8.0
    bins: int = 16

    @property
    def num_pairs(self) -> int:
        return self.num_classes * (self.num_classes + 1) // 2

    @property
    def size(self) -> int:
        return self.num_pairs * self.bins + self.num_classes


def constellation_descriptor(xyz: np.ndarray, cls: np.ndarray, spec: DescriptorSpec) -> np.ndarray:
    """Descriptor ``(spec.size,)`` float32 of objects at ``xyz`` ``(n, 3)`` with classes ``cls`` in ``[0, K)``."""
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    cls = np.asarray(cls, dtype=int).reshape(-1)
    out = np.zeros(spec.size, dtype=np.float64)
    counts = np.bincount(cls, minlength=spec.num_classes)[: spec.num_classes]
    out[spec.num_pairs * spec.bins :] = counts
    if len(xyz) >= 2:
        i, j = np.triu_indices(len(xyz), k=1)
        a, b = np.minimum(cls[i], cls[j]), np.maximum(cls[i], cls[j])
        pair = a * spec.num_classes - a * (a - 1) // 2 + (b - a)  # index of (a, b), a <= b
        dist = np.linalg.norm(xyz[i] - xyz[j], axis=1)
        keep = dist < spec.max_distance
        dbin = (dist[keep] / spec.max_distance * spec.bins).astype(int)
        np.add.at(out, pair[keep] * spec.bins + dbin, 1.0)
    norm = np.linalg.norm(out)
    return (out / norm if norm > 0 else out).astype(np.float32)


def similarity(query: np.ndarray, database: np.ndarray) -> np.ndarray:
    """Cosine similarity of one descriptor against ``(n, d)`` descriptors (all L2-normalised)."""
    database = np.asarray(database, dtype=np.float32).reshape(-1, len(query))
    return database @ np.asarray(query, dtype=np.float32)


@dataclass(frozen=True)
class Verification:
    """Outcome of geometric verification: ``T`` maps target points into the source frame."""

    accepted: bool
    T: np.ndarray
    inliers: np.ndarray  # (k, 2) index pairs (source, target)
    reason: str = ""

    @property
    def num_inliers(self) -> int:
        return len(self.inliers)


def class_consistent_pairs(src_cls: np.ndarray, dst_cls: np.ndarray) -> np.ndarray:
    """All ``(i, j)`` with equal class, ``(c, 2)``."""
    i, j = np.nonzero(np.asarray(src_cls)[:, None] == np.asarray(dst_cls)[None, :])
    return np.column_stack([i, j])


def consistent_clique(src: np.ndarray, dst: np.ndarray, pairs: np.ndarray, eps: float) -> np.ndarray:
    """Rows of ``pairs`` in the maximum clique of pairwise-distance-consistent correspondences."""
    if len(pairs) == 0:
        return np.zeros(0, dtype=int)
    ds = np.linalg.norm(src[pairs[:, 0], None] - src[None, pairs[:, 0]], axis=-1)
    dd = np.linalg.norm(dst[pairs[:, 1], None] - dst[None, pairs[:, 1]], axis=-1)
    distinct = (pairs[:, 0, None] != pairs[None, :, 0]) & (pairs[:, 1, None] != pairs[None, :, 1])
    err = np.abs(ds - dd)
    return max_clique(distinct & (err <= eps), err)


def verify(src_xyz: np.ndarray, src_cls: np.ndarray, dst_xyz: np.ndarray, dst_cls: np.ndarray,
           eps: float = 0.3, min_inliers: int = 4, min_spread: float = 0.5) -> Verification:
    """Relative pose between two labelled point sets (e.g. object centroids), or a rejection.

    ``eps``: tolerance on pairwise distances (m); after the fit a clique member stays an inlier
    within ``2 eps`` of its match (object centres from partial views disagree by a few
    decimetres); ``min_spread``: the inliers' second principal extent (m) must exceed this, so
    the rotation is not ambiguous about a line.
    """
    src_xyz = np.asarray(src_xyz, dtype=float).reshape(-1, 3)
    dst_xyz = np.asarray(dst_xyz, dtype=float).reshape(-1, 3)
    pairs = class_consistent_pairs(src_cls, dst_cls)
    clique = pairs[consistent_clique(src_xyz, dst_xyz, pairs, eps)]
    if len(clique) < min_inliers:
        return Verification(False, np.eye(4), clique, f"{len(clique)} inliers < {min_inliers}")
    s, d = src_xyz[clique[:, 0]], dst_xyz[clique[:, 1]]
    spread = np.linalg.svd(d - d.mean(0), compute_uv=False)
    if spread[1] / np.sqrt(len(d)) < min_spread / 2:
        return Verification(False, np.eye(4), clique, "inliers are nearly collinear")
    R, t, _ = umeyama(d, s)
    T = make_pose(R, t)
    resid = np.linalg.norm(d @ R.T + t - s, axis=1)
    inl = clique[resid <= 2 * eps]
    if len(inl) < min_inliers:
        return Verification(False, T, inl, f"{len(inl)} inliers after the fit < {min_inliers}")
    return Verification(True, T, inl)


def voxel_downsample(xyz: np.ndarray, labels: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """One point (the first) per occupied voxel and label."""
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    if len(xyz) == 0:
        return xyz, np.asarray(labels).reshape(-1)
    keys = np.floor(xyz / voxel).astype(np.int64)
    _, first = np.unique(np.column_stack([keys, np.asarray(labels).reshape(-1, 1)]), axis=0, return_index=True)
    first.sort()
    return xyz[first], np.asarray(labels)[first]


def voxel_centroids(xyz: np.ndarray, labels: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """One point per occupied voxel (of a grid anchored at the origin): the mean of its points,
    with their most frequent label (ties: the lowest), in voxel order.

    At the resolution of a :class:`~kimera_multi_py.mapping.registration.ScanRegistration`
    this is the cloud its own voxel downsampling makes of ``xyz`` (one mean per voxel), so a
    registration sees the same points whichever of the two it is handed."""
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    labels = np.asarray(labels).reshape(-1)
    if len(xyz) == 0:
        return xyz, labels
    _, inv, count = np.unique(np.floor(xyz / voxel).astype(np.int64), axis=0, return_inverse=True,
                              return_counts=True)
    inv = inv.reshape(-1)
    n = len(count)
    mean = np.stack([np.bincount(inv, weights=xyz[:, i], minlength=n) for i in range(3)], axis=1) / count[:, None]
    pairs, votes = np.unique(np.column_stack([inv, labels]), axis=0, return_counts=True)
    order = np.lexsort((pairs[:, 1], -votes, pairs[:, 0]))  # per voxel: most votes, then lowest label
    first = np.unique(pairs[order, 0], return_index=True)[1]
    return mean, pairs[order[first], 1].astype(labels.dtype)
