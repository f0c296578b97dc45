"""SE(3) helpers on 4x4 numpy matrices, gtsam conversion and Umeyama alignment.

Poses are homogeneous 4x4 float64 arrays ``T_a_b`` mapping points in frame b to frame a.
Batched functions accept arrays of shape ``(..., 3)`` / ``(..., 3, 3)`` / ``(..., 4, 4)``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    import gtsam

_EPS = 1e-9


def hat(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices of vectors ``(..., 3) -> (..., 3, 3)``."""
    w = np.asarray(w, dtype=float)
    z = np.zeros(w.shape[:-1])
    return np.stack(
        [
            np.stack([z, -w[..., 2], w[..., 1]], -1),
            np.stack([w[..., 2], z, -w[..., 0]], -1),
            np.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vectors ``(..., 3)`` to rotation matrices ``(..., 3, 3)``."""
    w = np.asarray(w, dtype=float)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = hat(w)
    small = theta < 1e-8
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(th) / th)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(th)) / th**2)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` to rotation vectors ``(..., 3)``."""
    R = np.asarray(R, dtype=float)
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = np.sin(theta)
    small = theta < 1e-6
    scale = np.where(small, 0.5 + theta**2 / 12.0, theta / (2.0 * np.where(small, 1.0, sin)))
    w = v * scale[..., None]
    # near pi: recover the axis from the symmetric part
    near_pi = theta > np.pi - 1e-4
    if np.any(near_pi):
        Rp = R[near_pi]
        B = (Rp + np.eye(3)) / 2.0
        axis_idx = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        cols = np.take_along_axis(B, axis_idx[:, None, None].repeat(3, -1), axis=-1)[..., 0]
        axis = cols / np.linalg.norm(cols, axis=-1, keepdims=True)
        sign = np.sign(np.einsum("ni,ni->n", axis, v[near_pi]))
        sign[sign == 0] = 1.0
        w[near_pi] = axis * (sign * theta[near_pi])[:, None]
    return w


def make_pose(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """Assemble 4x4 poses from rotations and translations (either may be batched)."""
    R = np.eye(3) if R is None else np.asarray(R, dtype=float)
    t = np.zeros(3) if t is None else np.asarray(t, dtype=float)
    batch = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(batch + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Pose from a tangent vector ``[rx, ry, rz, tx, ty, tz]`` (rotation first, as gtsam).

    Uses the decoupled retraction ``(Exp(r), t)``, which is what the noise models need.
    """
    xi = np.asarray(xi, dtype=float)
    return make_pose(so3_exp(xi[..., :3]), xi[..., 3:])


def se3_log(T: np.ndarray) -> np.ndarray:
    """Inverse of :func:`se3_exp` (decoupled): ``[log(R), t]``."""
    T = np.asarray(T, dtype=float)
    return np.concatenate([so3_log(T[..., :3, :3]), T[..., :3, 3]], -1)


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of (batched) rigid transforms."""
    T = np.asarray(T, dtype=float)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_pose(Rt, -(Rt @ T[..., :3, 3, None])[..., 0])


def relative(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """``T_a^{-1} T_b``: pose of b seen from a."""
    return inverse(T_a) @ T_b


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply one 4x4 transform to points ``(n, 3)``."""
    return p @ T[:3, :3].T + T[:3, 3]


def yaw_pose(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    """Planar pose with heading ``yaw`` (rad) about +z."""
    return make_pose(so3_exp(np.array([0.0, 0.0, yaw])), np.array([x, y, z]))


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` to unit quaternions ``(..., 4)`` as ``[qx, qy, qz, qw]``."""
    R = np.asarray(R, dtype=float)
    w = so3_log(R)
    theta = np.linalg.norm(w, axis=-1, keepdims=True)
    axis = np.where(theta > _EPS, w / np.where(theta > _EPS, theta, 1.0), 0.0)
    q = np.concatenate([axis * np.sin(theta / 2.0), np.cos(theta / 2.0)], -1)
    return q


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Quaternions ``[qx, qy, qz, qw]`` ``(..., 4)`` (normalised here) to rotation matrices."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def to_gtsam(T: np.ndarray) -> gtsam.Pose3:
    """4x4 numpy pose to ``gtsam.Pose3``."""
    import gtsam

    return gtsam.Pose3(np.asarray(T, dtype=float))


def from_gtsam(pose: gtsam.Pose3) -> np.ndarray:
    """``gtsam.Pose3`` to a 4x4 numpy pose."""
    return np.asarray(pose.matrix(), dtype=float)


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares ``(R, t, s)`` with ``dst ≈ s R src + t`` (Umeyama 1991).

    ``src`` and ``dst`` are ``(n, 3)`` corresponding points, n >= 3 for a unique rotation.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama needs two (n, 3) arrays of equal shape, got {src.shape} and {dst.shape}")
    if len(src) == 0:
        raise ValueError("umeyama needs at least one correspondence")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = 1.0
    if with_scale:
        var_s = (xs**2).sum() / len(src)
        s = float(np.trace(np.diag(D) @ S) / var_s) if var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s
