"""Person detections: the points of one keyframe labelled with a dynamic class, clustered
(docs/algorithms/people.md).

Points are linked within ``radius`` through core points
(:func:`~kimera_multi_py.mapping.detection`'s DBSCAN rule on a KD-tree radius graph, scipy), so
scattered label noise cannot chain into a person. The rays spread with range: beyond ``radius /
link_angle`` from ``sensor`` two points are linked within ``link_angle`` x their mean range (about
two of the camera's ray spacings), so that a far person seen as a sliver one ray wide (half hidden
behind another), or whose upper and lower body a few flipped labels separate, still has core points
that link it into one. A cluster is a person when it has at least ``min_points`` points, a
horizontal extent of at most ``max_width``, a vertical extent between ``min_height`` and
``max_height``, and holds at least ``min_purity`` of all the points (any class) in the voxels (edge
``radius / 2``) it covers: label noise on a wall seen from close by is dense enough to cluster, but
it is a small minority where it lies. A cluster that spans at least ``view_span`` of the keyframe's
vertical field of view (the elevation angles, seen from ``sensor``, of all its points) is cut off by
the view, not flat: a person right in front of the camera fills the image but shows only a few
centimetres of height; ``min_height`` does not apply to it. The others are dropped and counted by
reason. A camera sees only the near side of a person, so the centroid is pushed away from the sensor
by ``depth_offset`` (for an upright cylinder of radius r seen from the side, the visible points'
mean lies ``pi r / 4`` in front of its axis). When the side of the image cuts a person off (the
cluster reaches within ``edge_angle`` of the keyframe's widest azimuth), the visible points lean
towards the middle of the image and their mean is biased by up to r; the axis is then the centre
of the circle of radius r that best fits the body's waist, started r behind the silhouette on the
uncut side.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from kimera_multi_py.mapping import morton
from kimera_multi_py.mapping.detection import _core_clusters


@dataclass
class PersonDetections:
    """A keyframe's person detections (world frame of the robot's estimate)."""

    centroids: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (n, 3)
    extents: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (n, 3) box sizes
    counts: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # (n,) points

    def __len__(self) -> int:
        return len(self.centroids)

    def valid(self) -> np.ndarray:
        """Rows with a finite centroid and extent and at least one point."""
        return (np.all(np.isfinite(self.centroids), axis=1) & np.all(np.isfinite(self.extents), axis=1)
                & (self.counts > 0))

    def take(self, mask: np.ndarray) -> PersonDetections:
        return PersonDetections(self.centroids[mask], self.extents[mask], self.counts[mask])


def detect_people(points: np.ndarray, labels: np.ndarray, dynamic_classes: Iterable[int],
                  sensor: np.ndarray | None = None, *, radius: float = 0.3, min_core: int = 3,
                  min_points: int = 10, max_width: float = 1.2, min_height: float = 0.25,
                  max_height: float = 2.4, depth_offset: float = 0.2, min_purity: float = 0.5,
                  view_span: float = 0.9, link_angle: float = 0.05, edge_angle: float = 0.03,
                  dropped: Counter[str] | None = None) -> PersonDetections:
    """Person detections among ``points`` (n, 3, world frame) whose ``labels`` are in
    ``dynamic_classes``; ``sensor`` is the sensor's position (for the depth offset; none: no
    offset). Clusters that fail a gate are counted in ``dropped`` (``too_small``, ``too_wide``,
    ``too_flat``, ``too_tall``, ``impure``); so are non-finite points (``non_finite_points``)."""
    dropped = Counter() if dropped is None else dropped
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    lab = np.asarray(labels).reshape(-1)
    if len(pts) != len(lab):
        raise ValueError(f"{len(pts)} points but {len(lab)} labels")
    sel = np.isin(lab, np.array(sorted({int(c) for c in dynamic_classes}), dtype=np.int64))
    finite = np.all(np.isfinite(pts), axis=1)
    if (bad := int((sel & ~finite).sum())):
        dropped["non_finite_points"] += bad
    P = pts[sel & finite]
    if len(P) < min_points:
        return PersonDetections()
    comp = _core_clusters(P, radius, min_core, _neighbours(P, sensor, radius, link_angle))
    keep = comp >= 0
    P, comp = P[keep], comp[keep]
    if len(P) == 0:
        return PersonDetections()
    order = np.argsort(comp, kind="stable")
    P, comp = P[order], comp[order]
    sizes = np.bincount(comp)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    lo, hi = np.minimum.reduceat(P, starts, axis=0), np.maximum.reduceat(P, starts, axis=0)
    centroid = np.add.reduceat(P, starts, axis=0) / sizes[:, None]
    ext = hi - lo
    width = np.hypot(ext[:, 0], ext[:, 1])
    small, wide = sizes < min_points, width > max_width
    flat, tall = ext[:, 2] < min_height, ext[:, 2] > max_height
    if sensor is not None:
        flat &= ~_fills_view(pts[finite], P, starts, np.asarray(sensor, dtype=np.float64).reshape(3), view_span)
    for name, m in (("too_small", small), ("too_wide", wide & ~small), ("too_flat", flat & ~small & ~wide),
                    ("too_tall", tall & ~small & ~wide & ~flat)):
        if (n := int(m.sum())):
            dropped[name] += n
    voxel = radius / 2
    vox, vox_count = np.unique(morton.points_to_codes(pts[finite], voxel), return_counts=True)
    cells = np.unique(np.stack([comp, morton.points_to_codes(P, voxel)], axis=1), axis=0)
    total = np.bincount(cells[:, 0], weights=vox_count[np.searchsorted(vox, cells[:, 1])], minlength=len(sizes))
    impure = (sizes < min_purity * total) & ~(small | wide | flat | tall)
    if (n := int(impure.sum())):
        dropped["impure"] += n
    good = ~(small | wide | flat | tall | impure)
    if sensor is not None and depth_offset > 0 and good.any():
        sxy = np.asarray(sensor, dtype=np.float64).reshape(3)[:2]
        ray = centroid[:, :2] - sxy
        norm = np.linalg.norm(ray, axis=1, keepdims=True)
        axis = centroid[:, :2] + depth_offset * ray / np.maximum(norm, 1e-9)
        if edge_angle > 0:
            axis = _behind_silhouette(pts[finite][:, :2], P, starts, sxy, axis, 4 * depth_offset / np.pi, edge_angle)
        centroid[:, :2] = axis
    centroid, ext, sizes = centroid[good], ext[good], sizes[good]
    return PersonDetections(centroid, ext, sizes.astype(np.int64))


def _fills_view(scan: np.ndarray, P: np.ndarray, starts: np.ndarray, sensor: np.ndarray, share: float) -> np.ndarray:
    """Per cluster (``P`` sorted by cluster, from ``starts``): whether its elevation angles seen
    from ``sensor`` span at least ``share`` of those of the keyframe's points (``scan``) in the
    cluster's azimuth sector (a pinhole camera's image edge lies lower off its centre)."""
    def angles(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = X - sensor
        return np.arctan2(d[:, 1], d[:, 0]), np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))

    az_s, el_s = angles(scan)
    az, el = angles(P)
    ends = np.append(starts[1:], len(P))
    out = np.zeros(len(starts), dtype=bool)
    for c, (a, b) in enumerate(zip(starts.tolist(), ends.tolist(), strict=True)):  # per cluster, not per point
        ref = az[a]
        off = np.angle(np.exp(1j * (az[a:b] - ref)))
        sector = np.angle(np.exp(1j * (az_s - ref)))
        inside = (sector >= off.min()) & (sector <= off.max())
        view = el_s[inside]
        out[c] = np.ptp(el[a:b]) >= share * np.ptp(view) if len(view) else False
    return out


def _neighbours(P: np.ndarray, sensor: np.ndarray | None, radius: float, link_angle: float) -> np.ndarray | None:
    """Pairs of points within ``radius``, or within ``link_angle`` x their mean range from ``sensor``
    where that is larger (None: ``radius`` alone)."""
    if sensor is None or link_angle <= 0:
        return None
    rng = np.linalg.norm(P - np.asarray(sensor, dtype=np.float64).reshape(3), axis=1)
    reach = max(radius, link_angle * float(rng.max()))
    pairs = cKDTree(P).query_pairs(reach, output_type="ndarray")
    d = np.linalg.norm(P[pairs[:, 0]] - P[pairs[:, 1]], axis=1)
    return pairs[d <= np.maximum(radius, link_angle * 0.5 * (rng[pairs[:, 0]] + rng[pairs[:, 1]]))]


def _behind_silhouette(scan: np.ndarray, P: np.ndarray, starts: np.ndarray, sensor: np.ndarray, axis: np.ndarray,
                       radius: float, edge: float) -> np.ndarray:
    """Axes (n, 2) of the clusters (``P`` sorted by cluster, from ``starts``) that the side of the
    image cuts (their azimuth from ``sensor`` within ``edge`` of the keyframe's widest, ``scan``):
    the centre of the circle of ``radius`` that best fits the cluster's waist (the middle half of
    its height, where the body is widest), started a radius behind the silhouette on the uncut
    side (if the fit lands in front of the visible points, the centroid rule stands: a short arc
    fits a circle on either side). The others keep ``axis``."""
    def azimuth(X: np.ndarray, ref: float) -> np.ndarray:
        d = X[:, :2] - sensor
        return np.angle(np.exp(1j * (np.arctan2(d[:, 1], d[:, 0]) - ref)))

    d = scan - sensor
    ref = float(np.arctan2(d[:, 1].sum(), d[:, 0].sum()))  # the view's middle
    view = azimuth(scan, ref)
    az = azimuth(P, ref)
    lo, hi = np.minimum.reduceat(az, starts), np.maximum.reduceat(az, starts)
    out = axis.copy()
    ends = np.append(starts[1:], len(P))
    for c, (a, b) in enumerate(zip(starts.tolist(), ends.tolist(), strict=True)):  # per cluster, not per point
        cut_hi, cut_lo = hi[c] >= view.max() - edge, lo[c] <= view.min() + edge
        if cut_hi == cut_lo:  # whole, or wider than the view: the centroid rule holds
            continue
        z = P[a:b, 2]
        mid = np.abs(z - 0.5 * (z.min() + z.max())) <= 0.25 * np.ptp(z)
        Q, qa = P[a:b][mid, :2], az[a:b][mid]
        if len(Q) < 3:
            continue
        k = int(np.argmin(qa) if cut_hi else np.argmax(qa))  # where the waist's silhouette grazes a ray
        g = (Q[k] - sensor) / max(float(np.linalg.norm(Q[k] - sensor)), 1e-9)
        n = np.array([-g[1], g[0]])  # towards larger azimuth
        x = Q[k] + radius * (n if cut_hi else -n)
        for _ in range(10):  # Gauss-Newton on sum (|q - x| - radius)^2
            e = Q - x
            dist = np.maximum(np.linalg.norm(e, axis=1), 1e-9)
            step = np.linalg.lstsq(-e / dist[:, None], -(dist - radius), rcond=None)[0]
            x = x + step
            if np.linalg.norm(step) < 1e-4:
                break
        # a short arc fits a circle on either side of it: the body's axis lies behind what is seen
        if np.linalg.norm(x - sensor) > np.median(np.linalg.norm(Q - sensor, axis=1)):
            out[c] = x
    return out
