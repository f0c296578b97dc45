"""Object map: per-keyframe detections associated with landmarks (docs/algorithms/mapping.md).

Detections (:mod:`.detection`) are clusters of the same-class end points of one keyframe;
landmarks (:mod:`.landmark`) hold one object's evidence in its submap's reference frame.
Detections and landmarks are compatible when the landmark gives the detection's class a
posterior probability of at least ``min_class_prob``, and gated when their centroids are
within ``gate_distance`` or their boxes overlap (a partial view of a long table has a
centroid far from the table's). The assignment minimises the total centroid distance
(``scipy.optimize.linear_sum_assignment``). A detection left over that still gates with a
matched landmark is a second fragment of it and is absorbed; any other starts a tentative
landmark, which is confirmed after ``confirm_after`` sightings. Same-class landmarks are
merged when their boxes overlap strongly or one detection spans both, and, on request
(:meth:`ObjectMap.merge_fragments`), when the map shows that only unseen or occupied space
separates them (an object split by an occluder in every view). The walls' axes that orient
the landmarks' boxes (:mod:`.axes`) are estimated from the structure points of the same
keyframes.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from kimera_multi_py.core.geometry import inverse, transform_points
from kimera_multi_py.core.semantics import CLASS_NAMES, MAX_OBJECT_EXTENT
from kimera_multi_py.mapping import morton
from kimera_multi_py.mapping.axes import StructureAxes
from kimera_multi_py.mapping.detection import Detection, detect_objects
from kimera_multi_py.mapping.landmark import Landmark
from kimera_multi_py.mapping.semantic_octree import SemanticOctree

log = logging.getLogger(__name__)

_INFEASIBLE = 1e9


def _max_extent(labels: np.ndarray) -> np.ndarray:
    """Largest plausible horizontal extent per class id (``inf`` for classes without a prior)."""
    table = np.full(len(CLASS_NAMES), np.inf)
    for name, ext in MAX_OBJECT_EXTENT.items():
        table[CLASS_NAMES.index(name)] = ext
    return table[np.asarray(labels, dtype=int)]



class ObjectMap:
    """Object landmarks built from per-keyframe detections (see module docstring)."""

    def __init__(
        self,
        num_classes: int,
        object_classes: Iterable[int],
        *,
        resolution: float = 0.1,
        cluster_radius: float | None = None,
        min_points: int = 8,
        gate_distance: float = 0.5,
        box_margin: float = 0.1,
        min_class_prob: float = 0.3,
        confirm_after: int = 3,
        min_voxel_hits: int = 2,
        merge_iou: float = 0.3,
        class_prior: float = 0.5,
        min_purity: float = 0.5,
        min_core: int = 3,
        structure_classes: Iterable[int] = (),
    ) -> None:
        self.num_classes = int(num_classes)
        self.object_classes = tuple(sorted({int(c) for c in object_classes}))
        if any(c < 1 or c > self.num_classes for c in self.object_classes):
            raise ValueError(f"object classes must lie in 1..{self.num_classes}")
        if not resolution > 0:
            raise ValueError(f"resolution must be positive, got {resolution}")
        self.resolution = float(resolution)
        self.cluster_radius = (
            2.0 * self.resolution if cluster_radius is None else float(cluster_radius)
        )
        self.min_points = int(min_points)
        self.min_purity = float(min_purity)
        self.min_core = int(min_core)
        self.structure_classes = np.array(
            sorted({int(c) for c in structure_classes}), dtype=np.int64
        )
        self.gate_distance = float(gate_distance)
        self.box_margin = float(box_margin)
        self.min_class_prob = float(min_class_prob)
        self.confirm_after = int(confirm_after)
        self.min_voxel_hits = int(min_voxel_hits)
        self.merge_iou = float(merge_iou)
        self._prior = np.zeros(self.num_classes + 1)
        self._prior[list(self.object_classes)] = float(class_prior)
        self.landmarks: dict[int, Landmark] = {}
        self._submap_ref: dict[int, np.ndarray] = {}
        self._submap_pose: dict[int, np.ndarray] = {}
        self._axes = StructureAxes()
        self.axes_yaw: float | None = None  # heading of the walls' axes (see :mod:`.axes`)
        self._next_id = 0
        self._frame = 0
        self._merged_into: dict[int, int] = {}

    # ---- submaps ---------------------------------------------------------------------------
    def set_submap_pose(self, submap_id: int, pose: np.ndarray) -> None:
        """Record a submap's world pose; later calls re-anchor the landmarks created in it."""
        pose = np.asarray(pose, dtype=np.float64).copy()
        if submap_id not in self._submap_ref:
            self._submap_ref[submap_id] = pose.copy()
        self._submap_pose[submap_id] = pose
        C = pose @ inverse(self._submap_ref[submap_id])
        for lm in self.landmarks.values():
            if lm.submap == submap_id:
                lm.T_world_ref = C.copy()
                lm.invalidate()
        self._refresh_axes()

    def _refresh_axes(self, tolerance: float = np.radians(0.25)) -> None:
        """Adopt the walls' axes as the submaps now place them; boxes follow a change."""
        yaw = self._axes.yaw(self._correction)
        old = self.axes_yaw
        if (yaw is None) == (old is None) and (
            yaw is None or abs((yaw - old + np.pi / 4) % (np.pi / 2) - np.pi / 4) <= tolerance  # type: ignore[operator]
        ):
            return
        self.axes_yaw = yaw
        for lm in self.landmarks.values():
            lm.axes_yaw = yaw
            lm.invalidate()

    def _correction(self, submap_id: int) -> np.ndarray:
        if submap_id not in self._submap_ref:
            return np.eye(4)
        return self._submap_pose[submap_id] @ inverse(self._submap_ref[submap_id])

    # ---- update ----------------------------------------------------------------------------
    def update(
        self, points: np.ndarray, labels: np.ndarray, submap_id: int = 0, stamp: int | None = None
    ) -> list[int]:
        """Detect objects in one keyframe (world-frame end points) and fold them into the map.

        Returns the ids of the landmarks the detections were associated with (new ones too).
        The keyframe's structure points vote for the walls' axes (:mod:`.axes`).
        """
        lab = np.asarray(labels).reshape(-1)
        if len(self.structure_classes) and len(lab) == len(points):
            structure = np.isin(lab, self.structure_classes)
            self._axes.add(submap_id, np.asarray(points, dtype=np.float64).reshape(-1, 3)[structure],
                           self._correction(submap_id))
            self._refresh_axes()
        dets = detect_objects(
            points,
            labels,
            self.object_classes,
            self.cluster_radius,
            self.min_points,
            self.min_purity,
            min_core=self.min_core,
        )
        return self.observe(dets, submap_id, stamp)

    def observe(
        self, detections: list[Detection], submap_id: int = 0, stamp: int | None = None
    ) -> list[int]:
        """Associate detections with landmarks (Hungarian) and update or create landmarks."""
        self._frame = self._frame + 1 if stamp is None else int(stamp)
        if not detections:
            return []
        ids = list(self.landmarks)
        feasible, cost = self._gate(detections, ids)
        rows, cols = linear_sum_assignment(cost) if ids else (np.zeros(0, int), np.zeros(0, int))
        assigned: dict[int, int] = {}
        for r, c in zip(rows, cols, strict=True):
            if feasible[r, c]:
                assigned[int(r)] = ids[int(c)]
        matched_cols = sorted({ids.index(v) for v in assigned.values()})
        touched: list[int] = []
        self._merged_into = {}
        for i, det in enumerate(detections):
            if i in assigned:
                lid = assigned[i]
            elif matched_cols and feasible[i, matched_cols].any():
                # a second fragment of a landmark matched in this keyframe
                cand = [c for c in matched_cols if feasible[i, c]]
                lid = ids[min(cand, key=lambda c: cost[i, c])]
            else:
                lid = self._create(det, submap_id)
                touched.append(lid)
                continue
            while lid in self._merged_into:  # merged away earlier in this keyframe
                lid = self._merged_into[lid]
            self._absorb(self.landmarks[lid], det)
            touched.append(lid)
            self._merge_bridged(lid, det)
        self._merge_overlapping()
        out = []
        for t in touched:
            while t in self._merged_into:
                t = self._merged_into[t]
            out.append(t)
        return list(dict.fromkeys(out))

    def confirmed(self) -> list[Landmark]:
        return [lm for lm in self.landmarks.values() if lm.confirmed]

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """MAP classes ``(n,)`` and box centres ``(n, 3)`` (world) of the confirmed landmarks."""
        lms = self.confirmed()
        return (np.array([lm.label for lm in lms], dtype=np.int32),
                np.array([lm.position for lm in lms], dtype=float).reshape(-1, 3))

    # ---- internals -------------------------------------------------------------------------
    def _gate(self, dets: list[Detection], ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
        n, m = len(dets), len(ids)
        if m == 0:
            return np.zeros((n, 0), dtype=np.bool_), np.zeros((n, 0))
        dc = np.array([d.centroid for d in dets])
        dlo = np.array([d.box_min for d in dets]) - self.box_margin
        dhi = np.array([d.box_max for d in dets]) + self.box_margin
        lms = [self.landmarks[i] for i in ids]
        lc = np.array([lm.ref_position for lm in lms])
        boxes = [lm.ref_aabb() for lm in lms]
        llo = np.array([b[0] for b in boxes])
        lhi = np.array([b[1] for b in boxes])
        post = np.array([lm.posterior for lm in lms])  # (m, K+1)
        dl = np.array([d.label for d in dets])
        compatible = post[:, dl].T >= self.min_class_prob  # (n, m)
        dist = np.linalg.norm(dc[:, None, :] - lc[None, :, :], axis=2)
        overlap = np.all((dlo[:, None, :] <= lhi[None]) & (dhi[:, None, :] >= llo[None]), axis=2)
        feasible = compatible & ((dist <= self.gate_distance) | overlap)
        cost = np.where(feasible, dist, _INFEASIBLE)
        return feasible, cost

    def _ref_points(self, lm_submap: int, points: np.ndarray) -> np.ndarray:
        return transform_points(inverse(self._correction(lm_submap)), points)

    def _voxelise(self, pts_ref: np.ndarray) -> np.ndarray:
        """Sorted unique voxel codes of points (each voxel counts once per detection)."""
        codes = morton.points_to_codes(pts_ref, self.resolution)
        return np.unique(codes[codes >= 0])

    def _create(self, det: Detection, submap_id: int) -> int:
        lid = self._next_id
        self._next_id += 1
        pts = self._ref_points(submap_id, det.points)
        vox = self._voxelise(pts)
        counts = self._prior.copy()
        counts[det.label] += 1.0
        lm = Landmark(
            lid,
            submap_id,
            counts,
            pts.sum(0),
            len(pts),
            vox,
            np.ones(len(vox), dtype=np.int32),
            1,
            self._frame,
            self._frame,
            self.confirm_after <= 1,
            self._correction(submap_id),
            self.resolution,
            self.min_voxel_hits,
        )
        lm.axes_yaw = self.axes_yaw
        self.landmarks[lid] = lm
        return lid

    def _absorb(self, lm: Landmark, det: Detection) -> None:
        pts = self._ref_points(lm.submap, det.points)
        vox = self._voxelise(pts)
        lm.class_counts[det.label] += 1.0
        lm.point_sum = lm.point_sum + pts.sum(0)
        lm.num_points += len(pts)
        lm.voxels, lm.voxel_hits = _merge_counts(
            lm.voxels, lm.voxel_hits, vox, np.ones(len(vox), dtype=np.int32)
        )
        if lm.last_seen != self._frame:
            lm.num_observations += 1
        lm.last_seen = self._frame
        if lm.num_observations >= self.confirm_after:
            lm.confirmed = True
        lm.invalidate()

    def _merge_bridged(self, lid: int, det: Detection) -> None:
        """Merge into ``lid`` the same-class landmarks lying mostly inside this detection's box.

        One connected cluster spanning two landmarks (the two ends of a long table, first
        seen in separate partial views) shows they are one object.
        """
        keep = self.landmarks[lid]
        lo, hi = det.box_min - self.box_margin, det.box_max + self.box_margin
        for oid in [i for i in self.landmarks if i != lid]:
            other = self.landmarks[oid]
            if other.label != keep.label:
                continue
            olo, ohi = other.ref_aabb()
            inter = np.clip(np.minimum(hi, ohi) - np.maximum(lo, olo), 0, None).prod()
            if inter >= 0.5 * max(float(np.prod(ohi - olo)), 1e-12):
                self._merge(keep, self.landmarks.pop(oid))
                self._merged_into[oid] = lid

    def _merge_overlapping(self) -> None:
        """Merge pairs of same-class landmarks whose boxes overlap by ``merge_iou`` or more."""
        ids = list(self.landmarks)
        if len(ids) < 2:
            return
        lo, hi, labels = self._boxes(ids)
        inter = np.clip(
            np.minimum(hi[:, None], hi[None]) - np.maximum(lo[:, None], lo[None]), 0, None
        )
        vi = inter.prod(axis=2)
        vol = (hi - lo).prod(axis=1)
        iou = vi / np.maximum(vol[:, None] + vol[None] - vi, 1e-12)
        # a small box mostly inside a bigger one counts as overlapping too
        inside = vi / np.maximum(np.minimum(vol[:, None], vol[None]), 1e-12)
        same = (labels[:, None] == labels[None]) & ((iou >= self.merge_iou) | (inside >= 0.7))
        np.fill_diagonal(same, False)
        for a, b in zip(*np.nonzero(np.triu(same)), strict=True):
            ia, ib = ids[a], ids[b]
            if ia in self.landmarks and ib in self.landmarks:
                self._merge(self.landmarks[ia], self.landmarks.pop(ib))
                self._merged_into[ib] = ia

    def _boxes(self, ids: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        boxes = [self.landmarks[i].ref_aabb() for i in ids]
        return (
            np.array([b[0] for b in boxes]),
            np.array([b[1] for b in boxes]),
            np.array([self.landmarks[i].label for i in ids]),
        )

    def merge_fragments(self, octree: SemanticOctree, max_gap: float = 1.0) -> int:
        """Merge same-class landmarks that are fragments of one object hidden by an occluder.

        Two landmarks of one class whose nearest voxels are at most ``max_gap`` apart are
        merged when no cell on the segment between those voxels is *observed free* in
        ``octree`` (all are unknown or occupied): a chair in front of a table splits the table
        in every view, while two tables side by side have seen free space between them.
        Returns the number of merges.
        """
        merged = 0
        changed = True
        while changed:
            changed = False
            ids = list(self.landmarks)
            if len(ids) < 2:
                break
            lo, hi, labels = self._boxes(ids)
            gap = np.max(np.maximum(lo[:, None] - hi[None], lo[None] - hi[:, None]), axis=2)
            cand = (labels[:, None] == labels[None]) & (gap <= max_gap)
            union = np.maximum(hi[:, None], hi[None]) - np.minimum(lo[:, None], lo[None])
            cand &= union[..., :2].max(axis=2) <= _max_extent(labels)[:, None]
            for a, b in zip(*np.nonzero(np.triu(cand, 1)), strict=True):
                A, B = self.landmarks[ids[a]], self.landmarks[ids[b]]
                if self._hidden_between(A, B, octree, max_gap):
                    self._merge(A, self.landmarks.pop(ids[b]))
                    merged += 1
                    changed = True
                    break
        return merged

    def _hidden_between(
        self, a: Landmark, b: Landmark, octree: SemanticOctree, max_gap: float, pairs: int = 8
    ) -> bool:
        """Is some straight gap between two landmarks entirely unseen or filled by objects?

        The ``pairs`` closest voxel pairs are tried; a gap qualifies when none of its cells is
        observed free or occupied by a structure class (walls and floors do not occlude
        anything between two pieces of furniture standing on them).
        """
        ca, cb = _world_voxel_centers(a), _world_voxel_centers(b)
        if len(ca) == 0 or len(cb) == 0:
            return False
        d, j = cKDTree(cb).query(ca, k=1)
        for i in np.argsort(d)[:pairs]:
            if d[i] > max_gap + 1e-9:
                break
            p, q = ca[i], cb[j[i]]
            steps = max(2, int(np.ceil(np.linalg.norm(q - p) / (0.5 * self.resolution))) + 1)
            seg = p + np.linspace(0.0, 1.0, steps)[:, None] * (q - p)
            cls = octree.class_at(seg)
            if not np.any((cls == 0) | np.isin(cls, self.structure_classes)):
                return True
        return False

    def _merge(self, keep: Landmark, other: Landmark) -> None:
        centroid_world = other.centroid
        centroid_ref = transform_points(inverse(keep.T_world_ref), centroid_world[None])[0]
        keep.point_sum = keep.point_sum + centroid_ref * other.num_points
        keep.num_points += other.num_points
        keep.class_counts = keep.class_counts + other.class_counts - self._prior
        centers = morton.node_centers(
            other.voxels, np.zeros(len(other.voxels), np.int8), self.resolution
        )
        moved = transform_points(inverse(keep.T_world_ref) @ other.T_world_ref, centers)
        codes = morton.points_to_codes(moved, self.resolution)
        ok = codes >= 0
        order = np.argsort(codes[ok], kind="stable")
        vox, hits = codes[ok][order], other.voxel_hits[ok][order]
        uniq, first = np.unique(vox, return_index=True)
        hits = np.add.reduceat(hits, first) if len(vox) else hits
        keep.voxels, keep.voxel_hits = _merge_counts(keep.voxels, keep.voxel_hits, uniq, hits)
        keep.num_observations += other.num_observations
        keep.first_seen = min(keep.first_seen, other.first_seen)
        keep.last_seen = max(keep.last_seen, other.last_seen)
        keep.confirmed = (
            keep.confirmed or other.confirmed or (keep.num_observations >= self.confirm_after)
        )
        keep.invalidate()


def _world_voxel_centers(lm: Landmark) -> np.ndarray:
    """World centres of a landmark's well-supported voxels (all voxels if none is yet)."""
    return transform_points(lm.T_world_ref, lm.supported_centers())


def _merge_counts(
    a: np.ndarray, ac: np.ndarray, b: np.ndarray, bc: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Union of two sorted code sets with summed counts."""
    codes = np.concatenate([a, b])
    counts = np.concatenate([ac, bc]).astype(np.int32)
    uniq, inv = np.unique(codes, return_inverse=True)
    out = np.zeros(len(uniq), dtype=np.int32)
    np.add.at(out, inv, counts)
    return uniq, out
