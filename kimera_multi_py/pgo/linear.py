"""Gauss–Newton linearisation of a robot's pose-graph block (numpy, vectorised).

The cost is gtsam's ``½ Σ eᵀΛe`` with ``e = Log(Z⁻¹ Xᵢ⁻¹ Xⱼ)`` (full SE(3) log, rotation
first). Poses are perturbed on the right, ``X ← X Exp(δ)`` (full SE(3) exponential), so

    ∂e/∂δⱼ = J_r⁻¹(e),     ∂e/∂δᵢ = −J_r⁻¹(e) Ad(Xⱼ⁻¹ Xᵢ).

:class:`LocalSystem` is one robot's share of the team's Gauss–Newton system: the Hessian block
of its own poses (its intra-robot edges plus its side of every inter-robot edge), its gradient,
and the 6x6 coupling blocks of its inter-robot edges, which multiply the neighbours' pieces of
a direction vector (only their public poses). Its block is factored once (SuperLU) and is the
block-Jacobi preconditioner of the distributed conjugate gradients (:mod:`.gn`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from kimera_multi_py.core.errors import KimeraMultiError
from kimera_multi_py.core.geometry import hat, inverse, make_pose, so3_exp
from kimera_multi_py.pgo.factors import se3_log_full


class LinearSystemError(KimeraMultiError):
    """A robot's Gauss–Newton block could not be factored."""


def se3_expmap(xi: np.ndarray) -> np.ndarray:
    """gtsam's ``Pose3.Expmap`` batched: ``[ω, ρ] → (Exp(ω), V(ω) ρ)``."""
    xi = np.asarray(xi, dtype=float)
    w, rho = xi[..., :3], xi[..., 3:]
    theta2 = np.sum(w * w, axis=-1)[..., None, None]
    theta = np.sqrt(theta2)
    small = theta < 1e-5
    th = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(th)) / th**2)
    b = np.where(small, 1.0 / 6.0 - theta2 / 120.0, (th - np.sin(th)) / th**3)
    W = hat(w)
    V = np.eye(3) + a * W + b * (W @ W)
    return make_pose(so3_exp(w), (V @ rho[..., None])[..., 0])


def adjoint(T: np.ndarray) -> np.ndarray:
    """``Ad_T`` in gtsam's order (rotation first): ``[[R, 0], [t^ R, R]]``, batched."""
    R, t = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., 3:, :3] = hat(t) @ R
    return out


def right_jacobian_inverse(xi: np.ndarray) -> np.ndarray:
    """``J_r⁻¹(ξ)`` of SE(3) in gtsam's order, batched: ``Log(Exp(ξ)Exp(δ)) ≈ ξ + J_r⁻¹(ξ) δ``.

    ``J_r(ξ) = J_l(−ξ)`` and ``J_l = [[J, 0], [Q, J]]`` (Barfoot's ``Q(ρ, φ)``), so
    ``J_r⁻¹(ξ) = [[J⁻¹, 0], [−J⁻¹ Q J⁻¹, J⁻¹]]`` evaluated at ``−ξ``.
    """
    xi = -np.asarray(xi, dtype=float)
    phi, rho = xi[..., :3], xi[..., 3:]
    theta2 = np.sum(phi * phi, axis=-1)[..., None, None]
    theta = np.sqrt(theta2)
    small = theta < 1e-3
    th = np.where(small, 1.0, theta)
    P, Rh = hat(phi), hat(rho)
    PP = P @ P
    # SO(3) left Jacobian inverse: I − ½Φ + (1/θ² − (1+cosθ)/(2θ sinθ)) Φ²
    c_inv = np.where(small, 1.0 / 12.0 + theta2 / 720.0,
                     1.0 / th**2 - (1.0 + np.cos(th)) / (2.0 * th * np.sin(th)))
    Jinv = np.eye(3) - 0.5 * P + c_inv * PP
    c1 = np.where(small, 1.0 / 6.0 - theta2 / 120.0, (th - np.sin(th)) / th**3)
    c2 = np.where(small, 1.0 / 24.0 - theta2 / 720.0,
                  (th**2 + 2.0 * np.cos(th) - 2.0) / (2.0 * th**4))
    c3 = np.where(small, 1.0 / 120.0 - theta2 / 2520.0,
                  (2.0 * th - 3.0 * np.sin(th) + th * np.cos(th)) / (2.0 * th**5))
    PR, RP = P @ Rh, Rh @ P
    PRP = PR @ P
    Q = (0.5 * Rh + c1 * (PR + RP + PRP) + c2 * (P @ PR + RP @ P - 3.0 * PRP)
         + c3 * (PRP @ P + P @ PRP))
    out = np.zeros(xi.shape[:-1] + (6, 6))
    out[..., :3, :3] = Jinv
    out[..., 3:, 3:] = Jinv
    out[..., 3:, :3] = -Jinv @ Q @ Jinv
    return out


