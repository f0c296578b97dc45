"""Chordal initialisation as sparse linear least squares (numpy/scipy), whole graph or one block.

Rotations first: minimise ``Σ κ‖Rᵢ Z − Rⱼ‖²_F`` (linear in the entries, then projected onto
SO(3)); translations second, with the rotations fixed: ``Σ τ‖tⱼ − tᵢ − Rᵢ t_Z‖²``. The scalar
weights are DPGO's ``κ = 3 / (2 tr Ω_R⁻¹)`` and ``τ = 3 / tr Ω_t⁻¹`` of each edge's information,
which stay meaningful where gtsam's ``InitializePose3`` gives up (cubicle's indefinite matrices).

The block form is what a robot solves in the distributed initialisation (:mod:`.agent`): its own
poses are the unknowns, its neighbours' poses (from messages) are fixed, and the chordal cost is
minimised by block Gauss–Seidel over the robots. A tiny proximal term toward the current
estimate keeps every block well posed, including components that no edge anchors.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from kimera_multi_py.alignment.frames import project_so3

PROX = 1e-9  # proximal weight relative to the mean edge weight


def edge_weights(information: np.ndarray, eps: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """``(κ, τ)`` per edge from ``(m, 6, 6)`` information in gtsam order ``[rot, trans]``."""
    info = np.asarray(information, dtype=float)

    def inv_trace(block: np.ndarray) -> np.ndarray:
        ev = np.linalg.eigvalsh(0.5 * (block + np.swapaxes(block, 1, 2)))
        ev = np.maximum(ev, eps * np.maximum(ev.max(axis=1, keepdims=True), eps))
        return (1.0 / ev).sum(axis=1)

    kappa = 3.0 / (2.0 * inv_trace(info[:, :3, :3]))
    tau = 3.0 / inv_trace(info[:, 3:, 3:])
    return kappa, tau


def project_rotations(M: np.ndarray) -> np.ndarray:
    """Closest rotations to ``(n, 3, 3)`` matrices (batched SVD)."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    U[:, :, 2] *= d[:, None]
    return U @ Vt


def _solve(n: int, rows: list, cols: list, vals: list, rhs: np.ndarray, dim: int,
           current: np.ndarray, prox: float) -> np.ndarray:
    """Solve ``min ‖A x − rhs‖² + prox‖x − current‖²`` for ``x`` of shape ``(n·dim, k)``."""
    A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(len(rhs), n * dim))
    H = (A.T @ A + prox * sp.identity(n * dim)).tocsc()
    g = A.T @ rhs + prox * current
    return splu(H).solve(np.asarray(g, dtype=float))


