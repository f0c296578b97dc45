"""SE(2) pose graphs as planar SE(3): lifting on read, projection on write.

A 2-D pose ``(x, y, θ)`` is the SE(3) pose rotating by ``θ`` about z at height 0. An SE(2)
information matrix over ``(x, y, θ)`` becomes a 6x6 one in gtsam's ``[rotation, translation]``
order: ``θ`` on ``rz``, ``x, y`` on ``tx, ty``; the out-of-plane directions ``rx, ry, tz`` get
the largest in-plane precision. At planar poses their residuals are zero and their Jacobians
decouple from the in-plane ones (the problem is symmetric under z → −z), so the optimum stays
planar and the cost equals the SE(2) cost (Log of a planar SE(3) pose is the SE(2) Log).
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.core.geometry import make_pose

_IN_PLANE = np.array([3, 4, 2])  # x, y, θ -> tx, ty, rz in gtsam's [R, t] order
_OUT_OF_PLANE = np.array([0, 1, 5])  # rx, ry, tz
_TRIU3 = np.triu_indices(3)


def se2_to_pose(xyt: np.ndarray) -> np.ndarray:
    """``(..., 3)`` ``(x, y, θ)`` -> ``(..., 4, 4)`` planar SE(3) poses."""
    xyt = np.asarray(xyt, dtype=float)
    c, s = np.cos(xyt[..., 2]), np.sin(xyt[..., 2])
    R = np.zeros(xyt.shape[:-1] + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1] = c, -s, s, c
    R[..., 2, 2] = 1.0
    t = np.concatenate([xyt[..., :2], np.zeros(xyt.shape[:-1] + (1,))], axis=-1)
    return make_pose(R, t)


def pose_to_se2(T: np.ndarray) -> np.ndarray:
    """``(..., 4, 4)`` -> ``(..., 3)`` ``(x, y, θ)``: the planar part (yaw from the first column)."""
    T = np.asarray(T, dtype=float)
    theta = np.arctan2(T[..., 1, 0], T[..., 0, 0])
    return np.stack([T[..., 0, 3], T[..., 1, 3], theta], axis=-1)


def project_planar(T: np.ndarray) -> np.ndarray:
    """Poses with z, roll and pitch removed (exactly planar; TUM output of a 2-D graph)."""
    return se2_to_pose(pose_to_se2(T))


def information_from_se2(upper: np.ndarray) -> np.ndarray:
    """6 upper-triangular g2o values over ``(x, y, θ)`` -> 6x6 gtsam-order information."""
    info3 = np.zeros((3, 3))
    info3[_TRIU3] = upper
    info3 = info3 + np.triu(info3, 1).T
    out = np.zeros((6, 6))
    out[np.ix_(_IN_PLANE, _IN_PLANE)] = info3
    out[_OUT_OF_PLANE, _OUT_OF_PLANE] = max(float(np.max(np.diag(info3))), 1e-12)
    return out


def information_to_se2(info: np.ndarray) -> np.ndarray:
    """6x6 gtsam-order information -> the 6 upper-triangular g2o values over ``(x, y, θ)``."""
    return np.asarray(info)[np.ix_(_IN_PLANE, _IN_PLANE)][_TRIU3]
