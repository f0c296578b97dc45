"""Metrics: absolute trajectory error (ATE) and, below it, map and object quality metrics."""

from __future__ import annotations

import numpy as np

from kimera_multi_py.geometry import make_pose, umeyama


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