def relax_rotations(n: int, ei: np.ndarray, ej: np.ndarray, rot_meas: np.ndarray,
                    kappa: np.ndarray, fixed: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Chordal rotations of ``n`` unknown poses.

    Edge endpoints ``< n`` are unknowns, ``≥ n`` index ``fixed`` (``(f, 3, 3)`` rotations held
    fixed). ``current`` ``(n, 3, 3)`` is the proximal centre. Returns projected ``(n, 3, 3)``.
    """
    # unknown X_k = R_kᵀ; residual block of an edge: √κ (Zᵀ X_i − X_j), 3 rows, 3 rhs columns
    m = len(ei)
    s = np.sqrt(kappa)
    rows, cols, vals = [], [], []
    rhs = np.zeros((3 * m, 3))
    base = 3 * np.arange(m)
    Zt = np.swapaxes(rot_meas, 1, 2)
    for a in range(3):
        for b in range(3):
            # + √κ Zᵀ[a, b] X_i[b, :] in row 3e+a
            coef = s * Zt[:, a, b]
            own = ei < n
            rows.append(base[own] + a)
            cols.append(3 * ei[own] + b)
            vals.append(coef[own])
            fx = ~own
            rhs[base[fx] + a] -= coef[fx, None] * np.swapaxes(fixed[ei[fx] - n], 1, 2)[:, b, :]
        own = ej < n
        rows.append(base[own] + a)
        cols.append(3 * ej[own] + a)
        vals.append(-s[own])
        fx = ~own
        rhs[base[fx] + a] += s[fx, None] * np.swapaxes(fixed[ej[fx] - n], 1, 2)[:, a, :]
    prox = PROX * float(kappa.mean()) if m else 1.0
    cur = np.swapaxes(current, 1, 2).reshape(3 * n, 3)
    X = _solve(n, rows, cols, vals, rhs, 3, cur, prox).reshape(n, 3, 3)
    return project_rotations(np.swapaxes(X, 1, 2))


def relax_translations(n: int, ei: np.ndarray, ej: np.ndarray, t_meas: np.ndarray,
                       tau: np.ndarray, rot_i: np.ndarray, fixed: np.ndarray,
                       current: np.ndarray) -> np.ndarray:
    """Translations of ``n`` unknown poses with every rotation known: ``(n, 3)``.

    ``rot_i`` ``(m, 3, 3)`` is the rotation of each edge's ``i`` end; ``fixed`` ``(f, 3)``.
    """
    m = len(ei)
    s = np.sqrt(tau)
    rows, cols, vals = [], [], []
    # residual √τ (t_j − t_i − R_i t_Z), 3 rows per edge
    rhs = s[:, None] * np.einsum("mab,mb->ma", rot_i, t_meas)
    for end, sign in ((ei, -1.0), (ej, 1.0)):
        own = end < n
        for a in range(3):
            rows.append(3 * np.flatnonzero(own) + a)
            cols.append(3 * end[own] + a)
            vals.append(sign * s[own])
        fx = ~own
        rhs[fx] -= sign * s[fx, None] * fixed[end[fx] - n]
    prox = PROX * float(tau.mean()) if m else 1.0
    x = _solve(n, rows, cols, vals, rhs.reshape(-1, 1), 3, current.reshape(-1, 1), prox)
    return x.reshape(n, 3)


def chordal_block(n: int, ei: np.ndarray, ej: np.ndarray, measurement: np.ndarray,
                  kappa: np.ndarray, tau: np.ndarray, fixed: np.ndarray,
                  current: np.ndarray) -> np.ndarray:
    """Rotations then translations of ``n`` unknown poses ``(n, 4, 4)``; ``fixed`` ``(f, 4, 4)``."""
    fixed = np.asarray(fixed, dtype=float).reshape(-1, 4, 4)
    R = relax_rotations(n, ei, ej, measurement[:, :3, :3], kappa, fixed[:, :3, :3],
                        current[:, :3, :3])
    all_rot = np.concatenate([R, fixed[:, :3, :3]])
    t = relax_translations(n, ei, ej, measurement[:, :3, 3], tau, all_rot[ei], fixed[:, :3, 3],
                           current[:, :3, 3])
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = R
    out[:, :3, 3] = t
    return out


def chordal_poses(poses: np.ndarray, ei: np.ndarray, ej: np.ndarray, measurement: np.ndarray,
                  information: np.ndarray, anchor: int = 0) -> np.ndarray:
    """Whole-graph chordal initialisation, ``poses[anchor]`` held at its given value."""
    n = len(poses)
    keep = np.delete(np.arange(n), anchor)
    index = np.empty(n, dtype=int)
    index[keep] = np.arange(n - 1)
    index[anchor] = n - 1  # the one fixed pose
    kappa, tau = edge_weights(information)
    est = chordal_block(n - 1, index[ei], index[ej], measurement, kappa, tau,
                        poses[anchor][None], poses[keep])
    out = poses.copy()
    out[keep] = est
    return out


__all__ = ["chordal_block", "chordal_poses", "edge_weights", "project_rotations",
           "project_so3", "relax_rotations", "relax_translations"]
