"""Team-level SLAM evaluation against simulator ground truth: maps, objects, loop closures."""

from __future__ import annotations

import numpy as np

from kimera_multi_py.core.geometry import inverse, relative, so3_log, transform_points
from kimera_multi_py.eval.metrics import object_precision_recall, occupancy_f1, semantic_miou
from kimera_multi_py.mapping.object_fusion import object_groups


def map_quality(octree: object, T_world_map: np.ndarray, centers: np.ndarray,
                gt_labels: np.ndarray) -> dict[str, float]:
    """Occupancy F1 and semantic mIoU of a map placed in the world by ``T_world_map``.

    ``centers``/``gt_labels`` are the ground-truth grid's cell centres ``(n, 3)`` and labels;
    the map is queried at each centre (nearest leaf), so no re-binning of the map is needed.
    """
    pred = octree.class_at(transform_points(inverse(T_world_map), centers))  # type: ignore[attr-defined]
    return {"occupancy_f1": occupancy_f1(pred, gt_labels), "semantic_miou": semantic_miou(pred, gt_labels),
            "observed_cells": int(np.sum((pred >= 0) & (gt_labels >= 0)))}


def merge_objects(classes: np.ndarray, lo: np.ndarray, hi: np.ndarray, margin: float = -0.2,
                  min_iou: float = 0.2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fuse the team's object boxes into one object map: one per
    :func:`~kimera_multi_py.mapping.object_fusion.object_groups` group, the box their union.

    Returns ``(classes, lo, hi)`` of the fused objects.
    """
    classes = np.asarray(classes).reshape(-1)
    lo = np.asarray(lo, dtype=float).reshape(-1, 3)
    hi = np.asarray(hi, dtype=float).reshape(-1, 3)
    if len(classes) == 0:
        return classes, lo, hi
    comp = object_groups(classes, lo, hi, margin, min_iou)
    m = comp.max() + 1
    out_lo = np.full((m, 3), np.inf)
    out_hi = np.full((m, 3), -np.inf)
    np.minimum.at(out_lo, comp, lo)
    np.maximum.at(out_hi, comp, hi)
    out_cls = np.zeros(m, dtype=int)
    out_cls[comp] = classes
    return out_cls, out_lo, out_hi


def world_boxes(T: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds of boxes ``[lo, hi]`` moved by ``T``."""
    lo = np.asarray(lo, dtype=float).reshape(-1, 3)
    hi = np.asarray(hi, dtype=float).reshape(-1, 3)
    c = transform_points(T, (lo + hi) / 2)
    ext = (hi - lo) / 2 @ np.abs(T[:3, :3]).T
    return c - ext, c + ext


def object_quality(classes: np.ndarray, centroids: np.ndarray, gt_classes: np.ndarray,
                   gt_centroids: np.ndarray) -> dict[str, float]:
    res = object_precision_recall(classes, centroids, gt_classes, gt_centroids, max_distance=0.5)
    return {k: float(v) for k, v in res.items()}


def score_closures(Z: np.ndarray, T_a: np.ndarray, T_b: np.ndarray, max_trans: float = 1.0,
                   max_rot_deg: float = 10.0) -> np.ndarray:
    """True where a closure ``Z ≈ T_a^{-1} T_b`` agrees with the true poses (boolean ``(n,)``)."""
    if len(Z) == 0:
        return np.zeros(0, dtype=bool)
    E = relative(Z, relative(T_a, T_b))
    rot = np.degrees(np.linalg.norm(so3_log(E[:, :3, :3]), axis=1))
    return (np.linalg.norm(E[:, :3, 3], axis=1) <= max_trans) & (rot <= max_rot_deg)
