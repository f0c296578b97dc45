"""One scan message (a PointCloud2, or a depth and a semantic image) -> the agent's labelled rays.

Points end in the keyframe frame (the sensor's, body convention: x forward, z up). A return
whose class maps onto the vocabulary is a hit; one without a class at or beyond ``max_range``
(or a +inf depth) is a miss placed at ``max_range`` along its ray (free space up to it); any
other is dropped and counted as ``unmapped`` (non-finite cloud points as ``invalid``). See
docs/bags.md.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from kimera_multi_py.io.bag.config import BagConfig
from kimera_multi_py.io.bag.depth import R_FLU_OPTICAL, back_project, depth_metres, label_ids
from kimera_multi_py.io.bag.pointcloud import read_cloud, xyz_class


def labelled_rays(cfg: BagConfig, scan: Any, labels: Any, K: np.ndarray | None,
                  colours: tuple[np.ndarray, np.ndarray] | None,
                  dropped: dict[str, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(points (n, 3), labels (n,) int16, hit (n,) bool)``; ``dropped`` counts what was left out.
    Malformed messages raise ValueError, KeyError or TypeError."""
    if cfg.camera:
        assert K is not None
        depth = depth_metres(scan)
        ids = label_ids(labels, *(colours or (None, None)))
        if ids.shape != depth.shape:
            raise ValueError(f"semantic image {ids.shape} and depth image {depth.shape} differ in size")
        pts, rng, keep = back_project(depth, K, cfg.max_range)
        ids = ids.ravel()[keep]
        pts = pts @ R_FLU_OPTICAL.T
    else:
        xyz, ids = xyz_class(read_cloud(scan), cfg.class_field)
        finite = np.all(np.isfinite(xyz), axis=1)
        dropped["invalid"] += int((~finite).sum())
        xyz, ids = xyz[finite], ids[finite]
        rng = np.linalg.norm(xyz, axis=1)
        pts = xyz @ R_FLU_OPTICAL.T if cfg.is_optical else xyz
    lut = cfg.class_lut(int(max(ids.max(initial=0), 0)) + 1)
    mapped = np.where(ids >= 0, lut[np.clip(ids, 0, len(lut) - 1)], 0)
    hit = mapped > 0
    miss = ~hit & (rng >= cfg.max_range * (1 - 1e-5))
    far = miss & np.isfinite(rng) & (rng > 0)
    pts[far] *= (cfg.max_range / rng[far])[:, None]
    keep_pt = hit | miss
    dropped["unmapped"] += int((~keep_pt).sum())
    return pts[keep_pt], mapped[keep_pt].astype(np.int16), hit[keep_pt]