def linearise_edges(Ti: np.ndarray, Tj: np.ndarray, Z: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Errors ``(m, 6)`` and Jacobians ``(m, 6, 6)`` w.r.t. the right perturbations of each end."""
    A = inverse(Ti) @ Tj
    e = se3_log_full(inverse(Z) @ A)
    Jj = right_jacobian_inverse(e)
    Ji = -Jj @ adjoint(inverse(A))
    return e, Ji, Jj


def edge_costs(Ti: np.ndarray, Tj: np.ndarray, Z: np.ndarray, info: np.ndarray) -> np.ndarray:
    """``½ eᵀΛe`` per edge."""
    e = se3_log_full(inverse(Z) @ inverse(Ti) @ Tj)
    return 0.5 * np.einsum("mi,mij,mj->m", e, info, e)


def _block_indices(rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COO indices of 6x6 blocks at block rows/cols ``(m,)`` -> ``(m, 6, 6)`` each."""
    k = np.arange(6)
    r = (6 * rows)[:, None, None] + k[None, :, None]
    c = (6 * cols)[:, None, None] + k[None, None, :]
    return np.broadcast_to(r, (len(rows), 6, 6)), np.broadcast_to(c, (len(cols), 6, 6))


class LocalSystem:
    """One robot's share of the team's Gauss–Newton system at a linearisation point.

    ``poses`` ``(n, 4, 4)`` are the robot's own; intra-robot edges join own indices; inter-robot
    edge ``k`` joins own index ``inter_own[k]`` with a neighbour pose ``peer_poses[k]`` (its
    end ``i`` when ``inter_own_is_i[k]`` is false). ``anchor`` holds the robot's first pose
    (the team's gauge). ``damping`` adds ``λ·diag(H)`` (Levenberg–Marquardt).
    """

    def __init__(self, poses: np.ndarray, intra_i: np.ndarray, intra_j: np.ndarray,
                 intra_meas: np.ndarray, intra_info: np.ndarray, inter_own: np.ndarray,
                 inter_own_is_i: np.ndarray, peer_poses: np.ndarray, inter_meas: np.ndarray,
                 inter_info: np.ndarray, anchor: bool, damping: float) -> None:
        n = len(poses)
        self.n = n
        self.inter_own = inter_own
        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        vals: list[np.ndarray] = []
        g = np.zeros((n, 6))
        cost = 0.0
        if len(intra_i):
            e, Ji, Jj = linearise_edges(poses[intra_i], poses[intra_j], intra_meas)
            LJi, LJj = intra_info @ Ji, intra_info @ Jj
            Le = np.einsum("mij,mj->mi", intra_info, e)
            cost += 0.5 * float(np.einsum("mi,mi->", e, Le))
            JiT, JjT = np.swapaxes(Ji, 1, 2), np.swapaxes(Jj, 1, 2)
            for a, b, blk in ((intra_i, intra_i, JiT @ LJi), (intra_j, intra_j, JjT @ LJj),
                              (intra_i, intra_j, JiT @ LJj), (intra_j, intra_i, JjT @ LJi)):
                r, c = _block_indices(a, b)
                rows.append(r.ravel())
                cols.append(c.ravel())
                vals.append(blk.ravel())
            np.add.at(g, intra_i, np.einsum("mji,mj->mi", Ji, Le))
            np.add.at(g, intra_j, np.einsum("mji,mj->mi", Jj, Le))
        self.coupling = np.zeros((len(inter_own), 6, 6))
        if len(inter_own):
            own = poses[inter_own]
            Ti = np.where(inter_own_is_i[:, None, None], own, peer_poses)
            Tj = np.where(inter_own_is_i[:, None, None], peer_poses, own)
            e, Ji, Jj = linearise_edges(Ti, Tj, inter_meas)
            sel = inter_own_is_i[:, None, None]
            Jo, Jp = np.where(sel, Ji, Jj), np.where(sel, Jj, Ji)
            Le = np.einsum("mij,mj->mi", inter_info, e)
            cost += 0.25 * float(np.einsum("mi,mi->", e, Le))  # half: the peer counts the rest
            JoT = np.swapaxes(Jo, 1, 2)
            r, c = _block_indices(inter_own, inter_own)
            rows.append(r.ravel())
            cols.append(c.ravel())
            vals.append((JoT @ inter_info @ Jo).ravel())
            np.add.at(g, inter_own, np.einsum("mji,mj->mi", Jo, Le))
            self.coupling = JoT @ inter_info @ Jp
        H = sp.coo_matrix((np.concatenate(vals) if vals else np.zeros(0),
                           (np.concatenate(rows) if rows else np.zeros(0, int),
                            np.concatenate(cols) if cols else np.zeros(0, int))),
                          shape=(6 * n, 6 * n)).tocsc()
        self.cost = cost
        self.gradient = g.ravel()
        if anchor:  # the first pose is the gauge: no step there
            keep = np.ones(6 * n)
            keep[:6] = 0.0
            D = sp.diags(keep)
            H = D @ H @ D + sp.diags(1.0 - keep)
            self.gradient = self.gradient * keep
        self.keep = np.ones(6 * n) if not anchor else keep
        diag = H.diagonal()
        scale = np.maximum(diag, 1e-9 * max(float(diag.max(initial=1.0)), 1e-300))
        self.H = (H + sp.diags(damping * scale)).tocsc()
        try:
            self._lu = spla.splu(self.H)
        except RuntimeError as exc:
            raise LinearSystemError(f"robot block singular: {exc}") from exc

    def precondition(self, v: np.ndarray) -> np.ndarray:
        """``M⁻¹ v`` with ``M`` the robot's own (damped) block."""
        return np.asarray(self._lu.solve(v))

    def multiply(self, v: np.ndarray, peer_v: np.ndarray) -> np.ndarray:
        """The robot's rows of ``H v``: ``peer_v`` ``(k, 6)`` is ``v`` at each inter-robot
        edge's neighbour pose."""
        out = np.asarray(self.H @ v)
        if len(self.inter_own):
            contrib = np.einsum("kij,kj->ki", self.coupling, peer_v)
            acc = np.zeros((self.n, 6))
            np.add.at(acc, self.inter_own, contrib)
            out = out + acc.ravel() * self.keep
        return out
