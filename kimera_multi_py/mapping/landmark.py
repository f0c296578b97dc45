"""Object landmarks: one object's evidence over many keyframes (docs/algorithms/mapping.md).

A landmark keeps a Dirichlet class posterior, a running centroid of its points, the voxels its
points fell in with hit counts, and its number of observations. Its box is the extent of the
voxels hit at least ``min_voxel_hits`` times (one-off mislabelled points do not grow it), and
its ``position`` is the box centre: surface points are biased toward the sides that were seen,
the union of views is not. The box is upright and aligned with the walls' axes (:mod:`.axes`),
or with its submap's reference frame while the map has no clear walls. Geometry is stored in
the reference frame of the submap the landmark was created in, so it re-anchors exactly when
that submap moves. :class:`~.objects.ObjectMap` creates, updates and merges landmarks.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kimera_multi_py.core.geometry import so3_exp, transform_points
from kimera_multi_py.mapping import morton


@dataclass
class Landmark:
    """An object landmark; geometry is kept in its anchor submap's reference frame."""

    id: int
    submap: int
    class_counts: np.ndarray  # (K+1,) Dirichlet counts (prior included)
    point_sum: np.ndarray  # (3,) sum of observed points, reference frame
    num_points: int
    voxels: np.ndarray  # sorted voxel codes hit, reference frame
    voxel_hits: np.ndarray  # hits per voxel
    num_observations: int = 1
    first_seen: int = 0
    last_seen: int = 0
    confirmed: bool = False
    T_world_ref: np.ndarray = field(default_factory=lambda: np.eye(4))
    resolution: float = 0.1
    min_voxel_hits: int = 2
    axes_yaw: float | None = None  # world heading of the box's axes; None: the reference frame's
    _cache: dict[str, object] = field(default_factory=dict, repr=False, compare=False)

    def invalidate(self) -> None:
        """Forget cached derived values after the landmark changed or moved."""
        self._cache.clear()

    @property
    def label(self) -> int:
        if "label" not in self._cache:
            self._cache["label"] = int(np.argmax(self.class_counts))
        return self._cache["label"]  # type: ignore[return-value]

    @property
    def posterior(self) -> np.ndarray:
        """Class PMF (Dirichlet mean)."""
        return self.class_counts / self.class_counts.sum()

    @property
    def centroid(self) -> np.ndarray:
        """Running centroid of the observed points (world frame)."""
        return transform_points(self.T_world_ref, (self.point_sum / self.num_points)[None])[0]

    def supported_centers(self) -> np.ndarray:
        """Reference-frame centres of the voxels hit at least ``min_voxel_hits`` times (all
        voxels while none is)."""
        keep = self.voxel_hits >= self.min_voxel_hits
        codes = self.voxels[keep] if keep.any() else self.voxels
        return morton.node_centers(codes, np.zeros(len(codes), np.int8), self.resolution)

    def box(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Oriented box in the world, ``(center, size, R)``: the extent of the centres of the
        well-supported voxels along the box's axes (upright at ``axes_yaw``, or the reference
        frame's), one voxel wider."""
        if "box" not in self._cache:
            c = self.supported_centers()
            if self.axes_yaw is None:
                R, q, t = self.T_world_ref[:3, :3].copy(), c, self.T_world_ref[:3, 3]
            else:
                R, t = so3_exp(np.array([0.0, 0.0, self.axes_yaw])), np.zeros(3)
                q = transform_points(self.T_world_ref, c) @ R  # coordinates along the axes
            lo, hi = q.min(0), q.max(0)
            self._cache["box"] = (R @ ((lo + hi) / 2) + t, hi - lo + self.resolution, R)
        return self._cache["box"]  # type: ignore[return-value]

    @property
    def position(self) -> np.ndarray:
        """Centre of the landmark's box (world frame): the object's position estimate."""
        return self.box()[0].copy()

    def ref_aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """World bounds of the box in the landmark's reference axes. Association, merging and
        place descriptors use it (and :attr:`ref_position`), not the walls' axes: an estimate
        of the axes that moves never changes which detections are one object or which places
        look alike, so the front end does not depend on it."""
        if "ref_aabb" not in self._cache:
            c = self.supported_centers()
            lo, hi = c.min(0), c.max(0)
            center = transform_points(self.T_world_ref, ((lo + hi) / 2)[None])[0]
            ext = np.abs(self.T_world_ref[:3, :3]) @ ((hi - lo + self.resolution) / 2)
            self._cache["ref_aabb"] = (center - ext, center + ext)
        return self._cache["ref_aabb"]  # type: ignore[return-value]

    @property
    def ref_position(self) -> np.ndarray:
        """Centre of :meth:`ref_aabb` (world frame)."""
        lo, hi = self.ref_aabb()
        return (lo + hi) / 2

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """World axis-aligned bounds of the oriented box."""
        if "aabb" not in self._cache:
            center, size, R = self.box()
            ext = np.abs(R) @ (size / 2)
            self._cache["aabb"] = (center - ext, center + ext)
        return self._cache["aabb"]  # type: ignore[return-value]
