"""Team-level SLAM evaluation against simulator ground truth: maps, objects, loop closures."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kimera_multi_py.eval.metrics import object_precision_recall, occupancy_f1, semantic_miou
from kimera_multi_py.geometry import inverse, relative, so3_log, transform_points


def map_quality(octree: object, T_world_map: np.ndarray, centers: np.ndarray,
                gt_labels: np.ndarray) -> dict[str, float]:
    """Occupancy F1 and semantic mIoU of a map placed in the world by ``T_world_map``.

    ``centers``/``gt_labels`` are the ground-truth grid's cell centres ``(n, 3)`` and labels;
    the map is queried at each centre (nearest leaf), so no re-binning of the map is needed.
    """
    pred = octree.class_at(transform_points(inverse(T_world_map), centers))  # type: ignore[attr-defined]
    return {"occupancy_f1": occupancy_f1(pred, gt_labels), "semantic_miou": semantic_miou(pred, gt_labels),
            "observed_cells": int(np.sum((pred >= 0) & (gt_labels >= 0)))}


def merge_objects(classes: np.ndarray, centroids: np.ndarray, radius: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Fuse same-class objects closer than ``radius`` (greedy, by order): ``(classes, centroids)``."""
    classes = np.asarray(classes)
    centroids = np.asarray(centroids, dtype=float).reshape(-1, 3)
    out_c: list[int] = []
    out_p: list[np.ndarray] = []
    counts: list[int] = []
    for c, p in zip(classes, centroids, strict=True):
        for k, (oc, op) in enumerate(zip(out_c, out_p, strict=True)):
            if oc == c and np.linalg.norm(op - p) < radius:
                counts[k] += 1
                out_p[k] = op + (p - op) / counts[k]
                break
        else:
            out_c.append(int(c))
            out_p.append(p.copy())
            counts.append(1)
    return np.array(out_c, dtype=int), np.array(out_p).reshape(-1, 3)


def object_quality(classes: np.ndarray, centroids: np.ndarray, gt_classes: np.ndarray,
                   gt_centroids: np.ndarray) -> dict[str, float]:
    res = object_precision_recall(classes, centroids, gt_classes, gt_centroids, max_distance=0.5)
    return {k: float(v) for k, v in res.items()}


@dataclass(frozen=True)
class ClosureTruth:
    true: int
    false: int


def score_closures(Z: np.ndarray, T_a: np.ndarray, T_b: np.ndarray, max_trans: float = 1.0,
                   max_rot_deg: float = 10.0) -> np.ndarray:
    """True where a closure ``Z ≈ T_a^{-1} T_b`` agrees with the true poses (boolean ``(n,)``)."""
    if len(Z) == 0:
        return np.zeros(0, dtype=bool)
    E = relative(Z, relative(T_a, T_b))
    rot = np.degrees(np.linalg.norm(so3_log(E[:, :3, :3]), axis=1))
    return (np.linalg.norm(E[:, :3, 3], axis=1) <= max_trans) & (rot <= max_rot_deg)
