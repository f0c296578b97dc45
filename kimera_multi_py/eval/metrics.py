"""Metrics: absolute trajectory error (ATE) and, below it, map and object quality metrics."""

from __future__ import annotations

import numpy as np

from kimera_multi_py.core.geometry import make_pose, umeyama


def align_se3(est_xyz: np.ndarray, gt_xyz: np.ndarray) -> np.ndarray:
    """4x4 transform T (SE(3), no scale) minimising ``|gt - T est|`` (Umeyama)."""
    R, t, _ = umeyama(est_xyz, gt_xyz, with_scale=False)
    return make_pose(R, t)


def ate_rmse(est_xyz: np.ndarray, gt_xyz: np.ndarray, align: bool = True) -> float:
    """RMSE of position error after an SE(3) Umeyama alignment of ``est`` onto ``gt``.

    ``est_xyz`` and ``gt_xyz`` are ``(n, 3)`` positions of the same timestamps.
    """
    est_xyz = np.asarray(est_xyz, dtype=float)
    gt_xyz = np.asarray(gt_xyz, dtype=float)
    if est_xyz.shape != gt_xyz.shape:
        raise ValueError(f"ATE needs equal shapes, got {est_xyz.shape} and {gt_xyz.shape}")
    if align:
        T = align_se3(est_xyz, gt_xyz)
        est_xyz = est_xyz @ T[:3, :3].T + T[:3, 3]
    return float(np.sqrt(np.mean(np.sum((est_xyz - gt_xyz) ** 2, axis=1))))


# ---- map and object metrics ----------------------------------------------------------------
# Cell labels follow the ground-truth grid convention: -1 unknown, 0 free, k > 0 class k.


def _paired_cells(pred_labels: np.ndarray, gt_labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cells known to both the map and the ground truth (the observed ground-truth cells)."""
    pred = np.asarray(pred_labels).reshape(-1).astype(np.int64)
    gt = np.asarray(gt_labels).reshape(-1).astype(np.int64)
    if pred.shape != gt.shape:
        raise ValueError(f"label arrays differ in size: {pred.shape} vs {gt.shape}")
    both = (pred >= 0) & (gt >= 0)
    return pred[both], gt[both]


def occupancy_precision_recall(pred_labels: np.ndarray, gt_labels: np.ndarray) -> dict[str, float]:
    """Occupied-vs-free precision, recall and F1 over the cells both label (not unknown)."""
    pred, gt = _paired_cells(pred_labels, gt_labels)
    p, g = pred > 0, gt > 0
    tp = float(np.sum(p & g))
    fp = float(np.sum(p & ~g))
    fn = float(np.sum(~p & g))
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    f1 = 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 0.0
    return {"precision": precision, "recall": recall, "f1": f1, "tp": tp, "fp": fp, "fn": fn,
            "cells": float(len(pred))}


def occupancy_f1(pred_labels: np.ndarray, gt_labels: np.ndarray) -> float:
    """F1 of "occupied" over the observed ground-truth cells.

    ``pred_labels`` and ``gt_labels`` are per-cell labels of the same cells (-1 unknown,
    0 free, >0 a class); cells unknown to either side are not scored.
    """
    return occupancy_precision_recall(pred_labels, gt_labels)["f1"]


def semantic_iou_per_class(pred_labels: np.ndarray, gt_labels: np.ndarray,
                           classes: np.ndarray | None = None) -> dict[int, float]:
    """IoU of each class (>0) over the observed ground-truth cells.

    ``classes`` defaults to the classes present in the ground truth of those cells.
    """
    pred, gt = _paired_cells(pred_labels, gt_labels)
    if classes is None:
        classes = np.unique(gt[gt > 0])
    out: dict[int, float] = {}
    for c in np.asarray(classes, dtype=np.int64):
        inter = float(np.sum((pred == c) & (gt == c)))
        union = float(np.sum((pred == c) | (gt == c)))
        out[int(c)] = inter / union if union else 0.0
    return out


def semantic_miou(pred_labels: np.ndarray, gt_labels: np.ndarray,
                  classes: np.ndarray | None = None) -> float:
    """Mean IoU over the classes present in the observed ground truth (free is not a class)."""
    per_class = semantic_iou_per_class(pred_labels, gt_labels, classes)
    return float(np.mean(list(per_class.values()))) if per_class else 0.0


def object_precision_recall(pred_classes: np.ndarray, pred_centroids: np.ndarray,
                            gt_classes: np.ndarray, gt_centroids: np.ndarray,
                            max_distance: float = 0.5) -> dict[str, float]:
    """Object precision / recall: one-to-one matches of the same class within ``max_distance``.

    Matching is optimal per class (Hungarian on centroid distance, pairs beyond the gate are
    not matches). Returns precision, recall, f1, the mean centroid error of the matches and
    the counts.
    """
    from scipy.optimize import linear_sum_assignment

    pc = np.asarray(pred_classes).reshape(-1)
    gc = np.asarray(gt_classes).reshape(-1)
    pp = np.asarray(pred_centroids, dtype=float).reshape(-1, 3)
    gp = np.asarray(gt_centroids, dtype=float).reshape(-1, 3)
    if len(pc) != len(pp) or len(gc) != len(gp):
        raise ValueError("classes and centroids must have the same length")
    errors: list[float] = []
    for c in np.intersect1d(pc, gc):
        i, j = np.flatnonzero(pc == c), np.flatnonzero(gc == c)
        d = np.linalg.norm(pp[i][:, None, :] - gp[j][None, :, :], axis=2)
        r, k = linear_sum_assignment(np.where(d <= max_distance, d, 1e9))
        errors += [float(x) for x in d[r, k] if x <= max_distance]
    tp = len(errors)
    precision = tp / len(pc) if len(pc) else 0.0
    recall = tp / len(gc) if len(gc) else 0.0
    f1 = 2 * tp / (len(pc) + len(gc)) if len(pc) + len(gc) else 0.0
    return {"precision": precision, "recall": recall, "f1": f1,
            "mean_error": float(np.mean(errors)) if errors else float("nan"),
            "matches": float(tp), "predicted": float(len(pc)), "ground_truth": float(len(gc))}
