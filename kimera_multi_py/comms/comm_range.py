"""A communication-range model: robots farther apart than ``comm_range`` metres cannot hear each other."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np


def neighbours_within(positions: Mapping[int, np.ndarray], comm_range: float | None) -> dict[int, set[int]]:
    """Each robot's one-hop neighbours: the others within ``comm_range`` (None or inf: all of them).

    ``positions`` are the robots' true positions (3-vectors, or 4x4 poses whose translation is
    used). The relation is symmetric; a robot is never its own neighbour.
    """
    ids = sorted(int(i) for i in positions)
    if comm_range is not None and not comm_range >= 0:
        raise ValueError(f"comm_range must be non-negative or None, got {comm_range}")
    if comm_range is None or np.isinf(comm_range):
        return {i: set(ids) - {i} for i in ids}
    xyz = np.array([_position(positions[i]) for i in ids]).reshape(-1, 3)
    if not np.all(np.isfinite(xyz)):
        raise ValueError("robot positions must be finite")
    d = np.linalg.norm(xyz[:, None, :] - xyz[None, :, :], axis=2)
    near = d <= comm_range
    return {i: {ids[b] for b in np.flatnonzero(near[a]) if b != a} for a, i in enumerate(ids)}


def _position(p: np.ndarray) -> np.ndarray:
    p = np.asarray(p, dtype=np.float64)
    if p.shape == (4, 4):
        return p[:3, 3]
    if p.shape != (3,):
        raise ValueError(f"a robot position must be a 3-vector or a 4x4 pose, got shape {p.shape}")
    return p
